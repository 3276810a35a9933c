"""Stage 4, the verdict: a verified sphere's probability of being a ball, from a model fitted on both
sensor models.

Verification (``verification._verify_batch``) measures each candidate: its inliers, its free radius
and that radius's standard error, and how the pixels of its silhouette and outline lie against the
sphere (``verification_kernels.measurements``, by name ``MEASUREMENT_NAMES``). ``features`` turns
candidates' measurements into fixed vectors of scale-free quantities (shares, ratios to the frame's
noise, logarithms of counts and ranges), compiled, and ``verdict_features`` one candidate's by name
(a sphere's evidence: what the model's fit reads). A model fitted on the candidates of `train` and
`train-stereo` (``make train-verifier``) maps that vector to the probability that a ball's centre
lies within 2 cm (3 cm beyond 3 m) of the candidate's, calibrated on scenes held apart from its fit.

The model ships as ONNX beside this module (``verdict.onnx``, its card ``verdict_card.md``); it is
run by onnxruntime on one thread, the candidates verified together (``verification.verify_rows``)
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

from spherebench.method import verification_kernels as VK
from spherebench.method.compiled import kernel

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


#: the measurements the features read that a record may lack, and the value each then takes
_OPTIONAL = {"pixels_per_sample": 1.0, "noise_ratio": 1.0, "visible_fraction": 1.0, "ring_spread": 0.0}
#: the measurements the features read that a record must hold (the rest of
#: ``verification_kernels.MEASUREMENT_NAMES``, which they do not read, may be missing: nan)
_REQUIRED = frozenset(("depth_m", "sigma_m", "valid_disc", "inner_n", "inner_sum", "outer_h_n", "outer_h_sum",
                       "outer_v_n", "outer_v_sum", "free_radius_m", "free_radius_se_m", "n_inliers", "rmse_m",
                       "sigma_measured_m", "inlier", "invalid_disc", "behind", "front_near", "ring_continued",
                       "ring", "ring_front", "behind_inner", "valid_inner", "edge_behind", "edge_n"))


def measurement_row(stats: dict) -> np.ndarray:
    """(N_MEASURED,) float64: a candidate's measurements by name (``verification.Candidate.stats``, a
    ``Sphere``'s evidence) in ``verification_kernels.MEASUREMENT_NAMES``' order. KeyError where one
    the features need is missing."""
    missing = _REQUIRED - stats.keys()
    if missing:
        raise KeyError(f"the verdict's features need {', '.join(sorted(missing))}")
    return np.array([float(stats.get(k, _OPTIONAL.get(k, math.nan))) for k in VK.MEASUREMENT_NAMES], np.float64)


def verdict_features(stats: dict, radius_m: float) -> np.ndarray:
    """(N_FEATURES,) float32: one verified candidate's inputs to the verdict (``FEATURE_NAMES``), from
    its measurements by name (``measurement_row``: the silhouette's counts of
    ``verification_kernels.window_stats`` and depth_m, sigma_m, sigma_measured_m, noise_ratio,
    pixels_per_sample, n_inliers, rmse_m, free_radius_m, free_radius_se_m). radius_m: R."""
    return features(measurement_row(stats).reshape(1, -1), radius_m)[0]


def features(measured: np.ndarray, radius_m: float) -> np.ndarray:
    """(B, N_FEATURES) float32: the verdict's inputs (``FEATURE_NAMES``) of B candidates' measurements
    measured (B, N_MEASURED) (``verification_kernels.measurements``' rows); radius_m: R."""
    out = np.empty((len(measured), N_FEATURES), np.float32)
    _features(np.ascontiguousarray(measured, np.float64), float(radius_m), out)
    return out


@kernel
def _log(x, floor):
    return math.log(max(x, floor)) if math.isfinite(x) else math.log(floor)


@kernel
def _share(num, den):
    return num / den if den > 0 else 0.0


@kernel
def _relief(m, sigma, radius):
    """(relief_r, relief_t) of one candidate's measurements m (N_MEASURED,): how much flatter than a
    ball the inner zone is than the worse of the outer zones (in R, and in standard errors of the two
    means with the pixels' correlation, pixels_per_sample); 0 where the zones hold under 3 pixels."""
    n_in = m[VK.M_IN_N]
    if not n_in >= 3:
        return 0.0, 0.0
    m_in = m[VK.M_IN_SUM] / n_in
    per = m[VK.M_PIXELS_PER_SAMPLE]
    worst, relief_t = -math.inf, 0.0
    for side_n, side_sum in ((m[VK.M_OUTH_N], m[VK.M_OUTH_SUM]), (m[VK.M_OUTV_N], m[VK.M_OUTV_SUM])):
        if side_n >= 3:
            flatter = m_in - side_sum / side_n
            if flatter > worst:
                worst = flatter
                relief_t = flatter / (sigma * math.sqrt(per * (1.0 / n_in + 1.0 / side_n)))
    return (worst / radius if math.isfinite(worst) else 0.0), relief_t


@kernel
def _features(measured, radius, out):
    """``features``' rows: out (B, N_FEATURES) of measured (B, N_MEASURED), in ``FEATURE_NAMES``' order."""
    for b in range(measured.shape[0]):
        m, x = measured[b], out[b]
        sigma = max(m[VK.M_SIGMA], 1e-6)
        vd = m[VK.M_VALID_DISC]
        relief_r, relief_t = _relief(m, sigma, radius)
        fr, fse = m[VK.M_FREE_R], m[VK.M_FREE_SE]
        sized = math.isfinite(fr)
        se = fse if math.isfinite(fse) and fse > 0 else radius
        x[0] = _log(m[VK.M_DEPTH], 0.05)
        x[1] = math.log(sigma / radius)
        x[2] = _log(m[VK.M_NOISE_RATIO], 1e-3)
        x[3] = _log(m[VK.M_PIXELS_PER_SAMPLE], 1.0)
        x[4] = math.log1p(max(m[VK.M_N_INLIERS], 0.0))
        x[5] = _log(m[VK.M_RMSE] / sigma, 1e-3)
        x[6] = _log(m[VK.M_SIGMA_MEASURED] / sigma, 1e-3)
        x[7] = min(_share(m[VK.M_INLIER], vd), 2.0)
        x[8] = _share(m[VK.M_INVALID_DISC], vd + m[VK.M_INVALID_DISC])
        x[9] = _share(m[VK.M_BEHIND], vd)
        x[10] = _share(m[VK.M_FRONT_NEAR], vd)
        x[11] = m[VK.M_VISIBLE]
        x[12] = _share(m[VK.M_RING_CONT], m[VK.M_RING])
        x[13] = _share(m[VK.M_RING_FRONT], m[VK.M_RING])
        x[14] = m[VK.M_RING_SPREAD]
        x[15] = _share(m[VK.M_BEHIND_INNER], m[VK.M_VALID_INNER])
        x[16] = _share(m[VK.M_EDGE_BEHIND], m[VK.M_EDGE_N])
        x[17] = relief_r
        x[18] = max(min(relief_t, 50.0), -50.0)
        x[19] = (fr - radius) / radius if sized else 1.0
        x[20] = max(min((fr - radius) / se, 50.0), -50.0) if sized else 50.0
        x[21] = math.log(max(se, 1e-5) / radius)


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
        raw, p = self.scores_of(features(np.stack([measurement_row(s) for s in stats]), radius_m))
        return [(float(a), float(b)) for a, b in zip(raw, p)]

    def scores_of(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(model scores (B,), calibrated probabilities (B,)) of the features x (B, N_FEATURES)."""
        s = self.model_scores(x)
        return s, np.interp(s, self.knots_score, self.knots_p)

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


def verdicts(measured: np.ndarray, radius_m: float) -> tuple[np.ndarray, np.ndarray]:
    """(raw scores (B,), probabilities (B,)) of B verified candidates' measurements measured (B,
    N_MEASURED) (``verification_kernels.measurements``): the fitted verdict's, in one run of the model,
    or ``unscored``'s constant."""
    if _UNSCORED:
        return np.full(len(measured), _UNSCORED[-1]), np.full(len(measured), _UNSCORED[-1])
    if not len(measured):
        return np.zeros(0), np.zeros(0)
    return load_verdict().scores_of(features(measured, radius_m))
