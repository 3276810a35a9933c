"""Spheres seen as 2D circles: the ground-truth rule and the two projection rules of a detection.

Every 2D circle here is (cx, cy, r) in pixels, with the pixel-centre convention of
``spherebench.camera`` (u = column, v = row).

- ``mask_circle``: CircleNet's rule for turning a mask into a circle, the smallest enclosing
  circle of the mask's pixel centres (OpenCV). Along a long boundary some pixel centre lies
  almost on the true outline, so this circle is within a few tenths of a pixel of the true
  silhouette's (measured in tests/test_circles.py); growing it by half a pixel overshoots.
- ``sphere_circle_paper``: the paper's rule (Table 3): project the centre, and a point R to
  its left at the same depth; the pixel distance is the radius.
- ``sphere_circle_exact``: the sphere's true silhouette (an ellipse in a pinhole image, wider
  off-axis) reduced to a circle by ``mask_circle``, as the ground truth is (analytic when the
  silhouette lies wholly inside an undistorted image with fx = fy; rasterised otherwise).
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from spherebench.camera import Intrinsics, pixel_rays, project


def norm3(v) -> float:
    """|v| of a 3-vector in plain float arithmetic: numpy's norm of a vector is a BLAS dot product,
    whose rounding depends on the CPU's kernel (ground truth written on two machines would differ in
    its last bits)."""
    x, y, z = float(v[0]), float(v[1]), float(v[2])
    return math.sqrt(x * x + y * y + z * z)


def circle_bbox(cx: float, cy: float, r: float, decimals: int | None = None) -> list[float]:
    """The box [x, y, w, h] px round a circle (COCO's bbox), so that a circle result loads in any
    COCO tool (pycocotools' loadRes needs a bbox or a segmentation); rounded to ``decimals`` if given."""
    box = [float(cx) - float(r), float(cy) - float(r), 2.0 * float(r), 2.0 * float(r)]
    return box if decimals is None else [round(v, decimals) for v in box]


def mask_circle(mask: np.ndarray) -> tuple[float, float, float] | None:
    """Smallest enclosing circle (cx, cy, r) px of a boolean mask (H, W); None if empty."""
    m = np.asarray(mask).astype(np.uint8)
    if not m.any():
        return None
    contours, _ = cv2.findContours(m, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    pts = np.concatenate([c.reshape(-1, 2) for c in contours]).astype(np.float32)
    (cx, cy), r = cv2.minEnclosingCircle(pts)
    return float(cx), float(cy), float(r)


def sphere_circle_paper(intr: Intrinsics, centre_m, radius_m: float) -> tuple[float, float, float] | None:
    """The paper's rule: centre projected, radius = pixel distance to the point R to its left."""
    c = np.asarray(centre_m, dtype=np.float64).reshape(3)
    if c[2] <= 0:
        return None
    if not intr.has_distortion:  # a plain pinhole: the same numbers without numpy's per-call cost
        x, y, z = float(c[0]), float(c[1]), float(c[2])
        return intr.fx * x / z + intr.ppx, intr.fy * y / z + intr.ppy, intr.fx * radius_m / z
    uv = project(intr, np.stack([c, c - np.array([radius_m, 0.0, 0.0])]))
    (cx, cy), (lx, ly) = uv
    return float(cx), float(cy), float(math.hypot(cx - lx, cy - ly))


def sphere_silhouette_mask(intr: Intrinsics, centre_m, radius_m: float) -> np.ndarray:
    """Pixels (H, W) bool whose centre ray meets the sphere: its full, unoccluded silhouette.

    A ray meets the sphere iff its angle to the centre's direction is at most asin(R / |c|).
    Exact under the intrinsics' distortion model too, since rays come from ``pixel_rays``.
    """
    c = np.asarray(centre_m, dtype=np.float64).reshape(3)
    mask = np.zeros(intr.shape, dtype=bool)
    dist = norm3(c)
    if dist <= radius_m:  # camera inside the ball: every forward ray meets it
        mask[:] = True
        return mask
    box = _silhouette_box(intr, c, radius_m)
    if box is None:
        return mask
    u0, v0, u1, v1 = box
    v, u = np.mgrid[v0:v1 + 1, u0:u1 + 1]
    rays = pixel_rays(intr, u.astype(np.float64), v.astype(np.float64))
    along = rays[..., 0] * c[0] + rays[..., 1] * c[1] + rays[..., 2] * c[2]  # no BLAS product (``norm3``)
    cos_ray = along / (np.linalg.norm(rays, axis=-1) * dist)
    mask[v0:v1 + 1, u0:u1 + 1] = cos_ray >= math.sqrt(1.0 - (radius_m / dist) ** 2)
    return mask


def _silhouette_box(intr: Intrinsics, c: np.ndarray, radius_m: float):
    """Integer pixel box (u0, v0, u1, v1) holding the silhouette, clipped to the image; None if outside."""
    if c[2] <= radius_m:  # the silhouette reaches the image border or beyond: scan the whole image
        return 0, 0, intr.width - 1, intr.height - 1
    # extreme points of the sphere seen from the camera, sampled round the limb, projected
    dist = norm3(c)
    axis = c / dist
    a = np.cross(axis, [0.0, 1.0, 0.0] if abs(axis[1]) < 0.9 else [1.0, 0.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(axis, a)
    sin_t = radius_m / dist
    cos_t = math.sqrt(1.0 - sin_t * sin_t)
    phi = np.linspace(0, 2 * np.pi, 64, endpoint=False)
    # limb circle: points on the sphere where rays are tangent
    limb = (c[None, :] - radius_m * sin_t * axis[None, :]
            + radius_m * cos_t * (np.cos(phi)[:, None] * a + np.sin(phi)[:, None] * b))
    if np.any(limb[:, 2] <= 1e-6):
        return 0, 0, intr.width - 1, intr.height - 1
    uv = project(intr, limb)
    pad = 2 + 0.05 * (uv.max(0) - uv.min(0)).max()  # the polygon of 64 limb points under-reaches slightly
    u0 = max(0, int(math.floor(uv[:, 0].min() - pad)))
    v0 = max(0, int(math.floor(uv[:, 1].min() - pad)))
    u1 = min(intr.width - 1, int(math.ceil(uv[:, 0].max() + pad)))
    v1 = min(intr.height - 1, int(math.ceil(uv[:, 1].max() + pad)))
    if u0 > u1 or v0 > v1:
        return None
    return u0, v0, u1, v1


def sphere_circle_exact(intr: Intrinsics, centre_m, radius_m: float) -> tuple[float, float, float] | None:
    """The silhouette's smallest enclosing circle (the ground truth's rule), clipped to the image.

    When the intrinsics have no distortion, fx == fy, and the silhouette's amodal enclosing circle
    (``sphere_circle_amodal``, analytic) lies wholly inside the image, that circle is returned:
    nothing is clipped, and it is the enclosing circle of the true outline, which the rasterised
    rule matches to a few tenths of a pixel (see ``mask_circle``) at a fraction of the cost (a
    near ball's silhouette is tens of thousands of pixels). Otherwise the silhouette is rasterised
    within the image and reduced by ``mask_circle``.
    """
    c = np.asarray(centre_m, dtype=np.float64).reshape(3)
    if not intr.has_distortion and abs(intr.fx - intr.fy) <= 1e-9 * intr.fx:
        circ = sphere_circle_amodal(intr, c, radius_m)
        if circ is not None:
            cx, cy, r = circ
            if cx - r >= -0.5 and cy - r >= -0.5 and cx + r <= intr.width - 0.5 and cy + r <= intr.height - 0.5:
                return circ
    return mask_circle(sphere_silhouette_mask(intr, c, radius_m))


def sphere_circle_visible(intr: Intrinsics, centre_m, radius_m: float, depth_m: np.ndarray,
                          margin_m: float) -> tuple[float, float, float] | None:
    """The smallest enclosing circle of the silhouette's pixels that no nearer surface hides (the
    ground truth's rule for a partly hidden ball: its visible mask): the silhouette clipped to the
    image and to the pixels whose measured depth ``depth_m`` (H, W) metres (or what reads it at [v, u]) lies no more than
    ``margin_m`` in front of the sphere's near surface on the pixel's ray (a pixel without depth,
    NaN or 0, counts as seen). None when none is seen."""
    c = np.asarray(centre_m, dtype=np.float64).reshape(3)
    mask = sphere_silhouette_mask(intr, c, radius_m)
    v, u = np.nonzero(mask)
    if len(v) == 0:
        return None
    rays = pixel_rays(intr, u.astype(np.float64), v.astype(np.float64))  # z = 1: t is the depth
    along = rays[:, 0] * c[0] + rays[:, 1] * c[1] + rays[:, 2] * c[2]
    r2 = rays[:, 0] * rays[:, 0] + rays[:, 1] * rays[:, 1] + 1.0
    c2 = c[0] * c[0] + c[1] * c[1] + c[2] * c[2]
    z_near = (along - np.sqrt(np.maximum(along * along - r2 * (c2 - radius_m * radius_m), 0.0))) / r2
    z = np.asarray(depth_m[v, u], np.float64)  # an array, or a lookup of the pixels' depths (method.detector.FrameDepth)
    hidden = np.isfinite(z) & (z > 0) & (z < z_near - margin_m)
    mask[v[hidden], u[hidden]] = False
    return mask_circle(mask)


def sphere_circle_amodal(intr: Intrinsics, centre_m, radius_m: float) -> tuple[float, float, float] | None:
    """Smallest enclosing circle of the whole silhouette ellipse, not clipped to the image.

    For an undistorted pinhole with fx = fy the silhouette is an ellipse whose major axis is
    radial: its ends lie at angles theta -/+ alpha from the optical axis (theta: the centre's
    angle off axis, alpha = asin(R / |c|)); the enclosing circle is centred on the ellipse with
    the semi-major axis as radius. With distortion or fx != fy, the silhouette is rasterised on
    an enlarged canvas instead. None when the ball is not wholly in front of the camera.
    """
    c = np.asarray(centre_m, dtype=np.float64).reshape(3)
    dist = norm3(c)
    if dist <= radius_m:
        return None
    alpha = math.asin(radius_m / dist)
    theta = math.acos(max(-1.0, min(1.0, c[2] / dist)))
    if theta + alpha >= math.pi / 2 - 1e-6:
        return None
    if intr.has_distortion or abs(intr.fx - intr.fy) > 1e-9 * intr.fx:
        pad_w, pad_h = intr.width, intr.height
        big = Intrinsics(width=3 * intr.width, height=3 * intr.height, ppx=intr.ppx + pad_w, ppy=intr.ppy + pad_h,
                         fx=intr.fx, fy=intr.fy, model=intr.model, coeffs=intr.coeffs, depth_scale=intr.depth_scale)
        circ = mask_circle(sphere_silhouette_mask(big, c, radius_m))
        return None if circ is None else (circ[0] - pad_w, circ[1] - pad_h, circ[2])
    near, far = math.tan(theta - alpha), math.tan(theta + alpha)
    rho = math.hypot(c[0], c[1])
    dirx, diry = (c[0] / rho, c[1] / rho) if rho > 0 else (1.0, 0.0)
    mid = 0.5 * (near + far)
    return (intr.ppx + intr.fx * mid * dirx, intr.ppy + intr.fy * mid * diry, 0.5 * intr.fx * (far - near))


def circle_from_points(points_px: np.ndarray) -> tuple[float, float, float] | None:
    """Smallest enclosing circle of 2D points (N, 2) px, e.g. a polygon annotation."""
    pts = np.asarray(points_px, dtype=np.float32).reshape(-1, 2)
    if len(pts) == 0:
        return None
    (cx, cy), r = cv2.minEnclosingCircle(pts)
    return float(cx), float(cy), float(r)


def disc_mask(circle_px, shape: tuple[int, int]) -> np.ndarray:
    """Pixels (H, W) bool whose centre lies within the circle (cx, cy, r) px."""
    cx, cy, r = circle_px
    v, u = np.mgrid[0:shape[0], 0:shape[1]]
    return (u - cx) ** 2 + (v - cy) ** 2 <= r * r
