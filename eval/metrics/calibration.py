"""Calibration of detection scores: pure functions on arrays.

A score is read as the probability that its detection is correct. **Correct**
(``detection_correct``): the detection's centre lies within ``FOUND_M`` (2 cm) of the centre of one of
the scene's balls (``gt["balls"]``: the dataset's ball, of its radius), or within ``FOUND_FAR_M``
(3 cm) of a ball whose centre lies deeper (camera z) than ``FAR_RULE_FROM_M`` (3 m): the far rule of
``metrics3d``. A detection on a distractor ball (``gt["meta"]["distractors"]``: another size of
ball) or on anything else is incorrect. At most one detection per ball is correct: detections are
taken in decreasing score order (ties in the order given) and each takes the nearest ball still
untaken within its limit, so a ball's lower-scored duplicates are incorrect.

**Reliability** (``reliability``): the scores in [0, 1] fall into ``n_bins`` equal-width bins
[k/n, (k+1)/n), the last one closed; per bin the count, the mean score (confidence) and the
fraction correct (accuracy). **ECE** = sum over bins of n_b / N |acc_b - conf_b|; **MCE** = the
largest |acc_b - conf_b| over the non-empty bins. Both are NaN without any detection (nothing to
calibrate: no figure, not a perfect one). **The ECE floor** (``ece_floor``): the median ECE that a
perfectly calibrated detector with the same scores shows on as many detections, each correct with
its score's probability; a set's ECE near its floor cannot be told apart from calibrated. Detections
that are one trial (a scene's ball at several run seeds) share one draw there (``groups``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from spherebench.errors import SphereBenchError
from spherebench.eval.metrics.metrics3d import _points, _vector, found_limit_m

#: Bins of the reliability diagram over [0, 1].
N_BINS = 10


def detection_correct(det_centres_m, det_scores, gt: dict) -> np.ndarray:
    """(M,) bool: which of one scene's detections are correct (module docstring).

    det_centres_m: (M, 3) detected centres, metres, camera frame. det_scores: (M,) their scores.
    gt: the scene's ``gt.json`` (``inout.read_scene_gt``): its "balls" with center_m (m); balls
    without a known centre are ignored (label only scenes whose balls all have one).
    """
    dets = _points(det_centres_m, "detected centres")
    scores = _vector(det_scores, len(dets), "det_scores")
    balls = _points([b["center_m"] for b in gt.get("balls", []) if b.get("center_m") is not None],
                    "ball centres")
    limit_m = found_limit_m(balls[:, 2])  # (G,)
    dist_m = np.linalg.norm(dets[:, None, :] - balls[None, :, :], axis=2)  # (M, G)
    correct = np.zeros(len(dets), dtype=bool)
    taken = np.zeros(len(balls), dtype=bool)
    for i in np.argsort(-scores, kind="stable"):
        d = np.where(taken | (dist_m[i] > limit_m), np.inf, dist_m[i])
        if d.size and np.isfinite(d.min()):
            taken[int(np.argmin(d))] = correct[i] = True
    return correct


@dataclass(frozen=True)
class Reliability:
    """A reliability diagram's bins (B = n_bins).

    edges: (B + 1,) bin edges over [0, 1]. count: (B,) detections per bin (empty bins kept, 0).
    mean_score: (B,) the bin's mean score; NaN where empty. fraction_correct: (B,) its share of
    correct detections; NaN where empty.
    """

    edges: np.ndarray
    count: np.ndarray
    mean_score: np.ndarray
    fraction_correct: np.ndarray

    @property
    def n(self) -> int:
        return int(self.count.sum())

    @property
    def gap(self) -> np.ndarray:
        """(B,) |fraction correct - mean score| per bin; NaN where empty."""
        return np.abs(self.fraction_correct - self.mean_score)


def reliability(scores, correct, n_bins: int = N_BINS) -> Reliability:
    """Bin scores (N,) in [0, 1] with their labels (N,) bool into ``n_bins`` equal-width bins."""
    s = np.asarray(scores, dtype=np.float64).reshape(-1)
    c = _vector(correct, s.size, "correct").astype(bool)
    if n_bins < 1:
        raise SphereBenchError(f"n_bins={n_bins} must be >= 1")
    if not np.all((s >= 0.0) & (s <= 1.0)):  # NaN fails too
        raise SphereBenchError("scores must lie in [0, 1]")
    which = np.minimum((s * n_bins).astype(np.int64), n_bins - 1)  # a score of 1 joins the last bin
    count = np.bincount(which, minlength=n_bins)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.bincount(which, weights=s, minlength=n_bins) / count
        frac = np.bincount(which, weights=c.astype(np.float64), minlength=n_bins) / count
    return Reliability(edges=np.linspace(0.0, 1.0, n_bins + 1), count=count, mean_score=mean, fraction_correct=frac)


def expected_calibration_error(scores, correct, n_bins: int = N_BINS) -> float:
    """ECE = sum over bins of n_b / N |acc_b - conf_b|, in [0, 1]; NaN without detections."""
    r = reliability(scores, correct, n_bins)
    full = r.count > 0
    return float(np.sum(r.count[full] * r.gap[full]) / r.n) if r.n else float("nan")


def maximum_calibration_error(scores, correct, n_bins: int = N_BINS) -> float:
    """MCE = max over the non-empty bins of |acc_b - conf_b|, in [0, 1]; NaN without detections."""
    r = reliability(scores, correct, n_bins)
    return float(np.max(r.gap[r.count > 0])) if r.n else float("nan")


#: Draws of ``ece_floor`` (its median moves by about 0.002 between seeds at 60 detections).
FLOOR_DRAWS = 400


def ece_floor(scores, n_bins: int = N_BINS, draws: int = FLOOR_DRAWS, seed: int = 0, groups=None) -> float:
    """The median ECE over ``draws`` samples in which detection i (scores (N,) in [0, 1]) is correct
    with probability scores[i]: what sampling alone gives a calibrated score on N detections;
    NaN without detections. Seeded: the same scores give the same floor.

    groups: (N,) labels, or None (every detection on its own). Detections of one label share one
    uniform draw, so they are right or wrong together as far as their scores allow: the same ball of
    one scene detected at several run seeds is one trial, not several, and pooled seeds have the
    floor of their scenes, not of their detections."""
    s = np.asarray(scores, dtype=np.float64).reshape(-1)
    if s.size == 0:
        return float("nan")
    if groups is None:
        which, n_draw = np.arange(s.size), s.size
    else:
        labels = np.asarray(groups).reshape(-1)
        if labels.size != s.size:
            raise SphereBenchError(f"groups has {labels.size} labels for {s.size} scores")
        which = np.unique(labels, return_inverse=True)[1].reshape(-1)
        n_draw = int(which.max()) + 1
    rng = np.random.default_rng(seed)
    return float(np.median([expected_calibration_error(s, rng.random(n_draw)[which] < s, n_bins)
                            for _ in range(draws)]))
