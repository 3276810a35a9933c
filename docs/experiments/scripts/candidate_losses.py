"""Retired: it reads the hand-set verdict (its factors and raw score), which the fitted verdict replaced
(issue 45); it runs at commit 7347584 (`git worktree add ../sb-7347584 7347584`).

Where a near ball loses its ranked candidate: the stage, for each ball that the detector's ranked
output (down to ``rank_floor``) holds no sphere within 2 cm of.

For every ball within ``--max-range`` (surface distance, m) of every scene with a depth frame, at
run seed s (scene k detected with ``detection_seed(s, k)``, as the benchmark runs it): the nearest
ranked detection's error. A ball without one within 2 cm is verified from its true centre
(``eval.bench.oracle.ceiling``, the detector's own verification from the truth and the six rescore
starts) and given the first stage that applies:

- ``geometry``: no verification from the truth ends within 2 cm (the ball's depth does not hold its
  centre there, or the refinement runs off);
- ``size``: one ends within 2 cm, but none passes the size check there;
- ``score``: one ends within 2 cm with its size passed, below ``rank_floor``;
- ``off``: the oracle would rank it, and a ranked sphere lies within R of the ball (a verification
  ended near it, 2 cm or more off, or a better one suppressed it);
- ``search``: the oracle would rank it, and no ranked sphere lies within R (no verification started
  near it, or its verification failed where the truth's does not).

    python docs/experiments/scripts/candidate_losses.py data/train-stereo --limit 200 --seeds 0
    python docs/experiments/scripts/candidate_losses.py data/train-stereo --seeds 0 --set verification.verify_candidates=12
"""

from __future__ import annotations

import math
import sys
from collections import Counter

import numpy as np

import script_support as support
from spherebench import options
from spherebench.datasets import inout
from spherebench.eval.bench.oracle import CEILING_M, ceiling
from spherebench.eval.bench.seeds import detection_seed
from spherebench.method import detect, warm_up
from spherebench.parallel import single_thread_here

STAGES = ("ranked", "geometry", "size", "score", "off", "search")
#: Bands of surface distance (m) of the report.
BANDS_M = ((0.0, 0.75), (0.75, 1.0), (1.0, 1.25), (1.25, 1.5), (1.5, 2.5), (2.5, 9.0))


def stage(ranked_errors_m: list[float], oracle: dict | None, floor_raw: float, radius_m: float) -> str:
    """The first stage that loses a ball (STAGES), from the ranked spheres' distances to it (m) and the
    oracle's row (``oracle.ceiling``; None where the ball has a ranked sphere within 2 cm)."""
    if min(ranked_errors_m, default=math.inf) <= CEILING_M:
        return "ranked"
    if not oracle["error_m"] <= CEILING_M:
        return "geometry"
    if not oracle["size_ok"]:
        return "size"
    if oracle["score"] < floor_raw:
        return "score"
    return "off" if min(ranked_errors_m, default=math.inf) <= radius_m else "search"


def ball_rows(dataset: str, scenes, config, seeds: list[int], max_range_m: float) -> list[dict]:
    rows = []
    floor = config.verification.rank_floor
    with single_thread_here():
        warm_up(config)
        for scene in scenes:
            gt = inout.read_scene_gt(scene.path)
            balls = [(k, np.asarray(b["center_m"], np.float64)) for k, b in enumerate(gt.get("balls", []))
                     if b.get("center_m") is not None]
            balls = [(k, c) for k, c in balls if float(np.linalg.norm(c)) - config.radius_m <= max_range_m]
            if not balls:
                continue
            cloud = inout.load_cloud(scene.path)
            oracle_rows = None
            for seed in seeds:
                found = detect(cloud, config, seed=detection_seed(seed, scene.index), min_score=floor, max_spheres=100)
                for j, (k, c) in enumerate(balls):
                    errs = [float(np.linalg.norm(s.centre_m - c)) for s in found]
                    o = None
                    if min(errs, default=math.inf) > CEILING_M:
                        if oracle_rows is None:  # the same at every seed: the oracle draws nothing
                            oracle_rows = ceiling(cloud, [c for _, c in balls], config, separable=False)
                        o = oracle_rows[j]
                    rows.append({"scene": scene.path.name, "family": scene.family, "ball": k, "seed": seed,
                                 "distance_m": float(np.linalg.norm(c)) - config.radius_m,
                                 "resolution": scene.resolution,
                                 "ranked_error_mm": 1e3 * min(errs) if errs else None,
                                 "oracle_error_mm": None if o is None or not math.isfinite(o["error_m"])
                                 else 1e3 * o["error_m"],
                                 "stage": stage(errs, o, config.verification.floor_raw_score, config.radius_m)})
    return rows


def table(rows: list[dict]) -> list[dict]:
    out = []
    for lo, hi in BANDS_M:
        mine = [r for r in rows if lo <= r["distance_m"] < hi]
        if mine:
            n = Counter(r["stage"] for r in mine)
            out.append({"band": f"{lo:g}-{hi:g}", "balls": len(mine), **{s: n.get(s, 0) for s in STAGES}})
    n = Counter(r["stage"] for r in rows)
    out.append({"band": "all", "balls": len(rows), **{s: n.get(s, 0) for s in STAGES}})
    return out


def main(argv: list[str] | None = None) -> int:
    p = support.parser(__doc__)
    p.add_argument("--seeds", default="0", help="run seeds, e.g. 0-3 (default 0)")
    p.add_argument("--max-range", type=float, default=1.5, help="balls up to this surface distance (m; default 1.5)")
    p.add_argument("--set", action="append", default=[], metavar="PATH=VALUE",
                   help="a detector setting overridden, by its path (repeatable)")
    p.add_argument("--list", action="store_true", help="print every lost ball's row")
    support.add_json_argument(p)
    args = p.parse_args(argv)
    config = support.detector_config(args.dataset, support.settings(args.set, "candidate_losses"))
    seeds = options.parse_seeds(args.seeds)
    scenes = support.frame_scenes(args.dataset, args.limit, args.family)
    rows = ball_rows(args.dataset, scenes, config, seeds, args.max_range)
    summary = table(rows)
    print(f"candidate_losses on {args.dataset} ({len(scenes)} scenes), seeds {args.seeds}: balls within "
          f"{args.max_range:g} m by the stage that loses their ranked candidate\n")
    print("| band m | balls | " + " | ".join(STAGES) + " |")
    print("|---|---|" + "---|" * len(STAGES))
    for r in summary:
        print(support.row(r["band"], r["balls"], *(r[s] for s in STAGES)))
    if args.list:
        print("\n| scene | ball | seed | distance m | resolution | stage | ranked error mm | oracle error mm |")
        print("|---|---|---|---|---|---|---|---|")
        for r in rows:
            if r["stage"] != "ranked":
                print(support.row(r["scene"], r["ball"], r["seed"], f"{r['distance_m']:.2f}", r["resolution"],
                                  r["stage"], *(("-" if v is None else f"{v:.1f}")
                                                for v in (r["ranked_error_mm"], r["oracle_error_mm"]))))
    support.write_json(args.json, {"rows": rows, "summary": summary})
    return 0


if __name__ == "__main__":
    sys.exit(main())
