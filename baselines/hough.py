"""Classical 2D baseline: OpenCV's Hough circle transform on the reprojected depth images.

Input: the image every 2D method gets, the depth colourised with a colour map (BGR uint8,
``spherebench.datasets.reproject``). By default the depth level (0..255) is recovered first by
inverting that colour map (each colour -> the nearest of its 256 entries; black, invalid
depth -> 0), because a colour map such as JET is not monotonic in brightness and a plain grey
conversion can erase the edge between a ball and a background of equal luma. ``input="luma"``
uses the plain grey conversion instead.

Pipeline: depth level -> median blur -> ``cv2.HoughCircles`` (``HOUGH_GRADIENT`` or
``HOUGH_GRADIENT_ALT``) -> one score per circle.

Score: HoughCircles returns no score (its Python binding drops the accumulator votes), so each
circle is scored by its edge support: the fraction of n = max(16, ceil(2 pi r)) points evenly
spaced on the circle that lie within ``support_tol_px`` of a Canny edge (the thresholds
HOUGH_GRADIENT uses itself: param1 / 2, param1) where the image gradient is within
``support_angle_deg`` of the radial direction. The denominator is all n points, so a circle
half outside the image or half occluded scores at most about 0.5. In [0, 1]; ties keep
OpenCV's order (strongest accumulator first).

``tune`` chooses the parameters by mAP.50 (circle IoU, COCO protocol) on the images and
circles it is given: pass it the training split, never the benchmark scenes.
"""

from __future__ import annotations

import dataclasses
import functools
import itertools
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import cv2
import numpy as np

from spherebench.errors import SphereBenchError
from spherebench.eval.metrics.coco_eval import (coco_from_circles, evaluate_circles, load_ground_truth,
                                                results_from_circles)

#: The tuned configuration shipped with the package (a copy of results/hough_config.json, which
#: `make eval` writes and copies here): what `evaluate` uses without --hough-config, so that an
#: installed package never re-tunes.
SHIPPED_CONFIG = Path(__file__).resolve().with_name("hough_config.json")

_METHODS = {"gradient": cv2.HOUGH_GRADIENT, "gradient_alt": cv2.HOUGH_GRADIENT_ALT}
_INPUTS = ("colormap", "luma")


@dataclass(frozen=True)
class HoughConfig:
    """Parameters of the Hough baseline; ``tune`` picks the benchmark's values on the training split.

    Defaults: OpenCV's HoughCircles tutorial (dp 1, param1 100) with a lower vote threshold
    (15, not 30) for balls of 5-40 px radius, and radii for a basketball at 0.5-5 m in a
    424x240 D435 frame (f ~ 213 px: r ~ 213 * 0.12 / z px).

    method: "gradient" (cv2.HOUGH_GRADIENT) or "gradient_alt" (cv2.HOUGH_GRADIENT_ALT).
    dp: inverse accumulator resolution (1 = image resolution).
    min_dist_px: least distance between detected centres, pixels.
    param1: Canny's high threshold (low = param1 / 2).
    param2: accumulator threshold (gradient: votes, smaller = more circles; gradient_alt: circle
        "perfectness" in (0, 1]).
    min_radius_px, max_radius_px: radius range, pixels.
    blur_ksize: median blur aperture before the transform (odd; 0 or 1 = none).
    input: "colormap" (depth level recovered from the colour map) or "luma" (grey conversion).
    colormap: OpenCV colour map id of the images (the benchmark's: JET).
    max_circles: most circles kept per image (highest scores).
    support_tol_px, support_angle_deg: edge-support score tolerances (module docstring).
    """

    method: str = "gradient"
    dp: float = 1.0
    min_dist_px: float = 15.0
    param1: float = 100.0
    param2: float = 15.0
    min_radius_px: int = 4
    max_radius_px: int = 80
    blur_ksize: int = 5
    input: str = "colormap"
    colormap: int = cv2.COLORMAP_JET
    max_circles: int = 100
    support_tol_px: int = 1
    support_angle_deg: float = 30.0

    def __post_init__(self) -> None:
        problems = []
        if self.method not in _METHODS:
            problems.append(f"method '{self.method}' is not one of {', '.join(_METHODS)}")
        if not self.dp >= 1.0:
            problems.append(f"dp={self.dp} must be >= 1")
        if not self.min_dist_px > 0:
            problems.append(f"min_dist_px={self.min_dist_px} must be > 0")
        if not self.param1 > 0:
            problems.append(f"param1={self.param1} must be > 0")
        if self.method == "gradient_alt" and not 0 < self.param2 <= 1:
            problems.append(f"param2={self.param2} must be in (0, 1] for gradient_alt")
        if self.method == "gradient" and not self.param2 > 0:
            problems.append(f"param2={self.param2} must be > 0")
        if not 0 <= self.min_radius_px <= self.max_radius_px or self.max_radius_px <= 0:
            problems.append(f"radius range {self.min_radius_px}..{self.max_radius_px} px must satisfy "
                            "0 <= min <= max, max > 0")
        if self.blur_ksize not in (0, 1) and (self.blur_ksize < 3 or self.blur_ksize % 2 == 0):
            problems.append(f"blur_ksize={self.blur_ksize} must be 0, 1 or an odd number >= 3")
        if self.input not in _INPUTS:
            problems.append(f"input '{self.input}' is not one of {', '.join(_INPUTS)}")
        if self.max_circles < 1:
            problems.append(f"max_circles={self.max_circles} must be >= 1")
        if self.support_tol_px < 0 or not 0 < self.support_angle_deg <= 90:
            problems.append("support_tol_px must be >= 0 and support_angle_deg in (0, 90]")
        if problems:
            raise SphereBenchError("invalid Hough configuration: " + "; ".join(problems))


@functools.lru_cache(maxsize=8)
def _colormap_table(colormap: int) -> np.ndarray:
    """(256, 3) int32 BGR colour of each level 0..255 under an OpenCV colour map."""
    levels = np.arange(256, dtype=np.uint8).reshape(256, 1)
    return cv2.applyColorMap(levels, colormap).reshape(256, 3).astype(np.int32)


def depth_level(image_bgr: np.ndarray, colormap: int = cv2.COLORMAP_JET) -> np.ndarray:
    """Invert a colour map: (H, W, 3) uint8 BGR -> (H, W) uint8 level; black (invalid) -> 0.

    Each distinct colour goes to its nearest table colour (exact for lossless images).
    """
    img = _check_image(image_bgr)
    if img.ndim == 2:
        return img
    table = _colormap_table(int(colormap))
    packed = (img[..., 0].astype(np.int32) << 16) | (img[..., 1].astype(np.int32) << 8) | img[..., 2]
    colours, inverse = np.unique(packed.reshape(-1), return_inverse=True)
    bgr = np.stack([(colours >> 16) & 255, (colours >> 8) & 255, colours & 255], axis=1)
    d2 = ((bgr[:, None, :] - table[None, :, :]) ** 2).sum(axis=2)  # (U, 256), U = distinct colours
    level = np.argmin(d2, axis=1).astype(np.uint8)
    level[colours == 0] = 0
    return level[inverse].reshape(img.shape[:2])


def _check_image(image) -> np.ndarray:
    img = np.asarray(image)
    if img.dtype != np.uint8 or not (img.ndim == 2 or (img.ndim == 3 and img.shape[2] == 3)):
        raise SphereBenchError(f"expected an (H, W, 3) uint8 BGR image (or (H, W) uint8), got {img.dtype} "
                               f"of shape {img.shape}")
    if min(img.shape[:2]) < 8:
        raise SphereBenchError(f"image of shape {img.shape} is too small for circle detection")
    return img


def _prepare(image_bgr: np.ndarray, cfg: HoughConfig) -> np.ndarray:
    """The (H, W) uint8 image the transform sees: depth level or luma, median-blurred."""
    img = _check_image(image_bgr)
    if img.ndim == 2:
        grey = img
    elif cfg.input == "colormap":
        grey = depth_level(img, cfg.colormap)
    else:
        grey = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    return cv2.medianBlur(grey, cfg.blur_ksize) if cfg.blur_ksize >= 3 else np.ascontiguousarray(grey)


def edge_support(grey: np.ndarray, circles: np.ndarray, cfg: HoughConfig) -> np.ndarray:
    """Edge-support score (N,) in [0, 1] of circles (N, 3) (cx, cy, r) px on a prepared image (H, W)."""
    circles = np.asarray(circles, dtype=np.float64).reshape(-1, 3)
    if len(circles) == 0:
        return np.zeros(0)
    edges = cv2.Canny(grey, max(1.0, cfg.param1 / 2.0), cfg.param1)
    if cfg.support_tol_px > 0:
        k = 2 * cfg.support_tol_px + 1
        edges = cv2.dilate(edges, np.ones((k, k), np.uint8))
    g = grey.astype(np.float32)
    gx = cv2.Sobel(g, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(g, cv2.CV_32F, 0, 1, ksize=3)
    cos_tol = math.cos(math.radians(cfg.support_angle_deg))
    h, w = grey.shape
    scores = np.zeros(len(circles))
    for i, (cx, cy, r) in enumerate(circles):
        n = max(16, int(math.ceil(2.0 * math.pi * r)))
        th = np.linspace(0.0, 2.0 * math.pi, n, endpoint=False)
        ct, st = np.cos(th), np.sin(th)
        u = np.rint(cx + r * ct).astype(np.int64)
        v = np.rint(cy + r * st).astype(np.int64)
        inside = (u >= 0) & (u < w) & (v >= 0) & (v < h)
        u, v, ct, st = u[inside], v[inside], ct[inside], st[inside]
        gxs, gys = gx[v, u], gy[v, u]
        mag = np.hypot(gxs, gys)
        radial = np.abs(gxs * ct + gys * st) >= cos_tol * mag  # the edge runs along the circle
        scores[i] = np.count_nonzero((edges[v, u] > 0) & radial & (mag > 0)) / n
    return scores


def _detect_prepared(grey: np.ndarray, cfg: HoughConfig) -> list[tuple[float, float, float, float]]:
    found = cv2.HoughCircles(grey, _METHODS[cfg.method], cfg.dp, cfg.min_dist_px, param1=cfg.param1,
                             param2=cfg.param2, minRadius=int(cfg.min_radius_px), maxRadius=int(cfg.max_radius_px))
    if found is None:
        return []
    circles = found.reshape(-1, found.shape[-1])[:, :3].astype(np.float64)
    scores = edge_support(grey, circles, cfg)
    order = np.argsort(-scores, kind="stable")[:cfg.max_circles]
    return [(float(circles[i, 0]), float(circles[i, 1]), float(circles[i, 2]), float(scores[i])) for i in order]


def detect_circles(image_bgr: np.ndarray, config: HoughConfig | None = None) -> list[tuple[float, float, float, float]]:
    """Circles (cx, cy, r, score) in pixels, best first, of one (H, W, 3) uint8 BGR image."""
    cfg = config or HoughConfig()
    return _detect_prepared(_prepare(image_bgr, cfg), cfg)


#: A small default search: HOUGH_GRADIENT over its vote threshold and Canny threshold, and
#: HOUGH_GRADIENT_ALT over its perfectness threshold.
DEFAULT_GRID: list[dict] = (
    [{"method": "gradient", "dp": dp, "param1": p1, "param2": p2}
     for dp, p1, p2 in itertools.product((1.0, 1.5), (50.0, 100.0), (10.0, 15.0, 20.0, 30.0))]
    + [{"method": "gradient_alt", "dp": 1.5, "param1": p1, "param2": p2}
       for p1, p2 in itertools.product((50.0, 100.0, 200.0), (0.6, 0.75, 0.9))]
)


def _expand_grid(grid: dict | Sequence[dict] | None) -> list[dict]:
    """A dict of lists (Cartesian product, in key order) or a list of dicts -> list of overrides."""
    if grid is None:
        return [dict(g) for g in DEFAULT_GRID]
    if isinstance(grid, dict):
        keys = list(grid)
        values = [list(grid[k]) if isinstance(grid[k], (list, tuple)) else [grid[k]] for k in keys]
        combos = [dict(zip(keys, vals)) for vals in itertools.product(*values)]
    else:
        combos = [dict(g) for g in grid]
    if not combos:
        raise SphereBenchError("the tuning grid is empty: give at least one setting")
    fields = {f.name for f in dataclasses.fields(HoughConfig)}
    for combo in combos:
        unknown = set(combo) - fields
        if unknown:
            raise SphereBenchError(f"unknown Hough parameters in the grid: {', '.join(sorted(unknown))} "
                                   f"(known: {', '.join(sorted(fields))})")
    return combos


def grid_scores(images: Sequence[np.ndarray], gt_circles: Sequence, grid: dict | Sequence[dict] | None = None,
                base: HoughConfig | None = None) -> list[tuple[HoughConfig, dict]]:
    """Every configuration of ``grid`` (overrides of ``base``) with its COCO metrics on the images.

    images: N (H, W, 3) uint8 BGR. gt_circles: N arrays (G_i, 3) (cx, cy, r) px (G_i may be 0).
    Returns [(config, scalar metrics of ``evaluate_circles``)] in grid order.
    """
    if len(images) == 0 or len(images) != len(gt_circles):
        raise SphereBenchError(f"tuning needs images and ground-truth circles, as many of each "
                               f"(got {len(images)} images, {len(gt_circles)} circle lists)")
    base = base or HoughConfig()
    configs = [dataclasses.replace(base, **combo) for combo in _expand_grid(grid)]
    coco_gt = load_ground_truth(coco_from_circles(gt_circles))
    prepared: dict[tuple, list[np.ndarray]] = {}  # the prepared images depend on input and blur only
    out = []
    for cfg in configs:
        key = (cfg.input, cfg.colormap, cfg.blur_ksize)
        if key not in prepared:
            prepared[key] = [_prepare(img, cfg) for img in images]
        dets = [_detect_prepared(g, cfg) for g in prepared[key]]
        metrics = evaluate_circles(coco_gt, results_from_circles(dets))
        out.append((cfg, {k: v for k, v in metrics.items() if isinstance(v, (float, int))}))
    return out


def tune(images: Sequence[np.ndarray], gt_circles: Sequence, grid: dict | Sequence[dict] | None = None,
         base: HoughConfig | None = None) -> HoughConfig:
    """The configuration of ``grid`` with the best mAP.50 on the given (training) images.

    Ties go to the higher mAP (.50:.95), then to the earlier grid entry. Arguments as
    ``grid_scores``; ``grid`` = None searches DEFAULT_GRID.
    """
    scored = grid_scores(images, gt_circles, grid, base)

    def key(item: tuple[HoughConfig, dict]) -> tuple[float, float]:
        m = item[1]
        return (np.nan_to_num(m["mAP50"], nan=-1.0), np.nan_to_num(m["mAP"], nan=-1.0))

    best = scored[0]
    for item in scored[1:]:
        if key(item) > key(best):
            best = item
    return best[0]
