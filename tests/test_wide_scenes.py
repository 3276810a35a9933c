"""The wide scene grammar: its geometry, its surfaces in the stereo model, its presets' bytes."""

from __future__ import annotations

import hashlib
import math

import numpy as np
import pytest

from spherebench.camera import Intrinsics
from spherebench.datasets import presets, rendering, wide_scenes
from spherebench.datasets.layouts import Layout
from spherebench.datasets.primitives import Box, Cylinder, Plane, SolidSphere, Texture
from spherebench.datasets.stereo import StereoSensor, stereo_frame
from test_stereo_sensor import _files

INTR = Intrinsics.d435(424, 240)
SEEDS = range(12)


def _sha(scene) -> str:
    return hashlib.sha256(scene.depth.tobytes()).hexdigest()


def test_existing_presets_keep_their_bytes():
    # hashes of the depth frames built by the code before the wide grammar
    assert _sha(rendering.simulate_scene("default", 150, "cluttered", 0, "424x240")) \
        == "f00d5baf3d735dd3ecda7771efdf1a958c3590197b57570c7dc533b6bf678663"
    assert _sha(rendering.simulate_scene("paper", 0, "E3", 0, "424x240")) \
        == "e7ecfad58f47b6f342fb49a93098c7b5e2dc41b2af0eed6815236dcd234534ec"
    assert _sha(rendering.simulate_scene("default-stereo", 150, "cluttered", 0, "424x240", sensor=StereoSensor())) \
        == "e285cbf3ad6551448968641c5c3078055906f88cc728af4d1f862f864ee7a9a2"


def _gap_m(shape, centre: np.ndarray, radius: float) -> float:
    """Distance from a ball's surface to a primitive's (inf for planes)."""
    if isinstance(shape, Box):
        local = np.asarray(shape.rotation).T @ (centre - shape.centre_m)
        return float(np.linalg.norm(np.maximum(np.abs(local) - shape.half_size_m, 0))) - radius
    if isinstance(shape, Cylinder):
        a = shape.axis / np.linalg.norm(shape.axis)
        rel = centre - shape.base_m
        s = rel @ a
        rho = np.linalg.norm(rel - s * a)
        return math.hypot(max(-s, s - shape.height_m, 0), max(rho - shape.radius_m, 0)) - radius
    if isinstance(shape, SolidSphere):
        return float(np.linalg.norm(centre - shape.centre_m)) - shape.radius_m - radius
    return math.inf


def _layouts():
    return [(name, wide_scenes.FAMILIES[name](np.random.default_rng([seed, 31]), INTR, 0.12))
            for name in wide_scenes.FAMILIES for seed in SEEDS]


def test_wide_scenes_rest_the_ball_on_its_support_in_a_pitched_and_rolled_view():
    near, positives, tilted, distractors = 0, 0, 0, 0
    for name, layout in _layouts():
        m = layout.meta
        assert wide_scenes.PITCH_DEG[0] <= m["camera_pitch_deg"] <= wide_scenes.PITCH_DEG[1]
        assert wide_scenes.ROLL_DEG[0] <= m["camera_roll_deg"] <= wide_scenes.ROLL_DEG[1]
        assert wide_scenes.HEIGHT_M[0] <= m["camera_height_m"] <= wide_scenes.HEIGHT_M[1]
        assert m["support"] == name or name == "negative"
        floor = next(it.shape for it in layout.items if it.kind == "floor")
        assert abs(floor.point_m @ floor.normal) == pytest.approx(m["camera_height_m"], abs=1e-9)
        tilted += abs(floor.normal[1]) < 0.999  # the level frame turned into the camera's
        for it in layout.items:
            if it.kind == "distractor":
                distractors += 1
                assert any(lo <= it.shape.radius_m <= hi for lo, hi in wide_scenes.DISTRACTOR_RADII_M)
        targets = [it.shape for it in layout.items if it.kind == "target"]
        assert len(targets) == (name != "negative")
        if not targets:
            continue
        positives += 1
        c, r = np.asarray(targets[0].centre_m), targets[0].radius_m
        assert 0.39 <= np.linalg.norm(c) - r <= 4.01
        if name in ("floor", "wall"):  # on the floor: its centre one radius above the floor plane
            assert abs((c - floor.point_m) @ floor.normal) == pytest.approx(r, abs=1e-3)
        if name == "wall":
            back = [it.shape for it in layout.items if it.kind == "wall"][0]
            assert abs((c - back.point_m) @ back.normal) == pytest.approx(r, abs=1e-3)
        # an item (apart from the one it rests on) within a ball's diameter of the ball
        near += any(0.005 < _gap_m(it.shape, c, r) <= 0.24 for it in layout.items
                    if it.kind not in ("target", "floor", "wall"))
    assert tilted >= 0.9 * len(SEEDS) * len(wide_scenes.FAMILIES)
    assert near >= 0.75 * positives and distractors > 0


def test_wide_scenes_have_low_albedo_and_textured_surfaces():
    items = [it for _name, layout in _layouts() for it in layout.items]
    low = [it.albedo for it in items if it.albedo is not None]
    assert 0.1 * len(items) < len(low) and all(wide_scenes.LOW_ALBEDO[0] <= a <= wide_scenes.LOW_ALBEDO[1] for a in low)
    textured = [it.texture for it in items if it.texture is not None]
    assert 0.1 * len(items) < len(textured) and {t.pattern for t in textured} == {"stripes", "checks", "noise"}
    assert all(wide_scenes.TEXTURE_SCALE_M[0] <= t.scale_m <= wide_scenes.TEXTURE_SCALE_M[1] for t in textured)


def _wall(**surface) -> Layout:
    layout = Layout()
    layout.add(Plane(np.array([0.0, 0.0, 1.5]), np.array([0.0, 0.0, -1.0])), "wall")
    for k, v in surface.items():
        setattr(layout.items[0], k, v)
    return layout


def test_the_stereo_model_images_an_items_texture_and_albedo():
    ambient = StereoSensor(dot_peak_e_per_ms=0.0, albedo=(0.8, 0.8))  # ambient light only: no dots
    small = Intrinsics.d435(160, 90)
    plain = stereo_frame(_wall(), small, ambient, np.random.default_rng(0)).left_ir.astype(float)
    stripes = Texture("stripes", 0.05, 0.8, (1.0, 0.0, 0.0))
    textured = stereo_frame(_wall(texture=stripes), small, ambient, np.random.default_rng(0)).left_ir.astype(float)
    assert textured.var() > 5 * plain.var()
    fixed = StereoSensor(dot_peak_e_per_ms=0.0, albedo=(0.8, 0.8), auto_exposure=False)  # no exposure to undo it
    dark = stereo_frame(_wall(albedo=0.1), small, fixed, np.random.default_rng(0)).left_ir.astype(float)
    bright = stereo_frame(_wall(), small, fixed, np.random.default_rng(0)).left_ir.astype(float)
    assert dark.mean() < 0.2 * bright.mean()
    # a layout whose items set nothing renders as its list of primitives did
    scene = _wall()
    scene.add(SolidSphere(np.array([0.0, 0.0, 1.0]), 0.12), "target")
    a = stereo_frame(scene, small, StereoSensor(), np.random.default_rng(1)).depth
    b = stereo_frame([it.shape for it in scene.items], small, StereoSensor(), np.random.default_rng(1)).depth
    assert np.array_equal(a, b)


def test_generate_wide_gives_the_same_bytes_for_any_workers_and_records_its_grammar(tmp_path):
    from spherebench.scripts import cli
    from spherebench.datasets import inout

    for name, workers in (("one", "1"), ("two", "2")):
        assert cli.main(["generate", "--preset", "wide", "--n", "4", "--quiet", "--no-clouds",
                         "--workers", workers, "--out", str(tmp_path / name)]) == 0
    assert _files(tmp_path / "one") == _files(tmp_path / "two")
    assert inout.read_dataset_meta(tmp_path / "one")["grammar"] == "wide"
    for scene in sorted((tmp_path / "one" / "scenes").iterdir()):
        meta = inout.read_scene_gt(scene)["meta"]
        assert meta["support"] in wide_scenes.SUPPORTS and "distractors" in meta
        assert {"camera_pitch_deg", "camera_roll_deg", "camera_height_m"} <= set(meta)


def test_wide_stereo_is_its_twin_and_deterministic():
    twin = presets.PRESETS["wide-stereo"]
    assert (twin.families, twin.twin_of, twin.sensor_model, twin.grammar) == \
        (presets.PRESETS["wide"].families, "wide", "stereo", "wide")
    a, b = (rendering.simulate_scene("wide-stereo", 1, "shelf", 0, "424x240", sensor=StereoSensor()) for _ in range(2))
    assert np.array_equal(a.depth, b.depth) and a.balls and a.balls[0].visible_fraction >= 0.5
