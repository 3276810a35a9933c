"""CircleNet inference with ONNX Runtime on the CPU, decoding in numpy (no torch imported).

    detector = CircleNetDetector("baselines/circlenet/model.onnx")
    circles = detector.detect_file("data/bench/scenes/0001/image.png")   # (K, 4): cx, cy, r px, score

The input is the benchmark's image.png, read by ``imaging.load_image`` exactly as in training.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import onnxruntime as ort

from spherebench.baselines.circlenet.imaging import (check_size, decode_numpy, fit_image, input_size, load_image,
                                                     pad_image, scale_circles, to_network_input)
from spherebench.baselines.circlenet.onnx_export import FORMAT_VERSION, INPUT_NAME, METADATA_KEY, OUTPUT_NAMES
from spherebench.errors import SphereBenchError

#: The shipped model (committed by ``make train``).
DEFAULT_MODEL = Path(__file__).resolve().with_name("model.onnx")


class CircleNetDetector:
    """An exported CircleNet in an ONNX Runtime CPU session.

    model_path: the .onnx file written by ``onnx_export.export_onnx``. threads: ONNX Runtime
    intra-op threads (None: its default, all cores).
    """

    def __init__(self, model_path=DEFAULT_MODEL, threads: int | None = None):
        path = Path(model_path)
        if not path.is_file():
            raise SphereBenchError(f"model file {path} not found; train one with `spherebench train` "
                                   "or pass --model FILE")
        opts = ort.SessionOptions()
        opts.log_severity_level = 3  # errors only: ONNX Runtime's warnings are not ours to print
        if threads:
            opts.intra_op_num_threads = int(threads)
        try:
            self.session = ort.InferenceSession(str(path), sess_options=opts, providers=["CPUExecutionProvider"])
        except Exception as exc:  # ONNX Runtime raises its own types for corrupt files
            first = str(exc).strip().splitlines()[0][:160] if str(exc).strip() else type(exc).__name__
            raise SphereBenchError(f"cannot load model {path}: not a valid ONNX file ({first})") from None
        raw = self.session.get_modelmeta().custom_metadata_map.get(METADATA_KEY)
        try:
            self.metadata = json.loads(raw) if raw else None
        except json.JSONDecodeError:
            self.metadata = None
        outputs = [o.name for o in self.session.get_outputs()]
        if (self.metadata is None or self.metadata.get("format_version") != FORMAT_VERSION
                or outputs != list(OUTPUT_NAMES) or self.session.get_inputs()[0].name != INPUT_NAME):
            raise SphereBenchError(f"{path} is an ONNX file but not a SphereBench CircleNet model "
                                   f"(format {FORMAT_VERSION}); export one with `spherebench train`")
        cfg = self.metadata["config"]
        self.path = path
        self.image_size: tuple[int, int] = tuple(int(s) for s in cfg["image_size"])  # (H, W) px
        self.input_size = input_size(self.image_size)
        self.top_k = int(cfg.get("top_k", 100))

    def check_image(self, image: np.ndarray, exact: bool = False) -> None:
        """Raise SphereBenchError unless image is (h, w, 3) uint8 of the model's size (exact) or aspect ratio."""
        if not isinstance(image, np.ndarray) or image.dtype != np.uint8 or image.ndim != 3 or image.shape[2] != 3:
            desc = f"{image.dtype} {image.shape}" if isinstance(image, np.ndarray) else type(image).__name__
            raise SphereBenchError(f"the image is {desc}; the model takes (H, W, 3) uint8 RGB images")
        if exact and image.shape[:2] != self.image_size:
            h, w = self.image_size
            raise SphereBenchError(f"the image is {image.shape[1]}x{image.shape[0]} px; heads() takes {w}x{h} px")
        check_size(image.shape, self.image_size)

    def heads(self, images: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Raw heads for RGB images (B, H, W, 3) uint8 of the model's size:
        heat (B, 1, h, w), offset (B, 2, h, w), radius (B, 1, h, w)."""
        for im in images:
            self.check_image(im, exact=True)
        x = to_network_input(np.stack([pad_image(im, self.input_size) for im in images]))
        heat, offset, radius = self.session.run(list(OUTPUT_NAMES), {INPUT_NAME: x})
        return heat, offset, radius

    def detect(self, image: np.ndarray, min_score: float = 0.0, top_k: int | None = None) -> np.ndarray:
        """Circles in one RGB image (h, w, 3) uint8: (K, 4) (cx, cy, r, score), px of that image, best first.

        An image of the model's aspect ratio but another size (848x480, 1280x720) is scaled to
        the model's size first (``imaging.fit_image``, as in training) and the circles mapped back.
        """
        self.check_image(image)
        fitted, scale = fit_image(image, self.image_size)
        heat, offset, radius = self.heads(fitted[None])
        circles = decode_numpy(heat, offset, radius, top_k or self.top_k, min_score,
                               _valid_size(image.shape, scale, self.image_size))[0]
        return circles if scale == 1.0 else scale_circles(circles, 1.0 / scale)

    def detect_file(self, path, min_score: float = 0.0, top_k: int | None = None) -> np.ndarray:
        """Circles in an image.png file: (K, 4) (cx, cy, r, score), px."""
        return self.detect(load_image(path, self.image_size), min_score, top_k)


def _valid_size(shape, scale: float, image_size: tuple[int, int]) -> tuple[int, int]:
    """(H, W) px of the part of the model's input that the (scaled) image covers."""
    return (min(image_size[0], round(shape[0] * scale)), min(image_size[1], round(shape[1] * scale)))
