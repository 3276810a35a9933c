"""Compiled hot loops of the detector (numba, single thread, cached on disk).

Each kernel has a readable counterpart that the tests compare it with: the minimal solver and the
fits in ``sphere_model``, the search loops and the window statistics in ``tests/search_reference.py``
(test code, not shipped). Random numbers come from splitmix64 (``next_u01``), which the reference
replays exactly in pure Python, so the compiled and the reference search draw the same samples.

Conventions: points (N, 3) float32 metres in the camera frame; an organised cloud comes with
``index_image`` (H, W) int32, the point index of each pixel or -1 where depth is invalid.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

#: Every kernel's compilation: cached on disk, and numpy's error model: a float division by zero
#: gives inf or nan (the kernels guard the divisors that can vanish) instead of a zero check and a
#: Python exception path per division, which cost a fifth of the search's and verification's time.
kernel = njit(cache=True, error_model="numpy")
#: The same, inlined into its callers by numba (``inline="always"``): for the named parts of a long
#: kernel, called per pixel or per sample, where a call's cost (its array arguments' reference counts)
#: would show in the caller's time.
part = njit(cache=True, error_model="numpy", inline="always")

_GOLDEN = np.uint64(0x9E3779B97F4A7C15)
_MIX1 = np.uint64(0xBF58476D1CE4E5B9)
_MIX2 = np.uint64(0x94D049BB133111EB)
_INV53 = 1.0 / 9007199254740992.0  # 2^-53

# Categories of a pixel of a candidate's window (window statistics, in this order).
ST_VALID_DISC, ST_INLIER, ST_FRONT, ST_FRONT_NEAR, ST_BEHIND, ST_INVALID_DISC, ST_SSE, ST_RING, ST_RING_CONT, \
    ST_RING_FRONT, ST_VALID_INNER, ST_BEHIND_INNER, ST_EDGE_N, ST_EDGE_BEHIND = range(14)
#: The outline ring by angle about the centre's pixel: N_SECTORS sectors of equal angle, in angular
#: order from -180 degrees (image x right, y down); per sector its ring pixels (ST_SECTOR_RING + k)
#: and those RING_CONT or RING_FRONT (ST_SECTOR_ATTACHED + k).
N_SECTORS = 8
ST_SECTOR_RING = 14
ST_SECTOR_ATTACHED = ST_SECTOR_RING + N_SECTORS
ST_IN_N, ST_IN_SUM, ST_OUTH_N, ST_OUTH_SUM, ST_OUTV_N, ST_OUTV_SUM, ST_RING_SPREAD = range(
    ST_SECTOR_ATTACHED + N_SECTORS, ST_SECTOR_ATTACHED + N_SECTORS + 7)
N_STATS = ST_RING_SPREAD + 1

# The zones of a candidate's window (``window_stats``): the relief profile's inner zone (rays passing
# the centre within sqrt(PROFILE_INNER_SQ) R) and outer zone (up to sqrt(PROFILE_OUTER_SQ) R, short of
# the outline, where flying pixels mix in the background); the outline ring (rays passing the centre
# at R to RING_FACTOR R), whose pixels RING_FRONT_MIN_FRACTION R to RING_FRONT_MAX_FRACTION R in front
# of where their ray passes the centre are an attached surface in front (a cylinder's body, a
# corner's faces, a bigger object the sphere was fitted into; a free ball's ring sees what is behind
# it, a floor or a holder fills a small part of it, an occluder is usually farther in front). They
# define what the verdict's inputs measure (``verdict.FEATURE_NAMES``): the shipped model was fitted
# on these zones, and a change to them needs `make train-verifier`.
PROFILE_INNER_SQ = 0.3  # the inner zone: rays within sqrt(0.3) R = 0.55 R of the centre
PROFILE_OUTER_SQ = 0.8  # the outer zone: to sqrt(0.8) R = 0.89 R, a pixel short of the outline at 3 m
RING_FACTOR = 1.3  # the outline ring's outer radius / R: a few pixels beyond the outline at any range
RING_FRONT_MIN_FRACTION = 0.3  # nearer than this * R in front of its ray's pass: the noise, not a surface
RING_FRONT_MAX_FRACTION = 1.2  # farther in front than this * R: an occluder, not attached to the sphere


@kernel
def next_u01(state):
    """splitmix64: advance state (uint64 array of 1) and return a float64 uniform in [0, 1)."""
    state[0] += _GOLDEN
    z = state[0]
    z = (z ^ (z >> np.uint64(30))) * _MIX1
    z = (z ^ (z >> np.uint64(27))) * _MIX2
    z = z ^ (z >> np.uint64(31))
    return float(z >> np.uint64(11)) * _INV53


@kernel
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


@kernel
def build_index_image(rows, cols, height, width):
    """(H, W) int32 image of point indices (-1: no point) from per-point pixel rows, cols (N,)."""
    img = np.full((height, width), -1, np.int32)
    for i in range(rows.shape[0]):
        r, c = rows[i], cols[i]
        if 0 <= r < height and 0 <= c < width:
            img[r, c] = i
    return img


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
def faces_camera(points, i, cx, cy, cz):
    """True if point i is on the camera-facing side of the sphere centred at c: (p - c) . p < 0."""
    px, py, pz = points[i, 0], points[i, 1], points[i, 2]
    return (px - cx) * px + (py - cy) * py + (pz - cz) * pz < 0.0


@kernel
def disc_radius_px(cz, dist, radius, fx):
    """Approximate pixel radius of a sphere's image at centre depth cz, distance |c| (pinhole)."""
    return fx * radius / math.sqrt(max(dist * dist - radius * radius, 1e-12)) * dist / cz


@kernel
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


@kernel
def ring_sector(du, dv):
    """The ring sector (0-7: octants in angular order from the left, image y down) of a pixel at
    (du, dv) pixels from the centre's; comparisons, not an arctangent per pixel."""
    ax, ay = abs(du), abs(dv)
    if dv < 0.0:
        if du < 0.0:
            return 0 if ax > ay else 1
        return 2 if ay > ax else 3
    if du >= 0.0:
        return 4 if ax > ay else 5
    return 6 if ay > ax else 7


@kernel
def ring_spread(out):
    """The share of the ring's pixels attached (out[ST_SECTOR_ATTACHED + k]) outside the half ring,
    N_SECTORS / 2 consecutive sectors, that holds the most of them (``improved.RING_SPREAD_FREE``)."""
    total = 0.0
    attached = 0.0
    for k in range(N_SECTORS):
        total += out[ST_SECTOR_RING + k]
        attached += out[ST_SECTOR_ATTACHED + k]
    if total <= 0.0:
        return 0.0
    best = 0.0
    for k in range(N_SECTORS):
        w = 0.0
        for j in range(N_SECTORS // 2):
            w += out[ST_SECTOR_ATTACHED + (k + j) % N_SECTORS]
        best = max(best, w)
    return (attached - best) / total


@part
def _window_bounds(h, w, cx, cy, cz, dist, prm):
    """The pixels (rows r0-r1, columns c0-c1, inclusive, within an h x w image) that hold the outline
    ring of the sphere about c (m, dist = |c|, in front of the camera), and the pixel (u0, v0) of its
    centre."""
    fx, fy, ppx, ppy, radius = prm[P_FX], prm[P_FY], prm[P_PPX], prm[P_PPY], prm[P_R]
    rpx = disc_radius_px(cz, dist, radius, max(fx, fy)) * RING_FACTOR * 1.05 + 2.0
    u0 = fx * cx / cz + ppx
    v0 = fy * cy / cz + ppy
    c0 = max(0, int(math.floor(u0 - rpx)))
    c1 = min(w - 1, int(math.ceil(u0 + rpx)))
    r0 = max(0, int(math.floor(v0 - rpx)))
    r1 = min(h - 1, int(math.ceil(v0 + rpx)))
    return r0, r1, c0, c1, u0, v0


@part
def _ring_pixel(out, pn, tc, du, dv, ring_band, prm):
    """Count in out (N_STATS,) a pixel of the outline RING (its ray misses the sphere and passes the
    centre at R to RING_FACTOR R): RING_CONT if its point (range pn m) is within ring_band m of the
    depth tc m where the ray passes the centre (a surface continuing beyond the outline: a wall, a
    plane, a bigger object; a band of one sigma of the depth noise rather than eps: at 3 m eps is
    +/- R, and a background 20 cm behind a ball would count as continuing it), RING_FRONT if it is
    ring_front_min R to ring_front_max R in front of it (an attached surface in front: a cylinder's
    body); the same in its angular sector (``ring_sector`` of its offset (du, dv) px from the
    centre's pixel: ST_SECTOR_RING, ST_SECTOR_ATTACHED)."""
    radius = prm[P_R]
    out[ST_RING] += 1.0
    sector = ring_sector(du, dv)
    out[ST_SECTOR_RING + sector] += 1.0
    if abs(pn - tc) <= ring_band:
        out[ST_RING_CONT] += 1.0
        out[ST_SECTOR_ATTACHED + sector] += 1.0
    elif -RING_FRONT_MAX_FRACTION * radius <= pn - tc <= -RING_FRONT_MIN_FRACTION * radius:
        out[ST_RING_FRONT] += 1.0
        out[ST_SECTOR_ATTACHED + sector] += 1.0


@part
def _disc_pixel(out, dt, m2, du, dv, eps, prm):
    """Count in out (N_STATS,) a silhouette pixel with a point: dt its ray residual (m), m2 the squared
    distance (m^2) at which its ray passes the centre, (du, dv) its offset (px) from the centre's pixel.

    INLIER if |dt| <= eps (SSE sums dt^2), else FRONT (an occluder, dt < 0; FRONT_NEAR if also
    dt >= -R/2: a surface hugging the sphere, as a cylinder of the same radius does) or BEHIND
    (dt > 0: seen through the ball, evidence against it). VALID_INNER and BEHIND_INNER count the
    valid and the BEHIND pixels whose rays pass the centre within sqrt(profile_outer) R (short of the
    outline, where mixed pixels see past a real ball); EDGE_N and EDGE_BEHIND the pixels beyond that,
    up to the outline, that are INLIER or BEHIND, and the BEHIND ones (a smaller ball leaves this band
    to the background; an occluder's FRONT pixels tell nothing of the size and are left out).
    The relief profile: IN_N, IN_SUM count and sum the ray residuals of the inliers whose rays pass
    the centre within sqrt(profile_inner) R; OUTH_* and OUTV_* those between that and
    sqrt(profile_outer) R, left or right of the centre (OUTH) or above or below it (OUTV)."""
    radius, p_in, p_out = prm[P_R], PROFILE_INNER_SQ, PROFILE_OUTER_SQ
    out[ST_VALID_DISC] += 1.0
    if m2 <= p_out * radius * radius:  # short of the outline's mixed pixels
        out[ST_VALID_INNER] += 1.0
        if dt > eps:
            out[ST_BEHIND_INNER] += 1.0
    elif dt >= -eps:
        out[ST_EDGE_N] += 1.0
        if dt > eps:
            out[ST_EDGE_BEHIND] += 1.0
    # the relief profile: the inliers' mean ray residual per zone (a flat or a less curved surface
    # fitted by the sphere sits in front of it in the outer zone; occluders, such as a tripod's cup,
    # are not inliers and do not bias it)
    if abs(dt) > eps:
        pass
    elif m2 <= p_in * radius * radius:
        out[ST_IN_N] += 1.0
        out[ST_IN_SUM] += dt
    elif m2 <= p_out * radius * radius:
        # left and right of the centre, or above and below: a cylinder or an edge is curved along
        # one image axis only
        if abs(du) >= abs(dv):
            out[ST_OUTH_N] += 1.0
            out[ST_OUTH_SUM] += dt
        else:
            out[ST_OUTV_N] += 1.0
            out[ST_OUTV_SUM] += dt
    if abs(dt) <= eps:
        out[ST_INLIER] += 1.0
        out[ST_SSE] += dt * dt
    elif dt < 0.0:
        out[ST_FRONT] += 1.0
        if dt >= -0.5 * radius:
            out[ST_FRONT_NEAR] += 1.0
    else:
        out[ST_BEHIND] += 1.0


@kernel
def window_stats(points, index_image, cx, cy, cz, eps, ring_band, prm, stride, out):
    """Classify the pixels of a candidate's silhouette; out (N_STATS,) float64 gets the counts.

    A pixel whose ray meets the sphere (the silhouette, undistorted pinhole) with point p has the ray
    residual dt = |p| - t_near and is classified by it and by where its ray passes the centre
    (``_disc_pixel``); silhouette pixels without a point count as INVALID_DISC. Rays passing the
    centre at R to RING_FACTOR R form the outline RING (``_ring_pixel``; RING_CONT within ring_band of
    the depth where they pass the centre), and RING_SPREAD (``ring_spread``) how its attached pixels
    spread over its sectors. ``stride`` visits every stride-th pixel (counts scaled by stride^2,
    except the relief profile's, which stay the visited ones). The camera, R and the zones' sizes
    come from prm (see the zones' comment above).
    """
    fx, fy, ppx, ppy, radius = prm[P_FX], prm[P_FY], prm[P_PPX], prm[P_PPY], prm[P_R]
    for k in range(N_STATS):
        out[k] = 0.0
    h, w = index_image.shape
    dist = math.sqrt(cx * cx + cy * cy + cz * cz)
    if cz <= radius or dist <= radius:
        return
    r0, r1, c0, c1, u0, v0 = _window_bounds(h, w, cx, cy, cz, dist, prm)
    ring2 = (RING_FACTOR * radius) ** 2
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
            px, py, pz = float(points[i, 0]), float(points[i, 1]), float(points[i, 2])
            pn = math.sqrt(px * px + py * py + pz * pz)
            dt, hit = ray_residual(px, py, pz, cx, cy, cz, radius)
            tc = (px * cx + py * cy + pz * cz) / pn  # where the ray passes the centre (m)
            if hit:
                _disc_pixel(out, dt, dist * dist - tc ** 2, c - u0, r - v0, eps, prm)
            elif tc > 0.0 and dist * dist - tc * tc <= ring2:
                _ring_pixel(out, pn, tc, c - u0, r - v0, ring_band, prm)
    s2 = float(stride * stride)
    for k in range(ST_IN_N):  # the profile keeps the visited counts: its means' errors depend on them
        out[k] *= s2
    out[ST_RING_SPREAD] = ring_spread(out)


# ----------------------------------------------------------------------------------------------
# Organised clouds: the search. Scalar parameters travel in one float64 array (``prm``, indexed by
# the P_* names below): one argument instead of twenty keeps numba's call overhead small.
#
# The search works on a grid of cells of BIN x BIN pixels (1 at 424x240, 2 at 848x480, 3 at
# 1280x720: about 424 cells across whatever the stream; from 3 x 3 on a cell sums its middle pixel
# row only, ``improved.cell_rows``, P_CELL_PX pixels), through the summed-area table ``tab``
# (Hc + 1, Wc + 1) uint64 of the depth z in millimetres and of the valid-pixel count per cell, packed
# in one word (depth sum + count << COUNT_SHIFT); a box's mean range |p| is its mean depth times the
# length of the ray (z = 1) through the box's centre. The table is kept modulo 2^64: a box's packed
# sum comes out exact, its depth sum below 2^40 mm (a whole 4k frame at 60 m) and its count below
# 2^24, so one load per corner and one add per cell serve both (the 2.4 MB of a float64 table with
# a squared-depth channel did not stay in cache; two uint32 channels took twice the adds).

#: The parameter vector's slots, in order: the one list of what ``improved.parameters`` fills in per
#: frame (the stream's intrinsics, the model's R and eps, the frame's noise and grid). Each slot's
#: index is the module constant P_<name>, set from this list below (numba reads module-level ints as
#: constants).
PARAMETERS = (
    "FX", "FY", "PPX", "PPY",  # the stream's intrinsics (px)
    "R", "EPS",  # the ball radius and the shell half-width (m)
    "NOISE_A",  # sigma_z / z^2 (1/m): the frame's, or the model's
    "NOISE_K",  # the band's noise multiple (``noise.noise_sigmas``)
    "EPS_CAP",  # the band's cap (m): MAX_EPS_FRACTION * R
    "STRATUM_V", "BIN",  # a stratum's rows (cells), a cell's side (px)
    "RR_MIN", "RR_MAX",  # the disc radii (cells) a hypothesis may have
    "Z_FAR",  # the farthest depth searched (m)
    "STRATUM_U",  # a stratum's columns (cells)
    "CELL_PX",  # the pixels a cell's table entry sums
    # box means' noise over the independent-pixel figure sigma / sqrt(n): the noise's correlation
    # (``improved.mean_variance_inflation``), square-rooted
    "MEAN_NOISE",
    # the search's stencil follows the silhouette's off-axis stretch (1: on, ``improved``'s retry; 0:
    # square, as on the axis)
    "OFF_AXIS",
    # the descent leaves out side boxes more than R in front of the centre box, an occluder (1: on,
    # ``improved``'s second search of a frame where none was accepted; 0: off)
    "OCCLUDER_BOUND",
    # the hypotheses' score: the pretest's agreement (0), or the log-likelihood ratio of the cap's relief
    # against a flat surface (1, ``improved``'s relief search of a frame where none was accepted)
    "ORDER_RELIEF",
)
#: The band's cap over R: a band wider than 1.5 R takes in the background behind a far ball.
MAX_EPS_FRACTION = 1.5
for _index, _name in enumerate(PARAMETERS):
    globals()["P_" + _name] = _index
N_PRM = len(PARAMETERS)
#: The packed table's count field starts at this bit; the depth sum (mm) takes the bits below.
COUNT_SHIFT = 40
_DEPTH_MASK = (1 << COUNT_SHIFT) - 1


@kernel
def noise_eps(cz, eps, noise_a, noise_k, cap):
    """Shell half-width at depth cz: max(eps, k sigma_z), sigma_z = noise_a cz^2 (metres), at most cap."""
    e = max(eps, noise_k * noise_a * cz * cz)
    return min(e, cap) if cap > eps else eps


#: The depth histogram (for the scene's far depth) counts about HIST_SAMPLES points, every k-th one
#: (k at least HIST_STRIDE): enough for a percentile, and consecutive increments of one bin would
#: serialise the pass.
HIST_STRIDE = 8
HIST_SAMPLES = 32768


@kernel
def _packed(z):
    """One pixel's entry of the summed-area table: its depth z (float32 m) in mm, plus a count of one
    (``prepare_organised``)."""
    # a term's bound (mm): depths beyond 4,000 km saturate instead of wrapping; through int64:
    # numba's float-to-uint32 conversion cost a tenth of the pass
    mm = min(z * np.float32(1000.0) + np.float32(0.5), np.float32(2.0 ** 32))
    return np.uint64(np.int64(mm)) + (np.uint64(1) << np.uint64(COUNT_SHIFT))


@kernel
def _pixels_one_cell(points, rows, cols, img1, tab1, width, height, mm_limit):
    """``prepare_organised``'s pass where a table cell is one pixel: index and packed depth stored
    (img1, tab1: flat views). Returns (non-finite count, count of |z| > mm_limit)."""
    wc = width + 1
    n_bad = 0
    n_big = 0
    for i in range(points.shape[0]):
        x, y, z = points[i, 0], points[i, 1], points[i, 2]
        if not math.isfinite(x + y + z):  # NaN or inf anywhere (a huge finite sum too: no such point is sane)
            n_bad += 1
            continue
        if abs(z) > mm_limit:  # a branch, rarely taken: adding the comparison's bool cost 7-13 % of the pass
            n_big += 1
        r, c = rows[i], cols[i]
        if z > 0.0 and np.uint32(r) < np.uint32(height) and np.uint32(c) < np.uint32(width):
            img1[r * width + c] = i
            tab1[(r + 1) * wc + c + 1] = _packed(z)
    return n_bad, n_big


@kernel
def _pixels_to_cells(points, rows, cols, img1, tab1, width, height, wc, row_cell, col_cell, mm_limit):
    """``_pixels_one_cell`` where a table cell sums several pixels: the packed depth added to the
    pixel's cell (a read-modify-write; a cell's sum kept in a register was no faster)."""
    n_bad = 0
    n_big = 0
    for i in range(points.shape[0]):
        x, y, z = points[i, 0], points[i, 1], points[i, 2]
        if not math.isfinite(x + y + z):
            n_bad += 1
            continue
        if abs(z) > mm_limit:
            n_big += 1
        r, c = rows[i], cols[i]
        if z > 0.0 and np.uint32(r) < np.uint32(height) and np.uint32(c) < np.uint32(width):
            img1[r * width + c] = i
            if row_cell[r] >= 0:
                tab1[row_cell[r] * wc + col_cell[c]] += _packed(z)
    return n_bad, n_big


@kernel
def prepare_organised(points, rows, cols, img, tab, row_cell, col_cell, mm_limit, hist, hist_per_m):
    """One pass over an organised cloud, then the table's prefix sums.

    Fills img (H, W) int32 (the point index of each pixel, -1 where none), tab (Hc + 1, Wc + 1)
    uint64 (summed-area table over cells of the depth z in mm and of the valid count, packed: depth
    + count << COUNT_SHIFT, modulo 2^64; pixel (r, c) is in table cell (row_cell[r], col_cell[c]),
    both (H,), (W,) int32, 1-based; a row with row_cell -1 is left out of the table, see
    ``improved.cell_lookup``) and hist (B,) int64 (counts of z in bins of 1 / hist_per_m
    metres, the last bin open, over every k-th point that gets a pixel). Points with a non-finite
    coordinate or z <= 0 get no pixel, so the search never meets them; two points on one pixel: the
    last one. Returns (finite count, count of |z| > mm_limit). (Lookup tables: an integer division
    per point cost more than the rest.)
    """
    height, width = img.shape
    hc, wc = tab.shape[0], tab.shape[1]
    # flat views and unsigned bounds tests: no negative-index wraparound per 2D access
    img1 = img.reshape(img.size)  # views (contiguous arrays only: numba raises otherwise)
    tab1 = tab.reshape(tab.size)
    img1[:] = -1
    tab1[:] = 0
    # one loop per table layout, and the histogram in a pass of its own: a branch on either inside
    # the loop cost a third of the frame pass
    if hc == height + 1 and wc == width + 1:
        n_bad, n_big = _pixels_one_cell(points, rows, cols, img1, tab1, width, height, mm_limit)
    else:
        n_bad, n_big = _pixels_to_cells(points, rows, cols, img1, tab1, width, height, wc, row_cell, col_cell,
                                        mm_limit)
    hist[:] = 0
    nb = hist.shape[0]
    n = points.shape[0]
    for i in range(0, n, max(HIST_STRIDE, n // HIST_SAMPLES)):
        z = points[i, 2]
        if (math.isfinite(points[i, 0] + points[i, 1] + z) and z > 0.0 and np.uint32(rows[i]) < np.uint32(height)
                and np.uint32(cols[i]) < np.uint32(width)):
            hist[min(int(z * hist_per_m), nb - 1)] += 1
    # row by row: a running sum along the row (serial) plus the row above's prefix sums
    for r in range(1, hc):
        row, above = tab[r], tab[r - 1]
        a = np.uint64(0)
        for c in range(1, wc):
            a += row[c]
            row[c] = a + above[c]
    return n - n_bad, n_big


@kernel
def hist_percentile(hist, q, step_m):
    """The q-th percentile (0-100) of the values counted in hist (B,) int64 (bins of step_m), to a
    bin's upper edge: the first bin whose cumulative count reaches q % of the total; nan when empty."""
    total = 0
    for b in range(hist.shape[0]):
        total += hist[b]
    if total == 0:
        return math.nan
    target = q / 100.0 * total
    k = 0
    run = hist[0]
    while run < target and k < hist.shape[0] - 1:
        k += 1
        run += hist[k]
    return (k + 1) * step_m


@kernel
def noise_samples(points, img, lag, row_step, col_step, z_min, out):
    """Second differences of depth along image rows, as a frame's own noise sample.

    For every row_step-th row and col_step-th column where the pixels u - lag, u and u + lag all
    have depth, out receives |z(u - lag) - 2 z(u) + z(u + lag)| / (sqrt(6) z(u)^2) (1/m): on a smooth
    surface a lag-apart second difference is noise alone (a plane's curvature over a few pixels is
    a fraction of a millimetre), with variance 6 sigma_z^2 when the lag exceeds the noise's
    correlation length (edges and flying pixels give the few large values, which the caller trims:
    ``improved.frame_noise_a``). Pixels nearer than z_min metres are left
    out (1 mm depth counts dominate their noise). Returns the number of samples written (at most
    out.size).
    """
    height, width = img.shape
    m = 0
    inv = 1.0 / math.sqrt(6.0)
    for r in range(0, height, row_step):
        base = r * width
        for c in range(lag, width - lag, col_step):
            i0, i1, i2 = img.flat[base + c - lag], img.flat[base + c], img.flat[base + c + lag]
            if i0 < 0 or i1 < 0 or i2 < 0:
                continue
            z = points[i1, 2]
            if z < z_min:
                continue
            if m == out.shape[0]:
                return m
            out[m] = abs(points[i0, 2] - 2.0 * z + points[i2, 2]) * inv / (z * z)
            m += 1
    return m


# The organised search's stencil (``front_hypothesis``), in fractions of the ball's disc radius r (in
# cells, at the box's depth): a centre box and four side boxes on the cap, eight boxes on the outline
# ring, and the plane prefilter's boxes beyond the disc.
BOX_HALF_FRACTION = 0.25  # the boxes' half-side: small enough that the side boxes lie on the cap
BOX_OFFSET_FRACTION = 0.5  # the side boxes' offset: the cap's relief there is 13 % of R
RING_OFFSET_FRACTION = 1.5  # the outline ring's boxes: half a disc radius beyond the outline
RING_HALF_FRACTION = 0.25  # their half-side
PREFILTER_OFFSET_FRACTION = 2.0  # the plane prefilter's boxes: clear of the ball's own disc
DESCENT_STEPS = 3  # steps from the first cell toward the front point (a cell on the disc reaches it in 3)
BOX_MIN_VALID = 0.3  # a box with a smaller valid share of its pixels is invalid (a hole, the shadow band)
PRETEST_MAX_CONTINUED = 3  # of the 8 ring boxes, at most this many continue the surface at the ball's depth
PRETEST_SLACK = 0.1  # the pretest's added tolerance (* R): the cap's box means are not its points


@kernel
def box_sums(tab, v, u, h):
    """(depth sum in mm, valid count, area in cells) of the box of half-side h cells about cell (v, u),
    clipped to the grid (area 0 when it is wholly outside)."""
    hc, wc = tab.shape[0] - 1, tab.shape[1] - 1
    r0, r1 = max(v - h, 0), min(v + h + 1, hc)
    c0, c1 = max(u - h, 0), min(u + h + 1, wc)
    if r0 >= r1 or c0 >= c1:
        return 0, 0, 0
    p = tab[r1, c1] - tab[r0, c1] - tab[r1, c0] + tab[r0, c0]  # uint64: wraps, exact for the box
    return np.int64(p & np.uint64(_DEPTH_MASK)), np.int64(p >> np.uint64(COUNT_SHIFT)), (r1 - r0) * (c1 - c0)


@kernel
def box_range(tab, prm, v, u, h):
    """(mean range m, valid count) of the box of half-side h cells about cell (v, u); the mean is nan
    when under BOX_MIN_VALID of the box's pixels are valid (a hole, the shadow band, off the image)."""
    s, n, a = box_sums(tab, v, u, h)
    return sums_range(prm, v, u, s, n, a), n


@kernel
def sums_range(prm, v, u, s, n, a):
    """``box_range``'s mean range from the box's sums (``box_sums``)."""
    if n == 0 or n < BOX_MIN_VALID * a * prm[P_CELL_PX]:
        return math.nan
    b = prm[P_BIN]
    rx = (u * b + 0.5 * (b - 1.0) - prm[P_PPX]) / prm[P_FX]
    ry = (v * b + 0.5 * (b - 1.0) - prm[P_PPY]) / prm[P_FY]
    return s / n * 1e-3 * math.sqrt(1.0 + rx * rx + ry * ry)


@kernel
def descent_step(m0, mA, mB, d, k, off, lim, near):
    """Step (cells) toward the sphere's front point along one axis, from the mean ranges m0 at the
    current cell and mA, mB at -d and +d cells, with the sphere's known curvature k (metres per
    cell^2: near its front point a cap's range is front + k x^2). A side mean that is missing or
    more than ``off`` metres above m0 (off the cap: the background), or more than ``near`` metres
    below it (in front of the cap: an occluder; inf: no such bound), is not used; none usable: no
    step. (A free parabola through the three means overshoots when one of them is off the cap,
    and then oscillates.) Clamped to +/- lim."""
    okA = not math.isnan(mA) and mA - m0 <= off and m0 - mA <= near
    okB = not math.isnan(mB) and mB - m0 <= off and m0 - mB <= near
    if okA and okB:
        x = (mA - mB) / (4.0 * k * d)
    elif okB:
        x = (d * d - (mB - m0) / k) / (2.0 * d)
    elif okA:
        x = ((mA - m0) / k - d * d) / (2.0 * d)
    else:
        return 0.0
    return min(max(x, -lim), lim)


@kernel
def cap_relief(s):
    """Range relief of a sphere's visible cap, in units of R, at squared lateral offset s (units of R^2):
    1 - sqrt(1 - s) (s clipped to 1). A box's mean is approximated by its value at the box's mean s."""
    return 1.0 - math.sqrt(1.0 - min(s, 1.0))


@kernel
def stencil_stretch(prm, v, u):
    """(su, sv): pixels per pixel-on-the-axis of a small angle along the image's u and v axes at cell
    (v, u). A ball off the optical axis images larger than on it, 1 / cos^2 of its angle radially and
    1 / cos tangentially; with x, y the cell centre's normalised coordinates and n2 = 1 + x^2 + y^2,
    a step along u spans n2 / sqrt(1 + y^2) times the angle it spans on the axis, along v n2 / sqrt(1 + x^2).
    (1, 1) when prm[P_OFF_AXIS] is 0."""
    if prm[P_OFF_AXIS] == 0.0:
        return 1.0, 1.0
    b = prm[P_BIN]
    x = (u * b + 0.5 * (b - 1.0) - prm[P_PPX]) / prm[P_FX]
    y = (v * b + 0.5 * (b - 1.0) - prm[P_PPY]) / prm[P_FY]
    n2 = 1.0 + x * x + y * y
    return n2 / math.sqrt(1.0 + y * y), n2 / math.sqrt(1.0 + x * x)


@kernel
def plane_free(tab, prm, v, u, m0, s0, n0):
    """False if the inverse depth about cell (v, u) is affine within noise along every available axis
    (horizontal, vertical, then the diagonals while an axis is missing, two at most): the second
    difference of 1 / (box mean z) over boxes at +/- prefilter_offset r (half-side box_half r; the centre
    box has half-side 1), within 3 sigma (inverse depth has per-pixel noise noise_a at any depth:
    sigma_z = noise_a z^2) plus slack. A box off the image or without depth makes its axis missing;
    no axis at all, or a curved one, keeps the cell. m0, s0, n0: the centre box's mean range and sums
    (``box_sums``; the caller has them)."""
    R = prm[P_R]
    rr = prm[P_FX] / prm[P_BIN] * R / m0
    hp = max(1, int(BOX_HALF_FRACTION * rr + 0.5))
    su, sv = stencil_stretch(prm, v, u)
    dpu = int(PREFILTER_OFFSET_FRACTION * rr * su + 0.5)
    dpv = int(PREFILTER_OFFSET_FRACTION * rr * sv + 0.5)
    dgu = int(PREFILTER_OFFSET_FRACTION * rr * su * 0.7071067811865476 + 0.5)
    dgv = int(PREFILTER_OFFSET_FRACTION * rr * sv * 0.7071067811865476 + 0.5)
    bb = prm[P_CELL_PX]
    if n0 == 0:
        return True
    i0 = 1000.0 * n0 / s0
    planar = 0
    for axis in range(4):
        du = dpu if axis == 0 else (0 if axis == 1 else dgu)
        dv = 0 if axis == 0 else (dpv if axis == 1 else (dgv if axis == 2 else -dgv))
        sa, na_, aa = box_sums(tab, v + dv, u + du, hp)
        sb, nb_, ab = box_sums(tab, v - dv, u - du, hp)
        if na_ == 0 or nb_ == 0 or na_ < BOX_MIN_VALID * aa * bb or nb_ < BOX_MIN_VALID * ab * bb:
            continue
        q = 1000.0 * na_ / sa + 1000.0 * nb_ / sb - 2.0 * i0
        tol = (3.0 * prm[P_NOISE_A] * prm[P_MEAN_NOISE] * math.sqrt(1.0 / na_ + 1.0 / nb_ + 4.0 / n0)
               + PRETEST_SLACK * R / (m0 * m0))
        if abs(q) > tol:
            return True
        planar += 1
        if planar == 2:
            return False
    return planar == 0


@kernel
def ring_boxes(tab, prm, v, u, front, sig):
    """The eight boxes around the outline of the sphere whose front point (range ``front`` m) is on
    the ray through cell (v, u): at ring_offset r in the 4 axis and 4 diagonal directions, half-side
    ring_half r (r: the disc radius in cells). Each is background (farther than the centre, or
    invalid: the shadow band, nothing), an occluder (nearer than the front by 3 sigma / sqrt(n) +
    slack, sig: one pixel's noise) or continues the surface at the ball's depth (a wall, a floor, a
    bigger object). Returns (r, background count, continued count); stops counting past
    PRETEST_MAX_CONTINUED continued."""
    R = prm[P_R]
    dist = front + R
    rr = prm[P_FX] / prm[P_BIN] * R / math.sqrt(max(dist * dist - R * R, 1e-12))
    hr = max(1, int(RING_HALF_FRACTION * rr + 0.5))
    su, sv = stencil_stretch(prm, v, u)
    dru = RING_OFFSET_FRACTION * rr * su
    drv = RING_OFFSET_FRACTION * rr * sv
    ddu = dru * 0.7071067811865476
    ddv = drv * 0.7071067811865476
    slack = PRETEST_SLACK * R
    cont = 0
    bg = 0
    for j in range(8):
        if j < 4:
            ou = dru if j == 0 else (-dru if j == 1 else 0.0)
            ov = drv if j == 2 else (-drv if j == 3 else 0.0)
        else:
            ou = ddu if (j == 4 or j == 6) else -ddu
            ov = ddv if (j == 4 or j == 5) else -ddv
        m, n = box_range(tab, prm, v + int(math.floor(ov + 0.5)), u + int(math.floor(ou + 0.5)), hr)
        if math.isnan(m) or m > dist:
            bg += 1
        elif m >= front - (3.0 * sig / math.sqrt(n) + slack):
            cont += 1
            if cont > PRETEST_MAX_CONTINUED:
                break
    return rr, bg, cont


@part
def _stencil(tab, prm, v, u, rr):
    """The descent's five box means about cell (v, u), for a ball's disc radius of rr cells: returns
    (su, sv) (``stencil_stretch``), the boxes' half-side h = box_half r and the side boxes' offsets
    du, dv = box_offset r along u and v (cells, stretched by su, sv), then (mean range m, valid
    count) (``box_range``) of the centre box (m0, n0), and of the left (mL, nL), right (mR, nR),
    upper (mU, nU) and lower (mD, nD) boxes; the side boxes are nan and 0 when m0 is nan."""
    su, sv = stencil_stretch(prm, v, u)
    h = max(1, int(BOX_HALF_FRACTION * rr + 0.5))
    du = max(h + 1, int(BOX_OFFSET_FRACTION * rr * su + 0.5))
    dv = max(h + 1, int(BOX_OFFSET_FRACTION * rr * sv + 0.5))
    m0, n0 = box_range(tab, prm, v, u, h)
    if math.isnan(m0):
        return su, sv, h, du, dv, m0, n0, math.nan, 0, math.nan, 0, math.nan, 0, math.nan, 0
    mL, nL = box_range(tab, prm, v, u - du, h)
    mR, nR = box_range(tab, prm, v, u + du, h)
    mU, nU = box_range(tab, prm, v - dv, u, h)
    mD, nD = box_range(tab, prm, v + dv, u, h)
    return su, sv, h, du, dv, m0, n0, mL, nL, mR, nR, mU, nU, mD, nD


@part
def _descent_move(prm, rr, su, sv, du, dv, m0, n0, mL, mR, mU, mD):
    """The descent's move (iu, iv) in whole cells toward the front point, from the stencil's means
    (``_stencil``; m metres, n0 the centre box's valid count): ``descent_step`` along u and along v
    with the cap's curvature there, at most r / 2 cells (r = rr cells, stretched by su, sv)."""
    R = prm[P_R]
    na = prm[P_NOISE_A] * prm[P_MEAN_NOISE]  # box means: correlated pixels count as fewer
    slack = PRETEST_SLACK * R
    off = 0.6 * R + 3.0 * na * m0 * m0 / math.sqrt(n0) + slack
    ku, kv = 0.5 * R / (rr * su) ** 2, 0.5 * R / (rr * sv) ** 2
    # a side box more than R (and the noise) in front of the centre box lies on no cap through it:
    # an occluder, which pulls the descent off a partly hidden ball. (Beside a ball, on the
    # background, the ball's box is nearer by as much: there the bound stops the descent that
    # would reach the ball, so it is only for ``improved``'s second search)
    near = R + 3.0 * na * m0 * m0 / math.sqrt(n0) + slack if prm[P_OCCLUDER_BOUND] != 0.0 else np.inf
    iu = int(math.floor(descent_step(m0, mL, mR, du, ku, off, 0.5 * rr * su, near) + 0.5))
    iv = int(math.floor(descent_step(m0, mU, mD, dv, kv, off, 0.5 * rr * sv, near) + 0.5))
    return iu, iv


@part
def _cap_pretest(prm, rr, su, sv, h, du, dv, m0, mL, nL, mR, nR, mU, nU, mD, nD):
    """The pretest's side boxes at the resting cell (the last ``_stencil``'s values): the front range
    m0 - R cap_relief of the centre box, each side box's mean against the cap's range relief
    (``cap_relief``) above the front, within 3 sigma / sqrt(n) + slack. Returns (front m, one pixel's
    noise sig m at the centre box's range, the side boxes that agree, lie behind the cap (a surface
    seen through the ball) or well in front of it (more than R past the tolerance: an occluder hides
    that side of the ball), and the agreeing ones' chi^2)."""
    R = prm[P_R]
    na = prm[P_NOISE_A] * prm[P_MEAN_NOISE]  # box means: correlated pixels count as fewer
    slack = PRETEST_SLACK * R
    # offsets and the boxes' half-sides in units of the ball's angular radius along each axis (the
    # same on the axis)
    ahu = (h + 0.5) / (rr * su)
    ahv = (h + 0.5) / (rr * sv)
    spread = (ahu * ahu + ahv * ahv) / 3.0
    xu = du / (rr * su)
    xv = dv / (rr * sv)
    front = m0 - R * cap_relief(spread)
    pred_u = front + R * cap_relief(xu * xu + spread)
    pred_v = front + R * cap_relief(xv * xv + spread)
    sig = na * m0 * m0
    agree = 0
    behind = 0
    occl = 0
    chi = 0.0
    for j in range(4):
        m = mL if j == 0 else (mR if j == 1 else (mU if j == 2 else mD))
        nk = nL if j == 0 else (nR if j == 1 else (nU if j == 2 else nD))
        if math.isnan(m):
            continue
        tol = 3.0 * sig / math.sqrt(nk) + slack
        res = m - (pred_u if j < 2 else pred_v)
        if res > tol:
            behind += 1
        elif res >= -tol:
            agree += 1
            chi += (res / tol) ** 2
        elif res < -(tol + R):  # well in front: an occluder hides this side of the cap
            occl += 1
    return front, sig, agree, behind, occl, chi


@kernel
def front_hypothesis(tab, prm, v, u, out):
    """A hypothesis from the first cell (v, u), and its O(1) pretest; returns its score (-inf: rejected).

    Descent: the ball's front point is the local minimum of the range |p| (it lies on the ray through
    the centre). A stencil of five box means (``_stencil``: centre, left, right, up, down; half-side
    box_half r, offset box_offset r, r the ball's disc radius in cells at the centre box's range) and
    the sphere's known curvature give the step to the front point (``_descent_move``), at most r / 2,
    up to DESCENT_STEPS times. The means average sigma / sqrt(n) of the per-pixel noise, which is
    what makes a hypothesis possible at 3 m, where one pixel's depth is +/- 7 cm and the relief
    between two pixels 1-2 cm.
    Before it, ``plane_free`` drops first cells on a plane (most of them). Pretest at the resting
    cell, all from the table: at least three of the four side boxes must lie on the sphere's cap
    (``_cap_pretest``), or two and a third well in front (out[4] flags such a hypothesis, which
    ``improved`` verifies only while no sphere has been accepted), at most one *behind* it (one box
    may straddle the outline); of the eight ``ring_boxes`` at most PRETEST_MAX_CONTINUED may continue
    the surface at the ball's depth. out (5,) gets (v, u, front range m, disc radius cells, occluded
    flag); the score is 2 agreeing + background ring boxes - 2 continued - 2 behind - chi^2 / 2 of
    the agreeing ones (at most 16).
    """
    R = prm[P_R]
    fc = prm[P_FX] / prm[P_BIN]
    hc, wc = tab.shape[0] - 1, tab.shape[1] - 1
    s0, n0, a0 = box_sums(tab, v, u, 1)
    m0 = sums_range(prm, v, u, s0, n0, a0)
    if math.isnan(m0):
        return -np.inf
    # prefilter: inverse depth is affine in the pixel coordinates on any plane, so its second
    # difference over boxes two disc radii apart (off the ball wherever on it the first cell is)
    # vanishes on a wall, a floor, a box face (most first cells) and not where a ball stands out
    if not plane_free(tab, prm, v, u, m0, s0, n0):
        return -np.inf
    h = 1
    du = dv = 2
    rr = 1.0
    su = sv = 1.0
    mL = mR = mU = mD = 0.0
    nL = nR = nU = nD = 0
    steps = DESCENT_STEPS
    for step in range(steps + 1):
        rr = fc * R / m0
        if rr < prm[P_RR_MIN] or rr > prm[P_RR_MAX]:
            return -np.inf
        # the side boxes' offsets follow the silhouette's stretch along each axis (``stencil_stretch``)
        su, sv, h, du, dv, m0, n0, mL, nL, mR, nR, mU, nU, mD, nD = _stencil(tab, prm, v, u, rr)
        if math.isnan(m0):
            return -np.inf
        if step == steps:
            break
        iu, iv = _descent_move(prm, rr, su, sv, du, dv, m0, n0, mL, mR, mU, mD)
        if iu == 0 and iv == 0:
            break
        u += iu
        v += iv
        if u < 0 or u >= wc or v < 0 or v >= hc:
            return -np.inf
    front, sig, agree, behind, occl, chi = _cap_pretest(prm, rr, su, sv, h, du, dv, m0, mL, nL, mR, nR, mU, nU,
                                                        mD, nD)
    if behind > 1 or agree + min(occl, 1) < 3:
        return -np.inf
    # pretest: the ring around the outline
    rr, bg, cont = ring_boxes(tab, prm, v, u, front, sig)
    if cont > PRETEST_MAX_CONTINUED:
        return -np.inf
    out[0], out[1], out[2], out[3], out[4] = v, u, front, rr, 1.0 if agree < 3 else 0.0
    if prm[P_ORDER_RELIEF] != 0.0:
        return _relief_llr(prm, rr, su, sv, h, du, dv, m0, n0, mL, nL, mR, nR, mU, nU, mD, nD)
    return 2.0 * agree + bg - 2.0 * cont - 2.0 * behind - 0.5 * chi


@part
def _relief_llr(prm, rr, su, sv, h, du, dv, m0, n0, mL, nL, mR, nR, mU, nU, mD, nD):
    """The side boxes' evidence for the cap against a flat surface through the centre box: the sum over
    the boxes that agree with the cap (``_cap_pretest``'s tolerance) of the log-likelihood ratio of
    their mean's rise over the centre box's, d, under the cap's relief delta against none,
    (2 d delta - delta^2) / (2 var), var the two means' noise (one pixel's sigma^2 (1 / n + 1 / n0),
    correlated pixels counting as fewer). A near ball's cap stands many standard errors out; a bump
    of correlated noise on a wall a few."""
    R = prm[P_R]
    na = prm[P_NOISE_A] * prm[P_MEAN_NOISE]
    sig = na * m0 * m0
    ahu = (h + 0.5) / (rr * su)
    ahv = (h + 0.5) / (rr * sv)
    spread = (ahu * ahu + ahv * ahv) / 3.0
    xu = du / (rr * su)
    xv = dv / (rr * sv)
    base = cap_relief(spread)
    rise_u = R * (cap_relief(xu * xu + spread) - base)
    rise_v = R * (cap_relief(xv * xv + spread) - base)
    llr = 0.0
    for j in range(4):
        m = mL if j == 0 else (mR if j == 1 else (mU if j == 2 else mD))
        nk = nL if j == 0 else (nR if j == 1 else (nU if j == 2 else nD))
        if math.isnan(m) or nk == 0 or n0 == 0:
            continue
        delta = rise_u if j < 2 else rise_v
        d = m - m0
        if abs(d - delta) > 3.0 * sig / math.sqrt(nk) + PRETEST_SLACK * R:
            continue  # behind or in front of the cap: no evidence for it
        llr += (2.0 * d * delta - delta * delta) / (2.0 * max(sig * sig * (1.0 / nk + 1.0 / n0), 1e-12))
    return llr


@kernel
def _keep_hypothesis(cands, n_kept, v, u, front, rr, q, occluded, radius):
    """Keep the best distinct hypotheses in cands (K, 6) rows (v, u, front m, r cells, score, occluded
    flag), best first: one within r / 2 cells (and R in range) of a kept one is the same ball (the
    better stays)."""
    k_max = cands.shape[0]
    lim = 0.5 * rr
    for j in range(n_kept):
        if abs(cands[j, 0] - v) <= lim and abs(cands[j, 1] - u) <= lim and abs(cands[j, 2] - front) <= radius:
            if q <= cands[j, 4]:
                return n_kept
            for m in range(j, n_kept - 1):
                cands[m, :] = cands[m + 1, :]
            n_kept -= 1
            break
    if n_kept == k_max and q <= cands[n_kept - 1, 4]:
        return n_kept
    pos = n_kept if n_kept < k_max else k_max - 1
    while pos > 0 and cands[pos - 1, 4] < q:
        if pos < k_max:
            cands[pos, :] = cands[pos - 1, :]
        pos -= 1
    cands[pos, 0], cands[pos, 1], cands[pos, 2], cands[pos, 3], cands[pos, 4] = v, u, front, rr, q
    cands[pos, 5] = occluded
    return min(n_kept + 1, k_max)


@kernel
def disc_hypotheses(tab, prm, z_min_m, inner_fraction, side_offset_fraction, side_half_fraction, gap_min_m,
                    gap_sigmas, min_behind, step, cands):
    """Hypotheses of balls whose cap's relief is below the noise: discs that stand out of what is
    behind them. Every ``step``-th cell in both directions whose 3 x 3 box lies beyond z_min_m is a
    first cell; r is the disc radius (cells) of a ball at the range m_in of the box of half-side
    inner_fraction r about it (the middle of a ball's disc), and four side boxes (half-side
    side_half_fraction r) at side_offset_fraction r along the image axes lie off that disc. A side is
    *behind* when its mean range exceeds m_in by gap_min_m and by gap_sigmas standard errors of the
    two means; at least min_behind of the four (the fourth may be the floor the ball stands on, or an
    occluder). The score is the behind sides' gaps in standard errors (each at most 10), less a
    thousandth of m_in. Kept as ``search_organised`` keeps its (cands (K, 6): v, u, front m, r cells,
    score, 0), best first, the front range m_in less the cap's relief over the inner box. Returns
    the number kept.
    """
    R = prm[P_R]
    fc = prm[P_FX] / prm[P_BIN]
    na = prm[P_NOISE_A] * prm[P_MEAN_NOISE]
    hc, wc = tab.shape[0] - 1, tab.shape[1] - 1
    n_kept = 0
    for v in range(0, hc, step):
        for u in range(0, wc, step):
            m0, _ = box_range(tab, prm, v, u, 1)
            if math.isnan(m0) or m0 < z_min_m:
                continue
            r = fc * R / m0
            hi = max(1, int(inner_fraction * r))
            mi, ni = box_range(tab, prm, v, u, hi)
            if math.isnan(mi) or mi < z_min_m:
                continue
            r = fc * R / mi
            d = int(side_offset_fraction * r + 0.5)
            hs = max(1, int(side_half_fraction * r))
            var_i = (na * mi * mi) ** 2 / ni
            behind = 0
            q = 0.0
            for k in range(4):
                dv = -d if k == 0 else (d if k == 1 else 0)
                du = -d if k == 2 else (d if k == 3 else 0)
                ms, ns = box_range(tab, prm, v + dv, u + du, hs)
                if math.isnan(ms):
                    continue
                se = math.sqrt(var_i + (na * ms * ms) ** 2 / ns)
                gap = ms - mi
                if gap >= gap_min_m and gap >= gap_sigmas * se:
                    behind += 1
                    q += min(gap / se, 10.0)
            if behind < min_behind:
                continue
            # the inner box's mean squared offset is 2/3 (hi / r)^2 of r^2: the cap's relief there
            front = mi - R * cap_relief(2.0 * (hi / r) ** 2 / 3.0)
            # ties (sides far behind all reach the cap) go to the nearest inner mean, the cap's middle
            n_kept = _keep_hypothesis(cands, n_kept, float(v), float(u), front, r, q - 1e-3 * mi, 0.0, R)
    return n_kept


@part
def _ring_hit(tab, prm, v, u, dv, du, reach, min_cell):
    """March from cell (v, u) along (dv, du) cells per step, up to ``reach`` steps, to the first cell
    with at least ``min_cell`` valid pixels: (steps taken, that cell's mean range m); (0, nan) when
    none is met (off the grid, or the reach spent)."""
    hc, wc = tab.shape[0] - 1, tab.shape[1] - 1
    for t in range(1, reach + 1):
        vv, uu = v + dv * t, u + du * t
        if vv < 0 or vv >= hc or uu < 0 or uu >= wc:
            return 0, math.nan
        s, n, a = box_sums(tab, vv, uu, 0)
        if n >= min_cell:
            return t, sums_range(prm, vv, uu, s, n, a)
    return 0, math.nan


@kernel
def hole_hypotheses(tab, prm, z_min_m, step, min_ring, min_hole_fraction, cands):
    """Hypotheses of balls whose depth is missing over the middle of their face (a saturated or
    specular cap) and valid on a ring around it, which the descent cannot reach (its boxes in the
    hole have no mean). Every ``step``-th cell in both directions without a valid pixel is a first
    cell; from it, in the 4 axis and 4 diagonal directions, ``_ring_hit`` finds the hole's edge
    within the disc radius of a ball at z_min_m. A hole of a ball: at least ``min_ring`` of the
    eight edges found, their ranges within R (and 3 sigma of one pixel, and the slack) of their
    median, the hole's mean radius within the disc radius r of a ball at that range and at least
    ``min_hole_fraction`` r (smaller holes leave the descent its boxes). The hypothesis is the
    ray through the mean of the edge points (the hole's centre; a hole lies about the ball's
    specular point, on the ray through its centre), its front the edges' ranges less the cap's
    relief at their offsets; at most PRETEST_MAX_CONTINUED of its ``ring_boxes`` may continue the
    surface at its depth. Score: the edges found and the background ring boxes, less 2 per
    continued one and a thousandth of the front range; kept as ``search_organised`` keeps its (cands (K, 6): v, u, front m, r cells, score, 0). Returns the
    number kept.
    """
    R = prm[P_R]
    fc = prm[P_FX] / prm[P_BIN]
    hc, wc = tab.shape[0] - 1, tab.shape[1] - 1
    reach = int(fc * R / z_min_m) + 1
    min_cell = max(1.0, 0.5 * prm[P_CELL_PX])
    slack = PRETEST_SLACK * R
    rng = np.empty(8)
    ev = np.empty(8)
    eu = np.empty(8)
    work = np.empty(8)
    n_kept = 0
    for v in range(0, hc, step):
        for u in range(0, wc, step):
            _s, n0, _a = box_sums(tab, v, u, 0)
            if n0 > 0:
                continue
            k = 0
            for j in range(8):
                dv = 1 if j == 0 else (-1 if j == 1 else (0 if j < 4 else (1 if j < 6 else -1)))
                du = 0 if j < 2 else (1 if j == 2 else (-1 if j == 3 else (1 if j % 2 == 0 else -1)))
                t, m = _ring_hit(tab, prm, v, u, dv, du, reach, min_cell)
                if t == 0 or math.isnan(m):
                    continue
                # the edge lies half a cell before the first valid cell's centre
                ev[k], eu[k], rng[k] = v + dv * (t - 0.5), u + du * (t - 0.5), m
                k += 1
            if k < min_ring:
                continue
            work[:k] = rng[:k]
            med = np.median(work[:k])
            tol = R + 3.0 * prm[P_NOISE_A] * med * med + slack
            cv = 0.0
            cu = 0.0
            ring = 0
            for j in range(k):
                if abs(rng[j] - med) <= tol:
                    cv += ev[j]
                    cu += eu[j]
                    ring += 1
            if ring < min_ring:
                continue
            cv /= ring
            cu /= ring
            r = fc * R / med
            front = 0.0
            mean_d = 0.0
            for j in range(k):
                if abs(rng[j] - med) <= tol:
                    d = math.sqrt((ev[j] - cv) ** 2 + (eu[j] - cu) ** 2)
                    mean_d += d
                    front += rng[j] - R * cap_relief((d / r) ** 2)
            mean_d /= ring
            front /= ring
            if mean_d > r or mean_d < min_hole_fraction * r:
                continue
            vc, uc = int(math.floor(cv + 0.5)), int(math.floor(cu + 0.5))
            # a ball stands out of what is around it: the boxes about its outline lie behind it (a
            # hole in a wall, a dropout on a low-texture floor, has the wall or floor all round)
            sig = prm[P_NOISE_A] * prm[P_MEAN_NOISE] * med * med
            rr, bg, cont = ring_boxes(tab, prm, vc, uc, front, sig)
            if cont > PRETEST_MAX_CONTINUED:
                continue
            q = ring + bg - 2.0 * cont - 1e-3 * front
            # one hole's first cells give fronts that differ by the ring's few noisy pixels: the same ball
            n_kept = _keep_hypothesis(cands, n_kept, float(vc), float(uc), front, rr, q, 0.0,
                                      R + 2.0 * sig / math.sqrt(ring))
    return n_kept


@kernel
def cell_centres(prm, hyp):
    """The sphere centres (M, 3) of hypotheses hyp (M, >= 3) rows (v, u, front m, ...): on the ray
    through cell (v, u)'s centre pixel, at front range + R (the front point of a sphere lies on the
    ray through its centre)."""
    b = prm[P_BIN]
    out = np.empty((hyp.shape[0], 3))
    for k in range(hyp.shape[0]):
        rx = (hyp[k, 1] * b + 0.5 * (b - 1.0) - prm[P_PPX]) / prm[P_FX]
        ry = (hyp[k, 0] * b + 0.5 * (b - 1.0) - prm[P_PPY]) / prm[P_FY]
        t = (hyp[k, 2] + prm[P_R]) / math.sqrt(rx * rx + ry * ry + 1.0)
        out[k, 0], out[k, 1], out[k, 2] = rx * t, ry * t, t
    return out


@kernel
def search_organised(tab, prm, seed, cands, counters):
    """Stratified RANSAC on the cell grid: the grid is cut into strata of ``prm[P_STRATUM_V]`` x
    ``prm[P_STRATUM_U]`` cells (those at the far edges smaller), visited in raster order; in each, one
    first cell is drawn uniformly and gives one ``front_hypothesis``. The distinct passing ones are
    kept by score in cands (K, 6) (v, u, front m, r cells, score, occluded flag: ``front_hypothesis``),
    best first (``cell_centres`` gives their centres).

    Why strata rather than independent draws: a ball is missed only if every stratum it covers draws
    off it or fails, so the miss probability is at most that of as many independent draws (the
    bound, ``improved.strata``) and far below it once the ball covers whole strata; and first cells
    in raster order keep the table's rows in cache (a third of the time per draw of random points).
    counters (2,) int64 gets: first cells drawn, hypotheses past the pretest. Returns the number of
    hypotheses kept.
    """
    hc, wc = tab.shape[0] - 1, tab.shape[1] - 1
    sv, su = max(1, int(prm[P_STRATUM_V])), max(1, int(prm[P_STRATUM_U]))
    counters[:] = 0
    state = np.empty(1, np.uint64)
    state[0] = np.uint64(seed)
    out = np.empty(5, np.float64)
    n_kept = 0
    for v0 in range(0, hc, sv):
        nv = min(sv, hc - v0)
        for u0 in range(0, wc, su):
            nu = min(su, wc - u0)
            v = v0 + min(int(next_u01(state) * nv), nv - 1)
            u = u0 + min(int(next_u01(state) * nu), nu - 1)
            counters[0] += 1
            q = front_hypothesis(tab, prm, v, u, out)
            if q == -np.inf:
                continue
            counters[1] += 1
            n_kept = _keep_hypothesis(cands, n_kept, out[0], out[1], out[2], out[3], q, out[4], prm[P_R])
    return n_kept


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

# ----------------------------------------------------------------------------------------------
# Organised clouds: verification of one candidate, in one call.

V_CX, V_CY, V_CZ, V_EPS, V_N, V_FCX, V_FCY, V_FCZ, V_FR, V_FSE, V_RMSE, V_SIGMA = range(12)

# The refinement (``_refine_centre``, ``_final_fits``) and the size check's limit, in fractions of R or r.
FIRST_BAND_FRACTION = 0.5  # the first round's inlier band: a box-mean hypothesis is up to R / 2 off
FIRST_STEPS = 3  # the first round's 3D Gauss-Newton steps
COARSE_BAND_FRACTION = 0.25  # later rounds' band at most this * R (twice the last move while travelling)
SIZE_LIMIT_FRACTION = 0.25  # the free radius never differs from R by more than this * R, whatever its error
RADIUS_SE_S_MIN_FRACTION = 0.3  # the free radius's standard error floors s = sqrt(r^2 - m^2) at this * r
RAY_S_MIN_FRACTION = 0.03  # the ray fits floor s at this * r (a ray grazing the sphere)
FIT_MAX_POINTS = 400  # every fit uses at most about this many inliers, evenly strided

N_VOUT = 12
#: MAD of a normal sample times this is its standard deviation.
MAD_TO_SIGMA = 1.482602218505602


@kernel
def ray_residual_sigma(rays, cx, cy, cz, radius):
    """Robust standard deviation (MAD about the median, metres) of the ray residuals of the points on
    rays (K, 4) (``unit_rays``) about the sphere (c, R); nan when fewer than 8 rays meet it. The
    candidate's own depth noise, whatever the sensor: quantisation steps (a structured-light sensor)
    and spatially correlated errors count, which local differences of the depth image miss."""
    res = np.empty(rays.shape[0], np.float64)
    cc = cx * cx + cy * cy + cz * cz
    m = 0
    for k in range(rays.shape[0]):
        tc = rays[k, 0] * cx + rays[k, 1] * cy + rays[k, 2] * cz
        m2 = cc - tc * tc
        if m2 <= radius * radius:
            res[m] = rays[k, 3] - (tc - math.sqrt(radius * radius - m2))
            m += 1
    if m < 8:
        return math.nan
    r = res[:m]
    med = np.median(r)
    return MAD_TO_SIGMA * np.median(np.abs(r - med))


@kernel
def _strided(idx, n, max_points):
    """idx[:n] thinned by a stride to at most about max_points entries (a view)."""
    step = max(1, (n + max_points - 1) // max_points)
    return idx[0:n:step]


@kernel
def window_stride(cx, cy, cz, radius, fx, max_visits):
    """The stride (rows and columns) that visits about max_visits pixels of a candidate's window."""
    dist = math.sqrt(cx * cx + cy * cy + cz * cz)
    side = 2.0 * (1.1 * disc_radius_px(cz, dist, radius, fx) + 2.0) + 1.0
    return max(1, int(side / math.sqrt(max_visits)))


@part
def _centre_in_front(c, radius):
    """Whether the centre c (3,) m lies more than the radius (m) in front of the camera and from it."""
    return c[2] > radius and c[0] * c[0] + c[1] * c[1] + c[2] * c[2] > radius * radius


@part
def _refine_centre(points, index_image, c, prm, refine_iterations, max_fit_points, s_min, budget, rbuf, idx):
    """``verify_organised``'s refinement rounds, moving the centre c (3,) m in place; False when the
    candidate fails (its centre not in front, ``_centre_in_front``, or fewer than 3 inliers).

    Each round: inliers = silhouette pixels with ray residual within the noise-aware eps at the
    current depth (``gather_window`` into idx, every window visited with the stride that keeps it to
    about ``budget`` pixels; in the first round at least FIRST_BAND_FRACTION R, later at least twice
    the last move, up to COARSE_BAND_FRACTION R), then Gauss-Newton with R fixed on at most
    ``max_fit_points`` of them, evenly strided: in the first round FIRST_STEPS steps on the 3D
    residuals (``refine_fixed_radius``), later one step on the ray residuals (``ray_step``; rays in
    rbuf (max_fit_points, 4)), until the centre moves less than its standard error (or 0.1 mm)."""
    fx, fy, ppx, ppy, radius = prm[P_FX], prm[P_FY], prm[P_PPX], prm[P_PPY], prm[P_R]
    first_band, coarse_band = FIRST_BAND_FRACTION * radius, COARSE_BAND_FRACTION * radius
    moved = coarse_band
    for it in range(refine_iterations):
        if not _centre_in_front(c, radius):
            return False
        e = noise_eps(c[2], prm[P_EPS], prm[P_NOISE_A], prm[P_NOISE_K], prm[P_EPS_CAP])
        # a hypothesis from box means can be a few cm off, and the sphere's own points then lie up
        # to that far from the current one: near the camera eps is 1 cm, and inliers within it would
        # hold the fit where it started. So the band starts wide (first_band) and stays wider
        # than twice the last move while the centre travels
        e = max(e, first_band if it == 0 else min(coarse_band, 2.0 * moved))
        stride = window_stride(c[0], c[1], c[2], radius, max(fx, fy), budget)
        n = gather_window(points, index_image, c[0], c[1], c[2], radius, e, fx, fy, ppx, ppy, stride, idx)
        if n < 3:
            return False
        if it == 0:
            # 3D residuals first: a ray that misses the current sphere (a centre some cm to the side)
            # has a ray residual nearly flat in the centre, and ray steps then creep (a third of the
            # offset per round); ||p - c|| - R pulls from anywhere, and its bias (depth noise along
            # the rays, a few mm at 2 m) is left to the ray steps that follow
            c_new = refine_fixed_radius(points, _strided(idx, n, max_fit_points), c[0], c[1], c[2], radius,
                                        FIRST_STEPS)
            moved = math.sqrt((c_new[0] - c[0]) ** 2 + (c_new[1] - c[1]) ** 2 + (c_new[2] - c[2]) ** 2)
            c[0], c[1], c[2] = c_new[0], c_new[1], c_new[2]
            continue
        rays = unit_rays(points, _strided(idx, n, max_fit_points), rbuf)
        moved = ray_step(rays, c, radius, s_min)
        # the inliers change between rounds: a move within the centre's standard error (per-pixel
        # noise / sqrt(n)) is that jitter, not progress
        if moved < max(1e-4, noise_eps(c[2], 0.0, prm[P_NOISE_A], 1.0, prm[P_EPS_CAP]) / math.sqrt(rays.shape[0])):
            break
    return True


@part
def _final_window(points, index_image, c, prm, max_fit_points, data_noise, budget, rbuf, idx):
    """The inliers of the refined centre c (3,) m at the noise-aware eps (``gather_window`` into idx,
    strided to about ``budget`` pixels). Returns (band e m, stride, inlier count n (visited), their
    rays (K, 4) in rbuf, at most ``max_fit_points`` evenly strided, the per-pixel depth noise sigma m);
    n < 3: the candidate fails.

    sigma is the noise model's at the centre's depth: the most noise expected. A quieter sensor (or a
    nearer ball) shows less in the candidate's own residuals, and a band wider than that takes in the
    outline's mixed pixels, a holder, a hand, which bias the free radius upward. With data_noise the
    band narrows to noise_k times the robust spread of the candidate's own ray residuals
    (``ray_residual_sigma``) where that is below the model's, never below eps (and never widens: on
    clutter the residuals' spread is no noise level), and sigma becomes that spread."""
    fx, fy, ppx, ppy, radius = prm[P_FX], prm[P_FY], prm[P_PPX], prm[P_PPY], prm[P_R]
    e = noise_eps(c[2], prm[P_EPS], prm[P_NOISE_A], prm[P_NOISE_K], prm[P_EPS_CAP])
    stride = window_stride(c[0], c[1], c[2], radius, max(fx, fy), budget)
    n = gather_window(points, index_image, c[0], c[1], c[2], radius, e, fx, fy, ppx, ppy, stride, idx)
    if n < 3:
        return e, stride, n, rbuf[:0], math.nan
    rays = unit_rays(points, _strided(idx, n, max_fit_points), rbuf)
    sigma = noise_eps(c[2], 0.0, prm[P_NOISE_A], 1.0, prm[P_EPS_CAP])
    if sigma <= 0.0:  # no noise model: eps alone
        sigma = prm[P_EPS] / max(prm[P_NOISE_K], 1e-12)
    if data_noise:
        s_hat = ray_residual_sigma(rays, c[0], c[1], c[2], radius)
        if s_hat < sigma:  # False for nan
            sigma = s_hat
            e_data = max(prm[P_EPS], prm[P_NOISE_K] * s_hat)
            if e_data < e:
                e = e_data
                n = gather_window(points, index_image, c[0], c[1], c[2], radius, e, fx, fy, ppx, ppy, stride, idx)
                if n < 3:
                    return e, stride, n, rbuf[:0], sigma
                rays = unit_rays(points, _strided(idx, n, max_fit_points), rbuf)
    return e, stride, n, rays, sigma


@part
def _final_fits(rays, c, radius, hold_direction, s_min, se_s_min):
    """The last fits of the centre c (3,) m on rays (K, 4): 2 more steps with R fixed, then a free-radius
    fit (4 steps; the size check), by the ray residuals (``fit_ray``), or with hold_direction along
    c's ray only (``fit_range``). Returns (centre (3,) m, RMS ray residual m of the fixed-radius fit,
    free centre (3,) m, free radius m, its standard error m)."""
    if hold_direction:
        c, _, _, rms = fit_range(rays, c[0], c[1], c[2], radius, False, 2, s_min, se_s_min)
        fc, fr, fse, _ = fit_range(rays, c[0], c[1], c[2], radius, True, 4, s_min, se_s_min)
    else:
        c, _, _, rms = fit_ray(rays, c[0], c[1], c[2], radius, False, 2, s_min, se_s_min)
        fc, fr, fse, _ = fit_ray(rays, c[0], c[1], c[2], radius, True, 4, s_min, se_s_min)
    return c, rms, fc, fr, fse


@part
def _fails_size_gate(size_gate, fr, fse, radius):
    """Whether a candidate fails ``verify_organised``'s size gate (2,) (tolerance m, standard errors;
    inf tolerance: no gate): its free radius fr m (standard error fse m) off R by more than the
    tolerance plus the standard errors, or than SIZE_LIMIT_FRACTION R whatever its error."""
    if not math.isfinite(size_gate[0]):
        return False
    se = fse if math.isfinite(fse) else radius
    d = abs(fr - radius)
    return not (d <= size_gate[0] + size_gate[1] * se and d <= SIZE_LIMIT_FRACTION * radius)  # nan fails


@kernel
def verify_organised(points, index_image, c0, prm, refine_iterations, max_fit_points, s_min, data_noise, size_gate,
                     hold_direction, idx, out, stats):
    """Refine one candidate centre and measure it; results in out (N_VOUT,), stats (N_STATS,).

    The refinement rounds (``_refine_centre``), then the inliers at the final band (``_final_window``,
    with data_noise narrowed to the candidate's own noise), 2 more steps and a free-radius ray fit
    (``_final_fits``: the size check), and the silhouette statistics (``window_stats``). Every
    window is visited with the stride that keeps it to about 4 ``max_fit_points`` pixels (a ball at
    0.4 m covers 15,000 pixels at 424x240, 140,000 at 1280x720; ``final_inliers`` collects all of
    them for a reported sphere), and every fit uses at most ``max_fit_points`` of the inliers, evenly
    strided; idx receives the window's inliers.
    out[V_N] gets the inlier count (estimated: strided count times stride^2), out[V_RMSE] the RMS of
    the ray residuals over the fitted inliers, out[V_SIGMA] the per-pixel depth noise used (metres:
    the model's at the centre's depth, or the measured one where smaller); out[V_N] = 0 when fewer
    than 3 inliers remain. A candidate that fails the size gate (``_fails_size_gate``) gets
    out[V_N] = -1 and no statistics (most candidates fail here, and the statistics' pass over the
    window is the costliest).
    hold_direction: no refinement rounds, and both fits keep the centre on c0's ray (``fit_range``):
    c0 is a centre placed across the line of sight by other evidence (the outline).
    """
    radius = prm[P_R]
    budget = 4.0 * max_fit_points
    rbuf = np.empty((max_fit_points, 4))  # _strided keeps at most max_fit_points
    c = c0.copy()
    out[:] = math.nan
    out[V_N] = 0.0
    if not hold_direction and not _refine_centre(points, index_image, c, prm, refine_iterations, max_fit_points,
                                                 s_min, budget, rbuf, idx):
        return
    if not _centre_in_front(c, radius):
        return
    e, stride, n, rays, sigma = _final_window(points, index_image, c, prm, max_fit_points, data_noise, budget, rbuf,
                                              idx)
    if n < 3:
        return
    c, rms, fc, fr, fse = _final_fits(rays, c, radius, hold_direction, s_min, RADIUS_SE_S_MIN_FRACTION)
    out[V_FCX], out[V_FCY], out[V_FCZ], out[V_FR], out[V_FSE] = fc[0], fc[1], fc[2], fr, fse
    if _fails_size_gate(size_gate, fr, fse, radius):
        out[V_N] = -1.0
        return
    ring_band = min(e, max(prm[P_EPS], sigma))
    window_stats(points, index_image, c[0], c[1], c[2], e, ring_band, prm,
                 window_stride(c[0], c[1], c[2], radius * RING_FACTOR, max(prm[P_FX], prm[P_FY]), budget),
                 stats)
    out[V_CX], out[V_CY], out[V_CZ], out[V_EPS], out[V_N] = c[0], c[1], c[2], e, n * stride * stride
    out[V_RMSE] = rms
    out[V_SIGMA] = sigma


@kernel
def final_inliers(points, index_image, c, prm, e, idx):
    """All inliers of a verified sphere (every pixel of its window; ``gather_window`` with band e)
    into idx; returns (their count, the RMS of ||p - c|| - R over them)."""
    radius = prm[P_R]
    n = gather_window(points, index_image, c[0], c[1], c[2], radius, e, prm[P_FX], prm[P_FY], prm[P_PPX],
                      prm[P_PPY], 1, idx)
    sse = 0.0
    for k in range(n):
        i = idx[k]
        d = math.sqrt((points[i, 0] - c[0]) ** 2 + (points[i, 1] - c[1]) ** 2 + (points[i, 2] - c[2]) ** 2) - radius
        sse += d * d
    return n, math.sqrt(sse / n) if n > 0 else math.nan


@kernel
def gather_window(points, index_image, cx, cy, cz, radius, band, fx, fy, ppx, ppy, stride, out_idx):
    """Indices of the points in the candidate's silhouette whose ray residual is within band.

    stride: visit every stride-th row and column. out_idx: preallocated int64 buffer (large
    enough for the window); returns the count.
    """
    h, w = index_image.shape
    dist = math.sqrt(cx * cx + cy * cy + cz * cz)
    if cz <= radius or dist <= radius:
        return 0
    rpx = disc_radius_px(cz, dist, radius, max(fx, fy)) * 1.1 + 2.0
    u0 = fx * cx / cz + ppx
    v0 = fy * cy / cz + ppy
    # the distance to the sphere | ||p - c|| - R | never exceeds the ray residual (the sphere's point
    # on p's ray is at |dt| from p): points off the shell [R - band, R + band] are skipped on squared
    # distances alone, before the ray residual's square roots and division (most of a window)
    lo2 = (radius - band) ** 2 * (1.0 - 1e-9) if band < radius else 0.0
    hi2 = (radius + band) ** 2 * (1.0 + 1e-9)
    k = 0
    for r in range(max(0, int(math.floor(v0 - rpx))), min(h - 1, int(math.ceil(v0 + rpx))) + 1, stride):
        for c in range(max(0, int(math.floor(u0 - rpx))), min(w - 1, int(math.ceil(u0 + rpx))) + 1, stride):
            i = index_image[r, c]
            if i < 0:
                continue
            px, py, pz = points[i, 0] - cx, points[i, 1] - cy, points[i, 2] - cz
            d2 = px * px + py * py + pz * pz
            if d2 > hi2 or d2 < lo2:
                continue
            dt, hit = ray_residual(points[i, 0], points[i, 1], points[i, 2], cx, cy, cz, radius)
            if hit and abs(dt) <= band and k < out_idx.shape[0]:
                out_idx[k] = i
                k += 1
    return k


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
def search_unorganised(points, order, sorted_keys, origin, cell, dims, radius, eps, win_m, max_iter, min_iter,
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


# ------------------------------------------------------------------------- outline centring

@kernel
def _outline_side(points, index_image, r, k, zc, R, k_sig):
    """A pixel's class for the outline: 1 at the ball's depths (within k_sig of [zc - R, zc]), 2 behind
    (beyond max(k_sig, R) past zc), 0 neither or no depth."""
    i = index_image[r, k]
    if i < 0:
        return 0
    z = points[i, 2]
    if z > zc - R - k_sig and z < zc + k_sig:
        return 1
    if z > zc + max(k_sig, R):
        return 2
    return 0


@kernel
def outline_residuals(points, index_image, prm, cx, cy, cz, sigma, gap_sigmas, band_px, band_fraction, res, count):
    """The depth steps of a sphere's outline near its silhouette (``outline_centre``): each 4-neighbour
    pair of a pixel at the ball's depths and one behind (``_outline_side``; gap_sigmas sigma m),
    within band_px + band_fraction r px of the outline (r the disc's radius px) and stepping outward
    (within 60 degrees of the direction from the projected centre), adds to res[s, count[s]] the
    angle between the ray through the pair's midpoint and the centre's ray, minus the silhouette
    cone's half-angle (rad; > 0 outside the cone), s the quarter of the outline it lies in: 0 (+u),
    1 (-u), 2 (+v), 3 (-v). res (4, N); count (4,) is reset. Pinhole rays, as every kernel."""
    count[:] = 0
    R = prm[P_R]
    fx, fy, ppx, ppy = prm[P_FX], prm[P_FY], prm[P_PPX], prm[P_PPY]
    rho = math.sqrt(cx * cx + cy * cy + cz * cz)
    if cz <= 0.0 or rho <= R:
        return
    alpha = math.asin(R / rho)
    ux, uy, uz = cx / rho, cy / rho, cz / rho
    u0 = fx * cx / cz + ppx
    v0 = fy * cy / cz + ppy
    r_px = fx * math.tan(alpha)
    band = band_px + band_fraction * r_px
    m = int(r_px + band + 2.0)
    h, w = index_image.shape
    r0, r1 = max(0, int(v0) - m), min(h, int(v0) + m + 1)
    c0, c1 = max(0, int(u0) - m), min(w, int(u0) + m + 1)
    k_sig = gap_sigmas * sigma
    for axis in range(2):
        for r in range(r0, r1 - axis):
            for k in range(c0, c1 - 1 + axis):
                a = _outline_side(points, index_image, r, k, cz, R, k_sig)
                b = _outline_side(points, index_image, r + axis, k + 1 - axis, cz, R, k_sig)
                if a == b or a == 0 or b == 0:
                    continue
                sign = 1.0 if a == 1 else -1.0  # +1: the ball pixel first, the step outward along +axis
                pu = k + (0.5 if axis == 0 else 0.0)
                pv = r + (0.5 if axis == 1 else 0.0)
                du, dv = pu - u0, pv - v0
                d = math.sqrt(du * du + dv * dv) + 1e-9
                if sign * (du if axis == 0 else dv) / d <= 0.5 or abs(d - r_px) >= band:
                    continue
                x, y = (pu - ppx) / fx, (pv - ppy) / fy
                norm = math.sqrt(x * x + y * y + 1.0)
                cos_a = min(1.0, max(-1.0, (x * ux + y * uy + uz) / norm))
                if abs(du) >= abs(dv):
                    q = 0 if du > 0 else 1
                else:
                    q = 2 if dv > 0 else 3
                if count[q] < res.shape[1]:
                    res[q, count[q]] = math.acos(cos_a) - alpha
                    count[q] += 1


@kernel
def _axis_shift(res, count, s, f_px, min_side, max_bias_px):
    """One image axis of ``outline_centre``: half the difference of its sides' (quarters s and s + 1)
    median residuals (rad), or 0 where a side has fewer than min_side pairs or half their sum exceeds
    max_bias_px pixels (f_px: the axis's focal length)."""
    if count[s] < min_side or count[s + 1] < min_side:
        return 0.0
    ma, mb = np.median(res[s, :count[s]]), np.median(res[s + 1, :count[s + 1]])
    if abs(0.5 * (ma + mb)) * f_px > max_bias_px:
        return 0.0
    return 0.5 * (ma - mb)


@kernel
def outline_centre(points, index_image, prm, c, sigma, gap_sigmas, band_px, band_fraction, min_side, max_bias_px,
                   iterations, res, count, out):
    """``improved.outline_centre``'s rounds: out (3,) gets the centre c (3,) m moved across the line of
    sight, its range kept. Per image axis with at least min_side pairs (``outline_residuals``) on each
    of its two sides, half the difference of the two sides' median residuals, over cos 22.5 degrees
    (a quarter's median pair lies about 22.5 degrees off the axis), is the centre's shift along it;
    unless half their sum, the silhouette's size along the axis against the sphere's, is more than
    max_bias_px pixels off (mixed pixels make it a pixel at most: a surface the ball rests on or
    touches, seen behind it at a grazing angle, puts one side's steps beyond the outline)."""
    out[:] = c
    rho = math.sqrt(c[0] * c[0] + c[1] * c[1] + c[2] * c[2])
    gain = math.cos(math.pi / 8.0)
    for _ in range(iterations):
        outline_residuals(points, index_image, prm, out[0], out[1], out[2], sigma, gap_sigmas, band_px,
                          band_fraction, res, count)
        su = _axis_shift(res, count, 0, prm[P_FX], min_side, max_bias_px) / gain
        sv = _axis_shift(res, count, 2, prm[P_FY], min_side, max_bias_px) / gain
        if su == 0.0 and sv == 0.0:
            break
        ax, ay, az = out[0] / rho, out[1] / rho, out[2] / rho
        # the tangent directions of the image's +u (e_u) and +v (e_v = a x e_u, its y made positive)
        eux, euy, euz = 1.0 - ax * ax, -ax * ay, -ax * az
        nu = math.sqrt(eux * eux + euy * euy + euz * euz)
        eux, euy, euz = eux / nu, euy / nu, euz / nu
        evx, evy, evz = ay * euz - az * euy, az * eux - ax * euz, ax * euy - ay * eux
        if evy < 0.0:
            evx, evy, evz = -evx, -evy, -evz
        bx, by, bz = ax + su * eux + sv * evx, ay + su * euy + sv * evy, az + su * euz + sv * evz
        nb = math.sqrt(bx * bx + by * by + bz * bz)
        nx, ny, nz = rho * bx / nb, rho * by / nb, rho * bz / nb
        moved = math.sqrt((nx - out[0]) ** 2 + (ny - out[1]) ** 2 + (nz - out[2]) ** 2)
        out[0], out[1], out[2] = nx, ny, nz
        if moved < 1e-5:
            break
