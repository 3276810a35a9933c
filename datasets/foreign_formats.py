"""Other tools' formats that SphereBench reads (``prepare``'s inputs, ``detect``'s clouds): headerless
raw depth frames, camera intrinsics in JSON as pyrealsense2 prints them, PCD (the Point Cloud
Library's), XYZ point lists and LabelMe annotations. Each reader checks what it reads through the
reading gate (``spherebench.reading``) and says in one line what is wrong with a file. The project's
own dataset format is ``inout``'s.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

from spherebench.camera import INTRINSICS_NUMBERS, MAX_IMAGE_SIDE_PX, Intrinsics
from spherebench.cloud import Cloud
from spherebench.errors import SphereBenchError, require
from spherebench.reading import check_schema, read_json


# --------------------------------------------------------------------------- raw depth frames and camera JSON

RAW_DTYPES = {"uint16": "u2", "float32": "f4"}
RAW_BYTE_ORDERS = {"little": "<", "big": ">"}


def read_raw_depth(path: str | Path, width: int, height: int, dtype: str = "uint16",
                   byte_order: str = "little") -> np.ndarray:
    """A headerless row-major depth frame -> (height, width) array of ``dtype`` (native byte order).

    The file must hold exactly width * height values; anything else means a truncated file or a
    wrong size/dtype, reported as such.
    """
    path = Path(path)
    if dtype not in RAW_DTYPES or byte_order not in RAW_BYTE_ORDERS:
        raise SphereBenchError(f"raw depth dtype must be one of {', '.join(RAW_DTYPES)} and byte order one of "
                               f"{', '.join(RAW_BYTE_ORDERS)}, got {dtype} {byte_order}")
    if not path.is_file():
        raise SphereBenchError(f"{path}: file not found")
    dt = np.dtype(RAW_BYTE_ORDERS[byte_order] + RAW_DTYPES[dtype])
    expected = int(width) * int(height) * dt.itemsize
    size = path.stat().st_size
    if size != expected:
        other = next(k for k in RAW_DTYPES if k != dtype)
        if size == int(width) * int(height) * np.dtype(RAW_DTYPES[other]).itemsize:
            raise SphereBenchError(f"{path}: {size} bytes, but a {width}x{height} {dtype} frame is {expected} bytes; "
                                   f"it is exactly a {width}x{height} {other} frame: try --raw-dtype {other}")
        raise SphereBenchError(f"{path}: {size} bytes, but a {width}x{height} {dtype} frame is {expected} bytes: "
                               "the file is truncated, or --raw-size/--raw-dtype are wrong")
    data = np.fromfile(path, dtype=dt).reshape(int(height), int(width))
    return data.astype(dt.newbyteorder("="))


def _distortion_name(model) -> str:
    """'Brown Conrady', 'distortion.brown_conrady', 'RS2_DISTORTION_BROWN_CONRADY' -> 'brown_conrady'."""
    name = str(model).strip().lower().replace(" ", "_").replace("-", "_")
    return name.removeprefix("rs2_distortion_").removeprefix("distortion.") or "none"


def read_camera_json(path: str | Path) -> Intrinsics:
    """Intrinsics from a JSON object in pyrealsense2's field names (width, height, ppx, ppy, fx, fy,
    model, coeffs; depth_scale optional) or a scene's intrinsics.json.

    More lenient than ``read_intrinsics``: the distortion model may be spelled as pyrealsense2
    prints it ('Brown Conrady', 'distortion.brown_conrady'), and the object may be wrapped as
    {"intrinsics": {...}} or {"depth": {...}}.
    """
    path = Path(path)
    d = read_json(path)
    if isinstance(d, dict) and "fx" not in d:
        for key in ("intrinsics", "depth"):
            if isinstance(d.get(key), dict):
                d = d[key]
                break
    if not isinstance(d, dict):
        raise SphereBenchError(f"{path}: intrinsics must be a JSON object with width, height, ppx, ppy, fx, fy")
    d = dict(d)
    check_schema(path, d, INTRINSICS_NUMBERS)  # "615.0" is refused as read_intrinsics refuses it, not read as text
    if "model" in d:
        d["model"] = _distortion_name(d["model"])
    try:
        return Intrinsics.from_dict(d)
    except SphereBenchError as exc:
        raise SphereBenchError(f"{path}: {exc}") from None


# PCD (the Point Cloud Library's format, v0.7): ascii, binary and binary_compressed data, read by
# Open3D's tensor reader (NaN points kept). Its header is also read here: Open3D keeps no WIDTH and
# HEIGHT, which say whether the cloud is an organised depth grid.

def _pcd_header(path: Path) -> tuple[int, int]:
    """(WIDTH, HEIGHT) of a PCD file's header, checked before any point is read: x, y, z fields,
    POINTS = WIDTH x HEIGHT within a camera's frame (MAX_IMAGE_SIDE_PX a side), and data holding
    that many points (Open3D pads a file cut short with zeros)."""
    if not path.is_file():
        raise SphereBenchError(f"{path}: file not found")
    header: dict[str, list[str]] = {}
    with open(path, "rb") as f:
        while "DATA" not in header:
            raw = f.readline()
            if not raw.endswith(b"\n"):
                raise SphereBenchError(f"{path}: not a PCD file (no DATA line in the header; truncated?)")
            line = raw.decode("ascii", errors="replace").strip()
            if not line or line.startswith("#"):
                continue
            key, *values = line.split()
            header[key.upper()] = values
            if len(header) == 1 and key.upper() not in ("VERSION", "FIELDS"):
                raise SphereBenchError(f"{path}: not a PCD file (it starts with '{line[:40]}')")
        offset = f.tell()
    try:
        names = header["FIELDS"]
        width, height = int(header["WIDTH"][0]), int(header["HEIGHT"][0])
        n_points = int(header.get("POINTS", [width * height])[0])
        mode = header["DATA"][0].lower()
        counts = [int(c) for c in header.get("COUNT", ["1"] * len(names))]
        point_bytes = sum(int(b) * c for b, c in zip(header.get("SIZE", []), counts, strict=True))
    except (KeyError, IndexError, ValueError) as exc:
        raise SphereBenchError(f"{path}: PCD header is incomplete or malformed ({exc})") from None
    if not {"x", "y", "z"} <= set(names):
        raise SphereBenchError(f"{path}: PCD header must list x, y and z fields")
    if n_points != width * height:
        raise SphereBenchError(f"{path}: PCD says POINTS {n_points} but WIDTH x HEIGHT = {width}x{height}")
    if mode not in ("ascii", "binary", "binary_compressed"):
        raise SphereBenchError(f"{path}: unknown PCD DATA type '{mode}' (ascii, binary or binary_compressed)")
    if n_points > MAX_IMAGE_SIDE_PX ** 2 or (height > 1 and max(width, height) > MAX_IMAGE_SIDE_PX):
        raise SphereBenchError(f"{path}: PCD header promises {width}x{height} points, beyond any depth camera's "
                               f"frame ({MAX_IMAGE_SIDE_PX} px a side at most): the file is damaged")
    held = _pcd_points_held(path, mode, offset, point_bytes)
    if held < n_points:
        raise SphereBenchError(f"{path}: PCD data holds {held} points, the header promises {n_points}: the file "
                               "is truncated or corrupt")
    return width, height


def _pcd_points_held(path: Path, mode: str, offset: int, point_bytes: int) -> int:
    """How many points a PCD file's data (from ``offset``) holds: its non-blank lines (ascii), its
    bytes (binary) or its stated uncompressed size (binary_compressed, whose compressed bytes
    must all be there)."""
    size = path.stat().st_size - offset
    if mode == "ascii":
        with open(path, "rb") as f:
            f.seek(offset)
            return sum(1 for line in f if line.strip())
    if point_bytes <= 0:
        raise SphereBenchError(f"{path}: PCD header gives no SIZE of its fields, needed for {mode} data")
    if mode == "binary":
        return size // point_bytes
    with open(path, "rb") as f:
        f.seek(offset)
        stated = f.read(8)
    packed, unpacked = (int.from_bytes(stated[:4], "little"), int.from_bytes(stated[4:], "little"))
    return unpacked // point_bytes if len(stated) == 8 and size - 8 >= packed else 0


def _read_pcd(path: Path) -> tuple[Cloud, int, int]:
    """(cloud, width, height) of a PCD file; NaN points are dropped, an organised one keeps pixels."""
    width, height = _pcd_header(path)
    # here, not at the top: open3d takes seconds to import, only PCD files need it, and it is an extra
    o3d = require("open3d", "viz", "reading PCD files")
    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)  # its failures are ours to say
    pcd = o3d.t.io.read_point_cloud(str(path), remove_nan_points=False, remove_infinite_points=False)
    n = width * height
    xyz = pcd.point.positions.numpy().astype(np.float64) if "positions" in pcd.point else np.zeros((0, 3))
    if len(xyz) != n:
        raise SphereBenchError(f"{path}: PCD data holds {len(xyz)} points, the header promises {n}: the file "
                               "is truncated or corrupt")
    valid = np.all(np.isfinite(xyz), axis=1)
    idx = np.nonzero(valid)[0]
    pts = xyz[valid].astype(np.float32)
    if height > 1:
        return Cloud(pts, (idx // width).astype(np.int32), (idx % width).astype(np.int32)), width, height
    return Cloud(pts), width, height


def read_pcd(path: str | Path, intrinsics: Intrinsics | None = None) -> Cloud:
    """PCD (ascii, binary, binary_compressed) -> Cloud in the file's units (metres by convention).

    WIDTH x HEIGHT with HEIGHT > 1 is an organised cloud: point i is pixel (i // WIDTH, i % WIDTH)
    and NaN points are the invalid pixels (dropped, the others keep their row/col). Given
    intrinsics, an organised cloud's size must match them.
    """
    path = Path(path)
    cloud, width, height = _read_pcd(path)
    if intrinsics is not None:
        if cloud.rows is not None and (width, height) != (intrinsics.width, intrinsics.height):
            raise SphereBenchError(f"{path}: organised PCD is {width}x{height} but the intrinsics are "
                                   f"{intrinsics.width}x{intrinsics.height}: give the intrinsics of this camera")
        cloud.intrinsics = intrinsics
    return cloud


# --------------------------------------------------------------------------- XYZ point lists

def read_xyz(path: str | Path) -> Cloud:
    """Plain-text point list, one 'x y z [...]' per line (metres), unorganised."""
    path = Path(path)
    if not path.is_file():
        raise SphereBenchError(f"{path}: file not found")
    try:
        with warnings.catch_warnings():  # an empty file: numpy warns, and detect() says what is wrong
            warnings.simplefilter("ignore", UserWarning)
            data = np.loadtxt(path, dtype=np.float64, ndmin=2, comments="#", usecols=(0, 1, 2))
    except (ValueError, IndexError) as exc:
        raise SphereBenchError(f"{path}: not an XYZ text file with three numbers per line ({exc})") from None
    with np.errstate(over="ignore"):  # beyond float32 becomes inf, a non-finite point like NaN: callers drop them
        return Cloud(data.astype(np.float32))


# --------------------------------------------------------------------------- LabelMe

#: A LabelMe file and each of its shapes: the keys SphereBench uses.
LABELME_SCHEMA = {"imagePath?": "text", "imageWidth": "size", "imageHeight": "size", "shapes": ["object"]}
LABELME_SHAPE_SCHEMA = {"label?": "text", "shape_type?": "text", "points": "list"}


def read_labelme(path: str | Path) -> dict:
    """A LabelMe annotation file -> its JSON object, checked for the keys SphereBench uses
    (imagePath, imageWidth, imageHeight, shapes with label, shape_type, points)."""
    path = Path(path)
    d = read_json(path)
    if not isinstance(d, dict) or not isinstance(d.get("shapes"), list):
        raise SphereBenchError(f"{path}: not a LabelMe file (no 'shapes' list)")
    fix = "fix the shape in LabelMe or remove it"
    check_schema(path, d, LABELME_SCHEMA, fix)
    for i, shape in enumerate(d["shapes"]):
        name = f"LabelMe shape {i} ({shape.get('shape_type') or 'polygon'} {shape.get('label')!r})"
        check_schema(path, shape, LABELME_SHAPE_SCHEMA, fix, name)
        for k, point in enumerate(shape["points"]):
            check_schema(path, point, "xy", fix, f"point {k} of {name}")
            # a shape may reach past the image's edge (the shape of another image is said later), not
            # past any frame's reach: a point of 1e300 px is a damaged file
            if max(abs(point[0]), abs(point[1])) > 4 * MAX_IMAGE_SIDE_PX:
                raise SphereBenchError(f"{path}: point {k} of {name}, ({point[0]:g}, {point[1]:g}), lies beyond any "
                                       f"image (more than {4 * MAX_IMAGE_SIDE_PX} px from its corner); {fix}")
    return d
