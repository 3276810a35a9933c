"""The detector measures each frame's depth noise (``improved.frame_noise_a``) instead of trusting
the nominal D435 model: noisier and quieter units, correlated noise, other resolutions."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from spherebench.camera import Intrinsics
from spherebench.cloud import cloud_from_depth, depth_to_metres
from spherebench.datasets.sensor import D435Sensor, apply_sensor
from spherebench.method import config_for
from spherebench.method import verification as verification_stage
from spherebench.method.frame import PreparedFrame
from spherebench.method.noise import NOISE_MODEL_TOLERANCE, noise_a

# depth noise only: no holes, flying pixels or shadow band
BARE = D435Sensor(hole_probability=0.0, hole_blobs_per_mpx=0.0, flying_probability=0.0, shadow=False)


def _wall_cloud(width, height, subpixel, corr_px, z_m=2.0, tilt_deg=30.0, seed=0):
    """A wall at z_m metres, tilted tilt_deg about the vertical axis, seen through the sensor."""
    intr = Intrinsics.d435(width, height)
    u = (np.arange(width) - intr.ppx) / intr.fx
    x_over_z = np.broadcast_to(u, (height, width))
    # plane z = z_m + tan(tilt) x  ->  z = z_m / (1 - tan(tilt) x / z)
    z = z_m / (1.0 - np.tan(np.radians(tilt_deg)) * x_over_z)
    sensor = replace(BARE, subpixel=subpixel, correlation_px=corr_px)
    depth = apply_sensor(z, intr, sensor, np.random.default_rng(seed))
    return cloud_from_depth(depth_to_metres(depth, intr), intr), sensor


@pytest.mark.parametrize("width,height,subpixel,corr_px", [
    (424, 240, 0.08, 0.0), (424, 240, 0.16, 0.0), (424, 240, 0.05, 1.0), (424, 240, 0.20, 1.5),
    (848, 480, 0.12, 1.0), (1280, 720, 0.08, 1.0)])
def test_measured_noise_matches_the_sensor_within_10_percent(width, height, subpixel, corr_px):
    cloud, sensor = _wall_cloud(width, height, subpixel, corr_px)
    cfg = config_for("improved")
    frame = PreparedFrame(cloud, cfg)
    true_a = sensor.sigma_z_m(1.0, cloud.intrinsics.fx)  # sigma_z / z^2
    assert frame.noise_a_measured == pytest.approx(true_a, rel=0.10)
    model_a = noise_a(cfg, cloud.intrinsics.fx)
    if abs(frame.noise_a_measured / model_a - 1.0) > NOISE_MODEL_TOLERANCE:  # the kernels use it
        assert frame.noise_a == frame.noise_a_measured and abs(subpixel - 0.08) > 0.01
    else:  # measured as the nominal unit: the model kept exactly
        assert frame.noise_a == model_a and subpixel == 0.08


def test_the_override_and_a_frame_without_samples_use_the_configured_noise():
    cloud, _ = _wall_cloud(424, 240, 0.16, 0.0)
    told = config_for("improved", noise={"noise_z2_per_m": 0.01})
    frame = PreparedFrame(cloud, told)
    assert frame.noise_a_measured is None and frame.noise_a == 0.01
    near, _ = _wall_cloud(424, 240, 0.08, 0.0, z_m=0.4, tilt_deg=0.0)  # nearer than NOISE_ESTIMATE_MIN_DEPTH_M
    cfg = config_for("improved")
    frame = PreparedFrame(near, cfg)
    assert frame.noise_a_measured is None and frame.noise_a == noise_a(cfg, near.intrinsics.fx)
    off = PreparedFrame(cloud, config_for("improved", noise={"noise_estimate": False}))
    assert off.noise_a_measured is None and off.noise_a == noise_a(cfg, cloud.intrinsics.fx)


@pytest.mark.parametrize("width,height,subpixel,corr_px", [
    (424, 240, 0.08, 0.0), (424, 240, 0.16, 1.0), (424, 240, 0.08, 1.5), (848, 480, 0.12, 1.0),
    (1280, 720, 0.08, 1.0)])
def test_measured_noise_correlation_matches_the_sensor_within_10_percent(width, height, subpixel, corr_px):
    """The correlation length read off second differences at lags 1 and 3 (in the stream's pixels:
    the sensor's correlation_px is given at 424 wide); independent noise reads 0."""
    cloud, _ = _wall_cloud(width, height, subpixel, corr_px)
    frame = PreparedFrame(cloud, config_for("improved"))
    true_px = corr_px * width / 424
    if corr_px == 0:
        assert frame.noise_corr_px == 0.0
    else:
        assert frame.noise_corr_px == pytest.approx(true_px, rel=0.10)
    assert PreparedFrame(cloud, config_for("improved", noise={"noise_correlation": False})).noise_corr_px == 0.0


def test_effective_samples_of_correlated_noise():
    from spherebench.datasets.sensor import correlated_noise
    from spherebench.method.noise import _second_difference_ratio, correlation_from_ratio, mean_variance_inflation
    assert mean_variance_inflation(0.0) == 1.0 and mean_variance_inflation(0.3) == pytest.approx(1.0, abs=1e-4)
    assert mean_variance_inflation(4.0) == pytest.approx(np.pi * 16.0, rel=1e-3)  # pi length^2 when long
    assert (mean_variance_inflation(2.0, stride=4) < mean_variance_inflation(2.0, stride=2)
            < mean_variance_inflation(2.0))
    for length in (0.8, 1.0, 1.7, 2.5):  # the bisection stops at 1e-4 px
        assert correlation_from_ratio(_second_difference_ratio(length, 3), 3, 6.0) == pytest.approx(length, abs=1e-4)
    # patch means of such noise vary as the lattice sum says: 16 x 16 means of a length-1.5 field (a
    # finite patch: each lag k weighted by (16 - |k|) / 16), which the large-patch figure bounds
    rng = np.random.default_rng(0)
    field = correlated_noise(rng.standard_normal((512, 512)), 1.5)
    means = field.reshape(32, 16, 32, 16).mean(axis=(1, 3))
    k = np.arange(-15, 16)
    finite = np.sum((16 - np.abs(k)) / 16 * np.exp(-(k / 1.5) ** 2)) ** 2
    assert means.var() * 256 == pytest.approx(finite, rel=0.12) and finite < mean_variance_inflation(1.5)


def test_multistart_verification_only_where_noise_nears_the_radius():
    """A far ball on a noisy unit is verified from several starts and kept only through the mean of
    the starts about the best; a near ball, or the same frame with multistart off, goes the plain way."""
    from spherebench.method import detect
    calls = []
    real = verification_stage.verify_noisy

    def counting(*args, **kw):
        calls.append(1)
        return real(*args, **kw)

    cloud, _ = _wall_cloud(424, 240, 0.08, 0.0, z_m=2.0, tilt_deg=0.0)
    cfg = config_for("improved")
    verification_stage.verify_noisy = counting
    fraction = verification_stage.MULTISTART_NOISE_FRACTION
    try:
        detect(cloud, cfg, seed=0)  # sigma at 2 m: 3 cm, a quarter of R
        assert not calls
        verification_stage.MULTISTART_NOISE_FRACTION = 0.1
        detect(cloud, cfg, seed=0)
        assert calls
    finally:
        verification_stage.verify_noisy = real
        verification_stage.MULTISTART_NOISE_FRACTION = fraction
