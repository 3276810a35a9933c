"""`spherebench detect`: find balls of known radius in point clouds or scene folders.

One line per input: with --json, {"input", "radius_m", "radius_source", "spheres": [{"center",
"radius", "score", "inliers", "circle"}], "ms"} (ms: the detection alone, file reading excluded);
without, a short summary. The ball radius is --radius, else the dataset's (dataset.json two levels
above a scene folder), else the scene's (gt.json), else 0.12 m (a basketball); radius_source says
which ("--radius", "dataset", "scene", "default"). Every argument and input is checked before the
first detection. Files are read and written only through ``spherebench.datasets.inout``.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import cv2
import numpy as np

from spherebench import options
from spherebench.cloud import in_front_of_camera
from spherebench.datasets import inout
from spherebench.datasets.reproject import colorize_depth
from spherebench.errors import SphereBenchError
from spherebench.method import PRESETS, config_for, detect, warm_up

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
    p.add_argument("paths", nargs="+", metavar="PATH", help="PLY/PCD/XYZ clouds or scene folders")
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
    p.add_argument("--intrinsics", default=None, help="intrinsics.json for clouds without their own")
    p.add_argument("--seed", type=options.seed, default=0, help="random seed (same seed, same output)")
    p.add_argument("--json", action="store_true", help="one JSON line per input")
    p.add_argument("--out-ply", default=None, help="write the cloud with the inliers in red (one input only)")
    p.add_argument("--out-png", default=None,
                   help="draw the circles on the reprojected image (one input only; needs intrinsics)")


def _draw(image: np.ndarray, spheres) -> np.ndarray:
    out = image.copy()
    for k, s in enumerate(spheres):
        if s.circle_exact is None:
            continue
        cx, cy, r = s.circle_exact
        colour = (255, 255, 255) if k == 0 else (200, 200, 200)
        # sub-pixel drawing: OpenCV takes fixed-point coordinates with `shift` fractional bits
        sh = 4
        cv2.circle(out, (int(round(cx * 16)), int(round(cy * 16))), max(1, int(round(r * 16))), colour, 2,
                   cv2.LINE_AA, sh)
        cv2.drawMarker(out, (int(round(cx)), int(round(cy))), colour, cv2.MARKER_CROSS, 6, 1)
    return out


def _scene_dir(path: Path) -> Path | None:
    """The scene folder a path belongs to: the folder itself, or the folder of a scene's cloud.ply."""
    folder = path if path.is_dir() else path.parent
    return folder if (folder / "gt.json").is_file() and (path.is_dir() or path.name == "cloud.ply") else None


def _radius_of(value, where: Path) -> float:
    try:
        r = float(value)
    except (TypeError, ValueError):
        r = math.nan
    if not (math.isfinite(r) and r > 0):
        raise SphereBenchError(f"{where}: ball_radius_m {value!r} is not a radius in metres; fix the file or "
                               "give --radius")
    return r


def ball_radius(path: Path, given: float | None) -> tuple[float, str]:
    """(radius m, its source) for one input: --radius, the dataset's, the scene's or the default."""
    if given is not None:
        return given, "--radius"
    scene = _scene_dir(path)
    if scene is None:
        return DEFAULT_RADIUS_M, "default"
    meta = scene.parent.parent / "dataset.json"
    if scene.parent.name == "scenes" and meta.is_file():
        d = inout.read_json(meta)
        if isinstance(d, dict) and d.get("ball_radius_m") is not None:
            return _radius_of(d["ball_radius_m"], meta), "dataset"
    gt = inout.read_json(scene / "gt.json")
    if isinstance(gt, dict) and gt.get("ball_radius_m") is not None:
        return _radius_of(gt["ball_radius_m"], scene / "gt.json"), "scene"
    return DEFAULT_RADIUS_M, "default"


def _check_input(path: Path) -> None:
    """What can be told of an input without reading it: it exists and is a cloud or a scene folder."""
    if path.is_dir():
        if (path / "scenes").is_dir() and not (path / "cloud.ply").is_file():
            raise SphereBenchError(f"{path} is a dataset: give its scene folders ({path}/scenes/*)")
        return  # inout.load_cloud says what a folder lacks
    if not path.exists():
        raise SphereBenchError(f"{path}: file not found")
    if path.suffix.lower() not in inout.CLOUD_READERS:
        raise SphereBenchError(f"{path}: unknown point-cloud format '{path.suffix}' "
                               f"(use {', '.join(sorted(inout.CLOUD_READERS))} or a scene folder)")


def _check_outputs(args: argparse.Namespace) -> None:
    outs = {name: Path(p) for name, p in (("--out-ply", args.out_ply), ("--out-png", args.out_png)) if p}
    if outs and len(args.paths) != 1:
        raise SphereBenchError("--out-ply and --out-png take one input: give one PATH")
    source = Path(args.paths[0]).resolve()
    for name, out in outs.items():
        if out.is_dir():
            raise SphereBenchError(f"{name} {out} is a folder: give a file name")
        if out.resolve() == source:
            raise SphereBenchError(f"{name} {out} is the input: give another file name")
        if source.is_dir() and source in out.resolve().parents:  # a scene's own files are not ours to write
            raise SphereBenchError(f"{name} {out} is inside the input scene folder: write it elsewhere")
    if len(outs) == 2 and outs["--out-ply"].resolve() == outs["--out-png"].resolve():
        raise SphereBenchError("--out-ply and --out-png name the same file: give two names")


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
        image = inout.read_image(path / "image.png")
        intr = cloud.intrinsics
        if intr is not None and image.shape[:2] != intr.shape:
            raise SphereBenchError(f"{path}: image.png is {image.shape[1]}x{image.shape[0]} but the intrinsics say "
                                   f"{intr.width}x{intr.height}: the circles would be drawn off the image")
        return image
    if not cloud.organised:
        raise SphereBenchError(f"{path}: --out-png needs an organised cloud with intrinsics (rows, cols) "
                               "or a scene folder with image.png")
    intr = cloud.intrinsics
    depth = np.full(intr.shape, np.nan, np.float32)
    ok = (cloud.rows >= 0) & (cloud.rows < intr.height) & (cloud.cols >= 0) & (cloud.cols < intr.width)
    depth[cloud.rows[ok], cloud.cols[ok]] = cloud.points[ok, 2]
    return colorize_depth(depth)


def run(args: argparse.Namespace) -> int:
    # every argument and input first: nothing is detected, printed or written before all are good
    if args.radius is not None and not (np.isfinite(args.radius) and args.radius > 0):
        raise SphereBenchError(f"--radius {args.radius}: the ball radius must be > 0 metres (e.g. 0.12)")
    if args.depth_noise is not None and not (np.isfinite(args.depth_noise) and args.depth_noise >= 0):
        raise SphereBenchError(f"--depth-noise {args.depth_noise}: give sigma_z / z^2 in 1/m, >= 0 (e.g. 0.0015)")
    _check_outputs(args)
    extra = {} if args.depth_noise is None else {"noise_z2_per_m": args.depth_noise}
    intr = inout.read_intrinsics(args.intrinsics) if args.intrinsics else None
    jobs = []
    for raw in args.paths:
        path = Path(raw)
        _check_input(path)
        radius, source = ball_radius(path, args.radius)
        jobs.append((raw, path, radius, source, _tolerance(args, radius, source, raw)))
    configs: dict = {}
    for raw, path, radius, source, eps in jobs:
        cloud, behind = in_front_of_camera(inout.load_cloud(path, intr), raw)
        if behind:
            print(f"note: {raw}: {behind} points at z <= 0 left out (a depth camera sees only z > 0)",
                  file=sys.stderr)
        image = _image_for(path, cloud) if args.out_png else None  # before the work: it may be refused
        if (radius, eps) not in configs:
            configs[radius, eps] = config_for(args.method, radius_m=radius, eps_m=eps, **extra)
            warm_up(configs[radius, eps])  # the kernels' one-off loading is no detection time
        t = time.perf_counter()
        spheres = detect(cloud, configs[radius, eps], seed=args.seed)
        ms = (time.perf_counter() - t) * 1e3
        if args.json:
            rec = {"input": str(raw), "radius_m": radius, "radius_source": source,
                   "spheres": [{k: v for k, v in s.to_dict().items()
                                if k in ("center", "radius", "score", "inliers", "circle")} for s in spheres],
                   "ms": round(ms, 3)}
            print(json.dumps(rec), flush=True)
        else:
            parts = [f"({s.center_m[0]:+.3f}, {s.center_m[1]:+.3f}, {s.center_m[2]:.3f}) m score {s.score:.2f} "
                     f"{len(s.inlier_indices)} inliers" for s in spheres]
            print(f"{raw}: {len(spheres)} sphere(s) of radius {radius:g} m ({RADIUS_SOURCES[source]}) in {ms:.1f} ms"
                  + (": " + "; ".join(parts) if parts else ""), flush=True)
        if args.out_ply:
            colours = np.tile(np.array(OTHER_RGB, np.uint8), (len(cloud.points), 1))
            for s in spheres:
                colours[s.inlier_indices] = INLIER_RGB
            keep = np.isfinite(cloud.points).all(axis=1)
            inout.write_ply(args.out_ply, cloud.points[keep], colours[keep])
        if args.out_png:
            inout.write_png(args.out_png, _draw(image, spheres))
    return 0
