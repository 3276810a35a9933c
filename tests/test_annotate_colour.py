"""Ground truth from colour: the colour rule, LabelMe polygons, the mask-fit reference centre,
`spherebench annotate`, prepare keeping the colour frame, and the committed Kinect annotations."""

from __future__ import annotations

import hashlib
import json
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from spherebench.camera import Intrinsics, deproject, image_rays
from spherebench.circles import mask_circle, sphere_silhouette_mask
from spherebench.scripts.cli import main
from spherebench.datasets import foreign_formats, inout
from spherebench.datasets.annotate import (balls_from_labelme, colour_mask, fit_sphere_fixed_radius,
                                           labelme_from_mask, labelme_text, mask_fit_centre, parse_hsv)
from spherebench.datasets.scene import Scene
from spherebench.errors import SphereBenchError

REPO = Path(__file__).resolve().parents[1]
REALDATA = REPO.parent / "shared" / "realdata"
ANNOTATIONS = REPO / "datasets" / "annotations" / "kinect-pochang"
CAM = Intrinsics(width=160, height=120, ppx=80.0, ppy=60.0, fx=260.0, fy=260.0, depth_scale=0.001)
R = 0.2
CENTRE = (0.05, -0.02, 1.6)


def sphere_depth(intr=CAM, centre=CENTRE, radius=R, wall_m=3.0) -> np.ndarray:
    """(H, W) metres: a sphere in front of a wall, exact (the first hit along each pixel's ray)."""
    rays = image_rays(intr).reshape(-1, 3)
    c = np.asarray(centre)
    b = rays @ c
    disc = b * b - (rays * rays).sum(1) * (c @ c - radius * radius)
    t = np.where(disc >= 0, (b - np.sqrt(np.clip(disc, 0, None))) / (rays * rays).sum(1), wall_m)
    return (rays[:, 2] * t).reshape(intr.height, intr.width)


def scene_colour(intr=CAM, centre=CENTRE, radius=R) -> tuple[np.ndarray, np.ndarray]:
    """(colour BGR, the ball's true mask): a yellow ball with a white highlight at its rim, a dark
    stick and a skin-coloured hand in front of it, yellow specks and a big yellow board elsewhere."""
    rng = np.random.default_rng(0)
    ball = sphere_silhouette_mask(intr, centre, radius)
    hsv = np.zeros((intr.height, intr.width, 3), np.uint8)
    hsv[...] = (100, 30, 140)  # a grey-blue wall
    hsv[ball] = (29, 240, 210)
    cx, cy, r = mask_circle(ball)
    v, u = np.mgrid[0:intr.height, 0:intr.width]
    highlight = ball & ((u - cx) ** 2 + (v - (cy - 0.75 * r)) ** 2 < (0.3 * r) ** 2)  # reaching the rim
    hsv[highlight] = (30, 0, 255)  # washed out to white, on the rim
    stick = (np.abs((v - cy) - 0.3 * (u - cx)) < 2.5) & (u > cx)  # 5 px wide
    hand = (u - (cx + 0.8 * r)) ** 2 + (v - (cy + 0.5 * r)) ** 2 < (0.3 * r) ** 2
    hsv[stick] = (0, 0, 30)
    hsv[hand] = (10, 120, 180)
    hsv[(rng.random(ball.shape) < 0.01) & ~ball] = (29, 240, 210)  # specks
    hsv[5:25, 5:60] = (29, 240, 210)  # a yellow board, far larger than the ball at its depth
    truth = ball & ~stick & ~hand
    return cv2.cvtColor(hsv, cv2.COLOR_HSV2BGR), truth


def test_fixed_radius_fit_finds_a_known_sphere_with_an_honest_error():
    rng = np.random.default_rng(1)
    depth = sphere_depth()
    ball = sphere_silhouette_mask(CAM, CENTRE, R)
    v, u = np.nonzero(ball)
    pts = deproject(CAM, u, v, depth[v, u])
    exact = fit_sphere_fixed_radius(pts, R)
    assert np.linalg.norm(np.subtract(exact.centre_m, CENTRE)) < 1e-6 and exact.rms_m < 1e-6
    # 3 mm noise and 5 % of points 10 cm off (background behind the rim): the error is within 4 SE
    errors, ses = [], []
    for seed in range(6):
        rng = np.random.default_rng(seed)
        noisy = pts * (1 + rng.normal(0, 0.003, len(pts)) / pts[:, 2])[:, None]
        bad = rng.random(len(pts)) < 0.05
        noisy[bad] *= 1 + 0.1 / noisy[bad, 2:3]
        fit = fit_sphere_fixed_radius(noisy, R)
        assert fit.inliers < 0.97 * fit.points  # the outliers were left out
        errors.append(np.subtract(fit.centre_m, CENTRE))
        ses.append(fit.centre_se_m)
    errors, ses = np.abs(errors), np.asarray(ses)
    assert (errors < 4 * ses).all() and np.median(errors / ses) < 2.0
    assert np.linalg.norm(errors, axis=1).max() < 0.004
    assert fit_sphere_fixed_radius(pts[:10], R) is None


def test_mask_fit_centre_from_a_depth_image_and_its_mask():
    depth = sphere_depth()
    depth_noisy = depth + np.random.default_rng(2).normal(0, 0.003, depth.shape)
    mask = sphere_silhouette_mask(CAM, CENTRE, R)
    fit = mask_fit_centre(depth_noisy, CAM, mask, R)
    err = np.abs(np.subtract(fit.centre_m, CENTRE))
    assert err.max() < 0.003 and (err < 4 * np.asarray(fit.centre_se_m)).all()
    assert 0 < max(fit.centre_se_m) < 0.003  # the block jackknife's, not zero
    dilated = cv2.dilate(mask.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
    assert np.linalg.norm(np.subtract(mask_fit_centre(depth, CAM, dilated, R).centre_m, CENTRE)) < 1e-3
    assert mask_fit_centre(np.full(depth.shape, np.nan), CAM, mask, R) is None


def test_the_colour_rule_keeps_the_ball_and_leaves_the_hand_and_stick_out():
    colour, truth = scene_colour()
    mask = colour_mask(colour, sphere_depth(), CAM, R, parse_hsv("18:40,100:255,80:255"))
    iou = (mask & truth).sum() / (mask | truth).sum()
    assert iou > 0.95, iou
    hsv = cv2.cvtColor(colour, cv2.COLOR_BGR2HSV)
    assert mask[hsv[..., 2] < 60].mean() < 0.05  # the stick (its tip, enclosed by the ball, may be filled)
    assert not mask[(hsv[..., 0] < 15) & (hsv[..., 1] > 100)].any()  # the hand
    assert not mask[5:25, 5:60].any()  # the board: the wrong size for a ball at its depth
    white = hsv[..., 1] < 20
    assert mask[white & truth].mean() > 0.9  # the highlight at the rim is the ball's
    assert colour_mask(colour, sphere_depth(), CAM, R, parse_hsv("90:110,0:255,0:255")) is None


def test_labelme_polygons_give_the_mask_back(tmp_path):
    colour, truth = scene_colour()
    text = labelme_text(labelme_from_mask(truth, "colour.jpg", "ball", "test"))
    doc = json.loads(text)
    assert (doc["imageWidth"], doc["imageHeight"], doc["imagePath"]) == (160, 120, "colour.jpg")
    assert doc["shapes"][0]["shape_type"] == "polygon" and doc["shapes"][0]["label"] == "ball"
    (tmp_path / "scene_a.json").write_text(text)
    balls, ignored = balls_from_labelme(tmp_path / "scene_a.json", (120, 160), R, "scene_a", ("image.png", "colour.jpg"))
    assert not ignored and len(balls) == 1
    got = balls[0].mask
    assert (got & truth).sum() / (got | truth).sum() > 0.995
    np.testing.assert_allclose(balls[0].circle_px, mask_circle(truth), atol=0.6)


@pytest.mark.parametrize("text, match", [
    ("40:18,100:255,80:255", "inverted"), ("18:40,100:300,80:255", "outside 0:255"),
    ("18:40,100:255", "H0:H1,S0:S1,V0:V1"), ("a:b,1:2,3:4", "whole numbers"), ("18:190,0:255,0:255", "outside 0:179")])
def test_bad_hsv_ranges(text, match):
    with pytest.raises(SphereBenchError, match=match):
        parse_hsv(text)


# ---------------------------------------------------------------- the command

def make_dataset(root: Path, n: int = 3, colour_size=None, empty_frame: int | None = None) -> Path:
    """n scenes of the sphere with a colour frame (one frame without a ball when asked)."""
    colour, _ = scene_colour()
    depth_m = sphere_depth()
    for i in range(n):
        frame = colour.copy()
        if i == empty_frame:
            frame[:] = (140, 120, 110)
        if colour_size is not None and i == n - 1:
            frame = cv2.resize(frame, colour_size)
        path = root.parent / f"colour_{root.name}_{i}.jpg"
        cv2.imwrite(str(path), frame, [cv2.IMWRITE_JPEG_QUALITY, 98])
        depth = np.round(depth_m / CAM.depth_scale).astype(np.uint16)
        inout.write_scene(root / "scenes", Scene(f"frame_{i}", "recorded", CAM, depth, annotated=False), R,
                       colour=path)
    inout.finish_dataset(root, {"name": root.name, "preset": "recorded", "ball_radius_m": R, "category": "ball"})
    return root


def _cli(monkeypatch, capsys, *argv):
    monkeypatch.setattr(sys, "argv", ["spherebench", *argv])
    rc = main(list(argv))
    return rc, capsys.readouterr()


def _tree(root: Path) -> dict:
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}


def test_annotate_writes_labelme_beside_the_colour_and_notes_empty_frames(tmp_path, monkeypatch, capsys):
    ds = make_dataset(tmp_path / "ds", empty_frame=1)
    assert sorted(p.name for p in (ds / "scenes" / "frame_0").iterdir()) == sorted(
        ["cloud.ply", "colour.jpg", "depth.png", "gt.json", "image.png", "intrinsics.json"])
    rc, cap = _cli(monkeypatch, capsys, "annotate", str(ds), "--from-colour", "--sheet", str(tmp_path / "sheets"))
    assert rc == 0, cap.err
    assert "annotated 2 of 3 frames" in cap.out
    notes = [s for s in cap.err.splitlines() if s.startswith("note:")]
    assert len(notes) == 1 and "1 frame(s)" in notes[0] and "frame_1" in notes[0]
    assert not (ds / "scenes/frame_1/colour.json").exists()
    doc = foreign_formats.read_labelme(ds / "scenes/frame_0/colour.json")
    assert doc["imagePath"] == "colour.jpg" and len(doc["shapes"]) == 1
    assert {"closeup_01.png", "overview_01.png"} <= {p.name for p in (tmp_path / "sheets").iterdir()}
    # a second run would replace a person's corrections: refused, nothing touched
    before = _tree(ds)
    rc, cap = _cli(monkeypatch, capsys, "annotate", str(ds), "--from-colour")
    assert rc == 2 and len(cap.err.strip().splitlines()) == 1 and "--overwrite" in cap.err
    assert _tree(ds) == before
    # prepare --labelme reads them: the ball gets its mask, circle and mask-fit centre
    from spherebench.datasets.annotate import AnnotationIndex
    index = AnnotationIndex(labelme_dir=ds)
    balls = index.balls_for("frame_0", (120, 160), R, ("image.png", "colour.jpg"))
    assert len(balls) == 1 and index.balls_for("frame_1", (120, 160), R) is None


@pytest.mark.parametrize("case, match", [
    ("no-colour", "no scene holds a colour frame"), ("colour-size", "not registered to the depth"),
    ("bad-hsv", "inverted"), ("no-action", "--from-colour"), ("not-a-dataset", "not a dataset")])
def test_annotate_bad_input_is_one_line_and_writes_nothing(tmp_path, monkeypatch, capsys, case, match):
    ds = make_dataset(tmp_path / "ds", colour_size=(200, 150) if case == "colour-size" else None)
    args = ["annotate", str(ds), "--from-colour"]
    if case == "no-colour":
        for p in ds.glob("scenes/*/colour.jpg"):
            p.unlink()
    elif case == "bad-hsv":
        args += ["--hsv", "40:18,100:255,80:255"]
    elif case == "no-action":
        args = ["annotate", str(ds)]
    elif case == "not-a-dataset":
        args = ["annotate", str(ds / "scenes"), "--from-colour"]
    before = _tree(tmp_path)
    rc, cap = _cli(monkeypatch, capsys, *args)
    assert rc == 2
    assert len(cap.err.strip().splitlines()) == 1 and match in cap.err and "Traceback" not in cap.err, cap.err
    assert _tree(tmp_path) == before


# ---------------------------------------------------------------- the recorded Kinect set

def test_the_committed_kinect_annotations_name_every_frame():
    files = sorted(ANNOTATIONS.glob("*.json"))
    assert [p.stem for p in files] == [f"kinect_1_dep_{i:02d}" for i in range(0, 100, 3)]
    for p in files:
        doc = foreign_formats.read_labelme(p)
        assert (doc["imageWidth"], doc["imageHeight"], doc["imagePath"]) == (640, 480, "colour.jpg")
        assert [s["shape_type"] for s in doc["shapes"]] == ["polygon"] and doc["shapes"][0]["label"] == "ball"
        assert "reviewed by eye" in doc["shapes"][0]["description"]


@pytest.mark.skipif(not REALDATA.is_dir(), reason=f"{REALDATA} is absent")
def test_prepare_kinect_with_the_committed_masks(tmp_path, capsys):
    out = tmp_path / "kinect"
    assert main(["prepare", "--preset-source", "kinect-pochang", "--labelme", str(ANNOTATIONS), "--out", str(out),
                 "--frames", "7:9"]) == 0
    capsys.readouterr()
    ref = inout.read_dataset_meta(out)["reference_centres"]
    assert (ref["source"], ref["balls"], ref["without_centre"]) == ("mask-fit", 2, 0) and ref["se_median_m"] < 0.01
    s21, s24 = inout.list_scenes(out)
    src = REALDATA / "pochang_rgbd_sphere/sensors/Kinect_1/kinect_1_rgb_24.jpg"
    assert (s24 / "colour.jpg").read_bytes() == src.read_bytes()
    assert foreign_formats.read_labelme(s24 / "colour.json")["imagePath"] == "colour.jpg"
    g = inout.read_json(s24 / "gt.json")
    ball = g["balls"][0]
    assert g["annotated"] and ball["center_source"] == "mask-fit" and max(ball["center_se_m"]) < 0.01
    # the authors' own RANSAC fit (free radius) lies within a few centimetres of the mask fit
    assert np.linalg.norm(np.subtract(ball["center_m"], g["meta"]["reference_center_m"])) < 0.03
    assert 30 < ball["circle"][2] < 60
    # the LabelMe round trip: the dataset's own colour.json files carried into its rebuild
    assert main(["prepare", "--preset-source", "kinect-pochang", "--labelme", str(out), "--out", str(out),
                 "--frames", "7:9"]) == 0
    assert inout.read_json(s24 / "gt.json")["balls"][0]["circle"] == ball["circle"]
