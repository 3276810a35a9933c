"""Export a trained CircleNet to ONNX (opset 17) for ONNX Runtime inference.

The graph is ``CircleNet.forward``: image (B, 3, Hp, Wp) float32 RGB in [0, 255] -> heat
(B, 1, h, w) probabilities, offset (B, 2, h, w), radius (B, 1, h, w). Batch, height and width
are free (any multiple of 32; h, w = Hp / 4, Wp / 4): the network is fully convolutional, and
``infer.py`` runs an image of any size at the training focal length, so at a size of its own.
(Files exported before sizes were free declare 256x448; ``infer.free_input_size`` frees them
when they are loaded.) The model's configuration (image size, stride, backbone, ...), the
training images' focal length and its training facts travel in the ONNX metadata under
METADATA_KEY, so that the file alone is enough for inference.

``weights="float16"`` stores the weights in half precision (half the file: the full-width
ResNet-18's 46 MB become 23 MB) and casts them back to float32 inside the graph: the arithmetic
stays float32, ONNX Runtime folds the casts once when it loads the file, and only the weights'
rounding (relative 2^-11) differs from the float32 file.
"""

from __future__ import annotations

import copy
import io
import json
import os
import warnings
from pathlib import Path

import numpy as np
import onnx
import torch
from onnx import TensorProto, helper, numpy_helper

from spherebench.baselines.circlenet.imaging import (FORMAT_VERSION, INPUT_NAME, METADATA_KEY, OUTPUT_NAMES,
                                                     STRIDE, training_focal_px)
from spherebench.baselines.circlenet.model import CircleNet
from spherebench.errors import SphereBenchError

OPSET = 17
#: How the exported file stores its weights (the arithmetic is float32 in both).
WEIGHT_FORMATS = ("float32", "float16")


def export_onnx(model: CircleNet, path, metadata: dict | None = None, weights: str = "float32") -> Path:
    """Write the model as ONNX to path (atomically) with its config in the metadata; returns path.

    weights: "float32", or "float16" to store the weights in half precision (``store_weights_float16``).
    """
    if weights not in WEIGHT_FORMATS:
        raise SphereBenchError(f"weights must be one of {', '.join(WEIGHT_FORMATS)}, not {weights!r}")
    path = Path(path)
    model = copy.deepcopy(model).to("cpu", memory_format=torch.contiguous_format).float().eval()
    hp, wp = model.config.input_size
    dummy = torch.zeros(1, 3, hp, wp)
    buf = io.BytesIO()
    with warnings.catch_warnings():  # the TorchScript exporter: torch's dynamo exporter needs onnxscript
        warnings.simplefilter("ignore")
        torch.onnx.export(model, (dummy,), buf, opset_version=OPSET, dynamo=False, input_names=[INPUT_NAME],
                          output_names=list(OUTPUT_NAMES), do_constant_folding=True,
                          dynamic_axes={INPUT_NAME: {0: "batch", 2: "height", 3: "width"},
                                        **{n: {0: "batch", 2: "grid_height", 3: "grid_width"} for n in OUTPUT_NAMES}})
    proto = onnx.load_from_string(buf.getvalue())
    if weights == "float16":
        store_weights_float16(proto)
    onnx.checker.check_model(proto)
    meta = {"format_version": FORMAT_VERSION, "stride": STRIDE, "config": model.config.to_dict(),
            "focal_px": training_focal_px(model.config.image_size),
            **({"weights": weights} if weights != "float32" else {}), **(metadata or {})}
    entry = proto.metadata_props.add()
    entry.key, entry.value = METADATA_KEY, json.dumps(meta)
    proto.producer_name = "spherebench"
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".tmp-{path.name}")
    tmp.write_bytes(proto.SerializeToString())
    os.replace(tmp, path)
    return path


def store_weights_float16(proto: onnx.ModelProto) -> onnx.ModelProto:
    """Store every float32 initializer of the graph as float16, cast back to float32 in the graph (in place).

    Each initializer W (float32) becomes W__float16 (float16) and a Cast node at the head of the
    graph that outputs W as float32, so that every node still reads float32 and the graph's
    arithmetic is unchanged; only the stored values are rounded to half precision. Values beyond
    float16's range (|x| > 65504) are refused rather than saturated.
    """
    graph = proto.graph
    casts, kept = [], []
    for init in graph.initializer:
        if init.data_type != TensorProto.FLOAT:
            kept.append(init)
            continue
        values = numpy_helper.to_array(init)
        if values.size and float(np.abs(values).max()) > float(np.finfo(np.float16).max):
            raise SphereBenchError(f"initializer {init.name} has values beyond float16's range; export float32 weights")
        half = numpy_helper.from_array(values.astype(np.float16), name=f"{init.name}__float16")
        kept.append(half)
        casts.append(helper.make_node("Cast", [half.name], [init.name], name=f"{init.name}__to_float32",
                                      to=TensorProto.FLOAT))
    del graph.initializer[:]
    graph.initializer.extend(kept)
    nodes = casts + list(graph.node)
    del graph.node[:]
    graph.node.extend(nodes)
    return proto
