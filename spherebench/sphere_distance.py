"""A sphere of known radius and the points said to lie on it: the one definition of their distance
and of its root mean square (Table 2's RMSE, as this project defines it; the paper gives none),
shared by the detectors and the metrics."""

from __future__ import annotations

import numpy as np


def residuals(points_m: np.ndarray, centre_m, radius_m: float) -> np.ndarray:
    """Signed distances (N,) metres of points (N, 3) metres from the sphere of radius ``radius_m``
    about ``centre_m`` (3,) metres: ||p - c|| - R (negative inside)."""
    p = np.asarray(points_m, dtype=np.float64).reshape(-1, 3)
    return np.linalg.norm(p - np.asarray(centre_m, np.float64).reshape(1, 3), axis=1) - float(radius_m)


def rmse(points_m: np.ndarray, centre_m, radius_m: float) -> float:
    """Root mean square of ``residuals``, metres; NaN for no points."""
    r = residuals(points_m, centre_m, radius_m)
    return float(np.sqrt(np.mean(r * r))) if len(r) else float("nan")
