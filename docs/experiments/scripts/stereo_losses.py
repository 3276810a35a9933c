"""Retired: it reads the hand-set verdict (its factors and raw score), which the fitted verdict replaced
(issue 45); it runs at commit 7347584 (`git worktree add ../sb-7347584 7347584`).

Where the improved detector loses each ball (the stage), what the oracle's verification from the
truth reaches, the scores of true and false candidates, and the false detections, per range band.

``collect`` runs the detector on every scene of a dataset as the benchmark does
(``detect(load_cloud(scene), config, seed=detection_seed(0, k))``, k the scene's index in scene-id
order; the basketball detector, R 0.12, on every dataset), logs every candidate it verifies
(``truth_support.CandidateLog``), and verifies every true ball and distractor sphere from its true
centre as the oracle does (``eval.bench.oracle.ceiling``: the true centre and the six
``rescore_starts``, the best kept), with that verification's free radius, confidence factors and, apart,
the verification from the true centre alone ("first", no choice among starts: the free radius for
``size_separation.py``). One JSON line per scene, resumable. ``--noise-map`` (``noise_structure.py
noise-map``) sets ``noise.noise_z2_per_m`` per scene to the truth's A (a what-if: the detector given
the true noise level); ``--set PATH=VALUE`` changes any other setting.

``report`` tabulates collected lines: per band, found (a detection within 2 cm), the oracle's ceiling
and the stage of each missed ball, the first that applies: (b) the oracle fails geometry or size (no
sphere with its size check passed ends within 2 cm); (c) the oracle ends within 2 cm, size passed,
score below ``min_score``; (d) the oracle accepts it and the frame reports a false detection; (a) no
verified candidate within 12 cm of the ball (the search); (a2) one was, but none ended accepted within
2 cm. Then the oracle centre's range and lateral error, the factors of the score-low balls, the false
detections, and the score distributions of true, near (2-12 cm) and false (> 12 cm) candidates.

``check`` compares collected lines with the library: ``detect`` without the log gives the logged
detections, and ``eval.bench.oracle.ceiling`` the lines' oracle per ball (exit status 1 on a mismatch).

``outline`` verifies each ball from its true centre, moves the result onto the outline
(``improved.outline_centre``) and compares the lateral error before and after. ``lateral`` fits a
sphere of the true radius from the true centre on the ball's own pixels (the simulator's label,
``truth_support.rebuild``) and on a label-free window about the true silhouette: whether a centre's
lateral scatter is in the ball's own depth or in which pixels a fit takes.

    python docs/experiments/scripts/stereo_losses.py collect data/train-stereo out/train-stereo_q1.jsonl
    python docs/experiments/scripts/stereo_losses.py collect data/train-stereo out/ts-truenoise_q1.jsonl \\
        --noise-map out/train-stereo_noise_map.json
    python docs/experiments/scripts/stereo_losses.py collect data/train-stereo out/ts-lag6_q1.jsonl \\
        --set noise.noise_estimate_lag_px=6 --set noise.noise_correlation_max_px=8
    python docs/experiments/scripts/stereo_losses.py check data/train out/train_q1.jsonl --every 3
    python docs/experiments/scripts/stereo_losses.py report train=out/train_q1.jsonl \\
        train-stereo=out/train-stereo_q1.jsonl
    python docs/experiments/scripts/stereo_losses.py outline train=data/train train-stereo=data/train-stereo
    python docs/experiments/scripts/stereo_losses.py lateral train=data/train train-stereo=data/train-stereo
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np
from scipy import ndimage

import script_support as support
import truth_support as ts
from spherebench import options
from spherebench.camera import image_rays
from spherebench.circles import sphere_silhouette_mask
from spherebench.datasets import inout
from spherebench.eval.bench.oracle import CEILING_M, beats, ceiling, truth_verifications
from spherebench.eval.bench.seeds import detection_seed
from spherebench.method import detect, improved
from spherebench.method.detector import prepare_frame

FACTORS = ("support", "coverage", "behind", "hug", "ring_continued", "ring_front", "see_through",
           "edge_behind", "relief", "ring_spread", "size")
THRESHOLDS = (0.2, 0.25, 0.3, 0.35)


# ---------------------------------------------------------------- collect

def oracle_verify(frame, centre, config, buf) -> dict:
    """``oracle.ceiling``'s loop for one sphere, keeping the chosen Candidate's free radius, centre and
    factors, and "first": the verification from the true centre alone."""
    c = np.asarray(centre, np.float64)
    best, keep, first = {"score": 0.0, "size_ok": False, "error_m": math.inf, "within": False}, None, None
    for v in truth_verifications(frame, c, config, buf):
        if first is None:
            first = {"verified": v is not None}
            if v is not None:
                first.update(free_radius=float(v.free_radius_m), free_radius_se=float(v.free_radius_se_m),
                             size_ok=bool(v.size_ok), score=float(v.score),
                             error_m=float(np.linalg.norm(v.centre_m - c)))
        if v is None:
            continue
        err = float(np.linalg.norm(v.centre_m - c))
        if beats(best, v.score, v.size_ok, err):
            best = {"score": float(v.score), "size_ok": bool(v.size_ok), "error_m": err,
                    "within": bool(err <= CEILING_M and v.size_ok and v.score >= config.verification.accept_raw_score)}
            keep = v
    if keep is not None:
        best["free_radius"] = float(keep.free_radius_m)
        best["free_radius_se"] = float(keep.free_radius_se_m)
        best["center"] = [float(x) for x in keep.centre_m]
        # a Candidate keeps no inlier count: support is the single-start score over the others' product
        f = improved.confidence_factors(keep.stats, 10 ** 12, keep.free_radius_m, keep.free_radius_se_m, config, True)
        rest = math.prod(x for k, x in f.items() if k != "support")
        single = keep.stats.get("score_single", keep.score)
        f["support"] = single / rest if rest > 0 else float("nan")
        best["factors"] = {k: float(x) for k, x in f.items()}
        best["sigma_m"] = float(keep.stats.get("sigma_m", float("nan")))
    else:
        best["verified"] = False
    best["first"] = first
    if not math.isfinite(best["error_m"]):
        best["error_m"] = None
    return best


def candidate_row(v) -> dict:
    return {"center": [float(x) for x in v.centre_m], "score": float(v.score), "size_ok": bool(v.size_ok),
            "free_radius": float(v.free_radius_m), "free_radius_se": float(v.free_radius_se_m)}


def scene_record(k: int, sd: Path, config, noise: dict) -> dict:
    """One scene's line (fields in ``collect``'s help)."""
    gt = ts.read_gt(sd)
    if sd.name in noise:
        config = config.override({"noise.noise_z2_per_m": float(noise[sd.name])})
    cloud = inout.load_cloud(sd)
    with ts.CandidateLog() as log:
        spheres = detect(cloud, config, seed=detection_seed(0, k))
    frame = prepare_frame(cloud, config)
    buf = improved.workspace("inliers", (frame.index_image.size + 1,), np.int64)
    balls = [{"center": b["center_m"], "radius": b["radius_m"],
              "dist_surface": float(np.linalg.norm(b["center_m"]) - b["radius_m"]),
              "visible_fraction": b.get("visible_fraction"),
              "oracle": oracle_verify(frame, b["center_m"], config, buf)} for b in ts.balls_with_circle(gt)]
    dists = [{"center": d["center_m"], "radius": d["radius_m"],
              "dist_surface": float(np.linalg.norm(d["center_m"]) - d["radius_m"]),
              "oracle": oracle_verify(frame, d["center_m"], config, buf)}
             for d in (gt.get("meta") or {}).get("distractors", []) if d["center_m"][2] > 0]
    return {"scene": sd.name, "index": k, "family": gt.get("family"), "resolution": gt["meta"]["resolution"],
            "noise_a": float(frame.noise_a), "noise_corr_px": float(frame.noise_corr_px),
            "balls": balls, "distractors": dists,
            "detections": [{"center": [float(x) for x in s.centre_m], "score": float(s.raw_score),
                            "free_radius": float(s.free_radius_m), "free_radius_se": float(s.free_radius_se_m)}
                           for s in spheres],
            "verified": [candidate_row(v) for v in log.records]}


def collect(args) -> int:
    config = ts.study_config(support.settings(args.set, "stereo_losses.py"), args.radius)
    noise = json.loads(Path(args.noise_map).read_text()) if args.noise_map else {}
    ts.collect_jsonl(args.dataset, args.out, lambda k, sd: scene_record(k, sd, config, noise), args.limit)
    return 0


def check(args) -> int:
    """Every ``--every``-th scene of collected lines against the library: ``detect`` without the
    candidate log gives the logged detections, ``oracle.ceiling`` the lines' oracle per ball."""
    config = ts.study_config(support.settings(args.set, "stereo_losses.py"), args.radius)
    recs = {r["scene"]: r for r in ts.read_jsonl(args.out)}
    bad = checked = 0
    for k, sd in list(enumerate(inout.list_scenes(args.dataset)))[::args.every]:
        r = recs.get(sd.name)
        if r is None:
            continue
        checked += 1
        cloud = inout.load_cloud(sd)
        got = [round(s.raw_score, 9) for s in detect(cloud, config, seed=detection_seed(0, k))]
        if got != [round(d["score"], 9) for d in r["detections"]]:
            bad += 1
            print(f"{sd.name}: detections differ")
        if r["balls"]:
            for o, b in zip(ceiling(cloud, [x["center"] for x in r["balls"]], config, seed=detection_seed(0, k),
                                    separable=False), r["balls"]):
                if o["within"] != b["oracle"]["within"] or abs(o["score"] - b["oracle"]["score"]) > 1e-9:
                    bad += 1
                    print(f"{sd.name}: the oracle differs")
    print(f"{checked} scenes checked, {bad} mismatches")
    return 1 if bad else 0


# ---------------------------------------------------------------- report

def classify(rec: dict, min_score: float) -> tuple[list[dict], list[dict]]:
    """Per ball of a scene line: band, found, oracle status (ok, score-low, geom/size), search status,
    stage; and the scene's false detections (> 2 cm from every ball)."""
    balls, dets = rec["balls"], rec["detections"]
    false = [d for d in dets if all(ts.dist(d["center"], b["center"]) > ts.FOUND_M for b in balls)]
    out = []
    for b in balls:
        o = b["oracle"]
        err = o.get("error_m")
        if o["within"]:
            ost = "ok"
        elif o["size_ok"] and err is not None and err <= ts.FOUND_M:
            ost = "score-low"
        else:
            ost = "geom/size"
        found = any(ts.dist(d["center"], b["center"]) <= ts.FOUND_M for d in dets)
        near = [v for v in rec["verified"] if ts.dist(v["center"], b["center"]) <= ts.GATE_M]
        sst = ("none<12cm" if not near else "some<2cm"
               if any(ts.dist(v["center"], b["center"]) <= ts.FOUND_M for v in near) else "2-12cm only")
        stage = ("found" if found else "b" if ost == "geom/size" else "c" if ost == "score-low" else "d" if false
                 else "a" if sst == "none<12cm" else "a2")
        out.append({"band": ts.band_of(b["dist_surface"]), "found": found, "ost": ost, "sst": sst, "stage": stage,
                    "top_false": bool(dets) and dets[0] in false, "oracle_score": o["score"], "o": o, "ball": b})
    return out, false


def merged(verified: list[dict], nms_m: float) -> list[dict]:
    """A frame's verified candidates merged within the NMS distance, the best score kept."""
    out = []
    for v in sorted(verified, key=lambda v: -v["score"]):
        if all(ts.dist(v["center"], u["center"]) >= nms_m for u in out):
            out.append(v)
    return out


def own_band(centre) -> str | None:
    """The band of a detection or candidate by its own distance (|c| - R, R the basketball's)."""
    return ts.band_of(float(np.linalg.norm(centre)) - ts.BASKETBALL_M)


def quantiles(x, qs=(0.1, 0.25, 0.5, 0.75, 0.9)) -> list[str]:
    x = np.asarray(x, float)
    return ["-"] * len(qs) if len(x) == 0 else [f"{v:.3f}" for v in np.quantile(x, qs)]


def report_tables(data: dict[str, list[dict]], min_score: float, nms_m: float) -> tuple[str, dict]:
    """The Markdown tables of ``report`` and their headline counts per set."""
    md, summary, per = [], {}, {}
    for name, recs in data.items():
        balls, falses = [], []
        for r in recs:
            b, f = classify(r, min_score)
            balls += b
            falses += [(r, d) for d in f]
        per[name] = (balls, falses)
        summary[name] = {"scenes": len(recs), "balls": len(balls), "found": sum(b["found"] for b in balls),
                         "ceiling": sum(b["ost"] == "ok" for b in balls), "false": len(falses),
                         **{st: sum(b["stage"] == st for b in balls) for st in ("a", "a2", "b", "c", "d")}}
    bands = ts.BAND_NAMES

    md.append("### Balls found and the stage that loses each missed ball\n")
    rows = []
    for name, (balls, _f) in per.items():
        for band in bands + ("all",):
            bb = [b for b in balls if band == "all" or b["band"] == band]
            n = len(bb)
            if n:
                cnt = lambda st: sum(b["stage"] == st for b in bb)  # noqa: E731
                ok = sum(b["ost"] == "ok" for b in bb)
                rows.append([name, band, n, f"{cnt('found')} ({cnt('found') / n:.0%})", f"{ok} ({ok / n:.0%})",
                             cnt("a"), cnt("a2"), cnt("b"), cnt("c"), cnt("d")])
    md.append(ts.table(["set", "band", "balls", "found", "oracle ceiling", "(a) search",
                        "(a2) verif. from search start", "(b) oracle geom/size", f"(c) oracle score<{min_score:g}",
                        "(d) false det. in frame"], rows))

    md.append("\nPer stream resolution (all bands): balls, found, oracle ceiling, (b), (c):\n")
    rows = []
    for name, recs in data.items():
        for res in ("424x240", "848x480", "1280x720"):
            bb = [b for r in recs if r["resolution"] == res for b in classify(r, min_score)[0]]
            if bb:
                rows.append([name, res, len(bb), sum(b["found"] for b in bb), sum(b["ost"] == "ok" for b in bb),
                             sum(b["stage"] == "b" for b in bb), sum(b["stage"] == "c" for b in bb)])
    md.append(ts.table(["set", "resolution", "balls", "found", "oracle ceiling", "(b)", "(c)"], rows))

    md.append("\nMissed balls, search outcome (verified candidates near the ball) x oracle outcome:\n")
    rows = []
    for name, (balls, _f) in per.items():
        miss = [b for b in balls if not b["found"]]
        for sst in ("none<12cm", "2-12cm only", "some<2cm"):
            rows.append([name, sst] + [sum(b["sst"] == sst and b["ost"] == o for b in miss)
                                       for o in ("ok", "score-low", "geom/size")])
    md.append(ts.table(["set", "search \\ oracle", "ok", "score-low", "geom/size"], rows))

    md.append("\nOracle geom/size failures, which part fails (per band):\n")
    rows = []
    for name, (balls, _f) in per.items():
        for band in bands:
            bb = [b for b in balls if b["band"] == band and b["ost"] == "geom/size"]
            errs = [b["o"].get("error_m") for b in bb]
            rows.append([name, band, len(bb), sum(e is None for e in errs),
                         sum(e is not None and e > ts.FOUND_M for e in errs),
                         sum(e is not None and e <= ts.FOUND_M and not b["o"]["size_ok"] for e, b in zip(errs, bb))])
    md.append(ts.table(["set", "band", "geom/size fails", "no verification", "ends > 2 cm off",
                        "size check fails (within 2 cm)"], rows))

    md.append("\nThe oracle's verified centre against the truth (every ball with a verification): range error "
              "|c_est| - |c_true| (mm, + = behind) and lateral error (mm), median [q10, q90]:\n")
    rows = []
    for name, (balls, _f) in per.items():
        for band in bands:
            parts = [(ts.range_lateral(b["o"]["center"], b["ball"]["center"]),
                      ts.dist(b["o"]["center"], b["ball"]["center"]))
                     for b in balls if b["band"] == band and "center" in b["o"]]
            if parts:
                rows.append([name, band, len(parts), ts.median_range([1000 * p[0][0] for p in parts]),
                             ts.median_range([1000 * p[0][1] for p in parts]),
                             f"{np.mean([p[1] > ts.FOUND_M for p in parts]):.2f}"])
    md.append(ts.table(["set", "band", "n", "range error mm", "lateral error mm", "share |error| > 2 cm"], rows))

    md.append(f"\nOracle score-low balls (within 2 cm, size ok, score < {min_score:g}): median of each confidence "
              "factor\n")
    def fmed(bb):
        return [f"{np.median([b['o']['factors'].get(k, np.nan) for b in bb]):.3f}" for k in FACTORS]
    rows = []
    for name, (balls, _f) in per.items():
        for grp in ("score-low", "ok"):
            bb = [b for b in balls if b["ost"] == grp and "factors" in b["o"]]
            if bb:
                rows.append([f"{name} {grp}", len(bb), f"{np.median([b['o']['score'] for b in bb]):.3f}"] + fmed(bb))
    md.append(ts.table(["set", "n", "score", *FACTORS], rows))
    md.append("\nPer band, every ball the oracle verifies within 2 cm with the size check passed (ok and score-low "
              "together): median score and factors:\n")
    rows = []
    for name, (balls, _f) in per.items():
        for band in bands:
            bb = [b for b in balls if b["band"] == band and b["ost"] in ("ok", "score-low") and "factors" in b["o"]]
            if bb:
                rows.append([f"{name} {band}", len(bb), f"{np.median([b['o']['score'] for b in bb]):.3f}"] + fmed(bb))
    md.append(ts.table(["set band", "n", "score", *FACTORS], rows))
    md.append("\nShare of score-low balls whose factor is the smallest (the one that holds it):\n")
    rows = []
    for name, (balls, _f) in per.items():
        mins: dict[str, int] = {}
        bb = [b for b in balls if b["ost"] == "score-low" and "factors" in b["o"]]
        for b in bb:
            f = {k: v for k, v in b["o"]["factors"].items() if k in FACTORS and np.isfinite(v)}
            mins[min(f, key=f.get)] = mins.get(min(f, key=f.get), 0) + 1
        rows.append([name, len(bb), ", ".join(f"{k} {v}" for k, v in sorted(mins.items(), key=lambda kv: -kv[1]))])
    md.append(ts.table(["set", "n", "lowest factor: count"], rows))

    md.append("\n### False detections (reported spheres > 2 cm from every ball)\n")
    rows = []
    for name, (balls, falses) in per.items():
        recs = data[name]
        clutter = [d for r, d in falses if all(ts.dist(d["center"], b["center"]) > ts.GATE_M for b in r["balls"])]
        rows.append([name, len(recs), len(falses), len(clutter), len({r["scene"] for r, _ in falses}),
                     sum(len(r["detections"]) for r in recs if not r["balls"]),
                     sum(b["found"] and b["top_false"] for b in balls),
                     "/".join(quantiles([d["score"] for _, d in falses]))])
        summary[name]["clutter"] = len(clutter)
    md.append(ts.table(["set", "scenes", "false", "of them > 12 cm (clutter)", "scenes with one",
                        "false on ball-less scenes", "found balls whose frame's best detection is false",
                        "score q10/q25/q50/q75/q90"], rows))
    md.append("\nFalse detections per band of their own distance (|c| - R), with their scores:\n")
    rows = []
    for name, (_b, falses) in per.items():
        for band in bands:
            ff = [d["score"] for _, d in falses if own_band(d["center"]) == band]
            rows.append([name, band, len(ff), ", ".join(f"{s:.2f}" for s in sorted(ff))])
    md.append(ts.table(["set", "band", "false", "scores"], rows))

    md.append("\n### Scores: true spheres vs false candidates (every top-level verification of the detector)\n")
    md.append(f"Candidates merged per frame within the NMS distance ({nms_m:g} m), the best score kept. 'true': "
              "within 2 cm of a ball; 'near': 2-12 cm; 'false': > 12 cm from every ball. size_ok only, then all.\n")
    rows = []
    for name, recs in data.items():
        groups: dict = {}
        for r in recs:
            for v in merged(r["verified"], nms_m):
                dmin = min((ts.dist(v["center"], b["center"]) for b in r["balls"]), default=math.inf)
                cls = "true" if dmin <= ts.FOUND_M else ("near" if dmin <= ts.GATE_M else "false")
                groups.setdefault((cls, v["size_ok"]), []).append(v["score"])
        for cls in ("true", "near", "false"):
            for ok in (True, False):
                s = groups.get((cls, ok), [])
                if s:
                    rows.append([name, cls, "pass" if ok else "fail", len(s)]
                                + quantiles(s, (0.1, 0.25, 0.5, 0.75, 0.9, 0.99))
                                + [f"{np.mean(np.asarray(s) >= min_score):.2f}"])
    md.append(ts.table(["set", "class", "size check", "n", "q10", "q25", "q50", "q75", "q90", "q99",
                        f"share >= {min_score:g}"], rows))
    md.append("\nThe true balls' oracle score (best from the truth, size ok and within 2 cm only) per band, "
              "against the false candidates' (size ok, > 12 cm) per band of their distance:\n")
    rows = []
    clutter_cands = {}
    for name, recs in data.items():
        clutter_cands[name] = [(r["scene"], own_band(v["center"]), v["score"])
                               for r in recs for v in merged(r["verified"], nms_m)
                               if v["size_ok"] and all(ts.dist(v["center"], b["center"]) > ts.GATE_M
                                                       for b in r["balls"])]
        balls = per[name][0]
        for band in bands:
            os_ = [b["oracle_score"] for b in balls if b["band"] == band and b["ost"] in ("ok", "score-low")]
            fs = [s for _sc, bd, s in clutter_cands[name] if bd == band]
            rows.append([name, band, len(os_), *(quantiles(os_, (0.1, 0.5, 0.9))), len(fs),
                         *(quantiles(fs, (0.5, 0.9, 0.99))), f"{max(fs):.3f}" if fs else "-"])
    md.append(ts.table(["set", "band", "oracle balls n", "q10", "q50", "q90", "false cand. n", "q50", "q90", "q99",
                        "max"], rows))
    md.append("\nAt a lower threshold t (all else as is): balls the oracle verifies within 2 cm with the size check "
              "passed and score >= t, against false candidates (size ok, > 12 cm from every ball, one per NMS "
              "group) with score >= t, and the frames holding one (an upper bound: search and budget held fixed):\n")
    rows = []
    for name in data:
        balls = per[name][0]
        for t in THRESHOLDS:
            nb = sum(b["ost"] in ("ok", "score-low") and b["oracle_score"] >= t for b in balls)
            fc = [sc for sc, _bd, s in clutter_cands[name] if s >= t]
            rows.append([name, t, f"{nb} / {len(balls)}", len(fc), len(set(fc))])
    md.append(ts.table(["set", "t", "oracle balls >= t", "false candidates >= t", "frames with one"], rows))
    return "\n".join(md), summary


def report(args) -> int:
    config = ts.study_config()
    nms_m = config.verification.nms_distance_fraction * 2 * config.radius_m
    data = {name: ts.read_jsonl(path) for name, path in ts.named_paths(args.sets)}
    text, summary = report_tables(data, config.verification.accept_raw_score, nms_m)
    print(text)
    support.write_json(args.json, {"summary": summary})
    return 0


# ---------------------------------------------------------------- outline, lateral

def outline(args) -> int:
    config = ts.study_config(support.settings(args.set, "stereo_losses.py"))
    rows, result = [], {}
    for name, d in ts.named_paths(args.sets):
        per = []
        for sd in inout.list_scenes(d)[:args.limit]:
            balls = ts.balls_with_circle(ts.read_gt(sd))
            if not balls:
                continue
            frame = prepare_frame(inout.load_cloud(sd), config)
            buf = improved.workspace("inliers", (frame.index_image.size + 1,), np.int64)
            for b in balls:
                ct = np.asarray(b["center_m"], float)
                v = improved.verify_organised(frame, ct, config, buf, frame.no_gate)
                if v is None:
                    continue
                oc = improved.outline_centre(frame, v.centre_m, config)
                per.append({"band": ts.band_of(float(np.linalg.norm(ct) - b["radius_m"])),
                            "noise_r": support.noise_over_r(frame.noise_a, ct, config),
                            "lateral_mm": 1000 * ts.range_lateral(v.centre_m, ct)[1],
                            "lateral_outline_mm": 1000 * ts.range_lateral(oc, ct)[1],
                            "error_m": ts.dist(v.centre_m, ct), "error_outline_m": ts.dist(oc, ct)})
        result[name] = per
        for band in ts.BAND_NAMES:
            bb = [p for p in per if p["band"] == band]
            if bb:
                med = lambda k: f"{np.median([p[k] for p in bb]):.1f}"  # noqa: E731
                share = lambda f: f"{np.mean([f(p) for p in bb]):.2f}"  # noqa: E731
                rows.append([name, band, len(bb), f"{np.median([p['noise_r'] for p in bb]):.2f}", med("lateral_mm"),
                             med("lateral_outline_mm"), share(lambda p: p["error_m"] <= ts.FOUND_M),
                             share(lambda p: p["error_outline_m"] <= ts.FOUND_M),
                             share(lambda p: min(p["error_m"], p["error_outline_m"]) <= ts.FOUND_M)])
    print("### Verification from the truth, then centred on the outline\n")
    print(ts.table(["set", "band", "balls verified", "frame sigma at ball / R", "lateral mm (verified)",
                    "lateral mm (outline-centred)", "within 2 cm (verified)", "within 2 cm (outline-centred)",
                    "either"],
                   rows))
    support.write_json(args.json, {"balls": result})
    return 0


def lateral_rows(sd: Path, max_m: float) -> list[dict]:
    """Per target ball within ``max_m``: the R-fixed fit's (range, lateral) error on its own pixels and
    on the label-free window (valid pixels within 3 px of the silhouette, depth within R of the centre's)."""
    g = ts.rebuild(sd)
    depth, label, intr = g["depth"], g["label"], g["intr"]
    z = depth.astype(float) * intr.depth_scale
    valid = depth > 0
    rays = image_rays(intr)
    out = []
    for k, kind in enumerate(g["kinds"]):
        if kind != "target":
            continue
        c, R = np.asarray(g["shapes"][k].centre_m, float), float(g["shapes"][k].radius_m)
        distance = float(np.linalg.norm(c) - R)
        if distance > max_m:
            continue
        near = ndimage.distance_transform_edt(~sphere_silhouette_mask(intr, c, R)) <= 3
        row = {"band": ts.band_of(distance)}
        for nm, m in (("own", valid & (label == k + 1)), ("window", valid & near & (np.abs(z - c[2]) <= R))):
            ce = ts.fit_centre(z[m][:, None] * rays[m], c, R) if m.sum() >= 20 else None
            row[nm] = None if ce is None else ts.range_lateral(ce, c)
        out.append(row)
    return out


def lateral(args) -> int:
    rows, result = [], {}
    for name, d in ts.named_paths(args.sets):
        per = []
        for sd in inout.list_scenes(d)[:args.limit]:
            balls = ts.balls_with_circle(ts.read_gt(sd))
            if balls and min(np.linalg.norm(b["center_m"]) - b["radius_m"] for b in balls) <= args.max_range:
                per += lateral_rows(sd, args.max_range)
        result[name] = per
        for band in ts.BAND_NAMES:
            bb = [r for r in per if r["band"] == band]
            if not bb:
                continue
            cells = [name, band, len(bb)]
            for nm in ("own", "window"):
                v = [r[nm] for r in bb if r[nm] is not None]
                cells += ([ts.median_range([1000 * x[1] for x in v]), ts.median_range([1000 * x[0] for x in v]),
                           f"{np.mean([math.hypot(*x) <= ts.FOUND_M for x in v]):.2f}"] if v else ["-"] * 3)
            rows.append(cells)
    print("### R-fixed fit from the truth on the ball's own pixels vs on a label-free window\n")
    print(ts.table(["set", "band", "balls", "own px: lateral mm", "own: range mm", "own: within 2 cm",
                    "window px: lateral mm", "window: range mm", "window: within 2 cm"], rows))
    support.write_json(args.json, {"balls": result})
    return 0


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="command", required=True)
    c = sub.add_parser("collect", help="one JSON line per scene: detections, verified candidates, the oracle")
    c.add_argument("dataset")
    c.add_argument("out", help="the JSON-lines file (appended to; scenes already in it are skipped)")
    c.add_argument("--noise-map", default=None, metavar="JSON",
                   help="{scene: A (1/m)}: noise.noise_z2_per_m per scene (noise_structure.py noise-map)")
    c.add_argument("--radius", type=float, default=ts.BASKETBALL_M, help="the detector's radius (m; default 0.12)")
    c.add_argument("--limit", type=options.count, default=None, help="the first N scenes only")
    ck = sub.add_parser("check", help="collected lines against detect and oracle.ceiling (exit 1 on a mismatch)")
    ck.add_argument("dataset")
    ck.add_argument("out", help="collect's JSON lines of that dataset, run with the same --set and --radius")
    ck.add_argument("--every", type=options.count, default=3, help="every Nth scene (default 3)")
    ck.add_argument("--radius", type=float, default=ts.BASKETBALL_M, help="the detector's radius (m; default 0.12)")
    rp = sub.add_parser("report", help="tables from collected lines")
    rp.add_argument("sets", nargs="+", metavar="NAME=JSONL")
    support.add_json_argument(rp)
    for name, what in (("outline", "verification from the truth, then outline centring"),
                       ("lateral", "R-fixed fits from the truth on the ball's own pixels and on a window")):
        s = sub.add_parser(name, help=what)
        s.add_argument("sets", nargs="+", metavar="NAME=DATASET")
        s.add_argument("--limit", type=options.count, default=None, help="the first N scenes of each")
        support.add_json_argument(s)
        if name == "lateral":
            s.add_argument("--max-range", type=float, default=3.5, help="balls up to this surface distance (m)")
    for s in (c, ck, sub.choices["outline"]):
        s.add_argument("--set", action="append", default=[], metavar="PATH=VALUE",
                       help="a detector setting overridden, by its path (repeatable)")
    args = p.parse_args(argv)
    return {"collect": collect, "check": check, "report": report, "outline": outline,
            "lateral": lateral}[args.command](args)


if __name__ == "__main__":
    sys.exit(main())
