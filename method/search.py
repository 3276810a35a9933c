"""Stage 2, the search (organised clouds): hypotheses of ball centres from box means of depth.

One RANSAC draw per stratum of the cell grid (strata a few cells a side, in raster order, sized
by the standard bound for the smallest ball the frame can hold: ``strata``) gives a first cell;
from it a stencil of boxes whose size follows the ball's image radius at that depth descends to the
local minimum of the range (the ball's front point, on the ray through its centre) and tests the
cap and the outline in O(1) (``search_kernels.front_hypothesis``). Raw three-point samples cannot
place a ball beyond about 1.5 m at 424x240 (one pixel's noise exceeds the relief between two
samples); a box mean of n pixels has sigma / sqrt(n). The paper's three points within a ball
diameter are here five boxes about the first cell, and the known radius enters as the cap's
curvature.

While no sphere is accepted the improved pipeline searches again (``search_frame``'s switches,
``disc_search``, ``hole_search``): hypotheses ranked by their cap's relief, the descent past
occluders, the stencil stretched off the optical axis, discs standing out of their background, and
holes ringed by a ball's face.
"""

from __future__ import annotations

import math

import numpy as np

from spherebench.method import frame_kernels as FK
from spherebench.method import search_kernels as SK
from spherebench.method.config import DetectorConfig
from spherebench.method.frame import PreparedFrame

# How the search and its retries work; each chosen on the training splits
# (docs/experiments/2026-12-04-config-history.md and the records it points to). The stencil's
# geometry is ``search_kernels``'.
SEARCH_CANDIDATES = 16  # hypotheses kept per search, by score
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


def search_frame(frame: PreparedFrame, config: DetectorConfig, seed: int,
                 occluder_bound: bool = False, off_axis: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Run the compiled organised search. Returns (candidate centres (M, 3), scores (M,), occluded (M,)
    bool: passed the pretest with a side hidden by an occluder, ``search_kernels.front_hypothesis``), best first.
    occluder_bound: the descent leaves out side boxes in front of a cap (``frame_kernels.P_OCCLUDER_BOUND``);
    off_axis: the stencil follows the silhouette's stretch off the optical axis (``search_kernels.stencil_stretch``).
    The search without either keeps its passing hypotheses on the frame for ``relief_search``."""
    hyp = np.zeros((SEARCH_CANDIDATES, 6), np.float64)
    counters = np.zeros(2, np.int64)
    prm = frame.prm
    plain = not (occluder_bound or off_axis)
    if not plain:
        prm = prm.copy()
        if occluder_bound:
            prm[FK.P_OCCLUDER_BOUND] = 1.0
        if off_axis:
            prm[FK.P_OFF_AXIS] = 1.0
    passed = np.empty((frame.iterations if plain else 0, SK.N_HYP_OUT))  # at most one a first cell
    m = SK.search_organised(frame.tab, prm, np.uint64(seed), hyp, counters, passed)
    if plain:
        frame.passed = (seed, passed[:min(int(counters[1]), len(passed))], counters)
    return _found(frame, hyp[:m], counters)


def relief_search(frame: PreparedFrame, config: DetectorConfig, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``search_frame``'s hypotheses (of seed, without its switches) ranked by how far their cap stands
    out of the noise (``search_kernels._relief_llr``) in place of the pretest's agreement: the draws,
    descents and pretests are the same, so the plain search's passing hypotheses are ranked again
    (``search_kernels.relief_ranked``), the search run first where the frame holds none of this seed.
    Returns ``search_frame``'s (centres (M, 3), scores (M,), occluded (M,))."""
    if frame.passed is None or frame.passed[0] != seed:
        search_frame(frame, config, seed)
    _, passed, counters = frame.passed
    hyp = np.zeros((SEARCH_CANDIDATES, 6), np.float64)
    m = SK.relief_ranked(frame.prm, passed, hyp)
    return _found(frame, hyp[:m], counters)


def _found(frame: PreparedFrame, hyp: np.ndarray, counters: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A search's kept hypotheses hyp (M, 6) as (centres (M, 3), scores (M,), occluded (M,)); the
    frame keeps them and the search's counters for diagnostics (``search_kernels.search_organised``)."""
    frame.counters = counters
    frame.hypotheses = hyp
    return SK.cell_centres(frame.prm, hyp), hyp[:, 4].copy(), hyp[:, 5] > 0.0


def disc_search(frame: PreparedFrame, config: DetectorConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Run ``search_kernels.disc_hypotheses`` on the frame beyond the depth where one pixel's noise reaches
    ``DISC_NOISE_FRACTION`` R; returns ``search_frame``'s (centres (M, 3), scores (M,), occluded (M,))."""
    R = config.radius_m
    z_min = math.sqrt(DISC_NOISE_FRACTION * R / frame.noise_a) if frame.noise_a > 0 else math.inf
    fc = frame.prm[FK.P_FX] / frame.bin
    step = max(1, int(DISC_STEP_FRACTION * fc * R / config.search.max_range_m))
    hyp = np.zeros((SEARCH_CANDIDATES, 6), np.float64)
    m = SK.disc_hypotheses(frame.tab, frame.prm, z_min, DISC_INNER_FRACTION, DISC_SIDE_OFFSET_FRACTION,
                          DISC_SIDE_HALF_FRACTION, DISC_GAP_FRACTION * R, DISC_GAP_SIGMAS, DISC_MIN_BEHIND, step, hyp)
    frame.hypotheses = hyp[:m]
    return SK.cell_centres(frame.prm, hyp[:m]), hyp[:m, 4].copy(), np.zeros(m, bool)


def hole_search(frame: PreparedFrame, config: DetectorConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Run ``search_kernels.hole_hypotheses`` on the frame (every ``HOLE_STEP_FRACTION`` of a far ball's disc);
    returns ``search_frame``'s (centres (M, 3), scores (M,), occluded (M,))."""
    R = config.radius_m
    fc = frame.prm[FK.P_FX] / frame.bin
    step = max(1, int(HOLE_STEP_FRACTION * fc * R / config.search.max_range_m))
    hyp = np.zeros((SEARCH_CANDIDATES, 6), np.float64)
    m = SK.hole_hypotheses(frame.tab, frame.prm, HOLE_MIN_RANGE_M, step, HOLE_MIN_RING, HOLE_MIN_FRACTION, hyp)
    frame.hypotheses = hyp[:m]
    return SK.cell_centres(frame.prm, hyp[:m]), hyp[:m, 4].copy(), np.zeros(m, bool)
