"""Recorded depth frames: each input kind read as a stream of ``RecordedFrame``s (one scene-to-be each).

- RealSense recordings (.bag, ROS1; .db3, ROS2) by pyrealsense2 playback (``datasets.recordings``):
  the depth stream, its intrinsics and the depth sensor's depth scale. Frames can be picked by
  index range, every n-th, or by time from the first depth frame (``FrameSelection``). A colour
  stream, when recorded, gives each depth frame the colour frame nearest in time, aligned to the
  depth (``camera.align_to_depth``), kept as colour.png for annotation from colour.
- 16-bit depth PNGs with an intrinsics JSON.
- headerless raw depth frames (uint16 or float32, either byte order) with intrinsics (``RawFormat``).
- point clouds (PLY, PCD, XYZ). An organised cloud (PLY with row/col, PCD with HEIGHT > 1)
  with intrinsics gives its depth image directly; an unorganised one with intrinsics is
  projected into one (nearest surface per pixel); without intrinsics it stays an image-less
  scene (cloud.ply only: nothing that needs pixels). Points with a NaN or infinite coordinate
  are dropped (a note says how many); a cloud with no finite point is refused.

Depth units: depth.png keeps integer inputs' own counts (intrinsics.json's depth_scale says
metres per count); float inputs (clouds, float32 raw) are stored in FLOAT_DEPTH_SCALE_M counts.
Depth whose median is plainly not an indoor depth camera's (outside UNIT_CHECK_RANGE_M) is
refused with what would fix it (``check_units``): the other byte order when that reading is
plausible, else the depth scale (naming the unit it implies). A raw frame is also refused when
another reading of its bytes (width and height swapped, the other byte order) is far more
continuous than the one asked for: a misread frame is mostly jumps between neighbouring pixels.

``datasets.prepare`` writes the frames as scenes.
"""

from __future__ import annotations

import dataclasses
import math
import re
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from spherebench.camera import MAX_IMAGE_SIDE_PX, Intrinsics, align_to_depth, project
from spherebench.cloud import Cloud, depth_to_metres
from spherebench.datasets import foreign_formats, inout, recordings
from spherebench.errors import SphereBenchError

#: metres per depth.png count for inputs whose depth is not integer counts (clouds, float32 raw).
FLOAT_DEPTH_SCALE_M = 0.001
#: A median valid depth (m) outside this range is taken for a wrong unit (indoor depth camera).
UNIT_CHECK_RANGE_M = (0.05, 20.0)
#: A median (m) outside this range is no depth in any unit: bytes read as the wrong type.
ABSURD_DEPTH_M = (1e-8, 1e8)
#: Unit names of depth scales (metres per unit, as powers of ten) for the unit check's suggestion.
UNIT_NAMES = {0: "metres", -2: "centimetres", -3: "millimetres", -4: "tenths of a millimetre", -6: "micrometres"}
#: Neighbouring pixels jump when their depths differ by more than this fraction of the nearer,
#: or when only one is valid. A recorded frame has ~3 % jumps, one read with its width and height
#: swapped or in the wrong byte order 25-80 %.
JUMP_FRACTION = 0.05
#: A raw frame is refused when another reading of its bytes jumps RAW_READING_RATIO times less
#: (and by RAW_READING_MARGIN of the pairs at least, so that a flat frame never decides).
RAW_READING_RATIO = 2.5
RAW_READING_MARGIN = 0.005
#: Fewer neighbour pairs with valid depth than this tell nothing about a reading.
MIN_JUMP_PAIRS = 100
#: An organised cloud whose points land farther than this (px, median) from their own pixel
#: under the given intrinsics was taken with another camera model.
MAX_REPROJECTION_PX = 1.0

BAG_SUFFIXES = (".bag", ".db3")
PNG_SUFFIXES = (".png",)
CLOUD_SUFFIXES = (".ply", ".pcd", ".xyz", ".txt")
RAW_SUFFIXES = (".raw", ".dat", ".bin", ".depth")


# --------------------------------------------------------------------------- what a source gives

@dataclass(frozen=True)
class FrameSelection:
    """Which frames of a sequence to keep. Applied in this order: time range (recordings
    only; ms from the first depth frame, inclusive), index range [first, stop) over the
    sequence's frames (0-based), then every n-th frame of what is left."""

    every: int = 1
    first: int = 0
    stop: int | None = None
    time_range_ms: tuple[float, float] | None = None

    def __post_init__(self) -> None:
        if self.every < 1:
            raise SphereBenchError(f"--every must be >= 1, got {self.every}")
        if self.first < 0 or (self.stop is not None and self.stop <= self.first):
            raise SphereBenchError(f"--frames {self.first}:{self.stop} selects nothing; give A:B with 0 <= A < B")
        if self.time_range_ms is not None and not self.time_range_ms[0] <= self.time_range_ms[1]:
            raise SphereBenchError(f"--time-range {self.time_range_ms[0]:g}:{self.time_range_ms[1]:g} is empty")

    @classmethod
    def parse(cls, every: int = 1, frames: str | None = None, time_range: str | None = None) -> "FrameSelection":
        """From the command line's 'A:B' strings (either end may be left out)."""
        first, stop = 0, None
        if frames:
            a, b = _split_range(frames, "--frames", int)
            first, stop = (a or 0), b
        t = None
        if time_range:
            t0, t1 = _split_range(time_range, "--time-range", float)
            t = (t0 if t0 is not None else 0.0, t1 if t1 is not None else math.inf)
        return cls(every=every, first=first, stop=stop, time_range_ms=t)

    def pick(self, n: int) -> list[int]:
        """Indices kept out of a sequence of n frames without timestamps."""
        return list(range(self.first, n if self.stop is None else min(n, self.stop)))[::self.every]

    def apply(self, frames, where: str = "the recording") -> Iterator[tuple]:
        """(frame, ms from the first frame) of the timestamped frames kept (objects with ``index``,
        0-based, and ``timestamp_ms``), lazily: a stream is never held in memory. Stops reading at
        the end of the time range. Raises SphereBenchError when a time range starts past the last
        frame, so that it is not taken for an empty recording."""
        t_first = last_rel = None
        kept = 0
        for frame in frames:
            if self.stop is not None and frame.index >= self.stop:
                break  # a camera's stream has no end of its own
            t_first = frame.timestamp_ms if t_first is None else t_first
            last_rel = rel = frame.timestamp_ms - t_first
            if self.time_range_ms is not None:
                t0, t1 = self.time_range_ms
                if rel > t1:
                    break
                if rel < t0:
                    continue
            if frame.index < self.first:
                continue
            kept += 1
            if (kept - 1) % self.every == 0:
                yield frame, rel
        t = self.time_range_ms
        if kept == 0 and t is not None and last_rel is not None and last_rel < t[0]:
            raise SphereBenchError(f"--time-range {t[0]:g}:{t[1]:g} starts past the end of {where}: its last depth "
                                   f"frame is at {last_rel:.1f} ms from the first")


def _split_range(text: str, option: str, kind):
    parts = text.split(":")
    if len(parts) != 2:
        raise SphereBenchError(f"{option} must be A:B, got '{text}'")
    try:
        return tuple(kind(p) if p.strip() else None for p in parts)
    except ValueError:
        raise SphereBenchError(f"{option} must be A:B with numbers, got '{text}'") from None


@dataclass(frozen=True)
class RawFormat:
    """Headerless depth frames: size in pixels (None: the intrinsics'), value type, byte order."""

    width: int | None = None
    height: int | None = None
    dtype: str = "uint16"
    byte_order: str = "little"

    @classmethod
    def parse(cls, size: str | None, dtype: str = "uint16", byte_order: str = "little",
              option: str = "--raw-size") -> "RawFormat":
        """option: the command-line option the size came from, named in errors."""
        if not size:
            return cls(None, None, dtype, byte_order)
        m = re.fullmatch(r"\s*(\d+)\s*[xX]\s*(\d+)\s*", size)
        if not m or not all(0 < int(v) <= MAX_IMAGE_SIDE_PX for v in m.groups()):
            raise SphereBenchError(f"{option} must be WIDTHxHEIGHT in pixels, 1 to {MAX_IMAGE_SIDE_PX} a side, e.g. "
                                   f"640x480, got '{size}'")
        return cls(int(m.group(1)), int(m.group(2)), dtype, byte_order)


@dataclass
class RecordedFrame:
    """One scene-to-be. depth: (H, W) uint16 counts of intrinsics.depth_scale, or None for an
    image-less frame, which has cloud (metres) instead. image_names: file names an annotator
    may have drawn on (LabelMe's imagePath is checked against them). unit_sample_m: the valid
    depths (m) as read, before storage, for the unit check (default: from depth).
    unit_alternatives: (depths m, option) of other readings of the same bytes, which the unit
    check suggests when they are plausible; garbage_hint: what to check when no unit fits.
    colour: the recording's colour frame registered to depth, same size: a JPEG or PNG file, kept
    as colour.jpg / colour.png, or an image (H, W, 3) uint8 BGR, kept as colour.png; for annotation
    from colour (``spherebench annotate``). no_colour: why a frame whose source records colour has
    none (said once, with how many). notes: said once for the whole dataset."""

    scene_id: str
    source: str
    intrinsics: Intrinsics | None
    depth: np.ndarray | None = None
    cloud: Cloud | None = None
    meta: dict = field(default_factory=dict)
    image_names: tuple[str, ...] = ("image.png",)
    unit_sample_m: np.ndarray | None = None
    unit_alternatives: tuple[tuple[np.ndarray, str], ...] = ()
    garbage_hint: str | None = None
    colour: Path | np.ndarray | None = None
    no_colour: str | None = None
    notes: tuple[str, ...] = ()


@dataclass
class Plan:
    """Frames to prepare (an iterator: recordings are read as they are written), their count
    when known, what they came from (for dataset.json), and notes to print and keep."""

    frames: Iterable[RecordedFrame]
    total: int | None
    source: dict
    notes: list[str] = field(default_factory=list)


# --------------------------------------------------------------------------- helpers

_SAFE_ID = re.compile(r"[^A-Za-z0-9._-]+")


def scene_id_from(name: str) -> str:
    """A file stem as a scene id: letters, digits, '.', '_' and '-' only."""
    sid = _SAFE_ID.sub("_", name).strip("._")
    if not sid:
        raise SphereBenchError(f"cannot make a scene id from '{name}'")
    return sid


def natural_key(path: Path):
    """Sort key that orders frame_2 before frame_10."""
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", path.name)]


def _with_depth_scale(intr: Intrinsics, scale: float) -> Intrinsics:
    return dataclasses.replace(intr, depth_scale=float(scale))


def check_units(depth_m_valid: np.ndarray, where: str, scale: float, what: str = "depth",
                alternatives: tuple[tuple[np.ndarray, str], ...] = (), garbage_hint: str | None = None) -> None:
    """Refuse a frame whose median valid depth (m; NaN and infinities are left out) is plainly a
    wrong unit, saying what fixes it: the first of ``alternatives`` ((depths m, option): other
    readings of the same bytes) whose median is plausible; else, for a median no unit makes a
    depth (outside ABSURD_DEPTH_M), garbage_hint; else the depth scale and the unit it implies."""
    sample = np.asarray(depth_m_valid, dtype=np.float64).ravel()
    sample = sample[np.isfinite(sample)]
    if sample.size == 0:
        return
    med = float(np.median(sample))
    lo, hi = UNIT_CHECK_RANGE_M
    if lo <= med <= hi:
        return
    head = (f"{where}: median valid {what} is {med:.4g} m at {scale:g} m per unit, plainly the wrong unit "
            f"for a depth camera (expected {lo:g}-{hi:g} m)")
    for values, option in alternatives:
        alt = np.asarray(values, dtype=np.float64).ravel()
        alt = alt[np.isfinite(alt) & (alt > 0)]
        if alt.size and lo <= float(np.median(alt)) <= hi:
            raise SphereBenchError(f"{head}; with {option} it is {float(np.median(alt)):.3g} m: try {option}")
    if med == 0:
        raise SphereBenchError(f"{head}: most {what}s are 0, which sensors write for no return; remove those points")
    if not ABSURD_DEPTH_M[0] < med < ABSURD_DEPTH_M[1]:
        raise SphereBenchError(f"{head}, and no unit makes it a depth: "
                               f"{garbage_hint or 'the values are not depths'}")
    raise SphereBenchError(f"{head}; try {_scale_suggestion(med, scale)} (or --skip-unit-check for a "
                           "genuinely far scene)")


def _scale_suggestion(median_m: float, scale: float) -> str:
    """The depth scale that puts the median at 1-10 m, with its unit's name; the next smaller unit
    too when it puts the median at 0.3-1 m (500 units: centimetres at 5 m or millimetres at 0.5 m)."""
    k = -math.floor(math.log10(median_m))
    options = []
    for step in (k, k - 1):
        factor = 10.0 ** step
        depth = median_m * factor
        if step != k and depth < 0.3:
            break
        new = scale * factor
        exponent = math.log10(new)
        name = UNIT_NAMES.get(round(exponent)) if abs(exponent - round(exponent)) < 1e-9 else None
        options.append(f"{new:.3g} ({name + ': ' if name else ''}median {depth:.3g} m)")
    return "--depth-scale " + " or ".join(options)


def float_depth_to_counts(depth_m: np.ndarray, scale: float = FLOAT_DEPTH_SCALE_M) -> tuple[np.ndarray, int]:
    """(H, W) metres (NaN, inf, <= 0 invalid) -> (uint16 counts, number of pixels beyond range)."""
    z = np.asarray(depth_m, dtype=np.float64)
    valid = np.isfinite(z) & (z > 0)
    counts = np.zeros(z.shape, dtype=np.float64)
    counts[valid] = np.round(z[valid] / scale)
    too_far = int(np.count_nonzero(counts > 65535))
    counts[counts > 65535] = 0
    return counts.astype(np.uint16), too_far


def cloud_to_depth(cloud: Cloud, intr: Intrinsics, where: str) -> tuple[np.ndarray, dict]:
    """A cloud (metres) -> (H, W) depth counts of intr.depth_scale, with how many points were lost.

    Organised clouds put each point's z at its own pixel, after checking that the intrinsics
    project it there; unorganised ones are projected, keeping the nearest point per pixel.
    """
    pts = cloud.points.astype(np.float64)
    h, w = intr.shape
    info: dict = {}
    if cloud.rows is not None:
        if len(pts) and (cloud.rows.min() < 0 or cloud.cols.min() < 0 or cloud.rows.max() >= h
                         or cloud.cols.max() >= w):
            raise SphereBenchError(f"{where}: the cloud's pixels reach row {cloud.rows.max()}, col {cloud.cols.max()}, "
                                   f"outside the {w}x{h} image of the intrinsics: give this camera's intrinsics")
        front = pts[:, 2] > 0
        uv = project(intr, pts[front])
        off = np.hypot(uv[:, 0] - cloud.cols[front], uv[:, 1] - cloud.rows[front])
        if off.size and float(np.median(off)) > MAX_REPROJECTION_PX:
            raise SphereBenchError(f"{where}: the organised cloud's points land a median {np.median(off):.1f} px from "
                                   "their own pixels under the given intrinsics: they are not this camera's intrinsics")
        z = np.full((h, w), np.nan)
        z[cloud.rows[front], cloud.cols[front]] = pts[front, 2]
        info["points_behind_camera"] = int(np.count_nonzero(~front))
    else:
        front = pts[:, 2] > 0
        uv = project(intr, pts[front])
        col, row = np.round(uv[:, 0]), np.round(uv[:, 1])
        inside = np.isfinite(col) & np.isfinite(row) & (col >= 0) & (col < w) & (row >= 0) & (row < h)
        pix = row[inside].astype(np.int64) * w + col[inside].astype(np.int64)
        zs = pts[front][inside, 2]
        order = np.lexsort((zs, pix))  # per pixel, nearest first
        pix, zs = pix[order], zs[order]
        first = np.ones(len(pix), dtype=bool)
        first[1:] = pix[1:] != pix[:-1]
        z = np.full(h * w, np.nan)
        z[pix[first]] = zs[first]
        z = z.reshape(h, w)
        info["points_outside_image"] = int(len(pts) - np.count_nonzero(inside))
        info["points_hidden"] = int(np.count_nonzero(~first))
    counts, too_far = float_depth_to_counts(z, intr.depth_scale)
    info["points_beyond_depth_range"] = too_far
    return counts, info


# --------------------------------------------------------------------------- frame sources

def bag_frames(path: Path, selection: FrameSelection, depth_scale: float | None = None) -> Iterator[RecordedFrame]:
    """Depth frames of a RealSense recording, picked by ``selection``; with a colour stream, each
    with the colour frame nearest in time aligned to it (``align_to_depth``, with the depth in
    metres of the depth scale used) and, in meta, which colour frame it is and what the alignment
    did."""
    stem = scene_id_from(path.stem)
    recording = recordings.BagRecording(path)
    notes = (recording.colour_note,) if recording.colour_note else ()
    colour = recording.colour
    for bag_frame, rel in selection.apply(recording.frames(stop_after=selection.stop), path.name):
        index, stamp, intr = bag_frame.index, bag_frame.timestamp_ms, bag_frame.intrinsics
        if depth_scale is not None:
            intr = _with_depth_scale(intr, depth_scale)
        meta = {"source": path.name, "frame_index": index, "frame_number": bag_frame.number,
                "timestamp_ms": stamp, "time_from_first_frame_ms": round(rel, 6)}
        aligned = None
        if colour is not None:
            meta["colour"] = _colour_meta(colour, bag_frame)
            if bag_frame.colour is not None:
                aligned, counts = align_to_depth(depth_to_metres(bag_frame.depth, intr), intr, bag_frame.colour,
                                                 colour.intrinsics, colour.rotation, colour.translation)
                meta["colour"]["aligned_pixels"] = counts
        yield RecordedFrame(scene_id=f"{stem}_{index:06d}", source=f"{path} frame {index}", intrinsics=intr,
                    depth=bag_frame.depth, meta=meta, colour=aligned, no_colour=bag_frame.no_colour, notes=notes)


def _colour_meta(colour: recordings.BagColour, frame: recordings.BagFrame) -> dict:
    """What a scene records of its colour frame: which one, its offset in time, the stream."""
    offset = None if frame.colour_timestamp_ms is None else round(frame.colour_timestamp_ms - frame.timestamp_ms, 6)
    intrinsics = colour.intrinsics.to_dict()
    del intrinsics["depth_scale"]
    return {"frame_number": frame.colour_number, "timestamp_ms": frame.colour_timestamp_ms, "offset_ms": offset,
            "format": colour.format, "intrinsics": intrinsics,
            "depth_to_colour": {"rotation": [list(r) for r in colour.rotation],
                                "translation_m": list(colour.translation)},
            "aligned": "to the depth: each depth pixel's nearest colour pixel; black without depth, off the colour "
                       "image or hidden from the colour camera"}


def depth_png_frames(paths: list[Path], intr: Intrinsics | None, selection: FrameSelection,
                     depth_scale: float | None = None) -> Plan:
    """16-bit depth PNGs of one camera (``intr``; depth_scale overrides its depth unit)."""
    if intr is None:
        raise SphereBenchError(f"{paths[0].parent}: depth PNGs need intrinsics: give --intrinsics FILE "
                               "(pyrealsense2 fields) or --fx --fy --ppx --ppy")
    if depth_scale is not None:
        intr = _with_depth_scale(intr, depth_scale)
    picked = [paths[i] for i in selection.pick(len(paths))]

    def frames():
        for p in picked:
            depth = inout.read_depth_png(p)
            if depth.shape != intr.shape:
                raise SphereBenchError(f"{p}: depth image is {depth.shape[1]}x{depth.shape[0]} but the intrinsics "
                                       f"are {intr.width}x{intr.height}: give the intrinsics of this stream")
            yield RecordedFrame(scene_id_from(p.stem), p.name, intr, depth=depth, meta={"source": p.name},
                        image_names=("image.png", p.name))
    return Plan(frames(), len(picked), {"kind": "depth-png", "files": [p.name for p in picked]})


def jump_fraction(depth: np.ndarray) -> float | None:
    """Of the up-down and left-right neighbour pairs with at least one valid pixel (finite, > 0),
    the fraction that jump (see JUMP_FRACTION); None with fewer than MIN_JUMP_PAIRS pairs.
    Unit-free: counts or metres alike."""
    d = np.asarray(depth, dtype=np.float64)
    valid = np.isfinite(d) & (d > 0)
    d = np.where(valid, d, 0.0)
    jumps = pairs = 0
    for a, b, va, vb in ((d[1:], d[:-1], valid[1:], valid[:-1]), (d[:, 1:], d[:, :-1], valid[:, 1:], valid[:, :-1])):
        apart = np.abs(a - b) > JUMP_FRACTION * np.minimum(a, b)
        jumps += np.count_nonzero(va != vb) + np.count_nonzero(va & vb & apart)
        pairs += np.count_nonzero(va | vb)
    return jumps / pairs if pairs >= MIN_JUMP_PAIRS else None


def check_raw_reading(values: np.ndarray, where: str, readings: list[tuple[np.ndarray, str, str]]) -> None:
    """Refuse a raw frame (H, W) that another reading of its bytes shows far more continuous.

    readings: (values, how it was read, what to do), e.g. (the bytes as 480x640, "read as 480x640",
    "give --raw-size 480x640"); the first that jumps RAW_READING_RATIO times less is named.
    """
    given = jump_fraction(values)
    if given is None:
        return
    for other_values, how, fix in readings:
        other = jump_fraction(other_values)
        if other is not None and given > RAW_READING_RATIO * other + RAW_READING_MARGIN:
            raise SphereBenchError(f"{where}: {given:.1%} of neighbouring pixels jump in depth as read, {other:.1%} "
                                   f"{how}: {fix}")


def _raw_readings(values: np.ndarray, swapped_values: np.ndarray, raw: RawFormat) -> list[tuple[np.ndarray, str, str]]:
    """Other readings of a raw frame's bytes for check_raw_reading: width and height swapped (when
    they differ), the other byte order (swapped_values: the values byte-swapped), and both."""
    h, w = values.shape
    other_order = "big" if raw.byte_order == "little" else "little"
    if raw.width is not None:
        size_fix = f"width and height are swapped, give --raw-size {h}x{w}"
    else:
        size_fix = f"width and height are swapped, give the intrinsics of a {h}x{w} image"
    readings = [(swapped_values, f"read {other_order}-endian", f"try --raw-byte-order {other_order}")]
    if h != w:
        readings = [(values.reshape(w, h), f"read as {h}x{w}", size_fix), *readings,
                    (swapped_values.reshape(w, h), f"read {other_order}-endian as {h}x{w}",
                     f"try --raw-byte-order {other_order}, and {size_fix}")]
    return readings


def raw_frames(paths: list[Path], raw: RawFormat, intr: Intrinsics | None, selection: FrameSelection,
               depth_scale: float | None = None) -> Plan:
    """Headerless frames; uint16 keep their counts, float32 are stored as FLOAT_DEPTH_SCALE_M counts.
    Each frame is checked against other readings of its bytes (check_raw_reading)."""
    if intr is None:
        raise SphereBenchError(f"{paths[0]}: raw frames need intrinsics: give --intrinsics FILE or --fx --fy --ppx --ppy")
    if raw.width is not None and (raw.width, raw.height) != (intr.width, intr.height):
        raise SphereBenchError(f"--raw-size {raw.width}x{raw.height} disagrees with the intrinsics' "
                               f"{intr.width}x{intr.height}: give the intrinsics of this stream")
    if raw.dtype == "uint16":
        out_intr = _with_depth_scale(intr, depth_scale) if depth_scale is not None else intr
        in_scale = out_intr.depth_scale
    else:  # float32 values are metres unless told otherwise
        in_scale = depth_scale if depth_scale is not None else 1.0
        out_intr = _with_depth_scale(intr, FLOAT_DEPTH_SCALE_M)
    picked = [paths[i] for i in selection.pick(len(paths))]

    other_order = "big" if raw.byte_order == "little" else "little"

    def frames():
        for p in picked:
            values = foreign_formats.read_raw_depth(p, intr.width, intr.height, raw.dtype, raw.byte_order)
            swapped_values = values.byteswap()
            check_raw_reading(values, str(p), _raw_readings(values, swapped_values, raw))
            meta = {"source": p.name}
            sample = None
            swapped = swapped_values.astype(np.float64) * in_scale
            alternatives = ((swapped[swapped > 0], f"--raw-byte-order {other_order}"),)
            garbage = None
            if raw.dtype == "uint16":
                depth = values
            else:
                metres = values.astype(np.float64) * in_scale
                depth, too_far = float_depth_to_counts(metres, FLOAT_DEPTH_SCALE_M)
                meta["pixels_beyond_depth_range"] = too_far
                sample = metres[np.isfinite(metres) & (metres > 0)]
                garbage = ("these bytes are not float32 depth; are they integers (--raw-dtype uint16, with the "
                           "frame's own --raw-size)?")
            yield RecordedFrame(scene_id_from(p.stem), p.name, out_intr, depth=depth, meta=meta,
                        image_names=("image.png", p.name), unit_sample_m=sample, unit_alternatives=alternatives,
                        garbage_hint=garbage)
    return Plan(frames(), len(picked), {"kind": f"raw-{raw.dtype}-{raw.byte_order}-endian",
                                        "files": [p.name for p in picked], "input_depth_scale": in_scale})


def read_cloud_file(path: Path, intr: Intrinsics | None) -> Cloud:
    suffix = path.suffix.lower()
    if suffix == ".ply":
        return inout.read_ply(path)
    if suffix == ".pcd":
        return foreign_formats.read_pcd(path, intr)
    if suffix in (".xyz", ".txt"):
        return foreign_formats.read_xyz(path)
    raise SphereBenchError(f"{path}: unknown point-cloud format '{path.suffix}' (.ply, .pcd, .xyz)")


def cloud_frames(paths: list[Path], intr: Intrinsics | None, selection: FrameSelection,
                 depth_scale: float | None = None, scene_ids: list[str] | None = None,
                 metas: list[dict] | None = None) -> Plan:
    """Point-cloud files (coordinates times depth_scale = metres; default 1). With intrinsics a
    cloud becomes an organised depth frame in FLOAT_DEPTH_SCALE_M counts; without, an image-less scene."""
    scale = 1.0 if depth_scale is None else depth_scale
    out_intr = None if intr is None else _with_depth_scale(intr, FLOAT_DEPTH_SCALE_M)
    keep = selection.pick(len(paths))
    notes = []
    if intr is None:
        notes.append("clouds without intrinsics are kept as image-less scenes (cloud.ply only): no depth.png, "
                     "image.png, masks or 2D circles; give --intrinsics to project them into depth images")

    def frames():
        for i in keep:
            p = paths[i]
            cloud = read_cloud_file(p, intr)
            if len(cloud) == 0:
                raise SphereBenchError(f"{p}: the cloud has no valid point")
            with np.errstate(over="ignore"):  # a coordinate beyond float32 becomes inf, dropped below
                pts = (cloud.points.astype(np.float64) * scale).astype(np.float32)
            finite = np.isfinite(pts).all(axis=1)
            dropped = int(len(pts) - np.count_nonzero(finite))
            if dropped == len(pts):
                raise SphereBenchError(f"{p}: none of the cloud's {len(pts)} points has finite coordinates "
                                       "(all NaN, infinite or beyond float32)")
            if dropped:
                rows, cols = (None, None) if cloud.rows is None else (cloud.rows[finite], cloud.cols[finite])
                cloud = Cloud(pts[finite], rows, cols, None)
            else:
                cloud = Cloud(pts, cloud.rows, cloud.cols, None)
            sid = scene_ids[i] if scene_ids else scene_id_from(p.stem)
            meta = {"source": p.name, **(metas[i] if metas else {})}
            meta["organised_file"] = cloud.rows is not None
            if dropped:
                meta["non_finite_points_dropped"] = dropped
            if out_intr is None:
                yield RecordedFrame(sid, p.name, None, cloud=cloud, meta=meta, image_names=())
                continue
            depth, info = cloud_to_depth(cloud, out_intr, str(p))
            meta.update(info)
            yield RecordedFrame(sid, p.name, out_intr, depth=depth, meta=meta, image_names=("image.png",),
                        unit_sample_m=np.linalg.norm(cloud.points.astype(np.float64), axis=1))
    return Plan(frames(), len(keep), {"kind": "point-cloud", "files": [paths[i].name for i in keep],
                                      "coordinate_scale_m": scale}, notes)


def files_of(path: Path) -> tuple[str, list[Path]]:
    """An input path -> (kind, files): kind is bag, png, cloud or raw."""
    kinds = {"bag": BAG_SUFFIXES, "png": PNG_SUFFIXES, "cloud": CLOUD_SUFFIXES, "raw": RAW_SUFFIXES}
    if path.is_file():
        for kind, suffixes in kinds.items():
            if path.suffix.lower() in suffixes:
                return kind, [path]
        return "raw", [path]  # a headerless frame may have any name
    if not path.is_dir():
        raise SphereBenchError(f"{path}: no such file or folder")
    frame_suffixes = {suffix for suffixes in kinds.values() for suffix in suffixes}
    special = sorted(p.name for p in path.iterdir()
                     if p.suffix.lower() in frame_suffixes and not p.is_file() and not p.is_dir())
    if special:  # named as a frame, it is no file to read (a FIFO would hold the reader)
        raise SphereBenchError(f"{path / special[0]}: not a regular file (a FIFO, a device or a socket): move it out "
                               "of the folder")
    found = {kind: sorted((p for p in path.iterdir() if p.is_file() and p.suffix.lower() in sfx), key=natural_key)
             for kind, sfx in kinds.items()}
    found = {k: v for k, v in found.items() if v}
    if not found:
        raise SphereBenchError(f"{path}: no depth data in this folder (.bag, .db3, .png, .ply, .pcd, .xyz, .raw, .dat)")
    if len(found) > 1:
        raise SphereBenchError(f"{path}: the folder mixes {' and '.join(found)} files; give one kind per input")
    return next(iter(found.items()))


def camera_from_options(intrinsics_file: Path | None = None, fx: float | None = None, fy: float | None = None,
                        ppx: float | None = None, ppy: float | None = None, width: int | None = None,
                        height: int | None = None, model: str = "none",
                        coeffs: tuple[float, ...] | None = None, size_option: str = "--raw-size") -> Intrinsics | None:
    """Intrinsics from a JSON file or from the four numbers (and the image size); None if neither.
    size_option: the option the size came from (--raw-size or --size), named in errors."""
    numbers = {"--fx": fx, "--fy": fy, "--ppx": ppx, "--ppy": ppy}
    given = [k for k, v in numbers.items() if v is not None]
    if intrinsics_file is not None:
        if given:
            raise SphereBenchError(f"give intrinsics as --intrinsics FILE or as {', '.join(numbers)}, not both")
        if coeffs is not None or model != "none":  # the file's own model and coefficients hold
            raise SphereBenchError("--model and --coeffs go with --fx --fy --ppx --ppy: the distortion of "
                                   "--intrinsics FILE is the file's (its model and coeffs)")
        intr = foreign_formats.read_camera_json(intrinsics_file)
        if width is not None and (width, height) != (intr.width, intr.height):
            raise SphereBenchError(f"{intrinsics_file}: intrinsics are {intr.width}x{intr.height} but the frames "
                                   f"are {width}x{height} ({size_option}): give the intrinsics of this stream")
        return intr
    if not given:
        if size_option == "--size" and width is not None:
            raise SphereBenchError("--size is the image size of --fx --fy --ppx --ppy; give those too, or drop --size")
        return None
    missing = [k for k, v in numbers.items() if v is None]
    if missing:
        raise SphereBenchError(f"intrinsics options are incomplete: also give {', '.join(missing)}")
    if width is None or height is None:
        raise SphereBenchError("intrinsics given as numbers also need the image size (--raw-size WxH or --size WxH)")
    return Intrinsics(width=width, height=height, ppx=ppx, ppy=ppy, fx=fx, fy=fy, model=model,
                      coeffs=tuple(coeffs) if coeffs else (0.0,) * 5)
