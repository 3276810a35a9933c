"""`make sweep`: the 3D detector's detections over several seeds, and how much they move with it.

    python -m spherebench.scripts.sweep data/default data/hard --seeds 0-7 --out results/sweep
    python -m spherebench.scripts.sweep data/train --seeds 0-3 --set verify_candidates_if_none=10

One seed for all the scenes of a run, as in ``make bench``; per dataset and seed: basketballs found
(centre within 2 cm), false detections, detections on the negative scenes, distractor balls
rejected, and the same per scene family (``eval.metrics3d.scene_counts``). Detections only, no
timing: scenes are shared among ``--workers`` processes, each single-threaded, and each scene is
loaded once for all the seeds. ``--set NAME=VALUE`` overrides a field of the detector's
configuration (``method.config.DetectorConfig``), to compare a change over seeds: a difference of a
ball or two at one seed is within what the seed alone moves (see the README).
"""

from __future__ import annotations

import os
import sys

if "numba" not in sys.modules:  # one thread per worker process (see scripts/bench.py)
    os.environ.setdefault("NUMBA_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import json  # noqa: E402
import multiprocessing  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from spherebench import __version__, options  # noqa: E402
from spherebench.datasets import inout  # noqa: E402
from spherebench.errors import SphereBenchError  # noqa: E402
from spherebench.eval.metrics3d import detection_counts, scene_counts  # noqa: E402
from spherebench.parallel import ignore_interrupts  # noqa: E402


def parse_seeds(text: str) -> list[int]:
    """"0-3" -> [0, 1, 2, 3]; "0,2,5" -> [0, 2, 5] (ranges and lists mix: "0-2,7")."""
    seeds: list[int] = []
    try:
        for part in (p.strip() for p in text.split(",") if p.strip()):
            lo, _, hi = part.partition("-")
            seeds += list(range(int(lo), int(hi) + 1)) if hi else [int(lo)]
    except ValueError:
        seeds = []
    if not seeds or any(s < 0 for s in seeds):
        raise SphereBenchError(f"--seeds {text!r}: give non-negative seeds, e.g. 0-3 or 0,1,5")
    return sorted(set(seeds))


def parse_overrides(items: list[str]) -> dict:
    """["min_score=0.3", "adaptive=false"] -> {"min_score": 0.3, "adaptive": False}: each value is read
    as JSON (numbers, true/false, null), else kept as a string."""
    out = {}
    for item in items:
        name, sep, value = item.partition("=")
        if not sep or not name.strip():
            raise SphereBenchError(f"--set {item!r}: give NAME=VALUE, e.g. --set min_score=0.3")
        try:
            out[name.strip()] = json.loads(value)
        except json.JSONDecodeError:
            out[name.strip()] = value
    return out


def _work(task: tuple) -> list[dict]:
    """One worker's share: every (scene, seed) of its scenes, as scene_counts rows."""
    scenes, seeds, method, overrides = task
    from spherebench.method import config_for, detect
    rows = []
    for scene in scenes:
        gt = inout.read_json(Path(scene) / "gt.json")
        cloud = inout.load_cloud(scene)
        config = config_for(method, **{"radius_m": float(gt.get("ball_radius_m", 0.12)), **overrides})
        for seed in seeds:
            found = detect(cloud, config, seed=seed)
            rows.append({**scene_counts([s.center_m for s in found], gt), "scene": Path(scene).name,
                         "family": gt.get("family", ""), "seed": seed})
    return rows


def sweep(datasets: list[str], seeds: list[int], method: str = "improved", overrides: dict | None = None,
          workers: int = 2, limit: int | None = None) -> dict:
    """Detection counts per dataset, seed and family (see the module docstring)."""
    from spherebench.method import config_for
    overrides = overrides or {}
    config_for(method, **overrides)  # a clear error for a bad method or override before any work
    result = {"method": method, "overrides": overrides, "seeds": seeds, "datasets": {}}
    for ds in datasets:
        scenes = [str(s) for s in inout.list_scenes(ds)[:limit]]
        tasks = [(scenes[k::workers], seeds, method, overrides) for k in range(workers) if scenes[k::workers]]
        if workers > 1 and len(tasks) > 1:
            with multiprocessing.get_context("spawn").Pool(len(tasks), initializer=ignore_interrupts) as pool:
                rows = [r for part in pool.map(_work, tasks) for r in part]
        else:
            rows = [r for t in tasks for r in _work(t)]
        families = sorted({r["family"] for r in rows})
        per_seed = {}
        for seed in seeds:
            mine = [r for r in rows if r["seed"] == seed]
            per_seed[seed] = {"total": detection_counts(mine),
                              "families": {f: detection_counts([r for r in mine if r["family"] == f])
                                           for f in families}}
        result["datasets"][Path(ds).name] = {"path": str(ds), "scenes": len(scenes), "families": families,
                                             "per_seed": per_seed}
    return result


def markdown(result: dict) -> str:
    """The sweep's tables: totals per dataset and seed, then balls found (false detections) per family."""
    seeds = result["seeds"]
    head = f"{result['method']}" + (f" with {result['overrides']}" if result["overrides"] else "")
    lines = [f"### {head}: detections per seed (one seed for all scenes; centre within 2 cm)", "",
             "| dataset | seed | balls found | false det. | of them clutter (> R off) | det. on negatives | "
             "distractors rejected |", "|---|---|---|---|---|---|---|"]
    for name, d in result["datasets"].items():
        for seed in seeds:
            t = d["per_seed"][seed]["total"]
            neg = f"{t['detections_on_negatives']} in {t['negative_scenes']}" if t["negative_scenes"] else "-"
            dist = f"{t['distractors_rejected']}/{t['distractors']}" if t["distractors"] else "-"
            lines.append(f"| {name} | {seed} | {t['found']}/{t['balls']} | {t['false_detections']} | "
                         f"{t['clutter_detections']} | {neg} | {dist} |")
        found = [d["per_seed"][s]["total"]["found"] for s in seeds]
        false = [d["per_seed"][s]["total"]["false_detections"] for s in seeds]
        clutter = [d["per_seed"][s]["total"]["clutter_detections"] for s in seeds]
        lines.append(f"| {name} | mean | {np.mean(found):.2f} (min {min(found)}, max {max(found)}) | "
                     f"{np.mean(false):.2f} | {np.mean(clutter):.2f} | | |")
    for name, d in result["datasets"].items():
        lines += ["", f"{name}, balls found (false detections; of them clutter) per family and seed:", "",
                  "| family | " + " | ".join(f"seed {s}" for s in seeds) + " |", "|---|" + "---|" * len(seeds)]
        for f in d["families"]:
            cells = []
            for s in seeds:
                c = d["per_seed"][s]["families"][f]
                cells.append(f"{c['found']}/{c['balls']} ({c['false_detections']}; {c['clutter_detections']})")
            lines.append(f"| {f} | " + " | ".join(cells) + " |")
    lines += ["", f"- spherebench {__version__}; numpy {np.__version__}"]
    return "\n".join(lines) + "\n"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("datasets", nargs="+", help="dataset folders")
    p.add_argument("--seeds", default="0-3", help="detector seeds: a range, a list, or both (e.g. 0-3, 0,2,5)")
    p.add_argument("--method", default="improved", help="detector preset (improved, paper, paper-lstsq)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="NAME=VALUE",
                   help="override a DetectorConfig field (repeatable), e.g. --set min_score=0.3")
    p.add_argument("--workers", type=int, default=2, help="processes (each single-threaded)")
    p.add_argument("--limit", type=options.count, default=None, help="at most this many scenes per dataset (quick runs)")
    p.add_argument("--out", default=None, help="write OUT.md and OUT.json (atomically)")


def run(args: argparse.Namespace) -> int:
    for ds in args.datasets:
        inout.list_scenes(ds)  # a clear error for a missing dataset before any work
    if args.out:
        inout.check_report_out(args.out, "sweep")
    if args.workers < 1:
        raise SphereBenchError(f"--workers {args.workers}: give at least 1")
    result = sweep(args.datasets, parse_seeds(args.seeds), args.method, parse_overrides(args.overrides),
                   args.workers, args.limit)
    md = markdown(result)
    print(md)
    if args.out:
        print("wrote {} and {}".format(*inout.write_report(args.out, md, result, "sweep")), file=sys.stderr)
    return 0


def main(argv: list[str] | None = None) -> int:
    from spherebench.cli import run_module
    return run_module("sweep", sys.modules[__name__], argv)


if __name__ == "__main__":
    sys.exit(main())
