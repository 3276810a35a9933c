"""Detections to the Rerun viewer (rerun-sdk, the ``viz`` extra): per frame, the depth image, the
point cloud with each sphere's inliers in red, the spheres themselves and their circles on the
image, on a "frame" timeline (and the camera's clock, "camera_time"), so that a stream can be
watched live or its .rrd replayed later.

A viewer that cannot start is a note, not an error: the detection goes on without it.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from spherebench.cloud import cloud_from_depth, depth_to_metres
from spherebench.errors import require

#: Colours (RGB): the inliers of a sphere, the other points, the spheres and circles.
INLIER_RGB = (255, 0, 0)
OTHER_RGB = (150, 150, 150)
SPHERE_RGB = (255, 0, 255)


def import_rerun():
    """rerun, or a one-line SphereBenchError naming the extra that installs it."""
    return require("rerun", "viz", "--rerun and --rerun-save")


class RerunLog:
    """One Rerun recording: to a viewer it spawns (``spawn``) or to a file (``save``, an .rrd).
    ``frame`` logs one stream frame, ``cloud`` one cloud of a file input."""

    def __init__(self, app_id: str, save: str | Path | None = None, spawn: bool = False):
        rr = self.rr = import_rerun()
        self.enabled = True
        self._count = 0
        self._intrinsics = None
        rr.init(app_id.replace(" ", "_"))
        viewer = False
        if spawn:
            try:
                rr.spawn(connect=False)
                viewer = True
            except Exception as exc:  # no viewer binary, no display: the stream goes on without it
                print(f"note: the Rerun viewer cannot start ({str(exc).splitlines()[0] if str(exc) else exc}); "
                      "detecting without it (use --rerun-save FILE.rrd)", file=sys.stderr)
        sinks = ([rr.GrpcSink()] if viewer else []) + ([rr.FileSink(str(save))] if save else [])
        self.enabled = bool(sinks)
        if sinks:
            rr.set_sinks(*sinks)

    def _camera(self, intr) -> None:
        if intr == self._intrinsics:
            return
        self._intrinsics = intr
        rr = self.rr
        rr.log("camera", rr.Pinhole(focal_length=[intr.fx, intr.fy], principal_point=[intr.ppx + 0.5, intr.ppy + 0.5],
                                    resolution=[intr.width, intr.height]), static=True)

    def _spheres(self, cloud, spheres) -> None:
        rr = self.rr
        colours = np.tile(np.array(OTHER_RGB, np.uint8), (len(cloud.points), 1))
        for s in spheres:
            colours[s.inlier_indices] = INLIER_RGB
        rr.log("world/cloud", rr.Points3D(cloud.points, colors=colours, radii=0.002))
        centres = [s.centre_m for s in spheres]
        rr.log("world/spheres", rr.Ellipsoids3D(centers=centres, half_sizes=[[s.radius_m] * 3 for s in spheres],
                                                colors=[SPHERE_RGB] * len(spheres),
                                                labels=[f"{s.score:.2f}" for s in spheres]))
        circles = [s.circle_exact for s in spheres if s.circle_exact is not None]
        labels = [f"{s.score:.2f}" for s in spheres if s.circle_exact is not None]
        # pixel centres are integers here; Rerun's image space puts pixel i at [i, i + 1)
        rr.log("camera/circles", rr.Points2D([[c[0] + 0.5, c[1] + 0.5] for c in circles],
                                             radii=[c[2] for c in circles], colors=[SPHERE_RGB] * len(circles),
                                             labels=labels))

    def frame(self, source: str, frame, spheres) -> None:
        """One frame of a stream (a ``recordings.BagFrame``) and its spheres."""
        if not self.enabled:
            return
        rr = self.rr
        rr.set_time("frame", sequence=int(frame.number))
        rr.set_time("camera_time", duration=float(frame.timestamp_ms) / 1000.0)  # seconds
        intr = frame.intrinsics
        self._camera(intr)
        rr.log("camera/depth", rr.DepthImage(frame.depth, meter=1.0 / intr.depth_scale))
        self._spheres(cloud_from_depth(depth_to_metres(frame.depth, intr), intr), spheres)

    def cloud(self, source: str, cloud, spheres) -> None:
        """One cloud of a file input (a frame of its own on the timeline)."""
        if not self.enabled:
            return
        rr = self.rr
        rr.set_time("frame", sequence=self._count)
        self._count += 1
        if cloud.intrinsics is not None:
            self._camera(cloud.intrinsics)
        self._spheres(cloud, spheres)

    def close(self) -> None:
        try:
            self.rr.disconnect()
        except Exception:  # flushing a viewer that went away is no error of the detection
            pass
