"""Bad files read: every JSON file against its schema, headers promising frames no camera makes, data
cut short, values out of any physical range, and a batch with one bad input among good ones.

Each refusal: exit 2, one error line naming the file (or option) and what is wrong, nothing on
stdout, no traceback, nothing written. Fixtures of a few bytes are built in the tests.
"""

from __future__ import annotations

import json
import shutil
import struct
import zlib

import numpy as np
import pytest

from spherebench import options, reading
from spherebench.scripts import cli
from spherebench.datasets import inout, simulate
from spherebench.errors import SphereBenchError
from test_bad_input_commands import _fails, _listing  # noqa: E402  (tests/ is on sys.path under pytest)

PCD_HEADER = ("VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH {w}\nHEIGHT {h}\n"
              "VIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\nDATA ascii\n")
CAMERA = {"width": 160, "height": 120, "ppx": 79.5, "ppy": 59.5, "fx": 140.0, "fy": 140.0}


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    """Two annotated simulated scenes (424x240)."""
    return simulate.generate_dataset("default", tmp_path_factory.mktemp("ds") / "ds", n=2, progress=False)


def _copy(dataset, tmp_path):
    return shutil.copytree(dataset, tmp_path / "data")


def _png_header(width: int, height: int) -> bytes:
    """A PNG whose header promises width x height 16-bit grey pixels (its data is a few bytes)."""
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 16, 0, 0, 0, 0))
            + chunk(b"IDAT", zlib.compress(b"\0" * 8)) + chunk(b"IEND", b""))


# ---------------------------------------------------------------- schemas: one check per file read

def _edit(path, **fields):
    d = json.loads(path.read_text())
    d.update(fields)
    path.write_text(json.dumps(d))


DAMAGE = {  # what is done to a copy of the dataset -> the words of the one line
    "dataset.json a list": (lambda ds: (ds / "dataset.json").write_text("[1, 2]"),
                            ("dataset.json", "must be a JSON object, not [1, 2]")),
    "ball_radius_m text": (lambda ds: _edit(ds / "dataset.json", ball_radius_m="abc"),
                           ("dataset.json", "ball_radius_m must be a ball radius in metres", '"abc"')),
    "gt.json a list": (lambda ds: (inout.list_scenes(ds)[0] / "gt.json").write_text("[1]"),
                       ("gt.json", "must be a JSON object, not [1]")),
    "gt.json ball radius": (lambda ds: _edit(inout.list_scenes(ds)[0] / "gt.json",
                                             balls=[{"radius_m": "big", "circle": None}]),
                            ("gt.json", "balls[0].radius_m must be a ball radius in metres", '"big"')),
    "coco images a number": (lambda ds: (ds / "coco_gt.json").write_text('{"images": 5}'),
                             ("coco_gt.json", "images must be a list, not 5")),
}


@pytest.mark.parametrize("damage", sorted(DAMAGE))
def test_evaluate_names_the_file_and_field_of_a_damaged_dataset(dataset, tmp_path, capsys, damage):
    data = _copy(dataset, tmp_path)
    harm, words = DAMAGE[damage]
    harm(data)
    before = _listing(tmp_path)
    _fails(capsys, ["evaluate", "--data", data, "--out", tmp_path / "out", "--methods", "improved", "--workers", "1",
                    "--quiet", "--no-figures"], *words)
    assert _listing(tmp_path) == before


@pytest.mark.parametrize("damage", ["dataset.json a list", "ball_radius_m text"])
def test_detect_and_annotate_name_a_damaged_dataset_json(dataset, tmp_path, capsys, damage):
    data = _copy(dataset, tmp_path)
    harm, words = DAMAGE[damage]
    harm(data)
    before = _listing(tmp_path)
    _fails(capsys, ["detect", inout.list_scenes(data)[0]], *words)
    _fails(capsys, ["annotate", data, "--sheet", tmp_path / "sheet"], *words)
    assert _listing(tmp_path) == before


def test_show_names_a_damaged_gt_json(dataset, tmp_path, capsys):
    for damage in ("gt.json a list", "gt.json ball radius"):
        data = _copy(dataset, tmp_path / damage.replace(" ", "_"))
        harm, words = DAMAGE[damage]
        harm(data)
        _fails(capsys, ["show", inout.list_scenes(data)[0], "--out-png", tmp_path / "s.png", "--out-ply",
                        tmp_path / "s.ply"], *words)
    assert not (tmp_path / "s.png").exists() and not (tmp_path / "s.ply").exists()


def test_check_schema_names_nested_fields_and_allows_absent_optional_ones(tmp_path):
    schema = {"a": "int", "b?": [{"c": "xyz"}]}
    assert reading.check_schema("f.json", {"a": 1}, schema) == {"a": 1}
    assert reading.check_schema("f.json", {"a": 1, "b": None}, schema)
    for value, says in (({"b": []}, "f.json: a is missing"), ({"a": True}, "a must be an integer, not true"),
                        ({"a": 1, "b": [{"c": [0, 0, float("nan")]}]}, "b[0].c must be [x, y, z]")):
        with pytest.raises(SphereBenchError, match=says.replace("[", r"\[")):
            reading.check_schema("f.json", value, schema)


def test_a_labelme_point_that_is_not_a_number_is_named_with_its_shape(tmp_path, capsys):
    (tmp_path / "pngs").mkdir()
    inout.write_depth_png(tmp_path / "pngs" / "f.png", np.full((120, 160), 1500, np.uint16))
    (tmp_path / "cam.json").write_text(json.dumps(CAMERA))
    (tmp_path / "lm").mkdir()
    (tmp_path / "lm" / "f.json").write_text(  # json writes NaN as LabelMe would read it back
        json.dumps({"imagePath": "image.png", "imageWidth": 160, "imageHeight": 120,
                    "shapes": [{"label": "ball", "shape_type": "circle", "points": [[80, 60], [float("nan"), 60]]}]}))
    before = _listing(tmp_path)
    line = _fails(capsys, ["prepare", tmp_path / "pngs", "--intrinsics", tmp_path / "cam.json", "--labelme",
                           tmp_path / "lm", "--out", tmp_path / "out"],
                  "f.json", "point 1 of LabelMe shape 0 (circle 'ball')", "two finite numbers", "NaN")
    assert "zero radius" not in line
    assert _listing(tmp_path) == before


# ---------------------------------------------------------------- headers promising what no camera makes

def test_a_pcd_header_of_ten_billion_points_is_refused_before_reading(tmp_path, capsys):
    pytest.importorskip("open3d")
    big = tmp_path / "big.pcd"
    big.write_text(PCD_HEADER.format(w=100_000, h=100_000, n=10 ** 10) + "0 0 1\n")
    _fails(capsys, ["detect", big], "big.pcd", "100000x100000", "beyond any depth camera")


def test_a_png_header_of_ten_billion_pixels_is_refused_before_decoding(tmp_path, capsys):
    (tmp_path / "pngs").mkdir()
    (tmp_path / "pngs" / "f.png").write_bytes(_png_header(100_000, 100_000))
    (tmp_path / "cam.json").write_text(json.dumps(CAMERA))
    _fails(capsys, ["prepare", tmp_path / "pngs", "--intrinsics", tmp_path / "cam.json", "--out", tmp_path / "out"],
           "f.png", "100000x100000 px", "beyond any depth camera")
    _fails(capsys, ["detect-2d", tmp_path / "pngs" / "f.png"], "f.png", "100000x100000 px")
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("width, says", [(200_000, "200000x200000"), (424.7, "424.7x")])
def test_intrinsics_of_a_size_no_camera_has_are_refused(tmp_path, capsys, width, says):
    cloud = tmp_path / "c.xyz"
    cloud.write_text("0 0 1\n0.1 0 1\n0 0.1 1\n")
    cam = dict(CAMERA, width=width, height=200_000 if width > 8192 else 120)
    (tmp_path / "cam.json").write_text(json.dumps(cam))
    _fails(capsys, ["detect", cloud, "--intrinsics", tmp_path / "cam.json"], "cam.json", says,
           "whole numbers of pixels from 1 to 8192")


def test_seeds_are_bounded_before_the_list_is_built(dataset, tmp_path, capsys):
    with pytest.raises(SphereBenchError, match="more than 1000 seeds"):
        options.parse_seeds(f"0-{options.MAX_SEEDS}")
    assert len(options.parse_seeds(f"0-{options.MAX_SEEDS - 1}")) == options.MAX_SEEDS
    _fails(capsys, ["sweep", dataset, "--seeds", "0-99999999", "--out", tmp_path / "sw"], "--seeds", "more than 1000")
    assert not list(tmp_path.iterdir())


# ---------------------------------------------------------------- accepted before, refused now

def test_a_truncated_ascii_pcd_is_refused_not_padded_with_zeros(tmp_path, capsys):
    pytest.importorskip("open3d")
    cut = tmp_path / "cut.pcd"
    cut.write_text(PCD_HEADER.format(w=5, h=1, n=5) + "0 0 1\n0.1 0 1\n")
    _fails(capsys, ["detect", cut], "cut.pcd", "holds 2 points, the header promises 5")


@pytest.mark.parametrize("image", ["missing", "10x10"])
def test_evaluate_refuses_a_scene_whose_image_is_not_its_intrinsics_size(dataset, tmp_path, capsys, image):
    data = _copy(dataset, tmp_path)
    png = inout.list_scenes(data)[0] / "image.png"
    if image == "missing":
        png.unlink()
    else:
        inout.write_png(png, np.zeros((10, 10, 3), np.uint8))
    before = _listing(tmp_path)
    _fails(capsys, ["evaluate", "--data", data, "--out", tmp_path / "out", "--methods", "hough", "--workers", "1",
                    "--quiet", "--no-figures"], "image.png", "missing" if image == "missing" else "is 10x10")
    assert _listing(tmp_path) == before


@pytest.mark.parametrize("argv, says", [
    (["detect-2d", "{scene}", "--threads", "-3"], "--threads: -3"),
    (["detect-2d", "{scene}", "--min-score", "nan"], "--min-score: nan"),
    (["show", "{scene}", "--min-score", "nan", "--out-png", "{tmp}/s.png", "--out-ply", "{tmp}/s.ply"],
     "--min-score: nan"),
    (["bench", "{data}", "--peer-points", "-5", "--limit", "1", "--passes", "1"], "--peer-points: -5"),
    (["detect", "{scene}", "--radius", "1e9"], "a ball radius is 0.005 to 2 metres"),
    (["prepare", "{tmp}/pngs", "--intrinsics", "{tmp}/cam.json", "--radius", "1e9", "--out", "{tmp}/out"],
     "a ball radius is 0.005 to 2 metres"),
])
def test_values_out_of_range_are_refused_in_one_line(dataset, tmp_path, capsys, argv, says):
    (tmp_path / "pngs").mkdir()
    inout.write_depth_png(tmp_path / "pngs" / "f.png", np.full((120, 160), 1500, np.uint16))
    (tmp_path / "cam.json").write_text(json.dumps(CAMERA))
    before = _listing(tmp_path)
    names = {"scene": inout.list_scenes(dataset)[0], "data": dataset, "tmp": tmp_path}
    line = _fails(capsys, [a.format(**names) for a in argv], says)
    assert "units" not in line and "metres are expected" not in line  # the radius is absurd, not the cloud
    assert _listing(tmp_path) == before


def test_intrinsics_with_a_fractional_size_are_refused_by_prepare(tmp_path, capsys):
    (tmp_path / "pngs").mkdir()
    inout.write_depth_png(tmp_path / "pngs" / "f.png", np.full((120, 160), 1500, np.uint16))
    (tmp_path / "cam.json").write_text(json.dumps(dict(CAMERA, width=160.5)))
    _fails(capsys, ["prepare", tmp_path / "pngs", "--intrinsics", tmp_path / "cam.json", "--out", tmp_path / "out"],
           "cam.json", "160.5x120", "whole numbers")
    assert not (tmp_path / "out").exists()


# ---------------------------------------------------------------- batches and messages

def test_detect_reports_and_skips_a_bad_input_and_detects_the_others(tmp_path, capsys):
    pytest.importorskip("open3d")
    a, b, c = tmp_path / "a.xyz", tmp_path / "b.pcd", tmp_path / "c.xyz"
    a.write_text("0 0 1\n0.1 0 1\n0 0.1 1\n")
    b.write_text(PCD_HEADER.format(w=5, h=1, n=5) + "0 0 1\n")
    shutil.copy(a, c)
    status = cli.main(["detect", str(a), str(b), str(c), "--json"])
    cap = capsys.readouterr()
    assert status == 2
    assert [json.loads(x)["input"] for x in cap.out.splitlines()] == [str(a), str(c)]
    lines = cap.err.strip().splitlines()
    assert len(lines) == 1 and "b.pcd" in lines[0] and "truncated" in lines[0] and "Traceback" not in cap.err


def test_detect_camera_given_a_path_says_to_give_it_as_an_input(dataset, tmp_path, capsys):
    scene = inout.list_scenes(dataset)[0]
    for value in (str(scene), "rec.bag", "scans/x"):
        _fails(capsys, ["detect", "--camera", value], f"--camera {value}", "takes a serial number",
               "give the file as a PATH argument")
