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

from spherebench.errors import SphereBenchError

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
        if int(self.width) <= 0 or int(self.height) <= 0:
            problems.append(f"image size {self.width}x{self.height} must be positive")
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
        if len(self.coeffs) != 5 or not all(math.isfinite(c) for c in self.coeffs):
            problems.append("coeffs must be five finite numbers (k1, k2, p1, p2, k3)")
        if problems:
            raise SphereBenchError("invalid intrinsics: " + "; ".join(problems))

    @classmethod
    def d435(cls, width: int = 424, height: int = 240) -> "Intrinsics":
        """Nominal D435 depth intrinsics at one of its modes (optical axis at the image centre)."""
        f = D435_FOCAL_PER_WIDTH * width
        return cls(width=width, height=height, ppx=(width - 1) / 2.0, ppy=(height - 1) / 2.0,
                   fx=f, fy=f, model="brown_conrady", depth_scale=D435_DEPTH_SCALE_M)

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
        missing = [k for k in ("width", "height", "ppx", "ppy", "fx", "fy") if k not in d]
        if missing:
            raise SphereBenchError(f"intrinsics lack {', '.join(missing)}: give width, height, ppx, ppy, fx, fy "
                                   "(and optionally model, coeffs, depth_scale)")
        try:
            return cls(width=int(d["width"]), height=int(d["height"]), ppx=float(d["ppx"]), ppy=float(d["ppy"]),
                       fx=float(d["fx"]), fy=float(d["fy"]), model=d.get("model", "none") or "none",
                       coeffs=tuple(d.get("coeffs") or (0.0,) * 5),
                       depth_scale=float(d.get("depth_scale", D435_DEPTH_SCALE_M)))
        except (TypeError, ValueError) as exc:
            raise SphereBenchError(f"intrinsics have a value of the wrong type ({exc})") from None

    def scaled(self, width: int, height: int) -> "Intrinsics":
        """The same camera at another resolution (pixel-centre convention kept)."""
        sx, sy = width / self.width, height / self.height
        return Intrinsics(width=width, height=height, ppx=(self.ppx + 0.5) * sx - 0.5,
                          ppy=(self.ppy + 0.5) * sy - 0.5, fx=self.fx * sx, fy=self.fy * sy,
                          model=self.model, coeffs=self.coeffs, depth_scale=self.depth_scale)


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
    v, u = np.mgrid[0:intr.height, 0:intr.width]
    return pixel_rays(intr, u.astype(np.float64), v.astype(np.float64))
