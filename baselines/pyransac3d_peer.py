"""The generic peer: pyRANSAC-3D's ``Sphere().fit``, a free-radius 4-point sphere RANSAC.

It knows nothing of the ball's radius, of pixels or of the camera: it fits the sphere with the
most points within ``thresh_m`` of its surface. Its cost is about 2-3 s per 1,000 iterations on
100k points (every iteration measures every point), so it runs on a seeded random subsample of
``points`` points (default 10,000; the benchmark says so in its table); the reported inliers are
then counted on the whole cloud. A detection, in the benchmark's terms, is a fitted centre within
2 cm of a ball and a fitted radius within eps (1 cm) of R; ``detect`` reports the fit with its
radius either way, so that the scorer can apply that rule.

pyransac3d draws its samples with Python's global ``random`` module: ``fit`` seeds it from its own
seed (the benchmark's scene seed) and puts the previous state back, so a fit depends on its scene
and seed only (not on the scenes a worker ran before) and leaves the caller's generator untouched.
Across machines a fit can still change: its 4x4 determinants go through numpy's BLAS, whose kernel
OpenBLAS picks per CPU (recorded as ``machine.blas`` in the provenance), and a near-degenerate
sample (four points almost on a plane) turns last-bit differences into another best sphere: one
`default` scene of 200 gets a centre 7.7e14 m in front of the camera with the SkylakeX kernels and
397 m behind it with the Haswell ones (``OPENBLAS_CORETYPE=Haswell``), one circle more or less.
"""

from __future__ import annotations

import random
import time

import numpy as np
import pyransac3d

from spherebench.circles import sphere_circle_exact, sphere_circle_paper
from spherebench.cloud import Cloud
from spherebench.errors import SphereBenchError

#: Defaults: the subsample size, pyransac3d's own iteration count, and the inlier threshold (m)
#: (pyransac3d's default is 0.2 m, meant for metre-sized spheres; the paper's eps is 0.01 m).
POINTS = 10_000
ITERATIONS = 1000
THRESH_M = 0.01


def fit(points_m: np.ndarray, points: int = POINTS, iterations: int = ITERATIONS, thresh_m: float = THRESH_M,
        seed: int = 0) -> dict | None:
    """One pyransac3d sphere fit on finite points (N, 3) metres (subsampled to ``points``).

    Returns {"center_m" (3,), "radius_m", "inliers" (K,) indices into points_m (whole cloud),
    "subsample": number of points fitted, "ms": the fit's time} or None when it finds nothing.
    """
    p = np.asarray(points_m, np.float64).reshape(-1, 3)
    finite = np.flatnonzero(np.isfinite(p).all(axis=1))
    if len(finite) < 4:
        raise SphereBenchError(f"pyransac3d needs at least 4 finite points, the cloud has {len(finite)}")
    if iterations < 1 or points < 4 or not thresh_m > 0:
        raise SphereBenchError("pyransac3d: iterations >= 1, points >= 4 and thresh_m > 0 are required")
    rng = np.random.default_rng(seed)
    sub = finite if len(finite) <= points else np.sort(rng.choice(finite, size=points, replace=False))
    saved = random.getstate()
    random.seed(int(rng.integers(0, 2 ** 63)))
    try:
        t = time.perf_counter()
        with np.errstate(divide="ignore", invalid="ignore"):  # coplanar samples are its own business: no warning
            res = pyransac3d.Sphere().fit(p[sub], thresh=thresh_m, maxIteration=int(iterations))
        ms = (time.perf_counter() - t) * 1e3
    finally:
        random.setstate(saved)
    centre = np.asarray(res.center, np.float64).reshape(-1)
    if centre.size != 3 or not np.all(np.isfinite(centre)) or not np.isfinite(res.radius):
        return None
    radius = float(res.radius)
    dist = np.linalg.norm(p[finite] - centre, axis=1)
    inliers = finite[np.abs(dist - radius) <= thresh_m]
    return {"center_m": centre, "radius_m": radius, "inliers": inliers, "subsample": int(len(sub)), "ms": ms}


def detect(cloud: Cloud, points: int = POINTS, iterations: int = ITERATIONS, thresh_m: float = THRESH_M,
           seed: int = 0) -> list[dict]:
    """The peer as a detector: at most one sphere per cloud, as dicts with score (the inlier
    share of the cloud), center_m, radius_m, inliers (count), circle_exact and circle_paper (pixels,
    with the fitted radius; None without intrinsics or for a centre behind the camera)."""
    if not isinstance(cloud, Cloud):
        raise SphereBenchError(f"the pyransac3d peer needs a spherebench.cloud.Cloud, got {type(cloud).__name__}")
    if len(cloud.points) == 0:
        raise SphereBenchError("the point cloud is empty: nothing to fit")
    got = fit(cloud.points, points=points, iterations=iterations, thresh_m=thresh_m, seed=seed)
    if got is None:
        return []
    c, r = got["center_m"], got["radius_m"]
    circ_e = circ_p = None
    if cloud.intrinsics is not None and c[2] > 0 and r > 0:
        circ_p = sphere_circle_paper(cloud.intrinsics, c, r)
        circ_e = sphere_circle_exact(cloud.intrinsics, c, r) if np.linalg.norm(c) > r else None
    return [{"score": len(got["inliers"]) / max(len(cloud.points), 1), "center_m": c, "radius_m": r,
             "inliers": int(len(got["inliers"])), "circle_exact": circ_e, "circle_paper": circ_p, "ms": got["ms"]}]
