"""One scene of a dataset in memory: the depth frame, the camera, and the ground truth.

Simulated and recorded scenes are the same thing here; what a recording lacks (the full
silhouette, the 3D centre) is None. ``spherebench.datasets.inout`` writes and reads the folder form.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from spherebench.camera import Intrinsics
from spherebench.circles import mask_circle
from spherebench.cloud import Cloud, cloud_from_depth, depth_to_metres

@dataclass
class Ball:
    """Ground truth of one ball of the dataset's radius.

    mask: (H, W) bool, pixels where the ball is the first surface hit and depth is valid.
    silhouette: (H, W) bool, the ball's full silhouette ignoring occlusion (simulated only).
    centre_m: (3,) metres, camera frame, or None (recordings annotated in 2D only).
    circle_px: (cx, cy, r) smallest enclosing circle of ``mask`` (CircleNet's rule), or of an
        annotated circle/polygon for recordings.
    amodal_circle_px: (cx, cy, r) of the whole silhouette, unclipped by occluders and the frame.
    centre_source: how a recording's centre_m was obtained ("mask-fit": a fixed-radius fit to the
        mask's depth pixels, ``annotate.mask_fit_centre``), with centre_se_m its standard error (3,) m;
        None for simulated balls, whose centre is exact.
    """

    radius_m: float
    mask: np.ndarray | None = None
    silhouette: np.ndarray | None = None
    centre_m: tuple[float, float, float] | None = None
    circle_px: tuple[float, float, float] | None = None
    amodal_circle_px: tuple[float, float, float] | None = None
    visible_fraction: float | None = None
    centre_source: str | None = None
    centre_se_m: tuple[float, float, float] | None = None

    def __post_init__(self) -> None:
        if self.circle_px is None and self.mask is not None:
            self.circle_px = mask_circle(self.mask)
        if self.visible_fraction is None and self.mask is not None and self.silhouette is not None:
            full = int(self.silhouette.sum())
            self.visible_fraction = float(self.mask.sum()) / full if full else 0.0


@dataclass
class Scene:
    """A scene: an organised depth frame (or, for LiDAR-like data, only a cloud) and its truth.

    depth: (H, W) uint16 in counts of ``intrinsics.depth_scale``; 0 = no measurement. None for
        unorganised recordings, which then carry ``cloud``.
    balls: the balls of the dataset's radius (the objects to detect). Empty for a negative scene.
    annotated: False for a recording nobody has annotated: kept, but left out of scoring.
    meta: everything else worth keeping (distractors, source file, frame timestamp, ...).
    """

    scene_id: str
    family: str
    intrinsics: Intrinsics | None
    depth: np.ndarray | None = None
    balls: list[Ball] = field(default_factory=list)
    seed: int | None = None
    annotated: bool = True
    cloud: Cloud | None = None
    meta: dict = field(default_factory=dict)

    def depth_m(self) -> np.ndarray:
        """(H, W) float32 metres, NaN where invalid."""
        return depth_to_metres(self.depth, self.intrinsics)

    def to_cloud(self) -> Cloud:
        """The scene's point cloud (organised when it has a depth frame)."""
        if self.cloud is not None:
            return self.cloud
        return cloud_from_depth(self.depth_m(), self.intrinsics)
