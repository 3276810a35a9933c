"""`spherebench prepare` on ROS1 `.bag` recordings (the SDK <= 2.55 / RealSense Viewer format).

The bags are written by datasets/bagwrite.py in librealsense's ROS1 topic layout and read back
through pyrealsense2's own playback, as a user's recording would be.
"""

import numpy as np
import pytest

pytest.importorskip("pyrealsense2")

# rosbags is in the test extra (pure Python): missing, it is an error rather than a skip
from spherebench.datasets.bagwrite import write_realsense_bag  # noqa: E402

from spherebench.scripts import cli  # noqa: E402
from spherebench.camera import Intrinsics, image_rays  # noqa: E402
from spherebench.datasets import inout  # noqa: E402

# Principal point off the image centre and non-zero distortion, so that a field mixed up or
# dropped on the way (ppx/ppy swapped, coeffs lost, model defaulted) shows. All values are
# float32-exact to their shortest decimal, as librealsense keeps intrinsics in float32.
INTR = Intrinsics(width=64, height=48, ppx=33.25, ppy=22.75, fx=57.5, fy=56.8, model="inverse_brown_conrady",
                  coeffs=(0.031, -0.012, 0.0015, -0.0007, 0.004), depth_scale=0.001)
N_FRAMES = 5
FPS = 30


def render_frames(intr=INTR, n=N_FRAMES):
    """n depth frames (H, W) uint16 mm: a tilted wall with a ball of 0.12 m moving across it,
    and a few holes (0 = no depth), different in every frame so frames cannot be confused."""
    rays = image_rays(intr)  # z = 1: the ray parameter is the depth
    frames = []
    for i in range(n):
        # wall: the plane z = 1.6 + 0.2 x (m)
        wall = 1.6 / (1.0 - 0.2 * rays[..., 0])
        centre = np.array([-0.15 + 0.08 * i, 0.02 * i, 0.9 + 0.05 * i])
        a = (rays * rays).sum(-1)
        b = rays @ centre
        disc = b * b - a * (centre @ centre - 0.12 ** 2)
        ball = np.where(disc >= 0, (b - np.sqrt(np.maximum(disc, 0))) / a, np.inf)
        depth = np.round(np.minimum(wall, ball) * 1000).astype(np.uint16)
        depth[i:i + 3, 5 * i:5 * i + 4] = 0
        frames.append(depth)
    return frames


@pytest.fixture(scope="module", params=["sdk255", "older"])
def bag(request, tmp_path_factory):
    """A 5-frame depth recording; 'sdk255' as the last ROS1 SDKs write it (per-frame depth unit,
    'Depth_Units' option), 'older' without the per-frame unit and with 'Depth Units'."""
    new = request.param == "sdk255"
    frames = render_frames()
    path = write_realsense_bag(tmp_path_factory.mktemp("bag") / "d435.bag", frames, INTR, fps=FPS,
                               frame_depth_units=new, option_underscores=new)
    return path, frames


def run_prepare(*args):
    return cli.main(["prepare", *map(str, args)])


def test_frames_are_distinct_and_valid():
    frames = render_frames()
    assert all(f.dtype == np.uint16 and f.shape == (48, 64) for f in frames)
    assert all((f > 0).mean() > 0.9 for f in frames)
    assert len({f.tobytes() for f in frames}) == N_FRAMES
    # the ball is in every frame: depths well in front of the wall
    assert all(((f > 0) & (f < 1200)).sum() > 20 for f in frames)


def test_bag_round_trip(bag, tmp_path):
    path, frames = bag
    assert path.read_bytes().startswith(b"#ROSBAG V2.0\n")
    out = tmp_path / "ds"
    assert run_prepare(path, "--out", out) == 0
    scenes = inout.list_scenes(out)
    assert [s.name for s in scenes] == [f"d435_{i:06d}" for i in range(N_FRAMES)]
    for i, (scene, frame) in enumerate(zip(scenes, frames)):
        depth = inout.read_depth_png(scene / "depth.png")
        assert depth.dtype == np.uint16
        np.testing.assert_array_equal(depth, frame)
        assert inout.read_json(scene / "intrinsics.json") == INTR.to_dict()
        meta = inout.read_json(scene / "gt.json")["meta"]
        assert meta["frame_index"] == i and meta["frame_number"] == i
        assert meta["time_from_first_frame_ms"] == pytest.approx(i * 1000 / FPS, abs=1e-3)
    assert inout.read_dataset_meta(out)["source"] == {"kind": "realsense-recording", "files": ["d435.bag"]}


@pytest.mark.parametrize("options, kept", [(["--every", "2"], [0, 2, 4]),
                                           (["--frames", "1:4", "--every", "2"], [1, 3]),
                                           (["--time-range", "30:70"], [1, 2])])
def test_bag_frame_selection(bag, tmp_path, options, kept):
    path, frames = bag
    out = tmp_path / "ds"
    assert run_prepare(path, "--out", out, *options) == 0
    scenes = inout.list_scenes(out)
    assert [s.name for s in scenes] == [f"d435_{i:06d}" for i in kept]
    for scene, i in zip(scenes, kept):
        np.testing.assert_array_equal(inout.read_depth_png(scene / "depth.png"), frames[i])


def test_bag_without_depth_stream(tmp_path, capsys):
    colour = [np.full((48, 64, 3), 40 * i, np.uint8) for i in range(3)]
    path = write_realsense_bag(tmp_path / "colour_only.bag", colour, INTR, stream="color")
    out = tmp_path / "ds"
    rc = run_prepare(path, "--out", out)
    err = capsys.readouterr().err.strip()
    assert rc == 2, err
    assert len(err.splitlines()) == 1 and err.startswith("spherebench prepare: error:"), err
    assert "colour_only.bag" in err and "no depth stream" in err, err
    assert not out.exists()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".tmp-ds")]
