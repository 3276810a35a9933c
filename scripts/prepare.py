"""``spherebench prepare``: recorded depth data (.bag/.db3, depth PNGs, PLY/PCD/XYZ, raw) -> a dataset.

Examples::

    spherebench prepare rec.bag --out data/mine --every 10
    spherebench prepare pngs/ --intrinsics camera.json --masks masks/ --out data/mine
    spherebench prepare frames/ --raw-size 640x480 --fx 525 --fy 525 --ppx 319.5 --ppy 239.5 --out data/mine
    spherebench prepare --preset-source kinect-pochang --out data/real/kinect-pochang

Thin driver: the work is in ``spherebench.datasets.prepare``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from spherebench.datasets import frame_sources, outputs
from spherebench.datasets import prepare as prep
from spherebench.errors import SphereBenchError
from spherebench.options import out_path


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.formatter_class = argparse.RawDescriptionHelpFormatter
    p.epilog = ("Annotate in LabelMe: open OUT/scenes/<id>/image.png, draw circles or polygons round each ball, "
                "save, then rerun the same command with --labelme OUT. Other shapes (rectangles, points, "
                "lines, ...) and, with --label, other labels are ignored; a file holding only those leaves its "
                "scene unannotated, while a file with no shape at all marks a negative (no ball). "
                "The summary goes to stdout, notes to stderr.")
    p.add_argument("inputs", nargs="*", type=Path, help="recordings, files or folders (one kind per folder); "
                   "with --preset-source: the data folder (default ../shared/realdata/<set>)")
    p.add_argument("--out", type=out_path, required=True, help="dataset folder to write (replaced atomically)")
    p.add_argument("--preset-source", choices=sorted(prep.PRESET_SOURCES),
                   help="prepare one of the real data sets of shared/realdata with its own settings")
    g = p.add_argument_group("dataset")
    g.add_argument("--radius", type=float, default=None,
                   help=f"ball radius in metres (default {prep.DEFAULT_BALL_RADIUS_M}; a preset source's own)")
    g.add_argument("--category", default=None, help="category name in coco_gt.json (default basketball)")
    g.add_argument("--name", default=None, help="dataset name (default: the output folder's name)")
    g = p.add_argument_group("frames")
    g.add_argument("--every", type=int, default=1, metavar="N", help="keep every N-th selected frame")
    g.add_argument("--frames", metavar="A:B", help="frame indices A (inclusive) to B (exclusive), from 0")
    g.add_argument("--time-range", metavar="T0:T1", help="recordings: ms from the first depth frame, inclusive")
    g = p.add_argument_group("camera and units")
    g.add_argument("--intrinsics", type=Path, metavar="FILE",
                   help="JSON with width, height, ppx, ppy, fx, fy[, model, coeffs, depth_scale] (pyrealsense2 names)")
    for name in ("fx", "fy", "ppx", "ppy"):
        g.add_argument(f"--{name}", type=float, help=f"intrinsics {name} in pixels (instead of --intrinsics)")
    g.add_argument("--size", metavar="WxH", help="image size for --fx... when there is no --raw-size")
    g.add_argument("--model", default="none", help="distortion model with --fx... (none, brown_conrady, ...)")
    g.add_argument("--coeffs", type=float, nargs=5, metavar="K", help="five distortion coefficients with --fx...")
    g.add_argument("--depth-scale", type=float, metavar="M",
                   help="metres per unit of the input depth (default: the file's or sensor's; 0.001 for uint16 "
                        "PNG/raw; 1 for float32 raw and clouds)")
    g.add_argument("--skip-unit-check", action="store_true",
                   help=f"accept a median depth outside {frame_sources.UNIT_CHECK_RANGE_M[0]:g}-{frame_sources.UNIT_CHECK_RANGE_M[1]:g} m")
    g = p.add_argument_group("raw frames")
    g.add_argument("--raw-size", metavar="WxH", help="size of headerless frames (default: the intrinsics')")
    g.add_argument("--raw-dtype", choices=("uint16", "float32"), default="uint16")
    g.add_argument("--raw-byte-order", choices=("little", "big"), default="little")
    g = p.add_argument_group("ground truth")
    g.add_argument("--masks", type=Path, metavar="DIR", help="mask PNGs <scene_id>.png or <scene_id>_<k>.png")
    g.add_argument("--labelme", type=Path, metavar="DIR",
                   help="LabelMe files <scene_id>.json or <scene_id>/image.json (a prepared dataset works)")
    g.add_argument("--label", default=None, help="LabelMe: use only shapes with this label (default: all)")


def run(args: argparse.Namespace) -> int:
    # the output never replaces, contains or lies inside what is read (--labelme OUT is the round trip)
    sources = [*args.inputs, *(p for p in (args.masks, args.intrinsics) if p is not None)]
    if args.preset_source and not args.inputs:
        sources.append(prep.default_realdata_dir() / prep.PRESET_SOURCES[args.preset_source][1])
    outputs.check_output_dir(args.out, outputs.is_dataset_dir, inputs=sources)
    outputs.check_not_in_dataset(args.out)
    selection = frame_sources.FrameSelection.parse(args.every, args.frames, args.time_range)
    common = dict(depth_scale=args.depth_scale, unit_check=not args.skip_unit_check, selection=selection,
                  masks_dir=args.masks, labelme_dir=args.labelme, label=args.label, name=args.name)
    if args.preset_source:
        _, _, radius, category = prep.PRESET_SOURCES[args.preset_source]
        if len(args.inputs) > 1:
            raise SphereBenchError("--preset-source takes at most one input: the data set's folder")
        camera_given = args.intrinsics or any(getattr(args, k) is not None for k in ("fx", "fy", "ppx", "ppy"))
        if camera_given or args.raw_size or args.depth_scale is not None:
            raise SphereBenchError("--preset-source sets the camera and units itself; drop the camera options")
        options = prep.PrepareOptions(ball_radius_m=args.radius if args.radius is not None else radius,
                                      category=args.category or category, **common)
        report = prep.prepare_preset_source(args.preset_source, args.out, args.inputs[0] if args.inputs else None,
                                            options)
    else:
        options = prep.PrepareOptions(ball_radius_m=args.radius if args.radius is not None else prep.DEFAULT_BALL_RADIUS_M,
                                      category=args.category or "basketball", **common)
        if args.size and args.raw_size:
            raise SphereBenchError("give the image size once: --raw-size (raw frames; it also sizes --fx...) "
                                   "or --size, not both")
        raw = frame_sources.RawFormat.parse(args.raw_size, args.raw_dtype, args.raw_byte_order)
        size = frame_sources.RawFormat.parse(args.size, option="--size") if args.size else raw
        intr = frame_sources.camera_from_options(args.intrinsics, args.fx, args.fy, args.ppx, args.ppy, size.width,
                                        size.height, args.model, args.coeffs,
                                        size_option="--size" if args.size else "--raw-size")
        report = prep.prepare(prep.plan_inputs(args.inputs, options, intr, raw), args.out, options)
    print(report.summary())  # the result, on stdout; notes went to stderr
    return 0
