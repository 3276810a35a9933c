"""Drawing for people to look at: ground truth and detections on a scene's image (``show``,
``detect --out-png``), a scene's cloud coloured for a viewer (``show --out-ply``), and the review
tiles and contact sheets of colour-derived annotation (``annotate``). Arrays in, arrays out; the
files are written by the callers, marked as theirs (``outputs``).
"""

from __future__ import annotations

import cv2
import numpy as np

from spherebench.camera import Intrinsics, project
from spherebench.circles import disc_mask, mask_circle, sphere_silhouette_mask
from spherebench.datasets.scene import Scene


# --------------------------------------------------------------------------- review sheets

def _outline_on(image_bgr: np.ndarray, mask: np.ndarray | None, tint: bool, colour=(255, 0, 255)) -> np.ndarray:
    out = image_bgr.copy()
    if mask is not None and tint:
        tinted = out.copy()
        tinted[mask] = colour
        out = cv2.addWeighted(out, 0.65, tinted, 0.35, 0)
    if mask is not None:
        contours, _ = cv2.findContours(mask.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        cv2.drawContours(out, contours, -1, colour, 1, cv2.LINE_AA)
    return out


def review_tile(colour_bgr: np.ndarray, depth_image_bgr: np.ndarray, mask: np.ndarray | None, title: str,
                intr: Intrinsics | None = None, centre_m=None, radius_m: float | None = None,
                crop_px: int = 0, scale: float = 1.0) -> np.ndarray:
    """One scene for review: its colour frame and its reprojected depth image side by side, each
    with the mask tinted and outlined (magenta) and its smallest enclosing circle (green); the
    reference centre (when given) as a yellow cross with its sphere's projected outline (yellow).
    crop_px > 0: a square of that side round the mask instead of the whole frame (a close-up,
    the mask outlined only, so that the ball's own edge shows). scale: the panels' size factor
    (the title stays legible)."""
    panels = []
    for base in (colour_bgr, depth_image_bgr):
        im = _outline_on(base, mask, tint=not crop_px)
        if mask is not None and mask.any():
            cx, cy, r = mask_circle(mask)
            cv2.circle(im, (round(cx * 16), round(cy * 16)), round(r * 16), (0, 255, 0), 1, cv2.LINE_AA, 4)
        if centre_m is not None and intr is not None and radius_m is not None:
            u, v = project(intr, np.asarray([centre_m]))[0]
            silhouette = np.zeros(im.shape[:2], np.uint8)
            silhouette[sphere_silhouette_mask(intr, centre_m, radius_m)] = 1
            contours, _ = cv2.findContours(silhouette, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
            cv2.drawContours(im, contours, -1, (0, 255, 255), 1, cv2.LINE_AA)
            if np.isfinite(u) and np.isfinite(v):
                cv2.drawMarker(im, (round(u), round(v)), (0, 255, 255), cv2.MARKER_CROSS, 10, 1)
        if crop_px and mask is not None and mask.any():
            cx, cy, _ = mask_circle(mask)
            half = crop_px // 2
            pad = cv2.copyMakeBorder(im, half, half, half, half, cv2.BORDER_CONSTANT, value=(40, 40, 40))
            im = pad[round(cy):round(cy) + 2 * half, round(cx):round(cx) + 2 * half]
        panels.append(im if scale == 1.0 else cv2.resize(im, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA))
    tile = np.hstack(panels)
    bar = np.full((18, tile.shape[1], 3), 255, np.uint8)
    cv2.putText(bar, title, (4, 13), cv2.FONT_HERSHEY_SIMPLEX, 0.42, (0, 0, 0), 1, cv2.LINE_AA)
    return np.vstack([bar, tile])


def contact_sheet(tiles: list[np.ndarray], columns: int = 3) -> np.ndarray:
    """Tiles of one size in a grid, row by row (blank tiles pad the last row)."""
    h, w = tiles[0].shape[:2]
    rows = []
    for i in range(0, len(tiles), columns):
        row = list(tiles[i:i + columns])
        row += [np.full((h, w, 3), 255, np.uint8)] * (columns - len(row))
        rows.append(np.hstack([cv2.copyMakeBorder(t, 2, 2, 2, 2, cv2.BORDER_CONSTANT, value=(255, 255, 255))
                               for t in row]))
    return np.vstack(rows)


# --------------------------------------------------------------------------- drawing

GT_COLOUR_BGR = (0, 255, 0)
AMODAL_COLOUR_BGR = (255, 255, 255)
REFERENCE_COLOUR_BGR = (0, 255, 255)
#: Detections drawn over an image (show --predictions, detect --out-png): magenta, unlike any ground truth.
DETECTION_COLOUR_BGR = (255, 0, 255)
BALL_RGB = (255, 0, 0)
REFERENCE_RGB = (255, 200, 0)
REST_RGB = (150, 150, 150)
_SHIFT = 4  # cv2 fixed-point bits: sub-pixel circle centres and radii


def _dashed_circle(image: np.ndarray, circle, colour, thickness: int = 1, dash_deg: float = 12.0) -> None:
    cx, cy, r = circle
    for start in np.arange(0.0, 360.0, 2 * dash_deg):
        cv2.ellipse(image, (round(cx * (1 << _SHIFT)), round(cy * (1 << _SHIFT))),
                    (round(r * (1 << _SHIFT)), round(r * (1 << _SHIFT))), 0.0, float(start),
                    float(start + dash_deg), colour, thickness, cv2.LINE_AA, _SHIFT)


def draw_ground_truth(image_bgr: np.ndarray, scene: Scene) -> np.ndarray:
    """(H, W, 3) uint8 BGR copy of the image with each ball's circle drawn: the visible-mask
    circle solid green, the amodal circle (when known) dashed white, the centre as a cross; a
    reference centre from meta (not ground truth) as a yellow cross."""
    out = image_bgr.copy()
    for ball in scene.balls:
        if ball.amodal_circle_px is not None:
            _dashed_circle(out, ball.amodal_circle_px, AMODAL_COLOUR_BGR)
        if ball.circle_px is not None:
            cx, cy, r = ball.circle_px
            c = (round(cx * (1 << _SHIFT)), round(cy * (1 << _SHIFT)))
            cv2.circle(out, c, round(r * (1 << _SHIFT)), GT_COLOUR_BGR, 2, cv2.LINE_AA, _SHIFT)
            cv2.drawMarker(out, (round(cx), round(cy)), GT_COLOUR_BGR, cv2.MARKER_CROSS, 8, 1)
    ref = scene.meta.get("reference_center_m")
    if ref is not None and scene.intrinsics is not None and ref[2] > 0:
        u, v = project(scene.intrinsics, np.asarray([ref]))[0]
        if np.isfinite(u) and np.isfinite(v):
            cv2.drawMarker(out, (round(u), round(v)), REFERENCE_COLOUR_BGR, cv2.MARKER_TILTED_CROSS, 12, 2)
    return out


def draw_detections(image_bgr: np.ndarray, circles_px, scores, colour=DETECTION_COLOUR_BGR,
                    label: str = "") -> np.ndarray:
    """(H, W, 3) uint8 BGR copy of the image with each detection's circle (cx, cy, r) px, its centre
    and its score (``label`` before it, e.g. the method's name), best first: the best drawn
    thicker, so that it shows where detections overlap."""
    out = image_bgr.copy()
    h = out.shape[0]
    for k, (circle, score) in enumerate(zip(circles_px, scores)):
        if circle is None:
            continue
        cx, cy, r = (float(v) for v in circle[:3])
        c = (round(cx * (1 << _SHIFT)), round(cy * (1 << _SHIFT)))
        cv2.circle(out, c, max(1, round(r * (1 << _SHIFT))), colour, 2 if k == 0 else 1, cv2.LINE_AA, _SHIFT)
        cv2.drawMarker(out, (round(cx), round(cy)), colour, cv2.MARKER_CROSS, 6, 1)
        text = f"{label} {score:.2f}".strip()
        scale = max(0.4, h / 800)  # legible at 240 and 720 rows alike
        y = int(cy - r - 5 if cy - r - 5 >= 12 else min(cy + r + 14, h - 4))  # above the circle, else below
        cv2.putText(out, text, (int(max(0, cx - r)), y), cv2.FONT_HERSHEY_SIMPLEX, scale, (0, 0, 0), 3, cv2.LINE_AA)
        cv2.putText(out, text, (int(max(0, cx - r)), y), cv2.FONT_HERSHEY_SIMPLEX, scale, colour, 1, cv2.LINE_AA)
    return out


def ball_point_colours(scene: Scene, radius_m: float | None = None,
                      tolerance_m: float = 0.02) -> tuple[np.ndarray, np.ndarray, str]:
    """The scene's cloud coloured for viewing: (points (N, 3) m, colours (N, 3) uint8 RGB, how).

    Organised scenes: a point is the ball's when its pixel is in a ball's mask (or, lacking a
    mask, inside its circle). Image-less scenes: when within radius + tolerance_m of a ball's 3D
    centre. Lacking both, points within that distance of meta's reference_center_m (the source's
    own estimate, not ground truth) are coloured orange. ``how`` says which rule applied.
    radius_m: the dataset's ball radius, used round the reference centre (default: the balls').
    """
    cloud = scene.to_cloud()
    colours = np.tile(np.asarray(REST_RGB, np.uint8), (len(cloud), 1))
    ball = np.zeros(len(cloud), dtype=bool)
    how = []
    if cloud.rows is not None and scene.depth is not None:
        shape = scene.depth.shape
        union = np.zeros(shape, dtype=bool)
        for b in scene.balls:
            if b.mask is not None:
                union |= b.mask
            elif b.circle_px is not None:
                union |= disc_mask(b.circle_px, shape)
        ball = union[cloud.rows, cloud.cols]
        if scene.balls:
            how.append("ball = points on the ground-truth mask pixels")
    else:
        centres = [b.centre_m for b in scene.balls if b.centre_m is not None]
        for b in scene.balls:
            if b.centre_m is not None:
                ball |= np.linalg.norm(cloud.points - np.asarray(b.centre_m, np.float32), axis=1) \
                        <= b.radius_m + tolerance_m
        if centres:
            how.append(f"ball = points within radius + {tolerance_m:g} m of the ground-truth centre")
        elif scene.balls:
            how.append("no 3D ground-truth centre: the ball cannot be coloured in an image-less scene")
    colours[ball] = BALL_RGB
    ref = scene.meta.get("reference_center_m")
    radius = radius_m if radius_m is not None else (scene.balls[0].radius_m if scene.balls else None)
    if not ball.any() and ref is not None and radius is not None:
        near = np.linalg.norm(cloud.points - np.asarray(ref, np.float32), axis=1) <= radius + tolerance_m
        colours[near] = REFERENCE_RGB
        how.append(f"orange = within {radius:g} + {tolerance_m:g} m of the source's reference centre (NOT ground truth)")
    if not how:
        how.append("no ground truth: every point grey" if not scene.annotated or not scene.balls
                   else "no ball points")
    return cloud.points, colours, "; ".join(how)
