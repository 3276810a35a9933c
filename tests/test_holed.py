"""The holed family: a ball whose depth is missing over 30-70 % of its face, in either sensor model."""

from __future__ import annotations

import numpy as np
import pytest

from spherebench.datasets import inout, simulate
from spherebench.datasets.stereo import StereoSensor
from test_stereo_sensor import _files


def _scenes(preset: str, n: int, resolution: str = "424x240"):
    """The first n scenes of a preset at one resolution (the stereo model is slow at 848x480)."""
    sensor = StereoSensor() if preset.endswith("-stereo") else simulate.D435Sensor()
    jobs = [job for job in simulate.plan(preset, 20) if job[2] == resolution][:n]
    return [simulate.simulate_scene(preset, i, family, 0, res, sensor=sensor) for i, family, res in jobs]


@pytest.mark.parametrize("preset", ["holes", "holes-stereo"])
def test_the_hole_takes_30_to_70_percent_of_the_balls_valid_pixels(preset):
    for scene in _scenes(preset, 3):
        (ball,), (fraction,) = scene.balls, scene.meta["hole_fraction"]
        before, after = int(ball.mask.sum()), int((ball.mask & (scene.depth > 0)).sum())
        assert before > 50 and fraction == pytest.approx(1 - after / before)
        assert 0.3 <= fraction <= 0.7, (scene.scene_id, fraction)
        # a ring of valid depth stays: valid ball pixels lie on the rim all round the hole
        vs, us = np.nonzero(ball.mask & (scene.depth > 0))
        cx, cy, _r = ball.amodal_circle_px
        sectors = np.floor((np.arctan2(vs - cy, us - cx) + np.pi) / (np.pi / 4)).astype(int) % 8
        assert set(sectors.tolist()) == set(range(8)), scene.scene_id


@pytest.mark.parametrize("preset", ["holes", "holes-stereo"])
def test_the_hole_leaves_the_balls_ground_truth_as_it_was(preset, monkeypatch):
    """The mask, silhouette, circles and centre are those of the scene without its hole (a sensor
    effect), and the depth differs only on the hole's pixels, inside the mask."""
    holed = _scenes(preset, 1)[0]
    monkeypatch.setattr(simulate, "punch_hole", lambda *args: 0.0)
    whole = _scenes(preset, 1)[0]
    a, b = holed.balls[0], whole.balls[0]
    assert np.array_equal(a.mask, b.mask) and np.array_equal(a.silhouette, b.silhouette)
    assert a.centre_m == b.centre_m and a.amodal_circle_px == b.amodal_circle_px
    assert a.circle_px == b.circle_px and a.visible_fraction == b.visible_fraction
    changed = holed.depth != whole.depth
    assert changed.any() and not (changed & ~a.mask).any() and not holed.depth[changed].any()


def test_other_families_record_no_hole():
    scene = simulate.simulate_scene("default", 0, "clean", 0, "424x240")
    assert "hole_fraction" not in scene.meta


def test_holes_generates_the_same_bytes_for_any_workers_and_records_the_fraction(tmp_path):
    one = simulate.generate_dataset("holes", tmp_path / "one", n=4, workers=1, progress=False)
    two = simulate.generate_dataset("holes", tmp_path / "two", n=4, workers=2, progress=False)
    assert _files(one) == _files(two)
    for scene_dir in sorted((one / "scenes").iterdir()):
        gt = inout.read_scene_gt(scene_dir)
        assert len(gt["meta"]["hole_fraction"]) == len(gt["balls"]) == 1
        assert 0.3 <= gt["meta"]["hole_fraction"][0] <= 0.7
        scene = inout.read_scene(scene_dir)
        mask = scene.balls[0].mask
        assert gt["meta"]["hole_fraction"][0] == pytest.approx(1 - (mask & (scene.depth > 0)).sum() / mask.sum())
    assert not simulate.PRESETS["holes"].benchmark and not simulate.PRESETS["holes-stereo"].benchmark
    assert simulate.PRESETS["holes-stereo"].twin_of == "holes"
