"""The D435 sensor model's variations: correlated noise, dropouts, scale error, per-scene sensors,
the robust preset and ``generate --sensor``."""

from __future__ import annotations

import filecmp
import json
import math
from collections import Counter
from dataclasses import fields, replace

import cv2
import numpy as np
import pytest

from spherebench.scripts import cli
from spherebench.camera import Intrinsics, image_rays
from spherebench.datasets import inout, presets, rendering, simulate
from spherebench.datasets.layouts import Layout
from spherebench.datasets.primitives import Box, Cylinder, Plane, SolidSphere, raycast
from spherebench.datasets.sensor import D435Sensor, parse_settings
from spherebench.errors import SphereBenchError

# noise only: no holes, flying pixels or shadow band
BARE = D435Sensor(hole_probability=0.0, hole_blobs_per_mpx=0.0, flying_probability=0.0, shadow=False)
LEGACY = ("baseline_m", "subpixel", "depth_scale_m", "min_depth_m", "max_depth_m", "shadow", "flying_edge_jump",
          "flying_probability", "hole_probability", "hole_blobs_per_mpx", "hole_blob_radius_px")


def _wall(z_m: float) -> Layout:
    layout = Layout()
    layout.add(Plane(np.array([0.0, 0.0, z_m]), np.array([0.0, 0.0, -1.0])), "wall")
    return layout


def _room_with_ball() -> Layout:
    """Floor, wall, a box (planar faces), a standing cylinder (its side curved) and the ball."""
    layout = Layout(floor_y_m=0.6)
    layout.add(Plane(np.array([0.0, 0.6, 0.0]), np.array([0.0, -1.0, 0.0])), "floor")
    layout.add(Plane(np.array([0.0, 0.0, 3.0]), np.array([0.0, 0.0, -1.0])), "wall")
    layout.add(Box(np.array([-0.8, 0.35, 2.0]), np.array([0.25, 0.25, 0.25])), "clutter")
    layout.add(Cylinder(np.array([0.8, 0.6, 2.0]), np.array([0.0, -1.0, 0.0]), 0.12, 0.9), "cylinder")
    layout.add(SolidSphere(np.array([0.0, 0.0, 1.5]), 0.12), "target")
    return layout


def _correlation_length(e: np.ndarray, lag: int, axis: int) -> float:
    """Lag at which the autocorrelation would be 1/e, from its value at ``lag`` (Gaussian model)."""
    a, b = (e[:, :-lag], e[:, lag:]) if axis == 1 else (e[:-lag], e[lag:])
    rho = float(np.mean(a * b) / np.mean(e * e))
    return lag / math.sqrt(-math.log(rho))


@pytest.mark.parametrize("width,height,corr_px", [(424, 240, 0.0), (424, 240, 1.0), (424, 240, 2.5),
                                                  (848, 480, 1.0)])
def test_flat_wall_noise_keeps_its_rms_and_has_the_set_correlation_length(width, height, corr_px):
    """A fronto-parallel wall at 1.5 m: the error's RMS is the stereo model's sigma_z and its
    correlation length (1/e lag, rows and columns) is correlation_px x width / 424, within 10 %."""
    intr = Intrinsics.d435(width, height)
    sensor = replace(BARE, correlation_px=corr_px)
    depth, z_true, _ = rendering.render(_wall(1.5), intr, sensor, np.random.default_rng(3))
    assert (depth > 0).all()
    err = depth * intr.depth_scale - z_true
    sigma = float(sensor.sigma_z_m(1.5, intr.fx))
    rms = float(np.sqrt(np.mean(err ** 2)))
    e = err / sigma
    length = corr_px * width / 424
    if length == 0:
        rho = [float(np.mean(e[:, :-1] * e[:, 1:])), float(np.mean(e[:-1] * e[1:]))]
        print(f"{width}x{height} i.i.d.: RMS {rms * 1000:.2f} mm (model {sigma * 1000:.2f}), lag-1 autocorrelation "
              f"{rho[0]:.3f} (rows), {rho[1]:.3f} (columns)")
        assert max(abs(r) for r in rho) < 0.02
    else:
        lag = max(1, round(length))
        measured = [_correlation_length(e, lag, axis) for axis in (1, 0)]
        print(f"{width}x{height} correlation_px {corr_px}: RMS {rms * 1000:.2f} mm (model {sigma * 1000:.2f}), "
              f"correlation length {measured[0]:.3f} px (rows), {measured[1]:.3f} px (columns), set {length:g} px")
        assert all(abs(m - length) <= 0.1 * length for m in measured)
    assert abs(rms - sigma) <= 0.1 * sigma


def test_depth_scale_error_and_bias_shift_the_depth():
    intr = Intrinsics.d435(424, 240)
    sensor = replace(BARE, subpixel=0.02, depth_scale_error=0.004, depth_bias_m=-0.003)
    depth, z_true, _ = rendering.render(_wall(2.0), intr, sensor, np.random.default_rng(0))
    shift = float(np.mean(depth * intr.depth_scale - z_true))
    assert shift == pytest.approx(2.0 * 0.004 - 0.003, abs=3e-4)


@pytest.mark.parametrize("ball", [False, True])
def test_dropouts_take_the_set_share_of_planar_surfaces_in_blobs_and_spare_curved_ones(ball):
    intr = Intrinsics.d435(424, 240)
    layout = _room_with_ball()
    _z, label = raycast([it.shape for it in layout.items], image_rays(intr), intr)
    off = rendering.render(layout, intr, BARE, np.random.default_rng(0))[0]
    sensor = replace(BARE, dropout_probability=1.0, dropout_fraction=0.4, dropout_ball=ball)
    on = rendering.render(layout, intr, sensor, np.random.default_rng(0))[0]
    dropped = (on == 0) & (off > 0)
    assert (on[~dropped] == off[~dropped]).all()  # the dropouts leave the rest of the frame as it was
    shares = {it.kind: float(dropped[label == k + 1].mean()) for k, it in enumerate(layout.items)}
    print(f"dropout_ball={ball}: dropped share per surface kind {shares}")
    for kind in ("floor", "wall", "clutter"):  # the box's faces each drop 40 % (to a pixel)
        assert shares[kind] == pytest.approx(0.4, abs=0.01)
    assert shares["cylinder"] == 0.0  # its side is curved, its caps out of view
    assert shares["target"] == (pytest.approx(0.4, abs=0.01) if ball else 0.0)
    n_blobs, _ = cv2.connectedComponents(dropped.astype(np.uint8), connectivity=4)
    assert dropped.sum() / (n_blobs - 1) > 30  # blobs, not scattered pixels


def test_at_probability_one_half_a_cluttered_frame_loses_some_surfaces_never_the_ball():
    scene_off = rendering.simulate_scene("default", 3, "cluttered", 0, "424x240")
    half = D435Sensor(dropout_probability=0.5)
    scene_on = rendering.simulate_scene("default", 3, "cluttered", 0, "424x240", sensor=half)
    lost = (scene_on.depth == 0) & (scene_off.depth > 0)
    assert 0.02 < lost.mean() < 0.4
    assert not (lost & scene_on.balls[0].silhouette).any()


def test_new_parameters_at_their_off_values_reproduce_the_nominal_scene():
    """Features off (other newer parameters changed, off values given explicitly) draw nothing:
    the same depth and ground truth as the nominal sensor; a nominal dataset's scenes record no
    sensor of their own and its dataset.json record has the original keys only."""
    nominal = rendering.simulate_scene("default", 1, "cluttered", 0, "424x240")
    off = D435Sensor(dropout_fraction=0.9, dropout_blob_px=3.0, dropout_ball=True, correlation_px=0.0)
    explicit = {"correlation_px": 0.0, "dropout_probability": 0.0, "depth_scale_error": 0.0, "depth_bias_m": 0.0,
                "flying_mix": (0.1, 0.9)}
    for scene in (rendering.simulate_scene("default", 1, "cluttered", 0, "424x240", sensor=off),
                  rendering.simulate_scene("default", 1, "cluttered", 0, "424x240", sensor_overrides=explicit)):
        assert np.array_equal(scene.depth, nominal.depth)
        assert all(np.array_equal(a.mask, b.mask) for a, b in zip(scene.balls, nominal.balls))
        assert scene.meta["sensor"]["correlation_px"] == 0.0
    assert "sensor" not in nominal.meta and "sensor_cell" not in nominal.meta
    assert tuple(D435Sensor().to_dict(compact=True)) == LEGACY
    assert D435Sensor.from_dict(json.loads(json.dumps(off.to_dict()))) == off


def test_ranges_are_drawn_per_scene_from_the_scene_seed():
    ranges = {"subpixel": (0.05, 0.2), "correlation_px": (0.0, 1.5), "flying_mix": (0.2, 0.3)}
    draws = [rendering.scene_sensor("default", 0, i, overrides=ranges)[0] for i in range(20)]
    assert draws == [rendering.scene_sensor("default", 0, i, overrides=ranges)[0] for i in range(20)]
    assert all(0.05 <= s.subpixel <= 0.2 and 0 <= s.correlation_px <= 1.5 and s.flying_mix == (0.2, 0.3)
               for s in draws)
    assert len({s.subpixel for s in draws}) == 20
    assert draws[0] != rendering.scene_sensor("default", 1, 0, overrides=ranges)[0]  # another --seed


def test_robust_plan_balances_cells_families_and_resolutions():
    jobs = simulate.plan("robust")
    cells = [rendering.scene_sensor("robust", 0, i) for i, _f, _r in jobs]
    per_cell = Counter(c["cell"] for _s, c in cells)
    assert len(jobs) == 400 and len(per_cell) == 20 and set(per_cell.values()) == {20}
    mix = Counter((c["cell"], f, r) for (_s, c), (_i, f, r) in zip(cells, jobs))
    assert all(mix[(k, f, "424x240")] == 8 and mix[(k, f, "848x480")] == 2
               for k in range(20) for f in ("clean", "cluttered"))
    grid = {(c["subpixel"], c["correlation"], c["dropouts"]) for _s, c in cells}
    assert len(grid) == 20
    for sensor, c in cells:  # each scene's sensor is its cell's
        assert sensor.subpixel == c["subpixel"]
        assert sensor.correlation_px == {"none": 0.0, "1px": 1.0}[c["correlation"]]
        assert sensor.dropouts == (c["dropouts"] == "on")


def test_robust_dataset_is_byte_identical_for_the_same_seed_and_records_each_scene_sensor(tmp_path):
    ranges = {"flying_probability": (0.1, 0.5)}
    a = simulate.generate_dataset("robust", tmp_path / "a" / "ds", n=4, progress=False, workers=1,
                                  sensor_overrides=ranges)
    b = simulate.generate_dataset("robust", tmp_path / "b" / "ds", n=4, progress=False, workers=2,
                                  sensor_overrides=ranges)
    files = sorted(p.relative_to(a) for p in a.rglob("*") if p.is_file())
    assert files == sorted(p.relative_to(b) for p in b.rglob("*") if p.is_file())
    for f in files:
        assert filecmp.cmp(a / f, b / f, shallow=False), f
    meta = inout.read_dataset_meta(a)
    assert meta["sensor_ranges"]["cells"] == 20 and meta["sensor_overrides"] == {"flying_probability": [0.1, 0.5]}
    seen = []
    for scene_dir in inout.list_scenes(a):
        gt = json.loads((scene_dir / "gt.json").read_text())
        sensor = D435Sensor.from_dict(gt["meta"]["sensor"])
        assert 0.1 <= sensor.flying_probability <= 0.5
        seen.append((gt["meta"]["sensor_cell"]["cell"], sensor.correlation_px, sensor.dropouts))
    assert sorted(seen) == [(0, 0.0, False), (1, 0.0, True), (2, 1.0, False), (3, 1.0, True)]


def test_robust_seeds_are_disjoint_from_the_other_presets():
    robust = {presets.generation_seed(presets.PRESETS["robust"], s, i) for s in range(3) for i in range(400)}
    for name in ("default", "paper", "hard", "train"):
        assert not robust & {presets.generation_seed(presets.PRESETS[name], s, i) for s in range(3) for i in range(2000)}


@pytest.mark.parametrize("setting,named", [
    ("sub_pixel=0.1", "sub_pixel"),                  # unknown name
    ("subpixel=0.2:0.1", "subpixel"),                # LO > HI
    ("subpixel=-0.01", "subpixel"),                  # negative noise
    ("correlation_px=300", "correlation_px"),        # longer than the image
    ("dropout_blob_px=0", "dropout_blob_px"),
    ("flying_probability=1.5", "flying_probability"),
    ("hole_probability=nan", "hole_probability"),
    ("subpixel=fast", "subpixel"),
    ("subpixel", "subpixel"),
    ("shadow=0:1", "shadow"),
    ("flying_mix=0.9:0.2", "flying_mix"),
])
def test_bad_sensor_settings_fail_in_one_line_and_write_nothing(tmp_path, capsys, monkeypatch, setting, named):
    monkeypatch.setattr("sys.argv", ["spherebench"])
    out = tmp_path / "ds"
    assert cli.main(["generate", "--preset", "robust", "--n", "2", "--out", str(out), "--quiet",
                     "--sensor", setting]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err
    assert err.startswith("spherebench generate: error: --sensor ") and named in err
    assert list(tmp_path.iterdir()) == []


def test_sensor_settings_that_conflict_fail_before_any_work(tmp_path):
    with pytest.raises(SphereBenchError, match="min_depth_m"):  # drawn per scene: every scene checked first
        simulate.generate_dataset("default", tmp_path / "ds", n=5, progress=False,
                                  sensor_overrides={"min_depth_m": 3.0, "max_depth_m": (1.0, 3.05)})
    with pytest.raises(SphereBenchError, match="given twice"):
        parse_settings(["subpixel=0.1", "subpixel=0.2"])
    assert list(tmp_path.iterdir()) == []


def test_every_parameter_has_a_valid_range_holding_its_default():
    for f in fields(D435Sensor):
        lo, hi = f.metadata["range"]
        values = f.default if isinstance(f.default, tuple) else (f.default,)
        assert all(lo <= v <= hi for v in values), f.name
