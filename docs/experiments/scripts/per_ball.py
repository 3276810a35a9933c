"""Per-ball outcomes of the 3D detector on a dataset over run seeds, and an A/B of two configurations.

For every ball of every scene with a depth frame, at every run seed: the nearest detection's centre
error, whether it lies within 2 cm (found), or 3 cm for a ball deeper than 3 m (the far rule), that
detection's score, the ball's depth and one pixel's depth noise there over R (the configuration's
nominal noise model; ``--frame-noise``: the frame's own, as the kernels take it). Per scene: false
detections (farther than 2 cm from every ball), clutter (farther than R from every ball), and the
distractor balls accepted. Scene k of run seed s is
detected with ``detection_seed(s, k)`` on the benchmark's task loop, so the totals are
``spherebench sweep``'s on the same scenes.

With ``--set-b`` (or ``--method-b``) the same runs again with configuration B on the same scenes
and seeds, and the balls whose outcome differs are listed: found by A only, by B only.
``--by-noise EDGES`` adds a table by one pixel's noise over R: balls, found, and the median, mean
and 90th percentile centre error of the balls with a detection within R.

    python docs/experiments/scripts/per_ball.py data/train --seeds 0-3 --set-b outline.outline_max_bias_px=1.0
    python docs/experiments/scripts/per_ball.py data/hard --family occluded --seeds 0-3 --list
    python docs/experiments/scripts/per_ball.py data/train --seeds 0 \\
        --set outline.outline_noise_fraction=inf --set-b outline.outline_noise_fraction=0 \\
        --by-noise 0,0.1,0.2,0.25,0.3,0.35,0.4,0.5,0.7,1.0

Detections only, no timing (``ab_timing.py`` times two configurations).
"""

from __future__ import annotations

import math
import sys

import numpy as np

import script_support as support
from spherebench import options
from spherebench.datasets import inout
from spherebench.eval.bench.registry import at_operating_point, detector_spec
from spherebench.eval.bench.tasks import run_tasks, tasks_for
from spherebench.eval.metrics.metrics3d import (FAR_RULE_FROM_M, FOUND_FAR_M, FOUND_M, MATCH_GATE_M, detection_counts,
                                                scene_counts)
from spherebench.parallel import executor

NOISE_EDGES = "0,0.1,0.2,0.25,0.3,0.35,0.4,0.5,0.7,1.0"


def run_config(ex, dataset: str, scenes, seeds: list[int], method: str, overrides: dict,
               frame_noise: bool = False) -> dict:
    """One configuration on ``scenes`` at every seed: {"balls": per-ball rows, "scenes": per-scene rows}."""
    config = support.detector_config(dataset, overrides, method)
    noise = {s.scene_id: support.scene_noise_a(s, config, frame_noise) for s in scenes}
    spec = detector_spec(method, **{"radius_m": config.radius_m, **overrides})
    gts = {s.scene_id: inout.read_scene_gt(s.path) for s in scenes}
    records = run_tasks(ex, [t for seed in seeds for t in tasks_for(spec, scenes, seed)])
    balls, scene_rows = [], []
    for (seed, scene), rec in zip(((seed, s) for seed in seeds for s in scenes), records):
        gt = gts[scene.scene_id]
        ranked = rec["detections"]  # the ranked output, down to the benchmark's floor
        dets = at_operating_point(ranked, spec.config)
        counts = scene_counts([d["center_m"] for d in dets], gt)
        scene_rows.append({**counts, "scene": scene.path.name, "family": scene.family, "seed": seed})
        # ``scene_counts``' errors follow the scene's balls with a known centre; k: the ball's index in gt.json
        known = [(k, b["center_m"]) for k, b in enumerate(gt["balls"]) if b.get("center_m") is not None]
        for (k, centre), err in zip(known, counts["errs"]):
            nearest = min(dets, key=lambda d: np.linalg.norm(np.subtract(d["center_m"], centre)), default=None)
            balls.append({"scene": scene.path.name, "family": scene.family, "ball": k, "seed": seed,
                          "z_m": float(centre[2]),
                          "noise_r": support.noise_over_r(noise[scene.scene_id], centre, config),
                          "error_mm": 1e3 * err if math.isfinite(err) else None,
                          "found": bool(err <= FOUND_M),
                          "found_far_rule": bool(err <= (FOUND_FAR_M if centre[2] > FAR_RULE_FROM_M else FOUND_M)),
                          "score": None if nearest is None else float(nearest["score"]),
                          "ranked_error_mm": min((1e3 * float(np.linalg.norm(np.subtract(d["center_m"], centre)))
                                                  for d in ranked), default=None),
                          "distance_m": float(np.linalg.norm(centre)) - config.radius_m,
                          "sensor_cell": scene.sensor_cell})
    return {"method": method, "overrides": overrides, "balls": balls, "scenes": scene_rows}


def totals(run: dict, seeds: list[int]) -> dict:
    """Per seed: ``detection_counts`` of the scene rows (balls, found, false detections...)."""
    return {seed: detection_counts([r for r in run["scenes"] if r["seed"] == seed]) for seed in seeds}


def differing(a: dict, b: dict) -> list[dict]:
    """The balls (scene, ball, seed) found by one configuration and not the other."""
    key = lambda r: (r["scene"], r["ball"], r["seed"])  # noqa: E731
    b_rows = {key(r): r for r in b["balls"]}
    out = []
    for r in a["balls"]:
        s = b_rows[key(r)]
        if r["found"] != s["found"]:
            out.append({"scene": r["scene"], "family": r["family"], "ball": r["ball"], "seed": r["seed"],
                        "z_m": r["z_m"], "found_by": "A" if r["found"] else "B",
                        "a_error_mm": r["error_mm"], "a_score": r["score"],
                        "b_error_mm": s["error_mm"], "b_score": s["score"]})
    return out


def by_noise(run: dict, edges: list[float]) -> list[dict]:
    """Per bin of one pixel's noise over R: balls, found, and the error of those with a detection within R."""
    out = []
    labels = sorted({support.noise_bin(r["noise_r"], edges) for r in run["balls"]},
                    key=lambda s: float(s.split("-")[0].rstrip("+").lstrip("<")) if s != "unknown" else math.inf)
    for label in labels:
        rows = [r for r in run["balls"] if support.noise_bin(r["noise_r"], edges) == label]
        errs = np.array([r["error_mm"] for r in rows if r["error_mm"] is not None
                         and r["error_mm"] <= 1e3 * MATCH_GATE_M], float)
        out.append({"bin": label, "balls": len(rows), "found": sum(r["found"] for r in rows),
                    "median_mm": float(np.median(errs)) if errs.size else None,
                    "mean_mm": float(np.mean(errs)) if errs.size else None,
                    "p90_mm": float(np.percentile(errs, 90)) if errs.size else None})
    return out


#: Bands of a ball's surface distance (m) in ``--by-range``.
RANGE_EDGES_M = (0.0, 1.5, 2.5, 3.5, 9.0)


def by_range(run: dict, seeds: list[int]) -> list[dict]:
    """Per band of surface distance, balls over all seeds: found at the operating point, and a ranked
    detection (any score down to the floor) within 2 cm (3 cm beyond 3 m deep) and within 6 cm."""
    out = []
    for lo, hi in zip(RANGE_EDGES_M, RANGE_EDGES_M[1:]):
        rows = [r for r in run["balls"] if lo <= r["distance_m"] < hi]
        near = lambda r, mm: r["ranked_error_mm"] is not None and r["ranked_error_mm"] <= mm  # noqa: E731
        out.append({"band": f"{lo:g}-{hi:g}", "balls": len(rows), "found_far_rule": sum(r["found_far_rule"] for r in rows),
                    "ranked_2cm": sum(near(r, 1e3 * (FOUND_FAR_M if r["z_m"] > FAR_RULE_FROM_M else FOUND_M))
                                      for r in rows),
                    "ranked_6cm": sum(near(r, 60.0) for r in rows)})
    return out


def _mm(x) -> str:
    return "-" if x is None else f"{x:.2f}"


def markdown(result: dict) -> str:
    seeds = result["seeds"]
    lines = [f"per_ball on {result['dataset']} ({result['scenes']} scenes), seeds {','.join(map(str, seeds))}", "",
             "| config | seed | balls | found | far rule | false det. | clutter | on negatives | "
             "distractors rejected |",
             "|---|---|---|---|---|---|---|---|---|"]
    for name in ("a", "b"):
        if name not in result:
            continue
        run = result[name]
        label = f"{name.upper()}: {run['method']} {run['overrides'] or ''}".strip()
        for seed in seeds:
            t = run["totals"][seed]
            lines.append(f"| {label} | {seed} | {t['balls']} | {t['found']} | {t['found_far_rule']} | "
                         f"{t['false_detections']} | {t['clutter_detections']} | {t['detections_on_negatives']} | "
                         f"{t['distractors_rejected']}/{t['distractors']} |")
        mean = {k: np.mean([run["totals"][s][k] for s in seeds]) for k in ("found", "found_far_rule",
                                                                            "false_detections", "clutter_detections")}
        lines.append(f"| {label} | mean | | {mean['found']:.2f} | {mean['found_far_rule']:.2f} | "
                     f"{mean['false_detections']:.2f} | {mean['clutter_detections']:.2f} | | |")
    if "differ" in result:
        d = result["differ"]
        lines += ["", f"Balls found by A only: {sum(r['found_by'] == 'A' for r in d)}; "
                      f"by B only: {sum(r['found_by'] == 'B' for r in d)}.", ""]
        if d:
            lines += ["| scene | ball | seed | depth m | found by | A error mm | A score | B error mm | B score |",
                      "|---|---|---|---|---|---|---|---|---|"]
            for r in d:
                lines.append(f"| {r['scene']} | {r['ball']} | {r['seed']} | {r['z_m']:.2f} | {r['found_by']} | "
                             f"{_mm(r['a_error_mm'])} | {_mm(r['a_score'])} | {_mm(r['b_error_mm'])} | "
                             f"{_mm(r['b_score'])} |")
    if "by_noise" in result:
        lines += ["", "By one pixel's depth noise over R (nominal model) at the ball; errors over the balls "
                      "with a detection within R:", "",
                  "| sigma_z / R | balls | found A | found B | median mm A | B | mean mm A | B | p90 mm A | B |",
                  "|---|---|---|---|---|---|---|---|---|---|"]
        b_bins = {r["bin"]: r for r in result["by_noise"].get("b", [])}
        for r in result["by_noise"]["a"]:
            s = b_bins.get(r["bin"], {})
            lines.append(support.row(r["bin"], r["balls"], r["found"], s.get("found"), _mm(r["median_mm"]),
                                     _mm(s.get("median_mm")), _mm(r["mean_mm"]), _mm(s.get("mean_mm")),
                                     _mm(r["p90_mm"]), _mm(s.get("p90_mm"))))
    if "by_range" in result:
        lines += ["", f"By surface distance, balls over seeds {','.join(map(str, seeds))}: found at the operating "
                      "point (the far rule), and a ranked detection (down to the floor) within 2 cm (3 cm beyond "
                      "3 m) and within 6 cm:", "",
                  "| config | band m | balls | found | ranked within 2 cm | ranked within 6 cm |",
                  "|---|---|---|---|---|---|"]
        for name, rows in result["by_range"].items():
            for r in rows:
                lines.append(support.row(name.upper(), r["band"], r["balls"], r["found_far_rule"], r["ranked_2cm"],
                                         r["ranked_6cm"]))
    if result.get("list"):
        lines += ["", "| config | scene | ball | seed | family | depth m | sigma_z/R | found | error mm | score |",
                  "|---|---|---|---|---|---|---|---|---|---|"]
        for name in ("a", "b"):
            for r in result.get(name, {}).get("balls", []):
                lines.append(support.row(name.upper(), r["scene"], r["ball"], r["seed"], r["family"], f"{r['z_m']:.2f}",
                                         f"{r['noise_r']:.2f}", r["found"], _mm(r["error_mm"]), _mm(r["score"])))
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    p = support.parser(__doc__)
    p.add_argument("--seeds", default="0", help="run seeds, e.g. 0-3 or 0,2 (default 0)")
    support.add_ab_arguments(p)
    p.add_argument("--by-noise", nargs="?", const=NOISE_EDGES, default=None, type=support.parse_edges,
                   metavar="EDGES", help=f"add the table by sigma_z / R (bin edges; default {NOISE_EDGES})")
    p.add_argument("--list", action="store_true", help="print every ball's row")
    p.add_argument("--by-range", action="store_true",
                   help="add the table by surface distance: found, and a ranked detection within 2 / 6 cm")
    support.add_noise_argument(p)
    support.add_holes_argument(p)
    p.add_argument("--workers", type=options.workers, default=2, help="worker processes (1: this process)")
    support.add_json_argument(p)
    args = p.parse_args(argv)
    seeds = options.parse_seeds(args.seeds)
    scenes = support.frame_scenes(args.dataset, args.limit, args.family, args.holes)
    configs = {"a": (args.method, support.settings(args.a, "per_ball"))}
    if args.b or args.method_b:
        configs["b"] = (args.method_b or args.method, support.settings(args.b, "per_ball"))
    for method, overrides in configs.values():
        support.detector_config(args.dataset, overrides, method)  # a bad --set fails before any work
    result = {"dataset": str(args.dataset), "scenes": len(scenes), "seeds": seeds, "list": args.list}
    with executor(args.workers) as ex:
        for name, (method, overrides) in configs.items():
            run = run_config(ex, args.dataset, scenes, seeds, method, overrides, args.frame_noise)
            run["totals"] = totals(run, seeds)
            result[name] = run
    if "b" in result:
        result["differ"] = differing(result["a"], result["b"])
    if args.by_noise:
        result["by_noise"] = {name: by_noise(result[name], args.by_noise) for name in configs}
    if args.by_range:
        result["by_range"] = {name: by_range(result[name], seeds) for name in configs}
    print(markdown(result))
    support.write_json(args.json, result)
    return 0


if __name__ == "__main__":
    sys.exit(main())
