"""Ground truth of recorded scenes from manual annotation, and drawing ground truth for viewing.

Annotations are matched to scenes by file stem = scene id (``spherebench prepare`` names scenes
after their source file or frame):

- mask PNGs: ``<scene_id>.png`` (one ball) or ``<scene_id>_<k>.png`` (ball k), non-zero = ball,
  drawn on the scene's own image (same size). The circle is the mask's smallest enclosing circle
  (``spherebench.circles.mask_circle``, CircleNet's rule).
- LabelMe JSON: ``<scene_id>.json``, or ``<scene_id>/image.json`` (where LabelMe saves when one
  opens ``scenes/<scene_id>/image.png``). ``circle`` shapes are [centre, point on the rim] and
  give the circle directly; ``polygon`` shapes are rasterised to a mask and reduced to its
  smallest enclosing circle. Other shapes (rectangle, ellipse, point, line, ...) and, with
  ``--label``, shapes of other labels are ignored, and ``prepare`` says which. A LabelMe file with
  no shape at all is a deliberate empty annotation: the scene is annotated with no ball (a
  negative). A file whose shapes are all ignored says nothing about balls: its scene stays
  unannotated (not a negative). LabelMe stores Qt image coordinates, in which pixel i covers
  [i, i + 1); SphereBench puts pixel centres at integers, so LabelMe points are shifted by -0.5 px.

Drawing: ``draw_ground_truth`` renders circles on the reprojected image; ``ball_point_colors``
colours a scene's cloud (ball red, rest grey) for MeshLab.
"""

from __future__ import annotations

import math
import re
from collections import Counter
from pathlib import Path

import cv2
import numpy as np

from spherebench.datasets import io
from spherebench.datasets.scene import Ball, Scene
from spherebench.errors import SphereBenchError

#: LabelMe shape types that describe a ball; others (rectangle, point, line, ...) are ignored.
BALL_SHAPE_TYPES = ("circle", "polygon")
#: Offset from LabelMe (Qt: pixel i spans [i, i + 1)) to SphereBench pixel coordinates (centres at i).
LABELME_OFFSET_PX = -0.5


# --------------------------------------------------------------------------- geometry

def polygon_mask(points_px: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Pixels (H, W) bool whose centre lies inside the polygon (N, 2) of (u, v) px (even-odd rule)."""
    pts = np.asarray(points_px, dtype=np.float64).reshape(-1, 2)
    mask = np.zeros(shape, dtype=bool)
    if len(pts) < 3:
        return mask
    u0 = max(0, int(math.floor(pts[:, 0].min())))
    u1 = min(shape[1] - 1, int(math.ceil(pts[:, 0].max())))
    v0 = max(0, int(math.floor(pts[:, 1].min())))
    v1 = min(shape[0] - 1, int(math.ceil(pts[:, 1].max())))
    if u0 > u1 or v0 > v1:
        return mask
    v, u = np.mgrid[v0:v1 + 1, u0:u1 + 1].astype(np.float64)
    inside = np.zeros(u.shape, dtype=bool)
    a, b = pts, np.roll(pts, -1, axis=0)
    for (ax, ay), (bx, by) in zip(a, b):
        if ay == by:
            continue  # a horizontal edge never crosses a horizontal ray
        crosses = (ay > v) != (by > v)
        x_at = ax + (v - ay) * (bx - ax) / (by - ay)
        inside ^= crosses & (u < x_at)
    mask[v0:v1 + 1, u0:u1 + 1] = inside
    return mask


def disc_mask(circle_px, shape: tuple[int, int]) -> np.ndarray:
    """Pixels (H, W) bool whose centre lies within the circle (cx, cy, r) px."""
    cx, cy, r = circle_px
    v, u = np.mgrid[0:shape[0], 0:shape[1]]
    return (u - cx) ** 2 + (v - cy) ** 2 <= r * r


# --------------------------------------------------------------------------- annotation files

def balls_from_masks(paths: list[Path], shape: tuple[int, int], radius_m: float) -> list[Ball]:
    """One ball per mask PNG, its circle the mask's smallest enclosing circle."""
    balls = []
    for path in paths:
        mask = io.read_mask_png(path, shape)
        if not mask.any():
            raise SphereBenchError(f"{path}: the mask is empty (no non-zero pixel); draw the ball or delete the file")
        balls.append(Ball(radius_m=radius_m, mask=mask))
    return balls


def _labelme_image_matches(path: Path, doc: dict, scene_id: str, image_names: tuple[str, ...]) -> bool:
    """Does the LabelMe file's imagePath name this scene's image (or its source file)?

    'image.png' is every scene's image, so the scene is then told by the folder in imagePath
    (../<scene_id>/image.png) or, for a bare name, by where the JSON lies (<scene_id>/image.json)
    or its name (<scene_id>.json).
    """
    image_path = str(doc.get("imagePath") or "").replace("\\", "/")
    if not image_path:
        return True  # nothing to check against; the size check still applies
    p = Path(image_path)
    if p.name == "image.png":
        if p.parent.name not in ("", ".", ".."):
            return p.parent.name == scene_id
        return scene_id in (path.parent.name, path.stem)
    return p.stem == scene_id or p.name in image_names


def balls_from_labelme(path: Path, shape: tuple[int, int], radius_m: float, scene_id: str,
                       image_names: tuple[str, ...] = ("image.png",),
                       label: str | None = None) -> tuple[list[Ball], list[str]]:
    """Balls of a LabelMe file drawn on this scene's image: circles as drawn, polygons via their mask.

    image_names: file names the annotated image may have (the scene's image.png, its source file).
    label: keep only shapes with this label (None: every circle and polygon).
    Returns (balls, ignored): ignored names each shape that is not a ball, as "rectangle" or
    "circle labelled 'hand'".
    """
    doc = io.read_labelme(path)
    h, w = shape
    if (doc["imageWidth"], doc["imageHeight"]) != (w, h):
        raise SphereBenchError(f"{path}: LabelMe image is {doc['imageWidth']}x{doc['imageHeight']} but scene "
                               f"{scene_id} is {w}x{h}: annotate the scene's own image.png")
    if not _labelme_image_matches(path, doc, scene_id, image_names):
        raise SphereBenchError(f"{path}: LabelMe file is for image '{doc.get('imagePath')}', not scene {scene_id}: "
                               "annotate scenes/<scene_id>/image.png and name the file after the scene")
    balls, ignored = [], []
    for i, s in enumerate(doc["shapes"]):
        kind = s.get("shape_type") or "polygon"
        if kind not in BALL_SHAPE_TYPES:
            ignored.append(str(kind))
            continue
        if label is not None and s.get("label") != label:
            ignored.append(f"{kind} labelled '{s.get('label')}'")
            continue
        pts = np.asarray(s["points"], dtype=np.float64) + LABELME_OFFSET_PX
        if kind == "circle":
            if len(pts) != 2:
                raise SphereBenchError(f"{path}: LabelMe circle {i} must have 2 points (centre, rim), has {len(pts)}")
            r = float(np.hypot(*(pts[1] - pts[0])))
            if not r > 0:
                raise SphereBenchError(f"{path}: LabelMe circle {i} has zero radius")
            circle = (float(pts[0, 0]), float(pts[0, 1]), r)
            mask = disc_mask(circle, shape)
            if not mask.any():
                raise SphereBenchError(f"{path}: LabelMe circle {i} covers no pixel centre of the {w}x{h} image: "
                                       "was it drawn on another image?")
            balls.append(Ball(radius_m=radius_m, mask=mask, circle_px=circle))
        else:
            mask = polygon_mask(pts, shape)
            if not mask.any():
                raise SphereBenchError(f"{path}: LabelMe polygon {i} covers no pixel centre of the {w}x{h} image")
            balls.append(Ball(radius_m=radius_m, mask=mask))
    return balls, ignored


_INDEX_SUFFIX = re.compile(r"^(?P<stem>.+)_(?P<k>\d+)$")


class AnnotationIndex:
    """The annotation files of a mask folder and/or a LabelMe folder, looked up by scene id.

    masks_dir: PNGs named <scene_id>.png or <scene_id>_<k>.png. labelme_dir: <scene_id>.json or
    <scene_id>/image.json. A scene may have masks or a LabelMe file, not both. What LabelMe files
    left out (shapes that are not balls, files with no ball shape) is summed up by ``notes``.
    """

    def __init__(self, masks_dir: str | Path | None = None, labelme_dir: str | Path | None = None,
                 label: str | None = None):
        self.label = label
        self._masks: dict[str, list[Path]] = {}
        self._labelme: dict[str, Path] = {}
        self._used: dict[Path, str] = {}
        self._ignored: Counter[str] = Counter()  # shape descriptions over every LabelMe file read
        self._with_ignored: list[Path] = []  # files that held ignored shapes
        self._no_ball_shape: list[Path] = []  # files whose shapes were all ignored
        for kind, folder in (("--masks", masks_dir), ("--labelme", labelme_dir)):
            if folder is not None and not Path(folder).is_dir():
                raise SphereBenchError(f"{folder}: {kind} must be a folder of annotation files")
        if masks_dir is not None:
            self._mask_files = sorted(p for p in Path(masks_dir).iterdir() if p.suffix.lower() == ".png")
        else:
            self._mask_files = []
        if labelme_dir is not None:
            root = Path(labelme_dir)
            for p in sorted(root.glob("*.json")):
                self._labelme[p.stem] = p
            for p in sorted(root.glob("*/image.json")) + sorted(root.glob("scenes/*/image.json")):
                if p.parent.name in self._labelme and self._labelme[p.parent.name] != p:
                    raise SphereBenchError(f"{p}: scene {p.parent.name} has two LabelMe files "
                                           f"({self._labelme[p.parent.name]}); keep one")
                self._labelme[p.parent.name] = p

    @property
    def empty(self) -> bool:
        return not self._mask_files and not self._labelme

    def mask_files(self, scene_id: str) -> list[Path]:
        """<scene_id>.png, then <scene_id>_<k>.png in k order."""
        found = []
        for p in self._mask_files:
            m = _INDEX_SUFFIX.match(p.stem)
            if p.stem == scene_id:
                found.append((-1, p))
            elif m and m.group("stem") == scene_id:
                found.append((int(m.group("k")), p))
        return [p for _, p in sorted(found)]

    def _claim(self, path: Path, scene_id: str) -> None:
        # 'a_1.png' is ball 1 of scene 'a' and the mask of a scene 'a_1': refuse to guess
        other = self._used.get(path)
        if other is not None and other != scene_id:
            raise SphereBenchError(f"{path}: this annotation matches scenes {other} and {scene_id}; rename it "
                                   f"to <scene_id>.png or <scene_id>_<k>.png of one scene")
        self._used[path] = scene_id

    def balls_for(self, scene_id: str, shape: tuple[int, int], radius_m: float,
                  image_names: tuple[str, ...] = ("image.png",)) -> list[Ball] | None:
        """The scene's balls, or None when nothing annotates it."""
        masks = self.mask_files(scene_id)
        labelme = self._labelme.get(scene_id)
        if masks and labelme is not None:
            raise SphereBenchError(f"scene {scene_id} has both mask PNGs ({masks[0]}) and a LabelMe file ({labelme}); "
                                   "keep one kind of annotation per scene")
        for p in [*masks, *([labelme] if labelme is not None else [])]:
            self._claim(p, scene_id)
        if masks:
            return balls_from_masks(masks, shape, radius_m)
        if labelme is not None:
            balls, ignored = balls_from_labelme(labelme, shape, radius_m, scene_id, image_names, self.label)
            self._ignored.update(ignored)
            if ignored:
                self._with_ignored.append(labelme)
                if not balls:
                    self._no_ball_shape.append(labelme)
                    return None  # nothing was said about balls: not a negative
            return balls
        return None

    def labelme_file(self, scene_id: str) -> Path | None:
        return self._labelme.get(scene_id)

    def notes(self) -> list[str]:
        """What the LabelMe files read so far left out, each said once for all files."""
        if not self._ignored:
            return []
        what = ", ".join(f"{n} {kind}" for kind, n in sorted(self._ignored.items(), key=lambda kv: (-kv[1], kv[0])))
        ball = f"a circle or polygon labelled '{self.label}'" if self.label is not None else "a circle or polygon"
        notes = [f"LabelMe shapes that are not balls were ignored in {len(self._with_ignored)} file(s), e.g. "
                 f"{self._with_ignored[0]}: {what} (a ball is {ball})"]
        if self._no_ball_shape:
            notes.append(f"{len(self._no_ball_shape)} LabelMe file(s) hold no ball shape, e.g. "
                         f"{self._no_ball_shape[0]}: their scenes stay unannotated, not negatives (a file with "
                         "no shape at all marks a negative)")
        return notes

    def unused(self) -> list[Path]:
        """Annotation files that matched no scene (a typo in a name, or a frame not selected)."""
        return sorted(p for p in [*self._mask_files, *self._labelme.values()] if p not in self._used)


# --------------------------------------------------------------------------- drawing

GT_COLOR_BGR = (0, 255, 0)
AMODAL_COLOR_BGR = (255, 255, 255)
REFERENCE_COLOR_BGR = (0, 255, 255)
BALL_RGB = (255, 0, 0)
REFERENCE_RGB = (255, 200, 0)
REST_RGB = (150, 150, 150)
_SHIFT = 4  # cv2 fixed-point bits: sub-pixel circle centres and radii


def _dashed_circle(image: np.ndarray, circle, color, thickness: int = 1, dash_deg: float = 12.0) -> None:
    cx, cy, r = circle
    for start in np.arange(0.0, 360.0, 2 * dash_deg):
        cv2.ellipse(image, (round(cx * (1 << _SHIFT)), round(cy * (1 << _SHIFT))),
                    (round(r * (1 << _SHIFT)), round(r * (1 << _SHIFT))), 0.0, float(start),
                    float(start + dash_deg), color, thickness, cv2.LINE_AA, _SHIFT)


def draw_ground_truth(image_bgr: np.ndarray, scene: Scene) -> np.ndarray:
    """(H, W, 3) uint8 BGR copy of the image with each ball's circle drawn: the visible-mask
    circle solid green, the amodal circle (when known) dashed white, the centre as a cross; a
    reference centre from meta (not ground truth) as a yellow cross."""
    out = image_bgr.copy()
    for ball in scene.balls:
        if ball.amodal_circle_px is not None:
            _dashed_circle(out, ball.amodal_circle_px, AMODAL_COLOR_BGR)
        if ball.circle_px is not None:
            cx, cy, r = ball.circle_px
            c = (round(cx * (1 << _SHIFT)), round(cy * (1 << _SHIFT)))
            cv2.circle(out, c, round(r * (1 << _SHIFT)), GT_COLOR_BGR, 2, cv2.LINE_AA, _SHIFT)
            cv2.drawMarker(out, (round(cx), round(cy)), GT_COLOR_BGR, cv2.MARKER_CROSS, 8, 1)
    ref = scene.meta.get("reference_center_m")
    if ref is not None and scene.intrinsics is not None and ref[2] > 0:
        from spherebench.camera import project
        u, v = project(scene.intrinsics, np.asarray([ref]))[0]
        if np.isfinite(u) and np.isfinite(v):
            cv2.drawMarker(out, (round(u), round(v)), REFERENCE_COLOR_BGR, cv2.MARKER_TILTED_CROSS, 12, 2)
    return out


def ball_point_colors(scene: Scene, radius_m: float | None = None,
                      tolerance_m: float = 0.02) -> tuple[np.ndarray, np.ndarray, str]:
    """The scene's cloud coloured for viewing: (points (N, 3) m, colours (N, 3) uint8 RGB, how).

    Organised scenes: a point is the ball's when its pixel is in a ball's mask (or, lacking a
    mask, inside its circle). Image-less scenes: when within radius + tolerance_m of a ball's 3D
    centre. Lacking both, points within that distance of meta's reference_center_m (the source's
    own estimate, not ground truth) are coloured orange. ``how`` says which rule applied.
    radius_m: the dataset's ball radius, used round the reference centre (default: the balls').
    """
    cloud = scene.to_cloud()
    colors = np.tile(np.asarray(REST_RGB, np.uint8), (len(cloud), 1))
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
        centres = [b.center_m for b in scene.balls if b.center_m is not None]
        for b in scene.balls:
            if b.center_m is not None:
                ball |= np.linalg.norm(cloud.points - np.asarray(b.center_m, np.float32), axis=1) \
                        <= b.radius_m + tolerance_m
        if centres:
            how.append(f"ball = points within radius + {tolerance_m:g} m of the ground-truth centre")
        elif scene.balls:
            how.append("no 3D ground-truth centre: the ball cannot be coloured in an image-less scene")
    colors[ball] = BALL_RGB
    ref = scene.meta.get("reference_center_m")
    radius = radius_m if radius_m is not None else (scene.balls[0].radius_m if scene.balls else None)
    if not ball.any() and ref is not None and radius is not None:
        near = np.linalg.norm(cloud.points - np.asarray(ref, np.float32), axis=1) <= radius + tolerance_m
        colors[near] = REFERENCE_RGB
        how.append(f"orange = within {radius:g} + {tolerance_m:g} m of the source's reference centre (NOT ground truth)")
    if not how:
        how.append("no ground truth: every point grey" if not scene.annotated or not scene.balls
                   else "no ball points")
    return cloud.points, colors, "; ".join(how)
