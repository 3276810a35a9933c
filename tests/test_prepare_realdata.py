"""The real-data recipes (`--preset-source`) on a couple of frames of ../shared/realdata."""

from pathlib import Path

import numpy as np
import pytest

from spherebench.scripts import cli
from spherebench.datasets import inout

REALDATA = Path(__file__).resolve().parents[1].parent / "shared" / "realdata"
pytestmark = pytest.mark.skipif(not REALDATA.is_dir(), reason=f"{REALDATA} is absent")


def test_kinect_pochang_recipe(tmp_path, capsys):
    out = tmp_path / "kinect"
    assert cli.main(["prepare", "--preset-source", "kinect-pochang", "--out", str(out), "--frames", "8:10"]) == 0
    assert "unannotated" in capsys.readouterr().err  # a note: stderr
    meta = inout.read_dataset_meta(out)
    assert meta["ball_radius_m"] == 0.203 and meta["preset"] == "kinect-pochang"
    s24, s27 = inout.list_scenes(out)
    assert (s24.name, s27.name) == ("kinect_1_dep_24", "kinect_1_dep_27")
    intr = inout.read_intrinsics(s24)
    assert (intr.width, intr.height, intr.fx, intr.depth_scale) == (640, 480, 524.63924760208079, 0.001)
    raw = np.fromfile(REALDATA / "pochang_rgbd_sphere/sensors/Kinect_1/kinect_1_dep_24.dat", "<u2").reshape(480, 640)
    np.testing.assert_array_equal(inout.read_depth_png(s24 / "depth.png"), raw)
    g24, g27 = inout.read_json(s24 / "gt.json"), inout.read_json(s27 / "gt.json")
    assert not g24["annotated"] and g24["ball_radius_m"] == 0.203
    # frame 24 was tracked by the authors, 27 was not (path_01.txt: "27 0 0 -1000")
    assert "reference_center_m" in g24["meta"] and "reference_center_m" not in g27["meta"]
    centre = np.asarray(g24["meta"]["reference_center_m"])
    cloud = inout.load_cloud(s24)
    d = np.linalg.norm(cloud.points - centre, axis=1)
    assert np.count_nonzero(np.abs(d - 0.203) < 0.02) > 500  # the authors' centre sits in a ball of our points


def test_lidar_spherecalib_recipe(tmp_path, capsys):
    out = tmp_path / "lidar"
    assert cli.main(["prepare", "--preset-source", "lidar-spherecalib", "--out", str(out), "--frames", "8:10"]) == 0
    printed = capsys.readouterr()
    assert "image-less" in printed.out and "skipped" in printed.err  # the summary on stdout, notes on stderr
    assert inout.read_dataset_meta(out)["ball_radius_m"] == 0.3
    scenes = inout.list_scenes(out)
    assert [s.name for s in scenes] == ["example3_L1_S1", "example3_L1_S2"]
    assert sorted(p.name for p in scenes[0].iterdir()) == ["cloud.ply", "gt.json"]
    src = np.loadtxt(REALDATA / "spherecalib_lidar/examples/example3/data3D/L1_S1.xyz")
    np.testing.assert_allclose(inout.read_ply(scenes[0] / "cloud.ply").points, src, atol=1e-5)
    assert inout.read_coco_gt(out)["images"] == []
