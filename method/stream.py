"""The 3D detector over a stream of depth frames (a recording played back or a live camera,
``spherebench.datasets.depth_frames``), one frame at a time, and the latency it had.

    from spherebench.datasets.depth_frames import recording_frames
    from spherebench.method import config_for
    from spherebench.method.stream import detect_stream, track_stream

    for frame, spheres, ms, _cut_short in detect_stream(recording_frames("capture.bag"), config_for("improved")):
        print(frame.number, frame.timestamp_ms, [s.centre_m for s in spheres], ms)
    for r in track_stream(recording_frames("capture.bag"), config_for("improved"), budget_ms=11.1):
        print(r.frame.number, r.search, [(t.track_id, t.centre_m) for t in r.tracks if t.confirmed])

Each frame is deprojected, detected and let go: memory stays bounded over an hour-long recording.
``track_stream`` follows the balls (``tracking``): while a track is confirmed, a frame is searched
only in a window about each live track's predicted silhouette, the prediction verified first
(``local``); the whole frame (``full``) while none is confirmed, and at least every
``FULL_SEARCH_EVERY_S`` for balls that come into view.
"""

from __future__ import annotations

import math
import time
from collections.abc import Iterable, Iterator
from typing import NamedTuple, Protocol

import numpy as np

from spherebench.camera import Intrinsics, image_rays
from spherebench.cloud import Cloud
from spherebench.errors import SphereBenchError
from spherebench.method import detect
from spherebench.method import frame_kernels as FK
from spherebench.method.deadline import Deadline
from spherebench.method.noise import mean_variance_inflation
from spherebench.method.tracking import Detection, Tracker, TrackState

# How a stream is searched while its balls are followed; each a fact of the stream or the sensor.
FULL_SEARCH_EVERY_S = 0.5  # a ball that comes into view waits at most this long to be searched for, s
WINDOW_RADII = 2.0  # a window's half-side, in the ball's image radii: verification reads a ring of background as wide as the ball
WINDOW_SIGMAS = 3.0  # and this many standard deviations of the prediction's lateral error
WINDOW_MAX_SHARE = 0.25  # windows covering more of the image than this: the whole frame is searched instead
# A detection's centre errs by this many standard errors of the mean of its inliers' depth noise, per
# axis: 1.7 through the analytic sensor model, 1.3 through the stereo one, on the motion training
# recordings (docs/experiments/2026-12-06-tracking.md)
CENTRE_ERROR_FACTOR = 1.5


class DepthFrame(Protocol):
    """What the loop reads of a frame (``recordings.BagFrame`` is one): its index in the stream, the
    camera's frame number, its time (ms), depth in counts of ``intrinsics.depth_scale``."""

    index: int
    number: int
    timestamp_ms: float
    depth: np.ndarray
    intrinsics: Intrinsics


class StreamDetection(NamedTuple):
    """One frame's result: the frame, its spheres (best first), the detection's time (ms, the
    deprojection to a cloud included, reading the frame excluded) and whether its budget cut it short."""

    frame: DepthFrame
    spheres: list
    ms: float
    cut_short: bool = False


class _Rays:
    """image_rays of the stream's intrinsics, computed once (a stream keeps its camera)."""

    def __init__(self):
        self.intrinsics: Intrinsics | None = None
        self.rays: np.ndarray | None = None

    def __call__(self, intr: Intrinsics) -> np.ndarray:
        if intr != self.intrinsics:
            self.intrinsics, self.rays = intr, image_rays(intr)
        return self.rays


Window = tuple[int, int, int, int]  # rows [v0, v1), columns [u0, u1) of an image, px


def depth_cloud(depth: np.ndarray, intr: Intrinsics, rays: np.ndarray, window: Window | None = None) -> Cloud:
    """The organised cloud of a depth frame (H, W) uint16 in counts of ``intr.depth_scale``, 0 where
    it has none, through ``rays`` (H, W, 3; ``image_rays(intr)``): the cloud ``cloud_from_depth``
    makes of it, in one compiled pass. window: only these pixels, as an image of their own (its
    intrinsics' principal point moved to the window's corner: the same rays, the same points)."""
    if depth.shape != intr.shape:
        raise SphereBenchError(f"depth frame is {depth.shape[1]}x{depth.shape[0]} but its intrinsics are "
                               f"{intr.width}x{intr.height}")
    v0, v1, u0, u1 = (0, intr.height, 0, intr.width) if window is None else window
    points, rows, cols = FK.deproject_counts(np.ascontiguousarray(depth, np.uint16), intr.depth_scale, rays,
                                             v0, v1, u0, u1)
    return Cloud(points, rows, cols, intr if window is None else intr.window(v0, v1, u0, u1))


def detect_stream(frames: Iterable[DepthFrame], config, seed: int = 0, stats=None,
                  budget_ms: float | None = None) -> Iterator[StreamDetection]:
    """The detector over a stream of depth frames: (frame, spheres, ms, cut_short) per frame, lazily.
    Frame k's seed is (seed, k), k its index in the stream: the same recording gives the same output
    (without a budget). A frame with no depth at all gives no sphere. stats: the stream's
    ``depth_frames.StreamStats`` (frames detected, notes), or None; budget_ms: each frame's latency
    bound (``deadline``), or None."""
    rays = _Rays()
    for frame in frames:
        frame_rays = rays(frame.intrinsics)  # once per stream: its set-up, not a frame's time
        t = time.perf_counter()
        deadline = None if budget_ms is None else Deadline.after_ms(budget_ms, t)
        cloud = depth_cloud(frame.depth, frame.intrinsics, frame_rays)
        spheres = detect(cloud, config, seed=(int(seed), int(frame.index)), deadline=deadline) if len(cloud) else []
        ms = (time.perf_counter() - t) * 1e3
        _count(stats, frame, len(cloud))
        yield StreamDetection(frame, spheres, ms, deadline is not None and deadline.cut_short)


def _count(stats, frame, n_points: int) -> None:
    if stats is not None:
        stats.frames += 1
        if not n_points:
            stats.notes.append(f"frame {frame.number} has no depth (every pixel 0): no sphere")


class TrackedFrame(NamedTuple):
    """One frame of ``track_stream``: the frame, its spheres (best first; ``Sphere.inlier_indices``
    into the whole frame's cloud, circles in its pixels), the live tracks after it
    (``tracking.TrackState``; ``matched`` indexes ``spheres``, ``reported`` is the tracker's answer),
    how it was searched (``"full"``, ``"local"``), whether the budget cut the detection short, and
    its time (ms: deprojection, detection and tracking)."""

    frame: DepthFrame
    spheres: list
    tracks: list[TrackState]
    search: str
    cut_short: bool
    ms: float


def track_stream(frames: Iterable[DepthFrame], config, seed: int = 0, stats=None, budget_ms: float | None = None,
                 tracker: Tracker | None = None) -> Iterator[TrackedFrame]:
    """The detector and a tracker over a stream of depth frames, in time order: a ``TrackedFrame``
    per frame, lazily. budget_ms: each frame's latency bound (``deadline``; None: none, and the
    output is the seed's alone); tracker: default ``tracking.Tracker`` for a ball of the
    configuration's radius. Frame k's seed is (seed, k), a window's (seed, k, j); stats as
    ``detect_stream``'s."""
    rays = _Rays()
    tracker = Tracker(radius_m=config.radius_m) if tracker is None else tracker
    last_full_s, lost, noise = -math.inf, True, None  # lost: no confirmed track to look about
    for frame in frames:
        frame_rays = rays(frame.intrinsics)  # once per stream: its set-up, not a frame's time
        start = time.perf_counter()
        deadline = None if budget_ms is None else Deadline.after_ms(budget_ms, start)
        intr, time_s = frame.intrinsics, float(frame.timestamp_ms) / 1e3
        predicted = tracker.predict(time_s)
        windows = None
        if not lost and time_s - last_full_s < FULL_SEARCH_EVERY_S:
            windows = track_windows(predicted, intr, config.radius_m)
        if windows is None:
            cloud = depth_cloud(frame.depth, intr, frame_rays)
            hints = [t.centre_m for t in predicted if t.confirmed]  # then the rest of the frame
            spheres = detect(cloud, config, seed=(int(seed), int(frame.index)), deadline=deadline,
                             hints_m=np.array(hints).reshape(-1, 3)) if len(cloud) else []
            last_full_s, search = time_s, "full"
            _count(stats, frame, len(cloud))
        else:
            spheres = _detect_in_windows(frame, frame_rays, windows, config, (int(seed), int(frame.index)), deadline,
                                         noise)
            search = "local"
            _count(stats, frame, 1)
        if search == "full" and spheres:
            noise = spheres[0].evidence.get("frame_noise", noise)  # the camera's noise, for the windows
        tracks = tracker.update(time_s, [detection_of(s) for s in spheres])
        confirmed = [t for t in tracks if t.confirmed]
        lost = not confirmed  # a confirmed track that missed is looked for about its prediction until it ends
        ms = (time.perf_counter() - start) * 1e3
        yield TrackedFrame(frame, spheres, tracks, search, deadline is not None and deadline.cut_short, ms)


def detection_of(sphere) -> Detection:
    """A sphere as the tracker's detection: its centre, score, free radius and centre error."""
    e = sphere.evidence
    sigma = None
    if "sigma_m" in e and e.get("n_inliers", 0) > 0:
        # the standard error of a mean of its inliers' depth noise, correlated over noise_corr_px
        inflation = mean_variance_inflation(float(e.get("noise_corr_px", 0.0)))
        sigma = CENTRE_ERROR_FACTOR * float(e["sigma_m"]) * math.sqrt(inflation / float(e["n_inliers"]))
    return Detection(np.asarray(sphere.centre_m, np.float64), float(sphere.score),
                     float(sphere.free_radius_m) if math.isfinite(sphere.free_radius_m) else None, sigma)


def track_windows(tracks: list[TrackState], intr: Intrinsics, radius_m: float) -> list[tuple[Window, np.ndarray]] | None:
    """Where each track's ball should be seen: a window about its predicted silhouette,
    ``WINDOW_RADII`` of its image radius and ``WINDOW_SIGMAS`` of its lateral error a side, clipped to
    the image (one out of it is left out), with the predicted centre (3,) m; None where they would
    cover more than ``WINDOW_MAX_SHARE`` of the image or a track is too near to place (the whole frame
    is cheaper or needed)."""
    windows, covered = [], 0
    for t in tracks:
        x, y, z = (float(v) for v in t.centre_m)
        if not z > 2.0 * radius_m:
            return None
        f = max(float(intr.fx), float(intr.fy))
        sigma_m = math.sqrt(max(float(t.covariance[0, 0]), float(t.covariance[1, 1])))
        half = f * (WINDOW_RADII * radius_m + WINDOW_SIGMAS * sigma_m) / (z - radius_m)
        u, v = intr.fx * x / z + intr.ppx, intr.fy * y / z + intr.ppy
        u0, u1 = max(0, int(math.floor(u - half))), min(intr.width, int(math.ceil(u + half)) + 1)
        v0, v1 = max(0, int(math.floor(v - half))), min(intr.height, int(math.ceil(v + half)) + 1)
        if u1 - u0 < 3 or v1 - v0 < 3:
            continue  # out of the image: a track that matches nothing ends by itself
        windows.append(((v0, v1, u0, u1), np.array([x, y, z])))
        covered += (u1 - u0) * (v1 - v0)
    return windows if covered <= WINDOW_MAX_SHARE * intr.width * intr.height else None


def _detect_in_windows(frame: DepthFrame, rays: np.ndarray, windows: list[tuple[Window, np.ndarray]], config,
                       seed: tuple, deadline: Deadline | None, noise) -> list:
    """The spheres found in the windows of a frame, in its own pixels and point indices, best first;
    one found in two overlapping windows is kept once. noise: the depth noise measured on the last
    whole frame searched (``frame.FrameNoise``), or None to measure each window's."""
    found = []
    for j, (window, predicted_m) in enumerate(windows):
        if found and deadline is not None and deadline.passed():
            break
        cloud = depth_cloud(frame.depth, frame.intrinsics, rays, window)
        try:  # verified from the prediction first; the window searched only where that fails
            spheres = detect(cloud, config, seed=(*seed, j + 1), deadline=deadline, noise=noise,
                             hints_m=predicted_m.reshape(1, 3), search_all=False)
        except SphereBenchError:  # a window with too few points, or too far for a ball: none in it
            continue
        found += [_in_frame(s, frame.depth, window, cloud) for s in spheres]
    found.sort(key=lambda s: -s.score)
    kept = []
    for s in found:
        if all(np.linalg.norm(s.centre_m - k.centre_m) >= config.radius_m for k in kept):
            kept.append(s)
    return kept


def _in_frame(sphere, depth: np.ndarray, window: Window, cloud: Cloud):
    """A sphere found in a window's ``cloud``, its circles moved to the frame's pixels and its inlier
    indices to the whole frame's cloud (points in row-major order of the pixels with depth)."""
    v0, v1, u0, u1 = window
    has = depth[v0:v1] != 0  # the window's rows only: the rows above count as a whole
    before_row = np.count_nonzero(depth[:v0]) + np.concatenate([[0], np.cumsum(np.count_nonzero(has, axis=1))[:-1]])
    in_row = np.cumsum(has, axis=1) - 1  # a pixel with depth: its rank in its row, from u = 0
    r, c = cloud.rows[sphere.inlier_indices], cloud.cols[sphere.inlier_indices]
    sphere.inlier_indices = (before_row[r] + in_row[r, c + u0]).astype(np.int64)
    shift = np.array([u0, v0, 0.0])
    if sphere.circle_exact is not None:
        sphere.circle_exact = tuple(float(a) for a in np.asarray(sphere.circle_exact) + shift)
    if sphere.circle_paper is not None:
        sphere.circle_paper = tuple(float(a) for a in np.asarray(sphere.circle_paper) + shift)
    return sphere


def latency_summary(ms: np.ndarray) -> dict:
    """Median and 95th percentile (ms) of per-frame times, and their count."""
    ms = np.asarray(ms, dtype=np.float64)
    if ms.size == 0:
        return {"frames": 0, "median_ms": math.nan, "p95_ms": math.nan}
    return {"frames": int(ms.size), "median_ms": float(np.median(ms)), "p95_ms": float(np.percentile(ms, 95))}
