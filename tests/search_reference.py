"""Readable pure-Python/numpy replays of the compiled organised kernels, for the tests.

``search_organised`` replays ``_kernels.search_organised``: it draws the same first cells
(splitmix64, in Python integers) in the same order and applies the same tests, written plainly: the
box sums are summed directly over an image of the cells' depth sums and counts (the kernel uses a
summed-area table, depth and count packed in one uint64), the steps and the tests are the same
formulas in the same order, so the tests can require the same hypotheses. ``window_stats`` is the kernel's silhouette
classification, vectorised. Far too slow for real frames; they exist to check the fast path.
"""

from __future__ import annotations

import math

import numpy as np

from spherebench.method import frame_kernels, search_kernels, verification_kernels

_MASK = (1 << 64) - 1


class SplitMix64:
    """The kernels' generator: state += golden; mix; top 53 bits / 2^53."""

    def __init__(self, seed: int):
        self.state = int(seed) & _MASK

    def u01(self) -> float:
        self.state = (self.state + 0x9E3779B97F4A7C15) & _MASK
        z = self.state
        z = ((z ^ (z >> 30)) * 0xBF58476D1CE4E5B9) & _MASK
        z = ((z ^ (z >> 27)) * 0x94D049BB133111EB) & _MASK
        z ^= z >> 31
        return (z >> 11) * (1.0 / 9007199254740992.0)


def cell_images(points: np.ndarray, index_image: np.ndarray, bin_px: int) -> tuple[np.ndarray, np.ndarray]:
    """(depth sums in mm (Hc, Wc) int64, valid counts (Hc, Wc) int64) over cells of bin_px x bin_px pixels.

    Each pixel's depth is rounded to mm as the kernel does it (float32 z * 1000 + 0.5, truncated).
    """
    h, w = index_image.shape
    hc, wc = -(-h // bin_px), -(-w // bin_px)
    zs = np.zeros((hc, wc), np.int64)
    ns = np.zeros((hc, wc), np.int64)
    rr, cc = np.nonzero(index_image >= 0)
    if bin_px >= 3:  # the middle pixel row of each cell only (``improved.cell_rows``)
        keep = rr % bin_px == bin_px // 2
        rr, cc = rr[keep], cc[keep]
    z = points[index_image[rr, cc], 2].astype(np.float32)
    zmm = (z * np.float32(1000.0) + np.float32(0.5)).astype(np.uint32).astype(np.int64)
    np.add.at(zs, (rr // bin_px, cc // bin_px), zmm)
    np.add.at(ns, (rr // bin_px, cc // bin_px), 1)
    return zs, ns


class Grid:
    """The search grid: cell images, the parameters, and plainly summed boxes."""

    def __init__(self, zs: np.ndarray, ns: np.ndarray, prm: np.ndarray):
        self.zs, self.ns, self.prm = zs, ns, prm
        self.hc, self.wc = zs.shape

    def box_sums(self, v: int, u: int, h: int) -> tuple[int, int, int]:
        r0, r1 = max(v - h, 0), min(v + h + 1, self.hc)
        c0, c1 = max(u - h, 0), min(u + h + 1, self.wc)
        if r0 >= r1 or c0 >= c1:
            return 0, 0, 0
        return int(self.zs[r0:r1, c0:c1].sum()), int(self.ns[r0:r1, c0:c1].sum()), (r1 - r0) * (c1 - c0)

    def box_range(self, v: int, u: int, h: int) -> tuple[float, int]:
        """(mean range m or nan, valid count): mean depth times the ray length at the box's centre."""
        prm = self.prm
        s, n, a = self.box_sums(v, u, h)
        if n == 0 or n < search_kernels.BOX_MIN_VALID * a * prm[frame_kernels.P_CELL_PX]:
            return math.nan, n
        b = prm[frame_kernels.P_BIN]
        rx = (u * b + 0.5 * (b - 1.0) - prm[frame_kernels.P_PPX]) / prm[frame_kernels.P_FX]
        ry = (v * b + 0.5 * (b - 1.0) - prm[frame_kernels.P_PPY]) / prm[frame_kernels.P_FY]
        return s / n * 1e-3 * math.sqrt(1.0 + rx * rx + ry * ry), n


def cap_relief(s: float) -> float:
    return 1.0 - math.sqrt(1.0 - min(s, 1.0))


def stencil_stretch(prm, v: int, u: int) -> tuple[float, float]:
    """``_kernels.stencil_stretch``: the silhouette's stretch along u and v at cell (v, u)."""
    if prm[frame_kernels.P_OFF_AXIS] == 0.0:
        return 1.0, 1.0
    b = prm[frame_kernels.P_BIN]
    x = (u * b + 0.5 * (b - 1.0) - prm[frame_kernels.P_PPX]) / prm[frame_kernels.P_FX]
    y = (v * b + 0.5 * (b - 1.0) - prm[frame_kernels.P_PPY]) / prm[frame_kernels.P_FY]
    n2 = 1.0 + x * x + y * y
    return n2 / math.sqrt(1.0 + y * y), n2 / math.sqrt(1.0 + x * x)


def plane_free(g: Grid, v: int, u: int, m0: float) -> bool:
    """``_kernels.plane_free``: is the inverse depth about (v, u) curved along some available axis?"""
    prm = g.prm
    R = prm[frame_kernels.P_R]
    rr = prm[frame_kernels.P_FX] / prm[frame_kernels.P_BIN] * R / m0
    hp = max(1, int(search_kernels.BOX_HALF_FRACTION * rr + 0.5))
    su, sv = stencil_stretch(prm, v, u)
    f = search_kernels.PREFILTER_OFFSET_FRACTION * rr
    dpu, dpv = int(f * su + 0.5), int(f * sv + 0.5)
    dgu, dgv = int(f * su * 0.7071067811865476 + 0.5), int(f * sv * 0.7071067811865476 + 0.5)
    bb = prm[frame_kernels.P_CELL_PX]
    s0, n0, _ = g.box_sums(v, u, 1)
    if n0 == 0:
        return True
    i0 = 1000.0 * n0 / s0
    planar = 0
    for du, dv in ((dpu, 0), (0, dpv), (dgu, dgv), (dgu, -dgv)):
        sa, na, aa = g.box_sums(v + dv, u + du, hp)
        sb, nb, ab = g.box_sums(v - dv, u - du, hp)
        if na == 0 or nb == 0 or na < search_kernels.BOX_MIN_VALID * aa * bb or nb < search_kernels.BOX_MIN_VALID * ab * bb:
            continue
        q = 1000.0 * na / sa + 1000.0 * nb / sb - 2.0 * i0
        tol = (3.0 * prm[frame_kernels.P_NOISE_A] * prm[frame_kernels.P_MEAN_NOISE] * math.sqrt(1.0 / na + 1.0 / nb + 4.0 / n0)
               + search_kernels.PRETEST_SLACK * R / (m0 * m0))
        if abs(q) > tol:
            return True
        planar += 1
        if planar == 2:
            return False
    return planar == 0


def descent_step(m0, mA, mB, d, k, off, lim, near) -> float:
    """``_kernels.descent_step``: the front point's offset along one axis, from known curvature k; side
    means more than ``off`` behind or ``near`` in front of m0 are not used."""
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


def ring_boxes(g: Grid, v: int, u: int, front: float, sig: float) -> tuple[float, int, int]:
    """``_kernels.ring_boxes``: (disc radius, background boxes, continued boxes) of the outline ring."""
    prm = g.prm
    R = prm[frame_kernels.P_R]
    dist = front + R
    rr = prm[frame_kernels.P_FX] / prm[frame_kernels.P_BIN] * R / math.sqrt(max(dist * dist - R * R, 1e-12))
    hr = max(1, int(search_kernels.RING_HALF_FRACTION * rr + 0.5))
    su, sv = stencil_stretch(prm, v, u)
    dru, drv = search_kernels.RING_OFFSET_FRACTION * rr * su, search_kernels.RING_OFFSET_FRACTION * rr * sv
    ddu, ddv = dru * 0.7071067811865476, drv * 0.7071067811865476
    bg = cont = 0
    for ou, ov in ((dru, 0.0), (-dru, 0.0), (0.0, drv), (0.0, -drv), (ddu, ddv), (-ddu, ddv), (ddu, -ddv), (-ddu, -ddv)):
        m, n = g.box_range(v + int(math.floor(ov + 0.5)), u + int(math.floor(ou + 0.5)), hr)
        if math.isnan(m) or m > dist:
            bg += 1
        elif m >= front - (3.0 * sig / math.sqrt(n) + search_kernels.PRETEST_SLACK * R):
            cont += 1
            if cont > search_kernels.PRETEST_MAX_CONTINUED:
                break
    return rr, bg, cont


def front_hypothesis(g: Grid, v: int, u: int):
    """``_kernels.front_hypothesis``: (score, (v, u, front m, disc radius, occluded flag)) or (-inf, None)."""
    prm = g.prm
    R = prm[frame_kernels.P_R]
    fc = prm[frame_kernels.P_FX] / prm[frame_kernels.P_BIN]
    na = prm[frame_kernels.P_NOISE_A] * prm[frame_kernels.P_MEAN_NOISE]
    slack = search_kernels.PRETEST_SLACK * R
    m0, _ = g.box_range(v, u, 1)
    if math.isnan(m0) or not plane_free(g, v, u, m0):
        return -math.inf, None
    for step in range(search_kernels.DESCENT_STEPS + 1):
        rr = fc * R / m0
        if rr < prm[frame_kernels.P_RR_MIN] or rr > prm[frame_kernels.P_RR_MAX]:
            return -math.inf, None
        su, sv = stencil_stretch(prm, v, u)
        h = max(1, int(search_kernels.BOX_HALF_FRACTION * rr + 0.5))
        du = max(h + 1, int(search_kernels.BOX_OFFSET_FRACTION * rr * su + 0.5))
        dv = max(h + 1, int(search_kernels.BOX_OFFSET_FRACTION * rr * sv + 0.5))
        m0, n0 = g.box_range(v, u, h)
        if math.isnan(m0):
            return -math.inf, None
        sides = [g.box_range(v, u - du, h), g.box_range(v, u + du, h), g.box_range(v - dv, u, h),
                 g.box_range(v + dv, u, h)]
        if step == search_kernels.DESCENT_STEPS:
            break
        off = 0.6 * R + 3.0 * na * m0 * m0 / math.sqrt(n0) + slack
        # the occluder bound (``improved``'s retry): a side box more than R in front is left out
        near = R + 3.0 * na * m0 * m0 / math.sqrt(n0) + slack if prm[frame_kernels.P_OCCLUDER_BOUND] else math.inf
        iu = int(math.floor(descent_step(m0, sides[0][0], sides[1][0], du, 0.5 * R / (rr * su) ** 2, off,
                                         0.5 * rr * su, near) + 0.5))
        iv = int(math.floor(descent_step(m0, sides[2][0], sides[3][0], dv, 0.5 * R / (rr * sv) ** 2, off,
                                         0.5 * rr * sv, near) + 0.5))
        if iu == 0 and iv == 0:
            break
        u, v = u + iu, v + iv
        if not (0 <= u < g.wc and 0 <= v < g.hc):
            return -math.inf, None
    ahu, ahv = (h + 0.5) / (rr * su), (h + 0.5) / (rr * sv)
    spread = (ahu * ahu + ahv * ahv) / 3.0
    xu, xv = du / (rr * su), dv / (rr * sv)
    front = m0 - R * cap_relief(spread)
    preds = (front + R * cap_relief(xu * xu + spread),) * 2 + (front + R * cap_relief(xv * xv + spread),) * 2
    sig = na * m0 * m0
    agree = behind = occluded = 0
    chi = 0.0
    for (m, nk), pred in zip(sides, preds):
        if math.isnan(m):
            continue
        tol = 3.0 * sig / math.sqrt(nk) + slack
        res = m - pred
        if res > tol:
            behind += 1
        elif res >= -tol:
            agree += 1
            chi += (res / tol) ** 2
        elif res < -(tol + R):
            occluded += 1
    if behind > 1 or agree + min(occluded, 1) < 3:
        return -math.inf, None
    rr, bg, cont = ring_boxes(g, v, u, front, sig)
    if cont > search_kernels.PRETEST_MAX_CONTINUED:
        return -math.inf, None
    return (2.0 * agree + bg - 2.0 * cont - 2.0 * behind - 0.5 * chi,
            (v, u, front, rr, float(agree < 3), (su, sv, h, du, dv, m0, n0, sides)))


def relief_llr(prm, rr: float, stencil) -> float:
    """``search_kernels._relief_llr``: the agreeing side boxes' log-likelihood ratio of the cap's
    relief against a flat surface through the centre box, from a resting stencil."""
    su, sv, h, du, dv, m0, n0, sides = stencil
    R = prm[frame_kernels.P_R]
    sig = prm[frame_kernels.P_NOISE_A] * prm[frame_kernels.P_MEAN_NOISE] * m0 * m0
    ahu, ahv = (h + 0.5) / (rr * su), (h + 0.5) / (rr * sv)
    spread = (ahu * ahu + ahv * ahv) / 3.0
    xu, xv = du / (rr * su), dv / (rr * sv)
    base = cap_relief(spread)
    rises = (R * (cap_relief(xu * xu + spread) - base),) * 2 + (R * (cap_relief(xv * xv + spread) - base),) * 2
    llr = 0.0
    for (m, nk), delta in zip(sides, rises):
        if math.isnan(m) or nk == 0 or n0 == 0:
            continue
        d = m - m0
        if abs(d - delta) > 3.0 * sig / math.sqrt(nk) + search_kernels.PRETEST_SLACK * R:
            continue
        llr += (2.0 * d * delta - delta * delta) / (2.0 * max(sig * sig * (1.0 / nk + 1.0 / n0), 1e-12))
    return llr


def keep_hypothesis(kept: list, hyp: tuple, q: float, radius: float, k_max: int) -> None:
    """``_kernels._keep_hypothesis`` on a list of (score, (v, u, front, r)), best first."""
    v, u, front, rr = hyp[:4]
    for j, (qj, hj) in enumerate(kept):
        if abs(hj[0] - v) <= 0.5 * rr and abs(hj[1] - u) <= 0.5 * rr and abs(hj[2] - front) <= radius:
            if q <= qj:
                return
            del kept[j]
            break
    if len(kept) == k_max and q <= kept[-1][0]:
        return
    pos = len(kept)
    while pos > 0 and kept[pos - 1][0] < q:
        pos -= 1
    kept.insert(pos, (q, hyp))
    del kept[k_max:]


def search_organised(points, index_image, prm, seed: int, k_max: int, relief: bool = False):
    """Replay of ``_kernels.search_organised``: (hypotheses (M, 6) rows (v, u, front, r, score, occluded),
    counters (2,)); relief: ranked by ``relief_llr`` (``search.relief_search``)."""
    b = int(prm[frame_kernels.P_BIN])
    g = Grid(*cell_images(points, index_image, b), prm)
    hc, wc = g.zs.shape
    sv, su = int(prm[frame_kernels.P_STRATUM_V]), int(prm[frame_kernels.P_STRATUM_U])
    rng = SplitMix64(seed)
    kept: list = []
    counters = np.zeros(2, np.int64)
    for v0 in range(0, hc, sv):  # strata in raster order, one uniform first cell in each
        for u0 in range(0, wc, su):
            nv, nu = min(sv, hc - v0), min(su, wc - u0)
            v = v0 + min(int(rng.u01() * nv), nv - 1)
            u = u0 + min(int(rng.u01() * nu), nu - 1)
            counters[0] += 1
            q, hyp = front_hypothesis(g, v, u)
            if hyp is None:
                continue
            counters[1] += 1
            if relief:
                q = relief_llr(prm, hyp[3], hyp[5])
            keep_hypothesis(kept, hyp, q, prm[frame_kernels.P_R], k_max)
    out = np.array([[*h[:4], q, h[4]] for q, h in kept], np.float64).reshape(-1, 6)
    return out, counters


def window_stats(points, index_image, centre, e, ring_band, prm, stride) -> np.ndarray:
    """``_kernels.window_stats`` vectorised over the strided window: (N_STATS,) counts and sums."""
    fx, fy, ppx, ppy, radius = prm[frame_kernels.P_FX], prm[frame_kernels.P_FY], prm[frame_kernels.P_PPX], prm[frame_kernels.P_PPY], prm[frame_kernels.P_R]
    out = np.zeros(verification_kernels.N_STATS)
    h, w = index_image.shape
    cx, cy, cz = centre
    dist = math.sqrt(float(centre @ centre))
    rpx = fx * radius / math.sqrt(max(dist * dist - radius * radius, 1e-12)) * dist / cz
    rpx = rpx * verification_kernels.RING_FACTOR * 1.05 + 2.0
    u0, v0 = fx * cx / cz + ppx, fy * cy / cz + ppy
    r = np.arange(max(0, int(math.floor(v0 - rpx))), min(h - 1, int(math.ceil(v0 + rpx))) + 1, stride)
    c = np.arange(max(0, int(math.floor(u0 - rpx))), min(w - 1, int(math.ceil(u0 + rpx))) + 1, stride)
    rr, cc = np.meshgrid(r, c, indexing="ij")
    idx = index_image[rr, cc].ravel()
    rr, cc = rr.ravel(), cc.ravel()
    # pixels without depth inside the silhouette
    rays = np.stack([(cc - ppx) / fx, (rr - ppy) / fy, np.ones(len(cc))], axis=1)
    in_disc = rays @ centre / (np.linalg.norm(rays, axis=1) * dist) >= math.sqrt(1.0 - (radius / dist) ** 2)
    out[verification_kernels.ST_INVALID_DISC] = np.count_nonzero((idx < 0) & in_disc)
    ok = idx >= 0
    p = points[idx[ok]].astype(np.float64)
    du, dv = (cc[ok] - u0), (rr[ok] - v0)
    pn = np.linalg.norm(p, axis=1)
    tc = p @ centre / pn
    m2 = centre @ centre - tc * tc
    hit = m2 <= radius * radius
    dt = pn[hit] - (tc[hit] - np.sqrt(radius * radius - m2[hit]))
    inl = np.abs(dt) <= e
    out[verification_kernels.ST_VALID_DISC] = hit.sum()
    out[verification_kernels.ST_INLIER] = inl.sum()
    out[verification_kernels.ST_SSE] = float(np.sum(dt[inl] ** 2))
    front = ~inl & (dt < 0)
    out[verification_kernels.ST_FRONT] = front.sum()
    out[verification_kernels.ST_FRONT_NEAR] = np.count_nonzero(front & (dt >= -0.5 * radius))
    out[verification_kernels.ST_BEHIND] = np.count_nonzero(~inl & (dt >= 0))
    inner_disc = m2[hit] <= verification_kernels.PROFILE_OUTER_SQ * radius * radius
    out[verification_kernels.ST_VALID_INNER] = inner_disc.sum()
    out[verification_kernels.ST_BEHIND_INNER] = np.count_nonzero(inner_disc & (dt > e))
    out[verification_kernels.ST_EDGE_N] = np.count_nonzero(~inner_disc & (dt >= -e))
    out[verification_kernels.ST_EDGE_BEHIND] = np.count_nonzero(~inner_disc & (dt > e))
    ring = ~hit & (tc > 0) & (dist * dist - tc * tc <= (verification_kernels.RING_FACTOR * radius) ** 2)
    out[verification_kernels.ST_RING] = ring.sum()
    out[verification_kernels.ST_RING_CONT] = np.count_nonzero(ring & (np.abs(pn - tc) <= ring_band))
    attached = (pn - tc >= -verification_kernels.RING_FRONT_MAX_FRACTION * radius) & (pn - tc <= -verification_kernels.RING_FRONT_MIN_FRACTION * radius)
    out[verification_kernels.ST_RING_FRONT] = np.count_nonzero(ring & (np.abs(pn - tc) > ring_band) & attached)
    sector = ring_sectors(cc[ok] - u0, rr[ok] - v0)
    joined = ring & ((np.abs(pn - tc) <= ring_band) | attached)
    out[verification_kernels.ST_SECTOR_RING:verification_kernels.ST_SECTOR_RING + verification_kernels.N_SECTORS] = np.bincount(sector[ring], minlength=verification_kernels.N_SECTORS)
    out[verification_kernels.ST_SECTOR_ATTACHED:verification_kernels.ST_SECTOR_ATTACHED + verification_kernels.N_SECTORS] = np.bincount(sector[joined], minlength=verification_kernels.N_SECTORS)
    out[:verification_kernels.ST_IN_N] *= float(stride * stride)
    # the relief profile over the inliers: inner zone, outer zone left/right and above/below
    mz = m2[hit][inl]
    d_in = dt[inl]
    horiz = (np.abs(du[hit]) >= np.abs(dv[hit]))[inl]
    inner = mz <= verification_kernels.PROFILE_INNER_SQ * radius * radius
    outer = ~inner & (mz <= verification_kernels.PROFILE_OUTER_SQ * radius * radius)
    out[verification_kernels.ST_IN_N], out[verification_kernels.ST_IN_SUM] = inner.sum(), d_in[inner].sum()
    out[verification_kernels.ST_OUTH_N], out[verification_kernels.ST_OUTH_SUM] = (outer & horiz).sum(), d_in[outer & horiz].sum()
    out[verification_kernels.ST_OUTV_N], out[verification_kernels.ST_OUTV_SUM] = (outer & ~horiz).sum(), d_in[outer & ~horiz].sum()
    out[verification_kernels.ST_RING_SPREAD] = ring_spread(out[verification_kernels.ST_SECTOR_RING:verification_kernels.ST_SECTOR_RING + verification_kernels.N_SECTORS],
                                        out[verification_kernels.ST_SECTOR_ATTACHED:verification_kernels.ST_SECTOR_ATTACHED + verification_kernels.N_SECTORS])
    return out


def ring_sectors(du: np.ndarray, dv: np.ndarray) -> np.ndarray:
    """``_kernels.ring_sector`` over arrays: octants 0-7 in angular order from the left (y down)."""
    ax, ay = np.abs(du), np.abs(dv)
    upper = np.where(du < 0, np.where(ax > ay, 0, 1), np.where(ay > ax, 2, 3))
    lower = np.where(du >= 0, np.where(ax > ay, 4, 5), np.where(ay > ax, 6, 7))
    return np.where(dv < 0, upper, lower)


def ring_spread(sector_ring: np.ndarray, sector_attached: np.ndarray) -> float:
    """``_kernels.ring_spread``: the attached share of the ring (sectors (N_SECTORS,) of ring pixels and
    of attached ones) outside the half ring that holds the most of it."""
    total = float(np.sum(sector_ring))
    if total <= 0:
        return 0.0
    half = len(sector_attached) // 2
    windows = [np.sum(np.roll(sector_attached, -k)[:half]) for k in range(len(sector_attached))]
    return float((np.sum(sector_attached) - max(windows)) / total)
