"""Retired: it reads the hand-set verdict (its factors and raw score), which the fitted verdict replaced
(issue 45); it runs at commit 7347584 (`git worktree add ../sb-7347584 7347584`).

How far a monotone map of the detector's score goes toward a probability: the expected calibration
error (ECE) of the raw score and of an isotonic map fitted on the training splits, per dataset.

``collect`` runs the detector on every scene of a dataset at the given run seeds, as the benchmark
does (scene k of run seed s detected with ``detection_seed(s, k)``), and writes one JSON line per
detection: the dataset, scene, seed, rank, the detection's depth, its score, the FEATURES measured
on its frame and its inliers, and whether it is correct (``eval.metrics.calibration.detection_correct``:
within 2 cm of a true ball, 3 cm beyond 3 m deep, one per ball). ``predictions`` writes the same
lines from a benchmark run's prediction sets (``results/predictions/<preset>/improved.json``), so
that the benchmark presets are read as `make eval` scored them, not run again.

``fit`` fits the isotonic regression of correct on score (``scipy.optimize.isotonic_regression``) on
collected lines, the scenes of even index only with ``--half even`` (the odd ones held apart), and
writes the map as knots (score, probability; ``numpy.interp`` between them); ``--platt``, a logistic
map of the score's logit instead (two parameters, strictly increasing: every ranking kept);
``--logistic``, a logistic map of the logit and of what the detector measures on the frame and the
detection (FEATURES: collected beside each line). ``report`` prints, per
set of lines, the detections, the share correct, the ECE and MCE of the raw score and of the map
(``--half odd``: the held-apart scenes only), and the ECE a perfectly calibrated detector with the
map's probabilities would show on that many detections (``eval.metrics.calibration.ece_floor``: the
sampling noise), with each detection a trial and with a scene's detection of one rank at every run
seed one trial (``trial_groups``: pooled seeds see the same scenes again).

    python docs/experiments/scripts/score_calibration.py collect data/train out/cal_train.jsonl --seeds 0-3
    python docs/experiments/scripts/score_calibration.py collect data/train-stereo out/cal_ts.jsonl --seeds 0-3
    python docs/experiments/scripts/score_calibration.py predictions data results out/cal_bench.jsonl
    python docs/experiments/scripts/score_calibration.py fit out/cal_train.jsonl out/cal_ts.jsonl \\
        --half even --out out/cal_map.json
    python docs/experiments/scripts/score_calibration.py report out/cal_map.json \\
        train=out/cal_train.jsonl train-stereo=out/cal_ts.jsonl --half odd
    python docs/experiments/scripts/score_calibration.py report out/cal_map.json bench=out/cal_bench.jsonl
"""

from __future__ import annotations

import argparse
import functools
import json
import math
import sys
from pathlib import Path

import numpy as np
from scipy.optimize import isotonic_regression, minimize

import script_support as support
from spherebench import options
from spherebench.datasets import inout
from spherebench.datasets.outputs import atomic_write_bytes
from spherebench.eval.bench.cache import read_predictions
from spherebench.eval.bench.calibration import scene_truths
from spherebench.eval.bench.seeds import detection_seed
from spherebench.eval.metrics.calibration import (detection_correct, ece_floor, expected_calibration_error,
                                                  maximum_calibration_error)
from spherebench.eval.metrics.metrics3d import FAR_RULE_FROM_M, FOUND_FAR_M, FOUND_M
from spherebench.method.detector import detect, prepare_frame
from spherebench.method.improved import mean_variance_inflation, noise_a
from spherebench.parallel import executor


#: What ``--logistic`` maps besides the score's logit (``--features`` picks some): the frame's measured
#: noise over the nominal model's (log), its correlation length (px), one pixel's noise at the
#: detection over R, the detection's inliers (log), its visible share, its inliers' residual RMS over
#: R (log), its centre's lateral standard error over the 2 cm (3 cm) limit (log; ``lateral_se_m``),
#: its depth (log).
FEATURES = ("log_noise_ratio", "corr_px", "noise_r", "log_inliers", "visible", "log_residual_r",
            "log_lateral_se", "log_depth")


def frame_features(scene_path: Path, config) -> dict:
    """What the detector measures on a scene's frame (``PreparedFrame``): its noise A over the model's
    and its noise correlation length (px)."""
    return _frame_features(prepare_frame(inout.load_cloud(scene_path), config), config)


def _frame_features(frame, config) -> dict:
    model = noise_a(config, float(frame.cloud.intrinsics.fx))
    return {"noise_a": float(frame.noise_a), "log_noise_ratio": float(np.log(frame.noise_a / model)),
            "corr_px": float(frame.noise_corr_px)}


def lateral_se_m(points_m: np.ndarray, centre_m: np.ndarray, radius_m: float, corr_px: float) -> float:
    """The standard error (m) of a sphere's centre across the line of sight, from its inliers (N, 3) m:
    Gauss-Newton's covariance of the depth residual along each pixel's ray at the fitted centre, the
    residual variance inflated for the frame's noise correlation (``mean_variance_inflation``);
    the ray's chord is floored at 0.2 R so that limb pixels do not dominate. NaN below 6 inliers."""
    if len(points_m) < 6:
        return float("nan")
    u = points_m / np.linalg.norm(points_m, axis=1, keepdims=True)
    uc = u @ centre_m
    chord = np.sqrt(np.maximum(uc * uc - centre_m @ centre_m + radius_m ** 2, (0.2 * radius_m) ** 2))
    e = uc - chord - np.linalg.norm(points_m, axis=1)  # (N,) the front intersection's range minus the pixel's
    jac = u - (u * uc[:, None] - centre_m[None, :]) / chord[:, None]  # (N, 3) d(range)/d(centre)
    var = float(e @ e) / (len(e) - 3) * mean_variance_inflation(corr_px)
    try:
        cov = np.linalg.inv(jac.T @ jac) * var
    except np.linalg.LinAlgError:
        return float("nan")
    d = centre_m / np.linalg.norm(centre_m)
    across = np.eye(3) - np.outer(d, d)
    return float(np.sqrt(max(np.trace(across @ cov @ across), 0.0)))


def _detection_features(cloud, sphere, frame: dict, radius_m: float) -> dict:
    z = float(sphere.centre_m[2])
    pts = cloud.points[sphere.inlier_indices].astype(np.float64)
    limit = FOUND_FAR_M if z > FAR_RULE_FROM_M else FOUND_M
    lat = lateral_se_m(pts, np.asarray(sphere.centre_m, np.float64), radius_m, frame["corr_px"])
    return dict(log_noise_ratio=frame["log_noise_ratio"], corr_px=frame["corr_px"],
                noise_r=frame["noise_a"] * z * z / radius_m, log_inliers=float(np.log1p(len(sphere.inlier_indices))),
                visible=float(sphere.evidence.get("visible_fraction", 1.0)),
                log_residual_r=float(np.log(max(sphere.rmse_m, 1e-4) / radius_m)),
                log_lateral_se=float(np.log(max(lat, 1e-5) / limit)) if math.isfinite(lat) else 0.0,
                log_depth=float(np.log(max(z, 0.1))))


def _line(dataset: str, index: int, scene_id: str, seed: int, rank: int, z_m: float, score: float,
          correct: bool) -> dict:
    """One detection's line: rank, its order among its scene's detections at that seed (a scene's
    ball at several seeds is one trial of the ECE floor, ``trial_groups``)."""
    return {"dataset": dataset, "scene": scene_id, "index": index, "seed": seed, "rank": rank, "z_m": z_m,
            "score": score, "correct": bool(correct)}


def scene_lines(job: tuple, overrides: dict) -> list[dict]:
    """One scene's lines at every run seed (in a worker): job (dataset, scene dir, scene id, index,
    seeds, gt). Scene k of run seed s is detected with ``detection_seed(s, k)``, as the benchmark does."""
    dataset, scene_dir, scene_id, index, seeds, gt = job
    config = support.detector_config(dataset, overrides)
    cloud = inout.load_cloud(Path(scene_dir))
    frame = _frame_features(prepare_frame(cloud, config), config)
    out = []
    for seed in seeds:
        spheres = detect(cloud, config, seed=detection_seed(seed, index))
        if not spheres:
            continue
        correct = detection_correct([s.centre_m for s in spheres], [s.score for s in spheres], gt)
        for rank, (s, ok) in enumerate(zip(spheres, correct)):
            line = _line(Path(dataset).name, index, scene_id, seed, rank, float(s.centre_m[2]), float(s.score), ok)
            line.update(_detection_features(cloud, s, frame, config.radius_m))
            out.append(line)
    return out


def collect(dataset: str, out: Path, seeds: list[int], overrides: dict, workers: int) -> int:
    truths = scene_truths(dataset)
    jobs = [(str(dataset), str(s.path), s.scene_id, s.index, seeds, truths[s.scene_id])
            for s in support.frame_scenes(dataset) if s.scene_id in truths]
    with executor(workers) as ex:
        lines = [x for part in ex.map(functools.partial(scene_lines, overrides=overrides), jobs) for x in part]
    _write_lines(out, lines)
    return len(lines)


def from_predictions(data: Path, results: Path, out: Path, method: str = "improved") -> int:
    """The lines of a benchmark run's prediction sets (score and correct only: the records hold no
    inliers, so ``--logistic`` cannot be reported on them)."""
    lines = []
    for pred in sorted((results / "predictions").glob(f"*/{method}.json")):
        preset = pred.parent.name
        if not (data / preset / "coco_gt.json").is_file():
            continue
        meta = read_predictions(pred)[1]
        truths = scene_truths(data / preset)
        index_of = {sid: k for k, sid in enumerate(sorted(truths))}
        for r in meta["scenes"]:
            gt = truths.get(r["scene_id"])
            if gt is None or not r["detections"]:
                continue
            dets = r["detections"]
            correct = detection_correct([d["center_m"] for d in dets], [d["score"] for d in dets], gt)
            lines += [_line(preset, index_of[r["scene_id"]], r["scene_id"], int(meta.get("seed", 0)), k,
                            float(d["center_m"][2]), float(d["score"]), ok)
                      for k, (d, ok) in enumerate(zip(dets, correct))]
    _write_lines(out, lines)
    return len(lines)


def _write_lines(out: Path, lines: list[dict]) -> None:
    atomic_write_bytes(out, "".join(json.dumps(x) + "\n" for x in lines).encode())


def read_lines(paths, half: str | None = None) -> list[dict]:
    lines = [json.loads(t) for p in paths for t in Path(p).read_text().splitlines() if t]
    if half is not None:
        lines = [x for x in lines if x["index"] % 2 == (0 if half == "even" else 1)]
    return lines


def fit_isotonic(scores: np.ndarray, correct: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The isotonic (non-decreasing) regression of correct on score as knots: (scores (K,),
    probabilities (K,)), one knot per distinct score's block mean."""
    order = np.argsort(scores, kind="stable")
    fitted = isotonic_regression(correct[order].astype(np.float64)).x
    return scores[order], fitted


def _logit(s: np.ndarray) -> np.ndarray:
    s = np.clip(s, 1e-6, 1.0 - 1e-6)
    return np.log(s / (1.0 - s))


def fit_platt(scores: np.ndarray, correct: np.ndarray) -> tuple[float, float]:
    """(a, b) of p = 1 / (1 + exp(-(a logit(score) + b))), by maximum likelihood
    (``scipy.optimize.minimize``): strictly increasing where a > 0, so it keeps every ranking."""
    x, y = _logit(scores), correct.astype(np.float64)

    def loss(ab):
        t = ab[0] * x + ab[1]
        return float(np.sum(np.logaddexp(0.0, t) - y * t))

    a, b = minimize(loss, np.array([1.0, 0.0]), method="BFGS").x
    return float(a), float(b)


def design(lines: list[dict], scores: np.ndarray, features=FEATURES) -> np.ndarray:
    """(N, 2 + len(features)): the score's logit, 1, then the lines' features (of FEATURES)."""
    cols = [_logit(scores), np.ones(len(scores))] + [np.asarray([x[f] for x in lines], np.float64) for f in features]
    return np.stack(cols, axis=1)


def fit_logistic(x: np.ndarray, correct: np.ndarray) -> np.ndarray:
    """Weights w of p = 1 / (1 + exp(-x w)) by maximum likelihood (a tiny ridge keeps it finite
    where the classes separate)."""
    y = correct.astype(np.float64)

    def loss(w):
        t = x @ w
        return float(np.sum(np.logaddexp(0.0, t) - y * t) + 1e-3 * np.sum(w[2:] ** 2))

    w0 = np.zeros(x.shape[1])
    w0[0] = 1.0
    return minimize(loss, w0, method="BFGS").x


def apply_map(knots: dict, scores: np.ndarray, lines: list[dict] | None = None) -> np.ndarray:
    """The map's probabilities of scores: the logistic's (``weights``, with the lines' features),
    Platt's (``platt`` (a, b)), else the knots' (isotonic)."""
    if "weights" in knots:
        return 1.0 / (1.0 + np.exp(-(design(lines, scores, knots["features"]) @ np.asarray(knots["weights"]))))
    if "platt" in knots:
        a, b = knots["platt"]
        return 1.0 / (1.0 + np.exp(-(a * _logit(scores) + b)))
    return np.interp(scores, np.asarray(knots["score"]), np.asarray(knots["probability"]))


def trial_groups(lines: list[dict]) -> list[str]:
    """One label per line: its dataset, scene and rank, the same at every run seed (one trial of the
    ECE floor, ``eval.metrics.calibration.ece_floor``'s groups)."""
    return [f'{x["dataset"]}/{x["scene"]}/{x.get("rank", 0)}' for x in lines]


def report_rows(knots: dict, named: dict[str, list[dict]]) -> list[list]:
    rows = []
    for name, lines in named.items():
        for dataset in sorted({x["dataset"] for x in lines}) if name == "bench" else [None]:
            sel = [x for x in lines if dataset is None or x["dataset"] == dataset]
            s = np.asarray([x["score"] for x in sel])
            c = np.asarray([x["correct"] for x in sel], bool)
            p = apply_map(knots, s, sel)
            rows.append([dataset or name, len(sel), f"{c.mean():.3f}" if sel else "-",
                         f"{expected_calibration_error(s, c):.3f}", f"{maximum_calibration_error(s, c):.3f}",
                         f"{expected_calibration_error(p, c):.3f}", f"{maximum_calibration_error(p, c):.3f}",
                         f"{ece_floor(p):.3f}",
                         f"{ece_floor(p, groups=trial_groups(sel)):.3f}" if sel else "nan"])
    return rows


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    c = sub.add_parser("collect", help="detect on a dataset, one line per detection")
    c.add_argument("dataset")
    c.add_argument("out", type=Path)
    c.add_argument("--seeds", default="0")
    c.add_argument("--set", dest="a", action="append", default=[], metavar="PATH=VALUE")
    c.add_argument("--workers", type=options.workers, default=2)
    pr = sub.add_parser("predictions", help="the lines of a benchmark run's prediction sets")
    pr.add_argument("data", type=Path)
    pr.add_argument("results", type=Path)
    pr.add_argument("out", type=Path)
    f = sub.add_parser("fit", help="fit the isotonic map on collected lines")
    f.add_argument("lines", nargs="+")
    f.add_argument("--half", choices=("even", "odd"), default=None)
    f.add_argument("--out", type=Path, required=True)
    f.add_argument("--platt", action="store_true", help="a logistic map of the score's logit (keeps rankings)")
    f.add_argument("--logistic", action="store_true", help="a logistic map of the logit and the FEATURES")
    f.add_argument("--features", default=",".join(FEATURES),
                   help=f"--logistic's features, comma-separated (of {', '.join(FEATURES)})")
    r = sub.add_parser("report", help="ECE and MCE of the raw score and of the map")
    r.add_argument("map", type=Path)
    r.add_argument("named", nargs="+", metavar="NAME=LINES")
    r.add_argument("--half", choices=("even", "odd"), default=None)
    args = p.parse_args(argv)
    if args.cmd == "collect":
        overrides = support.settings(args.a, "score_calibration")
        n = collect(args.dataset, args.out, options.parse_seeds(args.seeds), overrides, args.workers)
        print(f"{n} detections -> {args.out}")
    elif args.cmd == "predictions":
        print(f"{from_predictions(args.data, args.results, args.out)} detections -> {args.out}")
    elif args.cmd == "fit":
        lines = read_lines(args.lines, args.half)
        s = np.asarray([x["score"] for x in lines])
        c = np.asarray([x["correct"] for x in lines], bool)
        fitted = {"fitted_on": [str(x) for x in args.lines], "half": args.half, "detections": len(lines)}
        if args.logistic:
            features = [x for x in args.features.split(",") if x]
            unknown = sorted(set(features) - set(FEATURES))
            if unknown:
                p.error(f"--features: unknown {', '.join(unknown)} (known: {', '.join(FEATURES)})")
            fitted.update(weights=fit_logistic(design(lines, s, features), c).tolist(), features=features)
        elif args.platt:
            fitted["platt"] = list(fit_platt(s, c))
        else:
            knots_s, knots_p = fit_isotonic(s, c)
            fitted.update(score=knots_s.tolist(), probability=knots_p.tolist())
        inout.write_json(args.out, fitted)
        kind = "logistic" if args.logistic else ("Platt" if args.platt else "isotonic")
        print(f"{kind} map of {len(lines)} detections -> {args.out}")
    else:
        knots = json.loads(args.map.read_text())
        named = {}
        for item in args.named:
            name, _, path = item.partition("=")
            named[name] = read_lines([path], args.half)
        print("| set | detections | correct | ECE raw | MCE raw | ECE mapped | MCE mapped | ECE floor | "
              "ECE floor, seeds as one trial |")
        print("|---|---|---|---|---|---|---|---|---|")
        for row in report_rows(knots, named):
            print(support.row(*row))
    return 0


if __name__ == "__main__":
    sys.exit(main())
