"""`spherebench show`: circles on the image, the ball's points red in the PLY."""

import json

import numpy as np
import pytest
from plyfile import PlyData

from spherebench.scripts import cli
from spherebench.camera import Intrinsics
from spherebench.cloud import Cloud
from spherebench.datasets import inout
from spherebench.datasets.drawing import BALL_RGB, REST_RGB, ball_point_colours
from spherebench.datasets.scene import Ball, Scene

INTR = Intrinsics(width=64, height=48, ppx=31.5, ppy=23.5, fx=60.0, fy=60.0)


@pytest.fixture
def dataset(tmp_path):
    v, u = np.mgrid[0:48, 0:64]
    ball = (u - 40) ** 2 + (v - 20) ** 2 <= 36
    depth = np.where(ball, 1500, 2500).astype(np.uint16)
    depth[0:3, 0:5] = 0  # no depth here
    depth[20, 40] = 0  # a hole inside the ball
    (tmp_path / "pngs").mkdir()
    inout.write_depth_png(tmp_path / "pngs" / "f.png", depth)
    (tmp_path / "masks").mkdir()
    inout.write_mask_png(tmp_path / "masks" / "f.png", ball)
    (tmp_path / "cam.json").write_text(json.dumps(INTR.to_dict()))
    out = tmp_path / "ds"
    assert cli.main(["prepare", str(tmp_path / "pngs"), "--intrinsics", str(tmp_path / "cam.json"),
                     "--masks", str(tmp_path / "masks"), "--out", str(out)]) == 0
    return out, ball, depth


def test_show_png_and_ply(dataset, tmp_path, capsys):
    out, ball, depth = dataset
    png, ply = tmp_path / "s.png", tmp_path / "s.ply"
    assert cli.main(["show", str(out / "scenes" / "f"), "--out-png", str(png), "--out-ply", str(ply)]) == 0
    img = inout.read_image(png)
    src = inout.read_image(out / "scenes" / "f")
    changed = np.any(img != src, axis=2)
    v, u = np.nonzero(changed)
    r = np.hypot(u - 40, v - 20)
    assert changed.sum() > 20 and np.median(r) == pytest.approx(6.0, abs=1.0)  # drawn on the circle
    assert img[v[0], u[0]].tolist() != src[v[0], u[0]].tolist()
    vert = PlyData.read(str(ply))["vertex"].data
    colours = np.stack([vert["red"], vert["green"], vert["blue"]], 1)
    red = np.all(colours == BALL_RGB, axis=1)
    assert red.sum() == np.count_nonzero(ball & (depth > 0))
    assert np.all(colours[~red] == REST_RGB)
    np.testing.assert_allclose(vert["z"][red], 1.5, atol=1e-6)


def test_show_image_less(tmp_path, capsys):
    pts = np.random.default_rng(1).uniform(-1, 1, (400, 3)) + [0, 0, 3]
    np.savetxt(tmp_path / "scan.xyz", pts)
    out = tmp_path / "ds"
    assert cli.main(["prepare", str(tmp_path / "scan.xyz"), "--out", str(out)]) == 0
    ply = tmp_path / "s.ply"
    assert cli.main(["show", str(out / "scenes" / "scan"), "--out-ply", str(ply)]) == 0
    assert "PLY only" in capsys.readouterr().out
    assert len(PlyData.read(str(ply))["vertex"].data) == 400
    assert cli.main(["show", str(out / "scenes" / "scan"), "--out-png", str(tmp_path / "x.png")]) == 2
    assert not (tmp_path / "x.png").exists()
    assert cli.main(["show", str(tmp_path)]) == 2


def test_image_less_ball_points_round_a_known_centre():
    pts = np.array([[0, 0, 2.0], [0, 0, 1.89], [0, 0.125, 2.0], [0, 0.2, 2.0], [1, 0, 2]], np.float32)
    scene = Scene("s", "recorded", None, cloud=Cloud(pts), balls=[Ball(radius_m=0.12, centre_m=(0, 0, 2.0))])
    _, colours, how = ball_point_colours(scene, tolerance_m=0.01)
    assert [tuple(c) == BALL_RGB for c in colours] == [True, True, True, False, False]
    assert "centre" in how
