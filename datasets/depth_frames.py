"""Depth frames one at a time: a RealSense recording played back or a live camera. The detector
runs over them in ``spherebench.method.stream``:

    from spherebench.datasets.depth_frames import recording_frames   # or camera_frames(width=848, ...)
    from spherebench.method import config_for
    from spherebench.method.stream import detect_stream

    for frame, spheres, ms, _cut_short in detect_stream(recording_frames("capture.bag"), config_for("improved")):
        print(frame.number, frame.timestamp_ms, [s.centre_m for s in spheres], ms)

Frames are ``recordings.BagFrame``s (depth in counts of ``intrinsics.depth_scale``). Nothing is
accumulated: each frame is read, handed on and let go, so that memory stays bounded over an
hour-long recording. Offline playback reads every frame; real-time playback and a live camera
deliver frames at the camera's rate and drop those that arrive while the consumer is still busy
(counted in ``StreamStats``).
"""

from __future__ import annotations

import sys
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from spherebench.camera import Intrinsics
from spherebench.cloud import Cloud, cloud_from_depth, depth_to_metres
from spherebench.datasets import recordings
from spherebench.datasets.frame_sources import FrameSelection
from spherebench.errors import SphereBenchError

#: Recording suffixes that pyrealsense2 plays back (ROS1 bag, ROS2 sqlite).
RECORDING_SUFFIXES = (".bag", ".db3")

#: Depth modes of the D435 (width, height) -> the frame rates it offers, for --camera's checks.
D435_DEPTH_MODES = {(424, 240): (6, 15, 30, 60, 90), (480, 270): (6, 15, 30, 60, 90),
                    (640, 360): (6, 15, 30, 60, 90), (640, 480): (6, 15, 30, 60, 90),
                    (848, 480): (6, 15, 30, 60, 90), (1280, 720): (6, 15, 30)}

#: How long a live camera may go without a depth frame before the stream is given up, ms.
CAMERA_TIMEOUT_MS = 5000


@dataclass
class StreamStats:
    """What a stream delivered: frames detected; dropped, by the reader, because detection fell
    behind (real-time playback, a live camera); missing: gaps in the frame numbers that were not
    ours to drop (frames the recording or the camera lost); fps: the stream's nominal rate (0:
    unknown)."""

    frames: int = 0
    fps: int = 0
    dropped: int = 0
    missing: int = 0
    first_number: int | None = None
    last_number: int | None = None
    notes: list[str] = field(default_factory=list)


def _rs():
    return recordings.import_pyrealsense2()


def cloud_from_rs_depth(depth_frame, rays: np.ndarray | None = None) -> Cloud:
    """An organised Cloud (metres) from pyrealsense2's ``rs.depth_frame``, with its stream's
    intrinsics and the frame's own depth unit (``get_units()``, metres per count). rays: optional
    ``image_rays`` of those intrinsics (saves their computation on every frame of a stream)."""
    profile = depth_frame.get_profile().as_video_stream_profile()
    intr = Intrinsics.from_rs(profile.get_intrinsics(), depth_frame.get_units())
    depth = np.asanyarray(depth_frame.get_data())
    return cloud_from_depth(depth_to_metres(depth, intr), intr, rays)


def is_recording(path: str | Path) -> bool:
    return Path(path).suffix.lower() in RECORDING_SUFFIXES


def recording_frames(path: str | Path, selection=None, real_time: bool = False,
                     stats: StreamStats | None = None) -> Iterator[recordings.BagFrame]:
    """The depth frames of a RealSense recording (.bag, .db3) picked by ``selection`` (a
    ``frame_sources.FrameSelection``; None: every frame). real_time: play at the recording's rate and
    drop what the consumer is too slow for (counted in ``stats.dropped``); else every frame is
    read. Raises SphereBenchError on opening when the file is no recording or has no depth."""
    recording = recordings.BagRecording(path)  # checked here, before the first frame is asked for
    selection = selection or FrameSelection()
    stats = stats if stats is not None else StreamStats()
    stats.fps = recording.fps

    def frames():
        reader = recording.frames(stop_after=selection.stop, real_time=real_time, with_colour=False)
        try:
            for frame, _ in selection.apply(_counted(reader, stats, lambda: recording.dropped["depth"]),
                                            Path(path).name):
                yield frame
        finally:
            reader.close()
            stats.dropped = recording.dropped["depth"]
            stats.missing = max(0, stats.missing - stats.dropped)
    return frames()


def _counted(frames: Iterable, stats: StreamStats, dropped_so_far=lambda: 0, gaps_are_drops: bool = False) -> Iterator:
    """frames, with the gaps in their frame numbers counted in stats.missing (a note for each gap
    that the reader did not make itself), or in stats.dropped (gaps_are_drops: a live camera's,
    whose librealsense queue drops the frames a slow consumer has not taken)."""
    for frame in frames:
        last = stats.last_number
        if last is not None and frame.number > last + 1:
            gap = frame.number - last - 1
            if gaps_are_drops:
                stats.dropped += gap
            else:
                stats.missing += gap
            if not gaps_are_drops and stats.missing > dropped_so_far():
                stats.notes.append(f"frame {frame.number}: {gap} frame(s) before it are missing from the stream "
                                   f"(numbers {last + 1}-{frame.number - 1})")
        if stats.first_number is None:
            stats.first_number = frame.number
        stats.last_number = frame.number
        yield frame


def find_camera(serial: str | None = None):
    """The connected RealSense device with this serial number (None: the only or first one).
    Raises SphereBenchError at once when none is connected or the serial is not among them."""
    rs = _rs()
    try:
        devices = list(rs.context().query_devices())
    except RuntimeError as exc:
        raise SphereBenchError(f"cannot list RealSense cameras ({exc})") from None
    if not devices:
        raise SphereBenchError("no RealSense camera is connected (pyrealsense2 finds none): plug one in on USB 3, "
                               "or give a recording (.bag, .db3)")
    serials = [d.get_info(rs.camera_info.serial_number) for d in devices]
    if serial is None:
        return devices[0], serials[0]
    if serial not in serials:
        raise SphereBenchError(f"no RealSense camera with serial number {serial} (connected: {', '.join(serials)})")
    return devices[serials.index(serial)], serial


def camera_frames(serial: str | None = None, width: int = 848, height: int = 480, fps: int = 90,
                  stats: StreamStats | None = None, timeout_ms: int = CAMERA_TIMEOUT_MS) -> Iterator[recordings.BagFrame]:
    """Depth frames of a live RealSense camera at one of its depth modes (width x height px, fps),
    until the consumer stops. The camera is opened here (an error at once if there is none); frames
    the consumer was too slow for are dropped by librealsense and counted in ``stats.dropped``."""
    rs = _rs()
    _, serial = find_camera(serial)
    stats = stats if stats is not None else StreamStats()
    stats.fps = int(fps)
    pipeline = rs.pipeline()
    config = rs.config()
    config.enable_device(serial)
    config.enable_stream(rs.stream.depth, int(width), int(height), rs.format.z16, int(fps))
    try:
        profile = pipeline.start(config)
    except RuntimeError as exc:
        raise SphereBenchError(f"camera {serial} cannot stream depth at {width}x{height} and {fps} fps ({exc}); "
                               "a D435 offers e.g. 848x480 or 424x240 at 30, 60 or 90 fps") from None
    depth_scale = profile.get_device().first_depth_sensor().get_depth_scale()

    def frames():
        index, intr = 0, None
        try:
            while True:
                try:
                    got = pipeline.wait_for_frames(timeout_ms)
                except RuntimeError:
                    raise SphereBenchError(f"camera {serial} sent no depth frame for {timeout_ms / 1000:g} s "
                                           "(unplugged?)") from None
                depth = got.get_depth_frame()
                if not depth:
                    continue
                if intr is None:
                    vp = depth.get_profile().as_video_stream_profile()
                    intr = Intrinsics.from_rs(vp.get_intrinsics(), depth_scale)
                yield recordings.BagFrame(index, int(depth.get_frame_number()), float(depth.get_timestamp()),
                                          np.array(np.asanyarray(depth.get_data()), dtype=np.uint16, copy=True), intr)
                index += 1
        finally:
            pipeline.stop()
    return _counted(frames(), stats, gaps_are_drops=True)


def print_notes(stats: StreamStats, prog: str = "note") -> None:
    for line in stats.notes:
        print(f"{prog}: {line}", file=sys.stderr)
    stats.notes.clear()
