"""Export a trained CircleNet to ONNX (opset 17) for ONNX Runtime inference.

The graph is ``CircleNet.forward``: image (B, 3, Hp, Wp) float32 RGB in [0, 255] -> heat
(B, 1, h, w) probabilities, offset (B, 2, h, w), radius (B, 1, h, w). The batch is dynamic;
height and width are **static**: the benchmark gives every 2D method images of one size (424x240,
padded to 448x256), a fixed shape lets ONNX Runtime plan its memory once, and an image of
another size is refused with a message (``infer.py``) instead of being silently rescaled.
The model's configuration (image size, stride, backbone, ...) and its training facts travel in
the ONNX metadata under METADATA_KEY, so that the file alone is enough for inference.
"""

from __future__ import annotations

import copy
import io
import json
import os
import warnings
from pathlib import Path

import onnx
import torch

from spherebench.baselines.circlenet.imaging import STRIDE
from spherebench.baselines.circlenet.model import CircleNet

OPSET = 17
METADATA_KEY = "spherebench.circlenet"
#: Bumped when the input/output contract changes; infer.py refuses other versions.
FORMAT_VERSION = 1
INPUT_NAME = "image"
OUTPUT_NAMES = ("heat", "offset", "radius")


def export_onnx(model: CircleNet, path, metadata: dict | None = None) -> Path:
    """Write the model as ONNX to path (atomically) with its config in the metadata; returns path."""
    path = Path(path)
    model = copy.deepcopy(model).to("cpu", memory_format=torch.contiguous_format).float().eval()
    hp, wp = model.config.input_size
    dummy = torch.zeros(1, 3, hp, wp)
    buf = io.BytesIO()
    with warnings.catch_warnings():  # the TorchScript exporter: torch's dynamo exporter needs onnxscript
        warnings.simplefilter("ignore")
        torch.onnx.export(model, (dummy,), buf, opset_version=OPSET, dynamo=False, input_names=[INPUT_NAME],
                          output_names=list(OUTPUT_NAMES), do_constant_folding=True,
                          dynamic_axes={n: {0: "batch"} for n in (INPUT_NAME, *OUTPUT_NAMES)})
    proto = onnx.load_from_string(buf.getvalue())
    onnx.checker.check_model(proto)
    meta = {"format_version": FORMAT_VERSION, "stride": STRIDE, "config": model.config.to_dict(), **(metadata or {})}
    entry = proto.metadata_props.add()
    entry.key, entry.value = METADATA_KEY, json.dumps(meta)
    proto.producer_name = "spherebench"
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".tmp-{path.name}")
    tmp.write_bytes(proto.SerializeToString())
    os.replace(tmp, path)
    return path
