"""How CircleNet should take images of other sizes: the measurement behind ``docs/baselines.md``.

    .venv/bin/python -m spherebench.baselines.circlenet.size_study [--n 24] [--model FILE] [--cameras A,B] [--out FILE]
    .venv/bin/python -m spherebench.baselines.circlenet.size_study --real data/real/kinect-pochang [--model FILE]

The same simulated scenes (the hard preset's families and the default preset's clean and
cluttered ones, seed 0) are rendered by each camera: the D435 at 424x240 (the training size),
848x480 and 1280x720, and a Kinect-type 640x480 camera with fx = 525 px (a narrower field of
view than the D435's, the recorded set's camera). Each image is given to the model
- ``native``: as it is, at its own size (the graph's free input size);
- ``focal``: scaled to the training focal length (213 px), then run at that size;
- ``width``: scaled to the model's width (what the detector does without the camera's focal).
Printed per camera and rule: circle mAP / mAP.50 (COCO protocol) against the scenes' ground
truth, the best circle's centre and radius error against it (median, px of the model's 424 px
width) and the time per image. ``--real DIR`` scores the three rules on an annotated recorded
dataset instead (its image.png, intrinsics.json and mask circles: ``make realdata``).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from unittest import mock

import numpy as np

from spherebench.baselines.circlenet.imaging import load_image
from spherebench.baselines.circlenet.infer import DEFAULT_MODEL, CircleNetDetector, scene_focal_px
from spherebench.baselines.circlenet.train import coco_circle_map
from spherebench.camera import Intrinsics
from spherebench.datasets import inout, presets, rendering, simulate
from spherebench.datasets.reproject import colourise_depth

#: The recorded set's camera (``datasets.prepare.POCHANG_INTRINSICS``), with the D435's depth unit.
KINECT = Intrinsics(width=640, height=480, ppx=316.6, ppy=256.2, fx=524.6, fy=523.5, model="none", depth_scale=0.001)
CAMERAS = ("424x240", "848x480", "1280x720", "kinect-640x480")
RULES = ("native", "focal", "width")


class _KinectCamera(Intrinsics):
    """Stands in for ``Intrinsics`` inside ``rendering`` so that its scenes are seen by KINECT."""

    @classmethod
    def d435(cls, width: int = 424, height: int = 240) -> Intrinsics:
        return KINECT


def render(preset: str, index: int, family: str, camera: str):
    """(RGB image, intrinsics, ground-truth circles (N, 3) px) of one scene seen by one camera."""
    if camera.startswith("kinect"):
        with mock.patch.object(rendering, "Intrinsics", _KinectCamera), \
                mock.patch.dict(presets.RESOLUTIONS, {camera: (KINECT.width, KINECT.height)}):
            scene = rendering.simulate_scene(preset, index, family, 0, camera)
    else:
        scene = rendering.simulate_scene(preset, index, family, 0, camera)
    rgb = colourise_depth(scene.depth_m())[:, :, ::-1].copy()
    gt = np.asarray([b.circle_px for b in scene.balls if b.circle_px is not None], np.float64).reshape(-1, 3)
    return rgb, scene.intrinsics, gt


def _score(detector, items) -> dict:
    """items: (RGB image, focal px, ground-truth circles (N, 3), width px) -> the figures per rule."""
    out = {}
    for rule in RULES:
        gt, dets, errors, times = {}, {}, [], []
        for k, (rgb, focal, circles, width) in enumerate(items):
            kw = {"scale": 1.0} if rule == "native" else ({"focal_px": focal} if rule == "focal" else {})
            t0 = time.perf_counter()
            found = detector.detect(rgb, **kw)
            times.append(time.perf_counter() - t0)
            gt[k], dets[k] = circles, found
            if len(circles) and len(found):
                to_model = detector.image_size[1] / width  # errors in px of the model's width
                errors.append([np.hypot(*(found[0, :2] - circles[0, :2])) * to_model,
                               abs(found[0, 2] - circles[0, 2]) * to_model])
        m = coco_circle_map(gt, dets)
        e = np.median(np.asarray(errors), axis=0) if errors else [float("nan")] * 2
        out[rule] = {"mAP": m["mAP"], "mAP50": m["mAP50"], "centre_err_px424": float(e[0]),
                     "radius_err_px424": float(e[1]), "ms": 1000 * float(np.median(times)), "scenes": len(items)}
    return out


def real_study(dataset, model=DEFAULT_MODEL) -> dict:
    """The three rules on an annotated recorded dataset's scenes (their mask circles as truth)."""
    detector = CircleNetDetector(model, threads=1)
    items = []
    for scene in inout.list_scenes(dataset):
        gt = inout.read_scene_gt(scene)
        if not gt.get("annotated") or not (scene / "image.png").is_file():
            continue
        circles = np.asarray([b["circle"] for b in gt["balls"] if b.get("circle")], np.float64).reshape(-1, 3)
        rgb = load_image(scene / "image.png")
        items.append((rgb, scene_focal_px(scene), circles, rgb.shape[1]))
    return {f"{Path(dataset).name} {rule}": r for rule, r in _score(detector, items).items()}


def study(n: int = 24, model=DEFAULT_MODEL, cameras=CAMERAS) -> dict:
    detector = CircleNetDetector(model, threads=1)
    scenes = [("hard", i, f) for i, f, _ in simulate.plan("hard", n=n)]
    scenes += [("default", i, f) for i, f, _ in simulate.plan("default", n=max(2, n // 3))]
    results = {}
    for camera in cameras:
        items = []
        for preset, index, family in scenes:
            rgb, intr, circles = render(preset, index, family, camera)
            items.append((rgb, float(np.sqrt(intr.fx * intr.fy)), circles, intr.width))
        results.update({f"{camera} {rule}": r for rule, r in _score(detector, items).items()})
    return results


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--n", type=int, default=24, help="scenes of the hard preset (and n/3 of default)")
    ap.add_argument("--model", default=str(DEFAULT_MODEL))
    ap.add_argument("--cameras", default=",".join(CAMERAS), help=f"comma-separated, of {', '.join(CAMERAS)}")
    ap.add_argument("--real", default=None, metavar="DIR", help="an annotated recorded dataset instead")
    ap.add_argument("--out", default=None, help="also write the figures as JSON here")
    args = ap.parse_args()
    results = (real_study(args.real, args.model) if args.real else
               study(args.n, args.model, tuple(args.cameras.split(","))))
    print(f"{'camera rule':28s} {'mAP':>6s} {'mAP50':>6s} {'centre':>7s} {'radius':>7s} {'ms':>6s}")
    for name, r in results.items():
        print(f"{name:28s} {r['mAP']:6.3f} {r['mAP50']:6.3f} {r['centre_err_px424']:7.2f} "
              f"{r['radius_err_px424']:7.2f} {r['ms']:6.1f}")
    if args.out:
        with open(args.out, "w") as f:
            json.dump({"model": args.model, "results": results}, f, indent=1)


if __name__ == "__main__":
    main()
