"""Compiled hot loops of the detector (numba, single thread, cached on disk).

Each kernel has a readable counterpart that the tests compare it with: the minimal solver and the
fits in ``sphere_model``, the search loops and the window statistics in ``reference``.
Random numbers come from splitmix64 (``next_u01``), which ``reference`` replays exactly in pure
Python, so the compiled and the reference search draw the same samples.

Conventions: points (N, 3) float32 metres in the camera frame; an organised cloud comes with
``index_image`` (H, W) int32, the point index of each pixel or -1 where depth is invalid.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

_GOLDEN = np.uint64(0x9E3779B97F4A7C15)
_MIX1 = np.uint64(0xBF58476D1CE4E5B9)
_MIX2 = np.uint64(0x94D049BB133111EB)
_INV53 = 1.0 / 9007199254740992.0  # 2^-53

# Categories of a pixel of a candidate's window (window statistics, in this order).
ST_VALID_DISC, ST_INLIER, ST_FRONT, ST_FRONT_NEAR, ST_BEHIND, ST_INVALID_DISC, ST_SSE, ST_RING, ST_RING_CONT = range(9)
N_STATS = 9

#: The outline ring: rays passing the centre at R to RING_FACTOR * R.
RING_FACTOR = 1.3


@njit(cache=True)
def next_u01(state):
    """splitmix64: advance state (uint64 array of 1) and return a float64 uniform in [0, 1)."""
    state[0] += _GOLDEN
    z = state[0]
    z = (z ^ (z >> np.uint64(30))) * _MIX1
    z = (z ^ (z >> np.uint64(27))) * _MIX2
    z = z ^ (z >> np.uint64(31))
    return float(z >> np.uint64(11)) * _INV53


@njit(cache=True)
def finite_rows(points):
    """(N,) bool: rows of points (N, 3) with three finite coordinates; and their count."""
    n = points.shape[0]
    ok = np.empty(n, np.bool_)
    k = 0
    for i in range(n):
        f = math.isfinite(points[i, 0]) and math.isfinite(points[i, 1]) and math.isfinite(points[i, 2])
        ok[i] = f
        k += f
    return ok, k


@njit(cache=True)
def build_index_image(rows, cols, height, width):
    """(H, W) int32 image of point indices (-1: no point) from per-point pixel rows, cols (N,)."""
    img = np.full((height, width), -1, np.int32)
    for i in range(rows.shape[0]):
        r, c = rows[i], cols[i]
        if 0 <= r < height and 0 <= c < width:
            img[r, c] = i
    return img


@njit(cache=True)
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


@njit(cache=True)
def faces_camera(points, i, cx, cy, cz):
    """True if point i is on the camera-facing side of the sphere centred at c: (p - c) . p < 0."""
    px, py, pz = points[i, 0], points[i, 1], points[i, 2]
    return (px - cx) * px + (py - cy) * py + (pz - cz) * pz < 0.0


@njit(cache=True)
def shell_eps(cz, eps, fx, noise_k, subpixel, baseline, cap):
    """Noise-aware shell half-width at depth cz: max(eps, k sigma_z(cz)), at most cap (metres)."""
    e = eps
    if subpixel > 0.0 and noise_k > 0.0:
        sz = noise_k * cz * cz * subpixel / (fx * baseline)
        if sz > e:
            e = sz
    return min(e, cap) if cap > eps else eps


@njit(cache=True)
def disc_radius_px(cz, dist, radius, fx):
    """Approximate pixel radius of a sphere's image at centre depth cz, distance |c| (pinhole)."""
    return fx * radius / math.sqrt(max(dist * dist - radius * radius, 1e-12)) * dist / cz


@njit(cache=True)
def ray_residual(px, py, pz, cx, cy, cz, radius):
    """Depth residual along the point's ray: |p| - t_near, and whether the ray meets the sphere.

    A depth camera's noise is along the viewing ray, so the ray residual is the natural error of
    an organised cloud's point (the 3D distance ||p - c|| - R shrinks it by cos of the incidence
    angle and biases fits toward the camera). Rays that miss the sphere return (nan, False).
    """
    pn = math.sqrt(px * px + py * py + pz * pz)
    if pn <= 0.0:
        return math.nan, False
    tc = (px * cx + py * cy + pz * cz) / pn
    m2 = cx * cx + cy * cy + cz * cz - tc * tc
    if m2 > radius * radius:
        return math.nan, False
    return pn - (tc - math.sqrt(radius * radius - m2)), True


@njit(cache=True)
def window_stats(points, index_image, cx, cy, cz, radius, eps, fx, fy, ppx, ppy, stride, out):
    """Classify the pixels of a candidate's silhouette; out (N_STATS,) float64 gets the counts.

    For a pixel whose ray meets the sphere (the silhouette, undistorted pinhole) with point p and
    ray residual dt = |p| - t_near: INLIER if |dt| <= eps (SSE sums dt^2), else FRONT (an occluder,
    dt < 0; FRONT_NEAR if also dt >= -R/2: a surface hugging the sphere, as a cylinder of the same
    radius does) or BEHIND (dt > 0: seen through the ball, evidence against it). Silhouette pixels
    without a point count as INVALID_DISC. Rays passing the centre at R to RING_FACTOR R form the
    outline RING; RING_CONT counts those whose point is within eps of the depth where the ray
    passes the centre (a surface continuing beyond the outline: a wall, a plane, a bigger object).
    ``stride`` visits every stride-th pixel (counts scaled).
    """
    for k in range(N_STATS):
        out[k] = 0.0
    h, w = index_image.shape
    dist = math.sqrt(cx * cx + cy * cy + cz * cz)
    if cz <= radius or dist <= radius:
        return
    rpx = disc_radius_px(cz, dist, radius, max(fx, fy)) * RING_FACTOR * 1.05 + 2.0
    u0 = fx * cx / cz + ppx
    v0 = fy * cy / cz + ppy
    ring2 = (RING_FACTOR * radius) ** 2
    c0 = max(0, int(math.floor(u0 - rpx)))
    c1 = min(w - 1, int(math.ceil(u0 + rpx)))
    r0 = max(0, int(math.floor(v0 - rpx)))
    r1 = min(h - 1, int(math.ceil(v0 + rpx)))
    cos_lim = math.sqrt(1.0 - (radius / dist) ** 2)
    for r in range(r0, r1 + 1, stride):
        for c in range(c0, c1 + 1, stride):
            i = index_image[r, c]
            if i < 0:
                rx, ry = (c - ppx) / fx, (r - ppy) / fy
                nrm = math.sqrt(rx * rx + ry * ry + 1.0)
                if (rx * cx + ry * cy + cz) / (nrm * dist) >= cos_lim:
                    out[ST_INVALID_DISC] += 1.0
                continue
            dt, hit = ray_residual(points[i, 0], points[i, 1], points[i, 2], cx, cy, cz, radius)
            if not hit:
                px, py, pz = points[i, 0], points[i, 1], points[i, 2]
                pn = math.sqrt(px * px + py * py + pz * pz)
                tc = (px * cx + py * cy + pz * cz) / pn
                if tc > 0.0 and dist * dist - tc * tc <= ring2:
                    out[ST_RING] += 1.0
                    if abs(pn - tc) <= eps:
                        out[ST_RING_CONT] += 1.0
                continue
            out[ST_VALID_DISC] += 1.0
            if abs(dt) <= eps:
                out[ST_INLIER] += 1.0
                out[ST_SSE] += dt * dt
            elif dt < 0.0:
                out[ST_FRONT] += 1.0
                if dt >= -0.5 * radius:
                    out[ST_FRONT_NEAR] += 1.0
            else:
                out[ST_BEHIND] += 1.0
    s2 = float(stride * stride)
    for k in range(N_STATS):
        out[k] *= s2


# ----------------------------------------------------------------------------------------------
# Organised clouds: the search. Scalar parameters travel in one float64 array (``prm``, indexed by
# the P_* names below): one argument instead of twenty keeps numba's call overhead small.

P_FX, P_FY, P_PPX, P_PPY, P_R, P_EPS, P_NOISE_A, P_NOISE_K, P_EPS_CAP, P_SAMPLE_R, P_SIGMA_T, P_H_MAX, \
    P_RETRIES, P_PRETEST_N, P_PRETEST_FRAC, P_SCORE_MAX, P_ITERS, P_DEDUP = range(18)
N_PRM = 18


@njit(cache=True)
def noise_eps(cz, eps, noise_a, noise_k, cap):
    """Shell half-width at depth cz: max(eps, k sigma_z), sigma_z = noise_a cz^2 (metres), at most cap."""
    e = max(eps, noise_k * noise_a * cz * cz)
    return min(e, cap) if cap > eps else eps


@njit(cache=True)
def prepare_organised(points, rows, cols, img, mm_limit):
    """One pass over an organised cloud: fills the index image img (H, W) int32; returns
    (finite count, count of |z| > mm_limit).

    Points with a non-finite coordinate or z <= 0 get no pixel (-1), so the search never meets them.
    """
    height, width = img.shape
    img[:] = -1
    n_ok = 0
    n_big = 0
    for i in range(points.shape[0]):
        x, y, z = points[i, 0], points[i, 1], points[i, 2]
        if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(z)):
            continue
        n_ok += 1
        if abs(z) > mm_limit:
            n_big += 1
        r, c = rows[i], cols[i]
        if z > 0.0 and 0 <= r < height and 0 <= c < width:
            img[r, c] = i
    return n_ok, n_big


#: Channels of the summed-area table: depth, valid count, squared depth (interleaved, so that one
#: corner of a patch is one cache line: the search is bound by memory latency).
T_Z, T_N, T_Z2 = range(3)


@njit(cache=True)
def depth_integrals(points, index_image, tab):
    """Fill tab (H + 1, W + 1, 3) float64 with the summed-area tables of z, count and z^2."""
    h, w = index_image.shape
    tab[0, :, :] = 0.0
    for r in range(h):
        a = 0.0
        b = 0.0
        k = 0.0
        tab[r + 1, 0, :] = 0.0
        for c in range(w):
            i = index_image[r, c]
            if i >= 0:
                z = float(points[i, 2])
                a += z
                b += z * z
                k += 1.0
            tab[r + 1, c + 1, T_Z] = tab[r, c + 1, T_Z] + a
            tab[r + 1, c + 1, T_N] = tab[r, c + 1, T_N] + k
            tab[r + 1, c + 1, T_Z2] = tab[r, c + 1, T_Z2] + b


@njit(cache=True)
def patch_half(z, noise_a, sigma_t, h_max):
    """Half-side (px) of the square patch whose mean depth has noise about sigma_t at depth z (0: none)."""
    if sigma_t <= 0.0 or noise_a <= 0.0:
        return 0
    sz = noise_a * z * z
    if sz <= sigma_t:
        return 0
    return min(h_max, int(math.ceil(0.5 * (sz / sigma_t - 1.0))))


@njit(cache=True)
def _box(tab, r0, r1, c0, c1, ch):
    return tab[r1, c1, ch] - tab[r0, c1, ch] - tab[r1, c0, ch] + tab[r0, c0, ch]


@njit(cache=True)
def denoised_point(points, tab, i, r, c, prm, out, k):
    """out[k] = point i moved along its ray to the mean depth of its pixel's patch; False to reject.

    The patch (``patch_half``) averages the independent per-pixel depth noise of a stereo camera;
    it is refused when under half of it is valid or its depth spread exceeds 2 sigma_z + R / 4 (it
    straddles an edge). Only the sample points of the search use it; scoring and fits use raw points.
    """
    z = float(points[i, 2])
    h = patch_half(z, prm[P_NOISE_A], prm[P_SIGMA_T], int(prm[P_H_MAX]))
    if h == 0:
        out[k, 0], out[k, 1], out[k, 2] = points[i, 0], points[i, 1], z
        return True
    hh = tab.shape[0] - 1
    ww = tab.shape[1] - 1
    r0, r1 = max(r - h, 0), min(r + h + 1, hh)
    c0, c1 = max(c - h, 0), min(c + h + 1, ww)
    n = _box(tab, r0, r1, c0, c1, T_N)
    if n < 0.5 * (r1 - r0) * (c1 - c0):
        return False
    m = _box(tab, r0, r1, c0, c1, T_Z) / n
    var = _box(tab, r0, r1, c0, c1, T_Z2) / n - m * m
    lim = 2.0 * prm[P_NOISE_A] * z * z + 0.25 * prm[P_R]
    if var > lim * lim:
        return False
    f = m / z
    out[k, 0], out[k, 1], out[k, 2] = points[i, 0] * f, points[i, 1] * f, m
    return True


@njit(cache=True)
def centres_xyz(p, radius, out):
    """Both centres of radius R through the three rows of p (3, 3); out (2, 3) gets (far, near).

    Returns 0 (collinear, or circumradius > R) or 2; ``known_radius_centres`` on coordinates.
    """
    x1, y1, z1 = p[0, 0], p[0, 1], p[0, 2]
    ax, ay, az = p[1, 0] - x1, p[1, 1] - y1, p[1, 2] - z1
    bx, by, bz = p[2, 0] - x1, p[2, 1] - y1, p[2, 2] - z1
    nx, ny, nz = ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx
    nn = nx * nx + ny * ny + nz * nz
    aa = ax * ax + ay * ay + az * az
    bb = bx * bx + by * by + bz * bz
    if not (nn > 1e-12 * aa * bb) or nn <= 0.0:
        return 0
    wx, wy, wz = aa * bx - bb * ax, aa * by - bb * ay, aa * bz - bb * az
    ox = (wy * nz - wz * ny) / (2.0 * nn)
    oy = (wz * nx - wx * nz) / (2.0 * nn)
    oz = (wx * ny - wy * nx) / (2.0 * nn)
    rho2 = ox * ox + oy * oy + oz * oz
    if rho2 > radius * radius:
        return 0
    hgt = math.sqrt(radius * radius - rho2)
    inv = 1.0 / math.sqrt(nn)
    ux, uy, uz = nx * inv, ny * inv, nz * inv
    qx, qy, qz = x1 + ox, y1 + oy, z1 + oz
    s = 1.0 if qx * ux + qy * uy + qz * uz >= 0.0 else -1.0
    out[0, 0], out[0, 1], out[0, 2] = qx + s * hgt * ux, qy + s * hgt * uy, qz + s * hgt * uz
    out[1, 0], out[1, 1], out[1, 2] = qx - s * hgt * ux, qy - s * hgt * uy, qz - s * hgt * uz
    return 2


@njit(cache=True)
def pixel_at(index_image, u0, v0, r_in, r_out, ang, u_rad):
    """The point index at the pixel at angle ang, radius sqrt(r_in^2 + (r_out^2 - r_in^2) u_rad)
    (uniform in the annulus) from (u0, v0); -1 when outside the image or without depth."""
    h, w = index_image.shape
    rad = math.sqrt(r_in * r_in + (r_out * r_out - r_in * r_in) * u_rad)
    c = int(math.floor(u0 + rad * math.cos(ang) + 0.5))
    r = int(math.floor(v0 + rad * math.sin(ang) + 0.5))
    if r < 0 or r >= h or c < 0 or c >= w:
        return -1
    return index_image[r, c]


@njit(cache=True)
def pretest(points, index_image, cx, cy, cz, e, prm, state):
    """Cheap test before scoring, stopping at the first decisive pixel.

    Pixels drawn in 0.8 of the candidate's disc must be ray inliers (|dt| <= e) in at least
    ``pretest_frac`` of the drawn ones (it fails as soon as that is out of reach); then of half as
    many pixels just outside the outline (1.1-1.3 of its radius) at most half may continue the
    surface at the ball's depth (a wall or a plane through the ball).
    """
    fx, fy, ppx, ppy, radius = prm[P_FX], prm[P_FY], prm[P_PPX], prm[P_PPY], prm[P_R]
    n_draws = int(prm[P_PRETEST_N])
    max_fail = int((1.0 - prm[P_PRETEST_FRAC]) * n_draws)
    dist = math.sqrt(cx * cx + cy * cy + cz * cz)
    rpx = disc_radius_px(cz, dist, radius, fx)
    u0 = fx * cx / cz + ppx
    v0 = fy * cy / cz + ppy
    valid = 0
    fails = 0
    for _ in range(n_draws):
        ang = 2.0 * math.pi * next_u01(state)
        i = pixel_at(index_image, u0, v0, 0.0, 0.8 * rpx, ang, next_u01(state))
        if i < 0:
            continue
        valid += 1
        dt, hit = ray_residual(float(points[i, 0]), float(points[i, 1]), float(points[i, 2]), cx, cy, cz, radius)
        if not (hit and abs(dt) <= e):
            fails += 1
            if fails > max_fail:
                return False
    if valid < 3 or valid - fails < prm[P_PRETEST_FRAC] * valid:
        return False
    valid = 0
    cont = 0
    n_ring = max(2, n_draws // 2)
    for _ in range(n_ring):
        ang = 2.0 * math.pi * next_u01(state)
        i = pixel_at(index_image, u0, v0, 1.1 * rpx, RING_FACTOR * rpx, ang, next_u01(state))
        if i < 0:
            continue
        px, py, pz = float(points[i, 0]), float(points[i, 1]), float(points[i, 2])
        pn = math.sqrt(px * px + py * py + pz * pz)
        tc = (px * cx + py * cy + pz * cz) / pn
        valid += 1
        if abs(pn - tc) <= e:
            cont += 1
            if cont > n_ring // 2:
                return False
    return not (valid >= 2 and cont > 0.5 * valid)


@njit(cache=True)
def patch_mean(tab, u, v, half):
    """(mean depth, valid count) of the square patch of half-side ``half`` px around pixel (u, v)."""
    hh = tab.shape[0] - 1
    ww = tab.shape[1] - 1
    c = int(math.floor(u + 0.5))
    r = int(math.floor(v + 0.5))
    r0, r1 = max(r - half, 0), min(r + half + 1, hh)
    c0, c1 = max(c - half, 0), min(c + half + 1, ww)
    if r0 >= r1 or c0 >= c1:
        return math.nan, 0.0
    n = _box(tab, r0, r1, c0, c1, T_N)
    if n <= 0.0:
        return math.nan, 0.0
    return _box(tab, r0, r1, c0, c1, T_Z) / n, n


@njit(cache=True)
def patch_pretest(tab, cx, cy, cz, e, prm):
    """A noise-proof test of a candidate on patch means (a few summed-area lookups).

    The patch around the projected centre (half-side a third of the disc radius) must not lie
    behind the sphere's front by more than e + 3 sigma_z / sqrt(n) (a surface seen through the
    ball; in front is allowed: an occluder). Of four patches just outside the outline (1.4 disc
    radii up, down, left, right), at most two may be *continued*, i.e. at a depth between the
    front of the sphere and its centre: a wall or a plane the sphere is tangent to or cut by. Unlike
    single pixels, these means stay decisive at 3 m and 424x240, where one pixel's noise is 7 cm.
    """
    fx, fy, ppx, ppy, radius = prm[P_FX], prm[P_FY], prm[P_PPX], prm[P_PPY], prm[P_R]
    dist = math.sqrt(cx * cx + cy * cy + cz * cz)
    rpx = disc_radius_px(cz, dist, radius, fx)
    u0 = fx * cx / cz + ppx
    v0 = fy * cy / cz + ppy
    z_front = (dist - radius) * cz / dist
    sz = prm[P_NOISE_A] * z_front * z_front
    half = max(1, int(rpx / 3.0))
    m, n = patch_mean(tab, u0, v0, half)
    if n >= 3.0 and m > z_front + e + 3.0 * sz / math.sqrt(n):
        return False
    half = max(1, int(rpx / 4.0))
    cont = 0
    for k in range(4):
        du = 1.4 * rpx if k == 0 else (-1.4 * rpx if k == 1 else 0.0)
        dv = 1.4 * rpx if k == 2 else (-1.4 * rpx if k == 3 else 0.0)
        m, n = patch_mean(tab, u0 + du, v0 + dv, half)
        if n < 0.3 * (2 * half + 1) ** 2:
            continue
        tol = e + 3.0 * sz / math.sqrt(n)
        if z_front - tol <= m <= cz:
            cont += 1
            if cont > 2:
                return False
    return True


@njit(cache=True)
def search_quality(stats, e):
    """Search score of window statistics: MSAC over inliers minus the pixels seen through the sphere
    or hugging it just in front (a bigger object), times (1 - share of the outline ring where the
    surface continues at the sphere's depth)^2 (a wall, or a big object at 3 m where eps is wide:
    a difference would favour big surfaces, which have more inliers)."""
    ring = 1.0 - stats[ST_RING_CONT] / max(stats[ST_RING], 1.0)
    return (stats[ST_INLIER] - stats[ST_SSE] / (e * e) - stats[ST_BEHIND] - stats[ST_FRONT_NEAR]) * ring * ring


@njit(cache=True)
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


@njit(cache=True)
def required_iterations(support, n_points, window_px, confidence):
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


@njit(cache=True)
def search_organised(points, rows, cols, index_image, tab, prm, seed, cands, quals, counters):
    """Local-sampling RANSAC on an organised cloud; fills cands (K, 3), quals (K,) best first.

    Each of the ``prm[P_ITERS]`` iterations (the bound is computed by the caller, see
    ``improved.iteration_bound``): a random valid point p1; two more pixels in the annulus 0.3-1 of
    the disc of radius ``sample_r`` (metres) at p1's depth, the 3rd at 90-270 degrees from the 2nd
    (well-shaped triangles), each kept only within 2R of p1 in 3D (else redrawn, up to ``retries``
    times); the three moved to their patch-mean depth (``denoised_point``); both known-radius
    centres on whose camera side the three lie; the early-exit ``pretest``; a centre within
    ``dedup`` of a kept one is skipped (verification refines it anyway); the rest are scored on
    their pixel window (``window_stats``, strided to about ``score_max`` pixels, ``search_quality``).
    counters (4,) int64 gets: samples drawn, centres solved, centres past the pretest, scored > 0.
    Returns the number of candidates kept.
    """
    n = points.shape[0]
    h, w = index_image.shape
    counters[:] = 0
    fx, fy, ppx, ppy, radius = prm[P_FX], prm[P_FY], prm[P_PPX], prm[P_PPY], prm[P_R]
    retries = int(prm[P_RETRIES])
    iters = int(prm[P_ITERS])
    dedup2 = prm[P_DEDUP] * prm[P_DEDUP]
    state = np.empty(1, np.uint64)
    state[0] = np.uint64(seed)
    pts = np.empty((3, 3), np.float64)
    picks = np.empty(3, np.int64)
    pix = np.empty((3, 2), np.int64)
    two = np.empty((2, 3), np.float64)
    stats = np.empty(N_STATS, np.float64)
    n_kept = 0
    for _ in range(iters):
        i1 = min(int(next_u01(state) * n), n - 1)
        r1, c1 = rows[i1], cols[i1]
        if index_image[r1, c1] != i1:  # no pixel: invalid point
            continue
        z1 = float(points[i1, 2])
        if z1 <= radius:
            continue
        rpx = fx * prm[P_SAMPLE_R] / z1
        # raw points for the 3D reach test (widened by the noise), patch means only for a full sample
        reach = 2.0 * radius + 3.0 * prm[P_NOISE_A] * z1 * z1
        reach2 = reach * reach
        ang2 = 0.0
        got = 1
        for slot in range(2):
            for _ in range(retries):
                if slot == 0:
                    ang = 2.0 * math.pi * next_u01(state)
                else:
                    ang = ang2 + 0.5 * math.pi + math.pi * next_u01(state)
                rad = rpx * math.sqrt(0.09 + 0.91 * next_u01(state))
                c = int(math.floor(c1 + rad * math.cos(ang) + 0.5))
                r = int(math.floor(r1 + rad * math.sin(ang) + 0.5))
                if r < 0 or r >= h or c < 0 or c >= w:
                    continue
                j = index_image[r, c]
                if j < 0:
                    continue
                dx = float(points[j, 0]) - float(points[i1, 0])
                dy = float(points[j, 1]) - float(points[i1, 1])
                dz = float(points[j, 2]) - z1
                if dx * dx + dy * dy + dz * dz > reach2:
                    continue
                picks[got] = j
                pix[got, 0], pix[got, 1] = r, c
                ang2 = ang
                got += 1
                break
        if got < 3:
            continue
        pix[0, 0], pix[0, 1] = r1, c1
        picks[0] = i1
        ok = True
        for k in range(3):
            if not denoised_point(points, tab, picks[k], pix[k, 0], pix[k, 1], prm, pts, k):
                ok = False
                break
        if not ok:
            continue
        counters[0] += 1
        if centres_xyz(pts, radius, two) == 0:
            continue
        counters[1] += 1
        for s in range(2):
            cx, cy, cz = two[s, 0], two[s, 1], two[s, 2]
            if cz <= radius:
                continue
            facing = True
            for k in range(3):
                if (pts[k, 0] - cx) * pts[k, 0] + (pts[k, 1] - cy) * pts[k, 1] + (pts[k, 2] - cz) * pts[k, 2] >= 0.0:
                    facing = False
            if not facing:
                continue
            e = noise_eps(cz, prm[P_EPS], prm[P_NOISE_A], prm[P_NOISE_K], prm[P_EPS_CAP])
            if not patch_pretest(tab, cx, cy, cz, e, prm):
                continue
            if not pretest(points, index_image, cx, cy, cz, e, prm, state):
                continue
            counters[2] += 1
            dup = False
            for j in range(n_kept):
                ddx, ddy, ddz = cands[j, 0] - cx, cands[j, 1] - cy, cands[j, 2] - cz
                if ddx * ddx + ddy * ddy + ddz * ddz <= dedup2:
                    dup = True
                    break
            if dup:
                continue
            dist = math.sqrt(cx * cx + cy * cy + cz * cz)
            box = 2.0 * (RING_FACTOR * 1.05 * disc_radius_px(cz, dist, radius, fx) + 2.0) + 1.0  # window side, px
            stride = max(1, int(math.ceil(box / math.sqrt(prm[P_SCORE_MAX]))))
            window_stats(points, index_image, cx, cy, cz, radius, e, fx, fy, ppx, ppy, stride, stats)
            q = search_quality(stats, e)
            if q <= 0.0:
                continue
            counters[3] += 1
            n_kept = _keep_candidate(cands, quals, n_kept, cx, cy, cz, q, 0.5 * radius)
    return n_kept


# ----------------------------------------------------------------------------------------------
# Organised clouds: verification of one candidate, in one call.

V_CX, V_CY, V_CZ, V_EPS, V_N, V_FCX, V_FCY, V_FCZ, V_FR, V_FSE, V_RMSE = range(11)
N_VOUT = 11


@njit(cache=True)
def _strided(idx, n, max_points):
    """idx[:n] thinned by a stride to at most about max_points entries (a view)."""
    step = max(1, (n + max_points - 1) // max_points)
    return idx[0:n:step]


@njit(cache=True)
def verify_organised(points, index_image, c0, prm, refine_iterations, max_fit_points, s_min, idx, out, stats):
    """Refine one candidate centre and measure it; results in out (N_VOUT,), stats (N_STATS,).

    Rounds of: inliers = silhouette pixels with ray residual within the noise-aware eps at the
    current depth (``gather_window``), then 2 Gauss-Newton steps on the ray residuals with R fixed
    (``fit_ray``; on at most ``max_fit_points`` inliers, evenly strided), until the centre moves
    less than 10 um. Then the final inliers (idx[:out[V_N]]), 2 more steps and a free-radius ray
    fit (the size check) on up to 4 ``max_fit_points`` of them,
    the RMS of ||p - c|| - R over the inliers, and the silhouette statistics (``window_stats``).
    out[V_N] = 0 when fewer than 3 inliers remain.
    """
    fx, fy, ppx, ppy, radius = prm[P_FX], prm[P_FY], prm[P_PPX], prm[P_PPY], prm[P_R]
    c = c0.copy()
    out[:] = math.nan
    out[V_N] = 0.0
    for _ in range(refine_iterations):
        e = noise_eps(c[2], prm[P_EPS], prm[P_NOISE_A], prm[P_NOISE_K], prm[P_EPS_CAP])
        n = gather_window(points, index_image, c[0], c[1], c[2], radius, e, fx, fy, ppx, ppy, idx)
        if n < 3:
            return
        cn = fit_ray(points, _strided(idx, n, max_fit_points), c[0], c[1], c[2], radius, False, 2, s_min)[0]
        moved = math.sqrt((cn[0] - c[0]) ** 2 + (cn[1] - c[1]) ** 2 + (cn[2] - c[2]) ** 2)
        c[:] = cn
        if moved < 1e-5:
            break
    if not c[2] > radius:
        return
    e = noise_eps(c[2], prm[P_EPS], prm[P_NOISE_A], prm[P_NOISE_K], prm[P_EPS_CAP])
    n = gather_window(points, index_image, c[0], c[1], c[2], radius, e, fx, fy, ppx, ppy, idx)
    if n < 3:
        return
    # the final estimates on up to 4x as many inliers: the centre (R fixed), then the free radius
    sub = _strided(idx, n, 4 * max_fit_points)
    c = fit_ray(points, sub, c[0], c[1], c[2], radius, False, 2, s_min)[0]
    fc, fr, fse, _ = fit_ray(points, sub, c[0], c[1], c[2], radius, True, 5, s_min)
    sse = 0.0
    for k in range(n):
        i = idx[k]
        d = math.sqrt((points[i, 0] - c[0]) ** 2 + (points[i, 1] - c[1]) ** 2 + (points[i, 2] - c[2]) ** 2) - radius
        sse += d * d
    dist = math.sqrt(c[0] * c[0] + c[1] * c[1] + c[2] * c[2])
    box = 2.0 * (RING_FACTOR * 1.05 * disc_radius_px(c[2], dist, radius, fx) + 2.0) + 1.0
    stride = max(1, int(math.ceil(box / math.sqrt(4.0 * max_fit_points))))
    window_stats(points, index_image, c[0], c[1], c[2], radius, e, fx, fy, ppx, ppy, stride, stats)
    out[V_CX], out[V_CY], out[V_CZ], out[V_EPS], out[V_N] = c[0], c[1], c[2], e, n
    out[V_FCX], out[V_FCY], out[V_FCZ], out[V_FR], out[V_FSE] = fc[0], fc[1], fc[2], fr, fse
    out[V_RMSE] = math.sqrt(sse / n)


@njit(cache=True)
def gather_window(points, index_image, cx, cy, cz, radius, band, fx, fy, ppx, ppy, out_idx):
    """Indices of the points in the candidate's silhouette whose ray residual is within band.

    out_idx: preallocated int64 buffer (large enough for the window); returns the count.
    """
    h, w = index_image.shape
    dist = math.sqrt(cx * cx + cy * cy + cz * cz)
    if cz <= radius or dist <= radius:
        return 0
    rpx = disc_radius_px(cz, dist, radius, max(fx, fy)) * 1.1 + 2.0
    u0 = fx * cx / cz + ppx
    v0 = fy * cy / cz + ppy
    k = 0
    for r in range(max(0, int(math.floor(v0 - rpx))), min(h - 1, int(math.ceil(v0 + rpx))) + 1):
        for c in range(max(0, int(math.floor(u0 - rpx))), min(w - 1, int(math.ceil(u0 + rpx))) + 1):
            i = index_image[r, c]
            if i < 0:
                continue
            dt, hit = ray_residual(points[i, 0], points[i, 1], points[i, 2], cx, cy, cz, radius)
            if hit and abs(dt) <= band and k < out_idx.shape[0]:
                out_idx[k] = i
                k += 1
    return k


@njit(cache=True)
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


@njit(cache=True)
def refine_fixed_radius(points, idx, cx, cy, cz, radius, iterations):
    """Gauss-Newton on sum (||p - c|| - R)^2 over points[idx]; returns the centre (3,) float64."""
    c = np.array([cx, cy, cz])
    A = np.empty((3, 3))
    g = np.empty(3)
    for _ in range(iterations):
        A[:] = 0.0
        g[:] = 0.0
        for k in range(idx.shape[0]):
            i = idx[k]
            dx, dy, dz = points[i, 0] - c[0], points[i, 1] - c[1], points[i, 2] - c[2]
            d = math.sqrt(dx * dx + dy * dy + dz * dz)
            if d <= 1e-12:
                continue
            u0, u1, u2 = dx / d, dy / d, dz / d
            r = d - radius
            A[0, 0] += u0 * u0
            A[0, 1] += u0 * u1
            A[0, 2] += u0 * u2
            A[1, 1] += u1 * u1
            A[1, 2] += u1 * u2
            A[2, 2] += u2 * u2
            g[0] += u0 * r
            g[1] += u1 * r
            g[2] += u2 * r
        A[1, 0], A[2, 0], A[2, 1] = A[0, 1], A[0, 2], A[1, 2]
        if abs(np.linalg.det(A)) < 1e-18:
            break
        step = np.linalg.solve(A, g)  # J = -u, so the GN step -(J^T J)^-1 J^T r = +A^-1 g
        c += step
        if math.sqrt(step[0] ** 2 + step[1] ** 2 + step[2] ** 2) < 1e-9:
            break
    return c


@njit(cache=True)
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


@njit(cache=True)
def fit_ray(points, idx, cx, cy, cz, radius, free_radius, iterations, s_min):
    """Gauss-Newton on the ray residuals |p| - t_near(c, r) of points[idx] (depth noise model).

    t_near = u.c - s, s = sqrt(r^2 - |c|^2 + (u.c)^2), u = p / |p| (s = 0 for rays that miss: the
    residual is then the depth past the point of closest approach). Near the outline s -> 0 and
    the derivative explodes: s is floored at ``s_min * r`` in the derivative only. free_radius: fit r too, else r = radius.
    Returns (centre (3,), r, standard error of r (nan if fixed), RMS residual).
    """
    x = np.array([cx, cy, cz, radius])
    npar = 4 if free_radius else 3
    A = np.zeros((4, 4))
    g = np.zeros(4)
    jj = np.zeros(4)
    n = idx.shape[0]
    for _ in range(iterations):
        A[:] = 0.0
        g[:] = 0.0
        for k in range(n):
            i = idx[k]
            px, py, pz = float(points[i, 0]), float(points[i, 1]), float(points[i, 2])
            pn = math.sqrt(px * px + py * py + pz * pz)
            ux, uy, uz = px / pn, py / pn, pz / pn
            tc = ux * x[0] + uy * x[1] + uz * x[2]
            s2 = x[3] * x[3] - (x[0] * x[0] + x[1] * x[1] + x[2] * x[2]) + tc * tc
            # res = pn - tc + s; d res / d c = -u + (tc u - c) / s; d res / d r = r / s, with s floored
            # in the derivative only, so that the residual stays exact (and continuous) at the outline
            sj = max(math.sqrt(max(s2, 0.0)), s_min * x[3])
            jj[0] = -ux + (tc * ux - x[0]) / sj
            jj[1] = -uy + (tc * uy - x[1]) / sj
            jj[2] = -uz + (tc * uz - x[2]) / sj
            jj[3] = x[3] / sj
            res = pn - tc + math.sqrt(max(s2, 0.0))
            for a in range(npar):
                g[a] += jj[a] * res
                for b in range(npar):
                    A[a, b] += jj[a] * jj[b]
        if npar == 3:
            A[3, 3] = 1.0
        if abs(np.linalg.det(A)) < 1e-30:
            break
        step = -np.linalg.solve(A, g)
        x += step
        if math.sqrt((step * step).sum()) < 1e-9:
            break
    sse = 0.0
    for k in range(n):
        i = idx[k]
        px, py, pz = float(points[i, 0]), float(points[i, 1]), float(points[i, 2])
        pn = math.sqrt(px * px + py * py + pz * pz)
        tc = (px * x[0] + py * x[1] + pz * x[2]) / pn
        s2 = x[3] * x[3] - (x[0] * x[0] + x[1] * x[1] + x[2] * x[2]) + tc * tc
        res = pn - tc + math.sqrt(max(s2, 0.0))
        sse += res * res
    se = math.nan
    if free_radius:
        if abs(np.linalg.det(A)) > 1e-30:
            se = math.sqrt(max(sse / max(n - 4, 1) * np.linalg.inv(A)[3, 3], 0.0))
        else:
            se = math.inf
    return x[:3].copy(), x[3], se, math.sqrt(sse / max(n, 1))


@njit(cache=True)
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


@njit(cache=True)
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


@njit(cache=True)
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


@njit(cache=True)
def search_unorganised(points, order, sorted_keys, origin, cell, dims, radius, eps, win_m, max_iter, min_iter,
                       confidence, retries, pretest_n, pretest_frac, score_max, seed, cands, quals):
    """Local-sampling RANSAC on an unorganised cloud (grid cells of size ``cell`` >= win_m / 1).

    The 2nd and 3rd points are drawn from the 27 cells around the 1st (kept if within win_m); both
    known-radius centres facing the camera at the origin; a pretest on points drawn near the
    candidate; quality = MSAC over the points of the cells covering the sphere (subsampled to
    about ``score_max``). Returns (iterations run, number of candidates kept).
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
        i1 = order[min(int(next_u01(state) * n), n - 1)]
        m = _cell_ranges(sorted_keys, origin, cell, dims, points[i1, 0], points[i1, 1], points[i1, 2], 1, starts, ends)
        total = 0
        for k in range(m):
            total += ends[k] - starts[k]
        picks[0] = i1
        got = 1
        for slot in range(2):
            for _ in range(retries):
                t = min(int(next_u01(state) * total), total - 1)
                k = 0
                while t >= ends[k] - starts[k]:
                    t -= ends[k] - starts[k]
                    k += 1
                j = order[starts[k] + t]
                if j == i1 or (slot == 1 and j == picks[1]):
                    continue
                dx, dy, dz = points[j, 0] - points[i1, 0], points[j, 1] - points[i1, 1], points[j, 2] - points[i1, 2]
                if dx * dx + dy * dy + dz * dz > win_m * win_m:
                    continue
                picks[got] = j
                got += 1
                break
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
            tot_s = 0
            for k in range(ms):
                tot_s += ends[k] - starts[k]
            if tot_s == 0:
                continue
            # pretest: among near points (inside the outer shell), the share on the shell
            near = 0
            inl = 0
            for _ in range(pretest_n * 3):
                t = min(int(next_u01(state) * tot_s), tot_s - 1)
                k = 0
                while t >= ends[k] - starts[k]:
                    t -= ends[k] - starts[k]
                    k += 1
                j = order[starts[k] + t]
                dx, dy, dz = points[j, 0] - cx, points[j, 1] - cy, points[j, 2] - cz
                d = math.sqrt(dx * dx + dy * dy + dz * dz)
                if d <= radius + eps:
                    near += 1
                    if d >= radius - eps:
                        inl += 1
            if near < 3 or inl < pretest_frac * near:
                continue
            step = max(1, tot_s // score_max)
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
            q *= step
            inliers *= step
            if q <= 0.0:
                continue
            n_kept = _keep_candidate(cands, quals, n_kept, cx, cy, cz, q, 0.5 * radius)
            if n_kept > 0 and quals[0] == q:
                # share of the 1st point's neighbourhood (27 cells, about (3 cell)^3) on the ball
                needed = required_iterations(inliers, float(n), float(total), confidence)
    return it, n_kept
