"""The organised search's kernels (``search``): box means over the summed-area table
(``frame_kernels``), the stencil's descent and pretest, the outline ring's boxes, the relief's
likelihood ratio, and the disc and hole searches.
"""

from __future__ import annotations

import math

import numpy as np

from spherebench.method.compiled import kernel, long_kernel, next_u01, part
from spherebench.method.frame_kernels import (
    COUNT_SHIFT, P_BIN, P_CELL_PX, P_FX, P_FY, P_MEAN_NOISE, P_NOISE_A, P_OCCLUDER_BOUND, P_OFF_AXIS,
    P_PPX, P_PPY, P_R, P_RR_MAX, P_RR_MIN, P_STRATUM_U, P_STRATUM_V, _DEPTH_MASK)


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
    the surface at the ball's depth. out (N_HYP_OUT,) gets (v, u, front range m, disc radius cells,
    occluded flag) and out[5:] its resting stencil (su, sv, h, du, dv, m0, n0, then each side box's mean
    and count: left, right, up, down); the score is 2 agreeing + background ring boxes - 2 continued
    - 2 behind - chi^2 / 2 of the agreeing ones (at most 16).
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
    # the resting stencil, from which ``relief_ranked`` scores the hypothesis by its cap's relief
    out[5], out[6], out[7], out[8], out[9], out[10], out[11] = su, sv, h, du, dv, m0, n0
    out[12], out[13], out[14], out[15], out[16], out[17], out[18], out[19] = mL, nL, mR, nR, mU, nU, mD, nD
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


@long_kernel
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
                if behind + 4 - k < min_behind:  # the sides left cannot make up the count (most cells)
                    break
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


@long_kernel
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


#: a passing hypothesis as ``front_hypothesis`` describes it: (v, u, front m, r cells, occluded flag)
#: and its resting stencil
N_HYP_OUT = 20


@long_kernel
def relief_ranked(prm, passed, cands):
    """The hypotheses of a search, passed (P, N_HYP_OUT) (``search_organised``'s), ranked by how far their
    cap stands out of the noise (``_relief_llr`` of their resting stencils) in place of the
    pretest's agreement, kept as ``search_organised`` keeps its, in the order drawn: the search that
    ranks its hypotheses so, without drawing and descending again. Returns the number kept."""
    n_kept = 0
    for k in range(passed.shape[0]):
        o = passed[k]
        q = _relief_llr(prm, o[3], o[5], o[6], int(o[7]), int(o[8]), int(o[9]), o[10], int(o[11]), o[12],
                        int(o[13]), o[14], int(o[15]), o[16], int(o[17]), o[18], int(o[19]))
        n_kept = _keep_hypothesis(cands, n_kept, o[0], o[1], o[2], o[3], q, o[4], prm[P_R])
    return n_kept


@long_kernel
def search_organised(tab, prm, seed, cands, counters, passed):
    """Stratified RANSAC on the cell grid: the grid is cut into strata of ``prm[P_STRATUM_V]`` x
    ``prm[P_STRATUM_U]`` cells (those at the far edges smaller), visited in raster order; in each, one
    first cell is drawn uniformly and gives one ``front_hypothesis``. The distinct passing ones are
    kept by score in cands (K, 6) (v, u, front m, r cells, score, occluded flag: ``front_hypothesis``),
    best first (``cell_centres`` gives their centres).

    Why strata rather than independent draws: a ball is missed only if every stratum it covers draws
    off it or fails, so the miss probability is at most that of as many independent draws (the
    bound, ``frame.strata``) and far below it once the ball covers whole strata; and first cells
    in raster order keep the table's rows in cache (a third of the time per draw of random points).
    counters (2,) int64 gets: first cells drawn, hypotheses past the pretest; passed (P, N_HYP_OUT)
    the first P of the latter (``front_hypothesis``' out; ``relief_ranked`` ranks them again).
    Returns the number of hypotheses kept.
    """
    hc, wc = tab.shape[0] - 1, tab.shape[1] - 1
    sv, su = max(1, int(prm[P_STRATUM_V])), max(1, int(prm[P_STRATUM_U]))
    counters[:] = 0
    state = np.empty(1, np.uint64)
    state[0] = np.uint64(seed)
    out = np.empty(N_HYP_OUT, np.float64)
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
            if counters[1] < passed.shape[0]:
                passed[counters[1]] = out
            counters[1] += 1
            n_kept = _keep_hypothesis(cands, n_kept, out[0], out[1], out[2], out[3], q, out[4], prm[P_R])
    return n_kept
