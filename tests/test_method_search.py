"""The compiled organised search against its readable replay, the iteration bound, the exact circle,
the pyransac3d peer, and inputs that must not crash or hang."""

from __future__ import annotations

import math

import numpy as np
import pytest

from spherebench.camera import Intrinsics
from spherebench.circles import mask_circle, sphere_circle_amodal, sphere_circle_exact, sphere_silhouette_mask
from spherebench.cloud import Cloud
from spherebench.errors import SphereBenchError
from spherebench.method import config_for, detect
from spherebench.method import compiled, frame_kernels, search_kernels, verification_kernels
from spherebench.method import frame as frame_stage
from spherebench.method import search as search_stage
from spherebench.method import detector as det
import search_reference as ref  # noqa: E402  (tests/ is on sys.path under pytest)

from test_method_detector import cap_points, scene

R = 0.12


def test_splitmix_replay_matches_kernel():
    state = np.array([12345], np.uint64)
    gen = ref.SplitMix64(12345)
    assert [compiled.next_u01(state) for _ in range(50)] == [gen.u01() for _ in range(50)]


@pytest.mark.parametrize("ball, noise, seed, width, off_axis, occluder",
                         [((0.1, -0.05, 1.6), 0.01, 99, 120, False, False),
                          ((-0.05, 0.02, 0.9), 0.003, 5, 120, False, False),
                          ((0.05, 0.0, 1.2), 0.004, 7, 260, False, False),
                          ((-0.75, 0.3, 1.4), 0.004, 3, 260, True, False),
                          ((0.1, -0.05, 1.6), 0.01, 99, 120, False, True),
                          ((0.05, 0.0, 1.2), 0.004, 7, 260, True, True)])
def test_compiled_search_equals_reference(ball, noise, seed, width, off_axis, occluder):
    # a small, noisy frame; the 260-pixel one is binned 2x2 (search_width_px=130); the fourth ball is
    # 30 degrees off the optical axis, searched with the stencil stretched as its silhouette is; the
    # last two searched as the detector's retries do (the descent's occluder bound)
    cloud = scene(ball_c=ball, noise=noise, width=width, height=width * 3 // 4, seed=seed)
    cfg = config_for("improved", search={"iterations": 2000, "adaptive": False, "search_width_px": 130})
    frame = det.prepare_frame(cloud, cfg)
    assert frame.bin == max(1, width // 130)
    cands, quals, _ = search_stage.search_frame(frame, cfg, seed, occluder_bound=occluder, off_axis=off_axis)
    prm = frame.prm.copy()
    prm[frame_kernels.P_OCCLUDER_BOUND] = 1.0 if occluder else 0.0
    prm[frame_kernels.P_OFF_AXIS] = 1.0 if off_axis else 0.0
    hyp, ctr = ref.search_organised(cloud.points, frame.index_image, prm, seed, search_stage.SEARCH_CANDIDATES)
    assert np.array_equal(frame.counters, ctr) and ctr[1] > 0
    assert np.array_equal(frame.hypotheses, hyp)
    # and the best hypothesis is the ball (unrefined: from box means)
    assert np.linalg.norm(cands[0] - ball) < 0.03
    if not (occluder or off_axis):  # the relief retry: the same hypotheses, ranked by their cap's relief
        search_stage.relief_search(frame, cfg, seed)
        by_relief, ctr = ref.search_organised(cloud.points, frame.index_image, prm, seed,
                                              search_stage.SEARCH_CANDIDATES, relief=True)
        assert np.array_equal(frame.hypotheses, by_relief) and not np.array_equal(by_relief, hyp)


def test_summed_area_table_gives_box_sums():
    cloud = scene(noise=0.01, width=100, height=60)
    for width_px, b in ((424, 1), (50, 2), (33, 3)):
        frame = det.prepare_frame(cloud, config_for("improved", search={"search_width_px": width_px}))
        assert frame.bin == b
        grid = ref.Grid(*ref.cell_images(cloud.points, frame.index_image, b), frame.prm)
        for (v, u, h) in ((0, 0, 2), (10, 15, 3), (19, 33, 1), (5, 2, 0), (-4, 3, 2), (40, 40, 1)):
            assert search_kernels.box_sums(frame.tab, v, u, h) == grid.box_sums(v, u, h)
            got, want = search_kernels.box_range(frame.tab, frame.prm, v, u, h), grid.box_range(v, u, h)
            assert got[1] == want[1] and (got[0] == want[0] or (math.isnan(got[0]) and math.isnan(want[0])))
        # cells of 2 x 2 count all their pixels, cells of 3 x 3 their middle row (every pixel is valid here)
        rows_counted = np.arange(60) % b == b // 2 if b >= 3 else np.ones(60, bool)
        assert frame.n_valid == 100 * rows_counted.sum() and frame.prm[frame_kernels.P_CELL_PX] == b * (1 if b >= 3 else b)
    # depth sums and counts packed in one uint64 stay apart: a frame of 10 m depths (2.4e9 mm in all at 240 x 1000)
    far = Cloud(np.column_stack([np.zeros(240_000), np.zeros(240_000), np.full(240_000, 10.0)]),
                np.repeat(np.arange(240), 1000), np.tile(np.arange(1000), 240), Intrinsics.d435(1000, 240))
    frame = det.prepare_frame(far, config_for("improved", search={"search_width_px": 1000}))
    assert search_kernels.box_sums(frame.tab, 120, 500, 10) == (441 * 10_000, 441, 441)


def test_window_stats_compiled_equals_reference():
    cloud = scene(ball_c=(0.1, -0.05, 1.0), noise=0.003, width=160, height=120, seed=3)
    frame = det.prepare_frame(cloud, config_for("improved"))
    c = np.array([0.102, -0.049, 1.003])
    for stride in (1, 2):
        got = np.zeros(verification_kernels.N_STATS)
        verification_kernels.window_stats(cloud.points, frame.index_image, *c, 0.006, 0.004, frame.prm, stride, got)
        want = ref.window_stats(cloud.points, frame.index_image, c, 0.006, 0.004, frame.prm, stride)
        assert np.allclose(got, want, rtol=1e-5, atol=2e-5)  # residual sums: the kernel rounds differently
        assert got[verification_kernels.ST_INLIER] > 0.7 * got[verification_kernels.ST_VALID_DISC] and got[verification_kernels.ST_IN_N] > 10 and got[verification_kernels.ST_OUTV_N] > 10


def test_strata_follow_the_ransac_bound():
    cfg = config_for("improved")
    intr = Intrinsics.d435(424, 240)
    grid = (240, 424)
    # a room 3 m deep: the bound provides for a ball at 3 m + R, a disc of r = fx R / z cells
    z_far = frame_stage.far_depth_m(cfg, intr, 3.0)
    assert z_far == pytest.approx(3.12)
    r = intr.fx * R / 3.12
    k = frame_stage.stratum_side_ratio(frame_stage.SAMPLE_SUCCESS, cfg.search.confidence)
    assert frame_stage.strata(cfg, intr, z_far, 1, grid) == (int(k * r), int(k * r))
    # k: the worst case over where the disc falls is within the confidence, a slightly larger one is not
    search = cfg.search
    assert frame_stage.stratified_miss(k, frame_stage.SAMPLE_SUCCESS) <= 1 - search.confidence < frame_stage.stratified_miss(1.05 * k, 0.8)
    # independent draws (the area bound) would need strata of 0.74 r: half as many again
    k_area = math.sqrt(frame_stage.SAMPLE_SUCCESS * math.pi / -math.log(1 - cfg.search.confidence))
    assert k_area == pytest.approx(0.739, abs=1e-3) and k > 1.18 * k_area
    # a partly visible ball: the area bound, which holds for any shape
    s_part = frame_stage.strata(cfg, intr, z_far, 1, grid, visible_fraction=0.5)[0]
    assert s_part == int(math.sqrt(0.8 * 0.5 * math.pi * r * r / -math.log(0.01)))
    # a shallow scene needs fewer, larger strata; a deep one is capped by the noise range limit (3.5 m at 424x240)
    assert frame_stage.strata(cfg, intr, frame_stage.far_depth_m(cfg, intr, 1.0), 1, grid)[0] > 2 * int(k * r)
    assert frame_stage.range_limit_m(cfg, intr.fx) == pytest.approx(math.sqrt(0.75 * R * intr.fx * 0.05 / 0.08))
    assert frame_stage.far_depth_m(cfg, intr, 8.0) == frame_stage.far_depth_m(cfg, intr, 5.0) == frame_stage.range_limit_m(cfg, intr.fx)
    # cells of 3 x 3 pixels: the disc is 3 times smaller in cells
    hd = Intrinsics.d435(1280, 720)
    assert frame_stage.strata(cfg, hd, z_far, 3, grid)[0] == int(k * hd.fx / 3 * R / 3.12)
    # without the bound: about `iterations` strata; never fewer than min_iterations
    sv, su = frame_stage.strata(config_for("improved", search={"adaptive": False, "iterations": 400}), intr, z_far, 1, grid)
    assert 400 <= -(-240 // sv) * -(-424 // su) <= 520
    sv, su = frame_stage.strata(config_for("improved", search={"min_iterations": 2000}), intr, 0.5, 1, grid)
    assert -(-240 // sv) * -(-424 // su) >= 2000


def test_stratified_miss_matches_simulated_draws():
    # one uniform draw per square stratum of side k, a disc of radius 1 at a given offset, success p
    rng = np.random.default_rng(0)
    p, k, trials = 0.8, 0.9, 20_000
    for ox, oy in ((0.0, 0.0), (0.45, 0.45), (0.2, 0.0)):
        j = np.arange(-3, 3)
        jx, jy = (a.ravel() for a in np.meshgrid(j, j, indexing="ij"))
        x = (jx * k - ox) + k * rng.random((trials, len(jx)))
        y = (jy * k - oy) + k * rng.random((trials, len(jx)))
        hit = (x * x + y * y <= 1.0) & (rng.random((trials, len(jx))) < p)
        simulated = 1.0 - hit.any(axis=1).mean()
        # the product formula at this offset, its areas by the midpoint rule
        share = []
        for a, b in zip(jx, jy):
            xs = (a * k - ox) + k * (np.arange(400) + 0.5) / 400
            h = np.sqrt(np.clip(1 - xs * xs, 0, None))
            y0 = b * k - oy
            share.append(np.clip(np.minimum(y0 + k, h) - np.maximum(y0, -h), 0, None).mean() / k)
        exact = float(np.prod(1 - p * np.array(share)))
        se = math.sqrt(exact * (1 - exact) / trials)
        assert abs(simulated - exact) < 4 * se + 1e-4
        assert exact <= frame_stage.stratified_miss(k, p) + 1e-9  # the worst case covers every offset
    # and the worst case is far below the area bound exp(-p pi / k^2) of independent draws
    assert frame_stage.stratified_miss(k, p) < 0.5 * math.exp(-p * math.pi / k ** 2)


def test_search_draws_one_first_cell_per_stratum():
    cloud = scene(ball_c=(0.05, 0.0, 1.2), noise=0.004, width=160, height=120, seed=2)
    cfg = config_for("improved")
    frame = det.prepare_frame(cloud, cfg)
    search_stage.search_frame(frame, cfg, 3)
    sv, su = frame.stratum
    assert frame.counters[0] == frame.iterations == -(-120 // sv) * -(-160 // su)


def test_scene_depth_from_the_histogram():
    # the scene depth comes from the frame's histogram (98th percentile, to a bin's upper edge)
    hist = np.zeros(frame_stage.HIST_BINS, np.int64)
    hist[[20, 40, 60]] = [50, 48, 2]
    assert frame_stage.hist_percentile(hist, 98.0) == pytest.approx(41 * frame_stage.HIST_STEP_M)


def test_exact_circle_analytic_inside_rasterised_at_border():
    intr = Intrinsics(width=424, height=240, ppx=211.5, ppy=119.5, fx=213.0, fy=213.0)
    # on the optical axis the silhouette is a circle of radius fx tan(asin(R / d))
    cx, cy, r = sphere_circle_exact(intr, [0, 0, 1.5], R)
    assert (cx, cy) == pytest.approx((211.5, 119.5))
    assert r == pytest.approx(213.0 * math.tan(math.asin(R / 1.5)))
    # inside the image: the analytic amodal circle, within a pixel or so of the rasterised rule
    c = [0.4, -0.1, 1.2]
    got = sphere_circle_exact(intr, c, R)
    assert got == sphere_circle_amodal(intr, c, R)
    ras = mask_circle(sphere_silhouette_mask(intr, c, R))
    assert abs(got[2] - ras[2]) < 0.5 and math.hypot(got[0] - ras[0], got[1] - ras[1]) < 1.5
    # crossing the border: clipped to the image (rasterised), unlike the amodal circle
    c = [-1.25, 0.0, 1.2]
    got = sphere_circle_exact(intr, c, R)
    assert got == pytest.approx(mask_circle(sphere_silhouette_mask(intr, c, R)))
    assert got[2] < sphere_circle_amodal(intr, c, R)[2] - 1.0


def test_pyransac3d_peer_fits_a_lone_sphere_deterministically():
    from spherebench.baselines import pyransac3d_peer as peer
    rng = np.random.default_rng(0)
    c = np.array([0.1, 0.0, 1.5])
    pts = cap_points(c, R, 800, rng, visible=False)
    a = peer.detect(Cloud(pts), points=500, iterations=200, seed=3)
    b = peer.detect(Cloud(pts), points=500, iterations=200, seed=3)
    assert len(a) == 1 and np.allclose(a[0]["center_m"], b[0]["center_m"])
    assert np.linalg.norm(a[0]["center_m"] - c) < 0.005 and abs(a[0]["radius_m"] - R) < 0.005
    assert a[0]["inliers"] > 700 and a[0]["circle_exact"] is None
    with pytest.raises(SphereBenchError):
        peer.detect(Cloud(np.zeros((0, 3))))


# ------------------------------------------------------------------------------------ bad input

def test_bad_organised_input():
    cloud = scene()
    pts = cloud.points.copy()
    pts[:] = np.nan
    with pytest.raises(SphereBenchError, match="at least 3"):
        detect(Cloud(pts, cloud.rows, cloud.cols, cloud.intrinsics))
    with pytest.raises(SphereBenchError, match="millimetres"):
        detect(Cloud(cloud.points * 1000, cloud.rows, cloud.cols, cloud.intrinsics))
    inf = cloud.points.copy()
    inf[::3] = np.inf
    out = detect(Cloud(inf, cloud.rows, cloud.cols, cloud.intrinsics), seed=0)
    assert all(np.all(np.isfinite(inf[s.inlier_indices])) for s in out)
    for kw in ({"radius_m": 0.0}, {"eps_m": 0.12}, {"eps_m": 0.5}, {"search.confidence": 1.0}, {"search.max_range_m": -1.0},
               {"search.search_width_px": 4}):
        with pytest.raises(SphereBenchError):
            config_for("improved", kw)


def test_huge_cloud_is_bounded_by_max_points():
    # stands for 20 million points: the search sees max_points of them, the final inliers all
    rng = np.random.default_rng(1)
    n = 400_000
    pts = np.column_stack([rng.uniform(-2, 2, n), rng.uniform(-1, 1, n), np.full(n, 3.0)]).astype(np.float32)
    ball = cap_points(np.array([0.2, 0.1, 2.0]), R, 40_000, rng)
    cloud = Cloud(np.vstack([pts, ball]))
    spheres = detect(cloud, config_for("improved", input={"max_points": 20_000}), seed=0)
    assert spheres and np.linalg.norm(spheres[0].centre_m - [0.2, 0.1, 2.0]) < 0.005
    assert len(spheres[0].inlier_indices) > 30_000


@pytest.mark.parametrize("width, height", [(424, 240), (848, 480), (1280, 720)])
def test_preparation_matches_numpy_in_any_point_order(width, height):
    """``prepare_organised`` for each table layout (a pixel per cell at 424 px wide, 2 x 2 pixels at 848,
    the middle row of 3 x 3 at 1280), the cloud in raster order and reversed: the same index image,
    counts, histogram and summed-area table, the table equal to numpy's cumulative sums of the packed
    depth and count over the cells, every stale entry overwritten, the histogram numpy's over every
    k-th point that gets a pixel; NaN points and points at z <= 0 get no pixel, depths in millimetres
    are counted."""
    cloud = scene(ball_c=(0.1, -0.05, 1.2), width=width, height=height)
    h, w = cloud.intrinsics.height, cloud.intrinsics.width
    b = max(1, w // 424)
    hc, wc = -(-h // b), -(-w // b)
    pts = cloud.points.copy()
    pts[::97, 0] = np.nan
    pts[5::89, 2] = -1.0
    pts[7::101, 2] = 1500.0  # millimetres
    row_cell, col_cell = frame_stage.cell_lookup(h, w, b)
    results = []
    for order in (np.arange(len(pts)), np.arange(len(pts))[::-1]):
        img = np.zeros((h, w), np.int32)
        tab = np.full((hc + 1, wc + 1), 7, np.uint64)  # stale contents: every entry must be written
        hist = np.ones(frame_stage.HIST_BINS, np.int64)
        n_ok, n_big = frame_kernels.prepare_organised(pts[order], cloud.rows[order], cloud.cols[order], img, tab, row_cell,
                                          col_cell, np.float32(50.0), hist, np.float32(1.0 / frame_stage.HIST_STEP_M))
        stride = max(frame_kernels.HIST_STRIDE, len(pts) // frame_kernels.HIST_SAMPLES)
        sampled = order[::stride]
        sampled = sampled[np.isfinite(pts[sampled]).all(axis=1) & (pts[sampled, 2] > 0)]
        bins = np.minimum((pts[sampled, 2] * np.float32(1.0 / frame_stage.HIST_STEP_M)).astype(np.int64), frame_stage.HIST_BINS - 1)
        assert np.array_equal(hist, np.bincount(bins, minlength=frame_stage.HIST_BINS))
        results.append((n_ok, n_big, np.where(img >= 0, order[np.maximum(img, 0)], -1), tab))
    (ok1, big1, img1, tab1), (ok2, big2, img2, tab2) = results
    finite = np.isfinite(pts).all(axis=1)
    good = finite & (pts[:, 2] > 0)
    assert ok1 == ok2 == finite.sum() and big1 == big2 == (finite & (np.abs(pts[:, 2]) > 50.0)).sum() > 0
    assert np.array_equal(img1, img2) and (img1 >= 0).sum() == good.sum()
    z_mm = (np.minimum(pts[good, 2] * np.float32(1000.0) + np.float32(0.5), np.float32(2.0 ** 32))
            .astype(np.int64).astype(np.uint64))
    packed = z_mm + (np.uint64(1) << np.uint64(frame_kernels.COUNT_SHIFT))
    cells = np.zeros((hc + 1, wc + 1), np.uint64)
    r, c = row_cell[cloud.rows[good]], col_cell[cloud.cols[good]]
    np.add.at(cells, (r[r >= 0], c[r >= 0]), packed[r >= 0])
    expected = cells.cumsum(axis=0, dtype=np.uint64).cumsum(axis=1, dtype=np.uint64)
    assert np.array_equal(tab1, expected) and np.array_equal(tab2, expected)
