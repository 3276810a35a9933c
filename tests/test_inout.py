"""The readers added to datasets/inout.py for recorded data: PCD, raw frames, camera JSON, LabelMe."""

import json

import numpy as np
import pytest

from spherebench.datasets import foreign_formats, inout
from spherebench.errors import SphereBenchError


def _pcd_header(fields, sizes, types, width, height, data):
    return ("# .PCD v0.7\nVERSION 0.7\n"
            f"FIELDS {' '.join(fields)}\nSIZE {' '.join(map(str, sizes))}\nTYPE {' '.join(types)}\n"
            f"COUNT {' '.join('1' for _ in fields)}\nWIDTH {width}\nHEIGHT {height}\n"
            f"VIEWPOINT 0 0 0 1 0 0 0\nPOINTS {width * height}\nDATA {data}\n").encode()


def _lzf_literals(data: bytes) -> bytes:
    """A valid LZF stream made of literal runs only (what a compressor may emit for noise)."""
    out = bytearray()
    for i in range(0, len(data), 32):
        chunk = data[i:i + 32]
        out.append(len(chunk) - 1)
        out += chunk
    return bytes(out)


@pytest.fixture
def points():
    rng = np.random.default_rng(3)
    return rng.uniform(-2, 2, size=(200, 3)).astype(np.float32)


@pytest.mark.parametrize("mode", ["ascii", "binary", "binary_compressed"])
def test_read_pcd_matches_open3d_writer(tmp_path, points, mode):
    o3d = pytest.importorskip("open3d")
    pts = points.copy()
    pts[:100] = np.round(pts[:100], 1)  # repeats, so the compressor emits back references
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts.astype(np.float64)))
    path = tmp_path / f"c_{mode}.pcd"
    o3d.io.write_point_cloud(str(path), pc, write_ascii=mode == "ascii", compressed=mode == "binary_compressed")
    assert f"DATA {mode}".encode() in path.read_bytes()[:400]
    cloud = foreign_formats.read_pcd(path)
    assert cloud.rows is None and len(cloud) == len(pts)
    np.testing.assert_allclose(cloud.points, pts, atol=1e-6)
    assert inout.load_cloud(path).points.shape == (len(pts), 3)  # registered in CLOUD_READERS


def test_read_pcd_organised_with_nan_and_padding_field(tmp_path):
    w, h = 4, 3
    rec = np.zeros(w * h, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("rgb", "<f4")])
    rec["x"] = np.arange(w * h)
    rec["y"], rec["z"] = 1.0, 2.0
    rec["x"][[1, 7]] = np.nan  # invalid pixels of an organised cloud
    path = tmp_path / "org.pcd"
    path.write_bytes(_pcd_header(["x", "y", "z", "rgb"], [4] * 4, ["F"] * 4, w, h, "binary") + rec.tobytes())
    cloud = foreign_formats.read_pcd(path)
    assert len(cloud) == 10
    keep = [i for i in range(12) if i not in (1, 7)]
    np.testing.assert_array_equal(cloud.rows, np.array(keep) // w)
    np.testing.assert_array_equal(cloud.cols, np.array(keep) % w)
    np.testing.assert_array_equal(cloud.points[:, 0], np.array(keep, np.float32))
    # column-major binary_compressed layout of the same data (a literal-only LZF stream)
    plain = b"".join(rec[name].tobytes() for name in ("x", "y", "z", "rgb"))
    comp = _lzf_literals(plain)
    path2 = tmp_path / "org_c.pcd"
    path2.write_bytes(_pcd_header(["x", "y", "z", "rgb"], [4] * 4, ["F"] * 4, w, h, "binary_compressed")
                      + np.array([len(comp), len(plain)], "<u4").tobytes() + comp)
    c2 = foreign_formats.read_pcd(path2)
    np.testing.assert_array_equal(c2.points, cloud.points)
    np.testing.assert_array_equal(c2.rows, cloud.rows)


@pytest.mark.parametrize("damage", ["truncate", "garbage", "points", "compressed"])
def test_read_pcd_bad_files(tmp_path, points, damage):
    body = _pcd_header(["x", "y", "z"], [4] * 3, ["F"] * 3, len(points), 1, "binary") + points.tobytes()
    if damage == "truncate":
        body = body[:len(body) - 100]
    elif damage == "garbage":
        body = b"\x00\x01 not a point cloud at all"
    elif damage == "points":
        body = body.replace(f"POINTS {len(points)}".encode(), b"POINTS 7")
    else:  # a binary_compressed body cut short
        plain = b"".join(np.ascontiguousarray(points[:, k]).tobytes() for k in range(3))
        comp = _lzf_literals(plain)
        body = (_pcd_header(["x", "y", "z"], [4] * 3, ["F"] * 3, len(points), 1, "binary_compressed")
                + np.array([len(comp), len(plain)], "<u4").tobytes() + comp[:len(comp) // 2])
    path = tmp_path / "bad.pcd"
    path.write_bytes(body)
    with pytest.raises(SphereBenchError, match="bad.pcd"):
        foreign_formats.read_pcd(path)


def test_read_raw_depth_orders_and_size(tmp_path):
    d = np.arange(12, dtype=np.uint16).reshape(3, 4) * 300
    (tmp_path / "le.raw").write_bytes(d.astype("<u2").tobytes())
    (tmp_path / "be.raw").write_bytes(d.astype(">u2").tobytes())
    f = d.astype(np.float32) / 1000
    (tmp_path / "bef.raw").write_bytes(f.astype(">f4").tobytes())
    np.testing.assert_array_equal(foreign_formats.read_raw_depth(tmp_path / "le.raw", 4, 3), d)
    np.testing.assert_array_equal(foreign_formats.read_raw_depth(tmp_path / "be.raw", 4, 3, byte_order="big"), d)
    np.testing.assert_array_equal(foreign_formats.read_raw_depth(tmp_path / "bef.raw", 4, 3, "float32", "big"), f)
    with pytest.raises(SphereBenchError, match="truncated"):
        foreign_formats.read_raw_depth(tmp_path / "le.raw", 5, 3)


def test_read_camera_json_lenient(tmp_path):
    d = {"width": 848, "height": 480, "ppx": 421.5, "ppy": 240.25, "fx": 426.0, "fy": 425.5,
         "model": "Brown Conrady", "coeffs": [0.1, 0, 0, 0, 0]}
    (tmp_path / "a.json").write_text(json.dumps({"depth": d}))
    intr = foreign_formats.read_camera_json(tmp_path / "a.json")
    assert intr.model == "brown_conrady" and intr.fx == 426.0 and intr.depth_scale == 0.001
    (tmp_path / "b.json").write_text(json.dumps({"width": 848, "fx": 1}))
    with pytest.raises(SphereBenchError, match="b.json.*lack"):
        foreign_formats.read_camera_json(tmp_path / "b.json")
    (tmp_path / "c.json").write_text('{"width": 8')
    with pytest.raises(SphereBenchError, match="truncated"):
        foreign_formats.read_camera_json(tmp_path / "c.json")


def test_read_labelme_checks_structure(tmp_path):
    good = {"shapes": [{"label": "ball", "shape_type": "circle", "points": [[1, 2], [3, 4]]}],
            "imagePath": "image.png", "imageWidth": 8, "imageHeight": 6}
    (tmp_path / "g.json").write_text(json.dumps(good))
    assert foreign_formats.read_labelme(tmp_path / "g.json")["imageWidth"] == 8
    bad = dict(good, shapes=[{"label": "ball", "points": "nope"}])
    (tmp_path / "b.json").write_text(json.dumps(bad))
    with pytest.raises(SphereBenchError, match="shape 0"):
        foreign_formats.read_labelme(tmp_path / "b.json")
    (tmp_path / "n.json").write_text(json.dumps({"imageWidth": 8}))
    with pytest.raises(SphereBenchError, match="not a LabelMe"):
        foreign_formats.read_labelme(tmp_path / "n.json")


def test_scene_folder_without_cloud_is_deprojected_from_its_depth(small_default, tmp_path):
    # the train preset ships depth.png and intrinsics.json only: the same points as cloud.ply
    import shutil
    scene = inout.list_scenes(small_default)[0]
    bare = tmp_path / scene.name
    shutil.copytree(scene, bare)
    (bare / "cloud.ply").unlink()
    a, b = inout.load_cloud(scene), inout.load_cloud(bare)
    assert np.array_equal(a.points, b.points) and np.array_equal(a.rows, b.rows) and b.intrinsics is not None
    (bare / "intrinsics.json").unlink()  # depth counts mean nothing without the depth scale
    with pytest.raises(SphereBenchError, match="depth.png and intrinsics.json"):
        inout.load_cloud(bare)
