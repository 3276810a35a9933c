"""RealSense recordings with a colour stream: `prepare` pairs each depth frame with the colour
frame nearest in time and keeps it aligned to the depth (colour.png), so that `annotate
--from-colour` and `prepare --labelme` work on a D435 recording as on the Kinect set.

The scenes are ray-cast twice, once in each camera, so the colour frame shows the ball where the
colour camera sees it; the bags are written by datasets/bagwrite.py (ROS1) and by pyrealsense2's
own recorder (ROS2, .db3) and read back through pyrealsense2 playback.
"""

from __future__ import annotations

import gc

import cv2
import numpy as np
import pytest

rs = pytest.importorskip("pyrealsense2")

from spherebench.datasets.bagwrite import ColourStream, write_realsense_bag  # noqa: E402

from spherebench.scripts import cli  # noqa: E402
from spherebench.camera import Intrinsics, align_to_depth, image_rays, project  # noqa: E402
from spherebench.datasets import inout  # noqa: E402

# a D435 at 424x240 depth; colour of another size, field of view and distortion, 15 mm to the side
DEPTH = Intrinsics(width=424, height=240, ppx=211.5, ppy=119.25, fx=213.0, fy=213.0, model="brown_conrady",
                   depth_scale=0.001)
COLOUR = Intrinsics(width=640, height=480, ppx=321.5, ppy=238.75, fx=615.0, fy=614.5,
                    model="inverse_brown_conrady", coeffs=(0.08, -0.05, 0.002, -0.001, 0.01))
_AY, _AX = np.radians(0.3), np.radians(-0.2)
ROTATION = (np.array([[np.cos(_AY), 0, np.sin(_AY)], [0, 1, 0], [-np.sin(_AY), 0, np.cos(_AY)]])
            @ np.array([[1, 0, 0], [0, np.cos(_AX), -np.sin(_AX)], [0, np.sin(_AX), np.cos(_AX)]]))
TRANSLATION = np.array([0.015, 0.0003, -0.0002])
RADIUS = 0.12
WALL = (np.array([-0.2, 0.0, 1.0]), 1.6)  # the plane n . p = d in the depth camera's frame: z = 1.6 + 0.2 x
YELLOW = (0, 220, 255)  # BGR
WALL_BGR = (90, 110, 130)
N_FRAMES = 3


def centre(i: int) -> np.ndarray:
    return np.array([0.04 + 0.03 * i, 0.02, 0.5 + 0.05 * i])


def ray_cast(rays: np.ndarray, ball_centre: np.ndarray, normal: np.ndarray, dist: float):
    """(depth z of the first hit (rays have z = 1), the ball is that hit) along each ray."""
    a = (rays * rays).sum(-1)
    b = rays @ ball_centre
    disc = b * b - a * (ball_centre @ ball_centre - RADIUS ** 2)
    ball = np.where(disc >= 0, (b - np.sqrt(np.maximum(disc, 0))) / a, np.inf)
    wall = dist / (rays @ normal)
    return np.minimum(ball, wall), ball < wall


def render(i: int, colour_intr: Intrinsics = COLOUR, rotation=ROTATION, translation=TRANSLATION):
    """Frame i: (depth counts (H, W) uint16 mm, the ball's silhouette in depth (H, W) bool,
    the colour camera's image (h, w, 3) uint8 BGR: a yellow ball on a brown-grey wall)."""
    z, ball = ray_cast(image_rays(DEPTH), centre(i), *WALL)
    depth = np.round(z * 1000).astype(np.uint16)
    # the same scene in the colour camera's frame: p_c = R p_d + t
    rot, trans = np.asarray(rotation), np.asarray(translation)
    normal = rot @ WALL[0]
    _, seen = ray_cast(image_rays(colour_intr), rot @ centre(i) + trans, normal, WALL[1] + normal @ trans)
    colour = np.empty(colour_intr.shape + (3,), np.uint8)
    colour[...] = WALL_BGR
    colour[seen] = YELLOW
    return depth, ball, colour


def yellow(image_bgr: np.ndarray) -> np.ndarray:
    return np.all(image_bgr == YELLOW, axis=-1)


def yuv422(image_bgr: np.ndarray, uyvy: bool = False) -> np.ndarray:
    """(H, W, 2) uint8 YUYV (or UYVY) bytes of a BGR image, BT.601 as OpenCV converts them back."""
    yuv = cv2.cvtColor(image_bgr, cv2.COLOR_BGR2YUV).astype(np.float64)
    out = np.empty(image_bgr.shape[:2] + (2,), np.uint8)
    chroma = (yuv[:, 0::2, 1:] + yuv[:, 1::2, 1:]) / 2  # (H, W / 2, [U, V])
    out[..., 1 if uyvy else 0] = yuv[..., 0]
    out[:, 0::2, 0 if uyvy else 1] = np.round(chroma[..., 0])
    out[:, 1::2, 0 if uyvy else 1] = np.round(chroma[..., 1])
    return out


def within_one_pixel(mask: np.ndarray, silhouette: np.ndarray) -> bool:
    """mask lies inside the silhouette grown by 1 px and covers it shrunk by 1 px."""
    k = np.ones((3, 3), np.uint8)
    grown = cv2.dilate(silhouette.astype(np.uint8), k).astype(bool)
    shrunk = cv2.erode(silhouette.astype(np.uint8), k).astype(bool)
    return bool(np.all(grown | ~mask) and np.all(mask | ~shrunk))


def run_prepare(*args):
    return cli.main(["prepare", *map(str, args)])


# --------------------------------------------------------------------------- the geometry

@pytest.mark.parametrize("model", ["none", "brown_conrady", "modified_brown_conrady", "inverse_brown_conrady"])
def test_projection_is_librealsenses(model):
    """The colour projection is rs2_project_point_to_pixel's, distortion model included."""
    intr = Intrinsics(width=640, height=480, ppx=321.5, ppy=238.75, fx=615.0, fy=614.5, model=model,
                      coeffs=(0.08, -0.05, 0.002, -0.001, 0.01))
    rng = np.random.default_rng(1)
    points = np.c_[rng.uniform(-0.4, 0.4, (300, 2)), rng.uniform(0.4, 3.0, 300)]
    theirs = np.array([rs.rs2_project_point_to_pixel(intr.to_rs(), list(p)) for p in points])
    np.testing.assert_allclose(project(intr, points), theirs, atol=1e-3)  # px; librealsense is float32


def test_alignment_matches_librealsense_pixel_for_pixel():
    """Each coloured depth pixel holds the colour pixel that librealsense's deproject / transform /
    project functions find for it, rounded to the nearest (bar float32 ties at a half pixel)."""
    depth, ball, _ = render(0)
    rng = np.random.default_rng(2)
    noise = rng.integers(0, 256, COLOUR.shape + (3,), dtype=np.uint8)  # every pixel its own value
    aligned, counts = align_to_depth(depth * 0.001, DEPTH, noise, COLOUR, ROTATION, TRANSLATION)
    extrinsics = rs.extrinsics()
    extrinsics.rotation = list(ROTATION.T.ravel())  # column-major
    extrinsics.translation = list(TRANSLATION)
    rows, cols = np.nonzero(np.any(aligned > 0, axis=-1))
    pick = rng.choice(len(rows), 400, replace=False)
    agree = 0
    for r, c in zip(rows[pick], cols[pick]):
        p = rs.rs2_deproject_pixel_to_point(DEPTH.to_rs(), [float(c), float(r)], float(depth[r, c]) * 0.001)
        q = rs.rs2_transform_point_to_point(extrinsics, p)
        u, v = rs.rs2_project_point_to_pixel(COLOUR.to_rs(), q)
        agree += np.array_equal(aligned[r, c], noise[int(np.floor(v + 0.5)), int(np.floor(u + 0.5))])
    assert agree >= 398, agree
    assert counts["with_depth"] == DEPTH.width * DEPTH.height
    assert counts["coloured"] + counts["off_image"] + counts["occluded"] == counts["with_depth"]


def test_aligned_ball_is_the_depth_silhouette_and_the_shadow_stays_black():
    depth, ball, colour = render(0)
    aligned, counts = align_to_depth(depth * 0.001, DEPTH, colour, COLOUR, ROTATION, TRANSLATION)
    assert within_one_pixel(yellow(aligned), ball)
    # the wall beside the ball that the colour camera sees only behind the ball: black, not yellow
    assert counts["occluded"] > 100
    hidden = ~np.any(aligned > 0, axis=-1) & ~ball
    grown = cv2.dilate(ball.astype(np.uint8), np.ones((15, 15), np.uint8)).astype(bool)
    assert (hidden & grown).sum() > 100  # beside the ball (the rest of the black is off the colour image)
    # the test can tell: without the extrinsics the disc would sit several pixels off
    naive, _ = align_to_depth(depth * 0.001, DEPTH, colour, COLOUR, np.eye(3), np.zeros(3))
    assert not within_one_pixel(yellow(naive), ball)
    # where depth is missing the aligned colour is black
    holed = depth.copy()
    holed[100:110, 200:220] = 0
    aligned2, _ = align_to_depth(holed * 0.001, DEPTH, colour, COLOUR, ROTATION, TRANSLATION)
    assert not aligned2[100:110, 200:220].any()
    np.testing.assert_array_equal(aligned2[:90], aligned[:90])


# --------------------------------------------------------------------------- recordings

def colour_bag(path, colour_intr=COLOUR, encoding="rgb8", n=N_FRAMES, **stream):
    """A D435-like recording: N depth frames at 30 fps and colour frames 10 ms after each."""
    frames = [render(i, colour_intr) for i in range(n)]
    colour = [c for _, _, c in frames]
    if encoding in ("rgb8", "rgba8"):
        colour = [cv2.cvtColor(c, cv2.COLOR_BGR2RGB if encoding == "rgb8" else cv2.COLOR_BGR2RGBA) for c in colour]
    elif encoding == "bgra8":
        colour = [cv2.cvtColor(c, cv2.COLOR_BGR2BGRA) for c in colour]
    elif encoding == "mono8":
        colour = [c[..., 0].copy() for c in colour]
    elif encoding in ("YUYV", "yuv422"):  # 4:2:2, a U and a V to each pair of pixels (yuv422 = UYVY)
        colour = [yuv422(c, uyvy=encoding == "yuv422") for c in colour]
    stream = {"rotation": ROTATION, "translation": TRANSLATION, "first_timestamp_ms": 1010.0, **stream}
    write_realsense_bag(path, [d for d, _, _ in frames], DEPTH,
                        colour=ColourStream(colour, colour_intr, encoding=encoding, **stream))
    return path, frames


@pytest.fixture(scope="module")
def d435(tmp_path_factory):
    return colour_bag(tmp_path_factory.mktemp("bag") / "d435.bag")


def test_the_writer_records_the_calibration(d435):
    dev = rs.context().load_device(str(d435[0]))
    profiles = {p.stream_type(): p for s in dev.query_sensors() for p in s.get_stream_profiles()}
    ext = profiles[rs.stream.depth].get_extrinsics_to(profiles[rs.stream.color])
    np.testing.assert_allclose(np.array(ext.rotation).reshape(3, 3).T, ROTATION, atol=1e-6)
    np.testing.assert_allclose(ext.translation, TRANSLATION, atol=1e-7)
    assert str(profiles[rs.stream.color].as_video_stream_profile().get_intrinsics().model) == \
        "distortion.inverse_brown_conrady"


def test_prepare_keeps_the_colour_aligned_to_the_depth(d435, tmp_path, capsys):
    path, frames = d435
    out = tmp_path / "ds"
    assert run_prepare(path, "--out", out) == 0
    assert "colour" not in capsys.readouterr().err  # nothing to say
    scenes = inout.list_scenes(out)
    assert len(scenes) == N_FRAMES
    for i, (scene, (depth, ball, _)) in enumerate(zip(scenes, frames)):
        np.testing.assert_array_equal(inout.read_depth_png(scene / "depth.png"), depth)
        colour = cv2.imread(str(scene / "colour.png"), cv2.IMREAD_UNCHANGED)
        assert colour.shape == (DEPTH.height, DEPTH.width, 3)
        assert within_one_pixel(yellow(colour), ball), scene.name
        meta = inout.read_json(scene / "gt.json")["meta"]["colour"]
        assert meta["frame_number"] == i and meta["offset_ms"] == pytest.approx(10.0, abs=1e-3)
        assert meta["format"] == "rgb8" and meta["intrinsics"]["model"] == "inverse_brown_conrady"
        assert meta["depth_to_colour"]["translation_m"] == pytest.approx(list(TRANSLATION), abs=1e-7)
        assert meta["aligned_pixels"]["occluded"] > 0
        assert not (scene / "colour.jpg").exists()


def test_colour_from_a_recording_is_byte_identical(d435, tmp_path):
    a, b = tmp_path / "1" / "ds", tmp_path / "2" / "ds"
    assert run_prepare(d435[0], "--out", a, "--frames", "0:2") == 0
    assert run_prepare(d435[0], "--out", b, "--frames", "0:2") == 0
    tree = {str(p.relative_to(a)): p.read_bytes() for p in sorted(a.rglob("*")) if p.is_file()}
    assert tree == {str(p.relative_to(b)): p.read_bytes() for p in sorted(b.rglob("*")) if p.is_file()}
    assert sum(name.endswith("colour.png") for name in tree) == 2


def test_annotate_from_colour_and_labelme_round_trip_on_a_recording(d435, tmp_path, capsys):
    """The Kinect set's path: prepare, annotate --from-colour, prepare --labelme; the masks are
    the depth silhouettes and the mask-fit centres the true ones."""
    path, frames = d435
    out = tmp_path / "ds"
    assert run_prepare(path, "--out", out) == 0
    assert cli.main(["annotate", str(out), "--from-colour"]) == 0
    scenes = inout.list_scenes(out)
    assert all((s / "colour.json").is_file() for s in scenes)
    assert inout.read_json(scenes[0] / "colour.json")["imagePath"] == "colour.png"
    assert run_prepare(path, "--labelme", out, "--out", out) == 0
    capsys.readouterr()
    for i, (scene, (_, ball, _)) in enumerate(zip(inout.list_scenes(out), frames)):
        assert (scene / "colour.json").is_file() and (scene / "colour.png").is_file()
        gt = inout.read_json(scene / "gt.json")
        assert gt["annotated"] and len(gt["balls"]) == 1
        mask = inout.read_mask_png(scene / gt["balls"][0]["mask"])
        assert within_one_pixel(mask, ball)
        assert np.linalg.norm(np.array(gt["balls"][0]["center_m"]) - centre(i)) < 0.005


@pytest.mark.parametrize("size", [(424, 240), (212, 120)])
def test_colour_of_the_depths_size_or_smaller(tmp_path, size):
    w, h = size
    s = w / 640
    intr = Intrinsics(width=w, height=h, ppx=(COLOUR.ppx + 0.5) * s - 0.5, ppy=(COLOUR.ppy + 0.5) * h / 480 - 0.5,
                      fx=COLOUR.fx * s, fy=COLOUR.fy * h / 480, model="none")
    path, frames = colour_bag(tmp_path / "small.bag", intr, n=1)
    out = tmp_path / "ds"
    assert run_prepare(path, "--out", out) == 0
    colour = cv2.imread(str(inout.list_scenes(out)[0] / "colour.png"), cv2.IMREAD_UNCHANGED)
    assert colour.shape == (DEPTH.height, DEPTH.width, 3)
    # a colour pixel larger than a depth pixel: the disc's edge is as sharp as the colour's pixels
    ball = frames[0][1]
    k = np.ones((3, 3), np.uint8) if w == 424 else np.ones((5, 5), np.uint8)
    assert np.all(cv2.dilate(ball.astype(np.uint8), k).astype(bool) | ~yellow(colour))
    assert np.all(yellow(colour) | ~cv2.erode(ball.astype(np.uint8), k).astype(bool))


@pytest.mark.parametrize("encoding", ["bgr8", "rgba8", "bgra8", "YUYV", "yuv422"])
def test_colour_formats(tmp_path, encoding):
    path, frames = colour_bag(tmp_path / f"{encoding}.bag", encoding=encoding, n=1)
    out = tmp_path / "ds"
    assert run_prepare(path, "--out", out) == 0
    colour = cv2.imread(str(inout.list_scenes(out)[0] / "colour.png"), cv2.IMREAD_UNCHANGED).astype(int)
    if encoding in ("YUYV", "yuv422"):  # chroma shared by two pixels, and YUV's rounding
        ball = (colour[..., 2] > 200) & (colour[..., 1] > 150) & (colour[..., 0] < 100)
        assert np.abs(colour[ball] - YELLOW).max() <= 40
    else:
        ball = yellow(colour)
    assert within_one_pixel(ball, frames[0][1])


def test_a_recording_without_colour_notes_it_once(tmp_path, capsys):
    depth = [render(i)[0] for i in range(2)]
    path = write_realsense_bag(tmp_path / "depth_only.bag", depth, DEPTH)
    out = tmp_path / "ds"
    assert run_prepare(path, "--out", out) == 0
    err = [line for line in capsys.readouterr().err.splitlines() if "colour" in line]
    assert len(err) == 1 and "depth_only.bag" in err[0] and "no colour stream" in err[0], err
    assert not [p for p in out.rglob("colour.*")]
    assert "colour" not in inout.read_json(inout.list_scenes(out)[0] / "gt.json")["meta"]


def test_an_unsupported_colour_format_is_a_clear_note_and_no_colour_file(tmp_path, capsys):
    path, _ = colour_bag(tmp_path / "mono.bag", encoding="mono8", n=2)
    out = tmp_path / "ds"
    assert run_prepare(path, "--out", out) == 0
    err = [line for line in capsys.readouterr().err.splitlines() if "colour" in line]
    assert len(err) == 1 and "mono.bag" in err[0] and "raw8" in err[0] and "rgb8" in err[0], err
    assert len(inout.list_scenes(out)) == 2 and not [p for p in out.rglob("colour.*")]
    # annotate then says, in one line, that there is nothing to annotate from
    assert cli.main(["annotate", str(out), "--from-colour"]) == 2
    assert len(capsys.readouterr().err.strip().splitlines()) == 1


def test_pairing_takes_the_nearest_colour_frame_and_notes_the_unpaired(tmp_path, capsys):
    """Colour at 15 fps with one frame lost: each depth frame gets the nearest colour frame (ties
    to the earlier) within half a colour period and 1 ms; one farther gets none, said once."""
    small_d = Intrinsics(width=32, height=24, ppx=15.5, ppy=11.5, fx=28.0, fy=28.0, depth_scale=0.001)
    small_c = Intrinsics(width=32, height=24, ppx=15.5, ppy=11.5, fx=28.0, fy=28.0)
    depth = [np.full((24, 32), 1000 + i, np.uint16) for i in range(10)]
    stamps = [1000.0 + 1000.0 / 15 * k for k in range(5)]
    del stamps[3]  # colour frames at 0, 66.7, 133.3 and 266.7 ms from the first depth frame
    colour = [np.full((24, 32, 3), 20 * k, np.uint8) for k in range(len(stamps))]
    path = write_realsense_bag(tmp_path / "drop.bag", depth, small_d,
                               colour=ColourStream(colour, small_c, fps=15, timestamps_ms=stamps))
    out = tmp_path / "ds"
    assert run_prepare(path, "--out", out) == 0
    err = [line for line in capsys.readouterr().err.splitlines() if "colour" in line]
    scenes = inout.list_scenes(out)
    numbers = [inout.read_json(s / "gt.json")["meta"]["colour"]["frame_number"] for s in scenes]
    # depth at 0, 33.3, ..., 300 ms; the frame lost at 200 ms leaves 200 ms 66.7 ms from either neighbour
    assert numbers == [0, 0, 1, 1, 2, 2, 2, 3, 3, 3]
    assert [(s / "colour.png").is_file() for s in scenes] == [True] * 6 + [False] + [True] * 3
    offsets = [inout.read_json(s / "gt.json")["meta"]["colour"]["offset_ms"] for s in scenes]
    assert offsets[:3] == pytest.approx([0.0, -1000 / 30, 0.0], abs=1e-3)
    assert len(err) == 1 and "1 frame(s) have no colour" in err[0] and "drop_000006" in err[0], err
    assert "66.7 ms away" in err[0]


def test_frames_beyond_a_colour_period_keep_no_colour(tmp_path, capsys):
    small_d = Intrinsics(width=32, height=24, ppx=15.5, ppy=11.5, fx=28.0, fy=28.0, depth_scale=0.001)
    depth = [np.full((24, 32), 1000 + i, np.uint16) for i in range(6)]
    colour = [np.full((24, 32, 3), 200, np.uint8)] * 2  # colour stops at 33 ms
    path = write_realsense_bag(tmp_path / "stop.bag", depth, small_d, colour=ColourStream(colour, small_d))
    out = tmp_path / "ds"
    assert run_prepare(path, "--out", out) == 0
    err = [line for line in capsys.readouterr().err.splitlines() if "colour" in line]
    kept = [(s / "colour.png").is_file() for s in inout.list_scenes(out)]
    assert kept == [True, True, False, False, False, False]  # 66.7 ms is 33.3 ms from the last
    assert len(err) == 1 and "4 frame(s) have no colour" in err[0] and "stop_000002" in err[0], err


def test_colour_in_another_clock_domain_is_not_paired(tmp_path, capsys):
    path, _ = colour_bag(tmp_path / "clock.bag", n=2, timestamp_domain="System Time")
    out = tmp_path / "ds"
    assert run_prepare(path, "--out", out) == 0
    err = [line for line in capsys.readouterr().err.splitlines() if "colour" in line]
    assert len(err) == 1 and "clock domains" in err[0], err
    assert not [p for p in out.rglob("colour.*")]


def test_ros2_recording_with_colour(tmp_path):
    """The SDK's own recorder (ROS2 .db3, pyrealsense2 >= 2.56): depth and colour sensors of a
    software device with their extrinsics, played back like a user's recording."""
    dev = rs.software_device()
    sensors, profiles, streams = [], [], []
    for uid, (name, kind, intr, fmt, bpp) in enumerate((("Stereo Module", rs.stream.depth, DEPTH, rs.format.z16, 2),
                                                         ("RGB Camera", rs.stream.color, COLOUR, rs.format.bgr8, 3))):
        vs = rs.video_stream()
        vs.type, vs.index, vs.uid, vs.width, vs.height, vs.fps = kind, 0, uid, intr.width, intr.height, 30
        vs.bpp, vs.fmt, vs.intrinsics = bpp, fmt, intr.to_rs()
        sensors.append(dev.add_sensor(name))
        profiles.append(sensors[-1].add_video_stream(vs))
        streams.append(vs)
    sensors[0].add_read_only_option(rs.option.depth_units, 0.001)
    extrinsics = rs.extrinsics()
    extrinsics.rotation, extrinsics.translation = list(ROTATION.T.ravel()), list(TRANSLATION)
    profiles[0].register_extrinsics_to(profiles[1], extrinsics)
    path = tmp_path / "d435.db3"
    recorder = rs.recorder(str(path), dev)
    queue = rs.frame_queue(8)
    for s, p in zip(sensors, profiles):
        s.open(p)
        s.start(queue)
    frames = [render(i) for i in range(2)]
    for i, (depth, _, colour) in enumerate(frames):
        for k, image in ((0, depth), (1, colour)):
            f = rs.software_video_frame()
            f.pixels = np.ascontiguousarray(image)
            f.bpp, f.stride = streams[k].bpp, streams[k].bpp * streams[k].width
            f.timestamp, f.domain, f.frame_number = 1000.0 + 33.3 * i + 5 * k, rs.timestamp_domain.hardware_clock, i
            f.profile = profiles[k].as_video_stream_profile()
            if k == 0:
                f.depth_units = 0.001
            sensors[k].on_video_frame(f)
            queue.wait_for_frame(2000)
    for s in sensors:
        s.stop()
        s.close()
    del recorder
    gc.collect()
    out = tmp_path / "ds"
    assert run_prepare(path, "--out", out) == 0
    for scene, (_, ball, _) in zip(inout.list_scenes(out), frames):
        assert within_one_pixel(yellow(cv2.imread(str(scene / "colour.png"))), ball)


def test_colour_on_the_depth_sensor(tmp_path):
    """A D405 records colour on its depth sensor: the sensor is opened with both streams at once."""
    path, frames = colour_bag(tmp_path / "d405.bag", n=2, on_depth_sensor=True)
    dev = rs.context().load_device(str(path))
    assert len(dev.query_sensors()) == 1
    out = tmp_path / "ds"
    assert run_prepare(path, "--out", out) == 0
    for scene, (_, ball, _) in zip(inout.list_scenes(out), frames):
        assert within_one_pixel(yellow(cv2.imread(str(scene / "colour.png"))), ball)
