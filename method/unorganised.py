"""Unorganised clouds (no image, no silhouette): the paper's three-point RANSAC with local samples in
a spatial grid (``ransac_search``), refinement on 3D residuals, the size check, and a hand-set score
(``unorganised_score``: support, an empty interior, the size), since the fitted verdict reads a
silhouette. Also the shell counts over a whole cloud that the paper's pipeline uses. Python and
kernels side by side.
"""

from __future__ import annotations

import math

import numpy as np

from spherebench import sphere_distance
from spherebench.method import fit_kernels as FIT
from spherebench.method.compiled import kernel, next_u01, part
from spherebench.method.config import DetectorConfig
from spherebench.method.fit_kernels import known_radius_centres
from spherebench.method.verification import Candidate, size_ok

# The unorganised search and score; each chosen on `train`
# (docs/experiments/2026-12-04-config-history.md and the records it points to).
SAMPLE_RETRIES = 4  # unorganised: draws for the 2nd and 3rd point before giving up
PRETEST_POINTS = 12  # unorganised: points checked before a candidate is scored fully ...
PRETEST_MIN_FRACTION = 0.5  # ... of which this share must be inliers
SCORE_MAX_POINTS = 400  # unorganised: at most about this many points scored per candidate
VERIFY_QUALITY_FRACTION = 0.15  # unorganised: skip candidates below this share of the best's quality
INTERIOR_BANDS = 3.0  # unorganised: the interior lies at least this many bands under the surface
#: unorganised clouds' score map, probability = sigmoid(slope logit(product) + offset): the map last fitted
#: (train + train-stereo) for the organised clouds' hand-set product, which the fitted verdict replaced;
#: unorganised clouds have no silhouette for it (docs/detector.md, "Unorganised clouds")
UNORGANISED_CALIBRATION = (2.102, 2.018)


@kernel
def faces_camera(points, i, cx, cy, cz):
    """True if point i is on the camera-facing side of the sphere centred at c: (p - c) . p < 0."""
    px, py, pz = points[i, 0], points[i, 1], points[i, 2]
    return (px - cx) * px + (py - cy) * py + (pz - cz) * pz < 0.0


@kernel
def _keep_candidate(cands, quals, n_kept, cx, cy, cz, q, merge):
    """Keep the best distinct candidates: (K, 3) centres and (K,) qualities, sorted best first."""
    k_max = cands.shape[0]
    # a close candidate is the same ball: keep the better of the two
    for j in range(n_kept):
        dx, dy, dz = cands[j, 0] - cx, cands[j, 1] - cy, cands[j, 2] - cz
        if dx * dx + dy * dy + dz * dz <= merge * merge:
            if q <= quals[j]:
                return n_kept
            for m in range(j, n_kept - 1):
                cands[m, 0], cands[m, 1], cands[m, 2] = cands[m + 1, 0], cands[m + 1, 1], cands[m + 1, 2]
                quals[m] = quals[m + 1]
            n_kept -= 1
            break
    if n_kept == k_max and q <= quals[n_kept - 1]:
        return n_kept
    pos = n_kept if n_kept < k_max else k_max - 1
    while pos > 0 and quals[pos - 1] < q:
        if pos < k_max:
            cands[pos, 0], cands[pos, 1], cands[pos, 2] = cands[pos - 1, 0], cands[pos - 1, 1], cands[pos - 1, 2]
            quals[pos] = quals[pos - 1]
        pos -= 1
    cands[pos, 0], cands[pos, 1], cands[pos, 2] = cx, cy, cz
    quals[pos] = q
    return min(n_kept + 1, k_max)


@kernel
def iterations_for_support(support, n_points, window_px, confidence):
    """Standard RANSAC bound log(1 - conf) / log(1 - p) for a local sampler.

    p = (support / N) * q^2: the 1st point on the ball, then the 2nd and 3rd from the sampling
    window, with q = support / window_px (the ball's share of the window), capped at 1.
    """
    w = support / max(n_points, 1.0)
    q = min(1.0, support / max(window_px, 1.0))
    p = w * q * q
    if p >= 1.0:
        return 1.0
    if p <= 1e-12:
        return 1e18
    return math.log(1.0 - confidence) / math.log(1.0 - p)


@kernel
def shell_indices(points, cx, cy, cz, radius, band, out_idx):
    """Indices of all points with | ||p - c|| - R | <= band (unorganised clouds); returns the count."""
    k = 0
    lo, hi = radius - band, radius + band
    lo2 = lo * lo if lo > 0 else 0.0
    hi2 = hi * hi
    for i in range(points.shape[0]):
        dx, dy, dz = points[i, 0] - cx, points[i, 1] - cy, points[i, 2] - cz
        d2 = dx * dx + dy * dy + dz * dz
        if lo2 <= d2 <= hi2 and k < out_idx.shape[0]:
            out_idx[k] = i
            k += 1
    return k


@kernel
def inside_count(points, cx, cy, cz, r_in):
    """The number of points closer than r_in to c (unorganised clouds: a ball's hidden interior)."""
    k = 0
    r2 = r_in * r_in
    for i in range(points.shape[0]):
        dx, dy, dz = points[i, 0] - cx, points[i, 1] - cy, points[i, 2] - cz
        k += dx * dx + dy * dy + dz * dz < r2
    return k


@kernel
def shell_counts(points, centres, radius, eps):
    """For each centre (M, 3): the number of points (N, 3) with | ||p - c|| - R | <= eps (the paper's step 3)."""
    m = centres.shape[0]
    out = np.zeros(m, np.int64)
    lo, hi = radius - eps, radius + eps
    lo2 = lo * lo if lo > 0 else 0.0
    hi2 = hi * hi
    for j in range(m):
        cx, cy, cz = centres[j, 0], centres[j, 1], centres[j, 2]
        k = 0
        for i in range(points.shape[0]):
            dx, dy, dz = points[i, 0] - cx, points[i, 1] - cy, points[i, 2] - cz
            d2 = dx * dx + dy * dy + dz * dz
            if lo2 <= d2 <= hi2:
                k += 1
        out[j] = k
    return out


# ----------------------------------------------------------------------------------------------
# Unorganised clouds: a uniform grid of cells sorted by key, looked up by binary search.


@kernel
def grid_keys(points, origin, cell, dims):
    """Linear cell key (N,) int64 of every point for a grid of ``dims`` (3,) cells of size ``cell``."""
    n = points.shape[0]
    keys = np.empty(n, np.int64)
    for i in range(n):
        ix = min(max(int((points[i, 0] - origin[0]) / cell), 0), dims[0] - 1)
        iy = min(max(int((points[i, 1] - origin[1]) / cell), 0), dims[1] - 1)
        iz = min(max(int((points[i, 2] - origin[2]) / cell), 0), dims[2] - 1)
        keys[i] = (ix * dims[1] + iy) * dims[2] + iz
    return keys


@kernel
def _cell_ranges(sorted_keys, origin, cell, dims, x, y, z, reach, starts, ends):
    """Sorted-order ranges of the cells within ``reach`` cells of (x, y, z); returns their count."""
    ix = min(max(int((x - origin[0]) / cell), 0), dims[0] - 1)
    iy = min(max(int((y - origin[1]) / cell), 0), dims[1] - 1)
    iz = min(max(int((z - origin[2]) / cell), 0), dims[2] - 1)
    m = 0
    for a in range(max(ix - reach, 0), min(ix + reach, dims[0] - 1) + 1):
        for b in range(max(iy - reach, 0), min(iy + reach, dims[1] - 1) + 1):
            for c in range(max(iz - reach, 0), min(iz + reach, dims[2] - 1) + 1):
                key = (a * dims[1] + b) * dims[2] + c
                s = np.searchsorted(sorted_keys, key)
                e = np.searchsorted(sorted_keys, key + 1)
                if e > s:
                    starts[m] = s
                    ends[m] = e
                    m += 1
    return m


@kernel
def _ranges_size(starts, ends, m):
    """The number of points in the first m sorted-order ranges."""
    total = 0
    for k in range(m):
        total += ends[k] - starts[k]
    return total


@kernel
def _draw_in_ranges(state, order, starts, ends, total):
    """A point drawn uniformly from the ranges (``total`` points in all): its index into points."""
    t = min(int(next_u01(state) * total), total - 1)
    k = 0
    while t >= ends[k] - starts[k]:
        t -= ends[k] - starts[k]
        k += 1
    return order[starts[k] + t]


@part
def _local_sample(state, points, order, sorted_keys, origin, cell, dims, n, win_m, retries, starts, ends, picks):
    """A local three-point sample into picks (3,): the 1st point drawn from all n, the 2nd and 3rd from
    the 27 grid cells around it (their sorted-order ranges left in starts, ends), each kept if within
    win_m m of the 1st and distinct, up to ``retries`` draws each. Returns (points drawn, 1-3; the
    number of points in those cells)."""
    i1 = order[min(int(next_u01(state) * n), n - 1)]
    m = _cell_ranges(sorted_keys, origin, cell, dims, points[i1, 0], points[i1, 1], points[i1, 2], 1, starts, ends)
    total = _ranges_size(starts, ends, m)
    picks[0] = i1
    got = 1
    for slot in range(2):
        for _ in range(retries):
            j = _draw_in_ranges(state, order, starts, ends, total)
            if j == i1 or (slot == 1 and j == picks[1]):
                continue
            dx, dy, dz = points[j, 0] - points[i1, 0], points[j, 1] - points[i1, 1], points[j, 2] - points[i1, 2]
            if dx * dx + dy * dy + dz * dz > win_m * win_m:
                continue
            picks[got] = j
            got += 1
            break
    return got, total


@part
def _near_pretest(state, points, order, starts, ends, tot_s, cx, cy, cz, radius, eps, pretest_n, pretest_frac):
    """The pretest of the sphere (c, R) m: of 3 pretest_n points drawn from the ranges (tot_s points),
    those near it (inside the outer shell, R + eps) must be at least 3 and at least pretest_frac of
    them on the shell (within eps of R)."""
    near = 0
    inl = 0
    for _ in range(pretest_n * 3):
        j = _draw_in_ranges(state, order, starts, ends, tot_s)
        dx, dy, dz = points[j, 0] - cx, points[j, 1] - cy, points[j, 2] - cz
        d = math.sqrt(dx * dx + dy * dy + dz * dz)
        if d <= radius + eps:
            near += 1
            if d >= radius - eps:
                inl += 1
    return near >= 3 and inl >= pretest_frac * near


@part
def _msac_quality(points, order, starts, ends, ms, step, cx, cy, cz, radius, eps):
    """The MSAC quality (sum of 1 - (res / eps)^2 over the points with |res| <= eps, res = ||p - c|| - R
    m) and the inlier count of the sphere (c, R) over every step-th point of the first ms ranges;
    unscaled by step."""
    q = 0.0
    inliers = 0.0
    for k in range(ms):
        for t in range(starts[k], ends[k], step):
            j = order[t]
            dx, dy, dz = points[j, 0] - cx, points[j, 1] - cy, points[j, 2] - cz
            res = math.sqrt(dx * dx + dy * dy + dz * dz) - radius
            if abs(res) <= eps:
                q += 1.0 - (res / eps) ** 2
                inliers += 1.0
    return q, inliers


@kernel
def ransac_search(points, order, sorted_keys, origin, cell, dims, radius, eps, win_m, max_iter, min_iter,
                       confidence, retries, pretest_n, pretest_frac, score_max, seed, cands, quals):
    """Local-sampling RANSAC on an unorganised cloud (grid cells of size ``cell`` >= win_m / 1).

    The 2nd and 3rd points are drawn from the 27 cells around the 1st (``_local_sample``); both
    known-radius centres facing the camera at the origin; a pretest on points drawn near the
    candidate (``_near_pretest``); quality = MSAC over the points of the cells covering the sphere
    (``_msac_quality``, subsampled to about ``score_max``). Returns (iterations run, number of
    candidates kept).
    """
    n = points.shape[0]
    state = np.empty(1, np.uint64)
    state[0] = np.uint64(seed)
    two = np.empty((2, 3), np.float64)
    starts = np.empty(125, np.int64)
    ends = np.empty(125, np.int64)
    picks = np.empty(3, np.int64)
    n_kept = 0
    needed = float(max_iter)
    it = 0
    reach_sphere = int(math.ceil((radius + eps) / cell))
    while it < max_iter:
        if it >= min_iter and it >= needed:
            break
        it += 1
        got, total = _local_sample(state, points, order, sorted_keys, origin, cell, dims, n, win_m, retries, starts,
                                   ends, picks)
        if got < 3:
            continue
        if known_radius_centres(points, picks[0], picks[1], picks[2], radius, two) == 0:
            continue
        for s in range(2):
            cx, cy, cz = two[s, 0], two[s, 1], two[s, 2]
            if not (faces_camera(points, picks[0], cx, cy, cz) and faces_camera(points, picks[1], cx, cy, cz)
                    and faces_camera(points, picks[2], cx, cy, cz)):
                continue
            ms = _cell_ranges(sorted_keys, origin, cell, dims, cx, cy, cz, reach_sphere, starts, ends)
            tot_s = _ranges_size(starts, ends, ms)
            if tot_s == 0:
                continue
            if not _near_pretest(state, points, order, starts, ends, tot_s, cx, cy, cz, radius, eps, pretest_n,
                                 pretest_frac):
                continue
            step = max(1, tot_s // score_max)
            q, inliers = _msac_quality(points, order, starts, ends, ms, step, cx, cy, cz, radius, eps)
            q *= step
            inliers *= step
            if q <= 0.0:
                continue
            n_kept = _keep_candidate(cands, quals, n_kept, cx, cy, cz, q, 0.5 * radius)
            if n_kept > 0 and quals[0] == q:
                # share of the 1st point's neighbourhood (27 cells, about (3 cell)^3) on the ball
                needed = iterations_for_support(inliers, float(n), float(total), confidence)
    return it, n_kept


def search_unorganised(points: np.ndarray, config: DetectorConfig, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Run the compiled unorganised search. Returns (candidate centres (M, 3), qualities (M,))."""
    k = max(2 * config.verification.max_spheres, 4)
    cands = np.zeros((k, 3), np.float64)
    quals = np.zeros(k, np.float64)
    grid = build_grid(points, config.local_radius_m)
    win = config.local_radius_m if config.search.sampling == "local" else math.inf
    s = config.search
    _, m = ransac_search(points, grid["order"], grid["keys"], grid["origin"], grid["cell"], grid["dims"],
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
    keys = grid_keys(points, lo, cell_m, dims)
    order = np.argsort(keys, kind="stable")
    return {"order": order, "keys": keys[order], "origin": lo, "cell": float(cell_m), "dims": dims}


def unorganised_score(stats: dict, n_inliers: int, free_r: float, free_se: float,
                      config: DetectorConfig) -> tuple[float, float]:
    """An unorganised cloud's (evidence product, probability), each in [0, 1]: no image, so no
    silhouette for the fitted verdict to read. The product of the support n / (n + min_inliers), the
    interior's emptiness (1 - min(1, q))^2, q the density of points in the ball's inner half over
    that in its shell (a wall it cuts, volumetric noise: a real ball hides its interior), and the
    size's agreement exp(-d^2 / 2), d the free radius's deviation from R in units of the tolerance
    plus its standard error; the probability is the product through ``UNORGANISED_CALIBRATION``'s
    logistic map. Hand-set: docs/detector.md, "Unorganised clouds"."""
    score = n_inliers / (n_inliers + config.verification.min_inliers)
    if "interior_density_ratio" in stats:
        score *= (1.0 - min(1.0, stats["interior_density_ratio"])) ** 2
    if config.refinement.size_check:
        se = free_se if math.isfinite(free_se) else config.radius_m
        d = (free_r - config.radius_m) / (config.radius_tolerance_m + se) if math.isfinite(free_r) else math.inf
        score *= math.exp(-0.5 * d * d) if math.isfinite(d) else 0.0
    score = float(min(max(score, 0.0), 1.0))
    if score <= 0.0 or score >= 1.0:
        return score, score
    slope, offset = UNORGANISED_CALIBRATION
    return score, 1.0 / (1.0 + math.exp(-(slope * math.log(score / (1.0 - score)) + offset)))


def verify_unorganised(points: np.ndarray, c0: np.ndarray, config: DetectorConfig) -> Candidate | None:
    """Refine one candidate of an unorganised cloud (3D residuals over the whole cloud), fit, score."""
    R = config.radius_m
    e = config.eps_m
    buf = np.empty(len(points), np.int64)
    c = np.asarray(c0, np.float64).copy()
    idx = buf[:0]
    for _ in range(config.refinement.refine_iterations):
        n = shell_indices(points, c[0], c[1], c[2], R, e, buf)
        if n < 3:
            break
        idx = buf[:n]
        c_new = FIT.refine_fixed_radius(points, idx, c[0], c[1], c[2], R, 3)
        moved = float(np.linalg.norm(c_new - c))
        c = c_new
        if moved < 1e-5:
            break
    n = shell_indices(points, c[0], c[1], c[2], R, e, buf)
    if n < config.verification.min_inliers:
        return None
    idx = buf[:n].copy()
    free_c, free_r, free_se, _ = FIT.fit_free_radius(points, idx, c[0], c[1], c[2], R, 8)
    rmse = sphere_distance.rmse(points[idx], c, R)
    # a ball hides its interior: points in its inner half (and ``INTERIOR_BANDS`` shell half-widths under
    # its surface) are another surface the sphere cuts (a wall, clutter) or volumetric noise; a noisy
    # sensor's returns off the ball itself do not reach that deep (a 16-beam LiDAR's do 3 cm deep)
    r_in = min(R - INTERIOR_BANDS * e, 0.5 * R)
    inside = float(inside_count(points, c[0], c[1], c[2], r_in)) if r_in > 0 else 0.0
    v_shell = (R + e) ** 3 - max(R - e, 0.0) ** 3  # volumes / (4 pi / 3)
    stats = {"inside": inside, "shell": float(n),
             "interior_density_ratio": (inside / max(r_in, 1e-12) ** 3) / (n / v_shell) if r_in > 0 else 0.0}
    raw, score = unorganised_score(stats, n, float(free_r), float(free_se), config)
    return Candidate(centre_m=c, inliers=idx, eps_m=e, free_centre_m=np.asarray(free_c), free_radius_m=float(free_r),
                     free_radius_se_m=float(free_se), rmse_m=rmse, stats=stats, score=score,
                     size_ok=size_ok(float(free_r), float(free_se), config), raw_score=raw)
