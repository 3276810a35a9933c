"""The improved pipeline: local sampling, windowed scoring, refinement, size check, NMS, confidence.

Search (compiled, ``_kernels``): the 2nd and 3rd points are drawn near the 1st (in the image disc
of radius ``sample_radius_m`` at the 1st point's depth for an organised cloud, or in the grid
cells around it for an unorganised one); for an organised cloud the three are moved to the mean
depth of a small pixel patch when the stereo noise at their depth exceeds ``denoise_sigma_m``
(at 3 m and 424x240 one pixel's depth is +/- 7 cm: three raw points give no usable centre);
both known-radius centres are kept when the three points lie on their camera side; a few pixels
of the candidate's silhouette pretest it (stopping at the first decisive one); the survivors are
scored on their pixel window only. The number of iterations is the standard RANSAC bound for the
smallest ball the frame can hold (``iteration_bound``).

Verification (compiled, one call per candidate, best first, at most ``verify_candidates``):
Gauss-Newton with R fixed, re-selecting the inliers each round, on the depth residual along each
pixel's ray for an organised cloud (the D435's noise is along the rays; the 3D residual
||p - c|| - R pulls the centre toward the camera by several mm at 2 m) and on ||p - c|| - R
otherwise; then the evidence of the whole silhouette (an organised cloud shows where the ball
should be): the share of its pixels that are inliers (coverage), seen *through* (behind: a
smaller ball or no ball), or hugged by a surface just in front of the sphere (a cylinder of the
same radius); a free-radius fit as the size check; and the confidence score that ranks
detections across frames.
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass

import numpy as np

from spherebench.cloud import Cloud
from spherebench.method import _kernels as K
from spherebench.method.config import DetectorConfig


@dataclass
class Candidate:
    """One verified sphere before it becomes a ``Sphere`` (indices into the searched points)."""

    center_m: np.ndarray
    inliers: np.ndarray
    eps_m: float
    free_center_m: np.ndarray
    free_radius_m: float
    free_radius_se_m: float
    rmse_m: float
    stats: dict
    score: float
    size_ok: bool


def noise_a(config: DetectorConfig, fx: float | None) -> float:
    """sigma_z / z^2 (1/m) of Intel's stereo model for focal length fx px; 0 without intrinsics."""
    if fx is None or config.noise_subpixel <= 0 or config.noise_baseline_m <= 0:
        return 0.0
    return config.noise_subpixel / (fx * config.noise_baseline_m)


def eps_at(config: DetectorConfig, depth_m: float, fx: float | None) -> float:
    """The shell half-width at a centre depth (metres): eps widened by the depth noise model."""
    return float(K.noise_eps(depth_m, config.eps_m, noise_a(config, fx), config.noise_sigmas,
                             config.max_eps_fraction * config.radius_m))


def parameters(config: DetectorConfig, intr, iterations: int) -> np.ndarray:
    """The float64 parameter vector (``_kernels.N_PRM``,) of the organised kernels."""
    prm = np.zeros(K.N_PRM, np.float64)
    R = config.radius_m
    prm[K.P_FX], prm[K.P_FY], prm[K.P_PPX], prm[K.P_PPY] = intr.fx, intr.fy, intr.ppx, intr.ppy
    prm[K.P_R], prm[K.P_EPS] = R, config.eps_m
    prm[K.P_NOISE_A], prm[K.P_NOISE_K] = noise_a(config, float(intr.fx)), config.noise_sigmas
    prm[K.P_EPS_CAP] = config.max_eps_fraction * R
    prm[K.P_SAMPLE_R] = config.sample_r_m
    prm[K.P_SIGMA_T], prm[K.P_H_MAX] = config.denoise_sigma_m, config.denoise_max_half_px
    prm[K.P_RETRIES], prm[K.P_PRETEST_N] = config.sample_retries, config.pretest_points
    prm[K.P_PRETEST_FRAC], prm[K.P_SCORE_MAX] = config.pretest_min_fraction, config.score_max_points
    prm[K.P_ITERS], prm[K.P_DEDUP] = iterations, 0.25 * R
    return prm


def range_limit_m(config: DetectorConfig, fx: float | None) -> float:
    """The farthest centre depth the iteration bound provides for (metres): where the per-pixel
    depth noise reaches ``bound_noise_fraction`` R (3.5 m at 424x240, 4.9 m at 848x480, 6 m at
    1280x720 for the D435 model), or ``max_range_m`` when that is nearer."""
    a = noise_a(config, fx)
    lim = math.sqrt(config.bound_noise_fraction * config.radius_m / a) if a > 0 else math.inf
    return min(lim, config.max_range_m)


def iteration_bound(config: DetectorConfig, intr, z_valid: np.ndarray, n_valid: int) -> int:
    """Iterations for the standard RANSAC bound, for the smallest ball the frame can hold.

    A ball of radius R at depth z covers A(z) = pi (fx R / z)^2 pixels, a share w = A / N of the
    N valid points; a local sample is good with probability p = w * ``sample_success`` (the 2nd
    and 3rd draws on the ball given the 1st is); k = log(1 - confidence) / log(1 - p). The
    binding z is the farthest a ball can be: the scene's 98th depth percentile plus R (a ball is
    in front of what is behind it) or ``range_limit_m``, whichever is nearer; and at least
    ``bound_visible_fraction`` of it is assumed visible. Clamped to [min_iterations, iterations].
    """
    if not config.adaptive:
        return config.iterations
    z_far = range_limit_m(config, float(intr.fx))
    if len(z_valid):
        z_far = min(z_far, float(np.percentile(z_valid, 98)) + config.radius_m)
    z_far = max(z_far, 2.0 * config.radius_m)
    area = math.pi * (intr.fx * config.radius_m / z_far) ** 2 * config.bound_visible_fraction
    p = min(area / max(n_valid, 1), 1.0) * config.sample_success
    k = math.log(1.0 - config.confidence) / math.log1p(-p) if 0 < p < 1 else (1.0 if p >= 1 else math.inf)
    return int(min(max(math.ceil(k), config.min_iterations), config.iterations))


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


class Frame:
    """An organised cloud made ready for the kernels: index image, depth integrals, parameters."""

    def __init__(self, cloud: Cloud, index_image: np.ndarray, n_valid: int, config: DetectorConfig):
        self.cloud = cloud
        self.points = cloud.points
        self.index_image = index_image
        intr = cloud.intrinsics
        step = max(1, len(cloud.points) // 2048)
        z = cloud.points[::step, 2]
        z = z[np.isfinite(z) & (z > 0)]
        self.iterations = iteration_bound(config, intr, z, n_valid)
        self.prm = parameters(config, intr, self.iterations)
        self.tab = workspace("tab", (index_image.shape[0] + 1, index_image.shape[1] + 1, 3), np.float64)
        K.depth_integrals(cloud.points, index_image, self.tab)


def search_organised(frame: Frame, config: DetectorConfig, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Run the compiled organised search. Returns (candidate centres (M, 3), qualities (M,))."""
    k = max(2 * config.max_spheres, 4)
    cands = np.zeros((k, 3), np.float64)
    quals = np.zeros(k, np.float64)
    counters = np.zeros(4, np.int64)
    c = frame.cloud
    m = K.search_organised(frame.points, c.rows, c.cols, frame.index_image, frame.tab, frame.prm, np.uint64(seed),
                           cands, quals, counters)
    frame.counters = counters  # diagnostics (see _kernels.search_organised)
    return cands[:m], quals[:m]


def search_unorganised(points: np.ndarray, config: DetectorConfig, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Run the compiled unorganised search. Returns (candidate centres (M, 3), qualities (M,))."""
    k = max(2 * config.max_spheres, 4)
    cands = np.zeros((k, 3), np.float64)
    quals = np.zeros(k, np.float64)
    grid = build_grid(points, config.local_radius_m)
    win = config.local_radius_m if config.sampling == "local" else math.inf
    _, m = K.search_unorganised(points, grid["order"], grid["keys"], grid["origin"], grid["cell"], grid["dims"],
                                config.radius_m, config.eps_m, win, config.iterations, config.min_iterations,
                                config.confidence, config.sample_retries, config.pretest_points,
                                config.pretest_min_fraction, config.score_max_points, np.uint64(seed), cands, quals)
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


#: Candidates whose search quality is below this fraction of the best one's are not verified.
VERIFY_QUALITY_FRACTION = 0.15

#: Ray fits floor s = sqrt(r^2 - m^2) at this fraction of r (see ``_kernels.fit_ray``).
RAY_S_MIN = 0.03

_STAT_NAMES = {"valid_disc": K.ST_VALID_DISC, "inlier": K.ST_INLIER, "front": K.ST_FRONT,
               "front_near": K.ST_FRONT_NEAR, "behind": K.ST_BEHIND, "invalid_disc": K.ST_INVALID_DISC,
               "ring": K.ST_RING, "ring_continued": K.ST_RING_CONT}


def confidence(stats: dict, n_inliers: int, free_r: float, free_se: float, config: DetectorConfig,
               organised: bool) -> tuple[float, bool]:
    """A confidence in [0, 1] and the size check's verdict.

    Factors (each in [0, 1]): support n / (n + min_inliers); for organised clouds the share of the
    silhouette's valid pixels that are inliers (coverage: occlusion lowers it), (1 - behind share)^2
    (the ball would hide what is seen through it) and (1 - share hugging the sphere just in front
    of it)^2 (a cylinder or another non-spherical surface), (1 - share of the outline ring where
    the surface continues at the ball's depth)^2 (a wall or a plane); the size agreement exp(-d^2 / 2) with
    d the free radius's deviation from R in units of (tolerance + its standard error).
    """
    R = config.radius_m
    score = n_inliers / (n_inliers + config.min_inliers)
    if organised:
        vd = max(stats["valid_disc"], 1.0)
        coverage = min(1.0, stats["inlier"] / vd)
        behind = min(1.0, stats["behind"] / vd)
        hug = min(1.0, stats["front_near"] / vd)
        ring = stats["ring_continued"] / max(stats["ring"], 1.0)
        score *= coverage * (1.0 - behind) ** 2 * (1.0 - hug) ** 2 * (1.0 - ring) ** 2
    size_ok = True
    if config.size_check:
        se = free_se if math.isfinite(free_se) else R
        d = (free_r - R) / (config.size_tolerance_m + se) if math.isfinite(free_r) else math.inf
        score *= math.exp(-0.5 * d * d) if math.isfinite(d) else 0.0
        # consistent with R given the noise, and never beyond a quarter of R whatever the error says
        size_ok = (math.isfinite(free_r) and abs(free_r - R) <= config.size_tolerance_m + config.size_sigmas * se
                   and abs(free_r - R) <= 0.25 * R)
    return float(min(max(score, 0.0), 1.0)), size_ok


def verify_organised(frame: Frame, c0: np.ndarray, config: DetectorConfig, buf: np.ndarray) -> Candidate | None:
    """Refine one candidate of an organised cloud, measure its evidence, fit the free radius, score it."""
    out = np.empty(K.N_VOUT, np.float64)
    st = np.empty(K.N_STATS, np.float64)
    K.verify_organised(frame.points, frame.index_image, np.asarray(c0, np.float64), frame.prm,
                       config.refine_iterations, config.fit_max_points, RAY_S_MIN, buf, out, st)
    n = int(out[K.V_N])
    if n < config.min_inliers:
        return None
    stats = {k: float(st[j]) for k, j in _STAT_NAMES.items()}
    score, size_ok = confidence(stats, n, out[K.V_FR], out[K.V_FSE], config, True)
    return Candidate(center_m=out[K.V_CX:K.V_CZ + 1].copy(), inliers=buf[:n].copy(), eps_m=float(out[K.V_EPS]),
                     free_center_m=out[K.V_FCX:K.V_FCZ + 1].copy(), free_radius_m=float(out[K.V_FR]),
                     free_radius_se_m=float(out[K.V_FSE]), rmse_m=float(out[K.V_RMSE]), stats=stats, score=score,
                     size_ok=size_ok)


def verify_unorganised(points: np.ndarray, c0: np.ndarray, config: DetectorConfig) -> Candidate | None:
    """Refine one candidate of an unorganised cloud (3D residuals over the whole cloud), fit, score."""
    R = config.radius_m
    e = config.eps_m
    buf = np.empty(len(points), np.int64)
    c = np.asarray(c0, np.float64).copy()
    idx = buf[:0]
    for _ in range(config.refine_iterations):
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
    if n < config.min_inliers:
        return None
    idx = buf[:n].copy()
    free_c, free_r, free_se, _ = K.fit_free_radius(points, idx, c[0], c[1], c[2], R, 8)
    res = np.linalg.norm(points[idx].astype(np.float64) - c, axis=1) - R
    rmse = float(np.sqrt(np.mean(res * res)))
    score, size_ok = confidence({}, n, float(free_r), float(free_se), config, False)
    return Candidate(center_m=c, inliers=idx, eps_m=e, free_center_m=np.asarray(free_c), free_radius_m=float(free_r),
                     free_radius_se_m=float(free_se), rmse_m=rmse, stats={}, score=score, size_ok=size_ok)


def run_improved(points: np.ndarray, frame: Frame | None, config: DetectorConfig,
                 seed: int) -> list[Candidate]:
    """Search, verify the best candidates, drop the failed ones, suppress duplicates. Best first.

    frame: the prepared organised cloud, or None to treat ``points`` (N, 3) as unorganised.
    """
    if frame is not None:
        cands, quals = search_organised(frame, config, seed)
        # gather_window's index buffer: one silhouette's pixels at most
        buf = workspace("inliers", (min(len(points), frame.index_image.size) + 1,), np.int64)
    else:
        cands, quals = search_unorganised(points, config, seed)
    found: list[Candidate] = []
    # candidates far below the best cannot win: verifying them would only cost time
    for c0, q in zip(cands[:config.verify_candidates], quals[:config.verify_candidates]):
        if q < VERIFY_QUALITY_FRACTION * quals[0]:
            break
        v = verify_organised(frame, c0, config, buf) if frame is not None else verify_unorganised(points, c0, config)
        if v is None or not v.size_ok or v.score < config.min_score:
            continue
        found.append(v)
    found.sort(key=lambda v: -v.score)
    kept: list[Candidate] = []
    min_sep = config.nms_distance_fraction * 2.0 * config.radius_m
    for v in found:
        if all(np.linalg.norm(v.center_m - k.center_m) >= min_sep for k in kept):
            kept.append(v)
        if len(kept) == config.max_spheres:
            break
    return kept
