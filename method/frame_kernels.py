"""The frame's kernels: the index image, the summed-area table of depth over cells, the depth
histogram, and the parameter vector's slots that every organised kernel reads (``PARAMETERS``,
filled by ``frame.parameters``).
"""

from __future__ import annotations

import math

import numpy as np

from spherebench.method.compiled import kernel


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
def deproject_counts(depth, scale, rays, v0, v1, u0, u1):
    """The organised cloud of a depth image's window [v0, v1) x [u0, u1): points (N, 3) float32 m and
    their pixel rows, cols (N,) int32 in the window, from depth (H, W) uint16 counts of ``scale`` m
    (0: no depth) and rays (H, W, 3) with z = 1. Row-major, each point as ``cloud.cloud_from_depth``
    makes it (float32 depth, times the float64 ray, rounded to float32): the same cloud in one pass."""
    s = np.float32(scale)
    n = 0
    for v in range(v0, v1):
        for u in range(u0, u1):
            n += depth[v, u] != 0
    points = np.empty((n, 3), np.float32)
    rows = np.empty(n, np.int32)
    cols = np.empty(n, np.int32)
    k = 0
    for v in range(v0, v1):
        for u in range(u0, u1):
            d = depth[v, u]
            if d == 0:
                continue
            z = np.float64(np.float32(d) * s)
            for j in range(3):
                points[k, j] = np.float32(rays[v, u, j] * z)
            rows[k], cols[k] = v - v0, u - u0
            k += 1
    return points, rows, cols


@kernel
def build_index_image(rows, cols, height, width):
    """(H, W) int32 image of point indices (-1: no point) from per-point pixel rows, cols (N,)."""
    img = np.full((height, width), -1, np.int32)
    for i in range(rows.shape[0]):
        r, c = rows[i], cols[i]
        if 0 <= r < height and 0 <= c < width:
            img[r, c] = i
    return img


# ----------------------------------------------------------------------------------------------
# Organised clouds: the search. Scalar parameters travel in one float64 array (``prm``, indexed by
# the P_* names below): one argument instead of twenty keeps numba's call overhead small.
#
# The search works on a grid of cells of BIN x BIN pixels (1 at 424x240, 2 at 848x480, 3 at
# 1280x720: about 424 cells across whatever the stream; from 3 x 3 on a cell sums its middle pixel
# row only, ``frame.cell_rows``, P_CELL_PX pixels), through the summed-area table ``tab``
# (Hc + 1, Wc + 1) uint64 of the depth z in millimetres and of the valid-pixel count per cell, packed
# in one word (depth sum + count << COUNT_SHIFT); a box's mean range |p| is its mean depth times the
# length of the ray (z = 1) through the box's centre. The table is kept modulo 2^64: a box's packed
# sum comes out exact, its depth sum below 2^40 mm (a whole 4k frame at 60 m) and its count below
# 2^24, so one load per corner and one add per cell serve both (the 2.4 MB of a float64 table with
# a squared-depth channel did not stay in cache; two uint32 channels took twice the adds).

#: The parameter vector's slots, in order: the one list of what ``frame.parameters`` fills in per
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
    # (``noise.mean_variance_inflation``), square-rooted
    "MEAN_NOISE",
    # the search's stencil follows the silhouette's off-axis stretch (1: on, ``improved``'s retry; 0:
    # square, as on the axis)
    "OFF_AXIS",
    # the descent leaves out side boxes more than R in front of the centre box, an occluder (1: on,
    # ``improved``'s second search of a frame where none was accepted; 0: off)
    "OCCLUDER_BOUND",
)
#: The band's cap over R: a band wider than 1.5 R takes in the background behind a far ball.
MAX_EPS_FRACTION = 1.5
for _index, _name in enumerate(PARAMETERS):
    globals()["P_" + _name] = _index
N_PRM = len(PARAMETERS)
#: The packed table's count field starts at this bit; the depth sum (mm) takes the bits below.
COUNT_SHIFT = 40
_DEPTH_MASK = (1 << COUNT_SHIFT) - 1


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
    ``frame.cell_lookup``) and hist (B,) int64 (counts of z in bins of 1 / hist_per_m
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
