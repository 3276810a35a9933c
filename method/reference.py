"""Readable pure-Python/numpy replay of the compiled organised search (``_kernels.search_organised``).

It draws the same random numbers (splitmix64, in Python integers) in the same order and applies
the same tests, written plainly: patch means are summed directly over the depth image (the
kernel uses summed-area tables), the window statistics are vectorised numpy, the minimal solver
is ``sphere_model.solve_known_radius``. The tests run both on a small cloud with one seed and
require the same candidates. Far too slow for real frames; it exists to check the fast path.
"""

from __future__ import annotations

import math

import numpy as np

from spherebench.method import _kernels as K
from spherebench.method import sphere_model as sm

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


def depth_image(points: np.ndarray, index_image: np.ndarray) -> np.ndarray:
    """(H, W) float64 depth of each pixel's point, NaN where there is none."""
    z = np.full(index_image.shape, np.nan)
    ok = index_image >= 0
    z[ok] = points[index_image[ok], 2]
    return z


def patch(zimg: np.ndarray, r: int, c: int, half: int) -> np.ndarray:
    """(the patch (h, w), its valid depths (K,)): the square of half-side ``half`` around pixel (r, c), clipped."""
    h, w = zimg.shape
    r0, r1 = max(r - half, 0), max(min(r + half + 1, h), 0)  # a patch off the image is empty
    c0, c1 = max(c - half, 0), max(min(c + half + 1, w), 0)
    block = zimg[r0:max(r1, r0), c0:max(c1, c0)]
    return block, block[np.isfinite(block)]


def noise_eps(cz, prm):
    e = max(prm[K.P_EPS], prm[K.P_NOISE_K] * prm[K.P_NOISE_A] * cz * cz)
    cap = prm[K.P_EPS_CAP]
    return min(e, cap) if cap > prm[K.P_EPS] else prm[K.P_EPS]


def disc_radius_px(cz, dist, radius, fx):
    return fx * radius / math.sqrt(max(dist * dist - radius * radius, 1e-12)) * dist / cz


def ray_residual(p, c, radius):
    """(|p| - t_near, hit) for point p (3,) and centre c (3,)."""
    pn = math.sqrt(float(p @ p))
    if pn <= 0:
        return math.nan, False
    tc = float(p @ c) / pn
    m2 = float(c @ c) - tc * tc
    if m2 > radius * radius:
        return math.nan, False
    return pn - (tc - math.sqrt(radius * radius - m2)), True


def denoised(points, zimg, i, r, c, prm):
    """Point i moved to its patch's mean depth, or None (see ``_kernels.denoised_point``)."""
    p = points[i].astype(np.float64)
    z = p[2]
    h = K.patch_half(z, prm[K.P_NOISE_A], prm[K.P_SIGMA_T], int(prm[K.P_H_MAX]))
    if h == 0:
        return p
    block, vals = patch(zimg, r, c, h)
    if len(vals) < 0.5 * block.size:
        return None
    m = vals.mean()
    lim = 2.0 * prm[K.P_NOISE_A] * z * z + 0.25 * prm[K.P_R]
    if (vals * vals).mean() - m * m > lim * lim:
        return None
    return p * (m / z)


def pixel_at(index_image, u0, v0, r_in, r_out, ang, u_rad):
    h, w = index_image.shape
    rad = math.sqrt(r_in * r_in + (r_out * r_out - r_in * r_in) * u_rad)
    c = int(math.floor(u0 + rad * math.cos(ang) + 0.5))
    r = int(math.floor(v0 + rad * math.sin(ang) + 0.5))
    return -1 if (r < 0 or r >= h or c < 0 or c >= w) else int(index_image[r, c])


def pretest(points, index_image, centre, e, prm, rng: SplitMix64) -> bool:
    """The pixel pretest, drawing exactly as the kernel (it stops at the first decisive pixel)."""
    fx, fy, ppx, ppy, radius = prm[K.P_FX], prm[K.P_FY], prm[K.P_PPX], prm[K.P_PPY], prm[K.P_R]
    n_draws = int(prm[K.P_PRETEST_N])
    max_fail = int((1.0 - prm[K.P_PRETEST_FRAC]) * n_draws)
    cx, cy, cz = centre
    rpx = disc_radius_px(cz, math.sqrt(float(centre @ centre)), radius, fx)
    u0, v0 = fx * cx / cz + ppx, fy * cy / cz + ppy
    valid = fails = 0
    for _ in range(n_draws):
        ang = 2.0 * math.pi * rng.u01()
        i = pixel_at(index_image, u0, v0, 0.0, 0.8 * rpx, ang, rng.u01())
        if i < 0:
            continue
        valid += 1
        dt, hit = ray_residual(points[i].astype(np.float64), centre, radius)
        if not (hit and abs(dt) <= e):
            fails += 1
            if fails > max_fail:
                return False
    if valid < 3 or valid - fails < prm[K.P_PRETEST_FRAC] * valid:
        return False
    valid = cont = 0
    n_ring = max(2, n_draws // 2)
    for _ in range(n_ring):
        ang = 2.0 * math.pi * rng.u01()
        i = pixel_at(index_image, u0, v0, 1.1 * rpx, K.RING_FACTOR * rpx, ang, rng.u01())
        if i < 0:
            continue
        p = points[i].astype(np.float64)
        pn = math.sqrt(float(p @ p))
        valid += 1
        if abs(pn - float(p @ centre) / pn) <= e:
            cont += 1
            if cont > n_ring // 2:
                return False
    return not (valid >= 2 and cont > 0.5 * valid)


def patch_pretest(zimg, centre, e, prm) -> bool:
    """``_kernels.patch_pretest`` with directly summed patches."""
    fx, fy, ppx, ppy, radius = prm[K.P_FX], prm[K.P_FY], prm[K.P_PPX], prm[K.P_PPY], prm[K.P_R]
    cx, cy, cz = centre
    dist = math.sqrt(float(centre @ centre))
    rpx = disc_radius_px(cz, dist, radius, fx)
    u0, v0 = fx * cx / cz + ppx, fy * cy / cz + ppy
    z_front = (dist - radius) * cz / dist
    sz = prm[K.P_NOISE_A] * z_front * z_front

    def mean(u, v, half):
        _, vals = patch(zimg, int(math.floor(v + 0.5)), int(math.floor(u + 0.5)), half)
        return (vals.mean(), len(vals)) if len(vals) else (math.nan, 0)

    m, n = mean(u0, v0, max(1, int(rpx / 3.0)))
    if n >= 3 and m > z_front + e + 3.0 * sz / math.sqrt(n):
        return False
    half = max(1, int(rpx / 4.0))
    cont = 0
    for du, dv in ((1.4 * rpx, 0.0), (-1.4 * rpx, 0.0), (0.0, 1.4 * rpx), (0.0, -1.4 * rpx)):
        m, n = mean(u0 + du, v0 + dv, half)
        if n < 0.3 * (2 * half + 1) ** 2:
            continue
        if z_front - (e + 3.0 * sz / math.sqrt(n)) <= m <= cz:
            cont += 1
            if cont > 2:
                return False
    return True


def window_stats(points, index_image, centre, e, prm, stride) -> np.ndarray:
    """``_kernels.window_stats`` vectorised over the strided window: (N_STATS,) counts."""
    fx, fy, ppx, ppy, radius = prm[K.P_FX], prm[K.P_FY], prm[K.P_PPX], prm[K.P_PPY], prm[K.P_R]
    out = np.zeros(K.N_STATS)
    h, w = index_image.shape
    cx, cy, cz = centre
    dist = math.sqrt(float(centre @ centre))
    rpx = disc_radius_px(cz, dist, radius, max(fx, fy)) * K.RING_FACTOR * 1.05 + 2.0
    u0, v0 = fx * cx / cz + ppx, fy * cy / cz + ppy
    r = np.arange(max(0, int(math.floor(v0 - rpx))), min(h - 1, int(math.ceil(v0 + rpx))) + 1, stride)
    c = np.arange(max(0, int(math.floor(u0 - rpx))), min(w - 1, int(math.ceil(u0 + rpx))) + 1, stride)
    rr, cc = np.meshgrid(r, c, indexing="ij")
    idx = index_image[rr, cc].ravel()
    rr, cc = rr.ravel(), cc.ravel()
    # pixels without depth inside the silhouette
    rays = np.stack([(cc - ppx) / fx, (rr - ppy) / fy, np.ones(len(cc))], axis=1)
    in_disc = rays @ centre / (np.linalg.norm(rays, axis=1) * dist) >= math.sqrt(1.0 - (radius / dist) ** 2)
    out[K.ST_INVALID_DISC] = np.count_nonzero((idx < 0) & in_disc)
    p = points[idx[idx >= 0]].astype(np.float64)
    pn = np.linalg.norm(p, axis=1)
    tc = p @ centre / pn
    m2 = centre @ centre - tc * tc
    hit = m2 <= radius * radius
    dt = pn[hit] - (tc[hit] - np.sqrt(radius * radius - m2[hit]))
    inl = np.abs(dt) <= e
    out[K.ST_VALID_DISC] = hit.sum()
    out[K.ST_INLIER] = inl.sum()
    out[K.ST_SSE] = float(np.sum(dt[inl] ** 2))
    front = ~inl & (dt < 0)
    out[K.ST_FRONT] = front.sum()
    out[K.ST_FRONT_NEAR] = np.count_nonzero(front & (dt >= -0.5 * radius))
    out[K.ST_BEHIND] = np.count_nonzero(~inl & (dt >= 0))
    ring = ~hit & (tc > 0) & (dist * dist - tc * tc <= (K.RING_FACTOR * radius) ** 2)
    out[K.ST_RING] = ring.sum()
    out[K.ST_RING_CONT] = np.count_nonzero(ring & (np.abs(pn - tc) <= e))
    return out * float(stride * stride)


def keep_candidate(kept: list, centre, q, merge, k_max):
    """``_kernels._keep_candidate`` on a list of (quality, centre), best first."""
    for j, (qj, cj) in enumerate(kept):
        if np.sum((cj - centre) ** 2) <= merge * merge:
            if q <= qj:
                return
            del kept[j]
            break
    if len(kept) == k_max and q <= kept[-1][0]:
        return
    pos = len(kept)
    while pos > 0 and kept[pos - 1][0] < q:
        pos -= 1
    kept.insert(pos, (q, centre.copy()))
    del kept[k_max:]


def search_organised(points, rows, cols, index_image, prm, seed: int, k_max: int):
    """Replay of ``_kernels.search_organised``: (centres (M, 3), qualities (M,), counters (4,))."""
    n = len(points)
    h, w = index_image.shape
    fx, radius = prm[K.P_FX], prm[K.P_R]
    zimg = depth_image(points, index_image)
    rng = SplitMix64(seed)
    kept: list = []
    counters = np.zeros(4, np.int64)
    for _ in range(int(prm[K.P_ITERS])):
        i1 = min(int(rng.u01() * n), n - 1)
        r1, c1 = int(rows[i1]), int(cols[i1])
        if index_image[r1, c1] != i1:
            continue
        z1 = float(points[i1, 2])
        if z1 <= radius:
            continue
        rpx = fx * prm[K.P_SAMPLE_R] / z1
        reach = 2.0 * radius + 3.0 * prm[K.P_NOISE_A] * z1 * z1
        picks, pix, ang2 = [i1], [(r1, c1)], 0.0
        for slot in range(2):
            for _ in range(int(prm[K.P_RETRIES])):
                ang = 2.0 * math.pi * rng.u01() if slot == 0 else ang2 + 0.5 * math.pi + math.pi * rng.u01()
                rad = rpx * math.sqrt(0.09 + 0.91 * rng.u01())
                c = int(math.floor(c1 + rad * math.cos(ang) + 0.5))
                r = int(math.floor(r1 + rad * math.sin(ang) + 0.5))
                if not (0 <= r < h and 0 <= c < w) or index_image[r, c] < 0:
                    continue
                j = int(index_image[r, c])
                if np.sum((points[j].astype(np.float64) - points[i1]) ** 2) > reach * reach:
                    continue
                picks.append(j)
                pix.append((r, c))
                ang2 = ang
                break
        if len(picks) < 3:
            continue
        pts = [denoised(points, zimg, i, r, c, prm) for i, (r, c) in zip(picks, pix)]
        if any(p is None for p in pts):
            continue
        counters[0] += 1
        near, far, ok = sm.solve_known_radius(pts[0], pts[1], pts[2], radius, both=True)
        if not ok[0]:
            continue
        counters[1] += 1
        for centre in (far[0], near[0]):
            if centre[2] <= radius or any(float((p - centre) @ p) >= 0.0 for p in pts):
                continue
            e = noise_eps(centre[2], prm)
            if not patch_pretest(zimg, centre, e, prm):
                continue
            if not pretest(points, index_image, centre, e, prm, rng):
                continue
            counters[2] += 1
            if any(np.sum((cj - centre) ** 2) <= prm[K.P_DEDUP] ** 2 for _, cj in kept):
                continue
            dist = math.sqrt(float(centre @ centre))
            box = 2.0 * (K.RING_FACTOR * 1.05 * disc_radius_px(centre[2], dist, radius, fx) + 2.0) + 1.0
            stride = max(1, int(math.ceil(box / math.sqrt(prm[K.P_SCORE_MAX]))))
            st = window_stats(points, index_image, centre, e, prm, stride)
            ring = 1.0 - st[K.ST_RING_CONT] / max(st[K.ST_RING], 1.0)
            q = (st[K.ST_INLIER] - st[K.ST_SSE] / (e * e) - st[K.ST_BEHIND] - st[K.ST_FRONT_NEAR]) * ring * ring
            if q <= 0.0:
                continue
            counters[3] += 1
            keep_candidate(kept, centre, q, 0.5 * radius, k_max)
    centres = np.array([c for _, c in kept]).reshape(-1, 3)
    return centres, np.array([q for q, _ in kept]), counters
