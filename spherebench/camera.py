"""Pinhole camera in librealsense's terms (``rs2_intrinsics``), with its distortion models.

Pixel convention (as librealsense): pixel (u, v) = (column, row); integer coordinates are pixel
centres, so the image spans u in [-0.5, width - 0.5]. Camera frame: x right, y down, z forward,
metres. ``project`` and ``deproject`` follow ``rs2_project_point_to_pixel`` and
``rs2_deproject_pixel_to_point`` (rsutil.h): the paper's Eq. (2) drops the depth factor; here
X = x_n * Z, Y = y_n * Z with (x_n, y_n) the undistorted normalised coordinates.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from spherebench.errors import SphereBenchError, require

#: Distortion models understood here (the librealsense names, lower case).
DISTORTION_MODELS = ("none", "brown_conrady", "modified_brown_conrady", "inverse_brown_conrady")

#: D435 depth focal length as a fraction of the image width (~213 px at 424, ~426 at 848,
#: ~643 at 1280: a ~89.6 deg horizontal field of view, as the D435's depth imagers report).
D435_FOCAL_PER_WIDTH = 0.5025

#: The D435's factory depth unit, metres per z16 count.
D435_DEPTH_SCALE_M = 0.001

#: Plausible focal lengths, as a multiple of the image's larger side: a field of view between about
#: 170 deg (0.044) and 1 deg (57); outside it the numbers are not a depth camera's (a unit slip, a
#: field of another stream).
FOCAL_PER_SIZE_RANGE = (0.04, 60.0)
#: The largest fx / fy (or fy / fx) accepted: pixels about square, as every depth camera's are.
MAX_FOCAL_RATIO = 3.0
#: The largest image side (px) read anywhere (intrinsics, depth and colour images, organised
#: clouds): twice the widest frame of a depth camera's streams (4096 px, the Azure Kinect's colour;
#: depth streams are at most 2448 px wide). A frame of 8192 x 8192 is 128 MiB of depth and 1.5 GiB
#: as a float64 cloud; a header promising more is damaged or not a camera's, and is refused before
#: anything is allocated for it.
MAX_IMAGE_SIDE_PX = 8192

#: intrinsics.json's real-valued fields, JSON numbers (a kind of ``reading.check_schema``) (a string such as "nan" is none): what is
#: missing, and the sizes, Intrinsics.from_dict words.
INTRINSICS_NUMBERS = {"ppx?": "number", "ppy?": "number", "fx?": "positive", "fy?": "positive",
                      "depth_scale?": "positive"}


#: The largest distortion coefficient taken: lens calibrations give |k| of a few units at most (a
#: fisheye's Brown-Conrady fit reaches tens); 1e308 overflows the projection.
MAX_DISTORTION_COEFF = 100.0

@dataclass(frozen=True)
class Intrinsics:
    """Camera intrinsics with the fields of pyrealsense2's ``rs.intrinsics`` plus the depth unit.

    width, height: image size, pixels. ppx, ppy: principal point, pixels. fx, fy: focal lengths,
    pixels. model: one of DISTORTION_MODELS. coeffs: five coefficients (k1, k2, p1, p2, k3).
    depth_scale: metres per depth-image count (0.001 on the D435).
    """

    width: int
    height: int
    ppx: float
    ppy: float
    fx: float
    fy: float
    model: str = "none"
    coeffs: tuple[float, float, float, float, float] = field(default=(0.0, 0.0, 0.0, 0.0, 0.0))
    depth_scale: float = D435_DEPTH_SCALE_M

    def __post_init__(self) -> None:
        object.__setattr__(self, "coeffs", tuple(float(c) for c in self.coeffs))
        object.__setattr__(self, "model", str(self.model).lower().removeprefix("rs2_distortion_").removeprefix("distortion."))
        problems = []
        if not all(float(v).is_integer() and 0 < v <= MAX_IMAGE_SIDE_PX for v in (self.width, self.height)):
            problems.append(f"image size {self.width}x{self.height} must be whole numbers of pixels from 1 to "
                            f"{MAX_IMAGE_SIDE_PX} a side (no depth camera's frame is larger)")
        for name in ("ppx", "ppy", "fx", "fy", "depth_scale"):
            if not math.isfinite(float(getattr(self, name))):
                problems.append(f"{name} is not a finite number")
        if not (float(self.fx) > 0 and float(self.fy) > 0):
            problems.append(f"focal lengths fx={self.fx}, fy={self.fy} must be > 0")
        elif not problems:
            problems += _implausible(self)
        if not float(self.depth_scale) > 0:
            problems.append(f"depth_scale={self.depth_scale} must be > 0 (0.001 for millimetre depth)")
        if self.model not in DISTORTION_MODELS:
            problems.append(f"distortion model '{self.model}' is not supported (use one of {', '.join(DISTORTION_MODELS)})")
        if len(self.coeffs) != 5 or not all(math.isfinite(c) and abs(c) <= MAX_DISTORTION_COEFF for c in self.coeffs):
            problems.append(f"coeffs must be five numbers (k1, k2, p1, p2, k3) within +-{MAX_DISTORTION_COEFF:g}, "
                            f"not {list(self.coeffs)}")
        if problems:
            raise SphereBenchError("invalid intrinsics: " + "; ".join(problems))

    @classmethod
    def d435(cls, width: int = 424, height: int = 240) -> "Intrinsics":
        """Nominal D435 depth intrinsics at one of its modes (optical axis at the image centre)."""
        f = D435_FOCAL_PER_WIDTH * width
        return cls(width=width, height=height, ppx=(width - 1) / 2.0, ppy=(height - 1) / 2.0,
                   fx=f, fy=f, model="brown_conrady", depth_scale=D435_DEPTH_SCALE_M)

    def window(self, v0: int, v1: int, u0: int, u1: int) -> "Intrinsics":
        """The intrinsics of pixels [v0, v1) x [u0, u1) as an image of their own (a crop): the
        principal point moved to its corner, where it may lie outside it. Not checked as a camera's
        are (a crop's principal point is off its image by design); a window of valid intrinsics is valid."""
        if not (0 <= v0 < v1 <= self.height and 0 <= u0 < u1 <= self.width):
            raise ValueError(f"window rows {v0}:{v1}, columns {u0}:{u1} is not within the {self.width}x{self.height} image")
        crop = object.__new__(Intrinsics)
        for name, value in {**self.__dict__, "width": int(u1 - u0), "height": int(v1 - v0),
                            "ppx": float(self.ppx) - u0, "ppy": float(self.ppy) - v0}.items():
            object.__setattr__(crop, name, value)
        return crop

    @property
    def shape(self) -> tuple[int, int]:
        """(height, width) of the image, numpy order."""
        return int(self.height), int(self.width)

    @property
    def has_distortion(self) -> bool:
        return self.model != "none" and any(c != 0.0 for c in self.coeffs)

    def to_dict(self) -> dict:
        return {"width": int(self.width), "height": int(self.height), "ppx": float(self.ppx),
                "ppy": float(self.ppy), "fx": float(self.fx), "fy": float(self.fy),
                "model": self.model, "coeffs": list(self.coeffs), "depth_scale": float(self.depth_scale)}

    @classmethod
    def from_dict(cls, d: dict) -> "Intrinsics":
        """From a dict of rs.intrinsics' fields (intrinsics.json), or from an ``rs.intrinsics`` itself
        (``from_rs``, with the D435's depth unit)."""
        if not isinstance(d, dict) and all(hasattr(d, k) for k in ("width", "height", "ppx", "ppy", "fx", "fy")):
            return cls.from_rs(d)
        missing = [k for k in ("width", "height", "ppx", "ppy", "fx", "fy") if k not in d]
        if missing:
            raise SphereBenchError(f"intrinsics lack {', '.join(missing)}: give width, height, ppx, ppy, fx, fy "
                                   "(and optionally model, coeffs, depth_scale)")
        try:
            return cls(width=_pixels(d["width"]), height=_pixels(d["height"]), ppx=float(d["ppx"]), ppy=float(d["ppy"]),
                       fx=float(d["fx"]), fy=float(d["fy"]), model=d.get("model", "none") or "none",
                       coeffs=tuple(d.get("coeffs") or (0.0,) * 5),
                       depth_scale=float(d.get("depth_scale", D435_DEPTH_SCALE_M)))
        except (TypeError, ValueError) as exc:
            raise SphereBenchError(f"intrinsics have a value of the wrong type ({exc})") from None

    @classmethod
    def from_rs(cls, rs_intr, depth_scale: float = D435_DEPTH_SCALE_M) -> "Intrinsics":
        """From pyrealsense2's ``rs.intrinsics`` (a stream profile's ``get_intrinsics()``) and the
        depth sensor's ``get_depth_scale()`` (metres per count). librealsense keeps these in float32:
        each is taken as the shortest decimal of the same float32 (0.0001, not 9.99999974e-05), so that
        intrinsics.json reads as the device reported it."""
        f32 = float32_decimal
        return cls(width=int(rs_intr.width), height=int(rs_intr.height), ppx=f32(rs_intr.ppx), ppy=f32(rs_intr.ppy),
                   fx=f32(rs_intr.fx), fy=f32(rs_intr.fy), model=str(rs_intr.model),
                   coeffs=tuple(f32(c) for c in rs_intr.coeffs), depth_scale=f32(depth_scale))

    def to_rs(self):
        """As pyrealsense2's ``rs.intrinsics`` (the inverse of ``from_rs``; the depth unit is not one
        of its fields), e.g. for a software device's stream."""
        rs = require("pyrealsense2", "realsense", "an rs.intrinsics")
        ri = rs.intrinsics()
        ri.width, ri.height = self.width, self.height
        ri.ppx, ri.ppy, ri.fx, ri.fy = self.ppx, self.ppy, self.fx, self.fy
        ri.model, ri.coeffs = getattr(rs.distortion, self.model), list(self.coeffs)
        return ri

    def scaled(self, width: int, height: int) -> "Intrinsics":
        """The same camera at another resolution (pixel-centre convention kept)."""
        sx, sy = width / self.width, height / self.height
        return Intrinsics(width=width, height=height, ppx=(self.ppx + 0.5) * sx - 0.5,
                          ppy=(self.ppy + 0.5) * sy - 0.5, fx=self.fx * sx, fy=self.fy * sy,
                          model=self.model, coeffs=self.coeffs, depth_scale=self.depth_scale)


def _pixels(value) -> int | float:
    """An image side from JSON: an int, a float kept as it is (424.7 is then refused, not cut to 424)."""
    if isinstance(value, bool) or not isinstance(value, (int, float, str)):
        raise TypeError(f"an image side must be a number, not {value!r}")
    value = float(value)
    return int(value) if value.is_integer() else value


def float32_decimal(value: float) -> float:
    """A float32 (librealsense's calibration values) as the shortest decimal that is the same float32."""
    return float(str(np.float32(value)))


def _implausible(intr: Intrinsics) -> list[str]:
    """What makes finite, positive intrinsics impossible for a depth camera: the principal point
    off the image (the image spans [-0.5, size - 0.5] px), a focal length beyond
    FOCAL_PER_SIZE_RANGE, pixels far from square."""
    w, h = int(intr.width), int(intr.height)
    out = []
    if not (-0.5 <= float(intr.ppx) <= w - 0.5 and -0.5 <= float(intr.ppy) <= h - 0.5):
        out.append(f"the principal point (ppx, ppy) = ({float(intr.ppx):g}, {float(intr.ppy):g}) px lies outside the "
                   f"{w}x{h} image: these intrinsics belong to another stream or resolution")
    lo, hi = (k * max(w, h) for k in FOCAL_PER_SIZE_RANGE)
    if not all(lo <= float(f) <= hi for f in (intr.fx, intr.fy)):
        out.append(f"focal lengths fx={float(intr.fx):g}, fy={float(intr.fy):g} px are not a camera's for a {w}x{h} "
                   f"image (expected {lo:.3g} to {hi:.3g} px, e.g. 0.5 x the width for a D435)")
    elif max(intr.fx / intr.fy, intr.fy / intr.fx) > MAX_FOCAL_RATIO:
        out.append(f"fx={float(intr.fx):g} and fy={float(intr.fy):g} px differ more than {MAX_FOCAL_RATIO:g}-fold "
                   "(pixels are about square): check both values")
    return out


def _distort(intr: Intrinsics, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Normalised undistorted -> distorted coordinates, as rs2_project_point_to_pixel."""
    if not intr.has_distortion:
        return x, y
    k1, k2, p1, p2, k3 = intr.coeffs
    r2 = x * x + y * y
    f = 1.0 + k1 * r2 + k2 * r2 * r2 + k3 * r2 * r2 * r2
    if intr.model == "brown_conrady":
        xd = x * f + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        yd = y * f + 2 * p2 * x * y + p1 * (r2 + 2 * y * y)
        return xd, yd
    # modified / inverse Brown-Conrady: tangential terms use the radially scaled coordinates
    xf, yf = x * f, y * f
    return xf + 2 * p1 * xf * yf + p2 * (r2 + 2 * xf * xf), yf + 2 * p2 * xf * yf + p1 * (r2 + 2 * yf * yf)


def _undistort(intr: Intrinsics, xd: np.ndarray, yd: np.ndarray, iterations: int = 20) -> tuple[np.ndarray, np.ndarray]:
    """Invert _distort by fixed-point iteration (librealsense iterates likewise)."""
    if not intr.has_distortion:
        return xd, yd
    x, y = xd.copy(), yd.copy()
    for _ in range(iterations):
        dx, dy = _distort(intr, x, y)
        x = x + (xd - dx)
        y = y + (yd - dy)
    return x, y


def project(intr: Intrinsics, points_m: np.ndarray) -> np.ndarray:
    """Camera-frame points (N, 3) metres -> pixel coordinates (N, 2) as (u, v) = (column, row).

    Points with z <= 0 project to NaN.
    """
    p = np.asarray(points_m, dtype=np.float64).reshape(-1, 3)
    with np.errstate(divide="ignore", invalid="ignore"):
        z = np.where(p[:, 2] > 0, p[:, 2], np.nan)
        x, y = _distort(intr, p[:, 0] / z, p[:, 1] / z)
    return np.stack([x * intr.fx + intr.ppx, y * intr.fy + intr.ppy], axis=1)


def pixel_rays(intr: Intrinsics, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Pixel coordinates -> rays (N, 3) with z = 1 (undistorted normalised coordinates, 1)."""
    x, y = _undistort(intr, (np.asarray(u, np.float64) - intr.ppx) / intr.fx,
                      (np.asarray(v, np.float64) - intr.ppy) / intr.fy)
    return np.stack([x, y, np.ones_like(x)], axis=-1)


def deproject(intr: Intrinsics, u: np.ndarray, v: np.ndarray, z_m: np.ndarray) -> np.ndarray:
    """Pixels (u = column, v = row) with depth z (metres, along the optical axis) -> points (N, 3) m."""
    return pixel_rays(intr, u, v) * np.asarray(z_m, np.float64)[..., None]


def image_rays(intr: Intrinsics) -> np.ndarray:
    """Rays (H, W, 3) with z = 1 through every pixel centre, for ray casting and deprojection."""
    if not intr.has_distortion:  # a row of x and a column of y, broadcast: no grid of pixel coordinates
        rays = np.empty((intr.height, intr.width, 3), np.float64)
        rays[..., 0] = ((np.arange(intr.width, dtype=np.float64) - intr.ppx) / intr.fx)[None, :]
        rays[..., 1] = ((np.arange(intr.height, dtype=np.float64) - intr.ppy) / intr.fy)[:, None]
        rays[..., 2] = 1.0
        return rays
    v, u = np.mgrid[0:intr.height, 0:intr.width]
    return pixel_rays(intr, u.astype(np.float64), v.astype(np.float64))


#: A depth pixel is hidden from the other camera (``align_to_depth``) when the depth surface, nearer
#: to that camera by more than the larger of these, covers the pixel it lands on there.
OCCLUSION_MARGIN_M = 0.01
OCCLUSION_MARGIN_FRACTION = 0.03
#: A depth pixel is at a depth edge when a neighbour has no depth or is farther by this fraction.
EDGE_JUMP_FRACTION = 0.1
#: A triangle of the depth surface covers at most this many pixels a side of the other image (a
#: larger one, across a wide depth edge, is clipped).
MAX_FOOTPRINT_PX = 16


def _transform(rotation: np.ndarray, translation: np.ndarray, x, y, z) -> tuple[np.ndarray, ...]:
    """rotation @ (x, y, z) + translation, one coordinate at a time (element-wise arithmetic, so
    the result is the same bit for bit on every machine, unlike a BLAS product)."""
    return tuple(rotation[i, 0] * x + rotation[i, 1] * y + rotation[i, 2] * z + translation[i] for i in range(3))


def _draw_boxes(nearest: np.ndarray, w: int, h: int, us: np.ndarray, vs: np.ndarray, z: np.ndarray) -> None:
    """Lower ``nearest`` (h * w, the other image's z-buffer) to z over each box: the pixels nearest
    to the corners' span (us, vs: (corners, n) px), clipped to MAX_FOOTPRINT_PX a side."""
    with np.errstate(invalid="ignore"):
        x0, x1 = np.floor(us.min(axis=0) + 0.5), np.floor(us.max(axis=0) + 0.5)
        y0, y1 = np.floor(vs.min(axis=0) + 0.5), np.floor(vs.max(axis=0) + 0.5)
        keep = np.flatnonzero(np.isfinite(z) & np.isfinite(x0) & np.isfinite(x1) & np.isfinite(y0) & np.isfinite(y1)
                              & (x1 >= 0) & (x0 < w) & (y1 >= 0) & (y0 < h))
    x0, y0 = np.maximum(x0[keep], 0), np.maximum(y0[keep], 0)
    span_x = (np.minimum(x1[keep], w - 1) - x0).clip(0, MAX_FOOTPRINT_PX - 1).astype(np.int64)
    span_y = (np.minimum(y1[keep], h - 1) - y0).clip(0, MAX_FOOTPRINT_PX - 1).astype(np.int64)
    x0, y0, z = x0.astype(np.int64), y0.astype(np.int64), z[keep]
    for dy in range(int(span_y.max(initial=-1)) + 1):
        tall = np.flatnonzero(span_y >= dy)
        for dx in range(int(span_x[tall].max(initial=-1)) + 1):
            sel = tall[span_x[tall] >= dx]
            np.minimum.at(nearest, (y0[sel] + dy) * w + x0[sel] + dx, z[sel])


def _draw_triangles(nearest: np.ndarray, w: int, h: int, tu: np.ndarray, tv: np.ndarray, tz: np.ndarray) -> None:
    """Lower ``nearest`` (h * w, the other image's z-buffer) over each triangle (tu, tv: (3, n) px
    of its corners, tz (3, n) their depths; NaN: no triangle) to its depth at each pixel centre it
    covers, interpolated linearly; clipped to MAX_FOOTPRINT_PX a side."""
    with np.errstate(invalid="ignore"):
        x0, x1 = np.ceil(tu.min(axis=0)), np.floor(tu.max(axis=0))  # the pixel centres it may cover
        y0, y1 = np.ceil(tv.min(axis=0)), np.floor(tv.max(axis=0))
        area = (tv[1] - tv[2]) * (tu[0] - tu[2]) + (tu[2] - tu[1]) * (tv[0] - tv[2])
        keep = np.flatnonzero(np.isfinite(tz).all(axis=0) & np.isfinite(area) & (area != 0)
                              & (x1 >= x0) & (y1 >= y0) & (x1 >= 0) & (x0 < w) & (y1 >= 0) & (y0 < h))
    tu, tv, tz, area = tu[:, keep], tv[:, keep], tz[:, keep], area[keep]
    x0, y0 = np.maximum(x0[keep], 0), np.maximum(y0[keep], 0)
    span_x = (np.minimum(x1[keep], w - 1) - x0).clip(0, MAX_FOOTPRINT_PX - 1).astype(np.int64)
    span_y = (np.minimum(y1[keep], h - 1) - y0).clip(0, MAX_FOOTPRINT_PX - 1).astype(np.int64)
    for dy in range(int(span_y.max(initial=-1)) + 1):
        tall = np.flatnonzero(span_y >= dy)
        for dx in range(int(span_x[tall].max(initial=-1)) + 1):
            sel = tall[span_x[tall] >= dx]
            px, py = x0[sel] + dx, y0[sel] + dy
            u, v, z, d = tu[:, sel], tv[:, sel], tz[:, sel], area[sel]
            l0 = ((v[1] - v[2]) * (px - u[2]) + (u[2] - u[1]) * (py - v[2])) / d  # barycentric coordinates
            l1 = ((v[2] - v[0]) * (px - u[2]) + (u[0] - u[2]) * (py - v[2])) / d
            l2 = 1.0 - l0 - l1
            hit = (l0 >= -1e-9) & (l1 >= -1e-9) & (l2 >= -1e-9)
            np.minimum.at(nearest, (py[hit] * w + px[hit]).astype(np.int64), (l0 * z[0] + l1 * z[1] + l2 * z[2])[hit])


def align_to_depth(depth_m: np.ndarray, depth_intr: Intrinsics, image: np.ndarray, image_intr: Intrinsics,
                   rotation, translation) -> tuple[np.ndarray, dict]:
    """Another camera's image (a colour frame) resampled onto the depth image's pixel grid.

    For every depth pixel with depth: deproject its centre with ``depth_intr`` and its depth
    (``deproject``), move the point into the other camera's frame (rotation (3, 3) @ p +
    translation (3,), metres: librealsense's depth-to-other extrinsics), project it with
    ``image_intr`` (``project``, the distortion model as rs2_project_point_to_pixel applies it)
    and take the nearest pixel there. A depth pixel stays black (0) where it has no depth, where
    it lands off the image or behind the camera, and where the other camera does not see it
    (occluded): the depth surface covers the pixel it lands on at a depth nearer to that camera
    by more than OCCLUSION_MARGIN_M or OCCLUSION_MARGIN_FRACTION, the larger. The surface drawn
    in the other image is each depth pixel's square at its own depth (the box of its corners
    there; at a depth edge, EDGE_JUMP_FRACTION, where the silhouette may lie anywhere up to the
    farther neighbour, reaching to its neighbours' centres) and the triangles between
    neighbouring pixel centres, the depth interpolated across each (a triangle across a depth
    edge hides what lies behind it). Without that test the cameras' baseline paints the
    background beside a near object in the object's colour.

    depth_m: (H, W) metres (0, NaN: no depth), H, W = depth_intr's. image: (h, w) or (h, w, C),
    h, w = image_intr's. Returns (the aligned image (H, W[, C]) of image's dtype, counts of depth
    pixels: with depth, coloured, off the image, occluded).
    """
    z = np.asarray(depth_m, dtype=np.float64)
    if z.shape != depth_intr.shape:
        raise SphereBenchError(f"the depth is {z.shape[1]}x{z.shape[0]} but its intrinsics are "
                               f"{depth_intr.width}x{depth_intr.height}")
    if image.shape[:2] != image_intr.shape:
        raise SphereBenchError(f"the image is {image.shape[1]}x{image.shape[0]} but its intrinsics are "
                               f"{image_intr.width}x{image_intr.height}")
    rot = np.asarray(rotation, dtype=np.float64).reshape(3, 3)
    trans = np.asarray(translation, dtype=np.float64).reshape(3)
    height, width = depth_intr.shape
    h, w = image_intr.shape
    with np.errstate(invalid="ignore"):
        valid = np.isfinite(z) & (z > 0)
    flat = np.flatnonzero(valid)
    rows, cols = np.divmod(flat, width)
    zs = z.ravel()[flat]
    ray = pixel_rays(depth_intr, cols.astype(np.float64), rows.astype(np.float64))
    x, y, z_other = _transform(rot, trans, ray[:, 0] * zs, ray[:, 1] * zs, zs)
    uv = project(image_intr, np.stack([x, y, z_other], axis=1))  # NaN behind the camera
    with np.errstate(invalid="ignore"):
        cu, cv = np.floor(uv[:, 0] + 0.5), np.floor(uv[:, 1] + 0.5)  # nearest pixel; pixel centres are integers
        inside = np.isfinite(cu) & np.isfinite(cv) & (cu >= 0) & (cu < w) & (cv >= 0) & (cv < h)
    sample = np.where(inside, cv * w + cu, 0).astype(np.int64)

    # the depth surface in the other image: each pixel's square (its corners at its own depth; to
    # its neighbours' centres at a depth edge, where the silhouette may lie anywhere up to them)
    # and the triangles between neighbouring pixel centres (two to each quad of a pixel and its
    # right, lower and lower-right neighbours), the depth interpolated across each
    nearest = np.full(h * w, np.inf)
    np.minimum.at(nearest, sample[inside], z_other[inside])
    z_front = np.where(z_other > 0, z_other, np.nan)
    padded = np.full((height + 2, width + 2), np.inf)
    padded[rows + 1, cols + 1] = np.where(z_other > 0, z_other, np.inf)
    farthest = np.max([padded[rows + 1 + dr, cols + 1 + dc] for dr in (-1, 0, 1) for dc in (-1, 0, 1)], axis=0)
    with np.errstate(invalid="ignore"):
        half = np.where(farthest > z_other * (1.0 + EDGE_JUMP_FRACTION), 1.0, 0.5)
    squares = []
    for du, dv in ((-1, -1), (1, -1), (-1, 1), (1, 1)):
        corner = pixel_rays(depth_intr, cols + du * half, rows + dv * half)
        cx, cy, cz = _transform(rot, trans, corner[:, 0] * zs, corner[:, 1] * zs, zs)
        squares.append(project(image_intr, np.stack([cx, cy, cz], axis=1)))
    _draw_boxes(nearest, w, h, np.stack([c[:, 0] for c in squares]), np.stack([c[:, 1] for c in squares]), z_front)
    grids = []
    for values in (uv[:, 0], uv[:, 1], z_front):
        grid = np.full((height + 1, width + 1), np.nan)
        grid[rows, cols] = values
        grids.append(grid)
    for corners in (((0, 0), (0, 1), (1, 1)), ((0, 0), (1, 0), (1, 1))):
        _draw_triangles(nearest, w, h, *(np.stack([g[rows + dr, cols + dc] for dr, dc in corners]) for g in grids))
    front = nearest[sample]
    with np.errstate(invalid="ignore"):
        occluded = inside & (z_other > front + np.maximum(OCCLUSION_MARGIN_M, OCCLUSION_MARGIN_FRACTION * front))
    shown = inside & ~occluded
    out = np.zeros((height, width) + image.shape[2:], dtype=image.dtype)
    pixels = image.reshape((h * w,) + image.shape[2:])
    out.reshape((height * width,) + image.shape[2:])[flat[shown]] = pixels[sample[shown]]
    counts = {"with_depth": int(flat.size), "coloured": int(np.count_nonzero(shown)),
              "off_image": int(np.count_nonzero(~inside)), "occluded": int(np.count_nonzero(occluded))}
    return out, counts
