"""Stage 1, the frame: an organised cloud made ready for the other stages (``PreparedFrame``).

One pass over the points (``frame_kernels.prepare_organised``) builds the index image, the
summed-area table of depth and valid count over cells of ``search_width_px``-wide binning, and a
depth histogram (the scene's far depth). The frame's noise is measured (``noise``), the search's
strata sized by the RANSAC bound for the smallest ball the frame can hold (``strata``), and the
kernels' parameter vector filled (``parameters``).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from spherebench.cloud import Cloud
from spherebench.method import frame_kernels as FK
from spherebench.method.compiled import workspace
from spherebench.method.config import DetectorConfig
from spherebench.method.noise import (
    NOISE_ESTIMATE_LAG_PX, NOISE_MODEL_TOLERANCE, frame_noise_correlation_px, mean_variance_inflation, noise_a,
    noise_mean_square)

# The frame's limits and the search's bound; each chosen on the training splits
# (docs/experiments/2026-12-04-config-history.md and the records it points to).
MM_LIMIT_M = 50.0  # a cloud whose median |z| is beyond this is in millimetres (``input.mm_check``)
SAMPLE_SUCCESS = 0.8  # the chance that a first cell on the ball gives a hypothesis that passes the pretest
BOUND_NOISE_FRACTION = 0.75  # the bound provides for balls to where one pixel's noise is this * R ...
HYPOTHESIS_MIN_RANGE_M = 3.5  # ... and hypotheses are kept to at least this depth (m) on a noisy unit


def parameters(config: DetectorConfig, intr, stratum: tuple[int, int], bin_px: int, grid_shape: tuple,
               z_far_m: float, a: float | None = None, corr_px: float = 0.0) -> np.ndarray:
    """The float64 parameter vector (``frame_kernels.N_PRM``,) of the organised kernels; a: the frame's
    sigma_z / z^2 (1/m), by default the configuration's (``noise_a``); corr_px: the noise's correlation
    length (stream pixels), which widens the search's box-mean tolerances."""
    a = noise_a(config, float(intr.fx)) if a is None else a
    prm = np.zeros(FK.N_PRM, np.float64)
    R = config.radius_m
    prm[FK.P_R], prm[FK.P_EPS], prm[FK.P_NOISE_K] = R, config.eps_m, config.noise.noise_sigmas
    prm[FK.P_FX], prm[FK.P_FY], prm[FK.P_PPX], prm[FK.P_PPY] = intr.fx, intr.fy, intr.ppx, intr.ppy
    prm[FK.P_NOISE_A] = a
    prm[FK.P_EPS_CAP] = FK.MAX_EPS_FRACTION * R
    prm[FK.P_STRATUM_V], prm[FK.P_STRATUM_U], prm[FK.P_BIN] = stratum[0], stratum[1], bin_px
    prm[FK.P_CELL_PX] = bin_px * cell_rows(bin_px)  # the pixels a cell's table entry sums
    # hypotheses whose ball would be beyond the range limit (with a margin; on a noisy unit never nearer than
    # HYPOTHESIS_MIN_RANGE_M), or larger than the grid
    far_m = max(range_limit_m(config, float(intr.fx), a),
                min(HYPOTHESIS_MIN_RANGE_M, config.search.max_range_m))
    prm[FK.P_RR_MIN] = 0.8 * intr.fx / bin_px * R / far_m
    prm[FK.P_RR_MAX] = float(max(grid_shape))
    prm[FK.P_Z_FAR] = z_far_m
    # a box of cells each bin_px wide: the correlation length in cells
    prm[FK.P_MEAN_NOISE] = math.sqrt(mean_variance_inflation(corr_px / bin_px))
    return prm


def range_limit_m(config: DetectorConfig, fx: float | None, a: float | None = None) -> float:
    """The farthest centre depth the iteration bound provides for (metres): where the per-pixel
    depth noise reaches ``BOUND_NOISE_FRACTION`` R (3.5 m at 424x240, 4.9 m at 848x480, 6 m at
    1280x720 for the D435 model), or ``max_range_m`` when that is nearer."""
    a = noise_a(config, fx) if a is None else a
    lim = math.sqrt(BOUND_NOISE_FRACTION * config.radius_m / a) if a > 0 else math.inf
    return min(lim, config.search.max_range_m)


def far_depth_m(config: DetectorConfig, intr, z_scene_m: float, a: float | None = None) -> float:
    """The farthest centre depth the search provides for (metres): the scene's depth ``z_scene_m``
    (its 98th percentile) plus R (a ball is in front of what is behind it) or ``range_limit_m``,
    whichever is nearer, and at least 2 R."""
    z_far = range_limit_m(config, float(intr.fx), a)
    if math.isfinite(z_scene_m):
        z_far = min(z_far, z_scene_m + config.radius_m)
    return max(z_far, 2.0 * config.radius_m)


def strata(config: DetectorConfig, intr, z_far_m: float, bin_px: int, grid_shape: tuple[int, int],
           visible_fraction: float = 1.0) -> tuple[int, int]:
    """The search's strata: (rows, columns) of cells; one first cell is drawn in each
    (``search_kernels.search_organised``).

    The standard RANSAC bound for the smallest ball the frame can hold: a ball of radius R at depth
    z_far shows a disc of r = fx R / (bin z_far) cells. A first cell on it gives a passing
    hypothesis with probability p = ``SAMPLE_SUCCESS``. With square strata of side s cells it is
    missed with probability prod_j (1 - p f_j), f_j the share of stratum j that the disc covers;
    the worst case over where the disc falls depends on s / r alone (``stratified_miss``), so
    s = k r with k the largest ratio whose worst case is within 1 - confidence
    (``stratum_side_ratio``: 0.89 for p = 0.8 and 99 %, where as many independent uniform draws as
    strata would need 0.74, nearly half as many draws again). With ``visible_fraction`` (the share of
    the ball provided for) below 1 the visible part is no disc, and the area bound is used instead:
    prod_j (1 - p f_j) <= exp(-p A / s^2), A the visible area, which holds for any shape. The number of strata is kept
    within [min_iterations, iterations] (about: strata are whole cells). Without ``adaptive``,
    ``iterations`` strata.
    """
    hc, wc = grid_shape
    cells = float(hc * wc)
    if config.search.adaptive:
        r = intr.fx / bin_px * config.radius_m / z_far_m
        if visible_fraction >= 1.0:
            side = stratum_side_ratio(SAMPLE_SUCCESS, config.search.confidence) * r
        else:
            area = math.pi * r * r * visible_fraction
            side = math.sqrt(SAMPLE_SUCCESS * area / -math.log1p(-config.search.confidence))
    else:
        side = math.sqrt(cells / config.search.iterations)
    search = config.search
    side = min(max(side, math.sqrt(cells / search.iterations)), math.sqrt(cells / max(search.min_iterations, 1)))
    s = max(1, int(side))
    return s, s


def stratified_miss(k: float, p: float, offsets: int = 9, samples: int = 256) -> float:
    """The worst case, over where a disc of radius 1 falls on a grid of square strata of side k, of the
    probability that one uniform draw per stratum never lands on the disc with a success (probability
    p per landing): max over offsets of prod_j (1 - p area(disc & stratum j) / k^2). Offsets on an
    offsets x offsets grid over a quarter stratum (the rest by symmetry); the areas by the midpoint
    rule over `samples` columns per stratum."""
    n = int(math.ceil(1.0 / k)) + 1
    j = np.arange(-n - 1, n + 1, dtype=np.float64)
    jx, jy = (a.ravel() for a in np.meshgrid(j, j, indexing="ij"))
    t = (np.arange(samples) + 0.5) / samples
    worst = 0.0
    for ox in np.linspace(0.0, 0.5 * k, offsets):
        x = (jx * k - ox)[:, None] + k * t[None, :]  # (strata, samples) column abscissae
        h = np.sqrt(np.clip(1.0 - x * x, 0.0, None))  # the disc's half-chord there
        for oy in np.linspace(0.0, 0.5 * k, offsets):
            y0 = (jy * k - oy)[:, None]
            chord = np.clip(np.minimum(y0 + k, h) - np.maximum(y0, -h), 0.0, None)
            share = chord.mean(axis=1) / k  # area / k^2
            worst = max(worst, float(np.prod(1.0 - p * share)))
    return worst


_SIDE_RATIOS: dict = {}


def stratum_side_ratio(p: float, confidence: float) -> float:
    """The largest k (stratum side / disc radius) whose ``stratified_miss`` is within 90 % of
    1 - confidence (the margin covers the offsets between the sampled ones); bisection, cached."""
    key = (float(p), float(confidence))
    if key not in _SIDE_RATIOS:
        lo, hi = 0.05, 2.0
        while hi - lo > 1e-3:
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if stratified_miss(mid, p) <= 0.9 * (1.0 - confidence) else (lo, mid)
        _SIDE_RATIOS[key] = lo
    return _SIDE_RATIOS[key]


#: Depth histogram of a frame (for the scene's far depth): bins of this many metres, up to 20 m.
HIST_STEP_M = 0.05
HIST_BINS = 400


def hist_percentile(hist: np.ndarray, q: float, step_m: float = HIST_STEP_M) -> float:
    """The q-th percentile (0-100) of the depths counted in hist (B,) (bins of step_m), to a bin's
    upper edge; nan when empty (``frame_kernels.hist_percentile``)."""
    return float(FK.hist_percentile(hist, float(q), float(step_m)))


_LOOKUPS: dict = {}


def cell_rows(bin_px: int) -> int:
    """Pixel rows of a cell that its table entry sums: all of them up to 2 x 2 cells; from 3 x 3 on,
    the middle one only (a cell's pixel count is then bin_px, ``frame_kernels.P_CELL_PX``). A box mean
    of n cells then averages bin_px n pixels instead of bin_px^2 n, and at 1280x720 one pixel's
    depth noise is a third of 424x240's: the search's box means stay more precise than at
    424x240, and the frame pass reads the depth of a third of the points (a third less time)."""
    return bin_px if bin_px < 3 else 1


def cell_lookup(h: int, w: int, bin_px: int) -> tuple[np.ndarray, np.ndarray]:
    """The table cell (1-based) of each pixel row (H,) and column (W,) int32, cached per size; rows
    the table leaves out (``cell_rows``) get -1."""
    key = (h, w, bin_px)
    if key not in _LOOKUPS:
        if len(_LOOKUPS) > 16:
            _LOOKUPS.clear()
        r = np.arange(h)
        row_cell = np.where((cell_rows(bin_px) == bin_px) | (r % bin_px == bin_px // 2), r // bin_px + 1, -1)
        _LOOKUPS[key] = (row_cell.astype(np.int32), (np.arange(w) // bin_px + 1).astype(np.int32))
    return _LOOKUPS[key]


class FrameNoise(NamedTuple):
    """A frame's measured depth noise: sigma_z / z^2 (1/m; None where not measured) and its
    correlation length (stream pixels; 0: independent pixels or not measured)."""

    a_measured: float | None
    corr_px: float


class PreparedFrame:
    """An organised cloud made ready for the kernels: index image, range integrals, parameters.

    One pass over the points (``frame_kernels.prepare_organised``); the buffers are reused between
    frames of one size. n_ok, n_big: finite points, and those with |z| beyond the millimetre limit.
    noise: the depth noise measured on the whole frame of which this cloud is a window (a window
    mostly of ball would mistake its curvature for noise), or None to measure the cloud's own.
    """

    def __init__(self, cloud: Cloud, config: DetectorConfig, noise: FrameNoise | None = None):
        intr = cloud.intrinsics
        h, w = int(intr.height), int(intr.width)
        self.cloud = cloud
        self.points = cloud.points
        self.bin = max(1, w // config.search.search_width_px)
        hc, wc = -(-h // self.bin), -(-w // self.bin)
        self.index_image = workspace("index", (h, w), np.int32)
        self.tab = workspace("tab", (hc + 1, wc + 1), np.uint64)
        self.hist = workspace("hist", (HIST_BINS,), np.int64)
        row_cell, col_cell = cell_lookup(h, w, self.bin)
        n_ok, n_big = FK.prepare_organised(cloud.points, cloud.rows, cloud.cols, self.index_image, self.tab, row_cell,
                                          col_cell, np.float32(MM_LIMIT_M), self.hist,
                                          np.float32(1.0 / HIST_STEP_M))
        self.n_ok, self.n_big = int(n_ok), int(n_big)
        self.n_valid = int(self.tab[-1, -1] >> np.uint64(FK.COUNT_SHIFT))  # the table's total count
        #: sigma_z / z^2 (1/m) the kernels use: noise_z2_per_m if set, else the frame's own where it
        #: differs from the model's by more than NOISE_MODEL_TOLERANCE, else the model's
        self.noise_a_measured = None
        lag_ms = None
        if noise is not None:
            self.noise_a_measured = noise.a_measured if config.noise.noise_z2_per_m is None else None
        elif config.noise.noise_z2_per_m is None and config.noise.noise_estimate:
            lag_ms = noise_mean_square(cloud.points, self.index_image, config,
                                        max(1, NOISE_ESTIMATE_LAG_PX * self.bin))
            self.noise_a_measured = None if lag_ms is None else math.sqrt(lag_ms)
        #: the depth noise's correlation length (stream pixels; 0: independent pixels or not measured)
        if noise is not None:
            self.noise_corr_px = noise.corr_px if config.noise.noise_correlation else 0.0
        else:
            self.noise_corr_px = (frame_noise_correlation_px(cloud.points, self.index_image, config, self.bin, lag_ms)
                                  if config.noise.noise_correlation else 0.0)
        #: what was measured, for a window of this frame (``noise``)
        self.noise = FrameNoise(self.noise_a_measured, self.noise_corr_px)
        model_a = noise_a(config, float(intr.fx))
        self.noise_a = model_a
        if self.noise_a_measured is not None and not (
                abs(self.noise_a_measured - model_a) <= NOISE_MODEL_TOLERANCE * model_a):
            self.noise_a = self.noise_a_measured
        #: the frame's measured noise over the sensor model's (1 where not measured)
        self.noise_ratio = 1.0 if self.noise_a_measured is None or not model_a > 0 else self.noise_a_measured / model_a
        self.z_far_m = far_depth_m(config, intr, hist_percentile(self.hist, 98.0), self.noise_a)
        self.stratum = strata(config, intr, self.z_far_m, self.bin, (hc, wc))
        #: first cells the search draws: one per stratum
        self.iterations = -(-hc // self.stratum[0]) * -(-wc // self.stratum[1])
        #: the plain search's (seed, passing hypotheses, counters), which ``search.relief_search`` ranks again
        self.passed = None
        self.prm = parameters(config, intr, self.stratum, self.bin, (hc, wc), self.z_far_m, self.noise_a,
                              self.noise_corr_px)
        # verification's size gate (``verification_kernels.verify_organised``: a candidate that fails the
        # size check stops before the costliest pass; the verdict reads every one that passes it) and its
        # output buffers
        fit = config.refinement
        self.gate = np.array([config.radius_tolerance_m if fit.size_check else math.inf, fit.size_sigmas], np.float64)
        #: no early stop (``rescore``: a start's whole score and size verdict count)
        self.no_gate = np.array([math.inf, fit.size_sigmas], np.float64)
