"""Write a minimal RealSense SDK recording in the ROS1 ``.bag`` layout: synthetic recordings for
the tests, ``make stream-bench`` and the motion presets (needs ``rosbags``, of the ``realsense`` and
``test`` extras).

pyrealsense2 >= 2.56 records ROS2 (``.db3``) only, but almost every existing D435 recording (the
RealSense Viewer's and ``rs.recorder``'s up to SDK 2.55) is a ROS1 bag. This module writes such a
bag of synthetic frames with the pure-Python ``rosbags`` library, in the topic layout that
librealsense's ROS1 reader (``src/media/ros/ros_reader.cpp``, ``ros_file_format.h``) plays back,
so that the ``.bag`` paths of ``spherebench prepare`` and ``detect`` are tested on the format users
actually have.

Layout written (one device; sensor_0 with one video stream, ``<S>`` = ``Depth_0`` or ``Color_0``;
with a ``ColourStream``, also sensor_1 = RGB Camera with ``Color_0``, or ``Color_0`` on sensor_0)::

    /file_version                                  std_msgs/UInt32              4
    /device_0/info                                 diagnostic_msgs/KeyValue     Name, Serial Number, ...
    /device_0/sensor_0/info                        diagnostic_msgs/KeyValue     Name = Stereo Module | RGB Camera
    /device_0/sensor_0/<S>/info                    realsense_msgs/StreamInfo    fps, encoding, is_recommended
    /device_0/sensor_0/<S>/info/camera_info        sensor_msgs/CameraInfo       size, K, D, distortion model
    /device_0/sensor_0/<S>/tf/0                    geometry_msgs/Transform      extrinsics to reference 0
    /device_0/sensor_0/option/<Name>/value         std_msgs/Float32             e.g. Depth Units (metres/count)
    /device_0/sensor_0/option/<Name>/description   std_msgs/String
    /device_0/sensor_0/<S>/image/data              sensor_msgs/Image            one per frame
    /device_0/sensor_0/<S>/image/metadata          diagnostic_msgs/KeyValue     timestamp_domain, system_time, ...

Conventions of the SDK's writer that the reader relies on:

- Static description messages (everything but frames and their metadata) are stamped with ROS's
  TIME_MIN, 1 ns; the reader reads the device description at exactly that time and starts
  playback at 2 ns, so frames must be stamped later. Frame messages are stamped with the time
  since the recording started; the image header's stamp is the frame's own timestamp (ms in the
  SDK, stored as seconds) and its ``seq`` the frame number.
- The SDK's Image serialiser re-purposes ``header.frame_id`` as a format version: when it is
  ``"1"`` a float32 depth unit (metres/count) follows the pixel data, after the standard fields
  (ROS tools ignore the extra 4 bytes). Bags of older SDKs have no such field and the reader
  falls back to the sensor's Depth Units option; ``frame_depth_units=False`` writes that form.
- Option topics are named with ``rs2_option_to_string`` ("Depth Units") in older writers and
  with underscores ("Depth_Units") in newer ones. The reader accepts both;
  ``option_underscores`` picks one.
- Intrinsics are librealsense's float32 values; K and D carry them as float64 here, so values
  that are not float32-exact come back as the nearest float32.
- Extrinsics: a stream's ``tf/0`` holds the extrinsics from the device's reference stream
  (extrinsics group 0) to it, as the reader gives it back for
  ``reference_profile.get_extrinsics_to(profile)``. The depth stream is the reference (the
  identity), so the colour stream's ``tf/0`` is the ``ColourStream``'s depth-to-colour rotation
  and translation (tests/test_prepare_bag_colour.py reads them back).
- Frame messages of all streams are written in record-time order; a frame's record time is its
  timestamp less the earliest first timestamp of the streams, plus one depth frame period.
"""

from __future__ import annotations

import gc
import struct
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from rosbags.rosbag1 import Writer
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from spherebench.camera import Intrinsics

#: realsense_msgs/StreamInfo as librealsense defines it (its MD5 sum, 311d7e24..., must match).
STREAM_INFO_MSG = """\
uint32 fps        # The nominal streaming rate, defined in Hz
string encoding   # Stream's data format
bool is_recommended # Is this stream recommended by RealSense SDK
"""

#: ROS TIME_MIN (0 s, 1 ns): the stamp of the file's static description.
STATIC_NS = 1

#: The D435's device description (rs2_camera_info names as keys).
D435_DEVICE_INFO = {
    "Name": "Intel RealSense D435",
    "Serial Number": "000000000000",
    "Firmware Version": "05.13.00.50",
    "Recommended Firmware Version": "05.13.00.50",
    "Physical Port": "/sys/devices/synthetic",
    "Debug Op Code": "15",
    "Advanced Mode": "YES",
    "Product Id": "0B07",
    "Camera Locked": "YES",
    "Usb Type Descriptor": "3.2",
    "Product Line": "D400",
}

# stream kind -> (sensor name, stream name, ROS encoding, bytes per pixel)
_STREAMS = {
    "depth": ("Stereo Module", "Depth", "mono16", 2),
    "color": ("RGB Camera", "Color", "rgb8", 3),
}

#: Colour encodings as librealsense's ROS writer names them (ros_file_format.h: ROS names for the
#: formats ROS has, rs2_format_to_string otherwise) -> bytes per pixel.
COLOUR_ENCODINGS = {"rgb8": 3, "bgr8": 3, "rgba8": 4, "bgra8": 4, "YUYV": 2, "yuv422": 2,  # yuv422 = UYVY
                    "mono8": 1, "8UC1": 1, "16UC1": 2, "RAW16": 2}


@dataclass(frozen=True)
class ColourStream:
    """A colour stream recorded beside the depth, on its own sensor (sensor_1, "RGB Camera") unless
    ``on_depth_sensor``.

    frames: (H, W, bpp) or (H, W) uint8 arrays holding each frame's bytes in ``encoding``
        (COLOUR_ENCODINGS; rgb8: R, G, B), H, W = intrinsics.height, width.
    rotation: 3x3 row-major, translation: metres; a depth point p is at rotation @ p + translation
        in the colour camera's frame (librealsense's depth-to-colour extrinsics).
    timestamps_ms: each frame's timestamp; default first_timestamp_ms + i * 1000 / fps.
    timestamp_domain: rs2_timestamp_domain's name, written in every frame's metadata.
    on_depth_sensor: record the stream on the depth sensor (sensor_0), as a D405 has it.
    """

    frames: Sequence[np.ndarray]
    intrinsics: Intrinsics
    rotation: Sequence[Sequence[float]] = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))
    translation: Sequence[float] = (0.015, 0.0, 0.0)
    fps: int = 30
    first_timestamp_ms: float = 1000.0
    timestamps_ms: Sequence[float] | None = None
    encoding: str = "rgb8"
    timestamp_domain: str = "Hardware Clock"
    on_depth_sensor: bool = False

    def stamps_ms(self) -> list[float]:
        if self.timestamps_ms is not None:
            return [float(t) for t in self.timestamps_ms]
        return [self.first_timestamp_ms + i * 1000.0 / self.fps for i in range(len(self.frames))]


def _quaternion(r: np.ndarray) -> tuple[float, float, float, float]:
    """(x, y, z, w) of a rotation matrix, as librealsense's rot2quat (w > 0 assumed)."""
    w = np.sqrt(1.0 + r[0, 0] + r[1, 1] + r[2, 2]) / 2.0
    return ((r[2, 1] - r[1, 2]) / (4 * w), (r[0, 2] - r[2, 0]) / (4 * w), (r[1, 0] - r[0, 1]) / (4 * w), w)


def _typestore():
    store = get_typestore(Stores.ROS1_NOETIC)
    store.register(get_types_from_msg(STREAM_INFO_MSG, "realsense_msgs/msg/StreamInfo"))
    return store


def _distortion_string(model: str) -> str:
    """'inverse_brown_conrady' -> 'Inverse Brown Conrady' (rs2_distortion_to_string)."""
    return " ".join(word.capitalize() for word in model.split("_"))


def _stamp(store, seconds: float):
    sec, nsec = divmod(round(seconds * 1e9), 1_000_000_000)
    return store.types["builtin_interfaces/msg/Time"](sec=int(sec), nanosec=int(nsec))


@dataclass(frozen=True)
class _Stream:
    """One stream as written: on sensor ``sensor`` (0 or 1), its kind (a _STREAMS key), frames,
    intrinsics, ROS encoding and bytes per pixel, each frame's timestamp (ms) and number, its
    nominal rate, timestamp domain and extrinsics from the depth stream ((rotation, translation);
    None: the identity, the reference stream itself)."""

    sensor: int
    kind: str
    frames: Sequence[np.ndarray]
    intrinsics: Intrinsics
    encoding: str
    bpp: int
    stamps_ms: list[float]
    numbers: list[int]
    fps: int
    domain: str
    extrinsics: tuple[np.ndarray, np.ndarray] | None = None


def _main_stream(frames: Sequence[np.ndarray], intrinsics: Intrinsics, stream: str, fps: int,
                 first_timestamp_ms: float, frame_numbers: Sequence[int] | None) -> _Stream:
    """write_realsense_bag's own stream, checked: depth (H, W) uint16 or colour (H, W, 3) uint8
    frames of the intrinsics' size, numbered increasingly."""
    h, w = intrinsics.height, intrinsics.width
    for i, f in enumerate(frames):
        want = (np.uint16, (h, w)) if stream == "depth" else (np.uint8, (h, w, 3))
        if f.dtype != want[0] or f.shape != want[1]:
            raise ValueError(f"frame {i} is {f.dtype} {f.shape}, expected {np.dtype(want[0])} {want[1]}")
    numbers = list(range(len(frames))) if frame_numbers is None else [int(n) for n in frame_numbers]
    if len(numbers) != len(frames) or any(b <= a for a, b in zip(numbers, numbers[1:])):
        raise ValueError("frame_numbers must give one increasing number per frame")
    _, _, encoding, bpp = _STREAMS[stream]
    stamps_ms = [first_timestamp_ms + n * 1000.0 / fps for n in numbers]
    return _Stream(0, stream, frames, intrinsics, encoding, bpp, stamps_ms, numbers, fps, "Hardware Clock")


def _colour_stream(colour: ColourStream) -> _Stream:
    """A ColourStream, checked: its encoding, its frames' size and its rotation."""
    if colour.encoding not in COLOUR_ENCODINGS:
        raise ValueError(f"colour encoding must be one of {sorted(COLOUR_ENCODINGS)}, not {colour.encoding!r}")
    bpp = COLOUR_ENCODINGS[colour.encoding]
    ci = colour.intrinsics
    for i, f in enumerate(colour.frames):
        if f.dtype != np.uint8 or f.size != ci.height * ci.width * bpp or f.shape[:2] != (ci.height, ci.width):
            raise ValueError(f"colour frame {i} is {f.dtype} {f.shape}, expected uint8 "
                             f"({ci.height}, {ci.width}) x {bpp} bytes ({colour.encoding})")
    rot = np.asarray(colour.rotation, dtype=np.float64).reshape(3, 3)
    if not np.allclose(rot @ rot.T, np.eye(3), atol=1e-9) or np.linalg.det(rot) <= 0:
        raise ValueError("the colour stream's rotation must be a rotation matrix")
    return _Stream(0 if colour.on_depth_sensor else 1, "color", colour.frames, ci, colour.encoding, bpp,
                   colour.stamps_ms(), list(range(len(colour.frames))), colour.fps, colour.timestamp_domain,
                   (rot, np.asarray(colour.translation, dtype=np.float64)))


class _Topics:
    """A bag being written: messages put on topics, each topic's connection added on first use."""

    def __init__(self, bag: Writer, store):
        self.bag, self.store, self.types = bag, store, store.types
        self._connections: dict = {}

    def put(self, topic: str, msgtype: str, t_ns: int, msg=None, data: bytes | None = None) -> None:
        """``msg`` (or ``data``, already serialised) on ``topic`` at record time ``t_ns``."""
        if topic not in self._connections:
            self._connections[topic] = self.bag.add_connection(topic, msgtype, typestore=self.store)
        if data is None:
            data = self.store.serialize_ros1(msg, msgtype)
        self.bag.write(self._connections[topic], t_ns, data)


_KEY_VALUE = "diagnostic_msgs/msg/KeyValue"


def _put_description(topics: _Topics, s: _Stream, option_underscores: bool) -> None:
    """A stream's static description: its StreamInfo, CameraInfo, extrinsics (tf/0) and, for depth,
    the sensor's Depth Units option."""
    T, store, intr = topics.types, topics.store, s.intrinsics
    prefix = f"/device_0/sensor_{s.sensor}"
    stream_prefix = f"{prefix}/{_STREAMS[s.kind][1]}_0"
    topics.put(f"{stream_prefix}/info", "realsense_msgs/msg/StreamInfo", STATIC_NS,
               T["realsense_msgs/msg/StreamInfo"](fps=s.fps, encoding=s.encoding, is_recommended=True))
    zero_header = T["std_msgs/msg/Header"](seq=0, stamp=_stamp(store, 0.0), frame_id="")
    K = np.zeros(9)
    K[[0, 2, 4, 5, 8]] = intr.fx, intr.ppx, intr.fy, intr.ppy, 1.0
    roi = T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
    topics.put(f"{stream_prefix}/info/camera_info", "sensor_msgs/msg/CameraInfo", STATIC_NS,
               T["sensor_msgs/msg/CameraInfo"](
                   header=zero_header, height=intr.height, width=intr.width,
                   distortion_model=_distortion_string(intr.model), D=np.asarray(intr.coeffs, dtype=np.float64),
                   K=K, R=np.zeros(9), P=np.zeros(12), binning_x=0, binning_y=0, roi=roi))
    # extrinsics from the reference (the depth stream): identity for depth, depth-to-colour for
    # colour (the reader gives a stream's tf/0 as the reference's get_extrinsics_to(stream))
    rot, trans = (np.eye(3), np.zeros(3)) if s.extrinsics is None else s.extrinsics
    qx, qy, qz, qw = _quaternion(rot)
    topics.put(f"{stream_prefix}/tf/0", "geometry_msgs/msg/Transform", STATIC_NS,
               T["geometry_msgs/msg/Transform"](
                   translation=T["geometry_msgs/msg/Vector3"](x=float(trans[0]), y=float(trans[1]), z=float(trans[2])),
                   rotation=T["geometry_msgs/msg/Quaternion"](x=float(qx), y=float(qy), z=float(qz), w=float(qw))))
    if s.kind == "depth":
        option = "Depth_Units" if option_underscores else "Depth Units"
        topics.put(f"{prefix}/option/{option}/value", "std_msgs/msg/Float32", STATIC_NS,
                   T["std_msgs/msg/Float32"](data=float(intr.depth_scale)))
        topics.put(f"{prefix}/option/{option}/description", "std_msgs/msg/String", STATIC_NS,
                   T["std_msgs/msg/String"](data="Number of meters represented by a single depth unit"))


def _frame_messages(store, s: _Stream, k: int, t0_ms: float, period_ns: int, frame_depth_units: bool):
    """Stream ``k``'s frame messages, each (record time ns, k, frame index, topic, msgtype, message or
    serialised bytes): its Image and its metadata, recorded at its timestamp less ``t0_ms`` plus one
    depth frame period (``period_ns``)."""
    T, intr = store.types, s.intrinsics
    stream_prefix = f"/device_0/sensor_{s.sensor}/{_STREAMS[s.kind][1]}_0"
    for i, (frame, stamp_ms, number) in enumerate(zip(s.frames, s.stamps_ms, s.numbers)):
        t_ns = round((stamp_ms - t0_ms) * 1e6) + period_ns
        header = T["std_msgs/msg/Header"](seq=number, stamp=_stamp(store, stamp_ms / 1000.0),
                                          frame_id="1" if frame_depth_units else "")
        pixels = np.ascontiguousarray(frame).astype(frame.dtype.newbyteorder("<"), copy=False)
        image = T["sensor_msgs/msg/Image"](header=header, height=intr.height, width=intr.width,
                                           encoding=s.encoding, is_bigendian=0, step=intr.width * s.bpp,
                                           data=pixels.reshape(-1).view(np.uint8))
        data = bytes(store.serialize_ros1(image, "sensor_msgs/msg/Image"))
        if frame_depth_units:
            # the SDK's extension of sensor_msgs/Image, read when frame_id == "1": 0 for colour
            data += struct.pack("<f", intr.depth_scale if s.kind == "depth" else 0.0)
        yield t_ns, k, i, f"{stream_prefix}/image/data", "sensor_msgs/msg/Image", data
        for key, value in (("system_time", f"{stamp_ms:.6f}"), ("timestamp_domain", s.domain),
                           ("Frame Counter", str(number)), ("Frame Timestamp", str(int(stamp_ms * 1000)))):
            yield t_ns, k, i, f"{stream_prefix}/image/metadata", _KEY_VALUE, T[_KEY_VALUE](key=key, value=value)


def write_realsense_bag(path: str | Path, frames: Sequence[np.ndarray], intrinsics: Intrinsics, *,
                        stream: str = "depth", fps: int = 30, first_timestamp_ms: float = 1000.0,
                        frame_depth_units: bool = True, option_underscores: bool = False,
                        device_info: dict[str, str] | None = None, colour: ColourStream | None = None,
                        frame_numbers: Sequence[int] | None = None) -> Path:
    """Write ``frames`` as a RealSense SDK ROS1 recording (file format version 4) at ``path``.

    frames: depth frames (H, W) uint16 in counts of ``intrinsics.depth_scale`` (stream="depth"),
        or colour frames (H, W, 3) uint8 RGB (stream="color"); H, W = intrinsics.height, width.
    intrinsics: the stream's intrinsics (pixels) and, for depth, its depth unit (metres/count),
        written as the sensor's Depth Units option.
    fps: nominal frame rate, Hz; frame i gets the timestamp first_timestamp_ms + i * 1000 / fps
        (ms) and frame number i.
    frame_depth_units: write the newer SDKs' Image extension (frame_id "1" + float32 depth unit).
    option_underscores: name option topics "Depth_Units" (as newer SDKs) rather than "Depth Units".
    colour: a colour stream recorded beside the depth (stream="depth" only).
    frame_numbers: the frames' numbers, increasing (default 0, 1, ...); a gap is a frame the camera
        lost, and frame k's timestamp is first_timestamp_ms + frame_numbers[k] * 1000 / fps.
    Returns ``path``.
    """
    if stream not in _STREAMS:
        raise ValueError(f"stream must be one of {sorted(_STREAMS)}, not {stream!r}")
    if colour is not None and stream != "depth":
        raise ValueError("a ColourStream goes beside a depth stream")
    streams = [_main_stream(frames, intrinsics, stream, fps, first_timestamp_ms, frame_numbers)]
    if colour is not None:
        streams.append(_colour_stream(colour))

    store = _typestore()
    path = Path(path)
    path.unlink(missing_ok=True)  # rosbags refuses to overwrite
    period_ns = round(1e9 / fps)
    t0_ms = min((s.stamps_ms[0] for s in streams if s.stamps_ms), default=0.0)  # the earliest first timestamp
    with Writer(path) as bag:
        topics = _Topics(bag, store)
        topics.put("/file_version", "std_msgs/msg/UInt32", STATIC_NS, store.types["std_msgs/msg/UInt32"](data=4))
        for key, value in (device_info or D435_DEVICE_INFO).items():
            topics.put("/device_0/info", _KEY_VALUE, STATIC_NS, store.types[_KEY_VALUE](key=key, value=value))
        timed = []
        for k, s in enumerate(streams):
            if all(other.sensor != s.sensor for other in streams[:k]):  # a sensor's name, once: its first stream's
                topics.put(f"/device_0/sensor_{s.sensor}/info", _KEY_VALUE, STATIC_NS,
                           store.types[_KEY_VALUE](key="Name", value=_STREAMS[s.kind][0]))
            _put_description(topics, s, option_underscores)
            timed += _frame_messages(store, s, k, t0_ms, period_ns, frame_depth_units)
        for t_ns, _, _, topic, msgtype, item in sorted(timed, key=lambda e: e[:3]):
            if isinstance(item, bytes):
                topics.put(topic, msgtype, t_ns, data=item)
            else:
                topics.put(topic, msgtype, t_ns, item)
    return path


def record_with_sdk(path: str | Path, frames: Sequence[np.ndarray], intrinsics: Intrinsics, *, fps: int = 30,
                    first_timestamp_ms: float = 1000.0, frame_numbers: Sequence[int] | None = None) -> Path:
    """Record depth frames with pyrealsense2's own recorder, as the SDK >= 2.56 writes (ROS2, ``.db3``
    for a .db3 path): a software device with one depth stream, frame k numbered frame_numbers[k]
    (default k) and stamped first_timestamp_ms + number * 1000 / fps. frames: (H, W) uint16 counts
    of ``intrinsics.depth_scale``. Returns ``path``."""
    import pyrealsense2 as rs  # here, not at the top: an extra (realsense), which only recording needs

    path = Path(path)
    numbers = list(range(len(frames))) if frame_numbers is None else [int(n) for n in frame_numbers]
    dev = rs.software_device()
    sensor = dev.add_sensor("Stereo Module")
    vs = rs.video_stream()
    vs.type, vs.index, vs.uid, vs.width, vs.height, vs.fps = rs.stream.depth, 0, 0, intrinsics.width, \
        intrinsics.height, fps
    vs.bpp, vs.fmt, vs.intrinsics = 2, rs.format.z16, intrinsics.to_rs()
    profile = sensor.add_video_stream(vs)
    sensor.add_read_only_option(rs.option.depth_units, intrinsics.depth_scale)
    recorder = rs.recorder(str(path), dev)
    queue = rs.frame_queue(8)
    sensor.open(profile)
    sensor.start(queue)
    for depth, number in zip(frames, numbers):
        f = rs.software_video_frame()
        f.pixels = np.ascontiguousarray(depth, dtype=np.uint16)
        f.bpp, f.stride = 2, 2 * intrinsics.width
        f.timestamp, f.domain = first_timestamp_ms + number * 1000.0 / fps, rs.timestamp_domain.hardware_clock
        f.frame_number, f.depth_units = number, intrinsics.depth_scale
        f.profile = profile.as_video_stream_profile()
        sensor.on_video_frame(f)
        queue.wait_for_frame(2000)
    sensor.stop()
    sensor.close()
    del recorder  # the file is complete once the recorder is gone
    gc.collect()
    return path
