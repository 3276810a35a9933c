"""`spherebench detect-2d`: run the CircleNet-style 2D detector on reprojected depth images.

    spherebench detect-2d PATH... [--model FILE] [--focal-px F] [--json] [--min-score S] [--top-k K]

PATH: an image.png (the depth colourised, as the benchmark gives every 2D method) or a scene
folder holding one, of any size. The image is scaled to the model's training focal length
(213 px: the D435 at 424x240), run, and the circles mapped back to its own pixels. Its focal
length comes from --focal-px, else from the intrinsics.json beside the image (a scene folder);
without either the camera is taken to have the D435's field of view (a note says so when the
image is not 424x240). With --json, one line per input in the schema that `detect` prints too
(docs/formats.md):
    {"input": PATH, "frame": null, "timestamp_ms": null, "detections": [{"score": s, "center_m": null,
     "radius_m": null, "circle_px": {"center": [cx, cy], "radius": r}, "bbox": [x, y, w, h],
     "inliers": null}, ...], "ms": T}
circles in the input's pixels, best first (a 2D detector knows no metres); ms = inference time
(scaling, padding, ONNX Runtime, decoding), not file reading. As in `detect`, an input that turns
out bad (missing, not an image, damaged) gets one line on stderr, ``spherebench detect-2d: error:
PATH: what is wrong``, and is skipped: the others are detected and printed, and the exit status
is then 2.
"""

from __future__ import annotations

import json
import math
import sys
import time
from pathlib import Path

from spherebench import options
from spherebench.scripts.cli import BadInputs
from spherebench.datasets import detections
from spherebench.errors import SphereBenchError


def add_arguments(parser) -> None:
    parser.add_argument("paths", nargs="+", metavar="PATH", help="image.png files or scene folders")
    parser.add_argument("--model", default=None, metavar="FILE",
                        help="ONNX model (default: the shipped baselines/circlenet/model.onnx)")
    parser.add_argument("--focal-px", type=float, default=None, metavar="F",
                        help="the images' focal length in pixels (default: each scene's intrinsics.json; "
                             "without one, the D435's field of view)")
    parser.add_argument("--json", action="store_true", help="one JSON line per input")
    parser.add_argument("--min-score", type=options.fraction, default=0.3, metavar="S",
                        help="drop circles scoring below S (default 0.3, CenterNet's display threshold; "
                             "use 0 for mAP)")
    parser.add_argument("--top-k", type=options.count, default=100, metavar="K", help="at most K circles per image (default 100)")
    parser.add_argument("--threads", type=options.threads, default=None, metavar="N", help="ONNX Runtime threads (default: all)")
    parser.add_argument("--provider", default=None, metavar="NAME",
                        help="ONNX Runtime execution provider: cpu (default), cuda (needs onnxruntime-gpu), or a "
                             "full name such as CUDAExecutionProvider")


def _image_path(path: Path) -> Path:
    if path.is_dir():
        if not (path / "image.png").is_file():
            raise SphereBenchError(f"{path} is a folder without image.png; pass image files or scene folders "
                                   "(DIR/scenes/<id>)")
        return path / "image.png"
    if not path.exists():
        raise SphereBenchError(f"{path} not found")
    return path


def run(args) -> int:
    # here, not at the top: infer loads onnx and onnxruntime (about a second), which `detect-2d --help` does not need
    from spherebench.baselines.circlenet.imaging import load_image
    from spherebench.baselines.circlenet.infer import DEFAULT_MODEL, CircleNetDetector, scene_focal_px

    if args.focal_px is not None and not (math.isfinite(args.focal_px) and args.focal_px > 0):
        raise SphereBenchError(f"--focal-px must be a positive number of pixels, got {args.focal_px:g}")
    bad = BadInputs("spherebench detect-2d")
    jobs = []  # (as given, image file, focal px): each input checked as far as it can be unread
    for given in args.paths:
        with bad.each(given):
            path = _image_path(Path(given))
            jobs.append((given, path, args.focal_px if args.focal_px is not None else scene_focal_px(path.parent)))
    if not jobs:
        return bad.status
    detector = CircleNetDetector(args.model or DEFAULT_MODEL, threads=args.threads, provider=args.provider)
    assumed = []  # images of another size than the model's without a focal length
    for given, path, focal in jobs:
        with bad.each(given):
            image = load_image(path)
            if focal is None and image.shape[:2] != detector.image_size:
                assumed.append(given)
            t0 = time.perf_counter()
            circles = detector.detect(image, min_score=args.min_score, top_k=args.top_k, focal_px=focal)
            ms = 1000 * (time.perf_counter() - t0)
            if args.json:
                print(json.dumps(detections.frame_record(given, [detections.detection_record(s, (cx, cy, r))
                                                                 for cx, cy, r, s in circles], ms)), flush=True)
            else:
                found = ", ".join(f"({cx:.1f}, {cy:.1f}) r {r:.1f} score {s:.2f}" for cx, cy, r, s in circles) or "none"
                print(f"{given}: {len(circles)} circle(s) {found} [{ms:.1f} ms]", flush=True)
    if assumed:
        h, w = detector.image_size
        print(f"note: {len(assumed)} image(s) without intrinsics.json, e.g. {assumed[0]}, were scaled to {w} px wide "
              "(the training camera's field of view); give --focal-px F for another camera", file=sys.stderr)
    return bad.status
