"""Table 2 on synthetic noiseless caps with answers known in closed form."""

import math

import numpy as np
import pytest

from spherebench.errors import SphereBenchError
from spherebench.eval.metrics.table2 import barycentre, sphere_rmse, table2_row

R = 0.12
C = np.array([0.1, -0.05, 1.5])


def _hemisphere(n_h: int = 40, n_phi: int = 72) -> tuple[np.ndarray, np.ndarray]:
    """Points on the camera-facing hemisphere, area-uniform: heights h (toward the camera, in
    units of R) at the midpoints of n_h equal bins of [0, 1] (Archimedes: equal heights, equal
    areas), n_phi azimuths. Returns points (n_h * n_phi, 3) and the height of each point."""
    h = (np.arange(n_h) + 0.5) / n_h
    phi = np.arange(n_phi) * 2 * np.pi / n_phi
    hh, pp = np.meshgrid(h, phi, indexing="ij")
    s = np.sqrt(1 - hh ** 2)
    pts = C + R * np.stack([s * np.cos(pp), s * np.sin(pp), -hh], axis=-1)  # -z faces the camera
    return pts.reshape(-1, 3), hh.reshape(-1)


def test_true_centre_gives_zero():
    pts, _ = _hemisphere()
    assert sphere_rmse(pts, C, R) == pytest.approx(0.0, abs=1e-12)


def test_shifted_centre_known_value():
    # the pole (facing the camera) and four points on the equator, centre shifted s away from
    # the camera: the pole's residual is s, each equator point's sqrt(R^2 + s^2) - R
    s = 0.01
    pts = C + R * np.array([[0, 0, -1], [1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0]], dtype=float)
    expected = math.sqrt((s ** 2 + 4 * (math.sqrt(R ** 2 + s ** 2) - R) ** 2) / 5)
    assert sphere_rmse(pts, C + [0, 0, s], R) == pytest.approx(expected, rel=1e-12)


def test_barycentre_of_hemisphere_and_table_row():
    pts, h = _hemisphere()
    # the mean height of the midpoints is 1/2: the barycentre is R/2 toward the camera
    b = barycentre(pts)
    assert b == pytest.approx(C + [0, 0, -R / 2], abs=1e-12)
    # from it (same side as the points), a point at height h lies at
    # R * sqrt((1 - h^2) + (h - 1/2)^2) = R * sqrt(5/4 - h)
    rmse_bary = R * math.sqrt(np.mean((np.sqrt(1.25 - h) - 1) ** 2))
    # "z filter": keep the points below height 0.9 (any subset works for the definitions)
    kept = pts[h < 0.9]
    rmse_bary_kept = sphere_rmse(kept, kept.mean(axis=0), R)
    refined = C + [0.0, 0.0, 0.001]
    row = table2_row(pts, kept, C, R, refined_centre_m=refined, true_centre_m=C)
    assert row["n_inliers"] == len(pts) and row["n_filtered"] == len(kept)
    assert row["rmse_ransac"] == pytest.approx(0.0, abs=1e-12)
    assert row["rmse_ransac_filtered"] == pytest.approx(0.0, abs=1e-12)
    assert row["rmse_barycentre"] == pytest.approx(rmse_bary_kept)
    assert row["rmse_ratio"] == pytest.approx(0.0, abs=1e-9)
    assert row["error_ransac_m"] == pytest.approx(0.0)
    assert row["error_barycentre_m"] == pytest.approx(np.linalg.norm(kept.mean(axis=0) - C))
    assert row["error_refined_m"] == pytest.approx(0.001)
    assert row["rmse_refined"] > 0
    full = table2_row(pts, pts, C, R, true_centre_m=C)
    assert full["rmse_barycentre"] == pytest.approx(rmse_bary, rel=1e-10)
    assert full["error_barycentre_m"] == pytest.approx(R / 2, abs=1e-12)
    assert "rmse_refined" not in full


def test_bad_input():
    pts, _ = _hemisphere(4, 8)
    with pytest.raises(SphereBenchError):
        sphere_rmse(np.zeros((0, 3)), C, R)
    with pytest.raises(SphereBenchError):
        sphere_rmse(pts, C, 0.0)
    with pytest.raises(SphereBenchError):
        table2_row(pts, pts[:, :2], C, R)
    with pytest.raises(SphereBenchError):
        table2_row(pts, pts, [0, np.nan, 1], R)
