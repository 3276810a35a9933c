"""`make robustness`: the improved detector across sensor conditions, against issue 16's targets.

    python -m spherebench.scripts.robustness data/robust --default data/default --hard data/hard \
        --seeds 0-3 --out results/robustness

On the `robust` preset (20 sensor cells: subpixel x correlation x dropouts), per cell and range
group (balls within 2 m; at 2-3 m), over the seeds: balls found (a detection within 2 cm), the
oracle's ceiling (``eval.oracle``, ``eval.robustness.ceiling_holds``: the detector's verification
started about the true centre, its score above every clutter sphere of its frame) and the share it
accepts at the detector's own threshold, the target (``eval.robustness``) and whether it holds. Then
the overall rate beside `default`'s, false detections, `hard`'s negatives and distractors, and the
time per 424x240 frame as a ratio to the `paper-lstsq` control (``scripts.bench``, same run, same
frames), with the frame noise estimate's own cost. A false detection lies farther than one radius
from every ball (the matching gate of ``eval.metrics3d``): a detection of a ball 2-3 cm off is a
miss of the 2 cm rate, not a false detection. Prints markdown; --out writes OUT.md and OUT.json
(atomically).
"""

from __future__ import annotations

import os
import sys

if "numba" not in sys.modules:  # single-threaded detector, as in bench and sweep
    os.environ.setdefault("NUMBA_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import argparse  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from spherebench import options  # noqa: E402
from spherebench.datasets import inout  # noqa: E402
from spherebench.errors import SphereBenchError  # noqa: E402
from spherebench.eval import robustness as rb  # noqa: E402
from spherebench.eval.metrics3d import FOUND_M, detection_counts, scene_counts  # noqa: E402
from spherebench.eval.sensor_grid import GRID_AXES, band_of, grid_key, surface_distance_m  # noqa: E402
from spherebench.parallel import process_pool  # noqa: E402
from spherebench.scripts.sweep import parse_overrides, parse_seeds  # noqa: E402

#: The issue's time figure before this work: improved's 424x240 frame over paper-lstsq's (ratio).
TIME_RATIO_BEFORE = 1.35
#: ... which may grow by at most this factor.
TIME_RATIO_GROWTH = 1.1


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("robust", help="the robust preset's folder (spherebench generate --preset robust)")
    p.add_argument("--default", default=None, help="the default preset's folder: its rate, error and the timing")
    p.add_argument("--hard", default=None, help="the hard preset's folder: negatives and distractors")
    p.add_argument("--seeds", default="0-3", help="detector seeds, e.g. 0-3 or 0,2")
    p.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                   help="override a DetectorConfig field (repeatable), as in sweep")
    p.add_argument("--workers", type=int, default=2, help="processes")
    p.add_argument("--limit", type=options.count, default=None,
                   help="at most this many scenes per dataset (quick runs)")
    p.add_argument("--no-timing", action="store_true", help="skip the timing against paper-lstsq")
    p.add_argument("--out", type=options.out_path, default=None, help="write OUT.md and OUT.json")


def _scene_work(task: tuple) -> dict:
    """One worker's share of one dataset: per-seed scene counts, and (oracle=True) per-ball rows."""
    scenes, seeds, overrides, oracle = task
    from spherebench.eval.oracle import ceiling
    from spherebench.method import config_for, detect
    out = {"scenes": [], "balls": []}
    for scene in scenes:
        gt = inout.read_json(Path(scene) / "gt.json")
        cloud = inout.load_cloud(scene)
        R = float(gt.get("ball_radius_m", 0.12))
        config = config_for("improved", **{"radius_m": R, **overrides})
        centres = [b["center_m"] for b in gt["balls"] if b.get("center_m") is not None]
        ceil = ceiling(cloud, centres, config) if oracle and centres else [{}] * len(centres)
        cell = grid_key((gt.get("meta") or {}).get("sensor_cell"), GRID_AXES)
        for seed in seeds:
            counts = scene_counts([s.center_m for s in detect(cloud, config, seed=seed)], gt)
            # a false detection is one farther than a radius from every ball (``clutter``): a detection of
            # the ball 2-3 cm off is a miss of the 2 cm rate, not a detection of something else
            counts["false_2cm"], counts["false"] = counts["false"], counts["clutter"]
            out["scenes"].append({**counts, "scene": Path(scene).name, "family": gt.get("family", ""), "seed": seed})
            if not oracle:
                continue
            for c, err, o in zip(centres, counts["errs"], ceil):
                out["balls"].append({"scene": Path(scene).name, "seed": seed, "cell": cell,
                                     "band": band_of(surface_distance_m(c, R)), "found": bool(err <= FOUND_M),
                                     "error_m": float(err), "within": bool(o.get("within")),
                                     "separable": o.get("separable"), "oracle_score": o.get("score")})
    return out


def _run(dataset: str, seeds: list[int], overrides: dict, oracle: bool, workers: int, limit: int | None) -> dict:
    scenes = [str(s) for s in inout.list_scenes(dataset)[:limit]]
    tasks = [(scenes[k::workers], seeds, overrides, oracle) for k in range(workers) if scenes[k::workers]]
    if workers > 1 and len(tasks) > 1:
        with process_pool(len(tasks), start_method="spawn") as pool:
            parts = list(pool.map(_scene_work, tasks))
    else:
        parts = [_scene_work(t) for t in tasks]
    return {"scenes": [r for p in parts for r in p["scenes"]], "balls": [r for p in parts for r in p["balls"]]}


def _default_figures(rows: list[dict]) -> dict:
    counts = detection_counts(rows)
    near = [e for r in rows for e, z in zip(r["errs"], r["z"]) if z <= 2.0]
    return {"balls": counts["balls"], "found": counts["found"], "rate": counts["found"] / max(counts["balls"], 1),
            "median_err_mm_within_2m": float(np.median(near) * 1e3) if near else None,
            "false_detections": counts["false_detections"]}


def _timing(default: str, limit: int | None, overrides: dict) -> dict:
    """improved's and paper-lstsq's CPU time per 424x240 frame (``scripts.bench``, best of 3), and
    the frame noise estimate's own median time on the same frames."""
    from spherebench.method import config_for
    from spherebench.method.detector import prepare_frame
    from spherebench.method.improved import frame_noise_a
    from spherebench.scripts import bench
    if overrides:
        raise SphereBenchError("--set with timing: the timing runs the shipped configuration; add --no-timing")
    res = bench.bench([default], paper_subset=-1, peer_subset=0, limit=limit, min_scores=(), progress=None)
    summ = next(iter(res["datasets"].values()))["summary"]
    imp = summ["improved"]["time"].get("424x240", {}).get("cpu_best_median_ms")
    ctl = summ["paper-lstsq"]["time"].get("424x240", {}).get("cpu_median_ms")
    config = config_for("improved")
    noise_ms = []
    for scene in inout.list_scenes(default)[:limit]:
        cloud = inout.load_cloud(scene)
        frame = prepare_frame(cloud, config)
        t0 = time.thread_time()
        for _ in range(20):
            frame_noise_a(frame.points, frame.index_image, config, frame.bin)
        noise_ms.append((time.thread_time() - t0) / 20 * 1e3)
    ratio = imp / ctl if imp and ctl else None
    limit_ratio = TIME_RATIO_BEFORE * TIME_RATIO_GROWTH
    return {"improved_ms": imp, "control_ms": ctl, "ratio": ratio, "ratio_limit": limit_ratio,
            "ok": None if ratio is None else ratio <= limit_ratio, "noise_estimate_ms": float(np.median(noise_ms)),
            "noise_estimate_share": float(np.median(noise_ms)) / imp if imp else None}


def robustness(robust: str, seeds: list[int], default: str | None = None, hard: str | None = None,
               overrides: dict | None = None, workers: int = 2, limit: int | None = None,
               timing: bool = True, progress=print) -> dict:
    overrides = overrides or {}
    progress(f"robust: {len(inout.list_scenes(robust)[:limit])} scenes x {len(seeds)} seeds, with the oracle")
    r = _run(robust, seeds, overrides, True, workers, limit)
    if any(b["cell"] is None for b in r["balls"]):
        raise SphereBenchError(f"{robust}: scenes without a sensor cell: give the robust preset's folder")
    result = {"seeds": seeds, "overrides": overrides, "robust": str(robust), "cells": rb.cell_table(r["balls"]),
              "levels": rb.by_level(r["balls"]), "rows": r}
    default_rate = None
    if default:
        progress(f"default: {len(inout.list_scenes(default)[:limit])} scenes x {len(seeds)} seeds")
        d = _run(default, seeds, overrides, False, workers, limit)
        result["default"] = _default_figures(d["scenes"])
        default_rate = result["default"]["rate"]
    result["overall"] = rb.overall(r["balls"], r["scenes"], default_rate)
    if hard:
        progress(f"hard: {len(inout.list_scenes(hard)[:limit])} scenes x {len(seeds)} seeds")
        h = _run(hard, seeds, overrides, False, workers, limit)
        result["hard"] = detection_counts(h["scenes"])
    if timing and default:
        progress("timing: improved and paper-lstsq on default's 424x240 frames")
        result["timing"] = _timing(default, limit, overrides)
    return result


def _pct(x) -> str:
    return "-" if x is None else f"{100 * x:.1f} %"


def _verdict(ok) -> str:
    return "-" if ok is None else "PASS" if ok else "FAIL"


def markdown(res: dict) -> str:
    seeds = ",".join(map(str, res["seeds"]))
    lines = [f"# Robustness: the improved detector across sensor conditions (seeds {seeds})", ""]
    if res["overrides"]:
        lines += [f"Overrides: `{res['overrides']}`", ""]
    lines += ["Per `robust` cell (20 scenes, pooled over the seeds): balls found (a detection within 2 cm); the "
              "oracle's ceiling (verified from about the true centre to within 2 cm, the right size, a score above "
              "every clutter sphere of the frame; or found) and the share the oracle accepts at the detector's "
              "threshold; the target (the issue's, or 97 % of the ceiling where that is lower).", "",
              "| subpixel | correlation | dropouts | range | balls | found | rate | ceiling | accepted | target | |",
              "|---|---|---|---|---|---|---|---|---|---|---|"]
    for c in res["cells"]:
        mark = "" if c["target"] >= c["nominal_target"] else " (of ceiling)"
        lines.append(f"| {c['subpixel']:g} | {c['correlation']} | {c['dropouts']} | {c['range']} | {c['n']} | "
                     f"{c['found']} | {_pct(c['rate'])} | {_pct(c['ceiling'])} | {_pct(c['accepted'])} | "
                     f"{_pct(c['target'])}{mark} | {_verdict(c['ok'])} |")
    held = sum(c["ok"] for c in res["cells"])
    lines += ["", f"Cells holding their target: {held}/{len(res['cells'])}.", "",
              "By noise level and range band (pooled over correlation and dropouts):", "",
              "| subpixel | band | balls | found | rate | ceiling | accepted |", "|---|---|---|---|---|---|---|"]
    for v in res["levels"]:
        lines.append(f"| {v['subpixel']:g} | {v['band']} | {v['n']} | {v['found']} | {_pct(v['rate'])} | "
                     f"{_pct(v['ceiling'])} | {_pct(v['accepted'])} |")
    o = res["overall"]
    lines += ["", "| overall | figure | target | |", "|---|---|---|---|",
              f"| robust rate | {_pct(o['rate'])} ({o['found']}/{o['balls']}; ceiling {_pct(o['ceiling'])}) | "
              f"default's - 3 points | {_verdict(o['gap_ok'])} |"]
    if "default" in res:
        d = res["default"]
        lines.append(f"| default rate | {_pct(d['rate'])} ({d['found']}/{d['balls']}) | >= 99 % | "
                     f"{_verdict(d['rate'] >= 0.99)} |")
        med = d["median_err_mm_within_2m"]
        lines.append(f"| default median centre error within 2 m | {med:.2f} mm | <= 3 mm | {_verdict(med <= 3.0)} |")
    lines.append(f"| robust false detections | {o['false_detections']} in {o['scene_runs_with_false']}/"
                 f"{o['scene_runs']} scene runs ({_pct(o['false_share'])}) | <= 0.5 % of scenes | "
                 f"{_verdict(o['false_ok'])} |")
    if "hard" in res:
        h = res["hard"]
        lines.append(f"| hard: detections on negatives | {h['detections_on_negatives']} "
                     f"({h['negative_scenes']} negative scene runs) | 0 | "
                     f"{_verdict(h['detections_on_negatives'] == 0)} |")
        lines.append(f"| hard: distractors rejected | {h['distractors_rejected']}/{h['distractors']} | all | "
                     f"{_verdict(h['distractors_rejected'] == h['distractors'])} |")
    if "timing" in res:
        t = res["timing"]
        lines.append(f"| 424x240 frame / paper-lstsq | {t['improved_ms']:.2f} / {t['control_ms']:.2f} ms = "
                     f"{t['ratio']:.2f} | <= {t['ratio_limit']:.2f} ({TIME_RATIO_BEFORE} x {TIME_RATIO_GROWTH}) | "
                     f"{_verdict(t['ok'])} |")
        lines.append(f"| frame noise estimate | {1e3 * t['noise_estimate_ms']:.0f} us "
                     f"({_pct(t['noise_estimate_share'])} of the frame) | a small fraction | - |")
    lines += ["", "The default preset's mAP (target >= 0.965) is Table 3 of `make eval` (results/README.md)."]
    return "\n".join(lines) + "\n"


def run(args: argparse.Namespace) -> int:
    seeds = parse_seeds(args.seeds)
    overrides = parse_overrides(args.set)
    from spherebench.method import config_for
    config_for("improved", **overrides)  # a bad override: one line before any work
    if args.workers < 1:
        raise SphereBenchError(f"--workers {args.workers}: give at least 1")
    for ds in (args.robust, args.default, args.hard):
        if ds:
            inout.list_scenes(ds)
    if args.out:
        inout.check_report_out(args.out, "robustness")
    if not ((inout.read_dataset_meta(args.robust).get("sensor_ranges") or {}).get("grid")):
        raise SphereBenchError(f"{args.robust}: no grid of sensor cells in its dataset.json: give the robust "
                               "preset's folder (spherebench generate --preset robust)")
    res = robustness(args.robust, seeds, args.default, args.hard, overrides, args.workers, args.limit,
                     not args.no_timing, progress=lambda s: print(s, file=sys.stderr, flush=True))
    md = markdown(res)
    print(md)
    if args.out:
        print("wrote {} and {}".format(*inout.write_report(args.out, md, res, "robustness")), file=sys.stderr)
    return 0


def main(argv: list[str] | None = None) -> int:
    from spherebench.cli import run_module
    return run_module("robustness", sys.modules[__name__], argv)


if __name__ == "__main__":
    sys.exit(main())
