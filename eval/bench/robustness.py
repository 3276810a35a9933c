"""`spherebench robustness` (`make robustness`): the improved detector across sensor conditions,
against the robustness targets (``eval.metrics.targets``).

On the `robust` preset (20 sensor cells: subpixel x correlation x dropouts), per cell and range
group (balls within 2 m; at 2-3 m), over the run seeds: balls found (the nearest detection within
2 cm), the oracle's ceiling (``eval.bench.oracle``, ``eval.metrics.targets.ceiling_holds``: the detector's
verification started about the true centre, its score above every clutter sphere of its frame)
and the share it accepts at the detector's own threshold, the target and whether it holds. Then
the overall rate beside `default`'s, false detections, `hard`'s negatives and distractors, and the
time per 424x240 frame as a ratio to the `paper-lstsq` control (``eval.bench.speed.frame_best_times``:
the two take turns on each frame, the fastest of five runs each; the median of the frames'
ratios), with the frame noise measurement's own cost. A false detection lies farther than one radius from every
ball (``metrics3d``' "clutter"): a detection of a ball 2-3 cm off is a miss of the 2 cm rate, not
a false detection. Detections and the oracle run on the one task loop (``eval.bench.tasks``), scene k of
run seed s with ``detection_seed(s, k)``, the oracle with ``detection_seed(0, k)`` (as `make eval`'s).
"""

from __future__ import annotations

import json
import time

import numpy as np

from spherebench.datasets import inout
from spherebench.errors import SphereBenchError
from spherebench.eval.bench.registry import at_operating_point, detector_spec
from spherebench.eval.bench.seeds import detection_seed
from spherebench.eval.bench.speed import frame_best_times
from spherebench.eval.bench.studies import oracle_scene
from spherebench.eval.bench.tasks import dataset_scenes, run_tasks, tasks_for
from spherebench.eval.metrics import targets
from spherebench.eval.metrics.metrics3d import FOUND_M, detection_counts, scene_counts
from spherebench.eval.metrics.sensor_grid import GRID_AXES, grid_key
from spherebench.method import config_for
from spherebench.method.detector import prepare_frame
from spherebench.method.noise import frame_noise_correlation_px
from spherebench.parallel import executor, single_thread_here

#: The issue's time figure before this work: improved's 424x240 frame over paper-lstsq's (ratio).
TIME_RATIO_BEFORE = 1.35
#: ... which may grow by at most this factor.
TIME_RATIO_GROWTH = 1.1




def _run(ex, dataset: str, seeds: list[int], overrides: dict, oracle: bool, limit: int | None) -> dict:
    """Per-seed scene counts of one dataset, and (oracle=True) per-ball rows with the oracle's ceiling."""
    scenes = [s for s in dataset_scenes(dataset, limit) if s.has_cloud]
    gts = {s.scene_id: inout.read_scene_gt(s.path) for s in scenes}
    radius = float((inout.read_dataset_meta(dataset) or {}).get("ball_radius_m", 0.12))
    spec = detector_spec("improved", **{"radius_m": radius, **overrides})
    ceilings = {}
    if oracle:
        config = json.dumps({k: v for k, v in spec.config.items() if k not in ("engine", "preset")})
        tasks = [(config, str(s.path), detection_seed(0, s.index)) for s in scenes]
        ceilings = {s.scene_id: rows for s, rows in zip(scenes, ex.map(oracle_scene, tasks))}
    out = {"scenes": [], "balls": []}
    pairs = [(seed, s) for seed in seeds for s in scenes]
    records = run_tasks(ex, [t for seed in seeds for t in tasks_for(spec, scenes, seed)])
    for (seed, scene), rec in zip(pairs, records):
        gt = gts[scene.scene_id]
        counts = scene_counts([d["center_m"] for d in at_operating_point(rec["detections"], spec.config)], gt)
        # a false detection is one farther than a radius from every ball (``clutter``): a detection of
        # the ball 2-3 cm off is a miss of the 2 cm rate, not a detection of something else
        counts["false_2cm"], counts["false"] = counts["false"], counts["clutter"]
        out["scenes"].append({**counts, "scene": scene.path.name, "family": gt.get("family", ""), "seed": seed})
        if not oracle:
            continue
        cell = grid_key((gt.get("meta") or {}).get("sensor_cell"), GRID_AXES)
        for err, o in zip(counts["errs"], ceilings[scene.scene_id]):
            out["balls"].append({"scene": scene.path.name, "seed": seed, "cell": cell, "band": o["band"],
                                 "found": bool(err <= FOUND_M), "error_m": float(err), "within": o["within"],
                                 "separable": o["separable"], "oracle_score": o["score"]})
    return out


def _default_figures(rows: list[dict]) -> dict:
    counts = detection_counts(rows)
    near = [e for r in rows for e, z in zip(r["errs"], r["z"]) if z <= 2.0]
    return {"balls": counts["balls"], "found": counts["found"], "rate": counts["found"] / max(counts["balls"], 1),
            "median_err_mm_within_2m": float(np.median(near) * 1e3) if near else None,
            "false_detections": counts["false_detections"]}


def _timing(default: str, limit: int | None, overrides: dict, passes: int = 5) -> dict:
    """improved's and paper-lstsq's CPU time per 424x240 frame of ``default``: on each frame the two
    take turns ``passes`` times in one worker pinned to one thread (``bench.frame_best_times``), each
    keeps its fastest run; the ratio is the median over the frames of each frame's ratio (the ratio
    of the medians moved by +/- 10 % between runs here, as the machine's speed drifted between the
    frames of one configuration and those of the other). And the frame's noise measurement's own
    median time on the same frames (sigma_z and the correlation length, ``frame_noise_correlation_px``)."""
    if overrides:
        raise SphereBenchError("--set with timing: the timing runs the shipped configuration; add --no-timing")
    scenes = [s for s in dataset_scenes(default, limit) if s.has_cloud and s.resolution == "424x240"]
    if not scenes:
        raise SphereBenchError(f"{default}: no 424x240 scene to time; give the default preset's folder")
    tasks = [(str(s.path), ("improved", "paper-lstsq"), detection_seed(0, s.index), passes) for s in scenes]
    with executor(1, isolated=True) as ex:
        times = np.array(list(ex.map(frame_best_times, tasks)))
    imp, ctl = float(np.median(times[:, 0])), float(np.median(times[:, 1]))
    config = config_for("improved")
    noise_ms = []
    with single_thread_here():
        for scene in scenes:
            cloud = inout.load_cloud(scene.path)
            frame = prepare_frame(cloud, config)
            t0 = time.thread_time()
            for _ in range(20):  # both of its lags' mean squares, as prepare_frame measures them
                frame_noise_correlation_px(frame.points, frame.index_image, config, frame.bin)
            noise_ms.append((time.thread_time() - t0) / 20 * 1e3)
    ratio = float(np.median(times[:, 0] / times[:, 1])) if np.all(times > 0) else None
    limit_ratio = TIME_RATIO_BEFORE * TIME_RATIO_GROWTH
    return {"improved_ms": imp, "control_ms": ctl, "ratio": ratio, "ratio_limit": limit_ratio, "frames": len(scenes),
            "passes": passes, "ok": None if ratio is None else ratio <= limit_ratio,
            "noise_estimate_ms": float(np.median(noise_ms)),
            "noise_estimate_share": float(np.median(noise_ms)) / imp if imp else None}


def robustness(robust: str, seeds: list[int], default: str | None = None, hard: str | None = None,
               overrides: dict | None = None, workers: int = 2, limit: int | None = None,
               timing: bool = True, progress=print, engine: str = "local", address: str | None = None) -> dict:
    """The robustness report's figures (see the module docstring)."""
    overrides = overrides or {}
    with executor(workers, engine, address) as ex:
        result = _robustness(ex, robust, seeds, default, hard, overrides, limit, progress)
    if timing and default:
        progress("timing: improved and paper-lstsq on default's 424x240 frames")
        result["timing"] = _timing(default, limit, overrides)
    return result


def _robustness(ex, robust: str, seeds: list[int], default: str | None, hard: str | None, overrides: dict,
                limit: int | None, progress) -> dict:
    progress(f"robust: {len(inout.list_scenes(robust)[:limit])} scenes x {len(seeds)} seeds, with the oracle")
    r = _run(ex, robust, seeds, overrides, True, limit)
    if any(b["cell"] is None for b in r["balls"]):
        raise SphereBenchError(f"{robust}: scenes without a sensor cell: give the robust preset's folder")
    result = {"seeds": seeds, "overrides": overrides, "robust": str(robust), "cells": targets.cell_table(r["balls"]),
              "levels": targets.by_level(r["balls"]), "rows": r}
    default_rate = None
    if default:
        progress(f"default: {len(inout.list_scenes(default)[:limit])} scenes x {len(seeds)} seeds")
        d = _run(ex, default, seeds, overrides, False, limit)
        result["default"] = _default_figures(d["scenes"])
        default_rate = result["default"]["rate"]
    result["overall"] = targets.overall(r["balls"], r["scenes"], default_rate)
    if hard:
        progress(f"hard: {len(inout.list_scenes(hard)[:limit])} scenes x {len(seeds)} seeds")
        h = _run(ex, hard, seeds, overrides, False, limit)
        result["hard"] = detection_counts(h["scenes"])
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
        lines.append(f"| 424x240 frame / paper-lstsq (median of the frames' ratios; medians "
                     f"{t['improved_ms']:.2f} / {t['control_ms']:.2f} ms) | {t['ratio']:.2f} | "
                     f"<= {t['ratio_limit']:.2f} ({TIME_RATIO_BEFORE} x {TIME_RATIO_GROWTH}) | "
                     f"{_verdict(t['ok'])} |")
        lines.append(f"| frame noise measurement (sigma_z and correlation) | {1e3 * t['noise_estimate_ms']:.0f} us "
                     f"({_pct(t['noise_estimate_share'])} of the frame) | a small fraction | - |")
    lines += ["", "The default preset's mAP (target >= 0.965) is Table 3 of `make eval` (results/README.md)."]
    return "\n".join(lines) + "\n"
