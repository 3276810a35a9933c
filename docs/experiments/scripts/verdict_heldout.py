"""Two verdicts (or two configurations) on the training splits' held-apart scenes.

``make train-verifier`` fits the verdict on the scenes of `train` and `train-stereo` whose index is
not 4 modulo 5 and calibrates it on those that are (``eval.bench.verdict_fit``). This script runs
the improved detector with configuration A and B (``--set``/``--set-b``), each with its verdict model
(``--model-a``/``--model-b``; default: the shipped one), on the held-apart scenes only (or ``--every 1``:
every scene), at each run seed, and prints per set and band of surface distance: the balls, those
found at the operating point (``verification.min_score``: a detection within 2 cm, 3 cm beyond 3 m),
the false detections there, and the average precision of the ranked output (every detection down
to the floor, matched best first, one per ball, over all balls of the set).

    python docs/experiments/scripts/verdict_heldout.py data/train data/train-stereo --seeds 0-3 \\
        --model-b checkpoints/verdict/verdict.onnx
"""

from __future__ import annotations

import functools
import math
from pathlib import Path

import numpy as np

import script_support as support
from spherebench import options
from spherebench.datasets import inout
from spherebench.eval.bench.seeds import detection_seed
from spherebench.eval.metrics.calibration import detection_correct
from spherebench.eval.metrics.metrics3d import DISTANCE_BANDS_M, band_name, found_limit_m
from spherebench.method import verdict as verdict_stage
from spherebench.method.detector import detect
from spherebench.parallel import executor


def scene_outcome(job: tuple, overrides: dict, model: str | None) -> dict:
    """One scene at one seed (in a worker): its balls' bands and found flags, its detections' scores and
    correctness, the false detections at the operating point; model: the verdict's ONNX file (None: the
    shipped one)."""
    dataset, scene_dir, index, seed = job
    verdict_stage.load_verdict = functools.partial(_load, model or str(verdict_stage.MODEL_PATH))
    config = support.detector_config(dataset, overrides)
    gt = inout.read_scene_gt(Path(scene_dir))
    spheres = detect(inout.load_cloud(Path(scene_dir)), config, seed=detection_seed(seed, index), min_score=0.0,
                     max_spheres=100)
    balls = [b for b in gt.get("balls", []) if b.get("center_m") is not None]
    centres = np.asarray([b["center_m"] for b in balls], np.float64).reshape(-1, 3)
    scores = [s.score for s in spheres]
    correct = detection_correct([s.centre_m for s in spheres], scores, gt) if spheres else np.zeros(0, bool)
    at = [s for s in spheres if s.score >= config.verification.min_score]
    found = []
    for c in centres:
        found.append(any(np.linalg.norm(s.centre_m - c) <= found_limit_m(c[2]) for s in at))
    surface = np.linalg.norm(centres, axis=1) - config.radius_m
    false_at = sum(1 for s, ok in zip(spheres, correct) if s.score >= config.verification.min_score and not ok)
    return {"dataset": Path(dataset).name, "bands": [_band(float(d)) for d in surface], "found": found,
            "scores": scores, "correct": correct.tolist(), "false": false_at, "balls": len(balls)}


_LOAD = verdict_stage.load_verdict


def _load(path: str):
    return _LOAD(path)


def _band(distance_m: float) -> str:
    return next(band_name(b) for b in DISTANCE_BANDS_M if b[0] <= distance_m < b[1])


def average_precision(scores: list[float], correct: list[bool], n_balls: int) -> float:
    """The area under the ranked output's precision-recall curve (every detection a point)."""
    if n_balls == 0:
        return math.nan
    order = np.argsort(-np.asarray(scores, np.float64), kind="stable")
    hit = np.asarray(correct, bool)[order]
    tp = np.cumsum(hit)
    precision = tp / np.arange(1, len(hit) + 1)
    return float(np.sum(precision[hit]) / n_balls)


def main() -> int:
    p = support.parser(__doc__)
    p.add_argument("more", nargs="*", help="more datasets")
    p.add_argument("--seeds", default="0", help="run seeds, e.g. 0-3")
    p.add_argument("--every", type=int, default=5, help="scenes whose index is 4 mod EVERY (1: all)")
    p.add_argument("--workers", type=options.workers, default=2)
    support.add_ab_arguments(p)
    p.add_argument("--model-a", help="A's verdict model (ONNX; default: the shipped one)")
    p.add_argument("--model-b", help="B's verdict model (ONNX; default: the shipped one)")
    args = p.parse_args()
    seeds = options.parse_seeds(args.seeds)
    configs = {"A": (support.settings(args.a, "verdict_heldout"), args.model_a),
               "B": (support.settings(args.b, "verdict_heldout"), args.model_b)}
    print(f"A: {configs['A']}  B: {configs['B']}  seeds {args.seeds}, scenes 4 mod {args.every}\n")
    print("| config | set | band m | balls | found | ranked AP | false at op. point |")
    print("|---|---|---|---|---|---|---|")
    for data in [args.dataset] + args.more:
        scenes = inout.list_scenes(data)[:args.limit]
        jobs = [(str(data), str(s), k, seed) for seed in seeds for k, s in enumerate(scenes)
                if args.every == 1 or k % args.every == 4]
        for name, (overrides, model) in configs.items():
            with executor(args.workers) as ex:
                out = list(ex.map(functools.partial(scene_outcome, overrides=overrides, model=model), jobs))
            bands = [b for o in out for b in o["bands"]]
            found = [f for o in out for f in o["found"]]
            scores = [s for o in out for s in o["scores"]]
            correct = [c for o in out for c in o["correct"]]
            n_balls = sum(o["balls"] for o in out)
            print(f"| {name} | {Path(data).name} | all | {n_balls} | {sum(found)} | "
                  f"{average_precision(scores, correct, n_balls):.3f} | {sum(o['false'] for o in out)} |")
            for band in map(band_name, DISTANCE_BANDS_M):
                sel = [f for f, b in zip(found, bands) if b == band]
                print(f"| {name} | {Path(data).name} | {band} | {len(sel)} | {sum(sel)} | | |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
