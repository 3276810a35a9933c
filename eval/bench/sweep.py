"""`spherebench sweep` (`make sweep`): the 3D detector's detections over several run seeds, and how
much they move with it.

Per dataset and run seed: basketballs found (nearest detection within 2 cm, ``metrics3d.scene_counts``;
in brackets where it differs, by the far rule: 3 cm for a ball deeper than 3 m), false detections,
detections on the negative scenes, distractor balls rejected, and the same per scene family.
Detections only, no timing: the scenes x seeds tasks run on the one task loop (``eval.bench.tasks``)
over the executor's workers, scene k of run seed s with ``detection_seed(s, k)``.
Overrides of the detector's configuration (settings by path, ``verification.min_score``) compare a
change over seeds: a difference of a ball or two at one seed is within what the seed alone moves.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from spherebench import __version__, options
from spherebench.datasets import inout
from spherebench.eval.bench.registry import at_operating_point, detector_spec
from spherebench.eval.bench.tasks import dataset_scenes, run_tasks, tasks_for
from spherebench.eval.metrics.metrics3d import detection_counts, scene_counts
from spherebench.method import config_for
from spherebench.method.config import dotted_overrides
from spherebench.parallel import executor


def read_settings(items: list[str], command: str) -> dict:
    """--set NAME=VALUE items as {path: value} (``options.parse_overrides``); a bare name of before the
    configuration's groups is read as its path, with one deprecation line on stderr."""
    return dotted_overrides(options.parse_overrides(items),
                            lambda line: print(f"spherebench {command}: {line}", file=sys.stderr))


def sweep(datasets: list[str], seeds: list[int], method: str = "improved", overrides: dict | None = None,
          workers: int = 2, limit: int | None = None, engine: str = "local", address: str | None = None) -> dict:
    """Detection counts per dataset, run seed and family (see the module docstring)."""
    overrides = overrides or {}
    config_for(method, **overrides)  # a clear error for a bad method or override before any work
    result = {"method": method, "overrides": overrides, "seeds": seeds, "datasets": {}}
    with executor(workers, engine, address) as ex:
        for ds in datasets:
            scenes = [s for s in dataset_scenes(ds, limit) if s.has_frame]
            gts = {s.scene_id: inout.read_scene_gt(s.path) for s in scenes}
            meta = inout.read_dataset_meta(ds) if (Path(ds) / "dataset.json").is_file() else {}
            spec = detector_spec(method, **{"radius_m": float(meta.get("ball_radius_m", 0.12)), **overrides})
            tasks = [t for seed in seeds for t in tasks_for(spec, scenes, seed)]
            rows = []
            for (seed, scene), rec in zip(((seed, s) for seed in seeds for s in scenes), run_tasks(ex, tasks)):
                gt = gts[scene.scene_id]
                dets = at_operating_point(rec["detections"], spec.config)
                rows.append({**scene_counts([d["center_m"] for d in dets], gt),
                             "scene": scene.path.name, "family": gt.get("family", ""), "seed": seed})
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


def _found(c: dict) -> str:
    """found/balls, and in brackets the far rule's count where it differs."""
    far = c.get("found_far_rule", c["found"])
    return f"{c['found']}/{c['balls']}" + (f" [{far}]" if far != c["found"] else "")


def markdown(result: dict) -> str:
    """The sweep's tables: totals per dataset and seed, then balls found (false detections) per family."""
    seeds = result["seeds"]
    head = f"{result['method']}" + (f" with {result['overrides']}" if result["overrides"] else "")
    lines = [f"### {head}: detections per run seed (scene k detected with SeedSequence((seed, k)); centre within 2 cm; "
             "[in brackets where it differs: within 3 cm for a ball deeper than 3 m, the far rule])", "",
             "| dataset | seed | balls found | false det. | of them clutter (> R off) | det. on negatives | "
             "distractors rejected |", "|---|---|---|---|---|---|---|"]
    for name, d in result["datasets"].items():
        for seed in seeds:
            t = d["per_seed"][seed]["total"]
            neg = f"{t['detections_on_negatives']} in {t['negative_scenes']}" if t["negative_scenes"] else "-"
            dist = f"{t['distractors_rejected']}/{t['distractors']}" if t["distractors"] else "-"
            lines.append(f"| {name} | {seed} | {_found(t)} | {t['false_detections']} | "
                         f"{t['clutter_detections']} | {neg} | {dist} |")
        found = [d["per_seed"][s]["total"]["found"] for s in seeds]
        far = [d["per_seed"][s]["total"].get("found_far_rule", f) for s, f in zip(seeds, found)]
        false = [d["per_seed"][s]["total"]["false_detections"] for s in seeds]
        clutter = [d["per_seed"][s]["total"]["clutter_detections"] for s in seeds]
        far_mean = f" [{np.mean(far):.2f}]" if far != found else ""
        lines.append(f"| {name} | mean | {np.mean(found):.2f} (min {min(found)}, max {max(found)}){far_mean} | "
                     f"{np.mean(false):.2f} | {np.mean(clutter):.2f} | | |")
    for name, d in result["datasets"].items():
        lines += ["", f"{name}, balls found (false detections; of them clutter) per family and seed:", "",
                  "| family | " + " | ".join(f"seed {s}" for s in seeds) + " |", "|---|" + "---|" * len(seeds)]
        for f in d["families"]:
            cells = []
            for s in seeds:
                c = d["per_seed"][s]["families"][f]
                cells.append(f"{_found(c)} ({c['false_detections']}; {c['clutter_detections']})")
            lines.append(f"| {f} | " + " | ".join(cells) + " |")
    lines += ["", f"- spherebench {__version__}; numpy {np.__version__}"]
    return "\n".join(lines) + "\n"
