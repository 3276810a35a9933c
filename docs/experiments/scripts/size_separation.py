"""Can the free radius tell a 0.11 m ball from the 0.12 m basketball, per range band and sensor model;
and how far the ball's depth spills past its silhouette (edge fattening).

``report`` reads ``stereo_losses.py collect``'s and ``noise_structure.py collect``'s lines of datasets
with 0.12 m balls and of their ``--radius 0.11`` twins (the same presets and seeds), and compares three
free-radius estimates per true radius and band of the surface distance: the detector's (the free radius
of ``verify_organised`` from the true centre with the basketball configuration, R 0.12: the "first"
verification, a single start, so the size check selects nothing), and the truth's trimmed least-squares
fits on the ray residuals of the sphere's own valid pixels (lsq_all) and of those 2 px inside its mask
(lsq_inner). Radii other than the target's come from the scenes' distractor spheres. Separability:
gap = median(0.12) - median(0.11), spread = the larger robust sd (1.4826 MAD) of the two, d' = gap /
spread; "accepted" is the oracle's acceptance (within 2 cm, size check, score) with R 0.12.

``fattening`` measures, per target ball within 2.5 m (the first ``--scenes`` scenes of each dataset
holding one), the share of the pixels 0-1, 1-2, 2-3 px outside its true silhouette
(``circles.sphere_silhouette_mask``) that show another surface yet carry a valid depth within R of the
ball's centre depth, their invalid share, and the same share on the ring a 0.12 m sphere at the same
centre adds (what a detector with R 0.12 takes for the ball's). A floor touching the ball counts too.

    python docs/experiments/scripts/size_separation.py report \\
        analytic=out/train_q1.jsonl:out/train_q23.jsonl analytic=out/train-r011_q1.jsonl:out/train-r011_q23.jsonl \\
        stereo=out/train-stereo_q1.jsonl:out/train-stereo_q23.jsonl \\
        stereo=out/train-stereo-r011_q1.jsonl:out/train-stereo-r011_q23.jsonl
    python docs/experiments/scripts/size_separation.py fattening train-stereo=data/train-stereo \\
        train-stereo-r011=data/train-stereo-r011
"""

from __future__ import annotations

import argparse
import math
import sys
from collections import defaultdict

import numpy as np
from scipy import ndimage

import script_support as support
import truth_support as ts
from spherebench import options
from spherebench.circles import sphere_silhouette_mask
from spherebench.datasets import inout

SOURCES = ("detector", "lsq_all", "lsq_inner")
RINGS_PX = ((0, 1), (1, 2), (2, 3))


def estimates(q1: list[dict], q23: list[dict], sensor: str) -> list[tuple]:
    """(sensor, source, true R, band, free radius or NaN, size_ok, accepted) per sphere and source."""
    rows = []
    for r in q1:
        for b in r["balls"] + r["distractors"]:
            first = b["oracle"].get("first") or {}
            key = (sensor, "detector", round(b["radius"], 3), ts.band_of(b["dist_surface"]))
            if first.get("verified"):
                rows.append(key + (first["free_radius"], first["size_ok"], bool(b["oracle"]["within"])))
            else:
                rows.append(key + (np.nan, False, False))
    for r in q23:
        for s in r["spheres"]:
            for src in SOURCES[1:]:
                f = s.get(src)
                rows.append((sensor, src, round(s["radius"], 3), ts.band_of(s["dist_surface"]),
                             np.nan if not f else f["r"], None, None))
    return rows


def stats(v) -> dict | None:
    v = np.asarray([x for x in v if np.isfinite(x)])
    if len(v) == 0:
        return None
    return {"n": len(v), "mean": float(np.mean(v)), "sd": float(np.std(v, ddof=1)) if len(v) > 1 else float("nan"),
            "rsd": ts.robust_sigma(v), "median": float(np.median(v))}


def report_tables(rows: list[tuple]) -> tuple[str, list[dict]]:
    groups = defaultdict(list)
    for row in rows:
        groups[row[:4]].append(row)
    sensors = list(dict.fromkeys(r[0] for r in rows))
    md = ["### Separability of R 0.11 from R 0.12 per band\n",
          "gap = median(0.12) - median(0.11); spread = the larger robust sd of the two; d' = gap / spread; "
          "separable when spread < the nominal 10 mm gap, and by the measured gap when spread < gap (mm).\n"]
    sep, out = [], []
    for sensor in sensors:
        for src in SOURCES:
            for band in ts.BAND_NAMES:
                a, b = groups.get((sensor, src, 0.12, band), []), groups.get((sensor, src, 0.11, band), [])
                sa, sb = stats([x[4] for x in a]), stats([x[4] for x in b])
                if not sa or not sb:
                    continue
                gap, spread = sa["median"] - sb["median"], max(sa["rsd"], sb["rsd"])
                acc = float(np.mean([bool(x[6]) for x in b])) if src == "detector" else None
                out.append({"sensor": sensor, "source": src, "band": band, "n_012": sa["n"], "n_011": sb["n"],
                            "median_012_mm": 1000 * sa["median"], "median_011_mm": 1000 * sb["median"],
                            "gap_mm": 1000 * gap, "d_prime": gap / spread if spread > 0 else None,
                            "accepted_011": acc})
                sep.append([sensor, src, band, f"{sa['n']} / {sb['n']}", f"{1000 * sa['median']:.1f}",
                            f"{1000 * sb['median']:.1f}", f"{1000 * gap:.1f}", f"{1000 * sa['rsd']:.1f}",
                            f"{1000 * sb['rsd']:.1f}", f"{gap / spread:.2f}" if spread > 0 else "-",
                            "yes" if spread < 0.01 else "no", "yes" if spread < gap else "no",
                            "-" if acc is None else f"{acc:.2f}"])
    md.append(ts.table(["sensor", "source", "band", "n 0.12 / 0.11", "median 0.12", "median 0.11", "gap", "rsd 0.12",
                        "rsd 0.11", "d'", "spread < 10 mm (nominal gap)", "spread < measured gap",
                        "0.11 accepted by the oracle"], sep))
    md.append("\n### Free-radius estimates per true radius, range band and sensor model (mm)\n")
    md.append("'no fit': the verification returned nothing or the least-squares fit ran away; 'size ok' the "
              "detector's size check; 'accepted' the oracle with R 0.12.\n")
    full = []
    for sensor in sensors:
        for src in SOURCES:
            for R in sorted({r[2] for r in rows}):
                for band in ts.BAND_NAMES:
                    g = groups.get((sensor, src, R, band))
                    if not g:
                        continue
                    st = stats([x[4] for x in g])
                    ok = f"{np.mean([bool(x[5]) for x in g]):.2f}" if src == "detector" else "-"
                    acc = f"{np.mean([bool(x[6]) for x in g]):.2f}" if src == "detector" else "-"
                    cells = (["-"] * 4 if st is None else
                             [f"{1000 * st[k]:.1f}" for k in ("mean", "median", "sd", "rsd")])
                    full.append([sensor, src, R, band, len(g), sum(not np.isfinite(x[4]) for x in g), *cells, ok, acc])
    md.append(ts.table(["sensor", "source", "true R", "band", "n", "no fit", "mean", "median", "sd", "rsd", "size ok",
                        "accepted"], full))
    return "\n".join(md), out


def report(args) -> int:
    rows = []
    for sensor, paths in ts.named_paths(args.sets):
        p1, _, p23 = paths.partition(":")
        rows += estimates(ts.read_jsonl(p1), ts.read_jsonl(p23) if p23 else [], sensor)
    text, sep = report_tables(rows)
    print(text)
    support.write_json(args.json, {"separability": sep})
    return 0


def fattening_rows(sd, max_m: float = 2.5) -> list[dict]:
    """Per target ball within ``max_m`` of the scene: the ring shares (see the module docstring)."""
    g = ts.rebuild(sd)
    depth, label, intr = g["depth"], g["label"], g["intr"]
    z = depth.astype(float) * intr.depth_scale
    valid = depth > 0
    out = []
    for k, kind in enumerate(g["kinds"]):
        if kind != "target":
            continue
        c, R = np.asarray(g["shapes"][k].centre_m, float), float(g["shapes"][k].radius_m)
        distance = float(np.linalg.norm(c) - R)
        if distance > max_m or c[2] <= R:
            continue
        sil = sphere_silhouette_mask(intr, c, R)
        dpx = ndimage.distance_transform_edt(~sil)  # pixels outside the silhouette, by their distance to it
        at_ball = valid & (np.abs(z - c[2]) <= R) & (label != k + 1)
        row = {"band": ts.band_of(distance), "width": depth.shape[1],
               "r_px": intr.fx * math.tan(math.asin(R / np.linalg.norm(c)))}
        for lo, hi in RINGS_PX:
            ring = (dpx > lo) & (dpx <= hi)
            row[f"{lo}-{hi}px"] = float((ring & at_ball).sum() / max(ring.sum(), 1))
            row[f"{lo}-{hi}px_invalid"] = float((ring & ~valid).sum() / max(ring.sum(), 1))
        ring = sphere_silhouette_mask(intr, c, ts.BASKETBALL_M) & ~sil
        row["to_0.12"] = float((ring & at_ball).sum() / ring.sum()) if ring.sum() >= 5 else None
        out.append(row)
    return out


def fattening(args) -> int:
    rows, result = [], {}
    for name, d in ts.named_paths(args.sets):
        per, taken = [], 0
        for sd in inout.list_scenes(d):
            balls = [b for b in ts.read_gt(sd).get("balls", []) if b.get("center_m")]
            if not balls or np.linalg.norm(balls[0]["center_m"]) - balls[0]["radius_m"] > args.max_range:
                continue
            per += fattening_rows(sd, args.max_range)
            taken += 1
            if taken >= args.scenes:
                break
        result[name] = per
        for band in ts.BAND_NAMES:
            bb = [r for r in per if r["band"] == band]
            if not bb:
                continue

            def med(k, bb=bb):
                v = [r[k] for r in bb if r.get(k) is not None]
                return f"{np.median(v):.2f}" if v else "-"
            rows.append([name, band, len(bb), f"{np.median([r['r_px'] for r in bb]):.1f}", med("0-1px"), med("1-2px"),
                         med("2-3px"), " / ".join(med(f"{a}-{b}px_invalid") for a, b in RINGS_PX), med("to_0.12")])
    print("### Edge fattening about the ball (share of ring pixels off the ball that carry the ball's depth)\n")
    print(ts.table(["set", "band", "balls", "median r_px", "ring 0-1 px out", "1-2 px", "2-3 px",
                    "invalid 0-1 / 1-2 / 2-3 px", "ring out to a 0.12 m silhouette"], rows))
    support.write_json(args.json, {"balls": result})
    return 0


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="command", required=True)
    rp = sub.add_parser("report", help="free-radius separability from collected lines")
    rp.add_argument("sets", nargs="+", metavar="SENSOR=Q1.jsonl[:Q23.jsonl]",
                    help="stereo_losses.py and noise_structure.py collect's lines; one sensor name may repeat")
    support.add_json_argument(rp)
    fp = sub.add_parser("fattening", help="edge fattening about the ball on the rebuilt truth")
    fp.add_argument("sets", nargs="+", metavar="NAME=DATASET")
    fp.add_argument("--scenes", type=options.count, default=40, help="scenes per dataset (default 40)")
    fp.add_argument("--max-range", type=float, default=2.5, help="balls up to this surface distance (m)")
    support.add_json_argument(fp)
    args = p.parse_args(argv)
    return {"report": report, "fattening": fattening}[args.command](args)


if __name__ == "__main__":
    sys.exit(main())
