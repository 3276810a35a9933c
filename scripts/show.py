"""``spherebench show DIR/scenes/<id>``: a scene's ground truth, and a method's detections, to look at.

Writes a PNG of the reprojected image (image.png) with the ground-truth circles (visible-mask
circle solid green, amodal circle dashed white, a source's reference centre, not ground truth,
as a yellow cross) and a binary PLY of the scene's points with the ball's in red and the rest
grey, for MeshLab. With --predictions FILE (a predictions file of `evaluate`, a COCO results
list) or --method NAME (results/predictions/<dataset>/<NAME>.json), the method's circles on
this scene are drawn too, magenta, each with its score. An image-less scene gets the PLY only.
Thin driver: the drawing is in ``spherebench.datasets.annotate``.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

from spherebench import options, reading
from spherebench.camera import MAX_IMAGE_SIDE_PX
from spherebench.datasets import inout, outputs
from spherebench.datasets.drawing import ball_point_colours, draw_detections, draw_ground_truth
from spherebench.errors import SphereBenchError


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("scene", type=Path, help="a scene folder, DIR/scenes/<scene_id>")
    p.add_argument("--out-png", help="image with circles (default ./<scene_id>_gt.png)")
    p.add_argument("--out-ply", help="coloured cloud (default ./<scene_id>_gt.ply)")
    p.add_argument("--tolerance", type=options.length, default=0.02,
                   help="image-less scenes: metres beyond the radius round a centre that count as the ball")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--predictions", type=Path, metavar="FILE",
                   help="also draw a method's circles with their scores: a predictions file of `evaluate` "
                        "(a COCO results list with circle_center, circle_radius, score)")
    g.add_argument("--method", metavar="NAME",
                   help="the same, from RESULTS/predictions/<dataset>/<NAME>.json (e.g. improved, circlenet)")
    p.add_argument("--results", type=Path, default=Path("results"), metavar="RESULTS",
                   help="the results folder of --method (default: results)")
    p.add_argument("--min-score", type=options.fraction, default=0.3, metavar="S",
                   help="draw detections scoring at least S (default 0.3; mAP files hold every score)")
    p.add_argument("--force", action="store_true",
                   help="replace an existing --out-png/--out-ply that SphereBench did not write")


def _predictions_file(args, scene_dir: Path) -> Path | None:
    if args.method:
        path = args.results / "predictions" / scene_dir.resolve().parent.parent.name / f"{args.method}.json"
        if not path.is_file():
            raise SphereBenchError(f"--method {args.method}: {path} not found (run `spherebench evaluate`, or give "
                                   "--results RESULTS or --predictions FILE)")
        return path
    if args.predictions is not None and not args.predictions.is_file():
        raise SphereBenchError(f"--predictions {args.predictions}: file not found")
    return args.predictions


#: What show reads of each result of a predictions file (COCO results with CircleNet's circle).
PREDICTION_SCHEMA = {"circle_center": "xy", "circle_radius": "length", "score": "number"}


def scene_predictions(path: Path, scene_id: str, min_score: float) -> list[tuple[tuple[float, float, float], float]]:
    """((cx, cy, r) px, score) of a predictions file's detections on one scene, best first."""
    results = inout.read_json(path)
    if not isinstance(results, list):
        raise SphereBenchError(f"{path}: not a predictions file (a COCO results list)")
    found = []
    for i, r in enumerate(results):
        if not isinstance(r, dict) or r.get("scene_id") != scene_id:
            continue
        reading.check_schema(path, r, PREDICTION_SCHEMA, "fix the file", f"result {i}")
        (cx, cy), rad, score = r["circle_center"], r["circle_radius"], float(r["score"])
        circle = (float(cx), float(cy), float(rad))
        # a circle is drawn in pixels: finite, and a radius no larger than a frame's side
        if not (all(math.isfinite(v) for v in (*circle, score)) and 0 <= circle[2] <= MAX_IMAGE_SIDE_PX
                and max(abs(circle[0]), abs(circle[1])) <= 4 * MAX_IMAGE_SIDE_PX):
            raise SphereBenchError(f"{path}: result {i} has a circle or score that is not a finite pixel circle "
                                   f"({r['circle_center']}, {r['circle_radius']}, {r['score']}); fix the file")
        if score >= min_score:
            found.append((circle, score))
    return sorted(found, key=lambda d: -d[1])


def run(args: argparse.Namespace) -> int:
    scene_dir = args.scene
    if not (scene_dir / "gt.json").is_file():
        raise SphereBenchError(f"{scene_dir}: not a scene folder (no gt.json); give DIR/scenes/<scene_id>")
    if inout.read_scene_gt(scene_dir).get("has_image", True) and not (scene_dir / "depth.png").is_file():
        raise SphereBenchError(f"depth.png is missing in {scene_dir}: gt.json says the scene has an image, so the "
                               "folder is damaged; rebuild the dataset with the command that wrote it")
    inout.scene_dataset_meta(scene_dir)  # not used, but a damaged dataset.json is refused, never passed over
    scene = inout.read_scene(scene_dir)
    radius = inout.read_scene_gt(scene_dir).get("ball_radius_m")
    image = None if scene.depth is None else inout.read_image(scene_dir)
    if image is not None and image.shape[:2] != scene.depth.shape:  # the circles are in depth.png's pixels
        raise SphereBenchError(f"{scene_dir}: image.png is {image.shape[1]}x{image.shape[0]} but depth.png and the "
                               f"intrinsics are {scene.depth.shape[1]}x{scene.depth.shape[0]}: the circles would be "
                               "drawn off the image; rebuild the dataset with the command that wrote it")
    if image is None and args.out_png:
        raise SphereBenchError(f"{scene_dir}: an image-less scene (a cloud without a camera) has no image; drop --out-png")
    pred_file = _predictions_file(args, scene_dir)
    detections = [] if pred_file is None else scene_predictions(pred_file, scene.scene_id, args.min_score)
    if pred_file is not None and image is None:
        raise SphereBenchError(f"{scene_dir}: an image-less scene has no image to draw detections on")
    # checked before any work: never a file of a dataset or the user's; both written or neither
    outs = {"--out-ply": Path(f"{scene.scene_id}_gt.ply") if args.out_ply is None else args.out_ply}
    if image is not None:
        outs = {"--out-png": Path(f"{scene.scene_id}_gt.png") if args.out_png is None else args.out_png, **outs}
    outs = outputs.check_output_files(outs, [scene_dir, *([pred_file] if pred_file else [])], args.force)
    files = {}
    status = "annotated" if scene.annotated else "unannotated (no ground truth)"
    print(f"scene {scene.scene_id}: {status}, {len(scene.balls)} ball(s)")
    if image is not None:
        out_png = outs["--out-png"]
        drawn = draw_ground_truth(image, scene)
        if pred_file is not None:
            label = args.method or ""
            drawn = draw_detections(drawn, [c for c, _ in detections], [s for _, s in detections], label=label)
        files[out_png] = inout.encode_png(drawn, str(out_png), mark=True)
        for k, b in enumerate(scene.balls):
            if b.circle_px is not None:
                print(f"  ball {k}: circle ({b.circle_px[0]:.1f}, {b.circle_px[1]:.1f}) r {b.circle_px[2]:.1f} px")
        for k, (c, score) in enumerate(detections):
            print(f"  detection {k}: circle ({c[0]:.1f}, {c[1]:.1f}) r {c[2]:.1f} px, score {score:.2f}")
        if pred_file is not None:
            print(f"  {len(detections)} detection(s) of {pred_file} scoring >= {args.min_score:g}")
    else:
        print("image-less scene: no image to draw on, writing the PLY only")
    points, colours, how = ball_point_colours(scene, radius, args.tolerance)
    out_ply = outs["--out-ply"]
    files[out_ply] = inout.encode_ply(points, colours)
    outputs.replace_files(files)
    if image is not None:
        print(f"wrote {out_png}")
    print(f"wrote {out_ply} ({len(points)} points; {how})")
    return 0
