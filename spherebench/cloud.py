"""The point cloud that flows from a recording to a detector: points, and where they came from.

A cloud from a depth image is *organised*: every point keeps its pixel (row, col), which lets the
detector sample neighbours in the image and lets results be drawn back onto the image. A cloud
read from an unorganised file (LiDAR .xyz, say) has no pixels.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from spherebench.camera import Intrinsics, image_rays
from spherebench.errors import SphereBenchError


@dataclass
class Cloud:
    """points: (N, 3) float32, metres, camera frame (x right, y down, z forward).
    rows, cols: (N,) int32 pixel of each point, or None for an unorganised cloud.
    intrinsics: the camera that took it, or None when unknown.
    """

    points: np.ndarray
    rows: np.ndarray | None = None
    cols: np.ndarray | None = None
    intrinsics: Intrinsics | None = None

    def __post_init__(self) -> None:
        self.points = np.ascontiguousarray(self.points, dtype=np.float32).reshape(-1, 3)
        if (self.rows is None) != (self.cols is None):
            raise SphereBenchError("a cloud needs both pixel rows and cols, or neither")
        if self.rows is not None:
            self.rows = np.ascontiguousarray(self.rows, dtype=np.int32).reshape(-1)
            self.cols = np.ascontiguousarray(self.cols, dtype=np.int32).reshape(-1)
            if len(self.rows) != len(self.points) or len(self.cols) != len(self.points):
                raise SphereBenchError(f"a cloud of {len(self.points)} points has {len(self.rows)} pixel rows "
                                       f"and {len(self.cols)} cols: they must match")

    def __len__(self) -> int:
        return len(self.points)

    @property
    def organised(self) -> bool:
        return self.rows is not None and self.intrinsics is not None

    def subset(self, keep: np.ndarray) -> "Cloud":
        """The cloud restricted to a boolean mask or index array over its points."""
        return Cloud(self.points[keep], None if self.rows is None else self.rows[keep],
                     None if self.cols is None else self.cols[keep], self.intrinsics)


#: An organised cloud with more than this share of its finite points at z <= 0 is refused rather than
#: trimmed: most of it behind a depth camera means another frame's axes or a flipped sign.
MAX_BEHIND_FRACTION = 0.5


def in_front_of_camera(cloud: Cloud, name: str = "the cloud") -> tuple[Cloud, int]:
    """An organised cloud (pixel rows and cols: a depth camera's) without its points at z <= 0, which
    no depth camera sees, and how many were dropped. An unorganised cloud is returned as it is (a
    LiDAR's 360 deg scan has points on every side). Raises SphereBenchError when most finite points
    lie behind the camera."""
    if cloud.rows is None:
        return cloud, 0
    z = cloud.points[:, 2]
    finite = np.isfinite(cloud.points).all(axis=1)
    behind = finite & (z <= 0)
    n_behind, n_finite = int(np.count_nonzero(behind)), int(np.count_nonzero(finite))
    if n_behind == 0:
        return cloud, 0
    if n_behind > MAX_BEHIND_FRACTION * n_finite:
        raise SphereBenchError(f"{name}: {n_behind} of its {n_finite} points lie at z <= 0, behind the camera; a cloud "
                               "with pixel rows and cols is a depth camera's, which sees only z > 0: give it in the "
                               "camera frame (x right, y down, z forward, metres)")
    return cloud.subset(~behind), n_behind


def depth_to_metres(depth: np.ndarray, intr: Intrinsics) -> np.ndarray:
    """Depth image in counts (uint16, 0 = invalid) -> float32 metres, NaN where invalid."""
    d = np.asarray(depth)
    z = d.astype(np.float32) * np.float32(intr.depth_scale)
    z[(d == 0) | ~np.isfinite(z)] = np.nan
    return z


def cloud_from_depth(depth_m: np.ndarray, intr: Intrinsics, rays: np.ndarray | None = None) -> Cloud:
    """Deproject a depth image (H, W) in metres (NaN or <= 0 = invalid) into an organised cloud.

    rays: optional precomputed ``image_rays(intr)`` (H, W, 3), to save work on streams.
    """
    z = np.asarray(depth_m, dtype=np.float32)
    if z.shape != intr.shape:
        raise SphereBenchError(f"depth image is {z.shape[1]}x{z.shape[0]} but the intrinsics are "
                               f"{intr.width}x{intr.height}: give the intrinsics of this stream")
    valid = np.isfinite(z) & (z > 0)
    rows, cols = np.nonzero(valid)
    if rays is None:
        rays = image_rays(intr)
    zv = z[valid].astype(np.float64)
    pts = np.empty((len(zv), 3), np.float32)
    for j in range(3):  # per component, in float64: a (N, 3) gather of the rays took twice as long
        np.multiply(rays[..., j][valid], zv, out=pts[:, j], casting="same_kind")
    return Cloud(pts, rows.astype(np.int32), cols.astype(np.int32), intr)
