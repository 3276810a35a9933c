"""`spherebench detect`: find balls of known radius in point clouds or scene folders.

One line per input: with --json, {"input", "spheres": [{"center", "radius", "score", "inliers",
"circle"}], "ms"} (ms: the detection alone, file reading excluded); without, a short summary.
Files are read and written only through ``spherebench.datasets.io``.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import cv2
import numpy as np

from spherebench.datasets import io
from spherebench.datasets.reproject import colorize_depth
from spherebench.errors import SphereBenchError
from spherebench.method import PRESETS, config_for, detect, warm_up

#: --out-ply colours: inliers red, the rest grey (RGB).
INLIER_RGB = (255, 0, 0)
OTHER_RGB = (128, 128, 128)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("paths", nargs="+", metavar="PATH", help="PLY/PCD/XYZ clouds or scene folders")
    p.add_argument("--radius", type=float, default=0.12, help="ball radius, metres (default 0.12: a basketball)")
    p.add_argument("--eps", type=float, default=0.01, help="inlier tolerance around the radius, metres")
    p.add_argument("--method", choices=sorted(PRESETS), default="improved", help="detector configuration")
    p.add_argument("--depth-noise", type=float, default=None, metavar="A",
                   help="the sensor's depth noise as sigma_z = A z^2 (A in 1/m) for organised clouds, in place of "
                        "the D435 stereo model at the stream's fx (0.08 / (fx 0.05 m)); set it for a sensor "
                        "noisier than that (a quieter one is measured from the data)")
    p.add_argument("--intrinsics", default=None, help="intrinsics.json for clouds without their own")
    p.add_argument("--seed", type=int, default=0, help="random seed (same seed, same output)")
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


def _image_for(path: Path, cloud) -> np.ndarray:
    """The reprojected image: a scene folder's image.png, else the organised cloud's depth colourised."""
    if path.is_dir() and (path / "image.png").is_file():
        return io.read_image(path / "image.png")
    if not cloud.organised:
        raise SphereBenchError(f"{path}: --out-png needs an organised cloud with intrinsics (rows, cols) "
                               "or a scene folder with image.png")
    intr = cloud.intrinsics
    depth = np.full(intr.shape, np.nan, np.float32)
    ok = (cloud.rows >= 0) & (cloud.rows < intr.height) & (cloud.cols >= 0) & (cloud.cols < intr.width)
    depth[cloud.rows[ok], cloud.cols[ok]] = cloud.points[ok, 2]
    return colorize_depth(depth)


def run(args: argparse.Namespace) -> int:
    if (args.out_ply or args.out_png) and len(args.paths) != 1:
        raise SphereBenchError("--out-ply and --out-png take one input: give one PATH")
    if not (np.isfinite(args.radius) and args.radius > 0):
        raise SphereBenchError(f"--radius {args.radius}: the ball radius must be > 0 metres (e.g. 0.12)")
    if not (np.isfinite(args.eps) and 0 < args.eps < args.radius):
        raise SphereBenchError(f"--eps {args.eps}: the tolerance must be > 0 and smaller than the radius (e.g. 0.01)")
    if args.depth_noise is not None and not (np.isfinite(args.depth_noise) and args.depth_noise >= 0):
        raise SphereBenchError(f"--depth-noise {args.depth_noise}: give sigma_z / z^2 in 1/m, >= 0 (e.g. 0.0015)")
    extra = {} if args.depth_noise is None else {"noise_z2_per_m": args.depth_noise}
    config = config_for(args.method, radius_m=args.radius, eps_m=args.eps, **extra)
    intr = io.read_intrinsics(args.intrinsics) if args.intrinsics else None
    warm_up(config)  # the kernels' one-off loading is no detection time
    for raw in args.paths:
        path = Path(raw)
        cloud = io.load_cloud(path, intr)
        t = time.perf_counter()
        spheres = detect(cloud, config, seed=args.seed)
        ms = (time.perf_counter() - t) * 1e3
        if args.json:
            rec = {"input": str(raw), "spheres": [{k: v for k, v in s.to_dict().items()
                                                   if k in ("center", "radius", "score", "inliers", "circle")}
                                                  for s in spheres], "ms": round(ms, 3)}
            print(json.dumps(rec), flush=True)
        else:
            parts = [f"({s.center_m[0]:+.3f}, {s.center_m[1]:+.3f}, {s.center_m[2]:.3f}) m score {s.score:.2f} "
                     f"{len(s.inlier_indices)} inliers" for s in spheres]
            print(f"{raw}: {len(spheres)} sphere(s) in {ms:.1f} ms" + (": " + "; ".join(parts) if parts else ""),
                  flush=True)
        if args.out_ply:
            colours = np.tile(np.array(OTHER_RGB, np.uint8), (len(cloud.points), 1))
            for s in spheres:
                colours[s.inlier_indices] = INLIER_RGB
            keep = np.isfinite(cloud.points).all(axis=1)
            io.write_ply(args.out_ply, cloud.points[keep], colours[keep])
        if args.out_png:
            io.write_png(args.out_png, _draw(_image_for(path, cloud), spheres))
    return 0
