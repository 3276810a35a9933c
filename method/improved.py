"""The improved pipeline: local sampling, windowed scoring, refinement, size check, NMS, confidence.

Search (compiled, ``_kernels``): the 2nd and 3rd points are drawn near the 1st (the organised
image window spanning ``local_radius_m`` at the 1st point's depth, or the grid cells around it for
an unorganised cloud); both known-radius centres are kept when the three points lie on their
camera side; a few pixels of the candidate's silhouette pretest it; the survivors are scored on
their pixel window only; the iteration count adapts by the standard bound.

Verification (here, per kept candidate, best first): Gauss-Newton with R fixed, re-selecting the
inliers each round, on the depth residual along each pixel's ray for an organised cloud (the
D435's noise is along the rays; the 3D residual ||p - c|| - R pulls the centre toward the camera
by several mm at 2 m) and on ||p - c|| - R otherwise; then the evidence of the whole silhouette (an
organised cloud shows where the ball should be): the share of its pixels that are inliers
(coverage), seen *through* (behind: a smaller ball or no ball), or hugged by a surface just in
front of the sphere (a cylinder of the same radius); a free-radius fit as the size check;
and the confidence score that ranks detections across frames.
"""

from __future__ import annotations

import math
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


def eps_at(config: DetectorConfig, depth_m: float, fx: float | None) -> float:
    """The shell half-width at a centre depth (metres): eps widened by the depth noise model."""
    if fx is None:
        return config.eps_m
    return float(K.shell_eps(depth_m, config.eps_m, fx, config.noise_sigmas, config.noise_subpixel,
                             config.noise_baseline_m, config.max_eps_fraction * config.radius_m))


def search(points: np.ndarray, cloud: Cloud | None, index_image: np.ndarray | None, config: DetectorConfig,
           seed: int) -> tuple[np.ndarray, np.ndarray, int]:
    """Run the compiled search. Returns (candidate centres (M, 3), qualities (M,), iterations)."""
    R = config.radius_m
    k = max(2 * config.max_spheres, 4)
    cands = np.zeros((k, 3), np.float64)
    quals = np.zeros(k, np.float64)
    counters = np.zeros(4, np.int64)
    if index_image is not None:
        intr = cloud.intrinsics
        its, m = K.search_organised(points, cloud.rows, cloud.cols, index_image, float(intr.fx), float(intr.fy),
                                    float(intr.ppx), float(intr.ppy), R, config.eps_m, config.noise_sigmas,
                                    config.noise_subpixel, config.noise_baseline_m, config.max_eps_fraction * R,
                                    config.local_radius_m, config.sampling == "local", config.iterations,
                                    config.min_iterations, config.confidence, config.sample_retries,
                                    config.pretest_points, config.pretest_min_fraction, config.score_max_points,
                                    np.uint64(seed), cands, quals, counters)
    else:
        grid = build_grid(points, config.local_radius_m)
        win = config.local_radius_m if config.sampling == "local" else math.inf
        its, m = K.search_unorganised(points, grid["order"], grid["keys"], grid["origin"], grid["cell"], grid["dims"],
                                      R, config.eps_m, win, config.iterations, config.min_iterations,
                                      config.confidence, config.sample_retries, config.pretest_points,
                                      config.pretest_min_fraction, config.score_max_points, np.uint64(seed),
                                      cands, quals)
    search.counters = counters  # diagnostics of the last organised search (see _kernels)
    return cands[:m].copy(), quals[:m].copy(), int(its)


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


def _shell(points, index_image, cloud, c, R, band):
    """Inlier indices: silhouette pixels with ray residual within band (organised), else points
    with | ||p - c|| - R | <= band (the whole cloud)."""
    if index_image is not None:
        intr = cloud.intrinsics
        dist = float(np.linalg.norm(c))
        if not (c[2] > R and dist > R):
            return np.empty(0, np.int64)
        rpx = K.disc_radius_px(c[2], dist, R, max(intr.fx, intr.fy)) * 1.1 + 3.0
        cap = int(min((2 * rpx + 3) ** 2, len(points)))
        buf = np.empty(max(cap, 1), np.int64)
        n = K.gather_window(points, index_image, c[0], c[1], c[2], R, band, intr.fx, intr.fy, intr.ppx, intr.ppy, buf)
    else:
        buf = np.empty(len(points), np.int64)
        n = K.shell_indices(points, c[0], c[1], c[2], R, band, buf)
    return buf[:n].copy()


#: Candidates whose search quality is below this fraction of the best one's are not verified.
VERIFY_QUALITY_FRACTION = 0.15

#: Ray fits floor s = sqrt(r^2 - m^2) at this fraction of r (see ``_kernels.fit_ray``).
RAY_S_MIN = 0.03


def _fit(points, idx, c, R, free, organised, iterations):
    """(centre, r, se_r, rms): ray residuals for organised clouds, 3D residuals otherwise."""
    if organised:
        return K.fit_ray(points, idx, c[0], c[1], c[2], R, free, iterations, RAY_S_MIN)
    if free:
        return K.fit_free_radius(points, idx, c[0], c[1], c[2], R, iterations)
    return K.refine_fixed_radius(points, idx, c[0], c[1], c[2], R, iterations), R, float("nan"), float("nan")


def refine(points, index_image, cloud, c0, config: DetectorConfig, fx):
    """Alternate inlier selection and Gauss-Newton with R fixed. Returns (centre (3,), inliers (K,), eps)."""
    R = config.radius_m
    organised = index_image is not None
    c = np.asarray(c0, np.float64).copy()
    idx = np.empty(0, np.int64)
    for _ in range(config.refine_iterations):
        e = eps_at(config, c[2], fx)
        idx = _shell(points, index_image, cloud, c, R, e)
        if len(idx) < 3:
            break
        c_new = np.asarray(_fit(points, idx, c, R, False, organised, 3)[0])
        moved = float(np.linalg.norm(c_new - c))
        c = c_new
        if moved < 1e-5:
            break
    e = eps_at(config, c[2], fx)
    idx = _shell(points, index_image, cloud, c, R, e)
    return c, idx, e


def silhouette_stats(points, index_image, cloud, c, R, e) -> dict:
    """Counts over the candidate's silhouette (see ``_kernels.window_stats``)."""
    intr = cloud.intrinsics
    out = np.zeros(K.N_STATS, np.float64)
    K.window_stats(points, index_image, c[0], c[1], c[2], R, e, intr.fx, intr.fy, intr.ppx, intr.ppy, 1, out)
    return {"valid_disc": out[K.ST_VALID_DISC], "inlier": out[K.ST_INLIER], "front": out[K.ST_FRONT],
            "front_near": out[K.ST_FRONT_NEAR], "behind": out[K.ST_BEHIND], "invalid_disc": out[K.ST_INVALID_DISC],
            "ring": out[K.ST_RING], "ring_continued": out[K.ST_RING_CONT]}


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


def verify(points, index_image, cloud, c0, config: DetectorConfig) -> Candidate | None:
    """Refine one candidate, measure its evidence, fit the free radius, score it."""
    organised = index_image is not None
    fx = float(cloud.intrinsics.fx) if organised else None
    R = config.radius_m
    c, idx, e = refine(points, index_image, cloud, c0, config, fx)
    if len(idx) < config.min_inliers:
        return None
    free_c, free_r, free_se, _ = _fit(points, idx, c, R, True, organised, 8)
    res = np.linalg.norm(points[idx].astype(np.float64) - c, axis=1) - R
    rmse = float(np.sqrt(np.mean(res * res)))
    stats = silhouette_stats(points, index_image, cloud, c, R, e) if organised else {}
    score, size_ok = confidence(stats, len(idx), float(free_r), float(free_se), config, organised)
    return Candidate(center_m=c, inliers=idx, eps_m=e, free_center_m=np.asarray(free_c), free_radius_m=float(free_r),
                     free_radius_se_m=float(free_se), rmse_m=rmse, stats=stats, score=score, size_ok=size_ok)


def run_improved(points: np.ndarray, cloud: Cloud | None, index_image: np.ndarray | None, config: DetectorConfig,
                 seed: int) -> tuple[list[Candidate], int]:
    """Search, verify each kept candidate, drop the failed ones, suppress duplicates. Best first."""
    cands, quals, its = search(points, cloud, index_image, config, seed)
    found: list[Candidate] = []
    # candidates far below the best cannot win: verifying them would only cost time
    for c0, q in zip(cands, quals):
        if q < VERIFY_QUALITY_FRACTION * quals[0]:
            break
        v = verify(points, index_image, cloud, c0, config)
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
    return kept, its
