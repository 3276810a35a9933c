"""The sphere fits the stages share: the known-radius minimal solver (three points, two centres),
Gauss-Newton with R fixed on 3D residuals, and the ray fits (the residual along each pixel's ray,
R fixed or free, or the centre held on its ray). Their readable counterparts: ``sphere_model``.
"""

from __future__ import annotations

import math

import numpy as np

from spherebench.method.compiled import kernel


@kernel
def known_radius_centres(points, i1, i2, i3, radius, out):
    """Both centres of radius R through points i1, i2, i3; out (2, 3) gets (far, near).

    Returns 0 (no solution: collinear or circumradius > R) or 2. Arithmetic of
    ``sphere_model.solve_known_radius`` in float64.
    """
    x1, y1, z1 = float(points[i1, 0]), float(points[i1, 1]), float(points[i1, 2])
    ax, ay, az = points[i2, 0] - x1, points[i2, 1] - y1, points[i2, 2] - z1
    bx, by, bz = points[i3, 0] - x1, points[i3, 1] - y1, points[i3, 2] - z1
    nx, ny, nz = ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx
    nn = nx * nx + ny * ny + nz * nz
    aa = ax * ax + ay * ay + az * az
    bb = bx * bx + by * by + bz * bz
    if not (nn > 1e-12 * aa * bb) or nn <= 0.0:
        return 0
    # circumcentre offset from p1: ((aa b - bb a) x n) / (2 nn)
    wx, wy, wz = aa * bx - bb * ax, aa * by - bb * ay, aa * bz - bb * az
    ox = (wy * nz - wz * ny) / (2.0 * nn)
    oy = (wz * nx - wx * nz) / (2.0 * nn)
    oz = (wx * ny - wy * nx) / (2.0 * nn)
    rho2 = ox * ox + oy * oy + oz * oz
    if rho2 > radius * radius:
        return 0
    h = math.sqrt(radius * radius - rho2)
    inv = 1.0 / math.sqrt(nn)
    ux, uy, uz = nx * inv, ny * inv, nz * inv
    qx, qy, qz = x1 + ox, y1 + oy, z1 + oz
    s = 1.0 if qx * ux + qy * uy + qz * uz >= 0.0 else -1.0
    out[0, 0], out[0, 1], out[0, 2] = qx + s * h * ux, qy + s * h * uy, qz + s * h * uz
    out[1, 0], out[1, 1], out[1, 2] = qx - s * h * ux, qy - s * h * uy, qz - s * h * uz
    return 2


@kernel
def refine_fixed_radius(points, idx, cx, cy, cz, radius, iterations):
    """Gauss-Newton on sum (||p - c|| - R)^2 over points[idx]; returns the centre (3,) float64.
    (Scalar sums and ``cholesky_solve``: a LAPACK call per step cost more than the sums.)"""
    c = np.array([cx, cy, cz])
    A = np.zeros((4, 4))
    g = np.zeros(4)
    step = np.zeros(4)
    for _ in range(iterations):
        a00 = a10 = a11 = a20 = a21 = a22 = g0 = g1 = g2 = 0.0
        for k in range(idx.shape[0]):
            i = idx[k]
            dx, dy, dz = points[i, 0] - c[0], points[i, 1] - c[1], points[i, 2] - c[2]
            d = math.sqrt(dx * dx + dy * dy + dz * dz)
            if d <= 1e-12:
                continue
            u0, u1, u2 = dx / d, dy / d, dz / d
            r = d - radius
            a00 += u0 * u0
            a10 += u1 * u0
            a11 += u1 * u1
            a20 += u2 * u0
            a21 += u2 * u1
            a22 += u2 * u2
            g0 += u0 * r
            g1 += u1 * r
            g2 += u2 * r
        A[0, 0], A[1, 0], A[1, 1], A[2, 0], A[2, 1], A[2, 2] = a00, a10, a11, a20, a21, a22
        g[0], g[1], g[2] = g0, g1, g2
        # J = -u, so the GN step -(J^T J)^-1 J^T r = +A^-1 g; a singular A (too few or collinear
        # directions) ends the fit where it is
        det = a00 * (a11 * a22 - a21 * a21) - a10 * (a10 * a22 - a21 * a20) + a20 * (a10 * a21 - a11 * a20)
        if abs(det) < 1e-18 or cholesky_solve(A, g, 3, step) < 0.0:
            break
        c[0] += step[0]
        c[1] += step[1]
        c[2] += step[2]
        if math.sqrt(step[0] ** 2 + step[1] ** 2 + step[2] ** 2) < 1e-9:
            break
    return c


@kernel
def fit_free_radius(points, idx, cx, cy, cz, radius, iterations):
    """Gauss-Newton on (centre, radius) from (c, R) over points[idx].

    Returns (centre (3,), radius, standard error of the radius, RMS residual), as
    ``sphere_model.fit_free_radius``.
    """
    x = np.array([cx, cy, cz, radius])
    A = np.zeros((4, 4))
    g = np.empty(4)
    n = idx.shape[0]
    for _ in range(iterations):
        A[:] = 0.0
        g[:] = 0.0
        for k in range(n):
            i = idx[k]
            dx, dy, dz = points[i, 0] - x[0], points[i, 1] - x[1], points[i, 2] - x[2]
            d = max(math.sqrt(dx * dx + dy * dy + dz * dz), 1e-12)
            j0, j1, j2, j3 = -dx / d, -dy / d, -dz / d, -1.0
            r = d - x[3]
            jj = (j0, j1, j2, j3)
            for a in range(4):
                g[a] += jj[a] * r
                for b in range(4):
                    A[a, b] += jj[a] * jj[b]
        if abs(np.linalg.det(A)) < 1e-30:
            return x[:3].copy(), x[3], np.inf, np.nan
        step = -np.linalg.solve(A, g)
        x += step
        if math.sqrt((step * step).sum()) < 1e-10:
            break
    sse = 0.0
    for k in range(n):
        i = idx[k]
        dx, dy, dz = points[i, 0] - x[0], points[i, 1] - x[1], points[i, 2] - x[2]
        r = math.sqrt(dx * dx + dy * dy + dz * dz) - x[3]
        sse += r * r
    s2 = sse / max(n - 4, 1)
    cov = np.linalg.inv(A)
    se = math.sqrt(max(s2 * cov[3, 3], 0.0))
    return x[:3].copy(), x[3], se, math.sqrt(sse / max(n, 1))


@kernel
def cholesky_solve(A, g, npar, x):
    """Solve A x = g for the leading npar x npar block of a symmetric A (4, 4) by Cholesky, in place
    of a LAPACK call (whose per-call cost exceeded the fit's). Returns 1 / L[npar-1, npar-1]^2, the
    last diagonal element of A^-1 (the variance factor of the last parameter), or -1 when A is not
    positive definite (then x is undefined)."""
    L = np.zeros((4, 4))
    for i in range(npar):
        for j in range(i + 1):
            acc = A[i, j]
            for k in range(j):
                acc -= L[i, k] * L[j, k]
            if i == j:
                if not acc > 1e-300:
                    return -1.0
                L[i, i] = math.sqrt(acc)
            else:
                L[i, j] = acc / L[j, j]
    y = np.zeros(4)
    for i in range(npar):
        acc = g[i]
        for k in range(i):
            acc -= L[i, k] * y[k]
        y[i] = acc / L[i, i]
    for i in range(npar - 1, -1, -1):
        acc = y[i]
        for k in range(i + 1, npar):
            acc -= L[k, i] * x[k]
        x[i] = acc / L[i, i]
    return 1.0 / (L[npar - 1, npar - 1] * L[npar - 1, npar - 1])


@kernel
def unit_rays(points, idx, out):
    """The viewing rays of points[idx] (K,) into out (>= K, 4) float64: (u (3,) = p / |p|, |p| m), which
    every Gauss-Newton pass of a fit needs (computed once: a square root and a division per point,
    and the scattered loads, cost as much as the pass itself). Returns out[:K]."""
    for k in range(idx.shape[0]):
        i = idx[k]
        px, py, pz = float(points[i, 0]), float(points[i, 1]), float(points[i, 2])
        pn = math.sqrt(px * px + py * py + pz * pz)
        ipn = 1.0 / pn
        out[k, 0], out[k, 1], out[k, 2], out[k, 3] = px * ipn, py * ipn, pz * ipn, pn
    return out[:idx.shape[0]]


@kernel
def ray_normal_equations(rays, x0, x1, x2, r, s_floor, with_radius):
    """The Gauss-Newton normal equations of the ray residuals of the points on rays (K, 4)
    (``unit_rays``) about centre (x0, x1, x2) and radius r: (A (4, 4) lower triangle,
    g (4,) = -J^T res, sum of squared residuals).

    res = |p| - u.c + s, s = sqrt(r^2 - |c|^2 + (u.c)^2) (0 for rays that miss), u = p / |p|;
    d res / d c = -u + (u.c u - c) / s, d res / d r = r / s, with s floored at s_floor in the
    derivatives only (near the outline s -> 0 and they explode; the residual stays exact there).
    with_radius False: the r row and column stay 0. (Scalar accumulators: sums kept in a (4, 4)
    array went through memory and cost 3-4 times as much.)
    """
    a00 = a10 = a11 = a20 = a21 = a22 = a30 = a31 = a32 = a33 = 0.0
    g0 = g1 = g2 = g3 = 0.0
    sse = 0.0
    cc = x0 * x0 + x1 * x1 + x2 * x2
    for k in range(rays.shape[0]):
        ux, uy, uz, pn = rays[k, 0], rays[k, 1], rays[k, 2], rays[k, 3]
        tc = ux * x0 + uy * x1 + uz * x2
        s = math.sqrt(max(r * r - cc + tc * tc, 0.0))
        res = pn - tc + s
        isj = 1.0 / max(s, s_floor)
        j0 = -ux + (tc * ux - x0) * isj
        j1 = -uy + (tc * uy - x1) * isj
        j2 = -uz + (tc * uz - x2) * isj
        sse += res * res
        a00 += j0 * j0
        a10 += j1 * j0
        a11 += j1 * j1
        a20 += j2 * j0
        a21 += j2 * j1
        a22 += j2 * j2
        g0 -= j0 * res
        g1 -= j1 * res
        g2 -= j2 * res
        if with_radius:
            j3 = r * isj
            a30 += j3 * j0
            a31 += j3 * j1
            a32 += j3 * j2
            a33 += j3 * j3
            g3 -= j3 * res
    A = np.zeros((4, 4))
    A[0, 0], A[1, 0], A[1, 1], A[2, 0], A[2, 1], A[2, 2] = a00, a10, a11, a20, a21, a22
    A[3, 0], A[3, 1], A[3, 2], A[3, 3] = a30, a31, a32, a33
    g = np.empty(4)
    g[0], g[1], g[2], g[3] = g0, g1, g2, g3
    return A, g, sse


@kernel
def ray_step(rays, c, radius, s_min):
    """One Gauss-Newton step of the ray residuals of the points on rays (K, 4) (``unit_rays``) with the
    radius fixed, applied to the centre c (3,) in place (left as it is if the normal matrix is
    singular); returns the move (m)."""
    A, g, _ = ray_normal_equations(rays, c[0], c[1], c[2], radius, max(s_min * radius, 1e-12), False)
    step = np.zeros(4)
    if cholesky_solve(A, g, 3, step) < 0.0:
        return 0.0
    c[0] += step[0]
    c[1] += step[1]
    c[2] += step[2]
    return math.sqrt(step[0] ** 2 + step[1] ** 2 + step[2] ** 2)


@kernel
def fit_ray(rays, cx, cy, cz, radius, free_radius, iterations, s_min, se_s_min):
    """Gauss-Newton on the ray residuals |p| - t_near(c, r) of the points on rays (K, 4)
    (``unit_rays``; depth noise model).

    t_near = u.c - s, s = sqrt(r^2 - |c|^2 + (u.c)^2), u = p / |p| (s = 0 for rays that miss: the
    residual is then the depth past the point of closest approach). Near the outline s -> 0 and
    the derivative explodes: s is floored at ``s_min * r`` in the derivative only
    (``ray_normal_equations``); the radius's standard error floors it at ``se_s_min * r``.
    free_radius: fit r too, else r = radius.
    Returns (centre (3,), r, standard error of r (nan if fixed), RMS residual).
    """
    x = np.array([cx, cy, cz, radius])
    npar = 4 if free_radius else 3
    step = np.zeros(4)
    n = rays.shape[0]
    for _ in range(iterations):
        A, g, _ = ray_normal_equations(rays, x[0], x[1], x[2], x[3], max(s_min * abs(x[3]), 1e-12),
                                       free_radius)
        if cholesky_solve(A, g, npar, step) < 0.0:
            break
        for a in range(npar):
            x[a] += step[a]
        if math.sqrt(step[0] ** 2 + step[1] ** 2 + step[2] ** 2 + (step[3] ** 2 if free_radius else 0.0)) < 1e-9:
            break
    # the residuals at the solution, and for the radius's standard error a normal matrix whose
    # derivatives floor s at se_s_min r: the floor of the fit (s_min) lets the few pixels at the
    # outline, where the residual has no derivative, claim a radius known to a fraction of a mm
    s_floor = max(max(s_min, se_s_min) * abs(x[3]), 1e-12)
    A, g, sse = ray_normal_equations(rays, x[0], x[1], x[2], x[3], s_floor, free_radius)
    se = math.nan
    if free_radius:
        var_r = cholesky_solve(A, g, 4, step)
        se = math.sqrt(max(sse / max(n - 4, 1) * var_r, 0.0)) if var_r > 0.0 else math.inf
    return x[:3].copy(), x[3], se, math.sqrt(sse / max(n, 1))


@kernel
def _on_ray(A, ax, ay, az):
    """The normal matrix A (4, 4, lower triangle; ``ray_normal_equations``) projected on the unit
    direction a: (a^T A_cc a, a^T A_cr), the range's own entry and its entry with the radius."""
    a_tt = (ax * ax * A[0, 0] + ay * ay * A[1, 1] + az * az * A[2, 2]
            + 2.0 * (ax * ay * A[1, 0] + ax * az * A[2, 0] + ay * az * A[2, 1]))
    return a_tt, ax * A[3, 0] + ay * A[3, 1] + az * A[3, 2]


@kernel
def fit_range(rays, cx, cy, cz, radius, free_radius, iterations, s_min, se_s_min):
    """``fit_ray`` with the centre held on its ray, c = t a (a = c / |c|): Gauss-Newton on the range t
    (and r where free_radius), the normal equations projected on a. Same returns as ``fit_ray``."""
    t, r = math.sqrt(cx * cx + cy * cy + cz * cz), radius
    ax, ay, az = cx / t, cy / t, cz / t
    for _ in range(iterations):
        A, g, _ = ray_normal_equations(rays, t * ax, t * ay, t * az, r, max(s_min * abs(r), 1e-12), free_radius)
        a_tt, a_tr = _on_ray(A, ax, ay, az)
        g_t = ax * g[0] + ay * g[1] + az * g[2]
        if not free_radius:
            if not a_tt > 0.0:
                break
            t += g_t / a_tt
            continue
        det = a_tt * A[3, 3] - a_tr * a_tr
        if not det > 0.0:
            break
        t += (A[3, 3] * g_t - a_tr * g[3]) / det
        r += (a_tt * g[3] - a_tr * g_t) / det
    s_floor = max(max(s_min, se_s_min) * abs(r), 1e-12)
    A, g, sse = ray_normal_equations(rays, t * ax, t * ay, t * az, r, s_floor, free_radius)
    n = rays.shape[0]
    se = math.nan
    if free_radius:
        a_tt, a_tr = _on_ray(A, ax, ay, az)
        det = a_tt * A[3, 3] - a_tr * a_tr
        se = math.sqrt(max(sse / max(n - 2, 1) * a_tt / det, 0.0)) if det > 0.0 else math.inf
    c = np.empty(3)
    c[0], c[1], c[2] = t * ax, t * ay, t * az
    return c, r, se, math.sqrt(sse / max(n, 1))
