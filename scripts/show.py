"""``spherebench show DIR/scenes/<id>``: a scene's ground truth, to look at.

Writes a PNG of the reprojected image (image.png) with the ground-truth circles (visible-mask
circle solid green, amodal circle dashed white, a source's reference centre, not ground truth,
as a yellow cross) and a binary PLY of the scene's points with the ball's in red and the rest
grey, for MeshLab. An image-less scene gets the PLY only. Thin driver: the drawing is in
``spherebench.datasets.annotate``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from spherebench.datasets import inout
from spherebench.datasets.annotate import ball_point_colors, draw_ground_truth
from spherebench.errors import SphereBenchError


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("scene", type=Path, help="a scene folder, DIR/scenes/<scene_id>")
    p.add_argument("--out-png", type=Path, help="image with circles (default ./<scene_id>_gt.png)")
    p.add_argument("--out-ply", type=Path, help="coloured cloud (default ./<scene_id>_gt.ply)")
    p.add_argument("--tolerance", type=float, default=0.02,
                   help="image-less scenes: metres beyond the radius round a centre that count as the ball")


def run(args: argparse.Namespace) -> int:
    scene_dir = args.scene
    if not (scene_dir / "gt.json").is_file():
        raise SphereBenchError(f"{scene_dir}: not a scene folder (no gt.json); give DIR/scenes/<scene_id>")
    if inout.read_json(scene_dir / "gt.json").get("has_image", True) and not (scene_dir / "depth.png").is_file():
        raise SphereBenchError(f"depth.png is missing in {scene_dir}: gt.json says the scene has an image, so the "
                               "folder is damaged; rebuild the dataset with the command that wrote it")
    scene = inout.read_scene(scene_dir)
    radius = inout.read_json(scene_dir / "gt.json").get("ball_radius_m")
    image = None if scene.depth is None else inout.read_image(scene_dir)
    if image is not None and image.shape[:2] != scene.depth.shape:  # the circles are in depth.png's pixels
        raise SphereBenchError(f"{scene_dir}: image.png is {image.shape[1]}x{image.shape[0]} but depth.png and the "
                               f"intrinsics are {scene.depth.shape[1]}x{scene.depth.shape[0]}: the circles would be "
                               "drawn off the image; rebuild the dataset with the command that wrote it")
    if image is None and args.out_png:
        raise SphereBenchError(f"{scene_dir}: an image-less scene (a cloud without a camera) has no image; drop --out-png")
    status = "annotated" if scene.annotated else "unannotated (no ground truth)"
    print(f"scene {scene.scene_id}: {status}, {len(scene.balls)} ball(s)")
    if image is not None:
        out_png = args.out_png or Path(f"{scene.scene_id}_gt.png")
        inout.write_png(out_png, draw_ground_truth(image, scene))
        for k, b in enumerate(scene.balls):
            if b.circle_px is not None:
                print(f"  ball {k}: circle ({b.circle_px[0]:.1f}, {b.circle_px[1]:.1f}) r {b.circle_px[2]:.1f} px")
        print(f"wrote {out_png}")
    else:
        print("image-less scene: no image to draw on, writing the PLY only")
    points, colors, how = ball_point_colors(scene, radius, args.tolerance)
    out_ply = args.out_ply or Path(f"{scene.scene_id}_gt.ply")
    inout.write_ply(out_ply, points, colors)
    print(f"wrote {out_ply} ({len(points)} points; {how})")
    return 0
