"""Recorded depth data -> a SphereBench dataset in the scene format of ``spherebench.datasets.inout``.

The inputs (RealSense recordings, depth PNGs, raw frames, point clouds) are read as frames by
``datasets.frame_sources``, which also checks their units; ``plan_inputs`` picks the reader for
each input, ``prepare`` writes one scene per frame, and the recipes at the end prepare the
recorded sets of ../shared/realdata.

Ground truth comes from mask PNGs or LabelMe files (``spherebench.datasets.annotate``); a
scene without annotation, or whose LabelMe file holds no ball shape, is kept and marked
unannotated; a LabelMe file with no shape at all marks a negative. To annotate a prepared dataset: open
``DIR/scenes/<id>/image.png`` in LabelMe (it saves ``image.json`` beside it), then run the same
``prepare`` command again with ``--labelme DIR``: the files are read before DIR is replaced and
each scene keeps its LabelMe file as ``image.json``.
"""

from __future__ import annotations

import dataclasses
import math
import sys
import time
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from spherebench import __version__, reading
from spherebench.camera import Intrinsics
from spherebench.cloud import depth_to_metres
from spherebench.datasets import foreign_formats, inout, outputs
from spherebench.datasets.annotate import AnnotationIndex, mask_fit_centre
from spherebench.datasets.frame_sources import (FrameSelection, Plan, RawFormat, RecordedFrame, bag_frames, check_units,
                                                cloud_frames, depth_png_frames, files_of, natural_key, raw_frames,
                                                scene_id_from)
from spherebench.datasets.scene import Scene
from spherebench.errors import SphereBenchError
from spherebench.progress import bar as progress_bar

DEFAULT_BALL_RADIUS_M = 0.12


# --------------------------------------------------------------------------- options

@dataclass(frozen=True)
class PrepareOptions:
    """What every input shares. ball_radius_m: the dataset's ball (m). depth_scale: metres per
    unit of the input's depth values (overrides the file's or sensor's; clouds: per coordinate
    unit, default 1). unit_check: refuse depth whose median is outside UNIT_CHECK_RANGE_M."""

    ball_radius_m: float = DEFAULT_BALL_RADIUS_M
    category: str = inout.DEFAULT_CATEGORY
    name: str | None = None
    depth_scale: float | None = None
    unit_check: bool = True
    selection: FrameSelection = field(default_factory=FrameSelection)
    masks_dir: Path | None = None
    labelme_dir: Path | None = None
    label: str | None = None

    def __post_init__(self) -> None:
        reading.check_ball_radius(self.ball_radius_m)
        if self.depth_scale is not None and not (math.isfinite(self.depth_scale) and self.depth_scale > 0):
            raise SphereBenchError(f"--depth-scale must be > 0 metres per unit, got {self.depth_scale}")


@dataclass
class PrepareReport:
    out_dir: Path
    scenes: int
    annotated: int
    balls: int
    image_less: int
    valid_points: list[int]
    seconds: float
    notes: list[str]

    def summary(self) -> str:
        pts = np.asarray(self.valid_points or [0])
        return (f"{self.scenes} scenes ({self.annotated} annotated, {self.balls} balls, {self.image_less} image-less) "
                f"-> {self.out_dir}; valid points per scene: min {pts.min()}, median {int(np.median(pts))}, "
                f"max {pts.max()}; {self.seconds:.1f} s")


# --------------------------------------------------------------------------- planning

def plan_inputs(inputs: list[Path], options: PrepareOptions, intr: Intrinsics | None = None,
                raw: RawFormat = RawFormat()) -> Plan:
    """Frames of the given files and folders, one kind per input, in the order given."""
    if not inputs:
        raise SphereBenchError("no input given: name .bag/.db3 recordings, depth PNGs, clouds or raw frames (or folders)")
    sel = options.selection
    plans = []
    for path in inputs:
        kind, files = files_of(Path(path))
        if sel.time_range_ms is not None and kind != "bag":
            raise SphereBenchError(f"{path}: --time-range needs timestamps, which only recordings (.bag, .db3) have; "
                                   "use --frames A:B")
        if kind == "bag":
            if intr is not None:
                raise SphereBenchError(f"{path}: a recording carries its own intrinsics; drop --intrinsics/--fx...")
            for f in files:
                plans.append(Plan(bag_frames(f, sel, options.depth_scale), None,
                                  {"kind": "realsense-recording", "files": [f.name]}))
        elif kind == "png":
            plans.append(depth_png_frames(files, intr, sel, options.depth_scale))
        elif kind == "raw":
            plans.append(raw_frames(files, raw, intr, sel, options.depth_scale))
        else:
            plans.append(cloud_frames(files, intr, sel, options.depth_scale))
    if len(plans) == 1:
        return plans[0]
    totals = [p.total for p in plans]

    def chain():
        for p in plans:
            yield from p.frames
    return Plan(chain(), None if None in totals else sum(totals), {"kind": "several", "inputs": [p.source for p in plans]},
                [n for p in plans for n in p.notes])


# --------------------------------------------------------------------------- recipes for the real data

#: Kinect-type camera 1 of PoChang007/RGBD_CameraNetwork_Calibration (SOURCE.md: calibrationHandler.cpp).
POCHANG_INTRINSICS = Intrinsics(width=640, height=480, ppx=316.625776542517880, ppy=256.231848585108540,
                                fx=524.639247602080790, fy=523.503043480237810, model="none", depth_scale=0.001)
POCHANG_RADIUS_M = 0.203
SPHERECALIB_RADIUS_M = 0.3


def _pochang_reference(root: Path) -> tuple[dict[int, list[float]], dict[int, float]]:
    """The authors' per-frame RANSAC fit of camera 1: centre (m) and radius (m) by frame index."""
    centres, radii = {}, {}
    path_file, radius_file = root / "tracking" / "path_01.txt", root / "tracking" / "radius_01.txt"
    if path_file.is_file():
        for line in path_file.read_text().splitlines():
            parts = line.split()
            if len(parts) == 4:
                idx, xyz = int(parts[0]), [float(v) / 1000.0 for v in parts[1:]]
                if not (xyz[0] == 0 and xyz[1] == 0 and xyz[2] == -1.0):  # "0 0 -1000": not detected
                    centres[idx] = xyz
    if radius_file.is_file():
        for idx, line in enumerate(radius_file.read_text().splitlines()):
            try:
                radii[idx] = float(line) / 1000.0
            except ValueError:
                pass  # '-------': not detected
    return centres, radii


def plan_kinect_pochang(root: Path, selection: FrameSelection) -> Plan:
    """Camera 1 of the Kinect-type RGB-D set: raw uint16 LE 640x480 depth in mm, 0.203 m ball.

    Each scene keeps the frame's colour JPEG (kinect_1_rgb_NN.jpg, registered to depth) as
    colour.jpg. Without annotation scenes are unannotated; the authors' tracking centre of the
    frame, when they detected the ball, is kept in meta as reference_center_m (their fit, not
    ground truth). The repository's reviewed colour-derived masks: datasets/annotations/kinect-pochang.
    """
    folder = root / "sensors" / "Kinect_1"
    files = sorted(folder.glob("kinect_1_dep_*.dat"), key=natural_key) if folder.is_dir() else []
    if not files:
        raise SphereBenchError(f"{root}: not the pochang_rgbd_sphere folder (no sensors/Kinect_1/kinect_1_dep_*.dat)")
    centres, radii = _pochang_reference(root)
    plan = raw_frames(files, RawFormat(640, 480, "uint16", "little"), POCHANG_INTRINSICS, selection)
    note = ("the dataset authors' RANSAC fit of the ball (tracking/path_01.txt, radius_01.txt): "
            "a reference, NOT ground truth")

    def frames():
        for frame in plan.frames:
            idx = int(frame.scene_id.rsplit("_", 1)[1])
            frame.meta["frame_index"] = idx
            if idx in centres:
                frame.meta["reference_center_m"] = centres[idx]
                if idx in radii:
                    frame.meta["reference_fit_radius_m"] = radii[idx]
                frame.meta["reference_note"] = note
            frame.meta["source"] = f"sensors/Kinect_1/{frame.source}"
            colour = folder / frame.source.replace("_dep_", "_rgb_").rsplit(".", 1)[0]
            frame.colour = colour.with_name(colour.name + ".jpg")
            yield frame
    source = {"kind": "kinect-pochang", "repository": "PoChang007/RGBD_CameraNetwork_Calibration",
              "commit": "28693df8a03b89f89d632cd85a131b565a707177", "licence": "MIT",
              "camera": "Kinect_1 (Kinect-type structured light, depth registered to colour)",
              "files": plan.source["files"], "radius_source": "authors' stated 203 mm"}
    notes = ["kinect-pochang: without --labelme (the reviewed colour-derived masks: datasets/annotations/"
             "kinect-pochang) every scene is unannotated (kept, not scored); reference_center_m in gt.json meta is "
             "the authors' own fit, not ground truth"]
    return Plan(frames(), plan.total, source, notes)


def plan_lidar_spherecalib(root: Path, selection: FrameSelection) -> Plan:
    """The SphereCalib LiDAR scans (.xyz, metres, unorganised, no camera): image-less scenes."""
    files = sorted(root.glob("examples/example*/data3D/*.xyz"), key=lambda p: (p.parts[-3], natural_key(p)))
    if not files:
        raise SphereBenchError(f"{root}: not the spherecalib_lidar folder (no examples/example*/data3D/*.xyz)")
    ids = [scene_id_from(f"{p.parts[-3]}_{p.stem}") for p in files]
    metas = [{"source": "/".join(p.parts[-4:]), "lidar": p.stem.split("_")[0], "scan": p.stem.split("_")[-1]}
             for p in files]
    plan = cloud_frames(files, None, selection, None, ids, metas)
    source = {"kind": "lidar-spherecalib", "repository": "tothtekla/SphereCalib",
              "commit": "1c660fb0da46357c89c5feb50a483dc363e088a9", "licence": "MIT",
              "sensor": "16-beam spinning LiDAR (model not stated)",
              "files": [metas[i]["source"] for i in selection.pick(len(files))],
              "radius_source": "authors: 'around 0.3 meter'"}
    notes = ["lidar-spherecalib: unorganised LiDAR scans with no camera model: kept as image-less scenes "
             "(cloud.ply only); depth.png, image.png, masks, 2D circles and COCO images are skipped",
             "lidar-spherecalib: no centre ground truth: scenes are unannotated; SOURCE.md warns that the best "
             "sphere in example2 L1 scans may be another object (example3 is the cleaner set)"]
    return Plan(plan.frames, plan.total, source, notes)


#: --preset-source NAME -> (planner, folder under shared/realdata, ball radius m, category)
PRESET_SOURCES = {
    "kinect-pochang": (plan_kinect_pochang, "pochang_rgbd_sphere", POCHANG_RADIUS_M, "ball"),
    "lidar-spherecalib": (plan_lidar_spherecalib, "spherecalib_lidar", SPHERECALIB_RADIUS_M, "calibration-sphere"),
}


def default_realdata_dir() -> Path:
    """../shared/realdata beside the repository (where CI checks it out)."""
    return Path(__file__).resolve().parents[1].parent / "shared" / "realdata"


# --------------------------------------------------------------------------- the preparation

def _input_scale(frame: RecordedFrame, options: PrepareOptions) -> float:
    """Metres per unit of the frame's input values, for the unit check's suggestion."""
    if options.depth_scale is not None:
        return options.depth_scale
    if frame.unit_sample_m is not None or frame.depth is None:
        return 1.0  # float inputs: clouds and float32 raw are metres unless told otherwise
    return frame.intrinsics.depth_scale


def _progress(frames: Iterable[RecordedFrame], total: int | None):
    # on a terminal only: the summary on stdout says what was prepared
    return progress_bar(frames, total=total, desc="prepare", unit="frame", leave=False, enabled=None)


def note_to_stderr(text: str) -> None:
    """Notes and warnings go to stderr: stdout is for the result (the summary)."""
    print(text, file=sys.stderr)


def _check_colour(path: Path, shape: tuple[int, int]) -> None:
    """A colour frame must be a readable image of the depth's size (it is registered to it)."""
    image = inout.read_image_as_stored(path)
    if image.shape[:2] != tuple(shape):
        raise SphereBenchError(f"{path}: the colour image is {image.shape[1]}x{image.shape[0]} but the depth is "
                               f"{shape[1]}x{shape[0]}: give colour registered to the depth (the same pixel grid)")


@dataclass
class _Tally:
    """What ``prepare`` counts and notes over the frames: for its notes, dataset.json and report."""

    notes: list[str]
    seen: set[str] = field(default_factory=set)  # scene ids
    annotated: int = 0
    balls: int = 0
    image_less: int = 0
    valid_points: list[int] = field(default_factory=list)
    empty: list[str] = field(default_factory=list)  # scenes without a valid point
    non_finite: dict[str, int] = field(default_factory=dict)  # source -> points with NaN/inf coordinates dropped
    no_colour: list[str] = field(default_factory=list)  # frames without their colour image
    fits: list[float] = field(default_factory=list)  # the mask-fit centres' standard errors (m)
    unfit: list[str] = field(default_factory=list)  # scenes of balls without a fitted centre


def _check_frame_units(frame: RecordedFrame, options: PrepareOptions) -> None:
    """check_units on a frame's valid depth (metres) or, for a cloud, its points' ranges."""
    if frame.depth is None:
        check_units(np.linalg.norm(frame.cloud.points.astype(np.float64), axis=1), frame.source,
                    _input_scale(frame, options), what="range")
        return
    sample = frame.unit_sample_m
    if sample is None:
        sample = frame.depth[frame.depth > 0].astype(np.float64) * frame.intrinsics.depth_scale
    check_units(sample, frame.source, _input_scale(frame, options), "depth", frame.unit_alternatives,
                frame.garbage_hint)


def _kept_colour(frame: RecordedFrame, tally: _Tally) -> Path | np.ndarray | None:
    """The frame's colour frame as its scene keeps it (a file checked, or an image aligned to the
    depth), or None, with the reason in tally.no_colour where the frame has none."""
    colour = frame.colour
    if isinstance(colour, np.ndarray):
        if colour.shape[:2] != frame.depth.shape:  # aligned to the depth by its reader
            raise SphereBenchError(f"{frame.source}: the aligned colour frame is {colour.shape[1]}x"
                                   f"{colour.shape[0]} but the depth is {frame.depth.shape[1]}x"
                                   f"{frame.depth.shape[0]}")
    elif colour is not None and not colour.is_file():
        tally.no_colour.append(str(colour))
        colour = None
    elif colour is not None:
        _check_colour(colour, frame.depth.shape)
    if colour is None and frame.no_colour:
        tally.no_colour.append(f"{frame.scene_id}: {frame.no_colour}")
    return colour


def _fit_centres(frame: RecordedFrame, balls, options: PrepareOptions, tally: _Tally) -> None:
    """Each annotated ball's 3D centre, fitted to its mask's depth pixels (``mask_fit_centre``) and
    noted in the frame's meta; a ball whose mask gives none keeps no centre (tally.unfit)."""
    for ball in balls:
        fit = (mask_fit_centre(depth_to_metres(frame.depth, frame.intrinsics), frame.intrinsics,
                               ball.mask, options.ball_radius_m) if ball.mask is not None else None)
        if fit is None:
            tally.unfit.append(frame.scene_id)
            continue
        ball.centre_m, ball.centre_se_m, ball.centre_source = fit.centre_m, fit.centre_se_m, "mask-fit"
        frame.meta.setdefault("mask_fit", []).append({"rms_m": round(fit.rms_m, 6), "inliers": fit.inliers,
                                                      "points": fit.points})
        tally.fits.append(float(np.linalg.norm(fit.centre_se_m)))


def _keep_labelme(labelme: Path, scene_dir: Path, colour_name: str | None, colour_sources: tuple[str, ...]) -> None:
    """A scene's LabelMe file kept beside the image it was drawn on (image.png, or the colour frame
    when its imagePath names the colour frame as kept or as given: ``colour_sources``), where
    LabelMe looks when that image is reopened."""
    doc = foreign_formats.read_labelme(labelme)
    drawn = Path(str(doc.get("imagePath") or "").replace("\\", "/")).name
    on_colour = colour_name is not None and drawn in (*outputs.COLOUR_FILES, *colour_sources)
    kept = colour_name if on_colour else "image.png"
    doc["imagePath"] = kept
    inout.write_json(scene_dir / (Path(kept).stem + ".json"), doc, indent=2)


def _prepare_frame(frame: RecordedFrame, scenes_dir: Path, annotations: AnnotationIndex, options: PrepareOptions,
                   tally: _Tally) -> None:
    """One frame written as a scene folder under ``scenes_dir``: its units checked, with its colour
    frame, its annotations (and their mask-fit centres) and its LabelMe file; counted in ``tally``."""
    if frame.scene_id in tally.seen:
        raise SphereBenchError(f"{frame.source}: two frames are named scene {frame.scene_id}; "
                               "give inputs whose file names differ")
    tally.seen.add(frame.scene_id)
    if options.unit_check:
        _check_frame_units(frame, options)
    balls = colour = colour_name = None
    colour_sources: tuple[str, ...] = ()  # the names the colour frame goes by (as kept, as given)
    if frame.depth is not None:
        n_valid = int(np.count_nonzero(frame.depth > 0))
        colour = _kept_colour(frame, tally)
        if colour is not None:
            colour_name = inout.colour_file_name(colour)
            colour_sources = (colour_name,) if isinstance(colour, np.ndarray) else (colour.name,)
        balls = annotations.balls_for(frame.scene_id, frame.depth.shape, options.ball_radius_m,
                                      frame.image_names + colour_sources)
        _fit_centres(frame, balls or (), options, tally)
    else:
        n_valid = len(frame.cloud)
        tally.image_less += 1
    tally.notes.extend(n for n in frame.notes if n not in tally.notes)
    if frame.meta.get("non_finite_points_dropped"):
        tally.non_finite[frame.source] = frame.meta["non_finite_points_dropped"]
    if n_valid == 0:
        tally.empty.append(frame.scene_id)
    tally.valid_points.append(n_valid)
    frame.meta["valid_points"] = n_valid
    scene = Scene(scene_id=frame.scene_id, family="recorded", intrinsics=frame.intrinsics, depth=frame.depth,
                  balls=balls or [], seed=None, annotated=balls is not None, cloud=frame.cloud, meta=frame.meta)
    scene_dir = inout.write_scene(scenes_dir, scene, options.ball_radius_m, colour=colour)
    # a LabelMe file is kept even when it held no ball shape: it is the user's work
    labelme = annotations.labelme_file(frame.scene_id) if frame.depth is not None else None
    if labelme is not None:
        _keep_labelme(labelme, scene_dir, colour_name, colour_sources)
    if balls is not None:
        tally.annotated += 1
        tally.balls += len(balls)


def _closing_notes(tally: _Tally, annotations: AnnotationIndex) -> list[str]:
    """The notes said once over all frames: points dropped, annotations' notes, frames without colour
    or valid depth, annotations that applied nowhere."""
    notes = []
    if tally.non_finite:
        first = next(iter(tally.non_finite))
        notes.append(f"{sum(tally.non_finite.values())} point(s) with NaN or infinite coordinates were dropped from "
                     f"{len(tally.non_finite)} cloud(s), e.g. {tally.non_finite[first]} in {first}")
    notes.extend(annotations.notes())
    if tally.no_colour:
        notes.append(f"{len(tally.no_colour)} frame(s) have no colour image (e.g. {tally.no_colour[0]}): "
                     "kept without one")
    if tally.empty:
        notes.append(f"{len(tally.empty)} scene(s) have no valid depth at all (e.g. {tally.empty[0]}): kept, "
                     "but nothing can be found there")
    if tally.image_less and not annotations.empty:
        notes.append("annotations apply to scenes with an image only; image-less scenes stay unannotated")
    unused = annotations.unused()
    if unused:
        notes.append(f"{len(unused)} annotation file(s) matched no selected scene, e.g. {unused[0].name}")
    return notes


def _dataset_meta(plan: Plan, options: PrepareOptions, out_dir: Path, preset: str, tally: _Tally) -> dict:
    """dataset.json of a prepared dataset."""
    meta = {"name": options.name or out_dir.name, "preset": preset, "ball_radius_m": float(options.ball_radius_m),
            "category": options.category, "seed": None, "source": plan.source,
            "scenes": len(tally.seen), "annotated_scenes": tally.annotated, "image_less_scenes": tally.image_less,
            "notes": tally.notes, "versions": {"spherebench": __version__, "format": 1}}
    if tally.fits or tally.unfit:  # said in the dataset, not on the terminal: a 2D annotation needs no 3D centre
        meta["reference_centres"] = {
            "source": "mask-fit", "radius_m": float(options.ball_radius_m), "balls": len(tally.fits),
            "se_median_m": round(float(np.median(tally.fits)), 6) if tally.fits else None,
            "without_centre": len(tally.unfit),
            "rule": "fixed-radius least squares on the mask's depth pixels (eroded 2 px), block-jackknife SE"}
    return meta


def prepare(plan: Plan, out_dir: str | Path, options: PrepareOptions, preset: str = "recorded",
            log=note_to_stderr) -> PrepareReport:
    """Write the plan's frames as a dataset at out_dir, atomically (nothing is left on error).
    Notes (what was dropped or ignored, said once each) are passed to ``log``."""
    t_start = time.perf_counter()
    out_dir = Path(out_dir)
    annotations = AnnotationIndex(options.masks_dir, options.labelme_dir, options.label)
    tally = _Tally(notes=list(plan.notes))
    # annotations read from out_dir itself (the LabelMe round trip) are carried into the new dataset
    carried = options.labelme_dir is not None and Path(options.labelme_dir).resolve() == out_dir.resolve()
    with outputs.atomic_directory(out_dir, lambda d: outputs.replaceable_dataset(d, labelme_carried=carried)) as tmp:
        for frame in _progress(plan.frames, plan.total):
            _prepare_frame(frame, tmp / "scenes", annotations, options, tally)
        if not tally.seen:
            raise SphereBenchError("no frame was selected: check --frames, --every and --time-range against the input")
        tally.notes.extend(_closing_notes(tally, annotations))
        inout.finish_dataset(tmp, _dataset_meta(plan, options, out_dir, preset, tally))
    for n in tally.notes:
        log(f"note: {n}")
    return PrepareReport(out_dir, len(tally.seen), tally.annotated, tally.balls, tally.image_less,
                         tally.valid_points, time.perf_counter() - t_start, tally.notes)


def prepare_preset_source(name: str, out_dir: str | Path, root: str | Path | None = None,
                          options: PrepareOptions | None = None, log=note_to_stderr) -> PrepareReport:
    """One command per real data set: ``name`` is a key of PRESET_SOURCES; root defaults to
    ../shared/realdata/<folder> beside the repository. options: frame selection, annotation
    folders, and a radius overriding the set's own (defaults: the set's radius and category)."""
    if name not in PRESET_SOURCES:
        raise SphereBenchError(f"unknown --preset-source '{name}' (one of {', '.join(PRESET_SOURCES)})")
    planner, folder, radius, category = PRESET_SOURCES[name]
    root = Path(root) if root is not None else default_realdata_dir() / folder
    if not root.is_dir():
        raise SphereBenchError(f"{root}: folder not found; give the path of the {folder} data")
    options = options or PrepareOptions(ball_radius_m=radius, category=category)
    plan = planner(root, options.selection)
    return prepare(plan, out_dir, dataclasses.replace(options, name=options.name or name), preset=name, log=log)

