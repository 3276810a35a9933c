"""Ground truth of recorded scenes from manual annotation and from the ball's colour.

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

Colour-derived annotation (``spherebench annotate DATASET --from-colour``): for a recording
whose colour frame is registered to depth (``colour.jpg`` or ``colour.png`` in the scene
folder), ``colour_mask`` takes the ball's pixels from an HSV range (default: a saturated
yellow), keeps the largest connected component whose size fits the ball's radius at its median
depth, and fills its holes; a hand or stick in front is not of the ball's colour and stays out.
``labelme_from_mask`` writes its outline as a LabelMe polygon beside the colour frame
(``colour.json``), for a person to review in LabelMe before ``prepare --labelme`` reads it.

Reference centre (``mask_fit_centre``): a fixed-radius least-squares sphere fit to the depth
pixels of a ball's mask, with its standard error: a recording's 3D reference, independent of
any detector's search (``prepare`` stores it as the ball's center_m, center_source "mask-fit").

The review tiles and contact sheets of an annotation, and every other drawing, are ``drawing``'s.
"""

from __future__ import annotations

import json
import math
import re
from collections import Counter
from pathlib import Path

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.optimize import least_squares

from spherebench.camera import Intrinsics, deproject
from spherebench.circles import disc_mask, mask_circle
from spherebench.datasets import foreign_formats, inout, outputs
from spherebench.datasets.scene import Ball
from spherebench.errors import SphereBenchError

#: LabelMe shape types that describe a ball; others (rectangle, point, line, ...) are ignored.
BALL_SHAPE_TYPES = ("circle", "polygon")
#: Offset from LabelMe (Qt: pixel i spans [i, i + 1)) to SphereBench pixel coordinates (centres at i).
LABELME_OFFSET_PX = -0.5
#: Image names that every scene folder uses (the reprojected depth, the recorded colour frame).
SCENE_IMAGE_NAMES = ("image.png", *outputs.COLOUR_FILES)


# --------------------------------------------------------------------------- geometry

#: Fixed-point bits of the polygon vertices given to cv2.fillPoly (1/256 px).
POLYGON_SHIFT = 8


def polygon_mask(points_px: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Pixels (H, W) bool of the polygon (N, 2) of (u, v) px, as cv2.fillPoly fills it (vertices to
    1/256 px): the pixels whose centre lies inside, give or take the pixels its edges cross (fillPoly
    fills some whose centre lies up to 1 px outside). ``mask_outline``'s polygons, 0.25 px outside
    the edge pixels' centres, give their mask back exactly."""
    pts = np.asarray(points_px, dtype=np.float64).reshape(-1, 2)
    mask = np.zeros(shape, dtype=np.uint8)
    if len(pts) >= 3:
        fixed = np.round(pts * (1 << POLYGON_SHIFT)).astype(np.int32).reshape(-1, 1, 2)
        cv2.fillPoly(mask, [fixed], 1, lineType=cv2.LINE_8, shift=POLYGON_SHIFT)
    return mask.astype(bool)


# --------------------------------------------------------------------------- annotation files

def balls_from_masks(paths: list[Path], shape: tuple[int, int], radius_m: float) -> list[Ball]:
    """One ball per mask PNG, its circle the mask's smallest enclosing circle."""
    balls = []
    for path in paths:
        mask = inout.read_mask_png(path, shape)
        if not mask.any():
            raise SphereBenchError(f"{path}: the mask is empty (no non-zero pixel); draw the ball or delete the file")
        balls.append(Ball(radius_m=radius_m, mask=mask))
    return balls


def _labelme_image_matches(path: Path, doc: dict, scene_id: str, image_names: tuple[str, ...]) -> bool:
    """Does the LabelMe file's imagePath name this scene's image (or its source file)?

    'image.png' (and 'colour.jpg') is every scene's image, so the scene is then told by the folder
    in imagePath (../<scene_id>/image.png) or, for a bare name, by where the JSON lies
    (<scene_id>/image.json, <scene_id>/colour.json) or its name (<scene_id>.json).
    """
    image_path = str(doc.get("imagePath") or "").replace("\\", "/")
    if not image_path:
        return True  # nothing to check against; the size check still applies
    p = Path(image_path)
    if p.name in SCENE_IMAGE_NAMES:
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
    doc = foreign_formats.read_labelme(path)
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

    masks_dir: PNGs named <scene_id>.png or <scene_id>_<k>.png. labelme_dir: <scene_id>.json,
    <scene_id>/image.json or <scene_id>/colour.json (drawn on the colour frame). A scene may have masks or a LabelMe file, not both. What LabelMe files
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
            beside = [p for name in outputs.LABELME_FILES for p in (*root.glob(f"*/{name}"), *root.glob(f"scenes/*/{name}"))]
            for p in sorted(beside):
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


# --------------------------------------------------------------------------- colour-derived masks

#: HSV range (OpenCV's scale: H 0-179, S and V 0-255) of a saturated yellow ball under indoor
#: light: hue 18-40 (the recorded ball's is 27-31), saturation and value from 100 and 80 (its
#: specular top keeps S ~200, V 255; a hand, a stick, a grey carpet fall below).
DEFAULT_HSV = ((18, 40), (100, 255), (80, 255))
#: Grown into the chosen component: pixels of its hue that are a specular highlight (S, V at least
#: these: the recorded ball's top is S 25-100 at V 250+) or its shaded side (S, V at least these: its
#: underside is S 220+ at V 70-100, a brown carpet S < 170),
#: connected to it and inside its enclosing circle enlarged by GROW_CIRCLE. A white wall (S < 20) or a
#: hand (another hue) is neither.
HIGHLIGHT_MIN_SV = (20, 230)
SHADE_MIN_SV = (200, 50)
GROW_CIRCLE = 1.05
#: The final mask is opened with a disc of this side (px): spurs thinner than that are cut.
SPUR_PX = 7
#: A component is the ball when its enclosing-circle radius is within this factor of the radius
#: expected at its median depth (below 1: a ball partly out of frame or hidden).
SIZE_RANGE = (0.4, 1.5)
#: Components smaller than this (px) are colour noise, never a ball.
MIN_COMPONENT_PX = 30
#: Polygon outline: vertices within this distance (px) of the mask's outline (approxPolyDP).
OUTLINE_TOLERANCE_PX = 0.25
LABELME_VERSION = "5.4.1"


def parse_hsv(text: str) -> tuple[tuple[int, int], tuple[int, int], tuple[int, int]]:
    """'H0:H1,S0:S1,V0:V1' (inclusive; H 0-179, S and V 0-255, OpenCV's scale) -> the three ranges."""
    parts = [p.split(":") for p in str(text).split(",")]
    if len(parts) != 3 or any(len(p) != 2 for p in parts):
        raise SphereBenchError(f"--hsv must be H0:H1,S0:S1,V0:V1 (e.g. 18:40,100:255,80:255), got '{text}'")
    try:
        ranges = tuple((int(a), int(b)) for a, b in parts)
    except ValueError:
        raise SphereBenchError(f"--hsv must be whole numbers H0:H1,S0:S1,V0:V1, got '{text}'") from None
    for (lo, hi), name, top in zip(ranges, "HSV", (179, 255, 255)):
        if not 0 <= lo <= top or not 0 <= hi <= top:
            raise SphereBenchError(f"--hsv {name} range {lo}:{hi} is outside 0:{top} (OpenCV's HSV scale)")
        if lo > hi:
            raise SphereBenchError(f"--hsv {name} range {lo}:{hi} is inverted (empty); give the low end first")
    return ranges


def expected_radius_px(intr: Intrinsics, radius_m: float, surface_depth_m: float) -> float:
    """Image radius (px) of a ball whose visible surface has this median depth (m): its centre is
    about 2R/3 behind that (the mean depth of a hemisphere seen from afar)."""
    z = surface_depth_m + 2.0 * radius_m / 3.0
    f = math.sqrt(float(intr.fx) * float(intr.fy))
    return f * radius_m / math.sqrt(max(z * z - radius_m * radius_m, 1e-12))


def colour_mask(colour_bgr: np.ndarray, depth_m: np.ndarray, intr: Intrinsics, radius_m: float,
                hsv=DEFAULT_HSV) -> np.ndarray | None:
    """The ball's pixels (H, W) bool in a colour frame registered to depth, or None if none fits.

    Pixels in the HSV range, opened (speckle) and closed (JPEG gaps); of the connected components
    whose enclosing circle is SIZE_RANGE times the radius expected at the component's median
    valid depth (m; ``depth_m`` NaN where invalid), the largest; grown by its highlight and shaded
    side (HIGHLIGHT_MIN_SV, SHADE_MIN_SV: the hue range, other S and V) and by the bright pixels in
    its convex hull (a highlight washed out to white); spurs cut (SPUR_PX); its holes filled.
    """
    hsv_image = cv2.cvtColor(colour_bgr, cv2.COLOR_BGR2HSV)
    raw = cv2.inRange(hsv_image, tuple(int(r[0]) for r in hsv), tuple(int(r[1]) for r in hsv))
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (3, 3))
    m = cv2.morphologyEx(cv2.morphologyEx(raw, cv2.MORPH_OPEN, kernel), cv2.MORPH_CLOSE,
                         cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (5, 5)))  # gaps up to ~4 px
    n, labels, stats, _ = cv2.connectedComponentsWithStats(m, connectivity=8)
    best, best_area = None, 0
    for k in range(1, n):
        area = int(stats[k, cv2.CC_STAT_AREA])
        if area < MIN_COMPONENT_PX or area <= best_area:
            continue
        comp = labels == k
        z = depth_m[comp]
        z = z[np.isfinite(z) & (z > 0)]
        if z.size < MIN_COMPONENT_PX:
            continue  # no depth under it: its size cannot be checked
        ratio = mask_circle(comp)[2] / expected_radius_px(intr, radius_m, float(np.median(z)))
        if SIZE_RANGE[0] <= ratio <= SIZE_RANGE[1]:
            best, best_area = comp, area
    if best is None:
        return None
    grown = _grow(best, hsv_image, hsv[0])
    # a highlight washed out to white at the rim leaves a notch that colour cannot tell from a
    # white wall; inside the mask's convex hull (within the ball) bright pixels are the ball's
    hull = np.zeros(grown.shape, np.uint8)
    cv2.fillConvexPoly(hull, cv2.convexHull(np.argwhere(grown)[:, ::-1].astype(np.int32)), 1)
    grown |= hull.astype(bool) & (hsv_image[..., 2] >= HIGHLIGHT_MIN_SV[1])
    # the smallest enclosing circle follows any spur: cut those a pixel or two wide (carpet, a seam)
    smooth = cv2.morphologyEx(grown.astype(np.uint8), cv2.MORPH_OPEN,
                              cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (SPUR_PX, SPUR_PX)))
    n, labels, stats, _ = cv2.connectedComponentsWithStats(smooth, connectivity=8)
    if n < 2:
        return None
    main = labels == 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    contours, _ = cv2.findContours(main.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    filled = np.zeros(main.shape, np.uint8)
    cv2.drawContours(filled, contours, -1, 1, thickness=cv2.FILLED)
    return filled.astype(bool)


def _grow(core: np.ndarray, hsv_image: np.ndarray, hue: tuple[int, int]) -> np.ndarray:
    """The core with the pixels of its hue that are its highlight or shade, connected to it, in its circle."""
    h, s, v = (hsv_image[..., k].astype(np.int32) for k in range(3))
    loose = (h >= hue[0]) & (h <= hue[1]) & (((s >= HIGHLIGHT_MIN_SV[0]) & (v >= HIGHLIGHT_MIN_SV[1]))
                                             | ((s >= SHADE_MIN_SV[0]) & (v >= SHADE_MIN_SV[1])))
    cx, cy, r = mask_circle(core)
    loose &= disc_mask((cx, cy, GROW_CIRCLE * r), core.shape)
    n, labels = cv2.connectedComponents((loose | core).astype(np.uint8), connectivity=8)
    keep = np.unique(labels[core])
    return np.isin(labels, keep[keep > 0])


def mask_outline(mask: np.ndarray) -> list[np.ndarray]:
    """Polygons (N, 2) (u, v) px of a mask's outer outlines, 0.25 px outside its edge pixels'
    centres, so that ``polygon_mask`` gives the mask back (the mask's holes are not kept)."""
    # on the mask doubled, the outline runs through the outer quarter of each edge pixel
    big = cv2.resize(np.asarray(mask, np.uint8), None, fx=2, fy=2, interpolation=cv2.INTER_NEAREST)
    contours, _ = cv2.findContours(big, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    out = []
    for c in contours:
        poly = cv2.approxPolyDP(c, 2 * OUTLINE_TOLERANCE_PX, closed=True).reshape(-1, 2).astype(np.float64)
        if len(poly) >= 3:
            out.append((poly + 0.5) / 2.0 - 0.5)
    return out


def _labelme_shape(points_px, shape_type: str, label: str, description: str) -> dict:
    """A LabelMe shape of SphereBench pixel coordinates (centres at integers), in LabelMe's."""
    return {"label": label, "points": [[round(float(x) - LABELME_OFFSET_PX, 2), round(float(y) - LABELME_OFFSET_PX, 2)]
                                       for x, y in points_px],
            "group_id": None, "description": description, "shape_type": shape_type, "flags": {}}


def _labelme_doc(shapes: list[dict], image_name: str, shape: tuple[int, int]) -> dict:
    return {"version": LABELME_VERSION, "flags": {}, "shapes": shapes, "imagePath": image_name,
            "imageData": None, "imageHeight": int(shape[0]), "imageWidth": int(shape[1])}


def labelme_from_mask(mask: np.ndarray | None, image_name: str, label: str = "ball",
                      description: str = "") -> dict:
    """A LabelMe document (one polygon per outline of the mask; none for None) for an image."""
    shapes = [_labelme_shape(poly, "polygon", label, description)
              for poly in (mask_outline(mask) if mask is not None else [])]
    return _labelme_doc(shapes, image_name, mask.shape if mask is not None else (0, 0))


def labelme_from_circles(circles_px, image_name: str, shape: tuple[int, int], label: str = "ball",
                         descriptions=None) -> dict:
    """A LabelMe document of circles (cx, cy, r) px on an image of ``shape`` (H, W): LabelMe's circle
    shape, its centre and a point on its rim, which ``balls_from_labelme`` reads back. descriptions:
    one text per circle (e.g. the detector's score), for the reviewer."""
    circles = [tuple(float(v) for v in c[:3]) for c in circles_px]
    descriptions = descriptions or [""] * len(circles)
    shapes = [_labelme_shape([(cx, cy), (cx + r, cy)], "circle", label, text)
              for (cx, cy, r), text in zip(circles, descriptions)]
    return _labelme_doc(shapes, image_name, shape)


def labelme_text(doc: dict) -> str:
    """A LabelMe document as JSON text, one [x, y] point per line (LabelMe reads any layout)."""
    text = json.dumps(doc, indent=1)
    return re.sub(r"\[\s+(-?[\d.]+),\s+(-?[\d.]+)\s+\]", r"[\1, \2]", text) + "\n"


# --------------------------------------------------------------------------- reference centre

#: Mask pixels within this many px of the mask's edge are left out of the fit: the colour-to-depth
#: registration and mixed depth at the ball's rim put background depths there.
FIT_ERODE_PX = 2
#: Depths farther than this many radii from the mask's median depth are not the ball's surface.
FIT_DEPTH_WINDOW_R = 1.5
#: Points whose residual exceeds this many robust sigmas are left out of the final fit.
FIT_INLIER_SIGMAS = 3.0
#: Fewer points than this give no reference centre.
FIT_MIN_POINTS = 30


#: Block jackknife of the mask fit: blocks of about this fraction of the mask's diameter.
FIT_BLOCK_FRACTION = 0.25


@dataclass(frozen=True)
class SphereFit:
    """A fixed-radius sphere fit: centre_m (3,) m; centre_se_m (3,) m standard errors: the block
    jackknife's when the points came in spatial blocks (it holds for depth noise correlated within
    a block and for local misfit), else the Gauss-Newton covariance's (independent point errors
    only: far smaller on real depth); rms_m the inliers' RMS residual; points used, points given."""

    centre_m: tuple[float, float, float]
    centre_se_m: tuple[float, float, float]
    rms_m: float
    inliers: int
    points: int


def fit_sphere_fixed_radius(points_m: np.ndarray, radius_m: float, blocks: np.ndarray | None = None) -> SphereFit | None:
    """Least-squares centre of a sphere of known radius through surface points (N, 3) m seen from
    the origin (a camera): residuals |p - c| - R, started R behind the points' median along its
    ray; a robust (soft L1) fit, then a plain one on the inliers. Standard errors: with blocks
    (N,) int (spatial blocks of the points, at least 4), the delete-one-block jackknife of the
    inlier fit; else its Gauss-Newton covariance. None for fewer than FIT_MIN_POINTS points."""
    pts = np.asarray(points_m, dtype=np.float64).reshape(-1, 3)
    finite = np.isfinite(pts).all(axis=1)
    pts = pts[finite]
    blocks = None if blocks is None else np.asarray(blocks).reshape(-1)[finite]
    if len(pts) < FIT_MIN_POINTS:
        return None
    med = np.median(pts, axis=0)
    start = med + radius_m * med / max(np.linalg.norm(med), 1e-9)

    def residuals(c, p):
        return np.linalg.norm(p - c, axis=1) - radius_m

    def jacobian(c, p):
        d = c - p
        return d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)

    scale = max(1.4826 * float(np.median(np.abs(residuals(start, pts)))), 1e-4)
    robust = least_squares(residuals, start, jac=jacobian, args=(pts,), loss="soft_l1", f_scale=scale)
    r = residuals(robust.x, pts)
    sigma = max(1.4826 * float(np.median(np.abs(r))), 1e-6)
    keep = np.abs(r) <= FIT_INLIER_SIGMAS * sigma
    if keep.sum() < FIT_MIN_POINTS:
        return None
    fit = least_squares(residuals, robust.x, jac=jacobian, args=(pts[keep],))
    r = fit.fun
    labels = np.unique(blocks[keep]) if blocks is not None else ()
    if len(labels) >= 4:
        ids = blocks[keep]
        loo = np.array([least_squares(residuals, fit.x, jac=jacobian, args=(pts[keep][ids != b],)).x
                        for b in labels])
        k = len(labels)
        se = np.sqrt((k - 1) / k * ((loo - loo.mean(axis=0)) ** 2).sum(axis=0))
    else:
        j = jacobian(fit.x, pts[keep])
        se = np.sqrt(np.diag(float(r @ r) / max(len(r) - 3, 1) * np.linalg.pinv(j.T @ j)))
    return SphereFit(tuple(float(x) for x in fit.x), tuple(float(x) for x in se),
                     float(np.sqrt(np.mean(r * r))), int(keep.sum()), len(pts))


def mask_fit_centre(depth_m: np.ndarray, intr: Intrinsics, mask: np.ndarray, radius_m: float) -> SphereFit | None:
    """The reference centre of a ball from its mask's depth pixels (``fit_sphere_fixed_radius``).

    depth_m: (H, W) metres, NaN where invalid. The mask is eroded by FIT_ERODE_PX and depths
    beyond FIT_DEPTH_WINDOW_R radii of its median dropped first; the standard error is the block
    jackknife's over square blocks of FIT_BLOCK_FRACTION of the mask's diameter (about 12-16
    blocks). None when too few points remain.
    """
    k = 2 * FIT_ERODE_PX + 1
    core = cv2.erode(np.asarray(mask, np.uint8), cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k))).astype(bool)
    if core.sum() < FIT_MIN_POINTS:  # a sliver of a ball: its own pixels, edge and all
        core = np.asarray(mask, bool)
    v, u = np.nonzero(core & np.isfinite(depth_m) & (depth_m > 0))
    if len(u) < FIT_MIN_POINTS:
        return None
    z = depth_m[v, u].astype(np.float64)
    near = np.abs(z - np.median(z)) <= FIT_DEPTH_WINDOW_R * radius_m
    u, v, z = u[near], v[near], z[near]
    side = max(4, round(FIT_BLOCK_FRACTION * 2.0 * math.sqrt(core.sum() / math.pi)))
    blocks = (v // side) * (intr.width // side + 1) + u // side
    return fit_sphere_fixed_radius(deproject(intr, u, v, z), radius_m, blocks)
