"""The D435 simulator: exact ground truth, the sensor model's noise, determinism."""

from __future__ import annotations

import filecmp
import json
import math
import os
import platform
from dataclasses import replace

import numpy as np
import pytest

from spherebench.camera import Intrinsics, image_rays
from spherebench.circles import mask_circle, norm3, sphere_circle_amodal, sphere_silhouette_mask
from spherebench.datasets import families, inout, presets, rendering, sequences, simulate
from spherebench.datasets.layouts import Layout
from spherebench.datasets.primitives import Box, Cylinder, Plane, SolidSphere, raycast
from spherebench.datasets.sensor import D435Sensor, apply_sensor, shadow_mask
from spherebench.errors import SphereBenchError

QUIET = D435Sensor(hole_probability=0.0, hole_blobs_per_mpx=0.0, flying_probability=0.0)


def _wall(z_m: float) -> Layout:
    layout = Layout()
    layout.add(Plane(np.array([0.0, 0.0, z_m]), np.array([0.0, 0.0, -1.0])), "wall")
    return layout


@pytest.mark.parametrize("z_m", [1.0, 3.0])
def test_wall_noise_matches_intels_stereo_model(z_m):
    """Depth noise on a flat wall facing the camera is sigma_z = z^2 subpixel / (f B), within 20 %."""
    intr = Intrinsics.d435(424, 240)
    depth, z_true, _ = rendering.render(_wall(z_m), intr, QUIET, np.random.default_rng(1))
    valid = depth > 0
    err = depth[valid] * intr.depth_scale - z_true[valid]
    expected = QUIET.sigma_z_m(z_m, intr.fx)
    measured = float(np.std(err))
    print(f"wall at {z_m} m: sigma measured {measured * 1000:.2f} mm, model {expected * 1000:.2f} mm")
    assert abs(measured - expected) <= 0.2 * expected
    assert abs(float(np.mean(err))) < 0.1 * expected  # unbiased


def test_raycast_primitives_hit_where_geometry_says():
    intr = Intrinsics.d435(424, 240)
    rays = image_rays(intr)
    objs = [Plane(np.array([0, 0, 4.0]), np.array([0, 0, -1.0])),
            SolidSphere(np.array([0.0, 0.0, 2.0]), 0.12),
            Box(np.array([-0.6, 0.0, 2.0]), np.array([0.1, 0.1, 0.1])),
            Cylinder(np.array([0.6, 0.3, 2.0]), np.array([0.0, -1.0, 0.0]), 0.1, 0.6)]
    z, label = raycast(objs, rays, intr)
    cv, cu = round(intr.ppy), round(intr.ppx)
    assert label[cv, cu] == 2 and z[cv, cu] == pytest.approx(2.0 - 0.12, abs=1e-3)
    u_box = round(intr.ppx + intr.fx * -0.6 / 1.9)
    assert label[cv, u_box] == 3 and z[cv, u_box] == pytest.approx(1.9, abs=1e-9)
    u_cyl = round(intr.ppx + intr.fx * 0.6 / 1.9)
    assert label[cv, u_cyl] == 4 and 1.9 <= z[cv, u_cyl] < 1.92
    assert label[0, 0] == 1 and z[0, 0] == pytest.approx(4.0)


def test_shadow_band_lies_left_of_foreground_and_has_the_stereo_width():
    """Background the right imager cannot see: f B (1/z_fg - 1/z_bg) pixels left of the edge."""
    intr = Intrinsics.d435(424, 240)
    layout = _wall(3.0)
    layout.add(Box(np.array([0.2, 0.0, 1.0]), np.array([0.2, 0.5, 0.01])), "clutter")
    z, _ = raycast([it.shape for it in layout.items], image_rays(intr), intr)
    hidden = shadow_mask(z, intr.fx, 0.05)
    row = hidden[round(intr.ppy)]
    edge = int(np.argmax(z[round(intr.ppy)] < 2))  # first foreground column
    width = intr.fx * 0.05 * (1 / (1.0 - 0.01) - 1 / 3.0)
    assert not row[edge:].any()  # nothing hidden on or right of the object's left edge... on its face
    band = np.nonzero(row[:edge])[0]
    assert band.max() == edge - 1
    assert abs(len(band) - width) <= 1.5


def test_unoccluded_ball_mask_circle_matches_the_analytic_silhouette(paper_dataset, small_default):
    """The GT circle (smallest enclosing circle of the visible mask) is within 1 px of the
    sphere's analytic silhouette (an ellipse: centre and semi-major axis)."""
    worst = 0.0
    n = 0
    for ds in (paper_dataset, small_default):
        for scene_dir in inout.list_scenes(ds):
            scene = inout.read_scene(scene_dir)
            for ball in scene.balls:
                if ball.visible_fraction < 0.97:
                    continue  # a tripod cup hides the lowest rim
                cx, cy, r = ball.circle_px
                ax, ay, ar = sphere_circle_amodal(scene.intrinsics, ball.centre_m, ball.radius_m)
                worst = max(worst, math.hypot(cx - ax, cy - ay), abs(r - ar))
                n += 1
    print(f"{n} unoccluded balls: worst centre/radius deviation {worst:.3f} px")
    assert n >= 3 and worst <= 1.0


def test_silhouette_rasterisation_agrees_with_the_analytic_ellipse_off_axis():
    intr = Intrinsics.d435(848, 480)
    for centre in ([0.0, 0.0, 1.0], [0.9, 0.4, 1.3], [-1.0, -0.5, 1.2], [0.3, 0.1, 4.0]):
        cx, cy, r = mask_circle(sphere_silhouette_mask(intr, centre, 0.12))
        ax, ay, ar = sphere_circle_amodal(intr, centre, 0.12)
        # an ellipse's enclosing circle rests on its two major-axis ends: discretisation moves it
        assert math.hypot(cx - ax, cy - ay) <= 1.0 and abs(r - ar) <= 1.0


def test_visible_mask_is_first_surface_and_valid_depth(paper_dataset):
    scene = inout.read_scene(paper_dataset / "scenes" / "E2")
    ball = scene.balls[0]
    assert not (ball.mask & (scene.depth == 0)).any()
    assert (ball.mask <= ball.silhouette).all()
    assert ball.visible_fraction == pytest.approx(ball.mask.sum() / ball.silhouette.sum())


def test_hard_families_meet_their_visibility_rules():
    occ = rendering.simulate_scene("hard", 3, "occluded", 0, "424x240")
    assert 0.4 <= occ.balls[0].visible_fraction <= 0.7
    out = rendering.simulate_scene("hard", 4, "out_of_frame", 0, "424x240")
    assert 0.3 <= out.balls[0].visible_fraction <= 0.85
    neg = rendering.simulate_scene("hard", 1, "negative", 0, "848x480")
    assert neg.balls == [] and neg.depth.shape == (480, 848)
    two = rendering.simulate_scene("hard", 6, "two", 0, "424x240")
    assert len(two.balls) == 2
    dis = rendering.simulate_scene("hard", 0, "distractor", 0, "424x240")
    assert dis.meta["distractors"] and all(d["radius_m"] != 0.12 for d in dis.meta["distractors"])


def test_same_seed_same_bytes_any_worker_count(tmp_path):
    a = simulate.generate_dataset("default", tmp_path / "a" / "ds", n=4, seed=5, progress=False, workers=1)
    b = simulate.generate_dataset("default", tmp_path / "b" / "ds", n=4, seed=5, progress=False, workers=2)
    c = simulate.generate_dataset("default", tmp_path / "c" / "ds", n=4, seed=6, progress=False, workers=1)
    files = sorted(p.relative_to(a) for p in a.rglob("*") if p.is_file())
    assert files == sorted(p.relative_to(b) for p in b.rglob("*") if p.is_file())
    for f in files:
        assert filecmp.cmp(a / f, b / f, shallow=False), f
    assert not filecmp.cmp(a / "coco_gt.json", c / "coco_gt.json", shallow=False)


def test_train_seeds_are_disjoint_from_every_evaluation_preset():
    train = {presets.generation_seed(presets.PRESETS["train"], 0, i) for i in range(2000)}
    for name in ("default", "paper", "hard"):
        evaluation = {presets.generation_seed(presets.PRESETS[name], s, i) for s in range(3) for i in range(300)}
        assert not train & evaluation


def test_coco_gt_has_circlenet_fields(small_default):
    coco = json.loads((small_default / "coco_gt.json").read_text())
    assert len(coco["images"]) == 6 and len(coco["annotations"]) == 6
    ann = coco["annotations"][0]
    r = ann["circle_radius"]
    assert ann["area"] == pytest.approx(math.pi * r * r)
    assert ann["iscrowd"] == 0 and ann["category_id"] == 1 and len(ann["circle_center"]) == 2
    assert "amodal_circle_radius" in ann and len(ann["center_m"]) == 3
    assert coco["categories"] == [{"id": 1, "name": "basketball", "supercategory": "ball"}]
    assert {im["family"] for im in coco["images"]} == {"clean", "cluttered"}


def test_scene_cloud_is_the_deprojected_depth(paper_dataset):
    scene_dir = paper_dataset / "scenes" / "E1"
    scene = inout.read_scene(scene_dir)
    cloud = inout.load_cloud(scene_dir)
    assert cloud.organised and len(cloud) == int((scene.depth > 0).sum())
    z = scene.depth[cloud.rows, cloud.cols] * 0.001
    np.testing.assert_allclose(cloud.points[:, 2], z, rtol=1e-6)
    intr = scene.intrinsics
    np.testing.assert_allclose(cloud.points[:, 0], (cloud.cols - intr.ppx) / intr.fx * z, rtol=1e-5, atol=1e-6)


def test_bad_generate_arguments_raise_one_line_errors(tmp_path):
    with pytest.raises(SphereBenchError, match="unknown preset"):
        simulate.generate_dataset("nope", tmp_path / "x")
    with pytest.raises(SphereBenchError, match="number of scenes"):
        simulate.generate_dataset("default", tmp_path / "x", n=0)
    with pytest.raises(SphereBenchError, match="ball radius"):
        simulate.generate_dataset("default", tmp_path / "x", n=1, radius_m=-1)
    assert not (tmp_path / "x").exists()


def test_sensor_range_limits_invalidate_out_of_range_depth():
    intr = Intrinsics.d435(424, 240)
    near = apply_sensor(np.full(intr.shape, 0.05), intr, QUIET, np.random.default_rng(0))
    far = apply_sensor(np.full(intr.shape, 12.0), intr, replace(QUIET, subpixel=0.0), np.random.default_rng(0))
    assert (near == 0).all() and (far == 0).all()


@pytest.mark.skipif(platform.machine() not in ("x86_64", "AMD64"), reason="OpenBLAS core types are x86's")
def test_generated_scenes_do_not_depend_on_the_blas_kernel(tmp_path):
    """The same seed gives the same bytes whichever kernel OpenBLAS picks for the CPU (machines differ
    in it): the simulator's geometry uses no BLAS product (``circles.norm3``). Two kernels every
    x86-64 CPU of this century runs, forced in fresh processes."""
    import subprocess
    import sys

    outs = []
    for core in ("Haswell", "Prescott"):
        out = tmp_path / core
        code = ("from spherebench.datasets import simulate\n"
                f"simulate.generate_dataset('train', {str(out)!r}, n=30, progress=False)\n")
        subprocess.run([sys.executable, "-c", code], check=True, env={**os.environ, "OPENBLAS_CORETYPE": core})
        outs.append(out / "scenes")
    names = sorted(p.name for p in outs[0].iterdir())
    assert names == sorted(p.name for p in outs[1].iterdir()) and len(names) == 30
    for name in names:
        for f in sorted((outs[0] / name).iterdir()):
            assert filecmp.cmp(f, outs[1] / name / f.name, shallow=False), f"{name}/{f.name}"


def test_norm3_is_the_vector_norm():
    rng = np.random.default_rng(3)
    for v in rng.normal(size=(100, 3)) * 10.0 ** rng.integers(-3, 3, size=(100, 1)):
        assert norm3(v) == pytest.approx(float(np.linalg.norm(v)), rel=1e-15)


def _same_tree(a, b) -> bool:
    """Two folders hold the same files with the same bytes."""
    cmp = filecmp.dircmp(a, b)
    if cmp.left_only or cmp.right_only or filecmp.cmpfiles(a, b, cmp.common_files, shallow=False)[1:] != ([], []):
        return False
    return all(_same_tree(os.path.join(a, d), os.path.join(b, d)) for d in cmp.common_dirs)


def test_the_hard_sensor_preset_is_hard_under_its_sensor_settings(tmp_path):
    """`--preset hard-sensor` builds, byte for byte, what `--preset hard --sensor ...` built."""
    variant = simulate.generate_dataset("hard-sensor", tmp_path / "a" / "hard-sensor", n=3, progress=False)
    flags = simulate.generate_dataset("hard", tmp_path / "b" / "hard-sensor", n=3, progress=False,
                                      sensor_overrides={"subpixel": (0.05, 0.20), "correlation_px": (0.0, 1.0),
                                                        "dropout_probability": (0.0, 0.5)})
    assert _same_tree(variant, flags)
    assert inout.read_dataset_meta(variant)["sensor_overrides"]["subpixel"] == [0.05, 0.2]
    assert simulate.plan("hard-sensor", 5) == simulate.plan("hard", 5)


def test_presets_and_families_are_registered():
    assert presets.benchmark_presets() == ("default", "hard", "robust", "wide", "default-stereo", "hard-stereo",
                                            "wide-stereo")
    assert presets.preset_with_role(presets.PRESET_PROTOCOL) == "default"
    for preset in presets.PRESETS.values():  # every preset's families are built by its grammar
        built = (lambda f: f in sequences.SEQUENCE_FAMILIES) if preset.grammar == "motion" else \
            (lambda f: (preset.grammar, f) in families.FAMILIES)
        assert all(built(f) for f, _share in preset.families), preset.name
    with pytest.raises(ValueError, match="registered already"):
        presets.register_preset(presets.PRESETS["default"])
    with pytest.raises(ValueError, match="registered already"):
        families.register_family("classic", "clean", lambda vis: True)(families.family_clean)
