"""CircleNet on any image size: the camera normalisation (scale to the training focal length),
free input sizes in ONNX, circles in the input's pixels, and the shipped models untouched."""

from __future__ import annotations

import json
import sys

import cv2
import numpy as np
import onnx
import onnxruntime as ort
import pytest
import torch

from spherebench.baselines.circlenet.imaging import unscale_circles
from spherebench.baselines.circlenet.infer import DEFAULT_MODEL, CircleNetDetector
from spherebench.baselines.circlenet.model import CircleNet, CircleNetConfig, decode
from spherebench.baselines.circlenet.onnx_export import export_onnx
from spherebench.baselines.circlenet.size_study import KINECT, render
from spherebench.camera import Intrinsics
from spherebench.scripts.cli import main
from spherebench.datasets import inout

TINY = dict(resnet_width=8, neck_channels=16, head_channels=16)
SHIPPED = [DEFAULT_MODEL, DEFAULT_MODEL.with_name("full") / "model.onnx"]
#: Agreement of the best circle of one scene seen at two D435 resolutions, in units of the image width
#: (0.006 = 2.5 px at 424 px wide): the two renders differ in their noise, not in the scene.
AGREE_WIDTH = 0.006


def _random_model(size=(48, 64)) -> CircleNet:
    """A tiny model with non-trivial weights and batch-norm statistics, as after training."""
    torch.manual_seed(0)
    model = CircleNet(CircleNetConfig(image_size=size, **TINY))
    gen = torch.Generator().manual_seed(1)
    with torch.no_grad():
        for name, t in model.state_dict().items():
            if name.endswith("running_var"):
                t.copy_(0.5 + 1.5 * torch.rand(t.shape, generator=gen))
            elif t.is_floating_point():  # weights, biases, running means
                t.add_(0.1 * torch.randn(t.shape, generator=gen))
    return model.eval()


def _image(h, w, seed=0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    v, u = np.mgrid[0:h, 0:w]
    level = (128 + 100 * np.sin(u / 9.0) * np.cos(v / 7.0)).astype(np.uint8)
    rgb = cv2.applyColorMap(level, cv2.COLORMAP_JET)[:, :, ::-1].copy()
    rgb[rng.random((h, w)) < 0.03] = 0
    return rgb


def _fix_size(path, hp, wp):
    """An exported file rewritten with a fixed input size, as files exported before sizes were free."""
    proto = onnx.load(str(path))
    for value, (h, w) in ((proto.graph.input[0], (hp, wp)), *((o, (hp // 4, wp // 4)) for o in proto.graph.output)):
        dims = value.type.tensor_type.shape.dim
        dims[2].dim_value, dims[3].dim_value = h, w
    onnx.save(proto, str(path))
    return path


def test_onnx_and_torch_agree_at_a_size_the_model_was_not_trained_on(tmp_path):
    model = _random_model()
    free = export_onnx(model, tmp_path / "free.onnx")
    fixed = _fix_size(export_onnx(model, tmp_path / "fixed.onnx"), 64, 64)
    with pytest.raises(Exception, match="dimensions"):  # ONNX Runtime itself enforces a declared size
        ort.InferenceSession(str(fixed), providers=["CPUExecutionProvider"]).run(
            None, {"image": np.zeros((1, 3, 96, 128), np.float32)})
    image = _image(70, 100)  # 100x70 px: padded to 128x96, a shape neither file was exported at
    x = torch.zeros(1, 3, 96, 128)
    x[0, :, :70, :100] = torch.from_numpy(image).permute(2, 0, 1).float()
    with torch.no_grad():
        heads = model(x)
    want = decode(*heads, top_k=5, image_size=(70, 100))[0].numpy()
    for path in (free, fixed):
        det = CircleNetDetector(path)
        got = det.detect(image, top_k=5, scale=1.0)
        np.testing.assert_allclose(got, want, atol=1e-3)
        onnx_heads = det.session.run(None, {"image": x.numpy()})
        assert max(float(np.abs(a - b.numpy()).max()) for a, b in zip(onnx_heads, heads)) <= 1e-4


def test_focal_normalisation_maps_circles_back_to_the_input(tmp_path):
    det = CircleNetDetector(export_onnx(_random_model(), tmp_path / "m.onnx"))
    assert det.focal_px == pytest.approx(0.5025 * 64)
    image = _image(120, 160)  # a 4:3 camera with twice the model's focal length: scaled by 0.5
    got = det.detect(image, top_k=5, focal_px=2 * det.focal_px)
    half = cv2.resize(image, (80, 60), interpolation=cv2.INTER_NEAREST_EXACT)
    np.testing.assert_allclose(got, unscale_circles(det.detect(half, top_k=5, scale=1.0), 0.5, 0.5), atol=1e-9)
    # without a focal length: the model's width (the training camera's field of view)
    np.testing.assert_allclose(det.detect(image, top_k=5), det.detect(image, top_k=5, scale=64 / 160), atol=1e-9)


@pytest.mark.parametrize("path", SHIPPED, ids=["circlenet", "circlenet-full"])
def test_shipped_models_are_unchanged_at_the_training_size(path):
    """Freeing the input size in memory changes nothing at 424x240: the heads are bit-identical."""
    if not path.is_file():
        pytest.skip(f"{path} not shipped")
    det = CircleNetDetector(path, threads=1)
    assert det.image_size == (240, 424)
    image = _image(240, 424, seed=1)
    plain = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    x = np.zeros((1, 3, 256, 448), np.float32)
    x[0, :, :240, :424] = image.transpose(2, 0, 1)
    for a, b in zip(det.heads(image[None]), plain.run(None, {"image": x})):
        assert np.array_equal(a, b)


def _best(det, camera, index=3):
    rgb, intr, gt = render("default", index, "clean", camera)
    found = det.detect(rgb, focal_px=float(np.sqrt(intr.fx * intr.fy)))
    return found[0], gt[0], intr


def test_one_scene_at_three_d435_resolutions_gives_the_same_circle():
    det = CircleNetDetector(DEFAULT_MODEL, threads=1)
    base, gt_base, intr = _best(det, "424x240")
    assert base[3] > 0.5 and np.hypot(*(base[:2] - gt_base[:2])) < 3 and abs(base[2] - gt_base[2]) < 3
    for camera in ("848x480", "1280x720"):
        best, _, other = _best(det, camera)
        assert (other.width, other.height) == tuple(map(int, camera.split("x")))
        a, b = base[:3] / intr.width, best[:3] / other.width  # units of the image width
        assert np.abs(a - b).max() < AGREE_WIDTH, (camera, a, b)


def test_a_kinect_camera_finds_the_ball_in_its_own_pixels():
    det = CircleNetDetector(DEFAULT_MODEL, threads=1)
    best, gt, intr = _best(det, "kinect-640x480")
    assert intr.fx == KINECT.fx and best[3] > 0.5
    assert np.hypot(*(best[:2] - gt[:2])) < 0.01 * intr.width and abs(best[2] - gt[2]) < 0.01 * intr.width


def _cli(monkeypatch, capsys, *argv):
    monkeypatch.setattr(sys, "argv", ["spherebench", *argv])
    rc = main(list(argv))
    return rc, capsys.readouterr()


def test_detect_2d_runs_on_any_size_with_the_scene_camera(tmp_path, monkeypatch, capsys):
    model = export_onnx(_random_model(), tmp_path / "m.onnx")
    det = CircleNetDetector(model)
    sizes = {"a": (240, 424), "b": (480, 640), "c": (480, 848), "d": (720, 1280), "e": (101, 333)}
    for name, (h, w) in sizes.items():
        (tmp_path / name).mkdir()
        cv2.imwrite(str(tmp_path / name / "image.png"), _image(h, w)[:, :, ::-1])
    inout.write_intrinsics(tmp_path / "b" / "intrinsics.json", Intrinsics(width=640, height=480, ppx=320, ppy=240,
                                                                       fx=525.0, fy=525.0))
    before = sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*"))
    rc, cap = _cli(monkeypatch, capsys, "detect-2d", *(str(tmp_path / n) for n in sizes), "--model", str(model),
                   "--json", "--min-score", "0", "--top-k", "3")
    assert rc == 0, cap.err
    lines = [json.loads(s) for s in cap.out.splitlines()]
    assert [d["input"] for d in lines] == [str(tmp_path / n) for n in sizes]
    for d, (name, (h, w)) in zip(lines, sizes.items()):  # b with its own camera, the others at the model's width
        want = det.detect(_image(h, w), top_k=3, focal_px=525.0 if name == "b" else None)
        assert len(want) >= 1
        np.testing.assert_allclose([c["circle_px"]["center"] + [c["circle_px"]["radius"]] for c in d["detections"]], want[:, :3], atol=0.01)
    image = _image(720, 1280)  # in the input's pixels, not the scaled 424x240's
    np.testing.assert_allclose(det.detect(image, top_k=3), unscale_circles(
        det.detect(cv2.resize(image, (64, 36), interpolation=cv2.INTER_NEAREST_EXACT), top_k=3, scale=1.0),
        64 / 1280, 36 / 720), atol=1e-9)
    # one note for the images that had no camera and are not the model's 64x48 (all but b)
    note = [s for s in cap.err.splitlines() if s.startswith("note:")]
    assert len(note) == 1 and "4 image(s) without intrinsics.json" in note[0], cap.err
    assert sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*")) == before


def test_a_model_trained_on_the_earlier_train_preset_says_so():
    from spherebench import provenance
    from spherebench.eval.bench import registry
    full = registry.circlenet_model_path("circlenet-full")
    if not full.is_file():
        pytest.skip("the full-size CircleNet is not shipped in this checkout")
    spec = registry.circlenet_spec(full, "circlenet-full")
    assert (provenance.file_sha256(full) in registry.EARLIER_TRAIN) == ("earlier train preset" in spec.note)
    assert "earlier train preset" not in registry.circlenet_spec(registry.circlenet_model_path(), "circlenet").note


def test_the_training_presets_of_a_shipped_model_come_from_its_card():
    from spherebench import provenance
    from spherebench.eval.bench import registry
    path = registry.circlenet_model_path("circlenet")
    card = inout.read_json(path.with_name("model_card.json"))
    named = [d["preset"] for d in card["data"].get("datasets") or [card["data"]]]
    said = registry.training_presets("circlenet", provenance.file_sha256(path))
    assert said == " + ".join(f"`{p}`" for p in named)
    assert registry.training_presets("circlenet", "0" * 64) is None  # another file: not the card's model
    assert registry.training_presets("hough", provenance.file_sha256(path)) is None
