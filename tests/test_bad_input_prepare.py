"""Issue 15, `spherebench prepare` and recorded data: bad input ends in a one-line error or a
correct answer, with what was dropped or ignored said once on stderr (stdout: the summary only)."""

import json
from pathlib import Path

import numpy as np
import pytest

from spherebench.scripts import cli
from spherebench.cloud import cloud_from_depth
from spherebench.datasets import frame_sources, inout, prepare
from test_prepare import INTR, counts, labelme, render, shape, write_intrinsics_json  # tests/ is on sys.path

CAM = ["--fx", str(INTR.fx), "--fy", str(INTR.fy), "--ppx", str(INTR.ppx), "--ppy", str(INTR.ppy)]
REALDATA = Path(__file__).resolve().parents[1].parent / "shared" / "realdata"
KINECT_FRAME = REALDATA / "pochang_rgbd_sphere" / "sensors" / "Kinect_1" / "kinect_1_dep_24.dat"


def tree(root):
    return {str(p.relative_to(root)): p.read_bytes() if p.is_file() else None for p in sorted(root.rglob("*"))}


def refused(capsys, tmp_path, args, out, *words, command="prepare"):
    """Run; assert exit 2, one line on stderr naming ``words``, nothing written, nothing touched."""
    before = tree(tmp_path)
    rc = cli.main([command, *map(str, args)])
    cap = capsys.readouterr()
    err = cap.err.strip()
    assert rc == 2, err
    assert len(err.splitlines()) == 1 and err.startswith(f"spherebench {command}: error:"), err
    assert "Traceback" not in err
    for w in words:
        assert w in err, err
    assert not Path(out).exists()
    assert tree(tmp_path) == before  # no partial output, no temporary left, no input changed
    return err


def prepared(capsys, *args):
    """Run a prepare that must succeed; returns (stdout, stderr) and checks stdout is the summary alone."""
    assert cli.main(["prepare", *map(str, args)]) == 0
    cap = capsys.readouterr()
    assert len(cap.out.strip().splitlines()) == 1 and " scenes (" in cap.out, cap.out
    assert "note:" not in cap.out
    return cap.out, cap.err


def cloud_points(n=300, seed=0, z=3.0):
    return np.random.default_rng(seed).uniform(-1, 1, (n, 3)) + [0, 0, z]


def raw_file(tmp_path, name, values):
    values.tofile(tmp_path / name)
    return tmp_path / name


def ramp_depth():
    """(60, 80) metres: the ball before a floor rising from 1.5 m to 2.7 m down the image, so
    that neighbouring pixels differ (a misreading of the bytes shows as jumps everywhere)."""
    depth, hit = render()
    floor = 1.5 + 0.02 * np.arange(60)[:, None] * np.ones((1, 80))
    return np.where(hit, depth, floor)


# --------------------------------------------------------------------------- 1. NaN and infinite points

@pytest.mark.parametrize("suffix", [".xyz", ".ply"])
def test_non_finite_points_are_dropped_and_said_once(tmp_path, capsys, suffix):
    pts = cloud_points()
    pts[5] = np.nan
    pts[6, 2] = np.inf
    pts[7, 0] = -np.inf
    path = tmp_path / f"scan{suffix}"
    if suffix == ".xyz":
        np.savetxt(path, pts, fmt="%.6f")
    else:
        inout.write_ply(path, pts)
    out = tmp_path / "ds"
    summary, err = prepared(capsys, path, "--out", out)
    assert "297" in summary  # valid points per scene: the finite ones
    assert err.count("NaN or infinite") == 1 and "3 point(s)" in err and path.name in err
    scene = inout.list_scenes(out)[0]
    back = inout.read_ply(scene / "cloud.ply")
    assert len(back) == 297 and np.isfinite(back.points).all()
    np.testing.assert_allclose(back.points, np.delete(pts, [5, 6, 7], axis=0), atol=1e-6)
    assert inout.read_json(scene / "gt.json")["meta"]["non_finite_points_dropped"] == 3


def test_non_finite_points_of_an_organised_cloud_keep_the_others_pixels(tmp_path, capsys):
    depth = counts(render()[0])
    cloud = cloud_from_depth(depth * np.float32(0.001), INTR)
    cloud.points[:40] = np.nan  # the first 40 pixels' points
    inout.write_cloud_ply(tmp_path / "org.ply", cloud)
    out = tmp_path / "ds"
    _, err = prepared(capsys, tmp_path / "org.ply", "--intrinsics", write_intrinsics_json(tmp_path / "cam.json"),
                      "--out", out)
    assert "40 point(s) with NaN" in err
    got = inout.read_depth_png(inout.list_scenes(out)[0] / "depth.png")
    expected = depth.copy()
    expected[cloud.rows[:40], cloud.cols[:40]] = 0
    np.testing.assert_array_equal(got, expected)


def test_cloud_with_no_finite_point_is_refused(tmp_path, capsys):
    np.savetxt(tmp_path / "nan.xyz", np.full((5, 3), np.nan))
    refused(capsys, tmp_path, [tmp_path / "nan.xyz", "--out", tmp_path / "ds"], tmp_path / "ds",
            "nan.xyz", "none of the cloud's 5 points has finite coordinates")


def test_check_units_ignores_nan_and_infinities():
    frame_sources.check_units(np.array([np.nan, np.inf, 2.0, 2.1, 1.9]), "x", 1.0)  # median of the finite: 2 m
    frame_sources.check_units(np.array([np.nan, np.nan]), "x", 1.0)  # nothing finite: nothing to check
    with pytest.raises(prepare.SphereBenchError, match="--depth-scale 0.001"):
        frame_sources.check_units(np.array([np.nan, -np.inf, 2000.0, 2100.0]), "x", 1.0)


# --------------------------------------------------------------------------- 2. LabelMe shapes that are not balls

def test_labelme_without_ball_shapes_leaves_the_scene_unannotated(tmp_path, capsys):
    folder = tmp_path / "pngs"
    folder.mkdir()
    for i in range(4):
        inout.write_depth_png(folder / f"frame_{i}.png", counts(render()[0]))
    lm = tmp_path / "labelme"
    others = [shape("rectangle", [[1, 1], [5, 5]]), shape("ellipse", [[20, 20], [25, 22]]),
              shape("point", [[3, 3]]), shape("line", [[1, 1], [9, 9]])]
    labelme(lm / "frame_0.json", others)
    labelme(lm / "frame_1.json", [shape("circle", [[40.5, 30.5], [48.5, 30.5]], label="hand")])
    labelme(lm / "frame_2.json", [])  # a deliberate empty annotation: a negative
    labelme(lm / "frame_3.json", [shape("circle", [[40.5, 30.5], [48.5, 30.5]]), shape("rectangle", [[1, 1], [5, 5]])])
    out = tmp_path / "ds"
    _, err = prepared(capsys, folder, "--intrinsics", write_intrinsics_json(tmp_path / "cam.json"),
                      "--labelme", lm, "--label", "basketball", "--out", out)
    g = {s.name: inout.read_json(s / "gt.json") for s in inout.list_scenes(out)}
    assert not g["frame_0"]["annotated"] and not g["frame_1"]["annotated"]
    assert g["frame_2"]["annotated"] and g["frame_2"]["balls"] == []
    assert g["frame_3"]["annotated"] and len(g["frame_3"]["balls"]) == 1
    # said once, naming the shapes, the label and a file
    assert err.count("not balls were ignored in 3 file(s)") == 1, err
    for words in ("2 rectangle", "1 ellipse", "1 point", "1 line", "circle labelled 'hand'", "labelled 'basketball'",
                  "frame_0.json"):
        assert words in err, (words, err)
    assert err.count("2 LabelMe file(s) hold no ball shape") == 1 and "unannotated, not negatives" in err
    # only annotated scenes are scored: the negative and the ball, not the two without a ball shape
    coco = inout.read_coco_gt(out)
    assert sorted(im["scene_id"] for im in coco["images"]) == ["frame_2", "frame_3"]
    # the user's LabelMe files survive the rerun with --labelme OUT, usable or not
    assert (out / "scenes" / "frame_0" / "image.json").is_file()
    prepared(capsys, folder, "--intrinsics", tmp_path / "cam.json", "--labelme", out, "--label", "basketball",
             "--out", out)
    assert not inout.read_json(out / "scenes" / "frame_0" / "gt.json")["annotated"]
    assert (out / "scenes" / "frame_0" / "image.json").is_file()


# --------------------------------------------------------------------------- 3. width and height swapped

def test_raw_frame_with_width_and_height_swapped(tmp_path, capsys):
    raw = raw_file(tmp_path, "f.raw", counts(ramp_depth()).astype("<u2"))
    out = tmp_path / "ds"
    prepared(capsys, raw, "--raw-size", "80x60", *CAM, "--out", out)
    refused(capsys, tmp_path, [raw, "--raw-size", "60x80", *CAM, "--out", tmp_path / "x"], tmp_path / "x",
            "f.raw", "read as 80x60", "swapped", "--raw-size 80x60")
    # the size from an intrinsics file: the intrinsics are named
    swapped = write_intrinsics_json(tmp_path / "swapped.json", INTR.scaled(60, 80))
    refused(capsys, tmp_path, [raw, "--intrinsics", swapped, "--out", tmp_path / "x"], tmp_path / "x",
            "f.raw", "swapped", "intrinsics of a 80x60 image")


@pytest.mark.skipif(not KINECT_FRAME.is_file(), reason=f"{KINECT_FRAME} is absent")
def test_raw_reading_check_on_a_recorded_frame():
    values = np.fromfile(KINECT_FRAME, "<u2").reshape(480, 640)
    fmt = frame_sources.RawFormat(640, 480)
    frame_sources.check_raw_reading(values, "kinect", frame_sources._raw_readings(values, values.byteswap(), fmt))
    wrong = values.reshape(640, 480)
    with pytest.raises(prepare.SphereBenchError, match="--raw-size 640x480"):
        frame_sources.check_raw_reading(wrong, "kinect", frame_sources._raw_readings(wrong, wrong.byteswap(),
                                                                         frame_sources.RawFormat(480, 640)))
    big = values.byteswap()
    with pytest.raises(prepare.SphereBenchError, match="--raw-byte-order big"):
        frame_sources.check_raw_reading(big, "kinect", frame_sources._raw_readings(big, values, fmt))


# --------------------------------------------------------------------------- 4. the unit check's suggestion

def test_wrong_byte_order_is_told_the_byte_order(tmp_path, capsys):
    raw = raw_file(tmp_path, "be.raw", counts(ramp_depth()).astype(">u2"))
    err = refused(capsys, tmp_path, [raw, "--raw-size", "80x60", *CAM, "--out", tmp_path / "x"], tmp_path / "x",
                  "be.raw", "--raw-byte-order big")
    assert "--depth-scale" not in err
    # a flat frame shows no jumps either way: the unit check names the byte order too
    np.full((60, 80), 2000, "<u2").byteswap().tofile(raw)
    err = refused(capsys, tmp_path, [raw, "--raw-size", "80x60", *CAM, "--out", tmp_path / "x"], tmp_path / "x",
                  "be.raw", "median valid depth is 53.26 m", "with --raw-byte-order big it is 2 m")
    assert "--depth-scale" not in err


def test_uint16_read_as_float32_is_told_the_dtype(tmp_path, capsys):
    mm = counts(render()[0]).astype("<u2")
    raw = raw_file(tmp_path, "u16.raw", mm)  # the size of an 80x60 uint16 frame
    refused(capsys, tmp_path, [raw, "--raw-size", "80x60", "--raw-dtype", "float32", *CAM, "--out", tmp_path / "x"],
            tmp_path / "x", "u16.raw", "exactly a 80x60 uint16 frame", "--raw-dtype uint16")
    np.concatenate([mm, mm]).tofile(raw)  # twice as many: the size of an 80x60 float32 frame
    err = refused(capsys, tmp_path, [raw, "--raw-size", "80x60", "--raw-dtype", "float32", *CAM,
                                     "--out", tmp_path / "x"], tmp_path / "x", "u16.raw", "no unit makes it a depth",
                  "--raw-dtype uint16")
    assert "--depth-scale" not in err


@pytest.mark.parametrize("per_m, z_m, first, second", [(100, 1.7, "0.01 (centimetres: median 1.7", None),
                                                       (100, 5.0, "0.01 (centimetres: median 5", "0.001 (millimetres"),
                                                       (1000, 1.5, "0.001 (millimetres: median 1.5", None)])
def test_unit_suggestion_names_the_unit(tmp_path, capsys, per_m, z_m, first, second):
    pts_m = cloud_points(z=0) * [0.1, 0.1, 0] + [0, 0, z_m]  # a patch at z_m
    np.savetxt(tmp_path / "scan.xyz", pts_m * per_m, fmt="%.3f")
    err = refused(capsys, tmp_path, [tmp_path / "scan.xyz", "--out", tmp_path / "x"], tmp_path / "x",
                  "scan.xyz", f"try --depth-scale {first}")
    assert (second in err) if second else (" or 0." not in err), err
    assert "looks like millimetres" not in err


# --------------------------------------------------------------------------- 5. option names, stdout and stderr

def test_size_errors_name_size(tmp_path, capsys):
    raw = raw_file(tmp_path, "f.raw", counts(ramp_depth()).astype("<u2"))
    err = refused(capsys, tmp_path, [raw, "--size", "80by60", *CAM, "--out", tmp_path / "x"], tmp_path / "x",
                  "--size must be WIDTHxHEIGHT", "80by60")
    assert "--raw-size" not in err
    refused(capsys, tmp_path, [raw, "--size", "80x60", "--out", tmp_path / "x"], tmp_path / "x",
            "--size is the image size of --fx")
    refused(capsys, tmp_path, [raw, "--size", "80x60", "--raw-size", "80x60", *CAM, "--out", tmp_path / "x"],
            tmp_path / "x", "--raw-size", "--size, not both")
    cam = write_intrinsics_json(tmp_path / "cam.json")
    refused(capsys, tmp_path, [raw, "--size", "40x30", "--intrinsics", cam, "--out", tmp_path / "x"],
            tmp_path / "x", "cam.json", "40x30 (--size)")
    # --size with the four numbers works for raw frames
    prepared(capsys, raw, "--size", "80x60", *CAM, "--out", tmp_path / "ok")


def test_notes_go_to_stderr(tmp_path, capsys):
    np.savetxt(tmp_path / "scan.xyz", cloud_points())
    summary, err = prepared(capsys, tmp_path / "scan.xyz", "--out", tmp_path / "ds")
    assert "image-less" in summary and "note: clouds without intrinsics" in err


# --------------------------------------------------------------------------- 6. show without depth.png

def test_show_scene_missing_depth_png(tmp_path, capsys, monkeypatch):
    folder = tmp_path / "pngs"
    folder.mkdir()
    inout.write_depth_png(folder / "f.png", counts(render()[0]))
    out = tmp_path / "ds"
    prepared(capsys, folder, "--intrinsics", write_intrinsics_json(tmp_path / "cam.json"), "--out", out)
    scene = out / "scenes" / "f"
    (scene / "depth.png").unlink()
    monkeypatch.chdir(tmp_path)  # where show writes by default
    err = refused(capsys, tmp_path, [scene], tmp_path / "f_gt.ply", "depth.png is missing in", str(scene),
                  command="show")
    assert "image-less" not in err


# --------------------------------------------------------------------------- 7. a LabelMe file of another image

@pytest.mark.parametrize("doc, words", [
    (dict(w=60, h=80), ["LabelMe image is 60x80", "scene frame_0 is 80x60"]),
    (dict(image="frame_9.png"), ["for image 'frame_9.png'", "not scene frame_0"]),
    (dict(image="C:\\shots\\frame_9.png"), ["not scene frame_0"]),
    (dict(shapes=[shape("circle", [[300.0, 200.0], [310.0, 200.0]])]), ["circle 0 covers no pixel", "another image"]),
])
def test_labelme_of_another_image(tmp_path, capsys, doc, words):
    folder = tmp_path / "pngs"
    folder.mkdir()
    inout.write_depth_png(folder / "frame_0.png", counts(render()[0]))
    shapes = doc.pop("shapes", [shape("circle", [[40.5, 30.5], [48.5, 30.5]])])
    labelme(tmp_path / "labelme" / "frame_0.json", shapes, **doc)
    refused(capsys, tmp_path, [folder, "--intrinsics", write_intrinsics_json(tmp_path / "cam.json"),
                               "--labelme", tmp_path / "labelme", "--out", tmp_path / "x"], tmp_path / "x",
            "frame_0.json", *words)


def test_a_fifo_named_as_a_frame_in_an_input_folder_is_refused(tmp_path, capsys):
    import os

    import cv2

    pngs = tmp_path / "pngs"
    pngs.mkdir()
    cv2.imwrite(str(pngs / "a.png"), np.full((48, 64), 1500, np.uint16))
    os.mkfifo(pngs / "zz.png")
    assert cli.main(["prepare", str(pngs), "--fx", "60", "--fy", "60", "--ppx", "32", "--ppy", "24", "--size", "64x48",
                     "--out", str(tmp_path / "p")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "zz.png: not a regular file" in err[0], err
    assert not (tmp_path / "p").exists()
