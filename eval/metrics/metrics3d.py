"""3D metrics where the ground-truth ball centres are known: pure functions on arrays.

Units: metres throughout; camera frame (x right, y down, z forward).

Two rules relate detections to balls; each report says which it uses.

**Matched** (``match_scene``; `evaluate` / `make eval`'s 3D table, its "matched <= 1 / 2 / 5 cm"
rates and its false detections): predictions are taken in decreasing score order; each takes the
nearest still-unmatched ground-truth ball whose centre lies within ``gate_m`` of its own
(``MATCH_GATE_M``, 0.12 m, one ball radius: the predicted centre is inside the true ball). A prediction
left unmatched is a false detection; a ball left unmatched is missed. This is COCO's greedy
matching with centre distance in place of IoU.

Summary (``summarize_3d``), over all scenes:
- detection rate within d (d = 1, 2, 5 cm): balls whose matched prediction is within d of the
  true centre, over all balls (missed balls count as failures);
- centre error statistics (median, RMSE, 95th percentile, mean, max) over the matched balls;
- radius error (predicted - true) statistics over the matched balls that have both radii;
- false detections: unmatched predictions in all scenes, and on negative scenes (scenes with
  no ball) the number of predictions and the fraction of negatives with at least one.
``error_vs_distance`` gives the (distance to camera, centre error) pairs for a figure.

**Nearest within 2 cm** (``scene_counts``, ``detection_counts``; `bench`, `sweep` and
`robustness`): no one-to-one matching; a ball is found when its nearest detection lies within
``FOUND_M`` (2 cm) of its centre; a detection farther than ``FOUND_M`` from every ball counts in
"false", one farther than ``MATCH_GATE_M`` from every ball in "clutter" (what the matched rule
calls a false detection; `robustness` reports this one). The two can differ on a ball with
several detections about it (matched: the best-scored one within the gate; nearest: the nearest).
Beside it, **the far rule**: within ``FOUND_M``, or within ``FOUND_FAR_M`` (3 cm) for
a ball whose centre lies deeper than ``FAR_RULE_FROM_M`` (3 m), where one pixel's depth noise is
10 cm or more (``detection_counts``' found_far_rule).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from spherebench.errors import SphereBenchError

#: Thresholds (metres) of the detection rates.
RATE_THRESHOLDS_M = (0.01, 0.02, 0.05)
#: The matching gate of ``match_scene``, metres (one basketball radius).
MATCH_GATE_M = 0.12


def _points(a, name: str) -> np.ndarray:
    arr = np.asarray(a, dtype=np.float64)
    if arr.size == 0:
        return arr.reshape(0, 3)
    if arr.ndim == 1 and arr.shape[0] == 3:
        arr = arr[None]
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise SphereBenchError(f"{name} must have shape (N, 3) metres, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise SphereBenchError(f"{name} hold NaN or infinite values")
    return arr


def _vector(a, n: int, name: str) -> np.ndarray:
    arr = np.asarray(a, dtype=np.float64).reshape(-1)
    if arr.shape[0] != n:
        raise SphereBenchError(f"{name} has {arr.shape[0]} entries, expected {n}")
    return arr


@dataclass(frozen=True)
class SceneMatch:
    """Matching of one scene's predictions to its ground-truth balls.

    gt_to_pred: (G,) int, index of the matched prediction or -1 (missed).
    pred_to_gt: (P,) int, index of the matched ball or -1 (false detection).
    centre_error_m: (G,) distance matched prediction - true centre; NaN where missed.
    radius_error_m: (G,) predicted - true radius; NaN where missed or a radius is unknown.
    gt_distance_m: (G,) distance of each true centre from the camera origin.
    """

    gt_to_pred: np.ndarray
    pred_to_gt: np.ndarray
    centre_error_m: np.ndarray
    radius_error_m: np.ndarray
    gt_distance_m: np.ndarray

    @property
    def n_gt(self) -> int:
        return int(self.gt_to_pred.shape[0])

    @property
    def n_pred(self) -> int:
        return int(self.pred_to_gt.shape[0])

    @property
    def n_false(self) -> int:
        return int(np.count_nonzero(self.pred_to_gt < 0))


def match_scene(pred_centres_m, pred_scores, gt_centres_m, gate_m: float = MATCH_GATE_M,
                pred_radii_m=None, gt_radii_m=None) -> SceneMatch:
    """Greedy matching by score of predicted centres (P, 3) to true centres (G, 3), metres.

    pred_scores: (P,) higher = more confident (ties keep the input order).
    gate_m: largest centre distance of a match, metres.
    pred_radii_m (P,), gt_radii_m (G,): optional, for the radius error.
    """
    pred = _points(pred_centres_m, "predicted centres")
    gt = _points(gt_centres_m, "ground-truth centres")
    scores = _vector(pred_scores, len(pred), "pred_scores")
    if not gate_m > 0:
        raise SphereBenchError(f"gate_m={gate_m} must be > 0 metres")
    dist = np.linalg.norm(pred[:, None, :] - gt[None, :, :], axis=2)  # (P, G); empty-safe
    gt_to_pred = np.full(len(gt), -1, dtype=np.int64)
    pred_to_gt = np.full(len(pred), -1, dtype=np.int64)
    for i in np.argsort(-scores, kind="stable"):
        if not len(gt):
            break
        d = np.where(gt_to_pred < 0, dist[i], np.inf)
        j = int(np.argmin(d))
        if d[j] <= gate_m:
            gt_to_pred[j], pred_to_gt[i] = i, j
    hit = gt_to_pred >= 0
    centre_err = np.full(len(gt), np.nan)
    centre_err[hit] = dist[gt_to_pred[hit], np.flatnonzero(hit)]
    radius_err = np.full(len(gt), np.nan)
    if pred_radii_m is not None and gt_radii_m is not None:
        pr = _vector(pred_radii_m, len(pred), "pred_radii_m")
        gr = _vector(gt_radii_m, len(gt), "gt_radii_m")
        radius_err[hit] = pr[gt_to_pred[hit]] - gr[hit]
    return SceneMatch(gt_to_pred=gt_to_pred, pred_to_gt=pred_to_gt, centre_error_m=centre_err,
                      radius_error_m=radius_err, gt_distance_m=np.linalg.norm(gt, axis=1))


def error_stats(errors_m) -> dict:
    """Statistics of non-negative errors (N,) metres, NaNs dropped: n, median, rmse, p95, mean, max.

    Empty -> n = 0 and NaN statistics.
    """
    e = np.asarray(errors_m, dtype=np.float64).reshape(-1)
    e = e[np.isfinite(e)]
    if e.size == 0:
        return {"n": 0, "median": float("nan"), "rmse": float("nan"), "p95": float("nan"),
                "mean": float("nan"), "max": float("nan")}
    return {"n": int(e.size), "median": float(np.median(e)), "rmse": float(np.sqrt(np.mean(e * e))),
            "p95": float(np.percentile(e, 95)), "mean": float(np.mean(e)), "max": float(np.max(e))}


def signed_error_stats(errors_m) -> dict:
    """Statistics of signed errors (N,) metres, NaNs dropped: n, mean (bias), median, rmse, median_abs."""
    e = np.asarray(errors_m, dtype=np.float64).reshape(-1)
    e = e[np.isfinite(e)]
    if e.size == 0:
        nan = float("nan")
        return {"n": 0, "mean": nan, "median": nan, "rmse": nan, "median_abs": nan}
    return {"n": int(e.size), "mean": float(np.mean(e)), "median": float(np.median(e)),
            "rmse": float(np.sqrt(np.mean(e * e))), "median_abs": float(np.median(np.abs(e)))}


def detection_rates(centre_errors_m, thresholds_m: Sequence[float] = RATE_THRESHOLDS_M) -> dict:
    """Fraction of balls (N,) found within each threshold; a NaN error (missed) counts as a miss.

    Keys 'within_1cm', 'within_2cm', 'within_5cm' for the default thresholds
    (f'within_{t * 100:g}cm' in general); NaN when there is no ball.
    """
    e = np.asarray(centre_errors_m, dtype=np.float64).reshape(-1)
    out = {}
    for t in thresholds_m:
        key = f"within_{t * 100:g}cm"
        out[key] = float(np.mean(np.nan_to_num(e, nan=np.inf) <= t)) if e.size else float("nan")
    return out


def summarize_3d(matches: Sequence[SceneMatch], thresholds_m: Sequence[float] = RATE_THRESHOLDS_M) -> dict:
    """The 3D metrics over scenes (one ``SceneMatch`` each); see the module docstring.

    Returns n_scenes, n_gt, n_pred, n_matched, detection rates, 'centre_error_m' (error_stats),
    'radius_error_m' (signed_error_stats), false_detections, false_per_scene, and on negative
    scenes: n_negative_scenes, negative_detections, negative_scenes_with_detection (fraction).
    """
    if not matches:
        raise SphereBenchError("no scenes to summarise: pass one SceneMatch per scene")
    centre = np.concatenate([m.centre_error_m for m in matches])
    radius = np.concatenate([m.radius_error_m for m in matches])
    negatives = [m for m in matches if m.n_gt == 0]
    out = {"n_scenes": len(matches), "n_gt": int(centre.size), "n_pred": sum(m.n_pred for m in matches),
           "n_matched": int(np.count_nonzero(np.isfinite(centre)))}
    out.update(detection_rates(centre, thresholds_m))
    out["centre_error_m"] = error_stats(centre)
    out["radius_error_m"] = signed_error_stats(radius)
    out["false_detections"] = sum(m.n_false for m in matches)
    out["false_per_scene"] = out["false_detections"] / len(matches)
    out["n_negative_scenes"] = len(negatives)
    out["negative_detections"] = sum(m.n_pred for m in negatives)
    out["negative_scenes_with_detection"] = (float(np.mean([m.n_pred > 0 for m in negatives]))
                                             if negatives else float("nan"))
    return out


def error_vs_distance(matches: Sequence[SceneMatch]) -> tuple[np.ndarray, np.ndarray]:
    """(distance_m (N,), centre_error_m (N,)) of every ball, NaN error where missed: for a figure."""
    if not matches:
        return np.zeros(0), np.zeros(0)
    return (np.concatenate([m.gt_distance_m for m in matches]),
            np.concatenate([m.centre_error_m for m in matches]))


# ---------------------------------------------------------------- the bench's counts (no matching)

#: The nearest-within rule: a basketball is found when a detection's centre is within this of its centre.
FOUND_M = 0.02
#: The far rule: a ball whose centre's depth (camera z) exceeds FAR_RULE_FROM_M is found within FOUND_FAR_M.
FOUND_FAR_M = 0.03
FAR_RULE_FROM_M = 3.0
#: A detection this close to a distractor ball's centre accepts it (reports it as a basketball).
DISTRACTOR_HIT_M = 0.05


def found_limit_m(depths_m) -> np.ndarray:
    """The far rule's distance (m) within which a ball counts as found, for centres at depths_m (camera
    z, m): FOUND_M, or FOUND_FAR_M deeper than FAR_RULE_FROM_M."""
    return np.where(np.asarray(depths_m, np.float64) > FAR_RULE_FROM_M, FOUND_FAR_M, FOUND_M)


def found_far_rule(centre_errors_m, depths_m) -> float:
    """The share of balls found by the far rule: centre error within FOUND_M, or within FOUND_FAR_M
    for a ball whose centre lies deeper (camera z, m) than FAR_RULE_FROM_M; NaN or inf (missed)
    counts as not found; NaN without balls."""
    e, z = np.asarray(centre_errors_m, np.float64), np.asarray(depths_m, np.float64)
    if e.shape != z.shape:
        raise SphereBenchError(f"found_far_rule: {e.size} errors for {z.size} depths")
    if not e.size:
        return float("nan")
    return float(np.count_nonzero(np.nan_to_num(e, nan=np.inf) <= found_limit_m(z)) / e.size)


#: Bands of a ball's surface distance |c| - R (m) for the per-band found shares: the stereo loss study's,
#: where the ball's own depth sets the ceiling (docs/experiments/2026-12-04-stereo-losses.md).
DISTANCE_BANDS_M = ((0.0, 1.5), (1.5, 2.5), (2.5, 3.5), (3.5, float("inf")))


def band_name(band: tuple[float, float]) -> str:
    """"0-1.5 m", "3.5+ m"."""
    lo, hi = band
    return f"{lo:g}+ m" if hi == float("inf") else f"{lo:g}-{hi:g} m"


def found_by_band(centre_errors_m, depths_m, distances_m, bands=DISTANCE_BANDS_M) -> dict[str, dict]:
    """Per band of surface distance (m): {name: {"balls": n, "found": the far rule's share (NaN without
    balls)}} of balls with these centre errors (NaN: missed), centre depths and surface distances."""
    e, z, d = (np.asarray(x, np.float64).ravel() for x in (centre_errors_m, depths_m, distances_m))
    if not e.shape == z.shape == d.shape:
        raise SphereBenchError(f"found_by_band: {e.size} errors, {z.size} depths, {d.size} distances")
    out = {}
    for band in bands:
        sel = (d >= band[0]) & (d < band[1])
        out[band_name(band)] = {"balls": int(np.count_nonzero(sel)), "found": found_far_rule(e[sel], z[sel])}
    return out


def scene_counts(det_centres_m, gt: dict) -> dict:
    """One scene's detections against its ground truth (a scene's ``gt.json``), unmatched: the bench's
    and the seed sweep's view, where any detection within FOUND_M finds a ball.

    det_centres_m: (D, 3) or a list of centres, metres. Returns errs (per basketball, the nearest
    detection's centre error in metres, inf without one), z (their depths, m), false (detections
    farther than FOUND_M from every basketball), clutter (those farther than MATCH_GATE_M, one radius,
    from every basketball: not a ball's detection 2-5 cm off, a detection of something else) and distractors ([{radius_m, z_m, accepted}] for the
    distractor balls listed in gt["meta"]).
    """
    dets = [np.asarray(c, float) for c in det_centres_m]
    balls = [np.asarray(b["center_m"], float) for b in gt["balls"] if b.get("center_m") is not None]
    errs = [min((float(np.linalg.norm(d - b)) for d in dets), default=float("inf")) for b in balls]
    false = sum(1 for d in dets if all(np.linalg.norm(d - b) > FOUND_M for b in balls))
    clutter = sum(1 for d in dets if all(np.linalg.norm(d - b) > MATCH_GATE_M for b in balls))
    distractors = []
    for dd in gt.get("meta", {}).get("distractors", []) or []:
        c = np.asarray(dd["center_m"], float)
        hit = any(np.linalg.norm(d - c) <= DISTRACTOR_HIT_M for d in dets)
        distractors.append({"radius_m": dd["radius_m"], "z_m": float(c[2]), "accepted": hit})
    return {"errs": errs, "z": [float(b[2]) for b in balls], "false": false, "clutter": clutter,
            "distractors": distractors}


def detection_counts(rows: Sequence[dict]) -> dict:
    """Totals over ``scene_counts`` rows that also carry their scene's "family": balls, found (within
    FOUND_M), found_far_rule (within FOUND_M, or FOUND_FAR_M beyond FAR_RULE_FROM_M deep),
    false_detections, clutter_detections (``scene_counts``' clutter), detections_on_negatives and
    negative_scenes (family "negative"), distractors and distractors_rejected."""
    errs = [e for r in rows for e in r["errs"]]
    depths = [z for r in rows for z in r["z"]]
    dist = [d for r in rows for d in r["distractors"]]
    return {"balls": len(errs), "found": int(sum(e <= FOUND_M for e in errs)),
            "found_far_rule": int(sum(e <= (FOUND_FAR_M if z > FAR_RULE_FROM_M else FOUND_M)
                                      for e, z in zip(errs, depths))),
            "false_detections": int(sum(r["false"] for r in rows)),
            "clutter_detections": int(sum(r.get("clutter", r["false"]) for r in rows)),
            "detections_on_negatives": int(sum(r["false"] for r in rows if r["family"] == "negative")),
            "negative_scenes": int(sum(1 for r in rows if r["family"] == "negative")),
            "distractors": len(dist), "distractors_rejected": int(sum(not d["accepted"] for d in dist))}
