"""The improved pipeline: a box-mean search, refinement, size check, NMS, confidence.

Search (compiled, ``_kernels``), for an organised cloud: one pass builds the index image and a
summed-area table of the depth (mm) and of the valid count over cells of width // search_width_px
pixels (about ``search_width_px`` cells across), so that the mean range of any box (its mean depth
times the ray length) costs a few loads.
Each RANSAC iteration draws a first cell, one per stratum of the grid (strata of a few cells
a side, in raster order, the cell uniform within its stratum: ``strata``), and makes one hypothesis
from box means about it whose size follows the ball's image radius at that depth (``front_hypothesis``):
a descent to the local minimum of the range (the ball's front point, on the ray through its
centre), then an O(1) pretest (the four side boxes on the sphere's cap, the eight boxes around
the outline not continuing the surface). Raw three-point samples cannot place a ball beyond about
1.5 m at 424x240 (one pixel's depth noise exceeds the relief between two samples); box means of
n pixels have sigma / sqrt(n). The distinct survivors are kept by score. The strata's size is
the standard RANSAC bound for the smallest ball the frame can hold (``strata``).
(The paper's three-point samples in a ball diameter are here a five-box stencil about the first
pixel, and the known radius enters as the cap's curvature: a box-mean sample gives a centre only
when all its boxes lie inside the disc, the descent from anywhere on it. ``search_off_axis``
stretches the stencil as a silhouette off the optical axis is, ``_kernels.stencil_stretch``; off
by default.)
Unorganised clouds: three-point local samples in a spatial grid (``_kernels.search_unorganised``).

Verification (compiled, one call per candidate, best first, at most ``verify_candidates``, or
``verify_candidates_if_none`` while none is accepted, and none whose search score is more than
``verify_score_margin`` below an accepted one's):
Gauss-Newton with R fixed, re-selecting the inliers each round, for an organised cloud first on
||p - c|| - R (from a start some cm to the side, the ray residual of the rays that miss the
current sphere hardly moves the centre) and then on the depth residual along each pixel's ray
(the D435's noise is along the rays; the 3D residual pulls the centre toward the camera by
several mm at 2 m), and on ||p - c|| - R otherwise; a free-radius fit as the size check (a
candidate failing it, most of them, stops there); then the evidence of the whole silhouette (an
organised cloud shows where the ball should be): the share of its pixels that are inliers
(coverage), seen *through* (behind: a smaller ball or no ball), or hugged by a surface just in
front of the sphere (a cylinder of the same radius); and the confidence score that ranks
detections across frames, averaged over verifications from several starts for a candidate near
the threshold (``rescore``).
"""

from __future__ import annotations

import contextlib
import functools
import math
from statistics import NormalDist
import threading
from dataclasses import dataclass

import numpy as np

from spherebench.circles import norm3
from spherebench.cloud import Cloud
from spherebench.method import _kernels as K
from spherebench.method.config import DetectorConfig
from spherebench.method.verdict import load_verdict

# The stages' constants: how each stage works, not what the user sets (``DetectorConfig`` holds the
# physical facts and the error rates). Each was chosen on the training splits; the record is
# docs/experiments/2026-12-04-config-history.md and the records it points to.

# frame noise (``frame_noise_a``, ``frame_noise_correlation_px``)
NOISE_ESTIMATE_LAG_PX = 3  # second differences at this lag (px at 424 wide): beyond the matcher's correlation
NOISE_ESTIMATE_SAMPLES = 1024  # on at most this many evenly spread pixels
NOISE_ESTIMATE_MIN_SAMPLES = 128  # fewer qualifying: the sensor model's noise
NOISE_ESTIMATE_MIN_DEPTH_M = 0.6  # nearer pixels left out: their noise is below the depth quantisation
NOISE_ESTIMATE_KEEP = 0.9  # the trimmed mean square keeps the smallest 90 %: edges and flying pixels out
NOISE_MODEL_TOLERANCE = 0.10  # the measured noise replaces the model's when they differ by more than 10 %
NOISE_CORRELATION_MIN_PX = 0.8  # a shorter correlation length reads 0 (px at 424 wide): the estimate's scatter
NOISE_CORRELATION_MAX_PX = 3.0  # the longest taken (px at 424 wide)
NOISE_FROM_DATA = True  # the band narrows to a candidate's own residual spread where that is below the model's
MM_LIMIT_M = 50.0  # a cloud whose median |z| is beyond this is in millimetres (``input.mm_check``)

# search (``strata``, ``range_limit_m``; the stencil's geometry is ``_kernels``')
SAMPLE_SUCCESS = 0.8  # the chance that a first cell on the ball gives a hypothesis that passes the pretest
BOUND_NOISE_FRACTION = 0.75  # the bound provides for balls to where one pixel's noise is this * R ...
HYPOTHESIS_MIN_RANGE_M = 3.5  # ... and hypotheses are kept to at least this depth (m) on a noisy unit
SEARCH_CANDIDATES = 16  # hypotheses kept per search, by score
SAMPLE_RETRIES = 4  # unorganised: draws for the 2nd and 3rd point before giving up
PRETEST_POINTS = 12  # unorganised: points checked before a candidate is scored fully ...
PRETEST_MIN_FRACTION = 0.5  # ... of which this share must be inliers
SCORE_MAX_POINTS = 400  # unorganised: at most about this many points scored per candidate

# retries (organised frames where none is accepted: ``disc_search``, ``hole_search``)
RETRY_NEW_FRACTION = 0.25  # a retry's hypothesis this near (* R) a verified start is not verified again
DISC_NOISE_FRACTION = 0.25  # the disc search starts where one pixel's noise reaches this * R
DISC_INNER_FRACTION = 0.5  # its inner box's half-side (* r, the disc radius)
DISC_SIDE_OFFSET_FRACTION = 1.7  # its four side boxes' offset (* r): clear of the outline's mixed pixels
DISC_SIDE_HALF_FRACTION = 0.35  # their half-side (* r)
DISC_GAP_FRACTION = 1.0  # a side box is behind when farther than the inner box by R ...
DISC_GAP_SIGMAS = 3.0  # ... and 3 standard errors
DISC_MIN_BEHIND = 3  # at least 3 of the four side boxes behind (a ball on a floor has one not)
DISC_STEP_FRACTION = 0.5  # visit every k-th cell, k half the disc radius at max_range_m
HOLE_MIN_RING = 6  # of the eight directions from a hole cell, at least this many reach its ring
HOLE_MIN_FRACTION = 0.45  # the hole's mean radius at least this * r (smaller: blobs of dropout)
HOLE_STEP_FRACTION = 0.25  # visit every k-th cell, k this * the disc radius at max_range_m
HOLE_MIN_RANGE_M = 0.3  # the ring is looked for within the disc radius of a ball this near (m)

# verification (``_verify_candidates`` and the starts it verifies from)
VERIFY_SCORE_MARGIN = 6.0  # once one is accepted, skip hypotheses whose search score is this far below it
VERIFY_QUALITY_FRACTION = 0.15  # unorganised: skip candidates below this share of the best's quality
RESCORE_BAND = 0.15  # a candidate within this of accept_score is verified again from six starts
RESCORE_OFFSET_XY = 0.2  # the six starts' offsets across the line of sight (* R) ...
RESCORE_OFFSET_Z = 0.33  # ... and along it (* R)
MULTISTART_NOISE_FRACTION = 0.5  # while none is accepted, seven starts where one pixel's noise exceeds this * R
OCCLUDED_PUSH_FRACTION = 0.5  # an occluded hypothesis is verified again pushed back by this * R ...
OCCLUDED_PUSH_STARTS = 4  # ... from up to this many starts ...
OCCLUDED_PUSH_NOISE_FRACTION = 0.25  # ... where one pixel's noise is below this * R
INTERIOR_BANDS = 3.0  # unorganised: the interior lies at least this many bands under the surface
#: unorganised clouds' score map, probability = sigmoid(slope logit(product) + offset): the map last fitted
#: (train + train-stereo) for the organised clouds' hand-set product, which the fitted verdict replaced;
#: unorganised clouds have no silhouette for it (docs/detector.md, "Unorganised clouds")
UNORGANISED_CALIBRATION = (2.102, 2.018)

# outline (``outline_centre``, ``outline_size``, the outline's evidence)
OUTLINE_EVIDENCE_NOISE_FRACTION = 0.5  # verify again on the outline where one pixel's noise is this * R ...
OUTLINE_EVIDENCE_MIN_MOVE_PX = 0.25  # ... not where the outline moves the centre less (px) ...
OUTLINE_EVIDENCE_MIN_SCORE = 0.05  # ... nor where the first verification scores below this
OUTLINE_SIZE_FLOOR_PX = 0.25  # the outline radius's least standard error (px): mixed pixels, the grid
OUTLINE_GAP_SIGMAS = 3.0  # an outline is a step farther than max(this * sigma_z, R)
OUTLINE_BAND_PX = 2.0  # outline pixels within this (px) ...
OUTLINE_BAND_FRACTION = 0.15  # ... plus this share of the disc radius of the silhouette's outline
OUTLINE_MIN_SIDE = 4  # re-centre an axis with at least this many outline pixels on each side
OUTLINE_MAX_SHIFT_FRACTION = 0.5  # a re-centring moving the centre more than this * R is not taken
OUTLINE_MAX_BIAS_PX = 1.0  # nor on an axis whose sides lie on average this far off the silhouette (px)
OUTLINE_ITERATIONS = 3  # rounds of re-centring


@dataclass
class Candidate:
    """One verified sphere before it becomes a ``Sphere`` (indices into the searched points)."""

    centre_m: np.ndarray
    inliers: np.ndarray
    eps_m: float
    free_centre_m: np.ndarray
    free_radius_m: float
    free_radius_se_m: float
    rmse_m: float
    stats: dict
    score: float  # the probability of a ball (``verdict``)
    size_ok: bool
    raw_score: float  # the verdict's score before its calibration


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


def _noise_mean_square(points: np.ndarray, index_image: np.ndarray, config: DetectorConfig, lag: int) -> float | None:
    """The trimmed mean square of ``_kernels.noise_samples`` at a lag (pixels): sigma_z^2 / z^4 (1/m^2)
    for a lag beyond the noise's correlation; None with too few samples (see ``frame_noise_a``)."""
    h, w = index_image.shape
    step = max(1, int(math.sqrt(h * w / NOISE_ESTIMATE_SAMPLES)))
    out = workspace("noise", (NOISE_ESTIMATE_SAMPLES,), np.float64)
    m = K.noise_samples(points, index_image, lag, step, step, NOISE_ESTIMATE_MIN_DEPTH_M, out)
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
    below ``noise_correlation_min_px``.
    lag_ms: the mean square at the long lag, when already measured."""
    lag = max(1, NOISE_ESTIMATE_LAG_PX * bin_px)
    long_ms = _noise_mean_square(points, index_image, config, lag) if lag_ms is None else lag_ms
    short_ms = _noise_mean_square(points, index_image, config, 1)
    if long_ms is None or short_ms is None or not long_ms > 0:
        return 0.0
    length = correlation_from_ratio(short_ms / long_ms, lag, NOISE_CORRELATION_MAX_PX * bin_px)
    return length if length >= NOISE_CORRELATION_MIN_PX * bin_px else 0.0


@functools.lru_cache(maxsize=64)  # every verified candidate of a frame asks with the same arguments
def mean_variance_inflation(length_px: float, stride: int = 1) -> float:
    """How much more a mean over a large patch of pixels (every stride-th in both directions) varies
    than one over as many independent ones, for noise of correlation length ``length_px``: the sum
    of the autocorrelation over the lattice, (sum_k exp(-(k stride / length)^2))^2. 1 for
    independent pixels; pi length^2 / stride^2 for long lengths. Pixels over this count as one
    effective sample in the evidence tests."""
    if length_px <= 0.0:
        return 1.0
    t = max(int(stride), 1) / length_px
    one_axis = 1.0 + 2.0 * sum(math.exp(-(k * t) ** 2) for k in range(1, int(4.0 / t) + 2))
    return one_axis * one_axis


def frame_noise_a(points: np.ndarray, index_image: np.ndarray, config: DetectorConfig, bin_px: int) -> float | None:
    """The frame's own depth noise as sigma_z / z^2 (1/m), from second differences of depth along image
    rows (``_kernels.noise_samples``) on about ``noise_estimate_samples`` evenly spread pixels, by their
    trimmed mean square (the smallest ``noise_estimate_keep`` of them: edges, flying pixels and curved
    surfaces make the largest; rescaled to a normal's second moment); None when fewer than
    ``noise_estimate_min_samples`` pixels qualify (a frame too near, or mostly holes).

    The lag, ``noise_estimate_lag_px`` at 424 px wide, scales with the stream's width as the stereo
    matcher's noise correlation does, so that the second difference sees independent errors."""
    ms = _noise_mean_square(points, index_image, config, max(1, NOISE_ESTIMATE_LAG_PX * bin_px))
    return None if ms is None else math.sqrt(ms)


def eps_at(config: DetectorConfig, depth_m: float, fx: float | None) -> float:
    """The shell half-width at a centre depth (metres): eps widened by the depth noise model."""
    return float(K.noise_eps(depth_m, config.eps_m, noise_a(config, fx), config.noise.noise_sigmas,
                             K.MAX_EPS_FRACTION * config.radius_m))


def parameters(config: DetectorConfig, intr, stratum: tuple[int, int], bin_px: int, grid_shape: tuple,
               z_far_m: float, a: float | None = None, corr_px: float = 0.0) -> np.ndarray:
    """The float64 parameter vector (``_kernels.N_PRM``,) of the organised kernels; a: the frame's
    sigma_z / z^2 (1/m), by default the configuration's (``noise_a``); corr_px: the noise's correlation
    length (stream pixels), which widens the search's box-mean tolerances."""
    a = noise_a(config, float(intr.fx)) if a is None else a
    prm = np.zeros(K.N_PRM, np.float64)
    R = config.radius_m
    prm[K.P_R], prm[K.P_EPS], prm[K.P_NOISE_K] = R, config.eps_m, config.noise.noise_sigmas
    prm[K.P_FX], prm[K.P_FY], prm[K.P_PPX], prm[K.P_PPY] = intr.fx, intr.fy, intr.ppx, intr.ppy
    prm[K.P_NOISE_A] = a
    prm[K.P_EPS_CAP] = K.MAX_EPS_FRACTION * R
    prm[K.P_STRATUM_V], prm[K.P_STRATUM_U], prm[K.P_BIN] = stratum[0], stratum[1], bin_px
    prm[K.P_CELL_PX] = bin_px * cell_rows(bin_px)  # the pixels a cell's table entry sums
    # hypotheses whose ball would be beyond the range limit (with a margin; on a noisy unit never nearer than
    # hypothesis_min_range_m), or larger than the grid
    far_m = max(range_limit_m(config, float(intr.fx), a),
                min(HYPOTHESIS_MIN_RANGE_M, config.search.max_range_m))
    prm[K.P_RR_MIN] = 0.8 * intr.fx / bin_px * R / far_m
    prm[K.P_RR_MAX] = float(max(grid_shape))
    prm[K.P_Z_FAR] = z_far_m
    # a box of cells each bin_px wide: the correlation length in cells
    prm[K.P_MEAN_NOISE] = math.sqrt(mean_variance_inflation(corr_px / bin_px))
    return prm


def range_limit_m(config: DetectorConfig, fx: float | None, a: float | None = None) -> float:
    """The farthest centre depth the iteration bound provides for (metres): where the per-pixel
    depth noise reaches ``bound_noise_fraction`` R (3.5 m at 424x240, 4.9 m at 848x480, 6 m at
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
    """The search's strata: (rows, columns) of cells; one first cell is drawn in each (``_kernels.search_organised``).

    The standard RANSAC bound for the smallest ball the frame can hold: a ball of radius R at depth
    z_far shows a disc of r = fx R / (bin z_far) cells. A first cell on it gives a passing
    hypothesis with probability p = ``sample_success``. With square strata of side s cells it is
    missed with probability prod_j (1 - p f_j), f_j the share of stratum j that the disc covers;
    the worst case over where the disc falls depends on s / r alone (``stratified_miss``), so
    s = k r with k the largest ratio whose worst case is within 1 - confidence
    (``stratum_side_ratio``: 0.89 for p = 0.8 and 99 %, where as many independent uniform draws as
    strata would need 0.74, nearly half as many draws again). With ``visible_fraction`` (of the ball, provided for) below 1 the
    visible part is no disc, and the area bound is used instead: prod_j (1 - p f_j) <=
    exp(-p A / s^2), A the visible area, which holds for any shape. The number of strata is kept
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
    upper edge; nan when empty (``_kernels.hist_percentile``)."""
    return float(K.hist_percentile(hist, float(q), float(step_m)))


_WORKSPACE: dict = {}


def workspace(name: str, shape: tuple, dtype) -> np.ndarray:
    """A reused scratch array (contents undefined): a fresh multi-megabyte array per frame costs
    more in page faults than the kernels that fill it. One per (name, shape, dtype, thread)."""
    key = (name, shape, np.dtype(dtype).str, threading.get_ident())
    buf = _WORKSPACE.get(key)
    if buf is None:
        if len(_WORKSPACE) > 32:  # many resolutions or threads: start over rather than grow
            _WORKSPACE.clear()
        buf = _WORKSPACE[key] = np.empty(shape, dtype)
    return buf


_LOOKUPS: dict = {}


def cell_rows(bin_px: int) -> int:
    """Pixel rows of a cell that its table entry sums: all of them up to 2 x 2 cells; from 3 x 3 on,
    the middle one only (a cell's pixel count is then bin_px, ``_kernels.P_CELL_PX``). A box mean
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


class PreparedFrame:
    """An organised cloud made ready for the kernels: index image, range integrals, parameters.

    One pass over the points (``_kernels.prepare_organised``); the buffers are reused between
    frames of one size. n_ok, n_big: finite points, and those with |z| beyond the millimetre limit.
    """

    def __init__(self, cloud: Cloud, config: DetectorConfig):
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
        n_ok, n_big = K.prepare_organised(cloud.points, cloud.rows, cloud.cols, self.index_image, self.tab, row_cell,
                                          col_cell, np.float32(MM_LIMIT_M), self.hist,
                                          np.float32(1.0 / HIST_STEP_M))
        self.n_ok, self.n_big = int(n_ok), int(n_big)
        self.n_valid = int(self.tab[-1, -1] >> np.uint64(K.COUNT_SHIFT))  # the table's total count
        #: sigma_z / z^2 (1/m) the kernels use: noise_z2_per_m if set, else the frame's own where it
        #: differs from the model's by more than noise_model_tolerance, else the model's
        self.noise_a_measured = None
        lag_ms = None
        if config.noise.noise_z2_per_m is None and config.noise.noise_estimate:
            lag_ms = _noise_mean_square(cloud.points, self.index_image, config,
                                        max(1, NOISE_ESTIMATE_LAG_PX * self.bin))
            self.noise_a_measured = None if lag_ms is None else math.sqrt(lag_ms)
        #: the depth noise's correlation length (stream pixels; 0: independent pixels or not measured)
        self.noise_corr_px = (frame_noise_correlation_px(cloud.points, self.index_image, config, self.bin, lag_ms)
                              if config.noise.noise_correlation else 0.0)
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
        self.prm = parameters(config, intr, self.stratum, self.bin, (hc, wc), self.z_far_m, self.noise_a,
                              self.noise_corr_px)
        # verification's size/score gate (``_kernels.verify_organised``) and its output buffers: every
        # candidate that may rank (``rank_floor``) gets its whole evidence, and those within rescore_band
        # below accept_score too (``rescore``)
        # (the verdict reads every candidate the size check passes)
        fit = config.refinement
        self.gate = np.array([size_tolerance(config) if fit.size_check else math.inf, fit.size_sigmas], np.float64)
        #: no early stop (``rescore``: a start's whole score and size verdict count)
        self.no_gate = np.array([math.inf, fit.size_sigmas], np.float64)
        self.vout = np.empty(K.N_VOUT, np.float64)
        self.vstats = np.empty(K.N_STATS, np.float64)


def search_frame(frame: PreparedFrame, config: DetectorConfig, seed: int,
                 occluder_bound: bool = False, off_axis: bool = False,
                 relief: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Run the compiled organised search. Returns (candidate centres (M, 3), scores (M,), occluded (M,)
    bool: passed the pretest with a side hidden by an occluder, ``_kernels.front_hypothesis``), best first.
    occluder_bound: the descent leaves out side boxes in front of a cap (``_kernels.P_OCCLUDER_BOUND``);
    off_axis: the stencil follows the silhouette's stretch off the optical axis (``_kernels.stencil_stretch``);
    relief: the hypotheses ranked by how far their cap stands out of the noise (``_kernels._relief_llr``)."""
    hyp = np.zeros((SEARCH_CANDIDATES, 6), np.float64)
    counters = np.zeros(2, np.int64)
    prm = frame.prm
    if occluder_bound or off_axis or relief:
        prm = prm.copy()
        if occluder_bound:
            prm[K.P_OCCLUDER_BOUND] = 1.0
        if off_axis:
            prm[K.P_OFF_AXIS] = 1.0
        if relief:
            prm[K.P_ORDER_RELIEF] = 1.0
    m = K.search_organised(frame.tab, prm, np.uint64(seed), hyp, counters)
    frame.counters = counters  # diagnostics (see _kernels.search_organised)
    frame.hypotheses = hyp[:m]
    centres = K.cell_centres(frame.prm, hyp[:m])
    return centres, hyp[:m, 4].copy(), hyp[:m, 5] > 0.0


def disc_search(frame: PreparedFrame, config: DetectorConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Run ``_kernels.disc_hypotheses`` on the frame beyond the depth where one pixel's noise reaches
    ``disc_noise_fraction`` R; returns ``search_frame``'s (centres (M, 3), scores (M,), occluded (M,))."""
    R = config.radius_m
    z_min = math.sqrt(DISC_NOISE_FRACTION * R / frame.noise_a) if frame.noise_a > 0 else math.inf
    fc = frame.prm[K.P_FX] / frame.bin
    step = max(1, int(DISC_STEP_FRACTION * fc * R / config.search.max_range_m))
    hyp = np.zeros((SEARCH_CANDIDATES, 6), np.float64)
    retry = config.retry
    m = K.disc_hypotheses(frame.tab, frame.prm, z_min, DISC_INNER_FRACTION, DISC_SIDE_OFFSET_FRACTION,
                          DISC_SIDE_HALF_FRACTION, DISC_GAP_FRACTION * R, DISC_GAP_SIGMAS, DISC_MIN_BEHIND, step, hyp)
    frame.hypotheses = hyp[:m]
    return K.cell_centres(frame.prm, hyp[:m]), hyp[:m, 4].copy(), np.zeros(m, bool)


def hole_search(frame: PreparedFrame, config: DetectorConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Run ``_kernels.hole_hypotheses`` on the frame (every ``hole_step_fraction`` of a far ball's disc);
    returns ``search_frame``'s (centres (M, 3), scores (M,), occluded (M,))."""
    R = config.radius_m
    fc = frame.prm[K.P_FX] / frame.bin
    retry = config.retry
    step = max(1, int(HOLE_STEP_FRACTION * fc * R / config.search.max_range_m))
    hyp = np.zeros((SEARCH_CANDIDATES, 6), np.float64)
    m = K.hole_hypotheses(frame.tab, frame.prm, HOLE_MIN_RANGE_M, step, HOLE_MIN_RING, HOLE_MIN_FRACTION, hyp)
    frame.hypotheses = hyp[:m]
    return K.cell_centres(frame.prm, hyp[:m]), hyp[:m, 4].copy(), np.zeros(m, bool)


def search_unorganised(points: np.ndarray, config: DetectorConfig, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Run the compiled unorganised search. Returns (candidate centres (M, 3), qualities (M,))."""
    k = max(2 * config.verification.max_spheres, 4)
    cands = np.zeros((k, 3), np.float64)
    quals = np.zeros(k, np.float64)
    grid = build_grid(points, config.local_radius_m)
    win = config.local_radius_m if config.search.sampling == "local" else math.inf
    s = config.search
    _, m = K.search_unorganised(points, grid["order"], grid["keys"], grid["origin"], grid["cell"], grid["dims"],
                                config.radius_m, config.eps_m, win, s.iterations, s.min_iterations, s.confidence,
                                SAMPLE_RETRIES, PRETEST_POINTS, PRETEST_MIN_FRACTION, SCORE_MAX_POINTS,
                                np.uint64(seed), cands, quals)
    return cands[:m], quals[:m]


def build_grid(points: np.ndarray, cell_m: float) -> dict:
    """A uniform grid over the points: order (N,) sorts them by cell key keys (N,) (int64)."""
    lo = points.min(axis=0).astype(np.float64)
    hi = points.max(axis=0).astype(np.float64)
    dims = np.maximum(np.ceil((hi - lo) / cell_m).astype(np.int64), 1)
    # a huge, sparse extent would overflow the linear key: coarsen the cell until it fits
    while float(np.prod(dims.astype(np.float64))) > 2.0 ** 62:
        cell_m *= 2.0
        dims = np.maximum(np.ceil((hi - lo) / cell_m).astype(np.int64), 1)
    keys = K.grid_keys(points, lo, cell_m, dims)
    order = np.argsort(keys, kind="stable")
    return {"order": order, "keys": keys[order], "origin": lo, "cell": float(cell_m), "dims": dims}


_STAT_NAMES = {"valid_disc": K.ST_VALID_DISC, "inlier": K.ST_INLIER, "front": K.ST_FRONT,
               "front_near": K.ST_FRONT_NEAR, "behind": K.ST_BEHIND, "invalid_disc": K.ST_INVALID_DISC,
               "ring": K.ST_RING, "ring_continued": K.ST_RING_CONT, "ring_front": K.ST_RING_FRONT,
               "valid_inner": K.ST_VALID_INNER, "behind_inner": K.ST_BEHIND_INNER,
               "edge_n": K.ST_EDGE_N, "edge_behind": K.ST_EDGE_BEHIND, "ring_spread": K.ST_RING_SPREAD,
               "inner_n": K.ST_IN_N, "inner_sum": K.ST_IN_SUM,
               "outer_h_n": K.ST_OUTH_N, "outer_h_sum": K.ST_OUTH_SUM, "outer_v_n": K.ST_OUTV_N,
               "outer_v_sum": K.ST_OUTV_SUM}


def size_tolerance(config: DetectorConfig) -> float:
    """The size check's tolerance before standard errors (metres): the larger of the absolute and the
    relative one (``DetectorConfig.refinement.size_tolerance_fraction``)."""
    return max(config.refinement.size_tolerance_m, config.refinement.size_tolerance_fraction * config.radius_m)


def size_ok(free_r: float, free_se: float, config: DetectorConfig) -> bool:
    """The size check: the free radius free_r (m) within the tolerance plus ``size_sigmas`` of its
    standard error free_se (m; R standing in for an unknown one) of R, and never beyond
    ``_kernels.SIZE_LIMIT_FRACTION`` R whatever the error says; True without ``size_check``."""
    if not config.refinement.size_check:
        return True
    R = config.radius_m
    se = free_se if math.isfinite(free_se) else R
    d = abs(free_r - R)
    return bool(math.isfinite(free_r) and d <= size_tolerance(config) + config.refinement.size_sigmas * se
                and d <= K.SIZE_LIMIT_FRACTION * R)


def unorganised_score(stats: dict, n_inliers: int, free_r: float, free_se: float, config: DetectorConfig) -> float:
    """An unorganised cloud's score in [0, 1]: no image, so no silhouette for the fitted verdict to
    read. The product of the support n / (n + min_inliers), the interior's emptiness
    (1 - min(1, q))^2, q the density of points in the ball's inner half over that in its shell (a
    wall it cuts, volumetric noise: a real ball hides its interior), and the size's agreement
    exp(-d^2 / 2), d the free radius's deviation from R in units of the tolerance plus its standard
    error; mapped by the logistic map fitted to the hand-set product on organised candidates
    (``UNORGANISED_CALIBRATION``). Hand-set: docs/detector.md, "Unorganised clouds"."""
    score = n_inliers / (n_inliers + config.verification.min_inliers)
    if "interior_density_ratio" in stats:
        score *= (1.0 - min(1.0, stats["interior_density_ratio"])) ** 2
    if config.refinement.size_check:
        se = free_se if math.isfinite(free_se) else config.radius_m
        d = (free_r - config.radius_m) / (size_tolerance(config) + se) if math.isfinite(free_r) else math.inf
        score *= math.exp(-0.5 * d * d) if math.isfinite(d) else 0.0
    score = min(max(score, 0.0), 1.0)
    if score <= 0.0 or score >= 1.0:
        return float(score)
    slope, offset = UNORGANISED_CALIBRATION
    return 1.0 / (1.0 + math.exp(-(slope * math.log(score / (1.0 - score)) + offset)))


def verify_organised(frame: PreparedFrame, c0: np.ndarray, config: DetectorConfig, buf: np.ndarray,
                     gate: np.ndarray | None = None, hold_direction: bool = False) -> Candidate | None:
    """Refine one candidate of an organised cloud, measure its evidence, fit the free radius, score it.
    Where one pixel's noise at the refined centre is at least ``outline_evidence_noise_fraction`` R
    (``DetectorConfig.outline.outline_evidence``), the candidate is then re-centred on its outline and
    verified again from there with its direction held: the cap's relief leaves the refined centre a
    pixel or more beside the ball, and the evidence is taken where the outline says the ball is.
    gate: the kernel's early stop (default ``frame.gate``). hold_direction: no refinement, and the
    fits move the centre along its ray only (``_kernels.fit_range``)."""
    v = _verify_once(frame, c0, config, buf, gate, hold_direction)
    if (v is None or hold_direction or not config.outline.outline_evidence or v.score < OUTLINE_EVIDENCE_MIN_SCORE
            or frame.noise_a * float(v.centre_m[2]) ** 2 < OUTLINE_EVIDENCE_NOISE_FRACTION * config.radius_m):
        return v
    oc = outline_centre(frame, v.centre_m, config)
    size = outline_size(frame, oc, config) if config.outline.outline_size else None
    # a move within a fraction of a pixel reclassifies few of the silhouette's pixels
    if size is None and (float(np.linalg.norm(oc - v.centre_m)) * frame.prm[K.P_FX] / float(oc[2])
                         < OUTLINE_EVIDENCE_MIN_MOVE_PX):
        return v
    # the kernel's early stop judges the depth fit's radius, which the outline's replaces
    return _verify_once(frame, oc, config, buf, gate if size is None else frame.no_gate, True, size)


def _outline_buffers(frame: PreparedFrame, rho: float, config: DetectorConfig) -> tuple[np.ndarray, np.ndarray]:
    """``_kernels.outline_residuals``' buffers for a sphere at distance rho (m): a quarter of the outline
    holds at most two pairs per pixel of the kernel's window; the capacity is rounded up to a power of
    two, so that balls of every size share a few reused buffers."""
    r_px = float(frame.prm[K.P_FX]) * math.tan(math.asin(config.radius_m / rho))
    side = 2 * int(r_px + OUTLINE_BAND_PX + OUTLINE_BAND_FRACTION * r_px + 3) + 1
    return (workspace("outline_res", (4, 1 << (2 * side * side - 1).bit_length()), np.float64),
            workspace("outline_count", (4,), np.int64))


def outline_size(frame: PreparedFrame, centre_m: np.ndarray, config: DetectorConfig) -> tuple[float, float] | None:
    """The angular radius (rad) of the silhouette's outline about centre_m (3,) m, and its standard
    error: the sphere's cone half-angle asin(R / |c|) plus the mean of the four quarters' median
    residuals (``_kernels.outline_residuals``; about a centre on the outline, their difference is
    the centre's error, their mean the silhouette's size against the sphere's). The standard error
    is the pooled residuals' (normal-consistent MAD, as a median over all pairs) with
    ``outline_size_floor_px`` added in quadrature (mixed pixels and the outline's pixel grid). None
    unless every quarter holds ``outline_min_side`` pairs: a ball on a floor or against a wall has
    a side whose steps are not its outline."""
    c = np.asarray(centre_m, np.float64)
    rho = float(np.linalg.norm(c))
    if not (c[2] > 0 and rho > config.radius_m):
        return None
    res, count = _outline_buffers(frame, rho, config)
    K.outline_residuals(frame.points, frame.index_image, frame.prm, c[0], c[1], c[2], frame.noise_a * float(c[2]) ** 2,
                        OUTLINE_GAP_SIGMAS, OUTLINE_BAND_PX, OUTLINE_BAND_FRACTION, res, count)
    if int(count.min()) < OUTLINE_MIN_SIDE:
        return None
    pooled = np.concatenate([res[q, :count[q]] for q in range(4)])
    spread = 1.4826 * float(np.median(np.abs(pooled - np.median(pooled))))
    angle = math.asin(config.radius_m / rho) + float(np.mean([np.median(res[q, :count[q]]) for q in range(4)]))
    se = math.hypot(1.2533 * spread / math.sqrt(pooled.size), OUTLINE_SIZE_FLOOR_PX / float(frame.prm[K.P_FX]))
    return angle, se


#: a constant standing in for the fitted verdict's probability (``unscored``); None: the verdict's
_UNSCORED: list[float] = []


@contextlib.contextmanager
def unscored(score: float = 0.5):
    """Within it, every organised candidate of this thread's process scores ``score`` (raw and
    probability) in place of the fitted verdict's, so that no model steers which candidates are
    verified and kept: with accept_score 1 nothing is accepted and every search and retry runs
    (``make train-verifier`` collects its candidates so)."""
    _UNSCORED.append(float(score))
    try:
        yield
    finally:
        _UNSCORED.pop()


def verdict(stats: dict, radius_m: float) -> tuple[float, float]:
    """(raw score, probability) of one verified candidate: the fitted verdict's
    (``verdict.FittedVerdict.scores``), or ``unscored``'s constant."""
    if _UNSCORED:
        return _UNSCORED[-1], _UNSCORED[-1]
    return load_verdict().scores(stats, radius_m)


def _verify_once(frame: PreparedFrame, c0: np.ndarray, config: DetectorConfig, buf: np.ndarray,
                 gate: np.ndarray | None, hold_direction: bool,
                 size: tuple[float, float] | None = None) -> Candidate | None:
    """One pass of the verification kernel (``_kernels.verify_organised``) from c0, scored. size: the
    outline's angular radius and its standard error (``outline_size``), which then give the size
    check's radius in place of the depth fit's (at the verified centre's distance)."""
    out, st = frame.vout, frame.vstats  # reused per candidate: what is kept is copied out below
    K.verify_organised(frame.points, frame.index_image, np.asarray(c0, np.float64), frame.prm,
                       config.refinement.refine_iterations, K.FIT_MAX_POINTS,
                       K.RAY_S_MIN_FRACTION, NOISE_FROM_DATA,
                       frame.gate if gate is None else gate, hold_direction, buf, out, st)
    n = int(out[K.V_N])
    if n < config.verification.min_inliers:  # too few, or failed the size check (-1)
        return None
    stats = {k: float(st[j]) for k, j in _STAT_NAMES.items()}
    # pixels per effective sample of the evidence's counts and zone means: the window's stride
    # (``_kernels.window_stride``, as the kernel took it) against the noise's correlation length
    cz = float(out[K.V_CZ])
    stride = K.window_stride(float(out[K.V_CX]), float(out[K.V_CY]), cz, config.radius_m * K.RING_FACTOR,
                             max(frame.prm[K.P_FX], frame.prm[K.P_FY]), 4.0 * K.FIT_MAX_POINTS)
    stats["pixels_per_sample"] = mean_variance_inflation(frame.noise_corr_px, int(stride))
    # the relief test's per-pixel noise: the model's, not the measured one (which only narrows the band): the
    # test treats pixels as independent, and a sensor whose errors are correlated (a structured-light sensor's
    # quantisation steps) would otherwise fail a real ball's zone means by a few mm
    stats["sigma_m"] = frame.prm[K.P_NOISE_A] * float(out[K.V_CZ]) ** 2
    stats["sigma_measured_m"] = float(out[K.V_SIGMA])
    stats["eps_m"] = float(out[K.V_EPS])
    # the share of the silhouette's pixels with depth that no nearer surface hides (an occluder: more
    # than R / 2 in front of the sphere; ``_kernels.window_stats``' FRONT less FRONT_NEAR)
    vd = stats["valid_disc"]
    stats["visible_fraction"] = 1.0 - max(0.0, stats["front"] - stats["front_near"]) / vd if vd > 0 else 0.0
    free_r, free_se = float(out[K.V_FR]), float(out[K.V_FSE])
    if size is not None:
        rho = float(np.linalg.norm(out[K.V_CX:K.V_CZ + 1]))
        free_r, free_se = rho * math.sin(size[0]), rho * math.cos(size[0]) * size[1]
    stats.update(depth_m=cz, n_inliers=float(n), rmse_m=float(out[K.V_RMSE]), free_radius_m=free_r,
                 free_radius_se_m=free_se, noise_ratio=frame.noise_ratio)
    raw, score = verdict(stats, config.radius_m)
    # inliers: filled in for the reported spheres only (``_kernels.final_inliers``)
    return Candidate(centre_m=out[K.V_CX:K.V_CZ + 1].copy(), inliers=buf[:0].copy(), eps_m=float(out[K.V_EPS]),
                     free_centre_m=out[K.V_FCX:K.V_FCZ + 1].copy(), free_radius_m=free_r,
                     free_radius_se_m=free_se, rmse_m=float(out[K.V_RMSE]), stats=stats, score=score,
                     size_ok=size_ok(free_r, free_se, config), raw_score=raw)


#: ``rescore``'s six starts about a refined centre (units of R): across the line of sight (camera x and y)
#: and along it (z), where the refinement's optima lie a cm or two apart at 2-3 m
RESCORE_STARTS = ((RESCORE_OFFSET_XY, 0.0, 0.0), (-RESCORE_OFFSET_XY, 0.0, 0.0), (0.0, RESCORE_OFFSET_XY, 0.0),
                  (0.0, -RESCORE_OFFSET_XY, 0.0), (0.0, 0.0, RESCORE_OFFSET_Z), (0.0, 0.0, -RESCORE_OFFSET_Z))


def verify_multistart(frame: PreparedFrame, c0: np.ndarray, config: DetectorConfig,
                      buf: np.ndarray) -> Candidate | None:
    """A hypothesis whose depth noise is a good part of R (``multistart_noise_fraction``), verified from
    its centre and from each of ``RESCORE_STARTS`` about it: where one pixel's noise nears R, the
    refinement's end depends on its start by a few cm, and a hypothesis a few cm off converges
    off the ball's optimum. The best-scoring verification that passes the size check is kept."""
    best = None
    for off in ((0.0, 0.0, 0.0),) + RESCORE_STARTS:
        v = verify_organised(frame, c0 + config.radius_m * np.asarray(off), config, buf)
        if v is not None and v.size_ok and (best is None or v.score > best.score):
            best = v
    return best


def verify_pushed(frame: PreparedFrame, c0: np.ndarray, config: DetectorConfig,
                  buf: np.ndarray) -> Candidate | None:
    """A hypothesis that passed the search's pretest by an occluded side, verified from its centre and,
    while that fails, from starts pushed back along its ray (``OCCLUDED_PUSH_FRACTION`` R each, at most
    ``OCCLUDED_PUSH_STARTS``, only where one pixel's noise is below ``OCCLUDED_PUSH_NOISE_FRACTION`` R):
    the occluder's pixels in its centre box pull the front range, and the start, towards the camera,
    by up to the occluder's gap. The first verification that passes the size check within
    ``RESCORE_BAND`` of accept_score is returned, else the best that passes it (the first of equals),
    else the last."""
    R = config.radius_m
    ray = c0 / max(norm3(c0), 1e-9)
    quiet = frame.prm[K.P_NOISE_A] * c0[2] ** 2 < OCCLUDED_PUSH_NOISE_FRACTION * R
    v = best = None
    for j in range(1 + (OCCLUDED_PUSH_STARTS if quiet else 0)):
        v = verify_organised(frame, c0 + j * OCCLUDED_PUSH_FRACTION * R * ray, config, buf)
        if v is not None and v.size_ok:
            if v.score >= config.verification.accept_score - RESCORE_BAND:
                return v
            best = v if best is None or v.score > best.score else best
    return best if best is not None else v


def rescore(frame: PreparedFrame, cand: Candidate, config: DetectorConfig, buf: np.ndarray) -> Candidate:
    """A candidate near the score threshold, verified again from each of ``RESCORE_STARTS`` about its centre
    (without the kernel's early stop, so that each start's whole score and size verdict count): its
    score becomes the mean of all (a start left with too few inliers counts 0) and its size check
    the majority's. The centre, evidence and fits stay the first verification's; stats gets
    "score_single", the first score (see ``RESCORE_BAND``); the raw score is averaged alike."""
    scores, raws = [cand.score], [cand.raw_score]
    size_ok = [cand.size_ok]
    for off in RESCORE_STARTS:
        v = verify_organised(frame, cand.centre_m + config.radius_m * np.asarray(off), config, buf, frame.no_gate)
        scores.append(0.0 if v is None else v.score)
        raws.append(0.0 if v is None else v.raw_score)
        size_ok.append(v is not None and v.size_ok)
    cand.stats["score_single"] = cand.score
    cand.score, cand.raw_score = float(np.mean(scores)), float(np.mean(raws))
    cand.size_ok = 2 * sum(size_ok) > len(size_ok)
    return cand


def verify_unorganised(points: np.ndarray, c0: np.ndarray, config: DetectorConfig) -> Candidate | None:
    """Refine one candidate of an unorganised cloud (3D residuals over the whole cloud), fit, score."""
    R = config.radius_m
    e = config.eps_m
    buf = np.empty(len(points), np.int64)
    c = np.asarray(c0, np.float64).copy()
    idx = buf[:0]
    for _ in range(config.refinement.refine_iterations):
        n = K.shell_indices(points, c[0], c[1], c[2], R, e, buf)
        if n < 3:
            break
        idx = buf[:n]
        c_new = K.refine_fixed_radius(points, idx, c[0], c[1], c[2], R, 3)
        moved = float(np.linalg.norm(c_new - c))
        c = c_new
        if moved < 1e-5:
            break
    n = K.shell_indices(points, c[0], c[1], c[2], R, e, buf)
    if n < config.verification.min_inliers:
        return None
    idx = buf[:n].copy()
    free_c, free_r, free_se, _ = K.fit_free_radius(points, idx, c[0], c[1], c[2], R, 8)
    res = np.linalg.norm(points[idx].astype(np.float64) - c, axis=1) - R
    rmse = float(np.sqrt(np.mean(res * res)))
    # a ball hides its interior: points in its inner half (and ``interior_bands`` shell half-widths under
    # its surface) are another surface the sphere cuts (a wall, clutter) or volumetric noise; a noisy
    # sensor's returns off the ball itself do not reach that deep (a 16-beam LiDAR's do 3 cm deep)
    r_in = min(R - INTERIOR_BANDS * e, 0.5 * R)
    inside = float(K.inside_count(points, c[0], c[1], c[2], r_in)) if r_in > 0 else 0.0
    v_shell = (R + e) ** 3 - max(R - e, 0.0) ** 3  # volumes / (4 pi / 3)
    stats = {"inside": inside, "shell": float(n),
             "interior_density_ratio": (inside / max(r_in, 1e-12) ** 3) / (n / v_shell) if r_in > 0 else 0.0}
    score = unorganised_score(stats, n, float(free_r), float(free_se), config)
    return Candidate(centre_m=c, inliers=idx, eps_m=e, free_centre_m=np.asarray(free_c), free_radius_m=float(free_r),
                     free_radius_se_m=float(free_se), rmse_m=rmse, stats=stats, score=score,
                     size_ok=size_ok(float(free_r), float(free_se), config), raw_score=score)


def outline_centre(frame: PreparedFrame, centre_m: np.ndarray, config: DetectorConfig) -> np.ndarray:
    """A sphere's centre (3,) m moved across the line of sight onto its outline, its range kept.

    Where one pixel's depth noise nears R, the cap's relief places the centre laterally to several
    mm; the outline against a background farther behind is a sharp depth step
    (``_kernels.outline_residuals``: 4-neighbour pairs of a pixel at the ball's depths and one
    behind, near the current outline and stepping outward, each with its angular residual, the
    angle to the centre's ray minus the cone's half-angle) that places it to about a millimetre at
    2-3 m. Per image axis, the pairs within 45 degrees of each of its two directions give their
    median residual; half the difference of the two is the shift along that axis
    (``_kernels.outline_centre``), which a silhouette uniformly a pixel larger or smaller than the
    sphere's (mixed pixels, edge fattening) leaves alone. An axis with fewer than
    ``outline_min_side`` pairs on either side (a ball on a floor or against a wall there, the stereo
    shadow) keeps its centre; a move beyond ``outline_max_shift_fraction`` R is not taken."""
    c_in = np.asarray(centre_m, np.float64)
    R = config.radius_m
    rho = float(np.linalg.norm(c_in))
    if not (c_in[2] > 0 and rho > R):
        return c_in
    res, count = _outline_buffers(frame, rho, config)
    out = np.empty(3, np.float64)
    K.outline_centre(frame.points, frame.index_image, frame.prm, c_in, frame.noise_a * float(c_in[2]) ** 2,
                     OUTLINE_GAP_SIGMAS, OUTLINE_BAND_PX, OUTLINE_BAND_FRACTION, OUTLINE_MIN_SIDE,
                     OUTLINE_MAX_BIAS_PX, OUTLINE_ITERATIONS, res, count, out)
    if float(np.linalg.norm(out - c_in)) > OUTLINE_MAX_SHIFT_FRACTION * R:
        return c_in
    return out


def _verify_candidates(points: np.ndarray, frame: PreparedFrame | None, cands: np.ndarray, quals: np.ndarray,
                       occluded: np.ndarray, config: DetectorConfig, buf: np.ndarray | None,
                       found: list[Candidate], ranked: list[Candidate], limit_none: int | None = None,
                       multistart: bool = True) -> list[np.ndarray]:
    """Verify the search's candidates (M, 3) m, best first, appending the accepted ones
    (``accept_score``) to ``found`` and the others that pass the size check and may rank
    (``rank_floor``) to ``ranked``; returns the starts verified. While none is accepted, an
    organised frame verifies up to
    ``verify_candidates_if_none`` (or ``limit_none``), and the hypotheses that passed the search's
    pretest only by an occluded side: a frame with a ball pays nothing for either. multistart: a
    noisy hypothesis is verified from several starts while none is accepted (``verify_multistart``)."""
    if limit_none is None:
        ver = config.verification
        limit_none = max(ver.verify_candidates, ver.verify_candidates_if_none if frame is not None else 0)
    q_accepted = -math.inf  # the best search score among the accepted
    verified: list[np.ndarray] = []
    for k, (c0, q) in enumerate(zip(cands, quals)):
        if k >= (config.verification.verify_candidates if found else limit_none):
            break
        if found and occluded[k]:
            continue
        # organised: hypotheses are sorted by score; those far below every accepted sphere's are clutter
        if frame is not None and q < q_accepted - VERIFY_SCORE_MARGIN:
            break
        # unorganised: candidates far below the best cannot win, verifying them would only cost time
        if frame is None and q < VERIFY_QUALITY_FRACTION * quals[0]:
            break
        # a start within R of a sphere already accepted converges onto it, and would be suppressed
        if any(math.dist(c0, v.centre_m) < config.radius_m for v in found):
            continue
        verified.append(c0)
        if frame is None:
            v = verify_unorganised(points, c0, config)
        elif (multistart and not found and frame.prm[K.P_NOISE_A] * c0[2] ** 2
              > MULTISTART_NOISE_FRACTION * config.radius_m):
            # while none is accepted (a frame with a ball pays nothing, and gets no second sphere this
            # way); the best of several starts is a biased draw: its score is always re-taken as the mean
            v = verify_multistart(frame, np.asarray(c0, np.float64), config, buf)
            v = rescore(frame, v, config, buf) if v is not None else None
        else:
            # a hypothesis with an occluded side (verified only while none is accepted): pushed back too
            v = (verify_pushed(frame, np.asarray(c0, np.float64), config, buf) if occluded[k]
                 else verify_organised(frame, c0, config, buf))
            if v is not None and abs(v.score - config.verification.accept_score) < RESCORE_BAND:
                v = rescore(frame, v, config, buf)
        if v is None or not v.size_ok or v.score < config.verification.rank_floor:
            continue
        if v.score < config.verification.accept_score:
            ranked.append(v)  # ranked, but the search goes on as if it were not there
            continue
        found.append(v)
        q_accepted = max(q_accepted, float(q))
    return verified


def run_improved(points: np.ndarray, frame: PreparedFrame | None, config: DetectorConfig,
                 seed: int, min_score: float | None = None, max_spheres: int | None = None) -> list[Candidate]:
    """Search, verify the best candidates, drop the failed ones, suppress duplicates. Best first.

    frame: the prepared organised cloud, or None to treat ``points`` (N, 3) as unorganised.
    The search and its verdicts are the same whatever is reported: the distinct verified spheres
    whose score is at least min_score (default ``verification.min_score``, never below ``rank_floor``),
    at most max_spheres (default ``verification.max_spheres``), are returned.
    """
    ver = config.verification
    least = max(ver.min_score if min_score is None else min_score, ver.rank_floor)
    most = ver.max_spheres if max_spheres is None else max_spheres
    if frame is not None:
        cands, quals, occluded = search_frame(frame, config, seed)
        # gather_window's index buffer: one silhouette's pixels at most. Sized by the image, not the
        # cloud, so that frames of one stream reuse it (a fresh 7 MB buffer per 1280x720 frame cost
        # more in page faults than the detection)
        buf = workspace("inliers", (frame.index_image.size + 1,), np.int64)
    else:
        cands, quals = search_unorganised(points, config, seed)
        occluded = np.zeros(len(cands), bool)
        buf = None
    found: list[Candidate] = []
    ranked: list[Candidate] = []
    verified = _verify_candidates(points, frame, cands, quals, occluded, config, buf, found, ranked)
    # organised frames where none is accepted: search again, the descent past occluders, then the
    # stencil stretched off the axis, then for discs standing out of their background, then for holes
    # ringed by a ball's face, and verify the hypotheses not verified before
    retries = [] if frame is None else (
        ([lambda: search_frame(frame, config, seed, relief=True)] if config.retry.retry_relief else [])
        + ([lambda: search_frame(frame, config, seed, occluder_bound=True)] if config.retry.retry_occluder else [])
        + ([lambda: search_frame(frame, config, seed, off_axis=True)]
           if config.retry.retry_off_axis and not False else [])
        + ([lambda: disc_search(frame, config)] if config.retry.retry_disc else [])
        + ([lambda: hole_search(frame, config)] if config.retry.retry_hole else []))
    for retry in retries:
        if found:  # a frame with a ball found pays nothing for the retries
            break
        cands, quals, occluded = retry()
        new = [k for k, c in enumerate(cands)
               if all(math.dist(c, c1) > RETRY_NEW_FRACTION * config.radius_m for c1 in verified)]
        # the best verify_candidates of a retry's new hypotheses, each verified from one start: on `train`
        # 16, or the multistart of noisy ones, found about as many balls, at twice the time on an empty frame
        verified += _verify_candidates(points, frame, cands[new], quals[new], occluded[new], config, buf, found,
                                       ranked, limit_none=config.verification.verify_candidates, multistart=False)
    # suppression before the cut, so that the spheres reported at any threshold are those above it at
    # the floor: a sphere is only ever suppressed by a better one
    kept: list[Candidate] = []
    min_sep = config.verification.nms_distance_fraction * 2.0 * config.radius_m
    for v in sorted(found + ranked, key=lambda v: -v.score):
        if v.score < least or len(kept) == most:
            break
        if all(math.dist(v.centre_m, k.centre_m) >= min_sep for k in kept):
            kept.append(v)
    if frame is not None:
        for v in kept:
            # where the noise nears R, the outline places the centre across the line of sight
            if frame.noise_a * float(v.centre_m[2]) ** 2 >= config.outline.outline_noise_fraction * config.radius_m:
                v.centre_m = outline_centre(frame, v.centre_m, config)
            # verification visited strided windows: collect every inlier of the reported ones
            n, v.rmse_m = K.final_inliers(frame.points, frame.index_image, v.centre_m, frame.prm, v.eps_m, buf)
            v.inliers = buf[:n].copy()
    return kept
