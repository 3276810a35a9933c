"""Stage 4, the verdict: a verified sphere's probability of being a ball, from a model fitted on both
sensor models.

Verification (``verification._verify_once``) measures each candidate: its inliers, its free radius
and that radius's standard error, and how the pixels of its silhouette and outline lie against the
sphere (``verification_kernels.window_stats``). ``verdict_features`` turns one candidate's
measurements into a fixed vector of scale-free quantities (shares, ratios to the frame's noise, logarithms of counts and
ranges); a model fitted on the candidates of `train` and `train-stereo` (``make train-verifier``)
maps that vector to the probability that a ball's centre lies within 2 cm (3 cm beyond 3 m) of the
candidate's, calibrated on scenes held apart from its fit.

The model ships as ONNX beside this module (``verdict.onnx``, its card ``verdict_card.md``); it is
run by onnxruntime on one thread, the candidates verified together (``verification.verify_starts``)
in one call. The calibration map travels in the model's metadata (``calibration_knots``: score and
probability knots, linear between them), so that one file holds the verdict.
"""

from __future__ import annotations

import contextlib
import functools
import json
import math
from pathlib import Path

import numpy as np

#: the model's inputs, in order (``verdict_features``); a model whose metadata lists other names is refused
FEATURE_NAMES = (
    "log_depth",           # ln(z / 1 m) of the verified centre
    "log_noise_r",         # ln(sigma_z / R): one pixel's depth noise at the centre (the frame's noise model)
    "log_noise_ratio",     # ln(the frame's measured noise / the sensor model's)
    "log_pixels_per_sample",  # ln(pixels per independent noise sample: the noise's correlation)
    "log_inliers",         # ln(1 + inliers) (estimated over the whole silhouette)
    "log_rmse_noise",      # ln(the inliers' RMS ray residual / sigma_z)
    "log_sigma_measured",  # ln(the candidate's own measured noise / sigma_z)
    "coverage",            # inliers / silhouette pixels with depth
    "invalid_share",       # silhouette pixels without depth / all its pixels
    "behind_share",        # silhouette pixels seen behind the sphere
    "hug_share",           # silhouette pixels just in front of it (another surface hugging the sphere)
    "visible_fraction",    # silhouette pixels that no nearer surface hides
    "ring_continued",      # outline ring where a surface continues at the ball's depth (a wall, a plane)
    "ring_front",          # outline ring where a surface attached in front continues (a cylinder's body)
    "ring_spread",         # outline ring attached outside the half ring that holds most of it
    "see_through",         # inner disc seen behind the sphere (a smaller ball, a cylinder's top)
    "edge_behind",         # silhouette's edge band seen behind the sphere (a smaller ball)
    "relief_r",            # (inner zone's mean residual - outer zones' worse) / R: flatter than a ball > 0
    "relief_t",            # the same over its standard error
    "size_r",              # (free radius - R) / R
    "size_z",              # (free radius - R) / its standard error
    "log_size_se_r",       # ln(the free radius's standard error / R)
)
N_FEATURES = len(FEATURE_NAMES)

#: where the shipped model lies (``make train-verifier`` installs it)
MODEL_PATH = Path(__file__).with_name("verdict.onnx")


def _share(num: float, den: float) -> float:
    return float(num) / den if den > 0 else 0.0


def _log(x: float, floor: float) -> float:
    return math.log(max(x, floor)) if math.isfinite(x) else math.log(floor)


def verdict_features(stats: dict, radius_m: float) -> np.ndarray:
    """(N_FEATURES,) float32: one verified candidate's inputs to the verdict (``FEATURE_NAMES``).

    stats: the candidate's measurements as ``verification._verify_once`` records them (the silhouette's
    counts of ``verification_kernels.window_stats`` and depth_m, sigma_m, sigma_measured_m, noise_ratio,
    pixels_per_sample, n_inliers, rmse_m, free_radius_m, free_radius_se_m). radius_m: R.
    """
    R = radius_m
    z = stats["depth_m"]
    sigma = max(stats["sigma_m"], 1e-6)
    vd = stats["valid_disc"]
    n_in = stats["inner_n"]
    relief_r, relief_t = 0.0, 0.0
    if n_in >= 3:
        m_in = stats["inner_sum"] / n_in
        per = stats.get("pixels_per_sample", 1.0)
        worst = -math.inf
        for side in ("outer_h", "outer_v"):
            n = stats[side + "_n"]
            if n >= 3:
                flatter = m_in - stats[side + "_sum"] / n
                if flatter > worst:
                    worst = flatter
                    relief_t = flatter / (sigma * math.sqrt(per * (1.0 / n_in + 1.0 / n)))
        relief_r = worst / R if math.isfinite(worst) else 0.0
    fr, fse = stats["free_radius_m"], stats["free_radius_se_m"]
    sized = math.isfinite(fr)
    se = fse if math.isfinite(fse) and fse > 0 else R
    x = (
        _log(z, 0.05),
        math.log(sigma / R),
        _log(stats.get("noise_ratio", 1.0), 1e-3),
        _log(stats.get("pixels_per_sample", 1.0), 1.0),
        math.log1p(max(stats["n_inliers"], 0.0)),
        _log(stats["rmse_m"] / sigma, 1e-3),
        _log(stats["sigma_measured_m"] / sigma, 1e-3),
        min(_share(stats["inlier"], vd), 2.0),
        _share(stats["invalid_disc"], vd + stats["invalid_disc"]),
        _share(stats["behind"], vd),
        _share(stats["front_near"], vd),
        stats.get("visible_fraction", 1.0),
        _share(stats["ring_continued"], stats["ring"]),
        _share(stats["ring_front"], stats["ring"]),
        stats.get("ring_spread", 0.0),
        _share(stats["behind_inner"], stats["valid_inner"]),
        _share(stats["edge_behind"], stats["edge_n"]),
        relief_r,
        max(min(relief_t, 50.0), -50.0),
        (fr - R) / R if sized else 1.0,
        max(min((fr - R) / se, 50.0), -50.0) if sized else 50.0,
        math.log(max(se, 1e-5) / R),
    )
    return np.asarray(x, np.float32)


class FittedVerdict:
    """A fitted verdict: onnxruntime over the ONNX model at ``path``, and its calibration map.

    The model takes "features" (B, N_FEATURES) float32 and gives the classifier's probability of
    the positive class; ``probability`` maps it through the calibration knots."""

    def __init__(self, path: Path):
        import onnxruntime as ort

        opts = ort.SessionOptions()
        opts.intra_op_num_threads = 1  # one candidate at a time: threads cost more than they give
        opts.inter_op_num_threads = 1
        opts.log_severity_level = 3  # the tree ensemble's unused "label" output warns of its shape on batches
        self.session = ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])
        meta = self.session.get_modelmeta().custom_metadata_map
        names = tuple(json.loads(meta.get("feature_names", "[]")))
        if names != FEATURE_NAMES:
            raise ValueError(f"{path}: the verdict model was fitted on other features; refit it with "
                             "`make train-verifier`")
        knots = json.loads(meta.get("calibration_knots", "[[0, 1], [0, 1]]"))
        self.knots_score = np.asarray(knots[0], np.float64)
        self.knots_p = np.asarray(knots[1], np.float64)
        self.input_name = self.session.get_inputs()[0].name
        self.output_name = next(o.name for o in self.session.get_outputs() if "prob" in o.name)

    def model_scores(self, x: np.ndarray) -> np.ndarray:
        """(B,) the classifier's uncalibrated probability for features x (B, N_FEATURES)."""
        p = self.session.run([self.output_name], {self.input_name: np.asarray(x, np.float32).reshape(-1, N_FEATURES)})[0]
        return p[:, 1].astype(np.float64)  # (B, 2): exported without ZipMap

    def scores(self, stats: dict, radius_m: float) -> tuple[float, float]:
        """One candidate's (model score, calibrated probability of being a ball); stats:
        ``verdict_features``'."""
        s = float(self.model_scores(verdict_features(stats, radius_m))[0])
        return s, float(np.interp(s, self.knots_score, self.knots_p))

    def batch_scores(self, stats: list[dict], radius_m: float) -> list[tuple[float, float]]:
        """``scores`` of several candidates in one run of the model (its per-call cost is most of one
        candidate's; each row's result is the same as alone)."""
        if len(stats) == 1:  # a third less than a batch of one
            return [self.scores(stats[0], radius_m)]
        s = self.model_scores(np.stack([verdict_features(s, radius_m) for s in stats]))
        p = np.interp(s, self.knots_score, self.knots_p)
        return [(float(a), float(b)) for a, b in zip(s, p)]

    def probability(self, stats: dict, radius_m: float) -> float:
        """One candidate's calibrated probability of being a ball (stats: ``verdict_features``')."""
        return self.scores(stats, radius_m)[1]


@functools.lru_cache(maxsize=4)
def load_verdict(path: str = str(MODEL_PATH)) -> FittedVerdict:
    """The fitted verdict at path (one per process)."""
    return FittedVerdict(Path(path))


#: the constants standing in for the fitted verdict (``unscored``, innermost last); empty: the verdict's
_UNSCORED: list[float] = []


@contextlib.contextmanager
def unscored(score: float = 0.5):
    """Within it, every organised candidate of this process scores ``score`` (raw and
    probability) in place of the fitted verdict's, so that no model steers which candidates are
    verified and kept: with accept_score 1 nothing is accepted and every search and retry runs
    (``make train-verifier`` collects its candidates so)."""
    _UNSCORED.append(float(score))
    try:
        yield
    finally:
        _UNSCORED.pop()


def verdicts(stats: list[dict], radius_m: float) -> list[tuple[float, float]]:
    """(raw score, probability) of each verified candidate: the fitted verdict's
    (``FittedVerdict.batch_scores``), or ``unscored``'s constant."""
    if not stats:
        return []
    if _UNSCORED:
        return [(_UNSCORED[-1], _UNSCORED[-1])] * len(stats)
    return load_verdict().batch_scores(stats, radius_m)
