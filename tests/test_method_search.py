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
from spherebench.method import _kernels as K
from spherebench.method import detector as det
from spherebench.method import improved as imp
from spherebench.method import reference as ref

from test_method_detector import cap_points, scene

R = 0.12


def test_splitmix_replay_matches_kernel():
    state = np.array([12345], np.uint64)
    gen = ref.SplitMix64(12345)
    assert [K.next_u01(state) for _ in range(50)] == [gen.u01() for _ in range(50)]


@pytest.mark.parametrize("ball, noise, seed", [((0.1, -0.05, 1.6), 0.01, 99), ((-0.05, 0.02, 0.9), 0.003, 5)])
def test_compiled_search_equals_reference(ball, noise, seed):
    # a small, noisy frame: far enough that sample points are moved to patch means (denoising)
    cloud = scene(ball_c=ball, noise=noise, width=120, height=90, seed=seed)
    cfg = config_for("improved", iterations=500, adaptive=False)
    frame = det.prepare_frame(cloud, cfg)
    assert K.patch_half(ball[2], frame.prm[K.P_NOISE_A], cfg.denoise_sigma_m, cfg.denoise_max_half_px) > 0
    k = max(2 * cfg.max_spheres, 4)
    cands, quals = imp.search_organised(frame, cfg, seed)
    rc, rq, rctr = ref.search_organised(cloud.points, cloud.rows, cloud.cols, frame.index_image, frame.prm, seed, k)
    assert np.array_equal(frame.counters, rctr)
    assert len(cands) == len(rc) >= 1
    assert np.allclose(cands, rc, atol=1e-9)
    assert np.allclose(quals, rq, rtol=1e-4)  # the kernel measures |p| in float32
    # and the best candidate is the ball (unrefined: a hypothesis from three noisy samples)
    assert np.linalg.norm(cands[0] - ball) < 0.08


def test_depth_integrals_give_patch_means():
    cloud = scene(noise=0.01, width=60, height=40)
    cfg = config_for("improved")
    frame = det.prepare_frame(cloud, cfg)
    zimg = ref.depth_image(cloud.points, frame.index_image)
    for (r, c, half) in ((0, 0, 2), (20, 30, 3), (39, 59, 1), (10, 5, 0)):
        m, n = K.patch_mean(frame.tab, float(c), float(r), half)
        _, vals = ref.patch(zimg, r, c, half)
        assert n == len(vals) and m == pytest.approx(vals.mean(), rel=1e-9)


def test_iteration_bound_follows_ball_area():
    cfg = config_for("improved")
    intr = Intrinsics.d435(424, 240)
    # a room 3 m deep: the bound provides for a ball at 3 m + R, of area pi (fx R / z)^2 pixels
    z = np.full(1000, 3.0)
    k = imp.iteration_bound(cfg, intr, z, 100_000)
    area = math.pi * (intr.fx * R / 3.12) ** 2
    expect = math.log(1 - cfg.confidence) / math.log(1 - area / 100_000 * cfg.sample_success)
    assert k == math.ceil(expect)
    # a shallow scene needs fewer; a deep one is capped by the noise range limit (3.5 m at 424x240)
    assert imp.iteration_bound(cfg, intr, np.full(1000, 1.0), 100_000) < k
    assert imp.range_limit_m(cfg, intr.fx) == pytest.approx(math.sqrt(0.75 * R * intr.fx * 0.05 / 0.08))
    assert imp.iteration_bound(cfg, intr, np.full(1000, 8.0), 100_000) == \
        imp.iteration_bound(cfg, intr, np.full(1000, 5.0), 100_000)
    assert imp.iteration_bound(config_for("improved", adaptive=False), intr, z, 100_000) == cfg.iterations


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
    for kw in ({"radius_m": 0.0}, {"eps_m": 0.12}, {"eps_m": 0.5}, {"confidence": 1.0}, {"denoise_sigma_m": -1.0}):
        with pytest.raises(SphereBenchError):
            config_for("improved", **kw)


def test_huge_cloud_is_bounded_by_max_points():
    # stands for 20 million points: the search sees max_points of them, the final inliers all
    rng = np.random.default_rng(1)
    n = 400_000
    pts = np.column_stack([rng.uniform(-2, 2, n), rng.uniform(-1, 1, n), np.full(n, 3.0)]).astype(np.float32)
    ball = cap_points(np.array([0.2, 0.1, 2.0]), R, 40_000, rng)
    cloud = Cloud(np.vstack([pts, ball]))
    spheres = detect(cloud, config_for("improved", max_points=20_000), seed=0)
    assert spheres and np.linalg.norm(spheres[0].center_m - [0.2, 0.1, 2.0]) < 0.005
    assert len(spheres[0].inlier_indices) > 30_000
