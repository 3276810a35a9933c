"""CircleNet inference with ONNX Runtime on the CPU, decoding in numpy (no torch imported).

    detector = CircleNetDetector("baselines/circlenet/model.onnx")
    circles = detector.detect_file("data/bench/scenes/0001/image.png")   # (K, 4): cx, cy, r px, score
    circles = detector.detect(image, focal_px=fx)                        # any size: px of that image

The input is the benchmark's image.png, read by ``imaging.load_image`` exactly as in training.
Any image size and camera: the image is scaled to the training focal length (``imaging``'s
camera normalisation), run at that size (the network is fully convolutional: a model file
exported with a fixed input size is given free height and width when it is loaded, in memory;
its weights and its outputs at the training size are unchanged), and the circles are mapped back.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np
import onnx

from spherebench.baselines.circlenet.imaging import (FORMAT_VERSION, INPUT_NAME, METADATA_KEY, OUTPUT_NAMES,
                                                     decode_numpy, focal_scale, input_size, load_image, pad_image,
                                                     scale_image, to_network_input, training_focal_px,
                                                     unscale_circles)
from spherebench.datasets import inout
from spherebench.errors import SphereBenchError
from spherebench.reading import parse_json

import onnxruntime as ort  # after spherebench's import, which turns its telemetry off (ORT_DISABLE_TELEMETRY)

#: The shipped model (committed by ``make train``; package data of the wheel).
DEFAULT_MODEL = Path(__file__).resolve().with_name("model.onnx")

#: ONNX Runtime's execution provider when none is given: this variable's value, else the CPU's. A
#: variable, so that `evaluate --provider` reaches the worker processes that load the model.
PROVIDER_VARIABLE = "SPHEREBENCH_ONNX_PROVIDER"
#: Short names of ONNX Runtime's execution providers.
PROVIDER_NAMES = {"cpu": "CPUExecutionProvider", "cuda": "CUDAExecutionProvider",
                  "tensorrt": "TensorrtExecutionProvider", "openvino": "OpenVINOExecutionProvider",
                  "coreml": "CoreMLExecutionProvider", "dml": "DmlExecutionProvider"}


def execution_provider(name: str | None = None) -> str:
    """ONNX Runtime's provider for a name ("cpu", "cuda", or its full name; None: $PROVIDER_VARIABLE,
    else the CPU), checked against this installation's: SphereBenchError if it lacks it."""
    name = name or os.environ.get(PROVIDER_VARIABLE) or "cpu"
    full = PROVIDER_NAMES.get(name.lower(), name)
    available = ort.get_available_providers()
    if full not in available:
        raise SphereBenchError(f"ONNX Runtime here has no {full} (it has {', '.join(available)}); for CUDA install "
                               "onnxruntime-gpu in place of onnxruntime")
    return full


class CircleNetDetector:
    """An exported CircleNet in an ONNX Runtime session (on the CPU unless told otherwise).

    model_path: the .onnx file written by ``onnx_export.export_onnx``. threads: ONNX Runtime
    intra-op threads (None: its default, all cores). provider: ``execution_provider``'s name (None:
    the CPU, unless $SPHEREBENCH_ONNX_PROVIDER names another).
    """

    def __init__(self, model_path=DEFAULT_MODEL, threads: int | None = None, provider: str | None = None):
        path = Path(model_path)
        provider = execution_provider(provider)
        if not path.is_file():
            raise SphereBenchError(f"model file {path} not found; train one with `spherebench train` "
                                   "or pass --model FILE")
        opts = ort.SessionOptions()
        opts.log_severity_level = 3  # errors only: ONNX Runtime's warnings are not ours to print
        if threads:
            opts.intra_op_num_threads = int(threads)
        try:
            proto = free_input_size(onnx.load(str(path)))
            self.session = ort.InferenceSession(proto.SerializeToString(), sess_options=opts,
                                                providers=[provider])
        except Exception as exc:  # onnx and ONNX Runtime raise their own types for corrupt files
            first = str(exc).strip().splitlines()[0][:160] if str(exc).strip() else type(exc).__name__
            raise SphereBenchError(f"cannot load model {path}: not a valid ONNX file ({first})") from None
        raw = self.session.get_modelmeta().custom_metadata_map.get(METADATA_KEY)
        try:
            self.metadata = parse_json(raw, f"{path}'s metadata") if raw else None
        except SphereBenchError:  # another tool's metadata: not our model (said below)
            self.metadata = None
        if not isinstance(self.metadata, dict):
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
        #: focal length (px) of the training images: every image is scaled to it
        self.focal_px = float(self.metadata.get("focal_px") or training_focal_px(self.image_size))

    def check_image(self, image: np.ndarray, exact: bool = False) -> None:
        """Raise SphereBenchError unless image is (h, w, 3) uint8 (of the model's size, when exact)."""
        if not isinstance(image, np.ndarray) or image.dtype != np.uint8 or image.ndim != 3 or image.shape[2] != 3:
            desc = f"{image.dtype} {image.shape}" if isinstance(image, np.ndarray) else type(image).__name__
            raise SphereBenchError(f"the image is {desc}; the model takes (H, W, 3) uint8 RGB images")
        if exact and image.shape[:2] != self.image_size:
            h, w = self.image_size
            raise SphereBenchError(f"the image is {image.shape[1]}x{image.shape[0]} px; heads() takes {w}x{h} px")

    def heads(self, images: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Raw heads for RGB images (B, H, W, 3) uint8 of the model's size:
        heat (B, 1, h, w), offset (B, 2, h, w), radius (B, 1, h, w)."""
        for im in images:
            self.check_image(im, exact=True)
        x = to_network_input(np.stack([pad_image(im, self.input_size) for im in images]))
        heat, offset, radius = self.session.run(list(OUTPUT_NAMES), {INPUT_NAME: x})
        return heat, offset, radius

    def detect(self, image: np.ndarray, min_score: float = 0.0, top_k: int | None = None,
               focal_px: float | None = None, scale: float | None = None) -> np.ndarray:
        """Circles in one RGB image (h, w, 3) uint8 of any size: (K, 4) (cx, cy, r, score), px of that
        image, best first.

        focal_px: the image's focal length (px; ``scene_focal_px``): the image is scaled by the
        model's focal_px / focal_px. None: scaled to the model's width (the training camera's field
        of view: exact for every D435 mode, 848x480 and 1280x720 alike). scale: a factor of one's
        own instead (1.0: the image as it is).
        """
        self.check_image(image)
        s = float(scale) if scale is not None else focal_scale(image.shape, self.image_size, focal_px, self.focal_px)
        if not (math.isfinite(s) and s > 0):
            raise SphereBenchError(f"the scale must be a positive number, got {scale}")
        scaled, (sx, sy) = scale_image(image, s)
        x = to_network_input(pad_image(scaled, input_size(scaled.shape[:2]))[None])
        heat, offset, radius = self.session.run(list(OUTPUT_NAMES), {INPUT_NAME: x})
        circles = decode_numpy(heat, offset, radius, top_k or self.top_k, min_score, scaled.shape[:2])[0]
        return circles if (sx, sy) == (1.0, 1.0) else unscale_circles(circles, sx, sy)

    def detect_file(self, path, min_score: float = 0.0, top_k: int | None = None,
                    focal_px: float | None = None) -> np.ndarray:
        """Circles in an image.png file: (K, 4) (cx, cy, r, score), px. focal_px None: that of the
        intrinsics.json beside the file, when there is one (a scene folder)."""
        path = Path(path)
        if focal_px is None:
            focal_px = scene_focal_px(path.parent)
        return self.detect(load_image(path), min_score, top_k, focal_px)


def scene_focal_px(scene_dir) -> float | None:
    """sqrt(fx * fy) px of a scene folder's intrinsics.json, or None when it has none."""
    path = Path(scene_dir) / "intrinsics.json"
    if not path.is_file():
        return None
    intr = inout.read_intrinsics(path)
    return math.sqrt(float(intr.fx) * float(intr.fy))


def free_input_size(proto: onnx.ModelProto) -> onnx.ModelProto:
    """Give an exported CircleNet graph free input height and width (in place; returns it).

    The graph is convolutions, pooling and scale-2 resizes, so nothing in it depends on the size;
    only the declared shapes of the input, the outputs and the intermediate values (from
    ``make train`` exports before sizes were free) fix it, and ONNX Runtime enforces them. The
    weights and every node stay as they are.
    """
    graph = proto.graph
    for value, names in ((graph.input[0], ("height", "width")),
                         *((o, ("grid_height", "grid_width")) for o in graph.output)):
        dims = value.type.tensor_type.shape.dim
        if len(dims) == 4:
            for d, name in zip(dims[2:], names):
                d.ClearField("dim_value")
                d.dim_param = name
    del graph.value_info[:]
    return proto
