"""The paper's Table 2 (RMSE of the sphere fit before and after the z-score filter), defined.

The paper does not define its RMSE. Here, for points P = {p_k} (K, 3) metres, a centre c (3,)
metres and the known ball radius R metres:

    RMSE(P, c) = sqrt( (1/K) * sum_k ( ||p_k - c|| - R )^2 )      [metres]

i.e. the root mean square distance of the points from the sphere of radius R about c
(0 for noiseless points on that sphere). Table 2's three columns, per scene and z threshold:

- ``rmse_ransac``:          RMSE(RANSAC inliers, RANSAC centre)
- ``rmse_ransac_filtered``: RMSE(z-filtered points, RANSAC centre)
- ``rmse_barycentre``:      RMSE(z-filtered points, barycentre of the z-filtered points)

and what the paper could not show, with ground truth:

- ``error_ransac_m``, ``error_barycentre_m``: ||centre - true centre||, metres;
- with the improved refinement's centre (least squares of ||p - c|| - R, R fixed), when given:
  ``rmse_refined`` = RMSE(z-filtered points, refined centre) and ``error_refined_m``.

The "RANSAC inliers" are the points the detector assigned to the chosen candidate (within
R +/- eps of it) and the "z-filtered points" those left by its z-score filter; the detector
supplies both (this module only scores them). Note that the barycentre of points on the
visible cap is pulled toward the camera (by R/2 for a hemisphere), so a low
``rmse_barycentre`` and a low ``error_barycentre_m`` are different claims.
"""

from __future__ import annotations

import numpy as np

from spherebench import sphere_distance
from spherebench.errors import SphereBenchError


def _points(a, name: str) -> np.ndarray:
    arr = np.asarray(a, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise SphereBenchError(f"{name} must have shape (K, 3) metres, got {arr.shape}")
    if arr.shape[0] == 0:
        raise SphereBenchError(f"{name} is empty: the RMSE needs at least one point")
    if not np.all(np.isfinite(arr)):
        raise SphereBenchError(f"{name} hold NaN or infinite values")
    return arr


def _centre(c, name: str) -> np.ndarray:
    arr = np.asarray(c, dtype=np.float64).reshape(-1)
    if arr.shape != (3,) or not np.all(np.isfinite(arr)):
        raise SphereBenchError(f"{name} must be three finite coordinates (x, y, z) metres")
    return arr


def sphere_rmse(points_m, centre_m, radius_m: float) -> float:
    """RMSE (metres) of ||p - c|| - R over points (K, 3) m, centre (3,) m, radius R m."""
    p = _points(points_m, "points")
    c = _centre(centre_m, "centre")
    if not radius_m > 0:
        raise SphereBenchError(f"radius_m={radius_m} must be > 0 metres")
    return sphere_distance.rmse(p, c, radius_m)


def barycentre(points_m) -> np.ndarray:
    """Mean (3,) metres of points (K, 3) metres: the paper's refined centre."""
    return _points(points_m, "points").mean(axis=0)


def table2_row(inlier_points_m, filtered_points_m, ransac_centre_m, radius_m: float,
               barycentre_m=None, refined_centre_m=None, true_centre_m=None) -> dict:
    """One row of Table 2 (definitions in the module docstring); metres.

    inlier_points_m: (K, 3) the RANSAC inliers. filtered_points_m: (K', 3) the points kept by
    the z-score filter. ransac_centre_m: (3,). barycentre_m: (3,), default the mean of the
    filtered points. refined_centre_m, true_centre_m: (3,) or None.
    Returns rmse_ransac, rmse_ransac_filtered, rmse_barycentre, rmse_ratio (rmse_ransac /
    rmse_barycentre), n_inliers, n_filtered; rmse_refined if a refined centre is given;
    error_ransac_m, error_barycentre_m (and error_refined_m) if the true centre is given.
    """
    inliers = _points(inlier_points_m, "inlier points")
    kept = _points(filtered_points_m, "z-filtered points")
    c_ransac = _centre(ransac_centre_m, "RANSAC centre")
    c_bary = kept.mean(axis=0) if barycentre_m is None else _centre(barycentre_m, "barycentre")
    row = {
        "n_inliers": int(len(inliers)),
        "n_filtered": int(len(kept)),
        "rmse_ransac": sphere_rmse(inliers, c_ransac, radius_m),
        "rmse_ransac_filtered": sphere_rmse(kept, c_ransac, radius_m),
        "rmse_barycentre": sphere_rmse(kept, c_bary, radius_m),
    }
    row["rmse_ratio"] = row["rmse_ransac"] / row["rmse_barycentre"] if row["rmse_barycentre"] > 0 else float("inf")
    c_ref = None if refined_centre_m is None else _centre(refined_centre_m, "refined centre")
    if c_ref is not None:
        row["rmse_refined"] = sphere_rmse(kept, c_ref, radius_m)
    if true_centre_m is not None:
        c_true = _centre(true_centre_m, "true centre")
        row["error_ransac_m"] = float(np.linalg.norm(c_ransac - c_true))
        row["error_barycentre_m"] = float(np.linalg.norm(c_bary - c_true))
        if c_ref is not None:
            row["error_refined_m"] = float(np.linalg.norm(c_ref - c_true))
    return row
