"""The holed family: a ball whose depth is missing over 30-70 % of its face, in either sensor model."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from spherebench.datasets import families, inout, presets, rendering, simulate
from spherebench.datasets.sensor import D435Sensor
from spherebench.datasets.stereo import StereoSensor
from test_stereo_sensor import _files


def _scenes(preset: str, n: int, resolution: str = "424x240"):
    """The first n scenes of a preset at one resolution (the stereo model is slow at 848x480)."""
    sensor = StereoSensor() if preset.endswith("-stereo") else D435Sensor()
    jobs = [job for job in simulate.plan(preset, 20) if job[2] == resolution][:n]
    return [rendering.simulate_scene(preset, i, family, 0, res, sensor=sensor) for i, family, res in jobs]


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
    monkeypatch.setattr(rendering, "punch_hole", lambda *args: 0.0)
    whole = _scenes(preset, 1)[0]
    a, b = holed.balls[0], whole.balls[0]
    assert np.array_equal(a.mask, b.mask) and np.array_equal(a.silhouette, b.silhouette)
    assert a.centre_m == b.centre_m and a.amodal_circle_px == b.amodal_circle_px
    assert a.circle_px == b.circle_px and a.visible_fraction == b.visible_fraction
    changed = holed.depth != whole.depth
    assert changed.any() and not (changed & ~a.mask).any() and not holed.depth[changed].any()


def test_other_families_record_no_hole():
    scene = rendering.simulate_scene("default", 0, "clean", 0, "424x240")
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
    assert not presets.PRESETS["holes"].benchmark and not presets.PRESETS["holes-stereo"].benchmark
    assert presets.PRESETS["holes-stereo"].twin_of == "holes"


def test_trains_share_of_holes_leaves_its_whole_scenes_as_they_were(monkeypatch):
    """train gives a fifth of its clean and cluttered scenes a hole from a stream of its own: with
    the share set to none, those scenes lose their hole only, and every other scene is unchanged."""
    jobs = [job for job in simulate.plan("train", 400) if job[1] in ("clean", "cluttered")
            and job[2] == "424x240"][:30]
    holed = [rendering.simulate_scene("train", i, f, 0, r) for i, f, r in jobs]
    monkeypatch.setitem(presets.PRESETS, "train",
                        dataclasses.replace(presets.PRESETS["train"], holes=()))
    whole = [rendering.simulate_scene("train", i, f, 0, r) for i, f, r in jobs]
    with_hole = [a for a in holed if "hole_fraction" in a.meta]
    assert 2 <= len(with_hole) <= 14, len(with_hole)  # a fifth of 30, loosely
    for a, b in zip(holed, whole):
        assert "hole_fraction" not in b.meta and a.balls[0].centre_m == b.balls[0].centre_m
        changed = a.depth != b.depth
        if "hole_fraction" in a.meta:
            assert 0.3 <= a.meta["hole_fraction"][0] <= 0.7
            assert changed.any() and not (changed & ~a.balls[0].mask).any() and not a.depth[changed].any()
        else:
            assert not changed.any()


# ------------------------------------------------------------------------ the detector's hole search

def _holed_frame(centre=(0.1, -0.05, 1.5), hole_fraction=0.5, wall_z=2.6, ball=True, noise=0.002, seed=0):
    """A 424x240 frame of a wall and a ball whose depth is missing over a centred disc holding
    ``hole_fraction`` of its image (ball=False: the same hole punched in the wall alone)."""
    from spherebench.cloud import cloud_from_depth
    from test_method_detector import scene

    cloud = scene(ball_c=tuple(centre) if ball else None, wall_z=wall_z, noise=noise, seed=seed, width=424, height=240)
    intr = cloud.intrinsics
    z = np.full(intr.shape, np.nan, np.float32)
    z[cloud.rows, cloud.cols] = cloud.points[:, 2]
    u0, v0 = intr.fx * centre[0] / centre[2] + intr.ppx, intr.fy * centre[1] / centre[2] + intr.ppy
    r_px = intr.fx * 0.12 / centre[2]
    vs, us = np.mgrid[: intr.height, : intr.width]
    z[np.hypot(us - u0, vs - v0) <= np.sqrt(hole_fraction) * r_px] = np.nan
    return cloud_from_depth(z, intr), (u0, v0, r_px)


def test_the_hole_search_finds_a_ringed_hole_and_not_one_in_a_wall():
    """``_kernels.hole_hypotheses``: a ball with its middle missing gives a hypothesis within a third
    of its disc radius of its image's centre and R of its front range; the same hole in the wall none."""
    from spherebench.method import config_for
    from spherebench.method import search as search_stage
    from spherebench.method.detector import prepare_frame

    cfg = config_for("improved")
    for centre in ((0.1, -0.05, 1.5), (-0.3, 0.1, 0.9), (0.2, 0.05, 2.3)):
        for fraction in (0.3, 0.7):
            cloud, (u0, v0, r_px) = _holed_frame(centre, fraction, wall_z=centre[2] + 1.0)
            frame = prepare_frame(cloud, cfg)
            centres, _scores, _occluded = search_stage.hole_search(frame, cfg)
            intr = cloud.intrinsics
            hu = intr.fx * centres[:, 0] / centres[:, 2] + intr.ppx
            hv = intr.fy * centres[:, 1] / centres[:, 2] + intr.ppy
            assert math.hypot(hu[0] - u0, hv[0] - v0) < r_px / 3, (centre, fraction)
            assert abs(np.linalg.norm(centres[0]) - np.linalg.norm(centre)) < 0.12, (centre, fraction)
            wall, _ = _holed_frame(centre, fraction, wall_z=centre[2] + 1.0, ball=False)
            assert len(search_stage.hole_search(prepare_frame(wall, cfg), cfg)[0]) == 0, (centre, fraction)


def test_the_hole_retry_finds_balls_whose_middle_is_missing():
    """Balls with 30-70 % of their face missing around the middle: the searches before the hole retry
    lose every one, with it each is found within 1 cm; a wall with the hole stays empty."""
    from spherebench.method import config_for, detect

    without = config_for("improved", retry={"retry_hole": False})
    for k, (centre, fraction) in enumerate([((0.1, -0.05, 1.5), 0.5), ((-0.3, 0.1, 0.9), 0.7),
                                            ((0.2, 0.05, 2.3), 0.4), ((0.0, 0.0, 1.2), 0.6)]):
        cloud, _ = _holed_frame(centre, fraction, wall_z=centre[2] + 1.0, seed=k)
        assert detect(cloud, without, seed=0) == [], (centre, fraction)
        (found,) = detect(cloud, seed=0)
        assert np.linalg.norm(np.subtract(found.centre_m, centre)) < 0.01, (centre, fraction)
        wall, _ = _holed_frame(centre, fraction, wall_z=centre[2] + 1.0, ball=False, seed=k)
        assert detect(wall, seed=0) == []


def test_hard_holds_twenty_holed_balls_after_its_first_140_scenes():
    """hard's holed family comes last: its first 140 scenes keep the families and resolutions they had
    with seven families (blocks of 20), and the stereo twin has the same plan."""
    jobs = simulate.plan("hard")
    assert len(jobs) == 160 and [f for _i, f, _r in jobs[140:]] == ["holed"] * 20
    assert [f for _i, f, _r in jobs[:140]] == [f for f in families.HARD_FAMILIES for _ in range(20)]
    rng = np.random.default_rng([presets.PRESETS["hard"].code, 0, 7])  # plan's resolution stream
    names, shares = zip(*presets.PRESETS["hard"].resolutions)
    before = rng.choice(names, size=140, p=np.asarray(shares) / sum(shares))
    assert [r for _i, _f, r in jobs[:140]] == [str(r) for r in before]
    assert [f for _i, f, _r in simulate.plan("hard-stereo")] == [f for _i, f, _r in jobs]
