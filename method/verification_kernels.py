"""Verification's kernels (``verification``): the refinement rounds, the window's inliers, the
silhouette's statistics (``window_stats``) and the size gate. The zones of a candidate's window and
the refinement's bands are constants here: the shipped verdict was fitted on what they measure.
"""

from __future__ import annotations

import math

import numpy as np
from numba import get_thread_id, prange

from spherebench.method.compiled import kernel, long_kernel, part, threaded_kernel
from spherebench.method.fit_kernels import fit_range, fit_ray, ray_step, refine_fixed_radius, unit_rays
from spherebench.method.frame_kernels import P_EPS, P_EPS_CAP, P_FX, P_FY, P_NOISE_A, P_NOISE_K, P_PPX, P_PPY, P_R
from spherebench.method.noise import mean_variance_inflation, noise_eps


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
    N_SECTORS / 2 consecutive sectors, that holds the most of them: a ball rests on one side, clutter
    shaped like a cap is embedded all round (a verdict input)."""
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


@long_kernel
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


@threaded_kernel
def verify_many(points, index_image, starts, prm, refine_iterations, max_fit_points, s_min, data_noise, size_gate,
                hold_direction, idx, outs, stats):
    """``verify_organised`` from each of starts (K, 3) m, into outs (K, N_VOUT) and stats (K, N_STATS):
    several starts (``verification.verify_rows``, which hands them to numba's threads one at a time:
    a start's cost varies tenfold, most stop at the size gate), each thread with its own row of idx
    (T, n), T numba's thread count (``get_thread_id``). Each start's result is the same whichever
    thread takes it."""
    for k in prange(starts.shape[0]):
        verify_organised(points, index_image, starts[k], prm, refine_iterations, max_fit_points, s_min,
                         data_noise, size_gate, hold_direction, idx[get_thread_id()], outs[k], stats[k])


#: A verified candidate's measurements (``measurements``' rows) by name: the verdict's inputs and a
#: reported sphere's evidence. First the silhouette's statistics (``window_stats``' slots, STAT_SLOTS),
#: then what the fits and the frame add.
MEASUREMENT_NAMES = (
    "valid_disc", "inlier", "front", "front_near", "behind", "invalid_disc", "ring", "ring_continued",
    "ring_front", "valid_inner", "behind_inner", "edge_n", "edge_behind", "ring_spread", "inner_n", "inner_sum",
    "outer_h_n", "outer_h_sum", "outer_v_n", "outer_v_sum",
    "pixels_per_sample", "sigma_m", "sigma_measured_m", "eps_m", "visible_fraction", "depth_m", "n_inliers",
    "rmse_m", "free_radius_m", "free_radius_se_m", "noise_ratio", "noise_corr_px")
STAT_SLOTS = np.array([ST_VALID_DISC, ST_INLIER, ST_FRONT, ST_FRONT_NEAR, ST_BEHIND, ST_INVALID_DISC, ST_RING,
                       ST_RING_CONT, ST_RING_FRONT, ST_VALID_INNER, ST_BEHIND_INNER, ST_EDGE_N, ST_EDGE_BEHIND,
                       ST_RING_SPREAD, ST_IN_N, ST_IN_SUM, ST_OUTH_N, ST_OUTH_SUM, ST_OUTV_N, ST_OUTV_SUM], np.int64)
(M_VALID_DISC, M_INLIER, M_FRONT, M_FRONT_NEAR, M_BEHIND, M_INVALID_DISC, M_RING, M_RING_CONT, M_RING_FRONT,
 M_VALID_INNER, M_BEHIND_INNER, M_EDGE_N, M_EDGE_BEHIND, M_RING_SPREAD, M_IN_N, M_IN_SUM, M_OUTH_N, M_OUTH_SUM,
 M_OUTV_N, M_OUTV_SUM, M_PIXELS_PER_SAMPLE, M_SIGMA, M_SIGMA_MEASURED, M_EPS, M_VISIBLE, M_DEPTH, M_N_INLIERS,
 M_RMSE, M_FREE_R, M_FREE_SE, M_NOISE_RATIO, M_NOISE_CORR) = range(len(MEASUREMENT_NAMES))
N_MEASURED = len(MEASUREMENT_NAMES)


@kernel
def measurements(outs, sts, prm, noise_corr_px, noise_ratio, min_inliers, out):
    """The measurements out (K, N_MEASURED) (``MEASUREMENT_NAMES``) of each verification's output outs
    (K, N_VOUT) and statistics sts (K, N_STATS) (``verify_organised``'s), in a frame whose noise has
    correlation length noise_corr_px and is noise_ratio times the model's. Rows with fewer than
    min_inliers inliers (or failing the size gate: V_N -1) are left as they were.

    pixels_per_sample: pixels per effective sample of the evidence's counts and zone means, the
    window's stride (``window_stride``, as the kernel took it) against the noise's correlation
    length. sigma_m: the noise model's per-pixel noise at the centre's depth, not the measured one
    (which only narrows the band): the relief test treats pixels as independent, and a sensor whose
    errors are correlated (a structured-light sensor's quantisation steps) would otherwise fail a
    real ball's zone means by a few mm. visible_fraction: the share of the silhouette's pixels with
    depth that no nearer surface hides (an occluder: more than R / 2 in front of the sphere, FRONT
    less FRONT_NEAR)."""
    radius = prm[P_R]
    f_max = max(prm[P_FX], prm[P_FY])
    for k in range(outs.shape[0]):
        o, st, m = outs[k], sts[k], out[k]
        if not o[V_N] >= min_inliers:
            continue
        for j in range(STAT_SLOTS.shape[0]):
            m[j] = st[STAT_SLOTS[j]]
        cz = o[V_CZ]
        stride = window_stride(o[V_CX], o[V_CY], cz, radius * RING_FACTOR, f_max, 4.0 * FIT_MAX_POINTS)
        m[M_PIXELS_PER_SAMPLE] = mean_variance_inflation(noise_corr_px, stride)
        m[M_SIGMA] = prm[P_NOISE_A] * (cz * cz)
        m[M_SIGMA_MEASURED], m[M_EPS] = o[V_SIGMA], o[V_EPS]
        vd = st[ST_VALID_DISC]
        m[M_VISIBLE] = 1.0 - max(0.0, st[ST_FRONT] - st[ST_FRONT_NEAR]) / vd if vd > 0 else 0.0
        m[M_DEPTH], m[M_N_INLIERS], m[M_RMSE] = cz, o[V_N], o[V_RMSE]
        m[M_FREE_R], m[M_FREE_SE] = o[V_FR], o[V_FSE]
        m[M_NOISE_RATIO], m[M_NOISE_CORR] = noise_ratio, noise_corr_px


@kernel
def size_checks(measured, kept, size_gate, radius, out):
    """out (K,) bool: whether each of measured's rows (K, N_MEASURED) is kept (K,) bool and passes the
    size check (``verification.size_ok``; size_gate (2,) as ``verify_organised``'s, the frame's ``gate``)."""
    for k in range(measured.shape[0]):
        out[k] = kept[k] and not _fails_size_gate(size_gate, measured[k, M_FREE_R], measured[k, M_FREE_SE], radius)


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
