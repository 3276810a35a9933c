"""Test helper: write a minimal RealSense SDK recording in the ROS1 ``.bag`` layout.

pyrealsense2 >= 2.56 records ROS2 (``.db3``) only, but almost every existing D435 recording (the
RealSense Viewer's and ``rs.recorder``'s up to SDK 2.55) is a ROS1 bag. This module writes such a
bag of synthetic frames with the pure-Python ``rosbags`` library, in the topic layout that
librealsense's ROS1 reader (``src/media/ros/ros_reader.cpp``, ``ros_file_format.h``) plays back,
so that the ``.bag`` path of ``spherebench prepare`` is tested on the format users actually have.

Layout written (one device, one sensor, one video stream; ``<S>`` = ``Depth_0`` or ``Color_0``)::

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
"""

from __future__ import annotations

import struct
from collections.abc import Sequence
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


def write_realsense_bag(path: str | Path, frames: Sequence[np.ndarray], intrinsics: Intrinsics, *,
                        stream: str = "depth", fps: int = 30, first_timestamp_ms: float = 1000.0,
                        frame_depth_units: bool = True, option_underscores: bool = False,
                        device_info: dict[str, str] | None = None) -> Path:
    """Write ``frames`` as a RealSense SDK ROS1 recording (file format version 4) at ``path``.

    frames: depth frames (H, W) uint16 in counts of ``intrinsics.depth_scale`` (stream="depth"),
        or colour frames (H, W, 3) uint8 RGB (stream="color"); H, W = intrinsics.height, width.
    intrinsics: the stream's intrinsics (pixels) and, for depth, its depth unit (metres/count),
        written as the sensor's Depth Units option.
    fps: nominal frame rate, Hz; frame i gets the timestamp first_timestamp_ms + i * 1000 / fps
        (ms) and frame number i, and is stamped i + 1 frame periods after the recording's start.
    frame_depth_units: write the newer SDKs' Image extension (frame_id "1" + float32 depth unit).
    option_underscores: name option topics "Depth_Units" (as newer SDKs) rather than "Depth Units".
    Returns ``path``.
    """
    if stream not in _STREAMS:
        raise ValueError(f"stream must be one of {sorted(_STREAMS)}, not {stream!r}")
    sensor_name, stream_name, encoding, bpp = _STREAMS[stream]
    h, w = intrinsics.height, intrinsics.width
    for i, f in enumerate(frames):
        want = (np.uint16, (h, w)) if stream == "depth" else (np.uint8, (h, w, 3))
        if f.dtype != want[0] or f.shape != want[1]:
            raise ValueError(f"frame {i} is {f.dtype} {f.shape}, expected {np.dtype(want[0])} {want[1]}")

    store = _typestore()
    T = store.types
    path = Path(path)
    path.unlink(missing_ok=True)  # rosbags refuses to overwrite
    prefix = "/device_0/sensor_0"
    stream_prefix = f"{prefix}/{stream_name}_0"
    period_ns = round(1e9 / fps)

    with Writer(path) as bag:
        connections = {}

        def put(topic: str, msgtype: str, t_ns: int, msg=None, data: bytes | None = None) -> None:
            if topic not in connections:
                connections[topic] = bag.add_connection(topic, msgtype, typestore=store)
            bag.write(connections[topic], t_ns, data if data is not None else store.serialize_ros1(msg, msgtype))

        kv = "diagnostic_msgs/msg/KeyValue"
        put("/file_version", "std_msgs/msg/UInt32", STATIC_NS, T["std_msgs/msg/UInt32"](data=4))
        for key, value in (device_info or D435_DEVICE_INFO).items():
            put("/device_0/info", kv, STATIC_NS, T[kv](key=key, value=value))
        put(f"{prefix}/info", kv, STATIC_NS, T[kv](key="Name", value=sensor_name))

        put(f"{stream_prefix}/info", "realsense_msgs/msg/StreamInfo", STATIC_NS,
            T["realsense_msgs/msg/StreamInfo"](fps=fps, encoding=encoding, is_recommended=True))
        zero_header = T["std_msgs/msg/Header"](seq=0, stamp=_stamp(store, 0.0), frame_id="")
        K = np.zeros(9)
        K[[0, 2, 4, 5, 8]] = intrinsics.fx, intrinsics.ppx, intrinsics.fy, intrinsics.ppy, 1.0
        roi = T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
        put(f"{stream_prefix}/info/camera_info", "sensor_msgs/msg/CameraInfo", STATIC_NS,
            T["sensor_msgs/msg/CameraInfo"](
                header=zero_header, height=h, width=w, distortion_model=_distortion_string(intrinsics.model),
                D=np.asarray(intrinsics.coeffs, dtype=np.float64), K=K, R=np.zeros(9), P=np.zeros(12),
                binning_x=0, binning_y=0, roi=roi))
        # identity extrinsics to the device's reference frame 0
        put(f"{stream_prefix}/tf/0", "geometry_msgs/msg/Transform", STATIC_NS,
            T["geometry_msgs/msg/Transform"](translation=T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
                                             rotation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0)))
        if stream == "depth":
            option = "Depth_Units" if option_underscores else "Depth Units"
            put(f"{prefix}/option/{option}/value", "std_msgs/msg/Float32", STATIC_NS,
                T["std_msgs/msg/Float32"](data=float(intrinsics.depth_scale)))
            put(f"{prefix}/option/{option}/description", "std_msgs/msg/String", STATIC_NS,
                T["std_msgs/msg/String"](data="Number of meters represented by a single depth unit"))

        for i, frame in enumerate(frames):
            t_ns = (i + 1) * period_ns
            stamp_ms = first_timestamp_ms + i * 1000.0 / fps
            header = T["std_msgs/msg/Header"](seq=i, stamp=_stamp(store, stamp_ms / 1000.0),
                                              frame_id="1" if frame_depth_units else "")
            pixels = np.ascontiguousarray(frame).astype(frame.dtype.newbyteorder("<"), copy=False)
            image = T["sensor_msgs/msg/Image"](header=header, height=h, width=w, encoding=encoding, is_bigendian=0,
                                               step=w * bpp, data=pixels.reshape(-1).view(np.uint8))
            data = store.serialize_ros1(image, "sensor_msgs/msg/Image")
            if frame_depth_units:
                # the SDK's extension of sensor_msgs/Image, read when frame_id == "1": 0 for colour
                data = bytes(data) + struct.pack("<f", intrinsics.depth_scale if stream == "depth" else 0.0)
            put(f"{stream_prefix}/image/data", "sensor_msgs/msg/Image", t_ns, data=data)
            for key, value in (("system_time", f"{stamp_ms:.6f}"), ("timestamp_domain", "Hardware Clock"),
                               ("Frame Counter", str(i)), ("Frame Timestamp", str(int(stamp_ms * 1000)))):
                put(f"{stream_prefix}/image/metadata", kv, t_ns, T[kv](key=key, value=value))
    return path
