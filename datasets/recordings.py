"""RealSense recordings (.bag, ROS1; .db3, ROS2) played back through pyrealsense2: the depth frames,
each with the colour frame nearest to it in time where the recording has a usable colour stream.

``BagRecording`` opens a recording and plays it back (``frames``); ``BagFrame`` is one depth frame
(also what ``spherebench.datasets.depth_frames`` yields from a live camera). pyrealsense2 is the
``realsense`` extra, imported only when a recording is opened (``import_pyrealsense2``).
"""

from __future__ import annotations

import atexit
import collections
import math
import queue
import threading
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from spherebench.camera import Intrinsics, float32_decimal
from spherebench.errors import SphereBenchError, require

#: The first bytes of a recording by suffix, and what they are.
RECORDING_MAGIC = {".bag": (b"#ROSBAG V2.0\n", "ROS1 bag"), ".db3": (b"SQLite format 3\x00", "ROS2 SQLite")}


def import_pyrealsense2():
    """pyrealsense2 (the ``realsense`` extra), or one line saying how to install it."""
    return require("pyrealsense2", "realsense", "reading RealSense recordings and cameras (also: apt-get install "
                   "libusb-1.0-0)")


#: Colour formats of a recording's colour stream that prepare keeps (pyrealsense2's rs.format
#: names) -> OpenCV's conversion to BGR (None: already BGR) and bytes per pixel.
BAG_COLOUR_FORMATS = {"rgb8": (cv2.COLOR_RGB2BGR, 3), "bgr8": (None, 3), "rgba8": (cv2.COLOR_RGBA2BGR, 4),
                      "bgra8": (cv2.COLOR_BGRA2BGR, 4), "yuyv": (cv2.COLOR_YUV2BGR_YUY2, 2),
                      "uyvy": (cv2.COLOR_YUV2BGR_UYVY, 2)}
#: Depth frames held back while the colour frame after them has not arrived yet; beyond this many
#: the oldest is paired with the colour frames seen so far (a colour stream that stops early).
BAG_PENDING_DEPTH_FRAMES = 8
#: Colour frames kept for pairing (the latest ones).
BAG_COLOUR_HISTORY = 8
#: Timestamp jitter (ms) allowed beyond half a colour frame period when pairing colour with depth.
BAG_COLOUR_SLACK_MS = 1.0


@dataclass
class BagFrame:
    """One depth frame of a recording or a live camera and, when the recording has a usable colour
    stream, the colour frame nearest to it in time. index counts depth frames from 0; timestamps
    are the frames' own (ms). colour: (h, w, 3) uint8 BGR at the colour stream's own size; None, with
    ``no_colour`` saying why, when no colour frame lies within BagColour.max_offset_ms (the nearest
    is then still named by colour_number and colour_timestamp_ms) or the two streams' timestamps
    are in different clock domains. All colour fields stay None without a colour stream."""

    index: int
    number: int
    timestamp_ms: float
    depth: np.ndarray
    intrinsics: Intrinsics
    colour: np.ndarray | None = None
    colour_number: int | None = None
    colour_timestamp_ms: float | None = None
    no_colour: str | None = None


@dataclass(frozen=True)
class BagColour:
    """A recording's colour stream: format (BAG_COLOUR_FORMATS), intrinsics (depth_scale unused),
    the depth-to-colour extrinsics (a depth point p is at rotation @ p + translation in the colour
    camera's frame, metres; from the recording's profile.get_extrinsics_to) and the largest time
    offset (ms) of a colour frame paired with a depth frame: half a colour frame period (the
    farthest the nearest frame of a regular stream can be) plus BAG_COLOUR_SLACK_MS."""

    format: str
    intrinsics: Intrinsics
    rotation: tuple[tuple[float, float, float], ...]
    translation: tuple[float, float, float]
    fps: int
    max_offset_ms: float


class BagRecording:
    """A RealSense recording (.bag, ROS1; .db3, ROS2) opened for pyrealsense2 playback: its depth
    stream, and its colour stream when it has one that can be kept (``colour``; else ``colour_note``
    says why there is none). Opening reads the file's description only; ``frames`` plays it back.

    The sensors are started directly (not through rs.pipeline, which drops frames when the consumer
    is slower than the file) with non-real-time playback and a small blocking queue: the playback
    thread waits for each frame to be taken, so none is lost and memory stays bounded. Colour is
    paired with depth by timestamp here, not by rs.syncer, which may emit a frame alone or drop it.
    """

    def __init__(self, path: str | Path):
        self.path = path = Path(path)
        if not path.is_file():
            raise SphereBenchError(f"{path}: file not found")
        magic, kind = RECORDING_MAGIC.get(path.suffix.lower(), (b"", ""))
        with path.open("rb") as f:
            head = f.read(len(magic))
        if head != magic:  # refused before librealsense starts (it writes ~/.rum/rum.json)
            raise SphereBenchError(f"{path}: not a RealSense recording (no {kind} header): "
                                   "give a .bag or .db3 file recorded by a RealSense camera")
        rs = import_pyrealsense2()
        try:
            self._device = rs.context().load_device(str(path))
            sensors = self._device.query_sensors()
            streams = [(i, s, p) for i, s in enumerate(sensors) for p in s.get_stream_profiles()]
        except RuntimeError as exc:
            raise SphereBenchError(f"{path}: not a readable RealSense recording, or one cut short ({exc})") from None
        depth = [(i, s, p) for i, s, p in streams if s.is_depth_sensor() and p.stream_type() == rs.stream.depth]
        if not depth:
            found = ", ".join(sorted({str(p.stream_type()).removeprefix("stream.") for *_, p in streams})) or "none"
            raise SphereBenchError(f"{path}: the recording has no depth stream (streams: {found}); "
                                   "record with depth enabled")
        self._depth_index, self._depth_sensor, self._depth_profile = depth[0]
        if self._depth_profile.format() != rs.format.z16:
            raise SphereBenchError(f"{path}: the depth stream is {self._depth_profile.format()}, "
                                   "only z16 depth is supported")
        self.depth_scale = float(self._depth_sensor.as_depth_sensor().get_depth_scale())
        self.fps = int(self._depth_profile.fps())  # the depth stream's nominal rate (0: not recorded)
        self.colour: BagColour | None = None
        self.colour_note: str | None = None
        self._colour_index = self._colour_sensor = self._colour_profile = None
        colour = [(i, s, p) for i, s, p in streams if p.stream_type() == rs.stream.color]
        if not colour:
            self.colour_note = (f"{path.name}: the recording has no colour stream: its scenes keep no colour frame "
                                "(annotate --from-colour needs one)")
            return
        sensor_index, sensor, profile = colour[0]
        fmt = str(profile.format()).removeprefix("format.")
        if fmt not in BAG_COLOUR_FORMATS:
            self.colour_note = (f"{path.name}: the colour stream is {fmt}, which prepare does not convert "
                                f"({', '.join(BAG_COLOUR_FORMATS)}): its scenes keep no colour frame")
            return
        try:
            ext = self._depth_profile.get_extrinsics_to(profile)
            c_intr = profile.as_video_stream_profile().get_intrinsics()
            intr = Intrinsics.from_rs(c_intr, 1.0)
        except (RuntimeError, SphereBenchError) as exc:
            self.colour_note = (f"{path.name}: the colour stream's calibration cannot be used ({exc}): "
                                "its scenes keep no colour frame")
            return
        r = [float32_decimal(v) for v in ext.rotation]  # column-major, as rs2_extrinsics
        self.colour = BagColour(format=fmt, intrinsics=intr,
                                rotation=tuple((r[i], r[3 + i], r[6 + i]) for i in range(3)),
                                translation=tuple(float32_decimal(v) for v in ext.translation), fps=int(profile.fps()),
                                max_offset_ms=(500.0 / profile.fps() if profile.fps() > 0 else math.inf)
                                + BAG_COLOUR_SLACK_MS)
        self._colour_index, self._colour_sensor, self._colour_profile = sensor_index, sensor, profile

    def frames(self, stop_after: int | None = None, stall_timeout_s: float = 10.0, real_time: bool = False,
               with_colour: bool = True):
        """BagFrames in recording order; stop_after: stop once this many have been yielded;
        with_colour=False plays the depth stream alone (a detector needs no colour).

        real_time: play at the recording's rate, as a camera would deliver it: a frame that
        arrives while the consumer is still busy with earlier ones is dropped (counted in
        ``self.dropped``, by stream: "depth", "colour") rather than waited for."""

        rs = import_pyrealsense2()
        playback = self._device.as_playback()
        playback.set_real_time(bool(real_time))
        items: queue.Queue = queue.Queue(maxsize=2 if real_time else 4)  # real time: hold little, drop the rest
        stopping = threading.Event()
        self.dropped = {"depth": 0, "colour": 0}
        colour = self.colour if with_colour else None
        started = self._start_sensors(playback, colour, _frame_queuer(rs, items, stopping, real_time, self.dropped))
        pairing = _ColourPairing(colour, self.depth_scale, self.path)

        def stop() -> None:
            stopping.set()
            _stop_sensors(started)

        _PLAYING.add(stop)
        try:
            played = _played_items(items, playback, rs, stall_timeout_s, self.path)
            while stop_after is None or pairing.index < stop_after:
                item = next(played, None)
                if item is None:
                    break
                pairing.add(*item)
                for frame in pairing.ready():
                    yield frame
                    if stop_after is not None and pairing.index >= stop_after:
                        return
            for frame in pairing.ready(final=True):
                if stop_after is not None and frame.index >= stop_after:
                    return
                yield frame
        finally:
            _PLAYING.discard(stop)
            stop()

    def _start_sensors(self, playback, colour: BagColour | None, on_frame) -> list:
        """Open the sensors of the streams played and start them with ``on_frame``, every one before
        the playback runs (none misses the first frames); the sensors started. Each sensor opens all
        of its streams at once (a D405's colour is on its depth sensor)."""
        opened = [(self._depth_sensor, [self._depth_profile])]
        if colour is not None:
            if self._colour_index == self._depth_index:
                opened[0][1].append(self._colour_profile)
            else:
                opened.append((self._colour_sensor, [self._colour_profile]))
        started = []
        try:
            if colour is not None:
                playback.pause()  # until every sensor is started
            for sensor, profiles in opened:
                sensor.open(profiles if len(profiles) > 1 else profiles[0])
                sensor.start(on_frame)
                started.append(sensor)
            if colour is not None:
                playback.resume()
        except RuntimeError as exc:
            _stop_sensors(started)
            raise SphereBenchError(f"{self.path}: pyrealsense2 cannot play the recording back ({exc})") from None
        return started


#: The playbacks running (their stops). A consumer that leaves a recording's frames unfinished has its
#: playback stopped at the interpreter's exit, before its teardown: librealsense's thread, still waiting
#: to queue a frame for Python then, would otherwise be killed inside a C++ handler and abort the process.
_PLAYING: set = set()


@atexit.register
def _stop_playbacks() -> None:
    for stop in list(_PLAYING):
        stop()


def _frame_queuer(rs, items: queue.Queue, stopping: threading.Event, real_time: bool, dropped: dict):
    """The sensors' frame callback: each frame copied out and released at once (librealsense's frame
    pool is small) and put on ``items`` as (is_depth, number, timestamp, pixels, the depth's
    intrinsics or the colour's (width, height), timestamp domain). In real time a frame that finds
    the queue full is dropped and counted in ``dropped``; else the playback thread waits for room,
    until ``stopping`` is set."""

    def on_frame(frame) -> None:
        vp = frame.get_profile().as_video_stream_profile()
        is_depth = vp.stream_type() == rs.stream.depth
        data = np.asanyarray(frame.get_data())
        image = np.array(data, dtype=np.uint16, copy=True) if is_depth else np.array(data, copy=True)
        item = (is_depth, int(frame.get_frame_number()), float(frame.get_timestamp()), image,
                vp.get_intrinsics() if is_depth else (vp.width(), vp.height()),
                str(frame.get_frame_timestamp_domain()))
        if real_time:
            try:
                items.put_nowait(item)
            except queue.Full:
                dropped["depth" if is_depth else "colour"] += 1
            return
        while not stopping.is_set():
            try:
                items.put(item, timeout=0.05)
                return
            except queue.Full:
                continue

    return on_frame


def _played_items(items: queue.Queue, playback, rs, stall_timeout_s: float, path: Path):
    """The items ``_frame_queuer`` queued, each frame once (one met again, with the same number and
    timestamp, is passed over), until the playback has stopped and the queue is empty; a SphereBenchError
    when nothing arrives for ``stall_timeout_s``."""
    idle_s, step_s, last = 0.0, 0.05, {}
    while True:
        try:
            item = items.get(timeout=step_s)
        except queue.Empty:
            idle_s += step_s
            if playback.current_status() == rs.playback_status.stopped and items.empty() and idle_s > 0.2:
                return
            if idle_s > stall_timeout_s:
                raise SphereBenchError(f"{path}: playback stalled for {stall_timeout_s:g} s; the file may be damaged")
            continue
        idle_s = 0.0
        is_depth, number, stamp = item[:3]
        kind = "depth" if is_depth else "colour"
        if last.get(kind) != (number, stamp):
            last[kind] = (number, stamp)
            yield item


class _ColourPairing:
    """Depth frames as BagFrames, in recording order, each with the colour frame nearest to it in
    time (BagRecording says why by timestamp). A depth frame waits until a colour frame at or after
    it has arrived, or until more than BAG_PENDING_DEPTH_FRAMES wait; the latest BAG_COLOUR_HISTORY
    colour frames are kept for pairing. Without a colour stream (``colour`` None) each depth frame
    is handed on at once."""

    def __init__(self, colour: BagColour | None, depth_scale: float, path: Path):
        self.colour, self.depth_scale, self.path = colour, depth_scale, path
        self._convert, self._bpp = BAG_COLOUR_FORMATS[colour.format] if colour is not None else (None, 0)
        self._pending: collections.deque = collections.deque()  # depth items waiting for a later colour frame
        self._recent: collections.deque = collections.deque(maxlen=BAG_COLOUR_HISTORY)  # colour items
        self._domains: dict[str, str] = {}
        self.index = 0  # depth frames handed on so far

    def add(self, is_depth: bool, number: int, stamp: float, image: np.ndarray, rs_intr, domain: str) -> None:
        """One item of ``_played_items``: a depth frame waits, a colour frame is kept as BGR."""
        self._domains.setdefault("depth" if is_depth else "colour", domain)
        if is_depth:
            self._pending.append((number, stamp, image, rs_intr))
        else:
            bgr = _colour_to_bgr(image, *rs_intr, self._bpp, self._convert, self.path)
            self._recent.append((number, stamp, bgr))

    def ready(self, final: bool = False):
        """The waiting depth frames that can be paired now; final: every one (the recording has ended)."""
        while self._pending and (final or self.colour is None or len(self._pending) > BAG_PENDING_DEPTH_FRAMES
                                 or (self._recent and self._recent[-1][1] >= self._pending[0][1])):
            yield self._paired(*self._pending.popleft())

    def _paired(self, number: int, stamp: float, image: np.ndarray, rs_intr) -> BagFrame:
        frame = BagFrame(self.index, number, stamp, image, Intrinsics.from_rs(rs_intr, self.depth_scale))
        self.index += 1
        if self.colour is not None:
            self._add_nearest_colour(frame)
        return frame

    def _add_nearest_colour(self, frame: BagFrame) -> None:
        """The colour fields of ``frame`` (BagFrame): the nearest colour frame, kept if it is near enough."""
        recent, domains, stamp, colour = self._recent, self._domains, frame.timestamp_ms, self.colour
        if not recent:
            frame.no_colour = "no colour frame was recorded up to it"
            return
        if domains["depth"] != domains["colour"]:
            frame.no_colour = (f"its timestamp and the colour stream's are in different clock domains "
                               f"({domains['depth'].removeprefix('timestamp_domain.')}, "
                               f"{domains['colour'].removeprefix('timestamp_domain.')}): they cannot be paired")
            return
        # the colour stream is in time order: the first frame at or after the depth and the one before it
        after = next((i for i, c in enumerate(recent) if c[1] >= stamp), None)
        candidates = [recent[-1]] if after is None else [recent[after]] + ([recent[after - 1]] if after else [])
        best = min(candidates, key=lambda c: (abs(c[1] - stamp), c[1]))
        frame.colour_number, frame.colour_timestamp_ms = best[0], best[1]
        if abs(best[1] - stamp) <= colour.max_offset_ms:
            frame.colour = best[2]
        else:
            frame.no_colour = (f"the nearest colour frame is {abs(best[1] - stamp):.1f} ms away, more than "
                               f"half a colour frame period and {BAG_COLOUR_SLACK_MS:g} ms "
                               f"({colour.max_offset_ms:.1f} ms; a colour frame was lost?)")


def _colour_to_bgr(data: np.ndarray, width: int, height: int, bpp: int, convert, path: Path) -> np.ndarray:
    """A colour frame's pixels (BAG_COLOUR_FORMATS, any array shape) -> (height, width, 3) uint8 BGR."""
    raw = np.ascontiguousarray(data).view(np.uint8).reshape(-1)
    if raw.size != width * height * bpp:
        raise SphereBenchError(f"{path}: a colour frame holds {raw.size} bytes, not the {width}x{height}x{bpp} of "
                               "its stream: the file is damaged")
    raw = raw.reshape(height, width, bpp)
    return raw.copy() if convert is None else cv2.cvtColor(raw, convert)


def _stop_sensors(sensors) -> None:
    """Stop and close each sensor; one already stopped (the file's end, or a stop before) is passed over."""
    for sensor in sensors:
        try:
            sensor.stop()
            sensor.close()
        except RuntimeError:
            pass  # already stopped at the end of the file
