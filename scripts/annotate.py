"""``spherebench annotate DATASET --from-colour``: ball masks of recorded frames from their colour.

    spherebench annotate DATASET --from-colour [--hsv H0:H1,S0:S1,V0:V1] [--label ball] [--overwrite]
    spherebench annotate DATASET --sheet DIR            (review sheets of the annotations as they are)

For every scene of a prepared dataset that kept its colour frame (colour.jpg or colour.png,
registered to depth: ``prepare`` keeps it for sources that record colour, the kinect-pochang set
and RealSense recordings with a colour stream), the ball's mask is taken from an
HSV range (default a saturated yellow, 18:40,100:255,80:255 on OpenCV's scale: H 0-179), as the
largest connected component of the ball's expected size at its depth, holes filled; a hand or a
stick in front is not of that colour and stays out. Its outline is written as a LabelMe polygon
beside the colour frame, ``scenes/<id>/colour.json``; a frame where nothing fits gets no file
and stays unannotated (said once). Review them in LabelMe (open colour.jpg / colour.png), then
``spherebench prepare ... --labelme DATASET --out DATASET`` reads them as ground truth.

--sheet DIR: PNG pages of every annotated scene for review by eye: the mask over the colour
frame and over the reprojected depth image (overview_NN.png), and close-ups round the ball
(closeup_NN.png), with the mask's circle (green) and the mask-fit sphere (yellow).
Thin driver: the rule, the files and the drawing are in ``spherebench.datasets.annotate``.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np

from spherebench import reading
from spherebench.cloud import depth_to_metres
from spherebench.datasets import foreign_formats, inout, outputs
from spherebench.datasets.annotate import (DEFAULT_HSV, LABELME_OFFSET_PX, colour_mask, labelme_from_mask, labelme_text,
                                           mask_fit_centre, parse_hsv, polygon_mask)
from spherebench.datasets.drawing import contact_sheet, review_tile
from spherebench.errors import SphereBenchError

SHEET_KIND = "annotate-sheets"
#: review sheets: scenes per page, columns, close-up side (px of the frame), overview scale
PAGE_SCENES, PAGE_COLUMNS, CLOSEUP_PX, OVERVIEW_SCALE = 12, 3, 160, 0.3


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("dataset", type=Path, help="a prepared dataset folder (its scenes keep colour.jpg or colour.png)")
    p.add_argument("--from-colour", action="store_true",
                   help="write each frame's ball mask from its colour as scenes/<id>/colour.json (LabelMe)")
    hsv = ",".join(f"{a}:{b}" for a, b in DEFAULT_HSV)
    p.add_argument("--hsv", default=hsv, metavar="H0:H1,S0:S1,V0:V1",
                   help=f"the ball's colour range, OpenCV's HSV scale (H 0-179, S, V 0-255; default {hsv}: yellow)")
    p.add_argument("--label", default="ball", help="the LabelMe label of the ball's polygon (default ball)")
    p.add_argument("--radius", type=float, default=None,
                   help="ball radius, metres (default: the dataset's ball_radius_m)")
    p.add_argument("--overwrite", action="store_true",
                   help="replace colour.json files that exist (they may hold a person's corrections)")
    p.add_argument("--sheet", type=Path, default=None, metavar="DIR",
                   help="also write review sheets (PNG pages) of the scenes' annotations to DIR")


def _scenes_with_colour(dataset: Path) -> list[tuple[Path, Path]]:
    """(scene folder, colour frame) of every scene with an image; refuses a dataset without colour."""
    scenes = [s for s in inout.list_scenes(dataset) if (s / "depth.png").is_file()]
    if not scenes:
        raise SphereBenchError(f"{dataset}: no scene has a depth image (image-less scenes cannot be annotated)")
    found = [(s, next((s / n for n in outputs.COLOUR_FILES if (s / n).is_file()), None)) for s in scenes]
    missing = [s for s, c in found if c is None]
    if len(missing) == len(found):
        raise SphereBenchError(f"{dataset}: no scene holds a colour frame ({' or '.join(outputs.COLOUR_FILES)}); prepare "
                               "keeps one for sources that record colour registered to depth")
    if missing:
        raise SphereBenchError(f"{missing[0]}: no colour frame ({len(missing)} of {len(found)} scenes lack one); "
                               "prepare the dataset again from its source")
    return found


def _load(scene: Path, colour_path: Path):
    """(colour BGR, depth m, intrinsics) of a scene, the colour checked against the depth's size."""
    intr = inout.read_intrinsics(scene / "intrinsics.json")
    depth = inout.read_depth_png(scene / "depth.png")
    colour = inout.read_image(colour_path)
    if colour.shape[:2] != depth.shape:
        raise SphereBenchError(f"{colour_path}: the colour frame is {colour.shape[1]}x{colour.shape[0]} but the depth is "
                               f"{depth.shape[1]}x{depth.shape[0]}: it is not registered to the depth")
    return colour, depth_to_metres(depth, intr), intr


def _labelme_mask(path: Path, shape) -> np.ndarray | None:
    """The union of a LabelMe file's polygons (None: no polygon, or no file)."""
    if not path.is_file():
        return None
    doc = foreign_formats.read_labelme(path)
    mask = np.zeros(shape, bool)
    for s in doc["shapes"]:
        if (s.get("shape_type") or "polygon") == "polygon":
            mask |= polygon_mask(np.asarray(s["points"], np.float64) + LABELME_OFFSET_PX, shape)
    return mask if mask.any() else None


def write_sheets(out: Path, scenes: list[tuple[Path, Path]], radius_m: float) -> list[Path]:
    """Review pages of the scenes' colour.json masks (see the module's doc), atomically into out."""
    overview, closeup = [], []
    for scene, colour_path in scenes:
        colour, depth_m, intr = _load(scene, colour_path)
        depth_image = inout.read_image(scene / "image.png")
        mask = _labelme_mask(scene / "colour.json", depth_m.shape)
        fit = mask_fit_centre(depth_m, intr, mask, radius_m) if mask is not None else None
        centre = fit.centre_m if fit is not None else None
        title = scene.name + ("" if mask is not None else "  (no mask)") + (
            f"  fit se {1000 * math.hypot(*fit.centre_se_m):.1f} mm rms {1000 * fit.rms_m:.1f} mm" if fit else "")
        overview.append(review_tile(colour, depth_image, mask, title, intr, centre, radius_m, scale=OVERVIEW_SCALE))
        if mask is not None:
            closeup.append(review_tile(colour, depth_image, mask, scene.name, intr, centre, radius_m, CLOSEUP_PX))
    written = []
    with outputs.atomic_directory(out, outputs.owned_by_kind(SHEET_KIND)) as tmp:
        outputs.write_owner_marker(tmp, SHEET_KIND)
        for name, tiles in (("overview", overview), ("closeup", closeup)):
            for page, start in enumerate(range(0, len(tiles), PAGE_SCENES), 1):
                inout.write_png(tmp / f"{name}_{page:02d}.png",
                             contact_sheet(tiles[start:start + PAGE_SCENES], PAGE_COLUMNS))
                written.append(out / f"{name}_{page:02d}.png")
    return written


def run(args: argparse.Namespace) -> int:
    if not args.from_colour and args.sheet is None:
        raise SphereBenchError("say what to do: --from-colour (masks from the colour frames) and/or --sheet DIR")
    hsv = parse_hsv(args.hsv)
    if not outputs.is_dataset_dir(args.dataset):
        raise SphereBenchError(f"{args.dataset}: not a dataset (no dataset.json); prepare one with `spherebench prepare`")
    radius = (reading.check_ball_radius(args.radius) if args.radius is not None
              else inout.read_dataset_meta(args.dataset).get("ball_radius_m"))
    if radius is None:
        raise SphereBenchError(f"{args.dataset}/dataset.json gives no ball_radius_m: give --radius")
    if not args.label.strip():
        raise SphereBenchError("--label is empty: give the ball's label, e.g. ball")
    scenes = _scenes_with_colour(args.dataset)
    if args.sheet is not None:
        outputs.check_output_dir(args.sheet, outputs.owned_by_kind(SHEET_KIND), "--sheet", inputs=(args.dataset,))
    if args.from_colour:
        existing = [s / "colour.json" for s, _ in scenes if (s / "colour.json").is_file()]
        if existing and not args.overwrite:
            raise SphereBenchError(f"{existing[0]} exists ({len(existing)} scene(s) have colour.json), perhaps with a "
                                   "person's corrections: pass --overwrite to replace them, or review those instead")
        docs, none_found = {}, []
        description = f"colour rule, HSV {args.hsv}; not reviewed"
        for scene, colour_path in scenes:
            colour, depth_m, intr = _load(scene, colour_path)
            mask = colour_mask(colour, depth_m, intr, radius, hsv)
            if mask is None:
                none_found.append(scene.name)
                continue
            docs[scene / "colour.json"] = labelme_from_mask(mask, colour_path.name, args.label, description)
        kept = [p for p in existing if p not in docs]  # this rule found no ball there: the earlier file stays
        # all or nothing: a failed write puts every file back as it was (a replaced one with a person's
        # corrections included)
        outputs.replace_files({path: labelme_text(doc).encode() for path, doc in docs.items()})
        print(f"annotated {len(docs)} of {len(scenes)} frames from colour -> {args.dataset}/scenes/<id>/colour.json")
        if none_found:
            print(f"note: {len(none_found)} frame(s) where no component of the colour range fits the ball (e.g. "
                  f"{none_found[0]}): no colour.json, they stay unannotated; draw the ball in LabelMe, or save a file "
                  "with no shape to mark a frame without the ball", file=sys.stderr)
        if kept:
            print(f"note: {len(kept)} earlier colour.json file(s) where the rule found nothing now were kept, e.g. "
                  f"{kept[0]}", file=sys.stderr)
    if args.sheet is not None:
        pages = write_sheets(args.sheet, scenes, radius)
        print(f"wrote {len(pages)} review page(s) to {args.sheet}")
    return 0
