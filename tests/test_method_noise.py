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
from spherebench.method.improved import Frame, noise_a

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
    frame = Frame(cloud, cfg)
    true_a = sensor.sigma_z_m(1.0, cloud.intrinsics.fx)  # sigma_z / z^2
    assert frame.noise_a_measured == pytest.approx(true_a, rel=0.10)
    model_a = noise_a(cfg, cloud.intrinsics.fx)
    if abs(frame.noise_a_measured / model_a - 1.0) > cfg.noise_model_tolerance:  # the kernels use it
        assert frame.noise_a == frame.noise_a_measured and abs(subpixel - 0.08) > 0.01
    else:  # measured as the nominal unit: the model kept exactly
        assert frame.noise_a == model_a and subpixel == 0.08


def test_the_override_and_a_frame_without_samples_use_the_configured_noise():
    cloud, _ = _wall_cloud(424, 240, 0.16, 0.0)
    told = config_for("improved", noise_z2_per_m=0.01)
    frame = Frame(cloud, told)
    assert frame.noise_a_measured is None and frame.noise_a == 0.01
    near, _ = _wall_cloud(424, 240, 0.08, 0.0, z_m=0.4, tilt_deg=0.0)  # nearer than noise_estimate_min_depth_m
    cfg = config_for("improved")
    frame = Frame(near, cfg)
    assert frame.noise_a_measured is None and frame.noise_a == noise_a(cfg, near.intrinsics.fx)
    off = Frame(cloud, config_for("improved", noise_estimate=False))
    assert off.noise_a_measured is None and off.noise_a == noise_a(cfg, cloud.intrinsics.fx)
