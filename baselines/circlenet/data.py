"""Training data of the CircleNet-style baseline: a dataset folder, augmentation, target rendering.

A dataset folder (``spherebench generate``) holds DIR/coco_gt.json (COCO with CircleNet's
``circle_center`` / ``circle_radius`` fields) and DIR/scenes/<id>/image.png. Only the COCO file
and the images are read here: the 2D method sees what every 2D method sees.

Augmentation (training from scratch needs it; CenterNet's recipe adapted to depth colourings):
horizontal flip, random scale and crop (one affine warp onto the network's input canvas), and a
jitter of the depth colouring (hue rotation = shifting the depth-to-colour map of a JET-like
colouring, saturation and brightness, pixel noise), on valid pixels only, so that black keeps
meaning "no depth". Every random draw comes from numpy.random.default_rng([seed, epoch, index]):
the same seed gives the same samples, whatever the worker count and across a resume.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from pathlib import Path

import cv2
import numpy as np
import torch

from spherebench.baselines.circlenet.imaging import (PAD_VALUE, STRIDE, fit_image, input_size, load_image, pad_image,
                                                     pixel_to_grid, scale_circles)
from spherebench.circles import circle_from_points
from spherebench.datasets import inout
from spherebench.errors import SphereBenchError

#: Targets are Gaussians whose radius is the centre displacement at which a circle still overlaps
#: its displaced copy with this IoU (CenterNet's min_overlap 0.7, made exact for circles).
MIN_OVERLAP_IOU = 0.7


@dataclass
class AugmentConfig:
    """Training augmentation; ``None`` in place of it means none (validation)."""

    flip: float = 0.5  # probability of a horizontal flip
    scale: tuple[float, float] = (0.6, 1.4)  # CenterNet's random scale range
    shift: float = 0.2  # random translation, fraction of the input side
    hue_deg: float = 20.0  # hue rotation, degrees: moves the depth-to-colour mapping
    saturation: float = 0.2  # relative
    brightness: float = 0.2  # relative
    noise: float = 3.0  # pixel noise std, grey levels
    min_visible_px: int = 16  # a ball cropped to fewer visible pixels is dropped from the targets

    def to_dict(self) -> dict:
        return asdict(self)


# ---------------------------------------------------------------- reading a dataset folder

@dataclass
class ImageRecord:
    """One image of a dataset: id, path, size (px), scene id, and its circles (N, 3) (cx, cy, r) px."""

    image_id: int
    path: Path
    width: int
    height: int
    scene_id: str
    circles: np.ndarray


def read_dataset(root) -> list[ImageRecord]:
    """The images of a dataset folder with their ground-truth circles, in COCO order."""
    root = Path(root)
    coco_path = root / "coco_gt.json"
    if not root.is_dir():
        raise SphereBenchError(f"dataset folder {root} not found")
    if not coco_path.is_file():
        raise SphereBenchError(f"{root} has no coco_gt.json: not a dataset folder "
                               "(make one with `spherebench generate --preset train`)")
    coco = inout.read_json(coco_path)
    try:
        images, anns = coco["images"], coco.get("annotations", [])
    except (KeyError, TypeError, AttributeError) as exc:
        raise SphereBenchError(f"{coco_path} is not a COCO file with images ({exc}); regenerate the dataset") from None
    if not images:
        raise SphereBenchError(f"{coco_path} lists no images: the dataset is empty")
    by_image: dict[int, list] = {}
    try:
        for a in anns:
            if a.get("iscrowd", 0):
                continue
            by_image.setdefault(int(a["image_id"]), []).append([*map(float, a["circle_center"]), float(a["circle_radius"])])
        records = [ImageRecord(int(im["id"]), root / im["file_name"], int(im["width"]), int(im["height"]),
                               str(im.get("scene_id", im["id"])),
                               np.asarray(by_image.get(int(im["id"]), []), dtype=np.float64).reshape(-1, 3))
                   for im in images]
    except (KeyError, TypeError, ValueError) as exc:
        raise SphereBenchError(f"{coco_path} lacks CircleNet's circle fields ({exc!r}); regenerate the dataset") from None
    missing = [str(r.path) for r in records if not r.path.is_file()]
    if missing:
        raise SphereBenchError(f"{len(missing)} image(s) listed in {coco_path} are missing, e.g. {missing[0]}")
    # the files of a dataset are checked before any work (docs/formats.md): each scene's gt.json too,
    # though training reads the circles of coco_gt.json only
    for r in records:
        if (r.path.parent / "gt.json").is_file():
            inout.read_scene_gt(r.path.parent)
    return records


def read_datasets(roots) -> list[ImageRecord]:
    """The images of one dataset folder (``read_dataset``), or of several as one: image ids
    renumbered in folder order and scene ids prefixed with the folder's position, so that two
    presets' scenes of the same name stay apart in the validation split."""
    roots = [roots] if isinstance(roots, (str, Path)) else list(roots)
    if len(roots) == 1:
        return read_dataset(roots[0])
    if len({Path(r).resolve() for r in roots}) < len(roots):
        raise SphereBenchError("the same training folder is given twice: give each --data once")
    records: list[ImageRecord] = []
    for k, root in enumerate(roots):
        for r in read_dataset(root):
            records.append(ImageRecord(len(records) + 1, r.path, r.width, r.height, f"{k}:{r.scene_id}", r.circles))
    return records


def split_scenes(records: list[ImageRecord], val_fraction: float, seed: int) -> tuple[list[ImageRecord], list[ImageRecord]]:
    """Split a training dataset into (train, validation) by scene, seeded; validation >= 1 scene."""
    scenes = sorted({r.scene_id for r in records})
    if len(scenes) < 2:
        raise SphereBenchError(f"the training data has {len(scenes)} scene(s); at least 2 are needed "
                               "(one for validation)")
    n_val = min(len(scenes) - 1, max(1, round(val_fraction * len(scenes))))
    order = np.random.default_rng(seed).permutation(len(scenes))
    val = {scenes[i] for i in order[:n_val]}
    return [r for r in records if r.scene_id not in val], [r for r in records if r.scene_id in val]


# ---------------------------------------------------------------- targets

def _equal_circle_iou(d_over_r: float) -> float:
    """IoU of two circles of equal radius whose centres are d = d_over_r * r apart."""
    x = min(d_over_r, 2.0)
    inter = 2 * math.acos(x / 2) - 0.5 * x * math.sqrt(4 - x * x)  # lens area / r^2
    return inter / (2 * math.pi - inter)


def _displacement_ratio(iou: float) -> float:
    """d / r at which _equal_circle_iou falls to iou (bisection: it decreases with d)."""
    lo, hi = 0.0, 2.0
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if _equal_circle_iou(mid) > iou else (lo, mid)
    return 0.5 * (lo + hi)


_DISPLACEMENT_RATIO = _displacement_ratio(MIN_OVERLAP_IOU)  # ~0.28


def gaussian_sigma(radius_grid: float) -> float:
    """Std of the target Gaussian (grid cells) for a circle of radius_grid cells (CenterNet's
    sigma = diameter / 6 with diameter = 2 * displacement + 1)."""
    return (2 * _DISPLACEMENT_RATIO * radius_grid + 1) / 6


def render_targets(circles: np.ndarray, grid_size: tuple[int, int], max_objects: int = 32) -> dict[str, np.ndarray]:
    """Training targets for the circles (N, 3) (cx, cy, r) px on a grid (h, w) cells.

    Returns heat (1, h, w) float32 (1 at each centre cell, Gaussians around, max where they
    meet), cells (M,) int64 flat centre cells, mask (M,) float32 (1 = a circle), offset (M, 2)
    sub-cell (dx, dy), radius (M, 1) grid units; M = max_objects (extra circles are dropped).
    """
    h, w = grid_size
    heat = np.zeros((1, h, w), np.float32)
    cells = np.zeros(max_objects, np.int64)
    mask = np.zeros(max_objects, np.float32)
    offset = np.zeros((max_objects, 2), np.float32)
    radius = np.zeros((max_objects, 1), np.float32)
    k = 0
    for cx, cy, r in np.asarray(circles, dtype=np.float64).reshape(-1, 3):
        g = pixel_to_grid([cx, cy])
        cell = np.floor(g).astype(int)
        if not (0 <= cell[0] < w and 0 <= cell[1] < h) or k >= max_objects:
            continue
        sigma = gaussian_sigma(r / STRIDE)
        span = int(math.ceil(3 * sigma))
        x0, x1 = max(0, cell[0] - span), min(w, cell[0] + span + 1)
        y0, y1 = max(0, cell[1] - span), min(h, cell[1] + span + 1)
        yy, xx = np.mgrid[y0:y1, x0:x1]
        blob = np.exp(-((xx - cell[0]) ** 2 + (yy - cell[1]) ** 2) / (2 * sigma * sigma))
        np.maximum(heat[0, y0:y1, x0:x1], blob, out=heat[0, y0:y1, x0:x1])
        cells[k] = cell[1] * w + cell[0]
        mask[k] = 1.0
        offset[k] = g - cell
        radius[k] = r / STRIDE
        k += 1
    return {"heat": heat, "cells": cells, "mask": mask, "offset": offset, "radius": radius}


# ---------------------------------------------------------------- augmentation

def jitter_colours(image: np.ndarray, aug: AugmentConfig, rng: np.random.Generator) -> np.ndarray:
    """Jitter the depth colouring of valid (non-black) pixels of an RGB image (H, W, 3) uint8."""
    valid = image.max(axis=2) > PAD_VALUE
    hsv = cv2.cvtColor(image, cv2.COLOR_RGB2HSV)  # uint8, H in [0, 180)
    levels = np.arange(256, dtype=np.float64)
    # per-channel look-up tables: a hue rotation, saturation and brightness gains
    lut_h = np.mod(np.round(levels + rng.uniform(-aug.hue_deg, aug.hue_deg) / 2), 180)
    lut_s = levels * (1 + rng.uniform(-aug.saturation, aug.saturation))
    lut_v = levels * (1 + rng.uniform(-aug.brightness, aug.brightness))
    for c, lut in enumerate((lut_h, lut_s, lut_v)):
        hsv[..., c] = np.clip(lut, 0, 255).astype(np.uint8)[hsv[..., c]]
    out = cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB).astype(np.float32)
    out += aug.noise * rng.standard_normal(out.shape, dtype=np.float32)
    out = np.clip(out, 1, 255).astype(np.uint8)  # >= 1: a valid pixel never turns into "no depth"
    return np.where(valid[..., None], out, image)


def _clip_circle(c: np.ndarray, rect: tuple[float, float, float, float], min_px: int) -> np.ndarray | None:
    """The ground-truth rule on a circle (cx, cy, r) px cut by a rectangle (x0, y0, x1, y1) (pixel
    edges): the smallest enclosing circle of the disc's visible pixel centres; None if too few."""
    cx, cy, r = c
    x0, y0, x1, y1 = rect
    if cx - r >= x0 and cx + r <= x1 and cy - r >= y0 and cy + r <= y1:
        return c
    u0, u1 = int(math.ceil(max(cx - r, x0 + 0.5))), int(math.floor(min(cx + r, x1 - 0.5)))
    v0, v1 = int(math.ceil(max(cy - r, y0 + 0.5))), int(math.floor(min(cy + r, y1 - 0.5)))
    if u0 > u1 or v0 > v1:
        return None
    vv, uu = np.mgrid[v0:v1 + 1, u0:u1 + 1]
    inside = (uu - cx) ** 2 + (vv - cy) ** 2 <= r * r
    if inside.sum() < min_px:
        return None
    return np.asarray(circle_from_points(np.stack([uu[inside], vv[inside]], axis=1)))


def augment(image: np.ndarray, circles: np.ndarray, size: tuple[int, int], aug: AugmentConfig,
            rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Flip, scale, crop and colour-jitter an RGB image (H, W, 3) uint8 with its circles (N, 3) px
    onto a canvas (Hp, Wp). Returns the canvas (Hp, Wp, 3) uint8 and the visible circles (N', 3)."""
    h, w = image.shape[:2]
    hp, wp = size
    image = jitter_colours(image, aug, rng)
    s = rng.uniform(*aug.scale)
    flip = rng.random() < aug.flip
    tx = (wp - 1) / 2 - s * (w - 1) / 2 + rng.uniform(-aug.shift, aug.shift) * wp
    ty = (hp - 1) / 2 - s * (h - 1) / 2 + rng.uniform(-aug.shift, aug.shift) * hp
    # pixel centres map as u' = s * u + tx (flipped: u -> w - 1 - u first), v' = s * v + ty
    m = np.array([[-s if flip else s, 0.0, tx + (s * (w - 1) if flip else 0.0)], [0.0, s, ty]])
    canvas = cv2.warpAffine(image, m, (wp, hp), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                            borderValue=(PAD_VALUE,) * 3)
    # the image's area on the canvas (pixel edges), clipped to the canvas
    ex = m[0, 0] * np.array([-0.5, w - 0.5]) + m[0, 2]
    ey = s * np.array([-0.5, h - 0.5]) + ty
    rect = (max(ex.min(), -0.5), max(ey.min(), -0.5), min(ex.max(), wp - 0.5), min(ey.max(), hp - 0.5))
    out = []
    for cx, cy, r in np.asarray(circles, dtype=np.float64).reshape(-1, 3):
        c = _clip_circle(np.array([m[0, 0] * cx + m[0, 2], s * cy + ty, s * r]), rect, aug.min_visible_px)
        if c is not None:
            out.append(c)
    return canvas, np.asarray(out, dtype=np.float64).reshape(-1, 3)


# ---------------------------------------------------------------- the torch Dataset

class CircleDataset(torch.utils.data.Dataset):
    """Samples for training (augment given) or validation (augment None: the inference input).

    Images of another size but the model's aspect ratio are first scaled to image_size
    (``imaging.fit_image``, as at inference); circles are in those scaled pixels.

    Each item: {"image": (3, Hp, Wp) uint8 RGB, "heat": (1, h, w), "cells": (M,), "mask": (M,),
    "offset": (M, 2), "radius": (M, 1), "image_id": int, "index": int (in this dataset)};
    Hp, Wp = input_size(image_size).
    """

    def __init__(self, records: list[ImageRecord], image_size: tuple[int, int], augment: AugmentConfig | None = None,
                 seed: int = 0, max_objects: int = 32):
        self.records = records
        self.image_size = tuple(image_size)
        self.size = input_size(self.image_size)
        self.grid = (self.size[0] // STRIDE, self.size[1] // STRIDE)
        self.aug = augment
        self.seed = seed
        self.epoch = 0
        self.max_objects = max_objects

    def set_epoch(self, epoch: int) -> None:
        """Draw this epoch's augmentation (call before iterating; workers copy the dataset then)."""
        self.epoch = epoch

    def __len__(self) -> int:
        return len(self.records)

    def __getitem__(self, i: int) -> dict:
        rec = self.records[i]
        image, scale = fit_image(load_image(rec.path, self.image_size), self.image_size)
        circles = scale_circles(rec.circles, scale)
        if self.aug is None:
            canvas = pad_image(image, self.size)
        else:
            rng = np.random.default_rng([self.seed, self.epoch, i])
            canvas, circles = augment(image, circles, self.size, self.aug, rng)
        item = render_targets(circles, self.grid, self.max_objects)
        item["image"] = np.ascontiguousarray(canvas.transpose(2, 0, 1))
        item["image_id"] = rec.image_id
        item["index"] = i
        return item

    def scale_of(self, i: int) -> float:
        """The factor by which item i's image is scaled to image_size (1 for the model's size)."""
        rec = self.records[i]
        if (rec.height, rec.width) == self.image_size:
            return 1.0
        return min(self.image_size[0] / rec.height, self.image_size[1] / rec.width)
