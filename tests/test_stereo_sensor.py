"""The stereo sensor model (rendered infrared pair + semi-global matching): small frames."""

from __future__ import annotations

import hashlib
from dataclasses import replace

import numpy as np
import pytest

from spherebench.camera import Intrinsics
from spherebench.datasets import stereo
from spherebench.datasets.primitives import Box, Plane, SolidSphere
from spherebench.datasets.stereo import StereoSensor, stereo_depth, stereo_frame
from spherebench.errors import SphereBenchError

SMALL = Intrinsics.d435(160, 90)  # the D435's aspect: its emitter lights the imagers' field
MEDIUM = Intrinsics.d435(320, 180)
WALL_ALBEDO = StereoSensor(albedo=(0.8, 0.8))


def _wall(z_m: float) -> Plane:
    return Plane(np.array([0.0, 0.0, z_m]), np.array([0.0, 0.0, -1.0]))


def _central(shape):
    h, w = shape
    roi = np.zeros(shape, bool)
    roi[h // 10: h - h // 10, w // 10: w - w // 10] = True
    return roi


def test_flat_wall_is_within_a_few_sigma_and_filled():
    z = 1.3
    depth = stereo_depth([_wall(z)], SMALL, WALL_ALBEDO, np.random.default_rng(0))
    roi = _central(depth.shape)
    ok = roi & (depth > 0)
    err = depth[ok] * 0.001 - z
    sigma = z * z * 0.08 / (SMALL.fx * 0.05)  # Intel's RMS at 0.08 px
    print(f"fill {ok.sum() / roi.sum():.3f}, RMS {np.sqrt(np.mean(err ** 2)) * 1000:.1f} mm, Intel {sigma * 1000:.1f} mm")
    assert ok.sum() / roi.sum() > 0.97
    assert abs(float(np.mean(err))) < sigma
    assert np.sqrt(np.mean(err ** 2)) < 3 * sigma


def test_subpixel_step_removes_sgbm_pixel_locking():
    """A wall at a disparity of n + 0.4 px: SGBM's own parabola answers about n; the refined
    disparity is unbiased to a tenth of a pixel."""
    d_true = 8.4
    z = MEDIUM.fx * 0.05 / d_true
    errors = {}
    for steps in (0, 1):
        frame = stereo_frame([_wall(z)], MEDIUM, replace(WALL_ALBEDO, refine_iterations=steps), np.random.default_rng(1))
        d = frame.disparity_px[_central(frame.depth.shape)]
        errors[steps] = float(np.nanmean(d) - d_true)
    print(errors)
    assert abs(errors[1]) < 0.1
    assert abs(errors[0]) > 0.2  # the lock this step is for


def test_foreground_box_leaves_the_occlusion_band_on_its_left():
    """Background beside a box's left edge that the right imager cannot see is not measured,
    over about f B (1/z_fg - 1/z_bg) px; beside its right edge the wall is measured."""
    z_fg, z_bg, half = 0.6, 1.5, 0.15
    box = Box(np.array([0.0, 0.0, z_fg + 0.05]), np.array([half, half, 0.05]))
    depth = stereo_depth([_wall(z_bg), box], MEDIUM, WALL_ALBEDO, np.random.default_rng(2)) * 0.001
    predicted = MEDIUM.fx * 0.05 * (1 / z_fg - 1 / z_bg)
    u_left = MEDIUM.ppx - MEDIUM.fx * half / z_fg   # the box's edges in the image
    u_right = MEDIUM.ppx + MEDIUM.fx * half / z_fg
    rows = range(int(MEDIUM.ppy) - 10, int(MEDIUM.ppy) + 10)
    wall = np.abs(depth - z_bg) < 0.05 * z_bg

    def run_beside(u_edge: float, step: int) -> float:
        widths = []
        for v in rows:
            u, n = int(np.floor(u_edge)) if step < 0 else int(np.ceil(u_edge)), 0
            while 0 <= u < depth.shape[1] and not wall[v, u]:
                u, n = u + step, n + 1
            widths.append(n)
        return float(np.median(widths))

    left, right = run_beside(u_left, -1), run_beside(u_right, +1)
    print(f"predicted {predicted:.1f} px, left {left}, right {right}")
    assert 0.7 * predicted <= left <= predicted + StereoSensor().block_size_px // 2 + 2
    assert right <= 0.3 * predicted


def test_points_hidden_from_the_emitter_get_ambient_light_only():
    """The emitter, between the imagers, shadows a strip of the wall left of a box: the left
    image is dark there (ambient only) and bright with dots on the lit wall."""
    z_fg, z_bg, half = 0.5, 1.5, 0.15
    box = Box(np.array([0.0, 0.0, z_fg + 0.05]), np.array([half, half, 0.05]))
    sensor = replace(WALL_ALBEDO, ambient_e_per_ms=5.0, auto_exposure=False)
    frame = stereo_frame([_wall(z_bg), box], MEDIUM, sensor, np.random.default_rng(3))
    shadow = MEDIUM.fx * sensor.emitter_x_m * (1 / z_fg - 1 / z_bg)  # its width, px
    u_edge = MEDIUM.ppx - MEDIUM.fx * half / z_fg
    rows = slice(int(MEDIUM.ppy) - 15, int(MEDIUM.ppy) + 15)
    dark = frame.left_ir[rows, int(u_edge - shadow + 1.5):int(u_edge - 1)].astype(float)
    lit = frame.left_ir[rows, int(u_edge - shadow - 25):int(u_edge - shadow - 5)].astype(float)
    ambient = 0.8 * sensor.ambient_e_per_ms * sensor.exposure_ms * sensor.counts_per_e
    print(f"shadow {shadow:.1f} px: dark mean {dark.mean():.1f}, max {dark.max()}, lit mean {lit.mean():.1f}; ambient {ambient:.1f}")
    assert dark.size and abs(dark.mean() - ambient) < 3
    assert lit.mean() > 3 * dark.mean()


def test_auto_exposure_brings_near_and_far_walls_to_the_same_brightness():
    """Within its exposure range (a wall 1.5 m away needs more than 33 ms and stays darker)."""
    means = [stereo_frame([_wall(z)], SMALL, WALL_ALBEDO, np.random.default_rng(4)).left_ir.mean() for z in (0.6, 1.0)]
    assert means == pytest.approx([StereoSensor().ae_mean_counts] * 2, rel=0.05)


def test_same_seed_same_bytes():
    scene = [_wall(2.0), SolidSphere(np.array([0.1, 0.0, 1.2]), 0.12), Box(np.array([-0.4, 0.2, 1.5]), np.array([0.1] * 3))]

    def digest(seed):
        frame = stereo_frame(scene, SMALL, StereoSensor(), np.random.default_rng(seed))
        return hashlib.sha256(frame.depth.tobytes() + frame.left_ir.tobytes() + frame.right_ir.tobytes()).hexdigest()

    assert digest(5) == digest(5)
    assert digest(5) != digest(6)


def test_the_shipped_pattern_is_the_one_its_seed_draws(tmp_path):
    stereo.write_pattern_file(tmp_path / "pattern.npz")  # what `make pattern` writes over the shipped file
    with np.load(stereo.PATTERN_FILE) as shipped, np.load(tmp_path / "pattern.npz") as redrawn:
        assert int(shipped["seed"]) == int(redrawn["seed"]) == stereo.PATTERN_SEED
        assert np.array_equal(shipped["dots"], stereo.draw_pattern(stereo.PATTERN_SEED, stereo.PATTERN_DOTS))
        assert np.array_equal(shipped["dots"], redrawn["dots"])


@pytest.mark.parametrize("changes, words", [
    ({"baseline_m": -0.05}, ["baseline_m", "0.01 to 0.5"]),
    ({"block_size_px": 8}, ["block_size_px", "3 to 21"]),
    ({"mode": "fast"}, ["mode", "sgbm"]),
    ({"albedo": (0.9, 0.2)}, ["albedo", "LO <= HI"]),
    ({"pattern_dots": 2.5}, ["pattern_dots", "integer"]),
    ({"p1": 40.0, "p2": 20.0}, ["p2", "exceed p1"]),
    ({"min_depth_m": 3.0, "max_depth_m": 2.0}, ["min_depth_m", "below"]),
    ({"auto_exposure": 1}, ["auto_exposure", "True or False"]),
])
def test_bad_parameters_are_one_line_errors(changes, words):
    with pytest.raises(SphereBenchError) as err:
        StereoSensor(**changes)
    message = str(err.value)
    assert "\n" not in message and all(w in message for w in words), message


@pytest.mark.parametrize("changes, words", [
    ({"disparity_shift_px": 400}, ["848x480", "disparities 400-526", "outside the valid range", "disparity_shift_px"]),
    ({"pattern_dots": 200}, ["848x480", "200 dots", "9x9 matching window", "raise pattern_dots"]),
])
def test_a_sensor_that_cannot_work_at_the_stream_fails_before_any_work(changes, words):
    rng = np.random.default_rng(0)
    state = rng.bit_generator.state
    with pytest.raises(SphereBenchError) as err:
        stereo_depth([_wall(1.0)], Intrinsics.d435(848, 480), StereoSensor(**changes), rng)
    message = str(err.value)
    assert "\n" not in message and all(w in message for w in words), message
    assert rng.bit_generator.state == state  # nothing drawn, nothing rendered


# ---------------------------------------------------------------- generate --sensor-model stereo

def _files(root) -> dict:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*"))
            if p.is_file() and p.name not in ("dataset.json", "coco_gt.json")}  # these name the folder


def test_generate_stereo_gives_the_same_bytes_for_any_workers_and_records_its_model(tmp_path):
    from spherebench.scripts import cli
    from spherebench.datasets import inout

    for name, workers in (("one", "1"), ("two", "2")):
        assert cli.main(["generate", "--preset", "default", "--n", "2", "--quiet", "--sensor-model", "stereo",
                         "--workers", workers, "--out", str(tmp_path / name)]) == 0
    assert _files(tmp_path / "one") == _files(tmp_path / "two")
    meta = inout.read_dataset_meta(tmp_path / "one")
    assert meta["sensor_model"] == "stereo" and meta["sensor"] == StereoSensor().to_dict()
    gt = inout.read_scene_gt(tmp_path / "one" / "scenes" / "clean_0000")
    assert gt["meta"]["sensor_model"] == "stereo"
    analytic = tmp_path / "analytic"
    assert cli.main(["generate", "--preset", "default", "--n", "2", "--quiet", "--workers", "1",
                     "--out", str(analytic)]) == 0
    assert "sensor_model" not in inout.read_dataset_meta(analytic)  # analytic records read as before
    assert _files(analytic) != _files(tmp_path / "one")


@pytest.mark.parametrize("argv", [["--preset", "robust"], ["--sensor", "subpixel=0.1"]])
def test_generate_stereo_refuses_the_analytic_models_settings(tmp_path, capsys, argv):
    from spherebench.scripts import cli

    assert cli.main(["generate", "--n", "2", "--quiet", "--sensor-model", "stereo", *argv,
                     "--out", str(tmp_path / "ds")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "--sensor-model stereo" in err, err
    assert not (tmp_path / "ds").exists()


# ---------------------------------------------------------------- the stereo twins

def test_stereo_twins_repeat_their_presets_families_with_other_seeds():
    from spherebench.datasets import presets, simulate

    for name in ("default", "hard", "train"):
        base, twin = presets.PRESETS[name], presets.PRESETS[f"{name}-stereo"]
        assert (twin.families, twin.n_default, twin.resolutions) == (base.families, base.n_default, base.resolutions)
        assert twin.sensor_model == "stereo" and twin.twin_of == name and twin.sensor is None
        # its own seed stream, shared only with its renderings at other resolutions (the resolution study)
        assert twin.code not in {p.code for p in presets.PRESETS.values() if p is not twin and p.resolution_of != twin.name}
        assert [f for _i, f, _r in simulate.plan(twin.name, 40)] == [f for _i, f, _r in simulate.plan(name, 40)]
    assert not presets.PRESETS["train-stereo"].clouds and presets.PRESETS["default-stereo"].clouds


def test_train_stereo_draws_each_scenes_unit_inside_its_ranges():
    from spherebench.datasets import presets, rendering

    ranges = presets.PRESETS["train-stereo"].stereo
    stereo.check_stereo_ranges(ranges)
    drawn = [rendering.scene_stereo("train-stereo", 0, i) for i in range(20)]
    for name, (lo, hi) in ranges.items():
        values = [getattr(s, name) for s in drawn]
        assert all(lo <= v <= hi for v in values) and len(set(values)) == 20, name
    assert rendering.scene_stereo("train-stereo", 0, 3) == drawn[3]  # a scene's draw depends on its seed only
    assert rendering.scene_stereo("default-stereo", 0, 3) == StereoSensor()  # no ranges: the nominal unit


@pytest.mark.parametrize("ranges,match", [({"mode": ("sgbm", "hh")}, "not a numeric"),
                                          ({"nonsense": (1, 2)}, "not a numeric"),
                                          ({"read_noise_e": (5.0, 2.0)}, "LO <= HI"),
                                          ({"read_noise_e": 3.0}, "LO <= HI"),
                                          ({"read_noise_e": (1.0, 500.0)}, "from 0 to 100")])
def test_bad_stereo_ranges_are_one_line_errors(ranges, match):
    with pytest.raises(SphereBenchError, match=match) as err:
        stereo.check_stereo_ranges(ranges)
    assert "\n" not in str(err.value)


def test_a_stereo_twin_refuses_the_analytic_model_and_records_its_draws(tmp_path, capsys):
    from spherebench.scripts import cli
    from spherebench.datasets import inout, presets

    assert cli.main(["generate", "--preset", "default-stereo", "--sensor-model", "analytic", "--n", "2", "--quiet",
                     "--out", str(tmp_path / "no")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "--preset default" in err and not (tmp_path / "no").exists()
    assert cli.main(["generate", "--preset", "train-stereo", "--n", "2", "--quiet", "--workers", "1",
                     "--out", str(tmp_path / "ts")]) == 0
    meta = inout.read_dataset_meta(tmp_path / "ts")
    assert (meta["sensor_model"], meta["twin_of"], meta["clouds"]) == ("stereo", "train", False)
    ranges = presets.PRESETS["train-stereo"].stereo
    assert set(meta["stereo_ranges"]) == set(ranges)
    scene = sorted((tmp_path / "ts" / "scenes").iterdir())[1]
    gt = inout.read_scene_gt(scene)
    assert gt["meta"]["sensor_model"] == "stereo" and not (scene / "cloud.ply").exists()
    for name, (lo, hi) in ranges.items():
        assert lo <= gt["meta"]["sensor"][name] <= hi
