"""The frame's depth noise: sigma_z = A z^2 (1/m), A from Intel's stereo model (subpixel over fx
times the baseline), given outright, or measured on the frame from second differences of depth
(``frame_noise_a``); and the noise's correlation length (``frame_noise_correlation_px``), which
sets how many pixels count as one independent sample (``mean_variance_inflation``). The inlier
band of every stage is max(eps, ``noise_sigmas`` sigma_z) at the candidate's depth (``noise_eps``).
Python and kernels side by side.
"""

from __future__ import annotations

import functools
import math
from statistics import NormalDist

import numpy as np

from spherebench.method import frame_kernels as FK
from spherebench.method.compiled import kernel, workspace
from spherebench.method.config import DetectorConfig

# How the frame's noise is measured (``frame_noise_a``, ``frame_noise_correlation_px``); each chosen on
# the training splits (docs/experiments/2026-12-04-config-history.md and the records it points to).
NOISE_ESTIMATE_LAG_PX = 3  # second differences at this lag (px at 424 wide): beyond the matcher's correlation
NOISE_ESTIMATE_SAMPLES = 1024  # on at most this many evenly spread pixels
NOISE_ESTIMATE_MIN_SAMPLES = 128  # fewer qualifying: the sensor model's noise
NOISE_ESTIMATE_MIN_DEPTH_M = 0.6  # nearer pixels left out: their noise is below the depth quantisation
NOISE_ESTIMATE_KEEP = 0.9  # the trimmed mean square keeps the smallest 90 %: edges and flying pixels out
NOISE_MODEL_TOLERANCE = 0.10  # the measured noise replaces the model's when they differ by more than 10 %
NOISE_CORRELATION_MIN_PX = 0.8  # a shorter correlation length reads 0 (px at 424 wide): the estimate's scatter
NOISE_CORRELATION_MAX_PX = 3.0  # the longest taken (px at 424 wide)


@kernel
def noise_eps(cz, eps, noise_a, noise_k, cap):
    """Shell half-width at depth cz: max(eps, k sigma_z), sigma_z = noise_a cz^2 (metres), at most cap."""
    e = max(eps, noise_k * noise_a * cz * cz)
    return min(e, cap) if cap > eps else eps


@kernel
def noise_samples(points, img, lag, row_step, col_step, z_min, out):
    """Second differences of depth along image rows, as a frame's own noise sample.

    For every row_step-th row and col_step-th column where the pixels u - lag, u and u + lag all
    have depth, out receives |z(u - lag) - 2 z(u) + z(u + lag)| / (sqrt(6) z(u)^2) (1/m): on a smooth
    surface a lag-apart second difference is noise alone (a plane's curvature over a few pixels is
    a fraction of a millimetre), with variance 6 sigma_z^2 when the lag exceeds the noise's
    correlation length (edges and flying pixels give the few large values, which the caller trims:
    ``frame_noise_a``). Pixels nearer than z_min metres are left
    out (1 mm depth counts dominate their noise). Returns the number of samples written (at most
    out.size).
    """
    height, width = img.shape
    m = 0
    inv = 1.0 / math.sqrt(6.0)
    for r in range(0, height, row_step):
        base = r * width
        for c in range(lag, width - lag, col_step):
            i0, i1, i2 = img.flat[base + c - lag], img.flat[base + c], img.flat[base + c + lag]
            if i0 < 0 or i1 < 0 or i2 < 0:
                continue
            z = points[i1, 2]
            if z < z_min:
                continue
            if m == out.shape[0]:
                return m
            out[m] = abs(points[i0, 2] - 2.0 * z + points[i2, 2]) * inv / (z * z)
            m += 1
    return m


def noise_a(config: DetectorConfig, fx: float | None) -> float:
    """sigma_z / z^2 (1/m): ``config.noise.noise_z2_per_m`` where set, else Intel's stereo model for focal
    length fx px; 0 without intrinsics."""
    if fx is None:
        return 0.0
    if config.noise.noise_z2_per_m is not None:
        return float(config.noise.noise_z2_per_m)
    if config.noise.noise_subpixel <= 0 or config.noise.noise_baseline_m <= 0:
        return 0.0
    return config.noise.noise_subpixel / (fx * config.noise.noise_baseline_m)


@functools.lru_cache(maxsize=8)
def _trimmed_second_moment(keep: float) -> float:
    """E[X^2 | |X| < q] for X ~ N(0, 1), q the ``keep`` quantile of |X|: the share of sigma^2 that the
    mean square of the smallest ``keep`` of a normal sample's absolute values estimates."""
    q = NormalDist().inv_cdf(0.5 + keep / 2.0)
    return 1.0 - 2.0 * q * NormalDist().pdf(q) / keep


def noise_mean_square(points: np.ndarray, index_image: np.ndarray, config: DetectorConfig, lag: int) -> float | None:
    """The trimmed mean square of ``noise_samples`` at a lag (pixels): sigma_z^2 / z^4 (1/m^2)
    for a lag beyond the noise's correlation; None with too few samples (see ``frame_noise_a``)."""
    h, w = index_image.shape
    step = max(1, int(math.sqrt(h * w / NOISE_ESTIMATE_SAMPLES)))
    out = workspace("noise", (NOISE_ESTIMATE_SAMPLES,), np.float64)
    m = noise_samples(points, index_image, lag, step, step, NOISE_ESTIMATE_MIN_DEPTH_M, out)
    if m < NOISE_ESTIMATE_MIN_SAMPLES:
        return None
    # a trimmed mean square, not the median: depth quantised in steps near sigma (a structured-light
    # sensor at range) makes the median of the few values it takes a biased estimate
    k = max(1, int(NOISE_ESTIMATE_KEEP * m))
    kept = np.partition(out[:m], k - 1)[:k]
    return float(np.dot(kept, kept)) / k / _trimmed_second_moment(NOISE_ESTIMATE_KEEP)


def _second_difference_ratio(length_px: float, lag_px: int) -> float:
    """E[D_1^2] / E[D_L^2] for second differences at lags 1 and L of a noise whose autocorrelation
    at lag d is exp(-(d / length)^2): E[D_l^2] = sigma^2 (6 - 8 rho(l) + 2 rho(2 l))."""
    if length_px <= 0.0:
        return 1.0

    def msq(lag: float) -> float:
        return 6.0 - 8.0 * math.exp(-(lag / length_px) ** 2) + 2.0 * math.exp(-(2.0 * lag / length_px) ** 2)

    return msq(1.0) / msq(float(lag_px))


def correlation_from_ratio(ratio: float, lag_px: int, max_px: float) -> float:
    """The correlation length (pixels) whose ``_second_difference_ratio`` is ``ratio``, by bisection
    (the ratio falls from 1 with the length) to 1e-4 px; 0 for a ratio near 1, ``max_px`` at most."""
    if not ratio < 0.97:  # white noise reads 1 within the estimates' scatter
        return 0.0
    lo, hi = 0.0, float(max_px)
    if _second_difference_ratio(hi, lag_px) >= ratio:
        return hi
    while hi - lo > 1e-4:  # far below the ratio's scatter; each step is a Python call
        mid = 0.5 * (lo + hi)
        if _second_difference_ratio(mid, lag_px) > ratio:
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)


def frame_noise_correlation_px(points: np.ndarray, index_image: np.ndarray, config: DetectorConfig,
                               bin_px: int, lag_ms: float | None = None) -> float:
    """The depth noise's correlation length on this frame (pixels of the stream, the lag where its
    autocorrelation is 1/e, taken as Gaussian): from the ratio of the mean squares of second
    differences at lag 1 and at the noise estimate's lag (``_second_difference_ratio``), which falls
    from 1 (independent pixels) as neighbours' errors correlate. 0 where it cannot be measured, or
    below ``NOISE_CORRELATION_MIN_PX``.
    lag_ms: the mean square at the long lag, when already measured."""
    lag = max(1, NOISE_ESTIMATE_LAG_PX * bin_px)
    long_ms = noise_mean_square(points, index_image, config, lag) if lag_ms is None else lag_ms
    short_ms = noise_mean_square(points, index_image, config, 1)
    if long_ms is None or short_ms is None or not long_ms > 0:
        return 0.0
    length = correlation_from_ratio(short_ms / long_ms, lag, NOISE_CORRELATION_MAX_PX * bin_px)
    return length if length >= NOISE_CORRELATION_MIN_PX * bin_px else 0.0


@kernel  # compiled: verification's measurements ask for it per candidate (``verification_kernels.measurements``)
def mean_variance_inflation(length_px, stride=1):
    """How much more a mean over a large patch of pixels (every stride-th in both directions) varies
    than one over as many independent ones, for noise of correlation length ``length_px``: the sum
    of the autocorrelation over the lattice, (sum_k exp(-(k stride / length)^2))^2. 1 for
    independent pixels; pi length^2 / stride^2 for long lengths. Pixels over this count as one
    effective sample in the evidence tests."""
    if length_px <= 0.0:
        return 1.0
    t = max(int(stride), 1) / length_px
    one_axis = 0.0
    for k in range(1, int(4.0 / t) + 2):
        one_axis += math.exp(-((k * t) * (k * t)))
    one_axis = 1.0 + 2.0 * one_axis
    return one_axis * one_axis


def frame_noise_a(points: np.ndarray, index_image: np.ndarray, config: DetectorConfig, bin_px: int) -> float | None:
    """The frame's own depth noise as sigma_z / z^2 (1/m), from second differences of depth along image
    rows (``noise_samples``) on about ``NOISE_ESTIMATE_SAMPLES`` evenly spread pixels, by their
    trimmed mean square (the smallest ``NOISE_ESTIMATE_KEEP`` of them: edges, flying pixels and curved
    surfaces make the largest; rescaled to a normal's second moment); None when fewer than
    ``NOISE_ESTIMATE_MIN_SAMPLES`` pixels qualify (a frame too near, or mostly holes).

    The lag, ``NOISE_ESTIMATE_LAG_PX`` at 424 px wide, scales with the stream's width as the stereo
    matcher's noise correlation does, so that the second difference sees independent errors."""
    ms = noise_mean_square(points, index_image, config, max(1, NOISE_ESTIMATE_LAG_PX * bin_px))
    return None if ms is None else math.sqrt(ms)


def eps_at(config: DetectorConfig, depth_m: float, fx: float | None) -> float:
    """The shell half-width at a centre depth (metres): eps widened by the depth noise model."""
    return float(noise_eps(depth_m, config.eps_m, noise_a(config, fx), config.noise.noise_sigmas,
                             FK.MAX_EPS_FRACTION * config.radius_m))
