"""`spherebench detect`: find balls of known radius in point clouds, scene folders, RealSense
recordings (.bag, .db3) and a live RealSense camera.

One line per input, or per frame of a recording or camera: with --json, a record of the schema of
docs/formats.md, {"input", "frame", "timestamp_ms", "radius_m", "radius_source", "detections":
[{"score", "center_m", "radius_m", "circle_px": {"center", "radius"}, "bbox", "inliers"}], "ms"}
(ms: the detection alone, file reading excluded; frame and timestamp_ms: null for a file);
without, a short summary. A stream ends with a summary on stderr: frames, median and 95th
percentile time per frame, frames dropped (--real-time, a camera: detection fell behind) and
missing (the recording lost them). The ball radius is --radius, else the dataset's (dataset.json
two levels above a scene folder), else the scene's (gt.json), else 0.12 m (a basketball);
radius_source says which ("--radius", "dataset", "scene", "default"). Every argument is checked
before the first detection, and every input as far as it can be unread (it exists, its format,
its radius). An input that turns out bad (missing, damaged, refused by the detector) gets one line
on stderr, ``spherebench detect: error: PATH: what is wrong``, and is skipped: the others are
detected and printed, and the exit status is then 2. Files are read and written only through
``spherebench.datasets.inout`` and ``spherebench.datasets.outputs``, the records printed are
``spherebench.datasets.detections``'; streams come from ``spherebench.datasets.depth_frames`` and
are detected by ``spherebench.method.stream``.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import sys
import time
from array import array
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from spherebench import options, reading, viz
from spherebench.scripts.cli import BadInputs
from spherebench.cloud import in_front_of_camera
from spherebench.datasets import depth_frames, detections, inout, outputs
from spherebench.datasets.annotate import labelme_from_circles, labelme_text
from spherebench.datasets.drawing import draw_detections
from spherebench.datasets.frame_sources import FrameSelection, scene_id_from
from spherebench.datasets.reproject import colourise_depth
from spherebench.errors import SphereBenchError
from spherebench.method import IMPROVED, PRESETS, config_for, detect, stream, warm_up

#: The ball radius without --radius or a scene's own, metres: a basketball's.
DEFAULT_RADIUS_M = 0.12
#: The inlier tolerance without --eps, metres.
DEFAULT_EPS_M = 0.01

#: How the plain summary names a radius source.
RADIUS_SOURCES = {"--radius": "--radius", "dataset": "the dataset's", "scene": "the scene's",
                  "default": "the default"}

#: --out-ply colours: inliers red, the rest grey (RGB).
INLIER_RGB = (255, 0, 0)
OTHER_RGB = (128, 128, 128)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("paths", nargs="*", metavar="PATH",
                   help="PLY/PCD/XYZ clouds, scene folders or RealSense recordings (.bag, .db3); a bad one gets one "
                        "line on stderr and is skipped, the others are detected, and the exit status is then 2")
    p.add_argument("--radius", type=float, default=None,
                   help="ball radius, metres (default: a scene's or its dataset's ball_radius_m, else 0.12: a "
                        "basketball)")
    p.add_argument("--eps", type=float, default=None,
                   help=f"inlier tolerance around the radius, metres (default {DEFAULT_EPS_M:g})")
    p.add_argument("--method", choices=sorted(PRESETS), default="improved", help="detector configuration")
    p.add_argument("--depth-noise", type=float, default=None, metavar="A",
                   help="the sensor's depth noise as sigma_z = A z^2 (A in 1/m) for organised clouds, in place of "
                        "the D435 stereo model at the stream's fx (0.08 / (fx 0.05 m)); set it for a sensor "
                        "noisier than that (a quieter one is measured from the data)")
    p.add_argument("--min-score", type=options.fraction, default=None, metavar="P",
                   help="report only detections whose score, the estimated probability that it is a ball within "
                        f"2 cm, is at least P (default {IMPROVED.verification.min_score:g}; the improved method only)")
    p.add_argument("--intrinsics", default=None, help="intrinsics.json for clouds without their own")
    p.add_argument("--seed", type=options.seed, default=0, help="random seed (same seed, same output)")
    p.add_argument("--json", action="store_true", help="one JSON line per input or frame (docs/formats.md)")
    p.add_argument("--out-ply", default=None, help="write the cloud with the inliers in red (one input only)")
    p.add_argument("--out-png", default=None,
                   help="draw every sphere's circle and score on the reprojected image (one input only; needs "
                        "intrinsics)")
    p.add_argument("--force", action="store_true",
                   help="replace an existing --out-ply/--out-png that SphereBench did not write")
    g = p.add_argument_group("streams: recordings and a live camera")
    g.add_argument("--camera", nargs="?", const="", default=None, metavar="SERIAL",
                   help="detect in a live RealSense camera's depth (the one with this serial number, else the "
                        "first found) until Ctrl-C or --frames' end")
    g.add_argument("--size", default="848x480", metavar="WxH", help="--camera's depth mode (default 848x480)")
    g.add_argument("--fps", type=options.count, default=90, help="--camera's frame rate (default 90)")
    g.add_argument("--every", type=options.count, default=1, metavar="N", help="detect every N-th selected frame")
    g.add_argument("--frames", metavar="A:B", help="frame indices A (inclusive) to B (exclusive), from 0")
    g.add_argument("--time-range", metavar="T0:T1", help="recordings: ms from the first depth frame, inclusive")
    g.add_argument("--real-time", action="store_true",
                   help="play recordings at their own rate, dropping the frames that arrive while the detector is "
                        "busy (as a camera would); default: every frame is read")
    g.add_argument("--track", action="store_true",
                   help="follow the balls over each recording or the camera (a Kalman filter per ball), searching "
                        "a window about each followed ball and the whole frame when one is lost: each frame's "
                        "line gains its tracks, with their ids, filtered centres and velocities")
    g.add_argument("--budget-ms", type=options.budget_ms, default=None, metavar="MS",
                   help="each frame's latency bound: the detector answers with what it has verified by then and "
                        "the frame's JSON says cut_short (default: the frame period for the camera and --real-time, "
                        "none for a recording read frame by frame, whose output is then the seed's alone)")
    g.add_argument("--labelme-out", metavar="DIR", default=None,
                   help="also write each frame's circles as a LabelMe file DIR/<scene_id>.json, to pre-annotate "
                        "the recording (read back by `spherebench prepare REC --labelme DIR`)")
    g.add_argument("--rerun", action="store_true",
                   help="log each frame (depth, cloud with inliers in red, spheres, circles) to a Rerun viewer "
                        "(needs the viz extra)")
    g.add_argument("--rerun-save", metavar="FILE.rrd", default=None,
                   help="log to a Rerun recording file (with --rerun, beside the viewer); open it later with "
                        "`rerun FILE.rrd`")


def _scene_dir(path: Path) -> Path | None:
    """The scene folder a path belongs to: the folder itself (whose gt.json, whatever it is, is read:
    a FIFO or a folder there is refused), or the folder of a scene's cloud.ply (beside which only a
    file counts)."""
    if path.is_dir():
        return path if os.path.lexists(path / "gt.json") else None
    return path.parent if path.name == "cloud.ply" and (path.parent / "gt.json").is_file() else None


def ball_radius(path: Path, given: float | None) -> tuple[float, str]:
    """(radius m, its source) for one input: --radius, the dataset's, the scene's or the default."""
    scene = _scene_dir(path)
    # a scene folder's dataset.json and gt.json are read even where --radius or the other makes them moot:
    # a damaged one is refused, never passed over. A cloud given by its path is read as that file: the
    # files beside it count only where they are a scene's of SphereBench, else they are another tool's
    meta, gt = {}, {}
    if scene is not None:
        try:
            gt = inout.read_scene_gt(scene)
            meta = inout.scene_dataset_meta(scene)
        except SphereBenchError as exc:  # it names the file
            if path.is_dir():
                raise
            print(f"note: {path}: the file beside it is not a SphereBench scene's, so it is ignored ({exc})",
                  file=sys.stderr)
    if given is not None:
        return given, "--radius"
    if meta.get("ball_radius_m") is not None:
        return meta["ball_radius_m"], "dataset"
    if gt.get("ball_radius_m") is not None:
        return gt["ball_radius_m"], "scene"
    return DEFAULT_RADIUS_M, "default"


def _check_input(path: Path) -> None:
    """What can be told of an input without reading it: it exists and is a cloud, a scene folder or
    a recording."""
    if path.is_dir():
        if (path / "scenes").is_dir() and not (path / "cloud.ply").is_file():
            raise SphereBenchError(f"{path} is a dataset: give its scene folders ({path}/scenes/*)")
        return  # inout.load_cloud says what a folder lacks
    if not path.exists():
        raise SphereBenchError(f"{path}: file not found")
    if path.suffix.lower() not in inout.CLOUD_READERS and not depth_frames.is_recording(path):
        raise SphereBenchError(f"{path}: unknown point-cloud format '{path.suffix}' "
                               f"(use {', '.join(sorted(inout.CLOUD_READERS))}, a scene folder or a RealSense "
                               f"recording: {', '.join(depth_frames.RECORDING_SUFFIXES)})")


def _check_outputs(args: argparse.Namespace, streaming: bool) -> None:
    outs = {name: p for name, p in (("--out-ply", args.out_ply), ("--out-png", args.out_png)) if p is not None}
    if outs and streaming:
        raise SphereBenchError("--out-ply and --out-png take one cloud, not a stream of frames: use --labelme-out "
                               "DIR or --rerun-save FILE.rrd for recordings and cameras")
    if outs and len(args.paths) != 1:
        raise SphereBenchError("--out-ply and --out-png take one input: give one PATH")
    sources = [Path(p).resolve() for p in (*args.paths, *([args.intrinsics] if args.intrinsics else []))]
    outputs.check_output_files(outs, sources, args.force)
    if args.rerun_save is not None:
        if not args.rerun_save.strip():
            raise SphereBenchError("--rerun-save is empty (an unset shell variable?): give a file name ending in .rrd")
        out = Path(args.rerun_save)
        outputs.check_regular(out, "--rerun-save")
        if any(out.resolve() == src or src in out.resolve().parents for src in sources):
            raise SphereBenchError(f"--rerun-save {out} is an input or inside one: write it elsewhere")
        outputs.check_not_in_dataset(out, "--rerun-save")
    if args.rerun_save and Path(args.rerun_save).suffix != ".rrd":
        raise SphereBenchError(f"--rerun-save {args.rerun_save}: give a file name ending in .rrd")
    if args.rerun_save and Path(args.rerun_save).exists() and Path(args.rerun_save).stat().st_size:
        raise SphereBenchError(f"--rerun-save {args.rerun_save} exists; it is never overwritten: give a new name")
    if args.labelme_out is not None:
        outputs.check_output_dir(args.labelme_out, outputs.owned_by_kind(LABELME_KIND), "--labelme-out", args.paths)


class _NothingWritten(Exception):
    """No LabelMe file was written: the --labelme-out folder is not made (``outputs.atomic_directory``
    removes its temporary folder on the way out)."""


#: The kind of a --labelme-out folder (outputs.OWNER_MARKER): replaced by a later run, never another's files.
LABELME_KIND = "detect-labelme"


def _tolerance(args: argparse.Namespace, radius: float, source: str, raw: str) -> float:
    eps = DEFAULT_EPS_M if args.eps is None else args.eps
    if args.eps is not None and not (np.isfinite(eps) and eps > 0):
        raise SphereBenchError(f"--eps {eps}: the tolerance must be > 0 metres (e.g. 0.01)")
    if eps < radius:
        return eps
    where = {"--radius": f"--radius {radius:g}", "default": f"the default radius {radius:g} m"}.get(
        source, f"{raw}'s ball radius {radius:g} m (from its {'dataset.json' if source == 'dataset' else 'gt.json'})")
    if args.eps is None:
        raise SphereBenchError(f"{where}: the ball must be larger than the inlier tolerance ({eps:g} m by default); "
                               "give a smaller --eps too")
    raise SphereBenchError(f"--eps {eps:g}: the tolerance must be smaller than {where}")


def _image_for(path: Path, cloud) -> np.ndarray:
    """The reprojected image: a scene folder's image.png, else the organised cloud's depth colourised."""
    if path.is_dir() and (path / "image.png").is_file():
        if cloud.intrinsics is not None:
            inout.check_scene_image(path, cloud.intrinsics)
        return inout.read_image(path / "image.png")
    if not cloud.organised:
        raise SphereBenchError(f"{path}: --out-png needs an organised cloud with intrinsics (rows, cols) "
                               "or a scene folder with image.png")
    intr = cloud.intrinsics
    depth = np.full(intr.shape, np.nan, np.float32)
    ok = (cloud.rows >= 0) & (cloud.rows < intr.height) & (cloud.cols >= 0) & (cloud.cols < intr.width)
    depth[cloud.rows[ok], cloud.cols[ok]] = cloud.points[ok, 2]
    return colourise_depth(depth)


def _size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise SphereBenchError(f"--size {text!r}: give WxH in pixels, e.g. 848x480") from None
    if w <= 0 or h <= 0:
        raise SphereBenchError(f"--size {text!r}: give a positive WxH, e.g. 848x480")
    return w, h


def _spheres_json(spheres) -> list[dict]:
    return [detections.detection_record(s.score, s.circle_exact, s.centre_m, s.radius_m, len(s.inlier_indices),
                                        s.evidence.get("visible_fraction"), s.raw_score)
            for s in spheres]


def _tracks_json(tracks) -> list[dict]:
    return [detections.track_record(t.track_id, t.confirmed, t.centre_m, t.velocity_m_s, t.probability, t.radius_m,
                                    t.matched, t.radius_se_m, t.reported) for t in tracks]


def _print_result(args, raw: str, spheres, ms: float, radius: float, source: str, frame=None, tracks=None,
                  **stream_fields) -> None:
    """One input's or frame's result, a JSON line or a sentence; stream_fields: a stream frame's
    cut_short and search, in its JSON line."""
    if args.json:
        extra = dict(stream_fields) if tracks is None else {**stream_fields, "tracks": _tracks_json(tracks)}
        print(json.dumps(detections.frame_record(raw, _spheres_json(spheres), ms,
                                                 frame=None if frame is None else frame.number,
                                                 timestamp_ms=None if frame is None else frame.timestamp_ms,
                                                 radius_m=radius, radius_source=source, **extra)), flush=True)
        return
    parts = [f"({s.centre_m[0]:+.3f}, {s.centre_m[1]:+.3f}, {s.centre_m[2]:.3f}) m score {s.score:.2f} "
             f"{len(s.inlier_indices)} inliers" for s in spheres]
    where = raw if frame is None else f"{raw} frame {frame.number} ({frame.timestamp_ms:.1f} ms)"
    followed = [f"track {t.track_id} at ({t.centre_m[0]:+.3f}, {t.centre_m[1]:+.3f}, {t.centre_m[2]:.3f}) m"
                for t in tracks or () if t.confirmed]
    cut = " (cut short by --budget-ms)" if stream_fields.get("cut_short") else ""
    print(f"{where}: {len(spheres)} sphere(s) of radius {radius:g} m ({RADIUS_SOURCES[source]}) in {ms:.1f} ms{cut}"
          + (": " + "; ".join(parts) if parts else "") + ("; " + ", ".join(followed) if followed else ""), flush=True)


def _labelme(out_dir: Path | None, scene_id: str, spheres, shape) -> None:
    """The frame's circles as a LabelMe file <scene_id>.json, named as `prepare` names its scene."""
    if out_dir is None:
        return
    circles = [s.circle_exact for s in spheres if s.circle_exact is not None]
    scores = [f"score {s.score:.3f}" for s in spheres if s.circle_exact is not None]
    doc = labelme_from_circles(circles, "image.png", shape, descriptions=scores)
    outputs.atomic_write_bytes(out_dir / f"{scene_id}.json", labelme_text(doc).encode())


def _stream_summary(raw: str, times_ms, stats: depth_frames.StreamStats, real_time: bool) -> None:
    """One line on stderr at a stream's end: frames, time per frame, frames dropped and missing."""
    lat = stream.latency_summary(np.frombuffer(times_ms, dtype=np.float64) if len(times_ms) else [])
    timing = (f", {lat['median_ms']:.1f} ms median and {lat['p95_ms']:.1f} ms p95 per frame" if lat["frames"]
              else "")
    dropped = f", {stats.dropped} dropped (detection behind the frame rate)" if real_time or stats.dropped else ""
    print(f"{raw}: {stats.frames} frame(s){timing}{dropped}, {stats.missing} missing", file=sys.stderr)


def _check_arguments(args: argparse.Namespace) -> bool:
    """Every argument checked, before any input is read; whether the inputs hold a stream (a
    recording or the camera)."""
    if args.radius is not None:
        reading.check_ball_radius(args.radius)
        _tolerance(args, args.radius, "--radius", "--radius")
    if args.depth_noise is not None and not (np.isfinite(args.depth_noise) and args.depth_noise >= 0):
        raise SphereBenchError(f"--depth-noise {args.depth_noise}: give sigma_z / z^2 in 1/m, >= 0 (e.g. 0.0015)")
    if args.min_score is not None and PRESETS[args.method].pipeline != "improved":
        raise SphereBenchError(f"--min-score: the {args.method} method reports every sphere it finds; --min-score "
                               "applies to --method improved")
    camera = args.camera or ""
    if camera and ("/" in camera or Path(camera).suffix or Path(camera).exists()):
        raise SphereBenchError(f"--camera {camera}: --camera takes a serial number; give the file as a PATH argument "
                               f"(spherebench detect {camera})")
    if args.camera is not None and args.paths:
        raise SphereBenchError("--camera reads the camera: give no PATH with it")
    if args.camera is None and not args.paths:
        raise SphereBenchError("nothing to detect in: give PATHs (clouds, scene folders, recordings) or --camera")
    streaming = args.camera is not None or any(depth_frames.is_recording(p) for p in args.paths)
    stream_only = [o for o, v in (("--every", args.every != 1), ("--frames", args.frames),
                                  ("--time-range", args.time_range), ("--real-time", args.real_time),
                                  ("--budget-ms", args.budget_ms is not None)) if v]
    if stream_only and not streaming:
        raise SphereBenchError(f"{stream_only[0]} is for the frames of a recording or the camera: give a .bag/.db3 or --camera")
    if args.track and not (args.camera is not None or (args.paths and all(depth_frames.is_recording(p)
                                                                          for p in args.paths))):
        raise SphereBenchError("--track follows balls over a recording or the camera, each on its own: give "
                               ".bag/.db3 recordings or --camera, not clouds or scene folders")
    if args.camera is not None and args.time_range:
        raise SphereBenchError("--time-range is for recordings; with --camera use --frames A:B")
    _check_outputs(args, streaming)
    return streaming


@dataclass
class _Job:
    """One input to detect in: as given (``raw``), its path (None: the camera), its ball radius and
    the radius's source, the inlier tolerance, and for a stream its frames and their StreamStats."""

    raw: str
    path: Path | None
    radius: float
    source: str
    eps: float
    streamed: tuple | None = None


def _jobs(args: argparse.Namespace, selection: FrameSelection, bad: BadInputs) -> list[_Job]:
    """The inputs, each checked as far as it can be unread (a bad one is skipped through ``bad``); a
    recording is opened now, so that one without depth is refused before any work; the camera last."""
    jobs = []
    for raw in args.paths:
        path = Path(raw)
        try:
            _check_input(path)
            radius, source = ball_radius(path, args.radius)
            job = _Job(raw, path, radius, source, _tolerance(args, radius, source, raw))
            if depth_frames.is_recording(path):
                stats = depth_frames.StreamStats()
                job.streamed = (depth_frames.recording_frames(path, selection, args.real_time, stats), stats)
            jobs.append(job)
        except (SphereBenchError, OSError) as exc:
            bad.skip(raw, exc)
    if args.camera is not None:
        width, height = _size(args.size)
        radius, source = (args.radius, "--radius") if args.radius is not None else (DEFAULT_RADIUS_M, "default")
        eps = _tolerance(args, radius, source, "--camera")
        stats = depth_frames.StreamStats()
        frames = depth_frames.camera_frames(args.camera or None, width, height, args.fps, stats)
        if selection.first or selection.stop is not None or selection.every != 1:
            frames = (f for f, _ in selection.apply(frames, "the camera's stream"))
        jobs.append(_Job(f"camera {args.camera}".strip(), None, radius, source, eps, (frames, stats)))
    return jobs


def _configs(method: str, extra: dict):
    """config(radius, eps): the detector's configuration for a ball, made and warmed up once each."""
    made: dict = {}

    def config(radius: float, eps: float):
        if (radius, eps) not in made:
            made[radius, eps] = config_for(method, radius_m=radius, eps_m=eps, **extra)
            warm_up(made[radius, eps])  # the kernels' one-off loading is no detection time
        return made[radius, eps]

    return config


def _in_time_order(frames, raw: str):
    """The frames, refused in one line from the first whose timestamp comes before the previous one's
    (tracks follow time)."""
    last = -math.inf
    for frame in frames:
        if frame.timestamp_ms < last:
            raise SphereBenchError(f"{raw}: frame {frame.number}'s timestamp ({frame.timestamp_ms:.3f} ms) comes "
                                   "before the previous frame's: the recording's clock jumps back, and tracks follow "
                                   "time; detect without --track, or select the frames before the jump (--frames)")
        last = frame.timestamp_ms
        yield frame


def _budget(args: argparse.Namespace, stats: depth_frames.StreamStats, live: bool) -> float | None:
    """A stream's per-frame budget, ms: --budget-ms, else where frames come in real time (``live``:
    the camera, --real-time) its frame period; None: no bound (a recording read frame by frame
    waits for the detector, and its output is then the seed's alone)."""
    if args.budget_ms is not None:
        return None if math.isinf(args.budget_ms) else args.budget_ms
    return 1000.0 / stats.fps if live and stats.fps > 0 else None


def _detect_in_stream(args: argparse.Namespace, job: _Job, config, labelme_dir: Path | None, log) -> None:
    """Each frame of a recording or the camera detected (and tracked with --track), printed, and kept
    as LabelMe and in Rerun where asked; the stream's summary at its end."""
    frames, stats = job.streamed
    stem = scene_id_from(job.path.stem) if job.path is not None else f"camera{args.camera or ''}"
    times = array("d")  # floats, not frames: bounded over an hour-long recording
    live = args.real_time or job.path is None
    cfg, budget = config(job.radius, job.eps), _budget(args, stats, live)
    if args.track:  # a tracker per recording: its balls are its own
        results = stream.track_stream(_in_time_order(frames, job.raw), cfg, args.seed, stats, budget)
    else:
        results = stream.detect_stream(frames, cfg, args.seed, stats, budget)
    for r in results:
        frame, spheres = r.frame, r.spheres
        depth_frames.print_notes(stats, f"note: {job.raw}")
        times.append(r.ms)
        extra = {} if budget is None else {"cut_short": r.cut_short}
        if args.track:
            extra.update(search=r.search, tracks=r.tracks)
        _print_result(args, job.raw, spheres, r.ms, job.radius, job.source, frame, **extra)
        _labelme(labelme_dir, f"{stem}_{frame.index:06d}", spheres, frame.intrinsics.shape)
        if log is not None:
            log.frame(job.raw, frame, spheres)
    depth_frames.print_notes(stats, f"note: {job.raw}")
    _stream_summary(job.raw, times, stats, live)


def _detect_in_file(args: argparse.Namespace, job: _Job, config, intr, labelme_dir: Path | None, log) -> None:
    """A cloud or scene folder detected and printed, kept as LabelMe and in Rerun where asked, and
    drawn to --out-ply and --out-png."""
    raw, path = job.raw, job.path
    cloud, behind = in_front_of_camera(inout.load_cloud(path, intr), raw)
    if behind:
        print(f"note: {raw}: {behind} points at z <= 0 left out (a depth camera sees only z > 0)", file=sys.stderr)
    image = _image_for(path, cloud) if args.out_png else None  # before the work: it may be refused
    if labelme_dir is not None and not cloud.organised:
        raise SphereBenchError(f"{raw}: --labelme-out needs an image: an organised cloud with intrinsics")
    cfg = config(job.radius, job.eps)
    t = time.perf_counter()
    spheres = detect(cloud, cfg, seed=args.seed)
    ms = (time.perf_counter() - t) * 1e3
    _print_result(args, raw, spheres, ms, job.radius, job.source)
    if labelme_dir is not None:
        scene_id = scene_id_from(path.name if path.is_dir() else path.stem)
        _labelme(labelme_dir, scene_id, spheres, cloud.intrinsics.shape)
    if log is not None:
        log.cloud(raw, cloud, spheres)
    outputs.replace_files(_drawn_files(args, cloud, spheres, image))


def _drawn_files(args: argparse.Namespace, cloud, spheres, image: np.ndarray | None) -> dict[Path, bytes]:
    """--out-ply (the cloud, inliers red) and --out-png (the circles on the image), to be written
    both or neither."""
    files = {}
    if args.out_ply:
        colours = np.tile(np.array(OTHER_RGB, np.uint8), (len(cloud.points), 1))
        for s in spheres:
            colours[s.inlier_indices] = INLIER_RGB
        keep = np.isfinite(cloud.points).all(axis=1)
        files[Path(args.out_ply)] = inout.encode_ply(cloud.points[keep], colours[keep])
    if args.out_png:
        drawn = draw_detections(image, [s.circle_exact for s in spheres], [s.score for s in spheres])
        files[Path(args.out_png)] = inout.encode_png(drawn, args.out_png, mark=True)
    return files


def run(args: argparse.Namespace) -> int:
    # every argument and input first: nothing is detected, printed or written before all are good
    _check_arguments(args)
    selection = FrameSelection.parse(args.every, args.frames, args.time_range)
    extra = {} if args.depth_noise is None else {"noise": {"noise_z2_per_m": args.depth_noise}}
    if args.min_score is not None:
        extra["verification"] = {"min_score": args.min_score}
    intr = inout.read_intrinsics(args.intrinsics) if args.intrinsics else None
    bad = BadInputs("spherebench detect")
    jobs = _jobs(args, selection, bad)
    log = None
    if args.rerun or args.rerun_save:
        log = viz.RerunLog("spherebench detect", save=args.rerun_save, spawn=args.rerun)
    labelme_ctx = (outputs.atomic_directory(args.labelme_out, outputs.owned_by_kind(LABELME_KIND))
                   if args.labelme_out is not None else contextlib.nullcontext())
    config = _configs(args.method, extra)
    try:
        with contextlib.suppress(_NothingWritten), labelme_ctx as labelme_dir:
            if labelme_dir is not None:
                outputs.write_owner_marker(labelme_dir, LABELME_KIND)
            for job in jobs:
                try:
                    if job.streamed is not None:
                        _detect_in_stream(args, job, config, labelme_dir, log)
                    else:
                        _detect_in_file(args, job, config, intr, labelme_dir, log)
                except (SphereBenchError, OSError) as exc:
                    bad.skip(job.raw, exc)
            if labelme_dir is not None and all(p.name.startswith(".") for p in labelme_dir.iterdir()):
                raise _NothingWritten  # every input refused: no folder holding its markers alone is left
    except BaseException as exc:
        if args.rerun_save and Path(args.rerun_save).exists():  # streamed as it went: what it has is readable
            exc.kept = f"{args.rerun_save} holds what was logged before the stop"
        raise
    finally:
        if log is not None:
            log.close()
    return bad.status
