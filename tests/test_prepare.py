"""`spherebench prepare`: every input kind into the scene format, frame picking, units, bad input."""

import gc
import json

import numpy as np
import pytest

from spherebench.scripts import cli
from spherebench.camera import Intrinsics, image_rays
from spherebench.cloud import cloud_from_depth
from spherebench.datasets import inout

INTR = Intrinsics(width=80, height=60, ppx=39.3, ppy=29.7, fx=70.0, fy=69.5, model="brown_conrady",
                  coeffs=(0.02, -0.01, 0.001, 0.0005, 0.0), depth_scale=0.001)
CENTRE = np.array([0.1, -0.05, 1.2])
RADIUS = 0.12
WALL_M = 2.0


def render(intr=INTR, centre=CENTRE, radius=RADIUS):
    """Depth (H, W) metres of a sphere before a wall at WALL_M, and the sphere's pixels (H, W) bool."""
    rays = image_rays(intr)  # z = 1, so the ray parameter is the depth
    a = (rays * rays).sum(-1)
    b = rays @ centre
    disc = b * b - a * (centre @ centre - radius * radius)
    hit = disc >= 0
    t = np.where(hit, (b - np.sqrt(np.maximum(disc, 0))) / a, np.inf)
    return np.where(hit, t, WALL_M), hit


def counts(depth_m, scale=0.001):
    return np.round(depth_m / scale).astype(np.uint16)


def run_cli(*args):
    return cli.main(["prepare", *map(str, args)])


def assert_failed(capsys, rc, out, *words):
    err = capsys.readouterr().err.strip()
    assert rc == 2, err
    assert len(err.splitlines()) == 1 and err.startswith("spherebench prepare: error:"), err
    for w in words:
        assert w in err, err
    assert not out.exists()
    assert not [p for p in out.parent.iterdir() if p.name.startswith(f".tmp-{out.name}")]


def write_intrinsics_json(path, intr=INTR, **extra):
    d = intr.to_dict()
    d.pop("depth_scale")
    d.update(extra)
    path.write_text(json.dumps(d))
    return path


def png_folder(tmp_path, n=3):
    folder = tmp_path / "pngs"
    folder.mkdir()
    depth, hit = render()
    for i in range(n):
        inout.write_depth_png(folder / f"frame_{i}.png", counts(depth))
    return folder, counts(depth), hit


# --------------------------------------------------------------------------- RealSense recordings

def record(path, frames, intr, depth_units=0.0001, stream="depth"):
    """Write a RealSense recording of synthetic frames with pyrealsense2's software device."""
    rs = pytest.importorskip("pyrealsense2")
    dev = rs.software_device()
    sensor = dev.add_sensor("Stereo Module" if stream == "depth" else "RGB Camera")
    ri = rs.intrinsics()
    ri.width, ri.height, ri.ppx, ri.ppy, ri.fx, ri.fy = intr.width, intr.height, intr.ppx, intr.ppy, intr.fx, intr.fy
    ri.model, ri.coeffs = rs.distortion.brown_conrady, list(intr.coeffs)
    vs = rs.video_stream()
    vs.type = rs.stream.depth if stream == "depth" else rs.stream.color
    vs.index, vs.uid, vs.width, vs.height, vs.fps = 0, 0, intr.width, intr.height, 30
    vs.bpp, vs.fmt = (2, rs.format.z16) if stream == "depth" else (3, rs.format.rgb8)
    vs.intrinsics = ri
    profile = sensor.add_video_stream(vs)
    if stream == "depth":
        sensor.add_read_only_option(rs.option.depth_units, depth_units)
    recorder = rs.recorder(str(path), dev)
    queue = rs.frame_queue(len(frames) + 1)
    sensor.open(profile)
    sensor.start(queue)
    for i, img in enumerate(frames):
        f = rs.software_video_frame()
        f.pixels = np.ascontiguousarray(img)
        f.bpp, f.stride = vs.bpp, vs.bpp * intr.width
        f.timestamp, f.domain, f.frame_number = 1000.0 + 33.3 * i, rs.timestamp_domain.hardware_clock, i
        f.profile = profile.as_video_stream_profile()
        if stream == "depth":
            f.depth_units = depth_units
        sensor.on_video_frame(f)
        queue.wait_for_frame(2000)
    sensor.stop()
    sensor.close()
    del recorder  # closes the file
    gc.collect()
    return path


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    """5 frames, 0.1 mm depth units; frame i has the ball i cm farther away."""
    path = tmp_path_factory.mktemp("bag") / "rec.db3"  # pyrealsense2 >= 2.56 records ROS2 (.db3)
    frames = [counts(render(centre=CENTRE + [0, 0, 0.01 * i])[0], 0.0001) for i in range(5)]
    record(path, frames, INTR)
    return path, frames


def test_recording_round_trip(recording, tmp_path):
    path, frames = recording
    out = tmp_path / "ds"
    assert run_cli(path, "--out", out) == 0
    scenes = inout.list_scenes(out)
    assert [s.name for s in scenes] == [f"rec_{i:06d}" for i in range(5)]
    for scene_dir, frame in zip(scenes, frames):
        np.testing.assert_array_equal(inout.read_depth_png(scene_dir / "depth.png"), frame)
        intr = inout.read_intrinsics(scene_dir)
        assert intr.depth_scale == 0.0001
        assert (intr.width, intr.height, intr.model) == (80, 60, "brown_conrady")
        # librealsense stores float32; the shortest decimal of each float32 is kept, so values read as given
        for name in ("ppx", "ppy", "fx", "fy", "coeffs"):
            assert getattr(intr, name) == getattr(INTR, name)
        gt = inout.read_json(scene_dir / "gt.json")
        assert gt["annotated"] is False and gt["ball_radius_m"] == 0.12
    meta = inout.read_json(scenes[3] / "gt.json")["meta"]
    assert meta["frame_index"] == 3 and abs(meta["time_from_first_frame_ms"] - 99.9) < 1e-3
    # the ball's points lie on the sphere: deprojection uses the stream's model and depth scale
    cloud = inout.load_cloud(scenes[0])
    near = np.linalg.norm(cloud.points - CENTRE, axis=1) < RADIUS + 0.01
    assert near.sum() > 50
    np.testing.assert_allclose(np.linalg.norm(cloud.points[near] - CENTRE, axis=1), RADIUS, atol=2e-3)


@pytest.mark.parametrize("options, kept", [(["--frames", "1:4", "--every", "2"], [1, 3]),
                                           (["--time-range", "30:70"], [1, 2]),
                                           (["--every", "3"], [0, 3])])
def test_recording_frame_selection(recording, tmp_path, options, kept):
    out = tmp_path / "ds"
    assert run_cli(recording[0], "--out", out, *options) == 0
    assert [s.name for s in inout.list_scenes(out)] == [f"rec_{i:06d}" for i in kept]


def test_recording_without_depth_stream(tmp_path, capsys):
    path = record(tmp_path / "colour.db3", [np.zeros((60, 80, 3), np.uint8)] * 2, INTR, stream="color")
    out = tmp_path / "ds"
    assert_failed(capsys, run_cli(path, "--out", out), out, "colour.db3", "no depth stream")


@pytest.mark.parametrize("damage", ["garbage", "truncated"])
def test_recording_corrupt(recording, tmp_path, capsys, damage):
    data = recording[0].read_bytes()
    bad = tmp_path / "bad.db3"
    bad.write_bytes(b"\x13\x37" * 500 if damage == "garbage" else data[:len(data) // 3])
    out = tmp_path / "ds"
    assert_failed(capsys, run_cli(bad, "--out", out), out, "bad.db3")
    (tmp_path / "bad.bag").write_bytes(b"#ROSBAG V2.0\n" + b"\x00" * 40)
    assert_failed(capsys, run_cli(tmp_path / "bad.bag", "--out", out), out, "bad.bag")


def test_recording_byte_identical(recording, tmp_path):
    a, b = tmp_path / "1" / "ds", tmp_path / "2" / "ds"  # the dataset's name is its folder's
    assert run_cli(recording[0], "--out", a, "--frames", "0:2") == 0
    assert run_cli(recording[0], "--out", b, "--frames", "0:2") == 0
    assert tree_bytes(a) == tree_bytes(b)


def tree_bytes(root):
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


# --------------------------------------------------------------------------- depth PNGs and raw frames

def test_png_folder_with_intrinsics(tmp_path):
    folder, depth, hit = png_folder(tmp_path)
    out = tmp_path / "ds"
    assert run_cli(folder, "--intrinsics", write_intrinsics_json(tmp_path / "cam.json"), "--out", out,
                   "--radius", "0.2", "--name", "mine") == 0
    scenes = inout.list_scenes(out)
    assert [s.name for s in scenes] == ["frame_0", "frame_1", "frame_2"]
    np.testing.assert_array_equal(inout.read_depth_png(scenes[1] / "depth.png"), depth)
    assert inout.read_image(scenes[1]).shape == (60, 80, 3)
    meta = inout.read_dataset_meta(out)
    assert meta["ball_radius_m"] == 0.2 and meta["name"] == "mine" and meta["source"]["kind"] == "depth-png"
    assert inout.read_json(scenes[0] / "gt.json")["ball_radius_m"] == 0.2
    coco = inout.read_coco_gt(out)
    assert coco["images"] == [] and coco["annotations"] == []  # nothing annotated, nothing to score


def test_png_folder_bad_input(tmp_path, capsys):
    folder, depth, _ = png_folder(tmp_path, n=1)
    out = tmp_path / "ds"
    assert_failed(capsys, run_cli(folder, "--out", out), out, "need intrinsics")
    small = INTR.scaled(40, 30)
    assert_failed(capsys, run_cli(folder, "--out", out, "--intrinsics", write_intrinsics_json(tmp_path / "s.json", small)),
                  out, "frame_0.png", "80x60", "40x30")
    (tmp_path / "partial.json").write_text(json.dumps({"width": 80, "height": 60, "fx": 70}))
    assert_failed(capsys, run_cli(folder, "--out", out, "--intrinsics", tmp_path / "partial.json"), out,
                  "partial.json", "ppx")
    assert_failed(capsys, run_cli(folder, "--out", out, "--fx", "70", "--fy", "70", "--size", "80x60"), out,
                  "--ppx", "--ppy")
    # wrong unit: millimetre counts declared as metres
    assert_failed(capsys, run_cli(folder, "--out", out, "--intrinsics", write_intrinsics_json(tmp_path / "m.json"),
                                  "--depth-scale", "1"), out, "frame_0.png", "--depth-scale 0.001")
    data = (folder / "frame_0.png").read_bytes()
    (folder / "frame_0.png").write_bytes(data[:len(data) // 2])
    assert_failed(capsys, run_cli(folder, "--out", out, "--intrinsics", tmp_path / "m.json"), out, "frame_0.png")


def test_raw_frames(tmp_path, capsys):
    depth_m, _ = render()
    folder = tmp_path / "raw"
    folder.mkdir()
    (folder / "a.raw").write_bytes(counts(depth_m).astype("<u2").tobytes())
    (folder / "b.raw").write_bytes(counts(depth_m).astype("<u2").tobytes())
    cam = ["--fx", INTR.fx, "--fy", INTR.fy, "--ppx", INTR.ppx, "--ppy", INTR.ppy]
    out = tmp_path / "ds"
    assert run_cli(folder, "--raw-size", "80x60", *cam, "--out", out, "--frames", "1:") == 0
    (scene,) = inout.list_scenes(out)
    assert scene.name == "b"
    np.testing.assert_array_equal(inout.read_depth_png(scene / "depth.png"), counts(depth_m))
    # float32 metres, big-endian -> millimetre counts
    f = tmp_path / "f.bin"
    f.write_bytes(depth_m.astype(">f4").tobytes())
    out2 = tmp_path / "ds2"
    assert run_cli(f, "--raw-size", "80x60", "--raw-dtype", "float32", "--raw-byte-order", "big", *cam, "--out", out2) == 0
    np.testing.assert_array_equal(inout.read_depth_png(inout.list_scenes(out2)[0] / "depth.png"), counts(depth_m))
    # the same floats in millimetres: plainly the wrong unit
    f.write_bytes((depth_m * 1000).astype(">f4").tobytes())
    assert_failed(capsys, run_cli(f, "--raw-size", "80x60", "--raw-dtype", "float32", "--raw-byte-order", "big", *cam,
                                  "--out", tmp_path / "x"), tmp_path / "x", "f.bin", "--depth-scale 0.001")
    # size mismatches: file too short for the size, and size against the intrinsics file
    assert_failed(capsys, run_cli(folder / "a.raw", "--raw-size", "80x61", *cam, "--out", tmp_path / "z"),
                  tmp_path / "z", "a.raw", "truncated")
    assert_failed(capsys, run_cli(folder / "a.raw", "--raw-size", "40x120", "--intrinsics",
                                  write_intrinsics_json(tmp_path / "cam.json"), "--out", tmp_path / "z"),
                  tmp_path / "z", "cam.json", "80x60", "40x120")


# --------------------------------------------------------------------------- point clouds

def test_ply_organised_and_unorganised(tmp_path, capsys):
    depth_m, _ = render()
    depth = counts(depth_m)
    cloud = cloud_from_depth(depth * np.float32(0.001), INTR)
    inout.write_cloud_ply(tmp_path / "org.ply", cloud)
    inout.write_ply(tmp_path / "flat.ply", cloud.points)  # no row/col: unorganised
    cam = write_intrinsics_json(tmp_path / "cam.json")
    for name in ("org", "flat"):
        out = tmp_path / f"ds_{name}"
        assert run_cli(tmp_path / f"{name}.ply", "--intrinsics", cam, "--out", out) == 0
        got = inout.read_depth_png(inout.list_scenes(out)[0] / "depth.png")
        np.testing.assert_array_equal(got, depth)
        meta = inout.read_json(inout.list_scenes(out)[0] / "gt.json")["meta"]
        assert meta["organised_file"] is (name == "org")
    # the organised cloud under another camera's intrinsics is refused
    other = write_intrinsics_json(tmp_path / "other.json", Intrinsics(80, 60, 30.0, 20.0, 140.0, 140.0))
    assert_failed(capsys, run_cli(tmp_path / "org.ply", "--intrinsics", other, "--out", tmp_path / "x"),
                  tmp_path / "x", "org.ply", "not this camera's intrinsics")
    # without intrinsics: an image-less scene keeping the cloud and its pixels
    out = tmp_path / "ds_none"
    assert run_cli(tmp_path / "org.ply", "--out", out) == 0
    scene = inout.list_scenes(out)[0]
    assert sorted(p.name for p in scene.iterdir()) == ["cloud.ply", "gt.json"]
    back = inout.read_ply(scene / "cloud.ply")
    np.testing.assert_array_equal(back.points, cloud.points)
    np.testing.assert_array_equal(back.rows, cloud.rows)


def _write_pcd(path, points, mode, width=None, height=1):
    width = width or len(points)
    head = (f"VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH {width}\nHEIGHT {height}\n"
            f"VIEWPOINT 0 0 0 1 0 0 0\nPOINTS {len(points)}\nDATA {mode}\n").encode()
    p = np.asarray(points, np.float32)
    body = p.astype("<f4").tobytes() if mode == "binary" else \
        "".join(f"{x!r} {y!r} {z!r}\n" for x, y, z in p.tolist()).encode()
    path.write_bytes(head + body)


@pytest.mark.parametrize("mode", ["ascii", "binary"])
def test_pcd_organised_and_unorganised(tmp_path, mode):
    depth_m, _ = render()
    depth = counts(depth_m)
    z = depth * np.float32(0.001)
    full = image_rays(INTR) * z[..., None]
    full[depth == 0] = np.nan
    full[5:8, 10:20] = np.nan  # invalid pixels of the organised cloud
    expected = depth.copy()
    expected[5:8, 10:20] = 0
    _write_pcd(tmp_path / "org.pcd", full.reshape(-1, 3), mode, width=80, height=60)
    out = tmp_path / "ds"
    assert run_cli(tmp_path / "org.pcd", "--intrinsics", write_intrinsics_json(tmp_path / "cam.json"), "--out", out) == 0
    np.testing.assert_array_equal(inout.read_depth_png(inout.list_scenes(out)[0] / "depth.png"), expected)
    pts = full.reshape(-1, 3)[::7]
    pts = pts[np.isfinite(pts).all(1)]
    _write_pcd(tmp_path / "flat.pcd", pts, mode)
    out2 = tmp_path / "ds2"
    assert run_cli(tmp_path / "flat.pcd", "--out", out2) == 0
    np.testing.assert_allclose(inout.read_ply(inout.list_scenes(out2)[0] / "cloud.ply").points, pts, atol=1e-6)


def test_xyz_image_less_and_units(tmp_path, capsys):
    rng = np.random.default_rng(0)
    pts = rng.uniform(-1, 1, (300, 3)) + [0, 0, 3]
    np.savetxt(tmp_path / "scan.xyz", pts, fmt="%.6f")
    out = tmp_path / "ds"
    assert run_cli(tmp_path / "scan.xyz", "--out", out, "--radius", "0.3") == 0
    scene = inout.list_scenes(out)[0]
    gt = inout.read_json(scene / "gt.json")
    assert gt["has_image"] is False and gt["annotated"] is False and gt["meta"]["valid_points"] == 300
    np.testing.assert_allclose(inout.read_ply(scene / "cloud.ply").points, pts, atol=1e-6)
    assert inout.read_coco_gt(out)["images"] == []
    assert "image-less" in capsys.readouterr().out
    np.savetxt(tmp_path / "mm.xyz", pts * 1000, fmt="%.3f")
    assert_failed(capsys, run_cli(tmp_path / "mm.xyz", "--out", tmp_path / "x"), tmp_path / "x",
                  "mm.xyz", "--depth-scale 0.001")
    assert run_cli(tmp_path / "mm.xyz", "--out", tmp_path / "y", "--depth-scale", "0.001") == 0
    assert "image-less" in capsys.readouterr().err  # the notes, on stderr
    np.testing.assert_allclose(inout.read_ply(inout.list_scenes(tmp_path / "y")[0] / "cloud.ply").points, pts, atol=1e-5)
    (tmp_path / "cut.xyz").write_text("1 2 3\n4 5\n")
    assert_failed(capsys, run_cli(tmp_path / "cut.xyz", "--out", tmp_path / "x"), tmp_path / "x", "cut.xyz")
    (tmp_path / "cut.ply").write_bytes((tmp_path / "y" / "scenes" / "mm" / "cloud.ply").read_bytes()[:300])
    assert_failed(capsys, run_cli(tmp_path / "cut.ply", "--out", tmp_path / "x"), tmp_path / "x", "cut.ply")


# --------------------------------------------------------------------------- annotations

def test_masks_give_circles(tmp_path, capsys):
    from spherebench.circles import mask_circle
    folder, depth, hit = png_folder(tmp_path, n=3)
    masks = tmp_path / "masks"
    masks.mkdir()
    second = np.zeros_like(hit)
    second[2:6, 3:9] = True
    inout.write_mask_png(masks / "frame_0.png", hit)
    inout.write_mask_png(masks / "frame_1_0.png", hit)
    inout.write_mask_png(masks / "frame_1_1.png", second)
    cam = write_intrinsics_json(tmp_path / "cam.json")
    out = tmp_path / "ds"
    assert run_cli(folder, "--intrinsics", cam, "--masks", masks, "--out", out) == 0
    g0, g1, g2 = (inout.read_json(s / "gt.json") for s in inout.list_scenes(out))
    assert g0["annotated"] and g1["annotated"] and not g2["annotated"]
    assert g0["balls"][0]["circle"] == pytest.approx(list(mask_circle(hit)))
    assert [b["circle"] for b in g1["balls"]] == [pytest.approx(list(mask_circle(m))) for m in (hit, second)]
    mask_back = inout.read_mask_png(out / "scenes" / "frame_1" / "mask_1.png")
    np.testing.assert_array_equal(mask_back, second)
    coco = inout.read_coco_gt(out)
    assert len(coco["images"]) == 2 and len(coco["annotations"]) == 3
    # bad masks: empty, wrong size
    inout.write_mask_png(masks / "frame_2.png", np.zeros_like(hit))
    assert_failed(capsys, run_cli(folder, "--intrinsics", cam, "--masks", masks, "--out", tmp_path / "x"),
                  tmp_path / "x", "frame_2.png", "empty")
    inout.write_mask_png(masks / "frame_2.png", np.ones((30, 40), bool))
    assert_failed(capsys, run_cli(folder, "--intrinsics", cam, "--masks", masks, "--out", tmp_path / "x"),
                  tmp_path / "x", "frame_2.png", "40x30")


def labelme(path, shapes, w=80, h=60, image="image.png"):
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps({"version": "5.4.1", "flags": {}, "shapes": shapes, "imagePath": image,
                                "imageData": None, "imageHeight": h, "imageWidth": w}, indent=2))
    return path


def shape(kind, points, label="basketball"):
    return {"label": label, "points": points, "group_id": None, "shape_type": kind, "flags": {}}


def test_labelme_circle_and_polygon(tmp_path, capsys):
    from spherebench.circles import sphere_circle_exact
    folder, depth, hit = png_folder(tmp_path, n=2)
    cam = write_intrinsics_json(tmp_path / "cam.json")
    truth = sphere_circle_exact(INTR, CENTRE, RADIUS)
    cx, cy, r = truth
    lm = tmp_path / "labelme"
    # LabelMe's coordinates put pixel centres at +0.5
    labelme(lm / "frame_0.json", [shape("circle", [[cx + 0.5, cy + 0.5], [cx + 0.5, cy + 0.5 + r]])],
            image="frame_0.png")
    a = np.linspace(0, 2 * np.pi, 40, endpoint=False)
    poly = np.stack([cx + 0.5 + (r + 0.3) * np.cos(a), cy + 0.5 + (r + 0.3) * np.sin(a)], 1)
    labelme(lm / "frame_1.json", [shape("polygon", poly.tolist()), shape("rectangle", [[1, 1], [5, 5]]),
                                  shape("polygon", [[1, 1], [9, 1], [9, 9]], label="hand")])
    out = tmp_path / "ds"
    assert run_cli(folder, "--intrinsics", cam, "--labelme", lm, "--label", "basketball", "--out", out) == 0
    g0, g1 = (inout.read_json(s / "gt.json") for s in inout.list_scenes(out))
    assert g0["balls"][0]["circle"] == pytest.approx([cx, cy, r], abs=1e-9)
    assert len(g1["balls"]) == 1  # the rectangle and the other label are not balls
    assert g1["balls"][0]["circle"] == pytest.approx([cx, cy, r], abs=1.0)
    assert json.loads((out / "scenes" / "frame_1" / "image.json").read_text())["imagePath"] == "image.png"
    err = capsys.readouterr().err  # the ignored shapes are named, once
    assert err.count("not balls were ignored") == 1 and "1 rectangle" in err and "polygon labelled 'hand'" in err
    # another image's annotation: by name, and by size
    labelme(lm / "frame_1.json", [shape("circle", [[5, 5], [9, 5]])], image="../scenes/frame_7/image.png")
    assert_failed(capsys, run_cli(folder, "--intrinsics", cam, "--labelme", lm, "--out", tmp_path / "x"),
                  tmp_path / "x", "frame_1.json", "frame_7", "not scene frame_1")
    labelme(lm / "frame_1.json", [shape("circle", [[5, 5], [9, 5]])], w=640, h=480)
    assert_failed(capsys, run_cli(folder, "--intrinsics", cam, "--labelme", lm, "--out", tmp_path / "x"),
                  tmp_path / "x", "frame_1.json", "640x480")


def test_labelme_drawn_on_prepared_dataset(tmp_path):
    """Prepare, draw on scenes/<id>/image.png in LabelMe, rerun the same command with --labelme OUT."""
    folder, depth, hit = png_folder(tmp_path, n=2)
    cam = write_intrinsics_json(tmp_path / "cam.json")
    out = tmp_path / "ds"
    assert run_cli(folder, "--intrinsics", cam, "--out", out) == 0
    labelme(out / "scenes" / "frame_1" / "image.json", [shape("circle", [[40.5, 30.5], [50.5, 30.5]])])
    assert run_cli(folder, "--intrinsics", cam, "--out", out, "--labelme", out) == 0
    g0, g1 = (inout.read_json(s / "gt.json") for s in inout.list_scenes(out))
    assert not g0["annotated"] and g1["balls"][0]["circle"] == [40.0, 30.0, 10.0]
    # the annotation survives, so the same command can be run again
    before = tree_bytes(out)
    assert run_cli(folder, "--intrinsics", cam, "--out", out, "--labelme", out) == 0
    assert tree_bytes(out) == before
