"""The paper's pipeline (section 2.5, Figure 3), step by step, with its intermediate values kept.

1. Draw three points from the whole cloud; compute a centre (the known-radius solver, or the
   literal least-squares Eq. (12) for the ablation) and its radius by Eq. (4) from the 1st point.
2. If |r - R| <= eps: a listed candidate centre within ``merge_m`` collects the sample, else the
   centre becomes a new candidate. (With the known-radius solver r = R whenever a centre exists,
   so the test is "the circumradius is at most R".)
3. After the iteration limit, assign every point to each candidate whose distance is R +/- eps.
4. Choose the candidate with the most points, then the least |r - R|.
5. Z-score of a per-point variable over the chosen points; drop |z| > threshold; the barycentre of
   the rest is the new centre ("least_squares" refinement: Gauss-Newton with R fixed instead);
   the sphere's points are those within R of the barycentre (the shell R +/- eps for least squares).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from spherebench.method.unorganised import shell_counts
from spherebench import sphere_distance
from spherebench.method import sphere_model as sm
from spherebench.method.config import DetectorConfig
from spherebench.method.ransac import draw_distinct, sample_loop


@dataclass
class PaperTrace:
    """The intermediate values of the paper's pipeline (for Table 2). Indices refer to cloud.points.

    ransac_centre_m (3,): the chosen candidate centre (step 4).
    ransac_indices (K,): the points assigned to it (R +/- eps).
    zscores (K,) (or (K, 3) for "xyz"): z-scores of the chosen points' variable.
    kept_indices (J,): the points with |z| <= threshold.
    barycentre_m (3,): the mean of the kept points (the paper's refined centre).
    candidate_centres_m (M, 3), candidate_votes (M,), candidate_counts (M,): the list of step 2
    with the samples each collected and the points assigned in step 3.
    """

    ransac_centre_m: np.ndarray
    ransac_radius_m: float
    ransac_indices: np.ndarray
    zscores: np.ndarray
    kept_indices: np.ndarray
    barycentre_m: np.ndarray
    zscore_threshold: float
    zscore_variable: str
    iterations: int
    candidate_centres_m: np.ndarray = field(repr=False)
    candidate_votes: np.ndarray = field(repr=False)
    candidate_counts: np.ndarray = field(repr=False)


def zscore_values(points_m: np.ndarray, centre_m: np.ndarray, radius_m: float, variable: str) -> np.ndarray:
    """The per-point value that is z-scored: (K,) or (K, 3) for "xyz". points_m (K, 3) metres."""
    p = np.asarray(points_m, np.float64)
    if variable == "distance":
        return np.linalg.norm(p - centre_m, axis=1)
    if variable == "residual":
        return np.abs(np.linalg.norm(p - centre_m, axis=1) - radius_m)
    if variable == "xyz":
        return p
    return p[:, "xyz".index(variable)]


def zscore_keep(values: np.ndarray, threshold: float) -> tuple[np.ndarray, np.ndarray]:
    """Eq. (13): z = (X - mean) / std; returns (z, keep mask |z| <= threshold on every column)."""
    v = np.asarray(values, np.float64)
    std = v.std(axis=0)
    z = (v - v.mean(axis=0)) / np.where(std > 0, std, 1.0)
    keep = np.abs(z) <= threshold
    return z, keep if keep.ndim == 1 else keep.all(axis=1)


def candidate_centres(points: np.ndarray, config: DetectorConfig, rng: np.random.Generator):
    """Steps 1-2: the list of candidate centres. Returns (centres (M, 3), radii (M,), votes (M,), iterations)."""
    R, eps, merge = config.radius_m, config.eps_m, config.merge_m
    n = len(points)
    centres: list[np.ndarray] = []
    radii: list[float] = []
    votes: list[int] = []

    def sample(g, k):
        return draw_distinct(g, n, k, 3)

    def estimate(s):
        p1, p2, p3 = (points[s[:, j]].astype(np.float64) for j in range(3))
        if config.search.solver == "known_radius":
            c, ok = sm.solve_known_radius(p1, p2, p3, R)
            r = np.full(len(c), R)
        else:
            c, r, ok = sm.solve_eq12_lstsq(p1, p2, p3)
        return np.column_stack([c, r]), ok

    def check(models):
        return np.abs(models[:, 3] - R) <= eps

    def visit(_it, model, _s):
        c = model[:3]
        if centres:
            d = np.linalg.norm(np.asarray(centres) - c, axis=1)
            j = int(np.argmin(d))
            if d[j] <= merge:
                votes[j] += 1
                return False
        centres.append(c)
        radii.append(float(model[3]))
        votes.append(1)
        return False

    its = sample_loop(config.search.iterations, sample, estimate, check, visit, rng)
    return (np.asarray(centres, np.float64).reshape(-1, 3), np.asarray(radii, np.float64),
            np.asarray(votes, np.int64), its)


def run_paper(points: np.ndarray, config: DetectorConfig, rng: np.random.Generator):
    """The whole pipeline on valid points (N, 3). Returns (centre (3,), inlier indices, trace) or None."""
    R, eps = config.radius_m, config.eps_m
    centres, radii, votes, its = candidate_centres(points, config, rng)
    if len(centres) == 0:
        return None
    counts = shell_counts(points, centres, R, eps)
    # most points, then least radius error
    order = np.lexsort((np.abs(radii - R), -counts))
    best = int(order[0])
    if counts[best] < 3:
        return None
    c0 = centres[best]
    chosen = np.flatnonzero(np.abs(sphere_distance.residuals(points, c0, R)) <= eps)
    z, keep = zscore_keep(zscore_values(points[chosen], c0, R, config.paper.zscore_variable),
                          config.paper.zscore_threshold)
    kept = chosen[keep]
    if len(kept) < 3:
        kept = chosen
    bary = points[kept].astype(np.float64).mean(axis=0)
    if config.paper.refine == "barycentre":
        centre = bary
        inliers = np.flatnonzero(np.linalg.norm(points - centre, axis=1) <= R)
    else:
        centre = sm.refine_fixed_radius(points[kept], c0, R)
        inliers = np.flatnonzero(np.abs(sphere_distance.residuals(points, centre, R)) <= eps)
    trace = PaperTrace(ransac_centre_m=c0, ransac_radius_m=float(radii[best]), ransac_indices=chosen, zscores=z,
                       kept_indices=kept, barycentre_m=bary, zscore_threshold=config.paper.zscore_threshold,
                       zscore_variable=config.paper.zscore_variable, iterations=its, candidate_centres_m=centres,
                       candidate_votes=votes, candidate_counts=counts)
    return centre, inliers, trace
