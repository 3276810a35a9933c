"""Circle intersection over union, exact: CircleNet's cIOU.

A circle is (cx, cy, r) in pixels. The intersection of two circles at centre distance d is
- empty when d >= r1 + r2 (disjoint or tangent from outside),
- the smaller disc, area pi * min(r1, r2)^2, when d <= |r1 - r2| (one inside the other),
- otherwise the lens: r1^2 acos(x1) + r2^2 acos(x2) - sqrt((-d+r1+r2)(d+r1-r2)(d-r1+r2)(d+r1+r2)) / 2,
  with x1 = (d^2 + r1^2 - r2^2) / (2 d r1) and x2 = (d^2 + r2^2 - r1^2) / (2 d r2)
  (two circular segments; the square root is four times the area of the triangle of sides
  d, r1, r2, by Heron's formula).
The IoU is that area over pi r1^2 + pi r2^2 - area. Two zero-radius circles have no area, and
their IoU is defined as 0 (a point earns no overlap credit), as a zero-radius circle with
any other circle.
"""

from __future__ import annotations

import math

import numpy as np

from spherebench.errors import SphereBenchError


def _as_circles(circles, name: str) -> np.ndarray:
    """(N, 3) float64 array of circles, checked: finite, radius >= 0."""
    arr = np.asarray(circles, dtype=np.float64)
    if arr.size == 0:
        return arr.reshape(0, 3)
    if arr.ndim == 1 and arr.shape[0] == 3:
        arr = arr[None, :]
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise SphereBenchError(f"{name} must be circles of shape (N, 3) as (cx, cy, r) pixels, got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise SphereBenchError(f"{name} hold NaN or infinite values: pass finite (cx, cy, r) pixels")
    if np.any(arr[:, 2] < 0):
        raise SphereBenchError(f"{name} hold a negative radius: radii must be >= 0 pixels")
    return arr


def _one_circle(circle, name: str) -> tuple[float, float, float]:
    arr = _as_circles(circle, name)
    if arr.shape != (1, 3):
        raise SphereBenchError(f"{name} must be one circle (cx, cy, r) pixels, got shape {np.shape(circle)}")
    return float(arr[0, 0]), float(arr[0, 1]), float(arr[0, 2])


def circle_intersection_area(a, b) -> float:
    """Area (px^2) of the intersection of circles a = (cx, cy, r) and b, pixels."""
    (ax, ay, ar), (bx, by, br) = _one_circle(a, "circle a"), _one_circle(b, "circle b")
    d = math.hypot(ax - bx, ay - by)
    if d >= ar + br:
        return 0.0
    if d <= abs(ar - br):
        return math.pi * min(ar, br) ** 2
    x1 = max(-1.0, min(1.0, (d * d + ar * ar - br * br) / (2.0 * d * ar)))
    x2 = max(-1.0, min(1.0, (d * d + br * br - ar * ar) / (2.0 * d * br)))
    heron = max(0.0, (-d + ar + br) * (d + ar - br) * (d - ar + br) * (d + ar + br))
    return ar * ar * math.acos(x1) + br * br * math.acos(x2) - 0.5 * math.sqrt(heron)


def circle_iou(a, b) -> float:
    """IoU in [0, 1] of two circles (cx, cy, r), pixels. 0 when both have zero area."""
    inter = circle_intersection_area(a, b)
    ar, br = _one_circle(a, "circle a")[2], _one_circle(b, "circle b")[2]
    union = math.pi * (ar * ar + br * br) - inter
    return inter / union if union > 0 else 0.0


def circle_intersection_matrix(dets, gts) -> np.ndarray:
    """Intersection areas (D, G) px^2 between circles dets (D, 3) and gts (G, 3), (cx, cy, r) pixels."""
    d_c = _as_circles(dets, "detections")
    g_c = _as_circles(gts, "ground-truth circles")
    if len(d_c) == 0 or len(g_c) == 0:
        return np.zeros((len(d_c), len(g_c)))
    dist = np.hypot(d_c[:, None, 0] - g_c[None, :, 0], d_c[:, None, 1] - g_c[None, :, 1])
    r1, r2 = np.broadcast_arrays(d_c[:, None, 2], g_c[None, :, 2])
    inter = np.zeros(dist.shape)
    inside = dist <= np.abs(r1 - r2)
    inter[inside] = np.pi * np.minimum(r1, r2)[inside] ** 2
    lens = ~inside & (dist < r1 + r2)  # here d > |r1 - r2| >= 0, so d > 0 and r1, r2 > 0
    if np.any(lens):
        d, p, q = dist[lens], r1[lens], r2[lens]
        x1 = np.clip((d * d + p * p - q * q) / (2.0 * d * p), -1.0, 1.0)
        x2 = np.clip((d * d + q * q - p * p) / (2.0 * d * q), -1.0, 1.0)
        heron = np.maximum(0.0, (-d + p + q) * (d + p - q) * (d - p + q) * (d + p + q))
        inter[lens] = p * p * np.arccos(x1) + q * q * np.arccos(x2) - 0.5 * np.sqrt(heron)
    return np.maximum(inter, 0.0)


def circle_iou_matrix(dets, gts) -> np.ndarray:
    """IoU (D, G) between detections (D, 3) and ground truths (G, 3), each (cx, cy, r) pixels.

    Vectorised form of ``circle_iou`` (same cases, same conventions); empty inputs give an
    empty (D, G) array.
    """
    d_c = _as_circles(dets, "detections")
    g_c = _as_circles(gts, "ground-truth circles")
    inter = circle_intersection_matrix(d_c, g_c)
    union = np.pi * (d_c[:, None, 2] ** 2 + g_c[None, :, 2] ** 2) - inter
    out = np.zeros(inter.shape)
    np.divide(inter, union, out=out, where=union > 0)
    return np.clip(out, 0.0, 1.0)
