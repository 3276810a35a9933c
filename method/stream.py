"""The 3D detector over a stream of depth frames (a recording played back or a live camera,
``spherebench.datasets.depth_frames``), one frame at a time, and the latency it had.

    from spherebench.datasets.depth_frames import recording_frames
    from spherebench.method import config_for
    from spherebench.method.stream import detect_stream

    for frame, spheres, ms in detect_stream(recording_frames("capture.bag"), config_for("improved")):
        print(frame.number, frame.timestamp_ms, [s.centre_m for s in spheres], ms)

Each frame is deprojected, detected and let go: memory stays bounded over an hour-long recording.
"""

from __future__ import annotations

import math
import time
from collections.abc import Iterable, Iterator
from typing import NamedTuple, Protocol

import numpy as np

from spherebench.camera import Intrinsics, image_rays
from spherebench.cloud import cloud_from_depth, depth_to_metres
from spherebench.method import detect


class DepthFrame(Protocol):
    """What the loop reads of a frame (``recordings.BagFrame`` is one): its index in the stream, the
    camera's frame number, depth in counts of ``intrinsics.depth_scale``."""

    index: int
    number: int
    depth: np.ndarray
    intrinsics: Intrinsics


class StreamDetection(NamedTuple):
    """One frame's result: the frame, its spheres (best first) and the detection's time (ms, the
    deprojection to a cloud included, reading the frame excluded)."""

    frame: DepthFrame
    spheres: list
    ms: float


class _Rays:
    """image_rays of the stream's intrinsics, computed once (a stream keeps its camera)."""

    def __init__(self):
        self.intrinsics: Intrinsics | None = None
        self.rays: np.ndarray | None = None

    def __call__(self, intr: Intrinsics) -> np.ndarray:
        if intr != self.intrinsics:
            self.intrinsics, self.rays = intr, image_rays(intr)
        return self.rays


def detect_stream(frames: Iterable[DepthFrame], config, seed: int = 0, stats=None) -> Iterator[StreamDetection]:
    """The detector over a stream of depth frames: (frame, spheres, ms) per frame, lazily. Frame
    k's seed is (seed, k), k its index in the stream: the same recording gives the same output. A
    frame with no depth at all gives no sphere. stats: the stream's ``depth_frames.StreamStats``
    (frames detected, notes), or None."""
    rays = _Rays()
    for frame in frames:
        t = time.perf_counter()
        cloud = cloud_from_depth(depth_to_metres(frame.depth, frame.intrinsics), frame.intrinsics,
                                 rays(frame.intrinsics))
        spheres = detect(cloud, config, seed=(int(seed), int(frame.index))) if len(cloud) else []
        ms = (time.perf_counter() - t) * 1e3
        if stats is not None:
            stats.frames += 1
            if not len(cloud):
                stats.notes.append(f"frame {frame.number} has no depth (every pixel 0): no sphere")
        yield StreamDetection(frame, spheres, ms)


def latency_summary(ms: np.ndarray) -> dict:
    """Median and 95th percentile (ms) of per-frame times, and their count."""
    ms = np.asarray(ms, dtype=np.float64)
    if ms.size == 0:
        return {"frames": 0, "median_ms": math.nan, "p95_ms": math.nan}
    return {"frames": int(ms.size), "median_ms": float(np.median(ms)), "p95_ms": float(np.percentile(ms, 95))}
