"""The file formats of SphereBench's datasets, read and written (as the BOP toolkit's inout.py).

Dataset layout (simulated and recorded alike)::

    DIR/dataset.json              name, preset, ball radius (m), category, seed, versions
    DIR/coco_gt.json              COCO ground truth with CircleNet's circle fields
    DIR/scenes/<scene_id>/
        depth.png                 uint16, counts of depth_scale (0 = no depth)
        intrinsics.json           pyrealsense2's rs.intrinsics fields + depth_scale
        cloud.ply                 binary PLY: float32 x, y, z (m) [+ int32 row, col]
        image.png                 the depth colourised (datasets.reproject): 2D methods' input
        gt.json                   balls (3D centre, radius, circles, visibility), family, seed
        mask_<k>.png              visible mask of ball k (255 = ball)
        silhouette_<k>.png        full silhouette of ball k (simulated scenes)

Writes are atomic, through ``spherebench.datasets.outputs`` (which also says what may be replaced):
a file is written to a temporary name and renamed; a scene folder and a whole dataset are built
under a temporary name and renamed when complete, so an interrupted or failed run leaves nothing
half-written behind. Every JSON file is read through the reading gate and checked against its
schema (``spherebench.reading``). Other tools' formats (raw frames, camera JSON, PCD, XYZ, LabelMe)
are ``foreign_formats``'; RealSense recordings are played back by ``recordings``; the detectors'
JSON records are ``detections``'.
"""

from __future__ import annotations

import functools
import io
import json
import math
import os
import shutil
import zlib
from pathlib import Path

import cv2
import numpy as np
from plyfile import PlyData, PlyElement

from spherebench.camera import INTRINSICS_NUMBERS, MAX_IMAGE_SIDE_PX, Intrinsics
from spherebench.cloud import Cloud, cloud_from_depth, depth_to_metres
from spherebench.datasets import foreign_formats
from spherebench.datasets.outputs import (COLOUR_FILES, MARK, PNG_SIGNATURE, atomic_directory, atomic_write_bytes,
                                          mark_png, never_replace)
from spherebench.datasets.reproject import colourise_depth
from spherebench.datasets.scene import Ball, Scene
from spherebench.errors import SphereBenchError
from spherebench.reading import check_schema, read_checked_json, read_json  # the reading gate

CATEGORY_ID = 1
DEFAULT_CATEGORY = "basketball"


# --------------------------------------------------------------------------- JSON

def json_bytes(obj, indent: int | None = 1) -> bytes:
    """JSON text as write_json writes it; floats as Python writes them (shortest repr: byte-stable)."""
    return (json.dumps(obj, indent=indent, sort_keys=False) + "\n").encode()


def write_json(path: str | Path, obj, indent: int | None = 1) -> None:
    """JSON (json_bytes), atomically."""
    atomic_write_bytes(path, json_bytes(obj, indent))


# --------------------------------------------------------------------------- images

def encode_png(image: np.ndarray, what: str, mark: bool = False) -> bytes:
    """uint8/uint16 image (grey or BGR) -> PNG bytes; ``mark``: with the mark of a file written for
    the user (``outputs.is_marked``)."""
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(image))
    if not ok:
        raise SphereBenchError(f"{what}: OpenCV could not encode this image as PNG")
    data = buf.tobytes()
    return mark_png(data) if mark else data


def write_png(path: str | Path, image: np.ndarray) -> None:
    """uint8/uint16 image (grey or BGR) -> PNG, atomically."""
    atomic_write_bytes(path, encode_png(image, str(path)))


def _header_size(data: bytes) -> tuple[int, int] | None:
    """(width, height) px from a PNG's IHDR or a JPEG's frame header; None for another format or
    a header cut short (OpenCV then says what it makes of the file)."""
    if data[:8] == PNG_SIGNATURE and data[12:16] == b"IHDR" and len(data) >= 24:
        return int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big")
    i = 2 if data[:2] == b"\xff\xd8" else len(data)
    while i + 9 <= len(data) and data[i] == 0xFF:
        marker = data[i + 1]
        if marker == 0xFF or 0xD0 <= marker <= 0xD8 or marker == 0x01:  # fill byte, markers with no length
            i += 1 if marker == 0xFF else 2
            continue
        if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC):  # a start of frame
            return int.from_bytes(data[i + 7:i + 9], "big"), int.from_bytes(data[i + 5:i + 7], "big")
        i += 2 + int.from_bytes(data[i + 2:i + 4], "big")
    return None


def _check_frame_size(path: Path, width: int, height: int) -> None:
    if max(width, height) > MAX_IMAGE_SIDE_PX:
        raise SphereBenchError(f"{path}: the image header says {width}x{height} px, beyond any depth camera's "
                               f"({MAX_IMAGE_SIDE_PX} px a side at most): the file is damaged or not a camera frame")


def _png_fault(data: bytes | memoryview) -> str | None:
    """What is wrong with a PNG's chunks (one running past the end of the file, a checksum that does
    not match, no IEND chunk), or None (also for another format): of such a file libpng prints a line
    of its own on stderr before OpenCV gives up, so it is refused before it is decoded."""
    if data[:8] != PNG_SIGNATURE:
        return None
    i = len(PNG_SIGNATURE)
    while i + 12 <= len(data):  # a chunk: length (4 bytes), type (4), data (length), CRC of type and data (4)
        end = i + 12 + int.from_bytes(data[i:i + 4], "big")
        kind = bytes(data[i + 4:i + 8])
        if end > len(data):
            break
        if zlib.crc32(data[i + 4:end - 4]) != int.from_bytes(data[end - 4:end], "big"):
            return f"damaged (the checksum of its {kind.decode('latin-1')!r} chunk does not match)"
        if kind == b"IEND":
            return None
        i = end
    return "truncated (it ends inside its data, before the IEND chunk)"


@functools.cache
def _quiet_opencv() -> None:
    """OpenCV's own log off, once per process: of a damaged image it prints WARN and ERROR lines of
    its decoder before _imread's one line says what is wrong and what to do."""
    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)


def _imread(path: Path, flags: int) -> np.ndarray:
    if not path.is_file():
        raise SphereBenchError(f"{path}: file not found")
    _quiet_opencv()
    data = np.fromfile(path, dtype=np.uint8)
    size = _header_size(data[:1 << 16].tobytes())
    if size is not None:
        _check_frame_size(path, *size)  # before OpenCV allocates the frame
    fault = _png_fault(memoryview(data))
    if fault:
        raise SphereBenchError(f"{path}: not a readable image: the PNG is {fault}")
    try:
        img = cv2.imdecode(data, flags) if data.size else None
    except cv2.error:  # e.g. an unknown format's header promising more than CV_IO_MAX_IMAGE_PIXELS
        img = None
    if img is None:
        raise SphereBenchError(f"{path}: not a readable image (corrupt or truncated?)")
    return img


def image_size(path: str | Path) -> tuple[int, int]:
    """(width, height) px of an image file, from its header where it is a PNG or JPEG (nothing
    decoded), else from the image read."""
    path = Path(path)
    if not path.is_file():
        raise SphereBenchError(f"{path}: file not found")
    with open(path, "rb") as f:
        size = _header_size(f.read(1 << 16))
    if size is None:
        img = _imread(path, cv2.IMREAD_UNCHANGED)
        return img.shape[1], img.shape[0]
    _check_frame_size(path, *size)
    return size


def check_scene_image(scene_dir: str | Path, intr: Intrinsics) -> None:
    """A scene's image.png is there and of its intrinsics' size (its circles are in those pixels):
    read from the header, nothing decoded."""
    path = Path(scene_dir) / "image.png"
    if not path.is_file():
        raise SphereBenchError(f"{scene_dir}: image.png is missing though the scene has an image (its gt.json, "
                               "coco_gt.json): the folder is damaged; rebuild the dataset with the command that wrote it")
    w, h = image_size(path)
    if (h, w) != intr.shape:
        raise SphereBenchError(f"{scene_dir}: image.png is {w}x{h} but the intrinsics say {intr.width}x{intr.height}: "
                               "the circles would be off the image; rebuild the dataset with the command that wrote it")


def read_image(path: str | Path) -> np.ndarray:
    """A reprojected image (H, W, 3) uint8 BGR; a scene folder gives its image.png."""
    path = Path(path)
    if path.is_dir():
        path = path / "image.png"
    img = _imread(path, cv2.IMREAD_COLOR)
    return img


def read_image_as_stored(path: str | Path) -> np.ndarray:
    """An image file as it is stored: any bit depth and channels (OpenCV's order: BGR, BGRA)."""
    return _imread(Path(path), cv2.IMREAD_UNCHANGED)


def write_depth_png(path: str | Path, depth: np.ndarray) -> None:
    """(H, W) uint16 depth counts -> 16-bit PNG."""
    d = np.asarray(depth)
    if d.dtype != np.uint16 or d.ndim != 2:
        raise SphereBenchError(f"{path}: depth must be a 2D uint16 array, got {d.dtype} {d.shape}")
    write_png(path, d)


def read_depth_png(path: str | Path) -> np.ndarray:
    """16-bit single-channel PNG -> (H, W) uint16 depth counts."""
    path = Path(path)
    d = _imread(path, cv2.IMREAD_UNCHANGED)
    if d.ndim != 2 or d.dtype != np.uint16:
        raise SphereBenchError(f"{path}: a depth PNG must be 16-bit single-channel, this one is "
                               f"{d.dtype} with shape {d.shape} (a colourised image is not depth)")
    return d


def write_mask_png(path: str | Path, mask: np.ndarray) -> None:
    write_png(path, np.asarray(mask, dtype=bool).astype(np.uint8) * 255)


def read_mask_png(path: str | Path, shape: tuple[int, int] | None = None) -> np.ndarray:
    """A mask PNG (any depth; non-zero = inside) -> (H, W) bool, checked against ``shape``."""
    path = Path(path)
    m = _imread(path, cv2.IMREAD_UNCHANGED)
    if m.ndim == 3:
        m = m[..., :3].max(axis=2) if m.shape[2] >= 3 else m[..., 0]
    if shape is not None and m.shape[:2] != tuple(shape):
        raise SphereBenchError(f"{path}: mask is {m.shape[1]}x{m.shape[0]} but the depth image is "
                               f"{shape[1]}x{shape[0]}: masks must be drawn on the scene's own image")
    return m > 0


# --------------------------------------------------------------------------- intrinsics

def write_intrinsics(path: str | Path, intr: Intrinsics) -> None:
    write_json(path, intr.to_dict())


def read_intrinsics(path: str | Path) -> Intrinsics:
    """intrinsics.json (pyrealsense2 field names; a scene folder gives its own)."""
    path = Path(path)
    if path.is_dir():
        path = path / "intrinsics.json"
    d = read_json(path)
    if not isinstance(d, dict):
        raise SphereBenchError(f"{path}: intrinsics must be a JSON object with width, height, ppx, ppy, fx, fy")
    check_schema(path, d, INTRINSICS_NUMBERS)
    try:
        return Intrinsics.from_dict(d)
    except SphereBenchError as exc:
        raise SphereBenchError(f"{path}: {exc}") from None


# --------------------------------------------------------------------------- point clouds

def write_cloud_ply(path: str | Path, cloud: Cloud) -> None:
    """Binary PLY: float32 x, y, z (m) and, for organised clouds, int32 row, col per point."""
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    if cloud.rows is not None:
        fields += [("row", "<i4"), ("col", "<i4")]
    v = np.empty(len(cloud), dtype=fields)
    v["x"], v["y"], v["z"] = cloud.points[:, 0], cloud.points[:, 1], cloud.points[:, 2]
    if cloud.rows is not None:
        v["row"], v["col"] = cloud.rows, cloud.cols
    _write_ply_vertices(path, v)


def encode_ply(points_m: np.ndarray, colours: np.ndarray | None = None) -> bytes:
    """Binary PLY of points (N, 3) m with optional colours (N, 3) uint8 RGB, for MeshLab, with the
    mark of a file written for the user (``outputs.is_marked``)."""
    p = np.asarray(points_m, dtype=np.float32).reshape(-1, 3)
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    if colours is not None:
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    v = np.empty(len(p), dtype=fields)
    v["x"], v["y"], v["z"] = p[:, 0], p[:, 1], p[:, 2]
    if colours is not None:
        c = np.asarray(colours, dtype=np.uint8).reshape(-1, 3)
        v["red"], v["green"], v["blue"] = c[:, 0], c[:, 1], c[:, 2]
    return _ply_bytes(v, comments=[MARK.decode()])


def write_ply(path: str | Path, points_m: np.ndarray, colours: np.ndarray | None = None) -> None:
    """encode_ply, written atomically."""
    atomic_write_bytes(path, encode_ply(points_m, colours))


def _write_ply_vertices(path: str | Path, vertices: np.ndarray) -> None:
    atomic_write_bytes(path, _ply_bytes(vertices))


def _ply_bytes(vertices: np.ndarray, comments=()) -> bytes:
    buf = io.BytesIO()
    PlyData([PlyElement.describe(vertices, "vertex")], byte_order="<", comments=list(comments)).write(buf)
    return buf.getvalue()


def read_ply(path: str | Path, intrinsics: Intrinsics | None = None) -> Cloud:
    """PLY (ASCII or binary) -> Cloud; organised when the vertices carry row and col."""
    path = Path(path)
    if not path.is_file():
        raise SphereBenchError(f"{path}: file not found")
    try:
        ply = PlyData.read(str(path))
        v = ply["vertex"].data
        pts = np.stack([v["x"], v["y"], v["z"]], axis=1).astype(np.float32)
    except (KeyError, ValueError) as exc:
        raise SphereBenchError(f"{path}: not a PLY point cloud with x, y, z vertices ({exc})") from None
    except Exception as exc:  # plyfile raises several types on truncated data
        raise SphereBenchError(f"{path}: unreadable PLY, corrupt or truncated ({type(exc).__name__}: {exc})") from None
    names = v.dtype.names
    if "row" in names and "col" in names:
        return Cloud(pts, v["row"], v["col"], intrinsics)
    return Cloud(pts, intrinsics=intrinsics)


#: The cloud files ``load_cloud`` reads, by suffix: the project's PLY, and other tools' formats.
CLOUD_READERS = {".ply": read_ply, ".pcd": foreign_formats.read_pcd, ".xyz": foreign_formats.read_xyz,
                 ".txt": foreign_formats.read_xyz}


def load_cloud(path: str | Path, intrinsics: Intrinsics | None = None) -> Cloud:
    """A cloud from a PLY/PCD/XYZ file or a scene folder (which supplies its own intrinsics): its
    cloud.ply, else its depth.png deprojected (the `train` preset ships no clouds; the two give the
    same points where a scene has both)."""
    path = Path(path)
    if path.is_dir():
        intr = intrinsics
        if intr is None and (path / "intrinsics.json").is_file():
            intr = read_intrinsics(path / "intrinsics.json")
        if (path / "cloud.ply").is_file():
            return read_ply(path / "cloud.ply", intr)
        if (path / "depth.png").is_file() and intr is not None:
            return cloud_from_depth(depth_to_metres(read_depth_png(path / "depth.png"), intr), intr)
        raise SphereBenchError(f"{path}: a folder must be a scene folder with cloud.ply, or depth.png and "
                               "intrinsics.json, in it")
    reader = CLOUD_READERS.get(path.suffix.lower())
    if reader is None:
        raise SphereBenchError(f"{path}: unknown point-cloud format '{path.suffix}' "
                               f"(use {', '.join(sorted(CLOUD_READERS))} or a scene folder)")
    cloud = reader(path) if reader is not read_ply else read_ply(path, intrinsics)
    if intrinsics is not None and cloud.intrinsics is None:
        cloud.intrinsics = intrinsics
    return cloud


# --------------------------------------------------------------------------- scenes

def _circle(c) -> list[float] | None:
    return None if c is None else [float(x) for x in c]


def colour_file_name(source: str | Path | np.ndarray) -> str:
    """The name a scene keeps a colour frame under: colour.png for a PNG or an image (an array),
    else colour.jpg."""
    if isinstance(source, np.ndarray):
        return COLOUR_FILES[1]
    return COLOUR_FILES[1] if Path(source).suffix.lower() == ".png" else COLOUR_FILES[0]


def write_scene(scenes_dir: str | Path, scene: Scene, ball_radius_m: float, write_cloud: bool = True,
                colour: Path | np.ndarray | None = None) -> Path:
    """Write one scene folder atomically under ``scenes_dir``; returns its path.

    write_cloud=False leaves cloud.ply out (it is depth.png deprojected; the training split of
    learned 2D baselines has no use for it and it is most of a scene's size).
    colour: a JPEG or PNG colour frame registered to the depth, copied byte for byte as colour.jpg
    or colour.png, or an image (H, W, 3) uint8 BGR, written as colour.png (the caller checks its
    size)."""
    final = Path(scenes_dir) / scene.scene_id
    with atomic_directory(final, never_replace) as tmp:
        balls = []
        for k, ball in enumerate(scene.balls):
            entry = {
                "center_m": None if ball.centre_m is None else [float(x) for x in ball.centre_m],
                "radius_m": float(ball.radius_m),
                "visible_fraction": None if ball.visible_fraction is None else float(ball.visible_fraction),
                "circle": _circle(ball.circle_px),
                "amodal_circle": _circle(ball.amodal_circle_px),
                "mask": None,
                "silhouette": None,
            }
            if ball.centre_source is not None:  # a recorded ball's centre: how it was obtained, its error
                entry["center_source"] = ball.centre_source
                entry["center_se_m"] = None if ball.centre_se_m is None else [float(x) for x in ball.centre_se_m]
            if ball.mask is not None:
                entry["mask"] = f"mask_{k}.png"
                write_mask_png(tmp / entry["mask"], ball.mask)
            if ball.silhouette is not None:
                entry["silhouette"] = f"silhouette_{k}.png"
                write_mask_png(tmp / entry["silhouette"], ball.silhouette)
            balls.append(entry)
        gt = {"scene_id": scene.scene_id, "family": scene.family, "seed": scene.seed,
              "annotated": bool(scene.annotated), "ball_radius_m": float(ball_radius_m),
              "has_image": scene.depth is not None, "balls": balls, "meta": scene.meta}
        if scene.depth is not None:
            write_depth_png(tmp / "depth.png", scene.depth)
            write_png(tmp / "image.png", colourise_depth(scene.depth_m()))
        if scene.intrinsics is not None:
            write_intrinsics(tmp / "intrinsics.json", scene.intrinsics)
        if write_cloud or scene.depth is None:
            write_cloud_ply(tmp / "cloud.ply", scene.to_cloud())
        if isinstance(colour, np.ndarray):
            write_png(tmp / colour_file_name(colour), colour)
        elif colour is not None:
            shutil.copyfile(colour, tmp / colour_file_name(colour))
        write_json(tmp / "gt.json", gt)
    return final


#: gt.json (write_scene): what the readers of a scene rely on.
BALL_SCHEMA = {"radius_m": "radius", "center_m?": "xyz", "circle?": "circle", "amodal_circle?": "circle",
               "visible_fraction?": "fraction", "mask?": "text", "silhouette?": "text", "center_source?": "text",
               "center_se_m?": "xyz"}
GT_SCHEMA = {"scene_id": "text", "family": "text", "annotated?": "bool", "has_image?": "bool",
             "ball_radius_m?": "radius", "balls": [BALL_SCHEMA], "meta?": "object"}


def read_scene_gt(scene_dir: str | Path) -> dict:
    """A scene folder's gt.json, checked against GT_SCHEMA."""
    return read_checked_json(Path(scene_dir) / "gt.json", GT_SCHEMA)


def read_scene(scene_dir: str | Path, load_masks: bool = True) -> Scene:
    """A scene folder -> Scene (depth, intrinsics, balls with masks)."""
    scene_dir = Path(scene_dir)
    gt = read_scene_gt(scene_dir)
    intr = read_intrinsics(scene_dir / "intrinsics.json") if (scene_dir / "intrinsics.json").is_file() else None
    depth = read_depth_png(scene_dir / "depth.png") if (scene_dir / "depth.png").is_file() else None
    if depth is not None and intr is not None and depth.shape != intr.shape:
        raise SphereBenchError(f"{scene_dir}: depth.png is {depth.shape[1]}x{depth.shape[0]} but intrinsics.json "
                               f"says {intr.width}x{intr.height}")
    cloud = None if depth is not None else read_ply(scene_dir / "cloud.ply", intr)
    balls = []
    for b in gt.get("balls", []):
        mask = sil = None
        if load_masks and b.get("mask"):
            mask = read_mask_png(scene_dir / b["mask"], depth.shape if depth is not None else None)
        if load_masks and b.get("silhouette"):
            sil = read_mask_png(scene_dir / b["silhouette"], depth.shape if depth is not None else None)
        balls.append(Ball(radius_m=b["radius_m"], mask=mask, silhouette=sil,
                          centre_m=None if b.get("center_m") is None else tuple(b["center_m"]),
                          circle_px=None if b.get("circle") is None else tuple(b["circle"]),
                          amodal_circle_px=None if b.get("amodal_circle") is None else tuple(b["amodal_circle"]),
                          visible_fraction=b.get("visible_fraction"), centre_source=b.get("center_source"),
                          centre_se_m=None if b.get("center_se_m") is None else tuple(b["center_se_m"])))
    return Scene(scene_id=gt["scene_id"], family=gt["family"], intrinsics=intr, depth=depth, balls=balls,
                 seed=gt.get("seed"), annotated=gt.get("annotated", True), cloud=cloud, meta=gt.get("meta", {}))


# --------------------------------------------------------------------------- datasets

def list_scenes(dataset_dir: str | Path) -> list[Path]:
    """Scene folders of a dataset, sorted by scene id."""
    scenes = Path(dataset_dir) / "scenes"
    if not scenes.is_dir():
        raise SphereBenchError(f"{dataset_dir}: not a dataset (no scenes/ folder); build one with "
                               "'spherebench generate' or 'spherebench prepare'")
    return sorted(p for p in scenes.iterdir() if p.is_dir() and not p.name.startswith("."))


#: dataset.json (finish_dataset): the fields its readers use.
DATASET_SCHEMA = {"name?": "text", "preset?": "text", "category?": "text", "ball_radius_m?": "radius"}


def read_dataset_meta(dataset_dir: str | Path) -> dict:
    """A dataset's dataset.json, checked against DATASET_SCHEMA."""
    return read_checked_json(Path(dataset_dir) / "dataset.json", DATASET_SCHEMA)


def scene_dataset_meta(scene_dir: str | Path) -> dict:
    """The dataset.json of the dataset a scene folder lies in (DIR/scenes/<id>), checked; {} for a
    scene of no dataset. Read by whatever reads such a scene, so that a damaged one is refused in
    one line, never passed over."""
    scene_dir = Path(scene_dir)
    dataset = scene_dir.parent.parent
    # there, whatever it is (a FIFO, a folder: refused), a dataset.json is read
    there = os.path.lexists(dataset / "dataset.json")
    return read_dataset_meta(dataset) if scene_dir.parent.name == "scenes" and there else {}


def build_coco_gt(dataset_dir: str | Path, category: str = DEFAULT_CATEGORY, name: str | None = None) -> dict:
    """COCO ground truth with CircleNet's circle fields, from the scenes' gt.json files.

    Image ids are 1-based in scene-id order. Unannotated scenes and scenes without an image are
    left out (they cannot be scored in 2D). Each annotation: circle_center [x, y] and
    circle_radius (px) of the visible mask's smallest enclosing circle, area = pi r^2, bbox of
    the circle, the amodal circle under amodal_circle_center / amodal_circle_radius, and the 3D
    centre (center_m) when known.
    """
    images, annotations = [], []
    for scene_dir in list_scenes(dataset_dir):
        gt = read_scene_gt(scene_dir)
        if not gt.get("annotated", True) or not gt.get("has_image", True):
            continue
        intr = read_intrinsics(scene_dir / "intrinsics.json")
        image_id = len(images) + 1
        images.append({"id": image_id, "file_name": f"scenes/{scene_dir.name}/image.png", "width": intr.width,
                       "height": intr.height, "scene_id": gt["scene_id"], "family": gt["family"]})
        for ball in gt["balls"]:
            if ball.get("circle") is None:
                continue  # wholly hidden: nothing to see in 2D
            cx, cy, r = ball["circle"]
            ann = {"id": len(annotations) + 1, "image_id": image_id, "category_id": CATEGORY_ID,
                   "circle_center": [cx, cy], "circle_radius": r, "area": math.pi * r * r,
                   "bbox": [cx - r, cy - r, 2 * r, 2 * r], "iscrowd": 0}
            if ball.get("amodal_circle") is not None:
                ax, ay, ar = ball["amodal_circle"]
                ann["amodal_circle_center"], ann["amodal_circle_radius"] = [ax, ay], ar
            if ball.get("center_m") is not None:
                ann["center_m"] = ball["center_m"]
            if ball.get("visible_fraction") is not None:
                ann["visible_fraction"] = ball["visible_fraction"]
            annotations.append(ann)
    return {"info": {"description": f"SphereBench dataset {name or Path(dataset_dir).name}"},
            "images": images, "annotations": annotations,
            "categories": [{"id": CATEGORY_ID, "name": category, "supercategory": "ball"}]}


def finish_dataset(dataset_dir: str | Path, meta: dict) -> None:
    """Write coco_gt.json and dataset.json once every scene is in place."""
    coco = build_coco_gt(dataset_dir, meta.get("category", DEFAULT_CATEGORY), meta.get("name"))
    write_json(Path(dataset_dir) / "coco_gt.json", coco, indent=None)
    write_json(Path(dataset_dir) / "dataset.json", meta)


#: coco_gt.json (build_coco_gt): COCO's lists with CircleNet's circle fields.
COCO_GT_SCHEMA = {"images": [{"id": "int", "width": "size", "height": "size", "file_name?": "text",
                              "scene_id?": "text"}],
                  "annotations": [{"image_id": "int", "category_id?": "int", "circle_center": "xy",
                                   "circle_radius": "length"}],
                  "categories": [{"id": "int", "name?": "text"}]}


def read_coco_gt(dataset_dir: str | Path) -> dict:
    """A dataset's coco_gt.json, checked against COCO_GT_SCHEMA."""
    path = Path(dataset_dir) / "coco_gt.json"
    if not path.is_file():
        raise SphereBenchError(f"{dataset_dir}: no coco_gt.json: the dataset is incomplete; rebuild it")
    coco = read_checked_json(path, COCO_GT_SCHEMA)
    # what scoring would otherwise meet only after every method has run
    rebuild = "the file is damaged; rebuild the dataset with the command that wrote it (generate or prepare)"
    if not coco["categories"]:
        raise SphereBenchError(f"{path}: categories is empty (it names the ball's category); {rebuild}")
    ids = {im["id"] for im in coco["images"]}
    categories = {c["id"] for c in coco["categories"]}
    for i, ann in enumerate(coco["annotations"]):
        if ann["image_id"] not in ids:
            raise SphereBenchError(f"{path}: annotations[{i}].image_id is {ann['image_id']}, which no image has; "
                                   f"{rebuild}")
        if ann.get("category_id") is not None and ann["category_id"] not in categories:
            raise SphereBenchError(f"{path}: annotations[{i}].category_id is {ann['category_id']}, which no category "
                                   f"has; {rebuild}")
    return coco
