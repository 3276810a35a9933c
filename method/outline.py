"""Stage 5, the outline: where one pixel's noise nears R, the ball's centre across the line of sight
and its size from the depth steps of its outline.

The cap's relief places a far ball's centre laterally to several mm; the outline against a
background farther behind is a sharp step that places it to about a millimetre at 2-3 m. The
outline's pixel pairs (a pixel at the ball's depth beside one behind it) each give an angular
residual against the sphere's cone; per image axis the median residual of each side gives the shift
(``outline_centre``), and the mean over the four quarters the silhouette's size (``outline_size``).
Verification takes a noisy candidate's evidence again on its outline's ray; the pipeline re-centres
the reported spheres. Python and kernels side by side.
"""

from __future__ import annotations

import math

import numpy as np

from spherebench.method import frame_kernels as FK
from spherebench.method.compiled import kernel, workspace
from spherebench.method.config import DetectorConfig
from spherebench.method.frame import PreparedFrame
from spherebench.method.frame_kernels import P_FX, P_FY, P_PPX, P_PPY, P_R

# The outline's pairs and rounds; each chosen on the training splits
# (docs/experiments/2026-12-04-config-history.md and the records it points to).
OUTLINE_EVIDENCE_NOISE_FRACTION = 0.5  # verify again on the outline where one pixel's noise is this * R ...
OUTLINE_EVIDENCE_MIN_MOVE_PX = 0.25  # ... not where the outline moves the centre less (px) ...
OUTLINE_EVIDENCE_MIN_SCORE = 0.05  # ... nor where the first verification scores below this
OUTLINE_SIZE_FLOOR_PX = 0.25  # the outline radius's least standard error (px): mixed pixels, the grid
OUTLINE_GAP_SIGMAS = 3.0  # an outline is a step farther than max(this * sigma_z, R)
OUTLINE_BAND_PX = 2.0  # outline pixels within this (px) ...
OUTLINE_BAND_FRACTION = 0.15  # ... plus this share of the disc radius of the silhouette's outline
OUTLINE_MIN_SIDE = 4  # re-centre an axis with at least this many outline pixels on each side
OUTLINE_MAX_SHIFT_FRACTION = 0.5  # a re-centring moving the centre more than this * R is not taken
OUTLINE_MAX_BIAS_PX = 1.0  # nor on an axis whose sides lie on average this far off the silhouette (px)
OUTLINE_ITERATIONS = 3  # rounds of re-centring


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
def centre_on_outline(points, index_image, prm, c, sigma, gap_sigmas, band_px, band_fraction, min_side, max_bias_px,
                   iterations, res, count, out):
    """``outline_centre``'s rounds: out (3,) gets the centre c (3,) m moved across the line of
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


def _outline_buffers(frame: PreparedFrame, rho: float, config: DetectorConfig) -> tuple[np.ndarray, np.ndarray]:
    """``outline_residuals``' buffers for a sphere at distance rho (m): a quarter of the outline
    holds at most two pairs per pixel of the kernel's window; the capacity is rounded up to a power of
    two, so that balls of every size share a few reused buffers."""
    r_px = float(frame.prm[FK.P_FX]) * math.tan(math.asin(config.radius_m / rho))
    side = 2 * int(r_px + OUTLINE_BAND_PX + OUTLINE_BAND_FRACTION * r_px + 3) + 1
    return (workspace("outline_res", (4, 1 << (2 * side * side - 1).bit_length()), np.float64),
            workspace("outline_count", (4,), np.int64))


def outline_size(frame: PreparedFrame, centre_m: np.ndarray, config: DetectorConfig) -> tuple[float, float] | None:
    """The angular radius (rad) of the silhouette's outline about centre_m (3,) m, and its standard
    error: the sphere's cone half-angle asin(R / |c|) plus the mean of the four quarters' median
    residuals (``outline_residuals``; about a centre on the outline, their difference is
    the centre's error, their mean the silhouette's size against the sphere's). The standard error
    is the pooled residuals' (normal-consistent MAD, as a median over all pairs) with
    ``OUTLINE_SIZE_FLOOR_PX`` added in quadrature (mixed pixels and the outline's pixel grid). None
    unless every quarter holds ``OUTLINE_MIN_SIDE`` pairs: a ball on a floor or against a wall has
    a side whose steps are not its outline."""
    c = np.asarray(centre_m, np.float64)
    rho = float(np.linalg.norm(c))
    if not (c[2] > 0 and rho > config.radius_m):
        return None
    res, count = _outline_buffers(frame, rho, config)
    outline_residuals(frame.points, frame.index_image, frame.prm, c[0], c[1], c[2], frame.noise_a * float(c[2]) ** 2,
                        OUTLINE_GAP_SIGMAS, OUTLINE_BAND_PX, OUTLINE_BAND_FRACTION, res, count)
    if int(count.min()) < OUTLINE_MIN_SIDE:
        return None
    mean_median, spread, n = _size_statistics(res, count)
    angle = math.asin(config.radius_m / rho) + mean_median
    se = math.hypot(1.2533 * spread / math.sqrt(n), OUTLINE_SIZE_FLOOR_PX / float(frame.prm[FK.P_FX]))
    return angle, se


@kernel
def _size_statistics(res, count):
    """``outline_size``'s statistics of the four quarters' residuals (res (4, M), count (4,)): the mean
    of their medians, the pooled residuals' normal-consistent MAD, and their count."""
    n = 0
    for q in range(4):
        n += count[q]
    pooled = np.empty(n, np.float64)
    k = 0
    medians = 0.0
    for q in range(4):
        pooled[k:k + count[q]] = res[q, :count[q]]
        k += count[q]
        medians += np.median(res[q, :count[q]])
    spread = 1.4826 * np.median(np.abs(pooled - np.median(pooled)))
    return medians / 4.0, spread, n


def outline_centre(frame: PreparedFrame, centre_m: np.ndarray, config: DetectorConfig) -> np.ndarray:
    """A sphere's centre (3,) m moved across the line of sight onto its outline, its range kept.

    Where one pixel's depth noise nears R, the cap's relief places the centre laterally to several
    mm; the outline against a background farther behind is a sharp depth step
    (``outline_residuals``: 4-neighbour pairs of a pixel at the ball's depths and one
    behind, near the current outline and stepping outward, each with its angular residual, the
    angle to the centre's ray minus the cone's half-angle) that places it to about a millimetre at
    2-3 m. Per image axis, the pairs within 45 degrees of each of its two directions give their
    median residual; half the difference of the two is the shift along that axis
    (``centre_on_outline``), which a silhouette uniformly a pixel larger or smaller than the
    sphere's (mixed pixels, edge fattening) leaves alone. An axis with fewer than
    ``OUTLINE_MIN_SIDE`` pairs on either side (a ball on a floor or against a wall there, the stereo
    shadow) keeps its centre; a move beyond ``OUTLINE_MAX_SHIFT_FRACTION`` R is not taken."""
    c_in = np.asarray(centre_m, np.float64)
    R = config.radius_m
    rho = float(np.linalg.norm(c_in))
    if not (c_in[2] > 0 and rho > R):
        return c_in
    res, count = _outline_buffers(frame, rho, config)
    out = np.empty(3, np.float64)
    centre_on_outline(frame.points, frame.index_image, frame.prm, c_in, frame.noise_a * float(c_in[2]) ** 2,
                     OUTLINE_GAP_SIGMAS, OUTLINE_BAND_PX, OUTLINE_BAND_FRACTION, OUTLINE_MIN_SIDE,
                     OUTLINE_MAX_BIAS_PX, OUTLINE_ITERATIONS, res, count, out)
    if float(np.linalg.norm(out - c_in)) > OUTLINE_MAX_SHIFT_FRACTION * R:
        return c_in
    return out
