"""The sphere model: minimal solvers and least-squares fits (readable numpy; the residuals and their
RMS, shared with the metrics, are ``spherebench.sphere_distance``'s).

This module is the reference: the compiled kernels (``fit_kernels``, ``unorganised``) do the same arithmetic point
by point and the tests compare them with these functions.

Minimal solvers (three points -> centre):
- ``solve_known_radius``: the three points fix their circumcircle (centre q, radius rho) and the
  plane's normal n; a sphere of radius R through them has its centre on the line q + t n, at
  t = +/- sqrt(R^2 - rho^2): two solutions, none if rho > R. A depth camera sees the side of a
  ball that faces it, so the centre is the solution farther from the camera (the origin).
- ``solve_eq12_lstsq``: the paper's Eq. (12) read literally. Its 3x3 matrix has rank 2 (row 3 is
  row 2 minus row 1, and so is the right-hand side), so the equations only say "the centre is on
  the line q + t n"; a least-squares solver returns the minimum-norm point of that line, the foot
  of the perpendicular from the camera. Kept as an ablation.
"""

from __future__ import annotations

import numpy as np

#: Triangles whose sine of the smallest-angle measure |a x b| / (|a| |b|) is below this are
#: treated as collinear (no circumcircle).
COLLINEAR_SINE = 1e-6


def _as3(p) -> np.ndarray:
    return np.asarray(p, dtype=np.float64).reshape(-1, 3)


def circumcircle(p1, p2, p3) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Circumcentres q (M, 3), circumradii rho (M,), unit normals n (M, 3) and a validity mask (M,).

    p1, p2, p3: (M, 3) or (3,) metres. Invalid (collinear or repeated points): q, rho, n are NaN.
    """
    p1, p2, p3 = _as3(p1), _as3(p2), _as3(p3)
    a, b = p2 - p1, p3 - p1
    n = np.cross(a, b)
    nn = np.einsum("ij,ij->i", n, n)
    aa, bb = np.einsum("ij,ij->i", a, a), np.einsum("ij,ij->i", b, b)
    ok = nn > (COLLINEAR_SINE ** 2) * aa * bb
    ok &= nn > 0
    with np.errstate(divide="ignore", invalid="ignore"):
        off = np.cross(aa[:, None] * b - bb[:, None] * a, n) / (2.0 * nn[:, None])
        q = p1 + off
        rho = np.sqrt(np.einsum("ij,ij->i", off, off))
        unit = n / np.sqrt(nn)[:, None]
    q[~ok], rho[~ok], unit[~ok] = np.nan, np.nan, np.nan
    return q, rho, unit, ok


def solve_known_radius(p1, p2, p3, radius_m: float, both: bool = False):
    """Centres (M, 3) of the spheres of radius R through three points, the far one from the origin.

    Returns (centres (M, 3), valid (M,)); with ``both=True`` returns (near (M, 3), far (M, 3),
    valid (M,)). Invalid where the points are collinear or their circumradius exceeds R (NaN rows).
    """
    q, rho, n, ok = circumcircle(p1, p2, p3)
    with np.errstate(invalid="ignore"):
        ok &= rho <= radius_m
        h = np.sqrt(np.maximum(radius_m * radius_m - rho * rho, 0.0))
    # the sign along n that moves away from the camera at the origin
    s = np.where(np.einsum("ij,ij->i", q, n) >= 0.0, 1.0, -1.0)
    far = q + (s * h)[:, None] * n
    near = q - (s * h)[:, None] * n
    far[~ok], near[~ok] = np.nan, np.nan
    return (near, far, ok) if both else (far, ok)


def eq12_system(p1, p2, p3) -> tuple[np.ndarray, np.ndarray]:
    """The paper's Eq. (12) as printed: A (M, 3, 3), b (M, 3) with A [a b c]^T = b."""
    p1, p2, p3 = _as3(p1), _as3(p2), _as3(p3)
    A = np.stack([p2 - p1, p3 - p1, p3 - p2], axis=1)
    s1, s2, s3 = (np.einsum("ij,ij->i", p, p) for p in (p1, p2, p3))
    b = 0.5 * np.stack([s2 - s1, s3 - s1, s3 - s2], axis=1)
    return A, b


def solve_eq12_lstsq(p1, p2, p3) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Minimum-norm least-squares solution of Eq. (12): (centres (M, 3), radii (M,), valid (M,)).

    The radius is Eq. (4) with the first point, as the paper computes it. Equal to
    ``numpy.linalg.lstsq(A, b)`` (tested) but in closed form: the foot of the perpendicular from
    the origin to the line of centres q + t n.
    """
    q, _, n, ok = circumcircle(p1, p2, p3)
    c = q - np.einsum("ij,ij->i", q, n)[:, None] * n
    r = np.linalg.norm(_as3(p1) - c, axis=1)
    return c, r, ok


def refine_fixed_radius(points_m: np.ndarray, centre_m, radius_m: float, iterations: int = 10,
                        tol_m: float = 1e-9) -> np.ndarray:
    """Gauss-Newton on sum (||p - c|| - R)^2 over the centre, R fixed: the refined centre (3,).

    points_m: (N, 3), N >= 3. Stops when the step is below tol_m. The barycentre of a visible cap
    is pulled toward the camera; this is not.
    """
    p = _as3(points_m)
    c = np.asarray(centre_m, np.float64).reshape(3).copy()
    for _ in range(iterations):
        d = p - c
        dist = np.linalg.norm(d, axis=1)
        keep = dist > 1e-12
        u = d[keep] / dist[keep, None]  # Jacobian rows are -u
        r = dist[keep] - radius_m
        JtJ = u.T @ u
        Jtr = -(u.T @ r)
        try:
            step = -np.linalg.solve(JtJ, Jtr)
        except np.linalg.LinAlgError:
            break
        c += step
        if np.linalg.norm(step) < tol_m:
            break
    return c


def fit_free_algebraic(points_m: np.ndarray) -> tuple[np.ndarray, float]:
    """Algebraic (Kasa) sphere fit: |p|^2 = 2 p.c + k, linear least squares. (centre (3,), radius)."""
    p = _as3(points_m)
    A = np.column_stack([2.0 * p, np.ones(len(p))])
    sol, *_ = np.linalg.lstsq(A, np.einsum("ij,ij->i", p, p), rcond=None)
    c = sol[:3]
    return c, float(np.sqrt(max(sol[3] + c @ c, 0.0)))


def fit_free_radius(points_m: np.ndarray, centre_m=None, radius_m: float | None = None,
                    iterations: int = 10) -> tuple[np.ndarray, float, float, float]:
    """Geometric fit of centre and radius (Gauss-Newton from (centre_m, radius_m), else algebraic).

    Returns (centre (3,), radius m, standard error of the radius m, RMS residual m). The standard
    error is sqrt(s^2 (J^T J)^-1)[r, r] with s^2 the residual variance; inf when ill-posed.
    """
    p = _as3(points_m)
    if centre_m is None or radius_m is None:
        c, r = fit_free_algebraic(p)
    else:
        c, r = np.asarray(centre_m, np.float64).reshape(3).copy(), float(radius_m)
    JtJ = np.eye(4)
    for _ in range(iterations):
        d = p - c
        dist = np.maximum(np.linalg.norm(d, axis=1), 1e-12)
        J = np.column_stack([-d / dist[:, None], -np.ones(len(p))])
        res = dist - r
        JtJ = J.T @ J
        try:
            step = -np.linalg.solve(JtJ, J.T @ res)
        except np.linalg.LinAlgError:
            return c, r, float("inf"), float("nan")
        c, r = c + step[:3], r + step[3]
        if np.linalg.norm(step) < 1e-10:
            break
    res = np.linalg.norm(p - c, axis=1) - r
    dof = max(len(p) - 4, 1)
    s2 = float(res @ res) / dof
    try:
        se = float(np.sqrt(max(s2 * np.linalg.inv(JtJ)[3, 3], 0.0)))
    except np.linalg.LinAlgError:
        se = float("inf")
    return c, float(r), se, float(np.sqrt(np.mean(res * res)))
