"""Retired: it reads the hand-set verdict (its factors and raw score), which the fitted verdict replaced
(issue 45); it runs at commit 7347584 (`git worktree add ../sb-7347584 7347584`).

The oracle's ceiling per ball: the detector's own verification started from the true centre.

For every ball of every scene with a depth frame, ``eval.bench.oracle.ceiling`` verifies it from
its true centre and the six rescore starts about it (the search cannot lose it then) and gives:
the best score ending within 2 cm, whether the size check passed, the refined centre's error,
*accepted* (within 2 cm, size check passed, score at least ``min_score``: the detector would
report it; beside it by issue 20's far rule, 3 cm beyond 3 m) and *separable* (its score beats
every clutter sphere the detector verifies in that frame with ``min_score`` 0: some threshold
would take it and no false detection of the frame).
Beside it, one pixel's depth noise at the ball over R (the nominal model; ``--frame-noise``: the
frame's own). ``--factors`` also
verifies each ball once from its true centre alone (no early stop) and takes that verification's
score apart into its factors (``improved.confidence_factors``: coverage, behind, ring_continued,
size...; the support factor, n / (n + min_inliers), as the score over the others' product), with
its free radius and ``visible_fraction``.

The clutter spheres of a scene come from one detection with the seed ``detection_seed(--seed, k)``
(scene k), as ``make robustness``'s oracle has them.

    python docs/experiments/scripts/oracle_ceiling.py data/hard --family far --family occluded
    python docs/experiments/scripts/oracle_ceiling.py data/train --by-noise 0,0.5,0.8,1.2 --no-separable
    python docs/experiments/scripts/oracle_ceiling.py data/robust --factors --set outline.outline_evidence=false
"""

from __future__ import annotations

import math
import sys

import numpy as np

import script_support as support
from spherebench import options
from spherebench.datasets import inout
from spherebench.eval.bench.oracle import ceiling
from spherebench.eval.bench.seeds import detection_seed
from spherebench.eval.metrics.metrics3d import FAR_RULE_FROM_M, FOUND_FAR_M, FOUND_M
from spherebench.method import improved, warm_up
from spherebench.method.detector import prepare_frame
from spherebench.parallel import single_thread_here


def truth_factors(cloud, centre_m, config) -> dict:
    """One verification from the true centre (no early stop): its score, factors, free radius, visibility."""
    frame = prepare_frame(cloud, config)
    buf = improved.workspace("inliers", (frame.index_image.size + 1,), np.int64)
    v = improved.verify_organised(frame, np.asarray(centre_m, np.float64), config, buf, frame.no_gate)
    if v is None:
        return {"verified": False}
    factors = improved.confidence_factors(v.stats, 0, v.free_radius_m, v.free_radius_se_m, config, organised=True)
    # a Candidate does not carry its fit's inlier count: the support factor is what the score leaves
    rest = math.prod(x for k, x in factors.items() if k != "support")
    factors["support"] = float(v.score) / rest if rest > 0 else 0.0
    return {"verified": True, "score": float(v.score), "size_ok": bool(v.size_ok),
            "error_mm": 1e3 * float(np.linalg.norm(v.centre_m - np.asarray(centre_m))),
            "free_radius_mm": 1e3 * float(v.free_radius_m), "free_radius_se_mm": 1e3 * float(v.free_radius_se_m),
            "visible_fraction": float(v.stats.get("visible_fraction", 1.0)),
            "factors": {k: float(x) for k, x in factors.items()}}


def ceiling_rows(dataset: str, scenes, config, seed: int, separable: bool, factors: bool,
                 frame_noise: bool = False) -> list[dict]:
    """Per ball: the oracle's ceiling row (and with ``factors`` the verification from the truth, taken apart)."""
    rows = []
    with single_thread_here():
        warm_up(config)
        for scene in scenes:
            gt = inout.read_scene_gt(scene.path)
            balls = [(k, b) for k, b in enumerate(gt.get("balls", [])) if b.get("center_m") is not None]
            if not balls:
                continue
            cloud = inout.load_cloud(scene.path)
            centres = [b["center_m"] for _, b in balls]
            a = support.scene_noise_a(scene, config, frame_noise)
            found = ceiling(cloud, centres, config, seed=detection_seed(seed, scene.index), separable=separable)
            for (k, b), o in zip(balls, found):
                row = {"scene": scene.path.name, "family": scene.family, "ball": k,
                       "radius_m": float(b.get("radius_m", config.radius_m)), "z_m": float(b["center_m"][2]),
                       "noise_r": support.noise_over_r(a, b["center_m"], config),
                       "score": o["score"], "size_ok": o["size_ok"],
                       "error_mm": 1e3 * o["error_m"] if math.isfinite(o["error_m"]) else None,
                       "accepted": o["within"], "separable": o["separable"], "sensor_cell": scene.sensor_cell}
                # issue 20's far rule: 3 cm for a ball deeper than 3 m (the oracle's own rule is 2 cm)
                limit_mm = 1e3 * (FOUND_FAR_M if row["z_m"] > FAR_RULE_FROM_M else FOUND_M)
                row["accepted_far_rule"] = bool(row["size_ok"] and row["score"] >= config.verification.accept_raw_score and
                                                row["error_mm"] is not None and row["error_mm"] <= limit_mm)
                if factors:
                    row["truth"] = truth_factors(cloud, b["center_m"], config)
                rows.append(row)
    return rows


def summary(rows: list[dict], key, min_score: float) -> list[dict]:
    """Per group (``key(row)``): balls, verifications ending within 2 cm, accepted (and by the far rule),
    separable; with the factors, the one verification from the true centre alone: accepted (size check
    and score) and ending within 2 cm."""
    out = []
    for group in sorted({key(r) for r in rows}):
        mine = [r for r in rows if key(r) == group]
        g = {"group": group, "balls": len(mine), "accepted": sum(r["accepted"] for r in mine),
             "accepted_far_rule": sum(r["accepted_far_rule"] for r in mine),
             "separable": sum(bool(r["separable"]) for r in mine),
             "within_2cm": sum(r["error_mm"] is not None and r["error_mm"] <= 20.0 for r in mine)}
        truth = [r["truth"] for r in mine if "truth" in r]
        if truth:
            g["truth_accepted"] = sum(t["verified"] and t["size_ok"] and t["score"] >= min_score for t in truth)
            g["truth_within_2cm"] = sum(t["verified"] and t["error_mm"] <= 20.0 for t in truth)
        out.append(g)
    return out


def markdown(result: dict) -> str:
    lines = [f"oracle_ceiling on {result['dataset']} ({result['scenes']} scenes, {len(result['balls'])} balls)", ""]
    for title, table in (("family", result["by_family"]), ("sigma_z / R", result.get("by_noise"))):
        if not table:
            continue
        one = "truth_accepted" in table[0]
        lines += [f"| {title} | balls | verification ends within 2 cm | accepted | accepted, far rule | separable |"
                  + (" from the truth alone: accepted | ends within 2 cm |" if one else ""),
                  "|---|---|---|---|---|---|" + ("---|---|" if one else "")]
        for g in table:
            lines.append(support.row(g["group"], g["balls"], g["within_2cm"], g["accepted"], g["accepted_far_rule"],
                                     g["separable"] if result["separable"] else None,
                                     *((g["truth_accepted"], g["truth_within_2cm"]) if one else ())))
        lines.append("")
    lines += ["| scene | ball | depth m | sigma_z/R | score | size ok | error mm | accepted | separable | "
              "factors below 0.97 |",
              "|---|---|---|---|---|---|---|---|---|---|"]
    for r in result["balls"]:
        low = ""
        if "truth" in r and r["truth"]["verified"]:
            low = ", ".join(f"{k} {v:.2f}" for k, v in r["truth"]["factors"].items() if v < 0.97 and k != "support")
        err = None if r["error_mm"] is None else f"{r['error_mm']:.1f}"
        lines.append(support.row(r["scene"], r["ball"], f"{r['z_m']:.2f}", f"{r['noise_r']:.2f}", f"{r['score']:.2f}",
                                 r["size_ok"], err, r["accepted"], r["separable"], low))
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    p = support.parser(__doc__)
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="NAME=VALUE",
                   help="a detector setting overridden, by its path (repeatable)")
    p.add_argument("--seed", type=options.seed, default=0, help="run seed of the clutter detection (default 0)")
    p.add_argument("--no-separable", action="store_true", help="skip the separable ceiling (no detection run)")
    p.add_argument("--factors", action="store_true", help="each ball's factors, verified from its true centre")
    p.add_argument("--by-noise", default=None, type=support.parse_edges, metavar="EDGES",
                   help="add a table by one pixel's noise over R at the ball, e.g. 0,0.5,0.8,1.2")
    support.add_noise_argument(p)
    support.add_holes_argument(p)
    support.add_json_argument(p)
    args = p.parse_args(argv)
    overrides = support.settings(args.overrides, "oracle_ceiling")
    config = support.detector_config(args.dataset, overrides)
    scenes = support.frame_scenes(args.dataset, args.limit, args.family, args.holes)
    rows = ceiling_rows(args.dataset, scenes, config, args.seed, not args.no_separable, args.factors,
                        args.frame_noise)
    result = {"dataset": str(args.dataset), "scenes": len(scenes), "overrides": overrides, "seed": args.seed,
              "separable": not args.no_separable, "balls": rows,
              "by_family": summary(rows, lambda r: r["family"], config.verification.accept_raw_score)}
    if args.by_noise:
        result["by_noise"] = summary(rows, lambda r: support.noise_bin(r["noise_r"], args.by_noise),
                                     config.verification.accept_raw_score)
    print(markdown(result))
    support.write_json(args.json, result)
    return 0


if __name__ == "__main__":
    sys.exit(main())
