"""The scores' calibration on the benchmark's datasets: each 3D method's detections labelled correct
or not and binned by score (``eval.metrics.calibration``), as a DataFrame of reliability bins with
the ECE per (preset, method), and its table.

Read from a dataset folder and a prediction set as ``eval.bench.cache`` writes it (the meta file's
per-scene records hold every detection's center_m and score): ``read_calibration`` from a results
folder's predictions/<preset>/, ``sets_calibration`` from the scored sets of a report. Only the
scenes whose balls all have a known centre are labelled (the annotated ones); a negative scene's
detections are all incorrect. A recorded dataset's centres are references (fits to its points), and
its table says so.

    python -m spherebench.eval.bench.calibration --data data --results results

prints the table of the prediction sets already there.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Sequence

import numpy as np
import pandas as pd

from spherebench.datasets import inout
from spherebench.datasets.presets import benchmark_presets
from spherebench.eval.bench.cache import meta_path, read_predictions
from spherebench.eval.bench.registry import ROLE_CEILING, methods_with_role
from spherebench.eval.bench.scoring import ScoredSet, not_run
from spherebench.eval.bench.tables import Table, fmt
from spherebench.eval.bench.tasks import dataset_scenes
from spherebench.eval.metrics.calibration import (N_BINS, detection_correct, ece_floor, expected_calibration_error,
                                                  maximum_calibration_error, reliability)

#: The frame's columns: one row per (preset, method, bin); the last four repeat per (preset, method).
COLUMNS = ["preset", "method", "bin", "bin_low", "bin_high", "count", "mean_score", "fraction_correct",
           "detections", "correct", "ece", "mce", "ece_floor"]


def scene_truths(data_dir: str | Path) -> dict[str, dict]:
    """{scene id: its gt.json} of the scenes of ``data_dir`` that can be labelled: annotated, every
    ball with a known centre."""
    truths = {s.scene_id: inout.read_scene_gt(s.path) for s in dataset_scenes(data_dir)}
    return {k: gt for k, gt in truths.items()
            if gt.get("annotated", True) and all(b.get("center_m") is not None for b in gt["balls"])}


def labelled_detections(truths: dict[str, dict], records: Sequence[dict]) -> tuple[np.ndarray, np.ndarray]:
    """(scores (D,), correct (D,) bool) of a prediction set's per-scene records (its meta file's
    "scenes"): every detection of the scenes in ``truths`` (``scene_truths``), in record order."""
    scores, correct = [np.zeros(0)], [np.zeros(0, bool)]
    for r in records:
        gt = truths.get(r["scene_id"])
        if gt is None:
            continue
        s = np.asarray([d["score"] for d in r["detections"]], np.float64)
        scores.append(s)
        correct.append(detection_correct([d["center_m"] for d in r["detections"]], s, gt))
    return np.concatenate(scores), np.concatenate(correct)


def calibration_frame(labelled: dict[tuple[str, str], tuple[np.ndarray, np.ndarray]],
                      n_bins: int = N_BINS) -> pd.DataFrame:
    """The reliability bins and ECE, MCE of each {(preset, method): (scores, correct)}, in its order
    (COLUMNS; a bin without detections has count 0 and NaN means; no detections at all: NaN ECE)."""
    rows = []
    for (preset, method), (scores, correct) in labelled.items():
        r = reliability(scores, correct, n_bins)
        ece = expected_calibration_error(scores, correct, n_bins)
        mce = maximum_calibration_error(scores, correct, n_bins)
        floor = ece_floor(scores, n_bins)
        for b in range(n_bins):
            rows.append([preset, method, b, r.edges[b], r.edges[b + 1], int(r.count[b]), r.mean_score[b],
                         r.fraction_correct[b], r.n, int(np.count_nonzero(correct)), ece, mce, floor])
    return pd.DataFrame(rows, columns=COLUMNS)


def _in_unit_interval(scores: np.ndarray) -> bool:
    return bool(np.all((scores >= 0.0) & (scores <= 1.0)))


def _frame(labelled: dict, n_bins: int) -> pd.DataFrame:
    """calibration_frame of the sets whose scores can be probabilities; the others are named in the
    frame's attrs["not_probabilities"]."""
    outside = [f"{m} on `{p}`" for (p, m), (s, _) in labelled.items() if not _in_unit_interval(s)]
    frame = calibration_frame({k: v for k, v in labelled.items() if _in_unit_interval(v[0])}, n_bins)
    frame.attrs["not_probabilities"] = outside
    return frame


def sets_calibration(per_dataset: dict[str, tuple[Path, Sequence[ScoredSet]]], n_bins: int = N_BINS,
                     references: Sequence[str] = ()) -> pd.DataFrame:
    """calibration_frame of the 3D methods' sets (one per detection run: the exact-rule one) that ran,
    {label: (dataset folder, its scored sets)}, those with labelled scenes; sets whose scores leave [0, 1] are named in
    attrs["not_probabilities"] instead. references: the labels whose true centres are reference fits
    (recorded data), named in attrs["references"]."""
    labelled = {}
    ceilings = {m.name for m in methods_with_role(ROLE_CEILING)}  # an oracle's score is no probability
    for label, (data_dir, sets) in per_dataset.items():
        mine = [s for s in sets if s.kind == "3d" and s.rule != "paper" and not not_run(s) and s.method not in ceilings]
        truths = scene_truths(data_dir) if mine else {}
        if not truths:  # nothing to label against (an unannotated recording)
            continue
        labelled.update({(label, s.method): labelled_detections(truths, s.scenes) for s in mine})
    frame = _frame(labelled, n_bins)
    frame.attrs["references"] = [label for label in references if label in per_dataset]
    return frame


def read_calibration(data: str | Path, results: str | Path, presets: Sequence[str] | None = None,
                     n_bins: int = N_BINS) -> pd.DataFrame:
    """calibration_frame from files: each preset's dataset data/<preset> and the 3D methods' sets in
    results/predictions/<preset>/ (presets: the benchmark's, those present)."""
    data, pred = Path(data), Path(results) / "predictions"
    labelled = {}
    ceilings = {m.name for m in methods_with_role(ROLE_CEILING)}
    for preset in presets or benchmark_presets():
        if not (data / preset / "coco_gt.json").is_file() or not (pred / preset).is_dir():
            continue
        truths = scene_truths(data / preset)
        for path in sorted((pred / preset).glob("*.json")):
            if path.name.endswith(".meta.json") or not meta_path(path).is_file():
                continue
            meta = read_predictions(path)[1]
            if meta["kind"] == "3d" and meta.get("rule") != "paper" and meta["method"] not in ceilings:
                labelled[(preset, meta["method"])] = labelled_detections(truths, meta["scenes"])
    return _frame(labelled, n_bins)


def calibration_table(frame: pd.DataFrame) -> Table | None:
    """The table `calibration`: one row per (preset, method), its ECE, MCE and each bin's mean score /
    fraction correct (detections); None for an empty frame."""
    if frame.empty:
        return None
    edges = frame.groupby("bin", sort=True)[["bin_low", "bin_high"]].first()
    rows = []
    for (preset, method), g in frame.groupby(["preset", "method"], sort=False):
        bins = g.sort_values("bin").to_dict("records")
        first = bins[0]
        rows.append([preset, method, int(first["detections"]), int(first["correct"]), fmt(first["ece"]),
                     fmt(first["ece_floor"]), fmt(first["mce"])] + [f"{fmt(b['mean_score'], 2)} / {fmt(b['fraction_correct'], 2)} ({b['count']})"
                                           if b["count"] else "–" for b in bins])
    notes = ["A detection is correct when its centre lies within 2 cm of a true ball's centre (3 cm for a ball "
             "deeper than 3 m), at most one per ball (the best-scored; the others are duplicates); a detection of "
             "a distractor ball or of anything else is not (`eval/metrics/calibration.py`).",
             "Bins of equal width over the score; each cell: mean score / fraction correct (detections); '–': "
             "none. ECE = sum over bins of n_b / N |fraction correct - mean score|, MCE = the largest gap; a "
             "calibrated score has both near 0 (figure `figures/reliability.png`).",
             "ECE floor: the median ECE of a perfectly calibrated detector with the same scores on as many "
             "detections (each correct with its score's probability, 400 seeded draws): an ECE near it is "
             "within what the set's size can tell."]
    if frame.attrs.get("references"):
        notes.append("On " + ", ".join(f"`{r}`" for r in frame.attrs["references"]) + " (recorded) a true centre is "
                     "the dataset's reference, a fit to its points, not a measured truth.")
    if frame.attrs.get("not_probabilities"):
        notes.append("Not calibrated (scores outside [0, 1]): " + ", ".join(frame.attrs["not_probabilities"]) + ".")
    return Table(name="calibration", title="Calibration of the 3D methods' scores",
                 columns=["preset", "method", "detections", "correct", "ECE", "ECE floor", "MCE"]
                 + [f"{lo:.1f}-{hi:.1f}" for lo, hi in edges.itertuples(index=False)], rows=rows, notes=notes)


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m spherebench.eval.bench.calibration",
                                 description="The calibration table of the prediction sets of a results folder.")
    ap.add_argument("--data", type=Path, default=Path("data"), help="the folder of the preset datasets")
    ap.add_argument("--results", type=Path, default=Path("results"), help="the results folder (predictions/)")
    ap.add_argument("--presets", nargs="*", help="presets (default: the benchmark's, those present)")
    args = ap.parse_args(argv)
    table = calibration_table(read_calibration(args.data, args.results, args.presets))
    print(table.markdown() if table is not None else "no 3D prediction set with its dataset")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
