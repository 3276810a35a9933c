"""The CircleNet-style 2D baseline: model, loss, decoding, data, training, ONNX, CLI, bad input.

Everything runs on tiny synthetic datasets made here: a tilted wall with one filled ball per
image, the depth colourised with OpenCV's JET map (black = no depth), in the dataset format
(DIR/coco_gt.json + DIR/scenes/<id>/image.png).
"""

from __future__ import annotations

import json
import math
import subprocess
import sys
import warnings

import cv2
import numpy as np
import pytest
import torch

from spherebench.baselines.circlenet import data as cdata
from spherebench.baselines.circlenet import train as ctrain
from spherebench.baselines.circlenet.imaging import (STRIDE, decode_numpy, fit_image, grid_to_pixel, pixel_to_grid,
                                                     scale_circles)
from spherebench.baselines.circlenet.infer import CircleNetDetector
from spherebench.baselines.circlenet.loss import circlenet_loss, focal_loss
from spherebench.baselines.circlenet.model import CircleNet, CircleNetConfig, decode
from spherebench.baselines.circlenet.onnx_export import export_onnx
from spherebench.circles import mask_circle
from spherebench.scripts.cli import main
from spherebench.errors import SphereBenchError

TINY = dict(resnet_width=8, neck_channels=16, head_channels=16, hourglass_stem=8,
            hourglass_channels=(8, 12, 16, 20), hourglass_stacks=2)


def make_dataset(root, n=8, size=(48, 64), seed=0, negatives=1, radius=(5.0, 9.0), double_every=0):
    """Write n JET-coloured depth images (size = (H, W) px), the first `negatives` without a ball;
    every double_every-th image twice as large (another sensor mode of the same aspect ratio)."""
    rng = np.random.default_rng(seed)
    images, anns = [], []
    for i in range(n):
        k = 2 if double_every and i % double_every == double_every - 1 else 1
        h, w = size[0] * k, size[1] * k
        v, u = np.mgrid[0:h, 0:w].astype(np.float64)
        radius_px = (radius[0] * k, radius[1] * k)
        depth = 2.5 + rng.uniform(-0.01, 0.01) * (u - w / 2) + rng.uniform(-0.01, 0.01) * (v - h / 2)
        if i >= negatives:
            r = rng.uniform(*radius_px)
            cx, cy = rng.uniform(r, w - 1 - r), rng.uniform(r, h - 1 - r)
            d2 = (u - cx) ** 2 + (v - cy) ** 2
            disc = d2 <= r * r
            depth[disc] = 1.2 - 0.3 * np.sqrt(np.clip(1 - d2[disc] / (r * r), 0, 1))
            c = mask_circle(disc)
            anns.append({"id": len(anns) + 1, "image_id": i + 1, "category_id": 1, "circle_center": [c[0], c[1]],
                         "circle_radius": c[2], "area": math.pi * c[2] ** 2,
                         "bbox": [c[0] - c[2], c[1] - c[2], 2 * c[2], 2 * c[2]], "iscrowd": 0})
        grey = np.clip((depth - 0.8) / (3.0 - 0.8) * 255, 0, 255).astype(np.uint8)
        bgr = cv2.applyColorMap(grey, cv2.COLORMAP_JET)
        bgr[rng.random((h, w)) < 0.02] = 0  # holes: no depth
        scene = f"{i:04d}"
        (root / "scenes" / scene).mkdir(parents=True)
        cv2.imwrite(str(root / "scenes" / scene / "image.png"), bgr)
        images.append({"id": i + 1, "file_name": f"scenes/{scene}/image.png", "width": w, "height": h,
                       "scene_id": scene, "family": "synthetic"})
    coco = {"images": images, "annotations": anns, "categories": [{"id": 1, "name": "basketball"}]}
    (root / "coco_gt.json").write_text(json.dumps(coco))
    (root / "dataset.json").write_text(json.dumps({"name": "tiny", "preset": "test", "seed": seed}))
    return root


@pytest.fixture(scope="module")
def tiny_data(tmp_path_factory):
    return make_dataset(tmp_path_factory.mktemp("tiny"), n=10, double_every=4)


def tiny_config(**kw) -> ctrain.TrainConfig:
    return ctrain.TrainConfig(model=CircleNetConfig(image_size=(48, 64), **TINY), **{**dict(epochs=2, batch_size=4, warmup_iters=2, lr=3e-3), **kw})


# ---------------------------------------------------------------- model

@pytest.mark.parametrize("backbone,stages", [("resnet18", 1), ("hourglass", 2)])
def test_backbone_output_shapes(backbone, stages):
    cfg = CircleNetConfig(backbone=backbone, image_size=(40, 90), **TINY)
    assert cfg.input_size == (64, 96) and cfg.grid_size == (16, 24)
    model = CircleNet(cfg).eval()
    x = torch.rand(2, 3, 64, 96) * 255
    outs = model.forward_stages(x)
    assert len(outs) == stages
    for o in outs:
        assert o["heat"].shape == (2, 1, 16, 24) and o["offset"].shape == (2, 2, 16, 24)
        assert o["radius"].shape == (2, 1, 16, 24)
    heat, offset, radius = model(x)
    assert heat.shape == (2, 1, 16, 24) and offset.shape == (2, 2, 16, 24) and radius.shape == (2, 1, 16, 24)
    assert float(heat.detach().min()) > 0 and float(heat.detach().max()) < 1
    # CenterNet's initialisation: the heat bias starts at -log(0.9 / 0.1)
    assert float(model.heads[-1].heads["heat"][-1].bias.detach()) == pytest.approx(-2.197, abs=1e-3)


def test_default_backbones_fit_the_benchmark_images_and_the_size_limit():
    for backbone in ("resnet18", "hourglass"):
        cfg = CircleNetConfig(backbone=backbone)
        assert cfg.input_size == (256, 448)  # 424x240 padded to multiples of 32
        n = sum(p.numel() for p in CircleNet(cfg).parameters())
        assert 4 * n < 25e6, f"{backbone}: {n} parameters, the ONNX file would exceed 25 MB"
    # ResNet-18 at its own widths (`make train-full`): 25 MB only with its weights stored as float16
    n = sum(p.numel() for p in CircleNet(CircleNetConfig(resnet_width=64)).parameters())
    assert 4 * n > 25e6 > 2 * n


def test_unknown_backbone_is_an_error():
    with pytest.raises(SphereBenchError, match="unknown backbone"):
        CircleNetConfig(backbone="vgg")


# ---------------------------------------------------------------- loss

def test_focal_loss_on_a_hand_made_case():
    p = torch.tensor([0.8, 0.3, 0.1])
    logits = torch.log(p / (1 - p)).view(1, 1, 1, 3)
    target = torch.tensor([1.0, 0.5, 0.0]).view(1, 1, 1, 3)
    expected = (-(0.2 ** 2) * math.log(0.8)  # the centre
                - (0.5 ** 4) * 0.3 ** 2 * math.log(0.7)  # near it: reduced penalty
                - 0.1 ** 2 * math.log(0.9))  # background
    assert float(focal_loss(logits, target)) == pytest.approx(expected, rel=1e-5)
    # normalised by the number of centres
    assert float(focal_loss(logits.repeat(1, 1, 1, 2), target.repeat(1, 1, 1, 2))) == pytest.approx(expected, rel=1e-5)
    # confident and right: near zero; no centres at all: divided by 1, not 0
    good = torch.tensor([9.0, -9.0, -9.0]).view(1, 1, 1, 3)
    assert float(focal_loss(good, target)) < 1e-3
    assert math.isfinite(float(focal_loss(logits, torch.zeros_like(target))))


def test_regression_losses_only_count_object_cells():
    heat = torch.zeros(1, 1, 4, 4)
    heat[0, 0, 1, 2] = 1
    targets = {"heat": heat, "cells": torch.tensor([[6, 0]]), "mask": torch.tensor([[1.0, 0.0]]),
               "offset": torch.tensor([[[0.25, 0.75], [9.0, 9.0]]]), "radius": torch.tensor([[[3.0], [9.0]]])}
    offset = torch.zeros(1, 2, 4, 4)
    radius = torch.full((1, 1, 4, 4), 100.0)  # wrong everywhere but at cell 6
    radius[0, 0, 1, 2] = 2.0
    stage = {"heat": torch.full((1, 1, 4, 4), -9.0), "offset": offset, "radius": radius}
    _, parts = circlenet_loss([stage], targets)
    assert parts["offset"] == pytest.approx(0.5, rel=1e-3)  # (0.25 + 0.75) / 2 channels
    assert parts["radius"] == pytest.approx(1.0, rel=1e-3)


# ---------------------------------------------------------------- decoding and targets

def test_decode_on_a_hand_made_heat_map():
    heat = np.zeros((1, 1, 6, 8), np.float32)
    heat[0, 0, 2, 3] = 0.9  # a peak
    heat[0, 0, 2, 4] = 0.8  # its neighbour: not a peak
    heat[0, 0, 4, 6] = 0.6  # a second peak
    heat[0, 0, 5, 1] = 0.7  # a peak in the padding rows of a 20-px-high image: dropped
    offset = np.zeros((1, 2, 6, 8), np.float32)
    offset[0, :, 2, 3] = (0.25, 0.5)
    radius = np.zeros((1, 1, 6, 8), np.float32)
    radius[0, 0, 2, 3], radius[0, 0, 4, 6] = 2.5, 1.0
    got = decode_numpy(heat, offset, radius, top_k=10, min_score=0.05, image_size=(20, 32))[0]
    expected = np.array([[(3 + 0.25) * 4 - 0.5, (2 + 0.5) * 4 - 0.5, 10.0, 0.9],
                         [6 * 4 - 0.5, 4 * 4 - 0.5, 4.0, 0.6]])
    np.testing.assert_allclose(got, expected, atol=1e-6)
    # the torch decoder (used in validation) follows the same rule
    t = decode(*(torch.from_numpy(a) for a in (heat, offset, radius)), top_k=10, image_size=(20, 32))[0].numpy()
    np.testing.assert_allclose(t[t[:, 3] > 0.05], expected, atol=1e-6)


def test_torch_and_numpy_decoders_agree_on_random_heads():
    rng = np.random.default_rng(1)
    heat = rng.random((2, 1, 16, 24)).astype(np.float32)
    offset = rng.random((2, 2, 16, 24)).astype(np.float32)
    radius = rng.uniform(-1, 5, (2, 1, 16, 24)).astype(np.float32)
    a = decode_numpy(heat, offset, radius, top_k=20, image_size=(60, 90))
    b = decode(*(torch.from_numpy(x) for x in (heat, offset, radius)), top_k=20, image_size=(60, 90)).numpy()
    for ai, bi in zip(a, b):
        np.testing.assert_allclose(ai, bi[bi[:, 3] > 0], atol=1e-5)


def test_targets_decode_back_to_the_circles():
    circles = np.array([[10.3, 7.9, 6.2], [40.0, 30.6, 3.1]])
    t = cdata.render_targets(circles, (16, 24), max_objects=4)
    assert t["mask"].tolist() == [1, 1, 0, 0] and t["heat"].max() == 1.0
    assert int((t["heat"] == 1).sum()) == 2
    # perfect heads made from the targets decode to the input circles
    offset, radius = np.zeros((1, 2, 16, 24), np.float32), np.zeros((1, 1, 16, 24), np.float32)
    for k in range(2):
        y, x = divmod(int(t["cells"][k]), 24)
        offset[0, :, y, x], radius[0, 0, y, x] = t["offset"][k], t["radius"][k, 0]
    got = decode_numpy(t["heat"][None], offset, radius, top_k=2)[0]
    np.testing.assert_allclose(got[np.argsort(got[:, 0]), :3], circles, atol=1e-5)
    np.testing.assert_allclose(grid_to_pixel(pixel_to_grid([[3.0, 5.0]])), [[3.0, 5.0]])
    # the Gaussian's radius: a displaced copy of a circle keeps IoU 0.7 at ~0.28 r
    assert cdata._equal_circle_iou(cdata._DISPLACEMENT_RATIO) == pytest.approx(0.7, abs=1e-9)


def test_augmentation_moves_circles_with_the_ball_and_is_seeded():
    img = np.full((48, 64, 3), 60, np.uint8)
    disc = (np.mgrid[0:48, 0:64][1] - 20.0) ** 2 + (np.mgrid[0:48, 0:64][0] - 25.0) ** 2 <= 8.0 ** 2
    img[disc] = (250, 10, 10)
    aug = cdata.AugmentConfig(hue_deg=0, saturation=0, brightness=0, noise=0, shift=0.1)
    for k in range(12):
        canvas, circles = cdata.augment(img, np.array([[20.0, 25.0, 8.0]]), (64, 96), aug, np.random.default_rng(k))
        assert canvas.shape == (64, 96, 3)
        for cx, cy, r in circles:
            vv, uu = np.mgrid[0:64, 0:96]
            inner = (uu - cx) ** 2 + (vv - cy) ** 2 <= (0.7 * r) ** 2
            assert inner.any() and (canvas[inner][:, 0] > 200).mean() > 0.9
    same = [cdata.augment(img, np.array([[20.0, 25.0, 8.0]]), (64, 96), cdata.AugmentConfig(),
                          np.random.default_rng([3, 1, 2])) for _ in range(2)]
    assert np.array_equal(same[0][0], same[1][0]) and np.array_equal(same[0][1], same[1][1])


def test_colour_jitter_keeps_no_depth_black():
    img = np.zeros((8, 8, 3), np.uint8)
    img[2:6, 2:6] = (0, 128, 255)
    out = cdata.jitter_colours(img, cdata.AugmentConfig(), np.random.default_rng(0))
    assert (out[0, 0] == 0).all() and (out[2:6, 2:6].max(axis=2) > 0).all()


def test_a_circle_cut_by_the_crop_follows_the_ground_truth_rule():
    rect = (-0.5, -0.5, 30.5, 40.5)
    assert np.array_equal(cdata._clip_circle(np.array([10.0, 10.0, 5.0]), rect, 16), [10.0, 10.0, 5.0])
    # centre outside: the visible lens's enclosing circle has the chord at u = 30 as diameter
    cut = cdata._clip_circle(np.array([33.0, 20.0, 8.0]), rect, 16)
    np.testing.assert_allclose(cut, [30.0, 20.0, math.sqrt(64 - 9)], atol=0.5)
    assert cdata._clip_circle(np.array([40.0, 20.0, 8.0]), rect, 16) is None  # outside


def test_other_sensor_modes_are_scaled_to_the_model_size(tmp_path):
    recs = cdata.read_dataset(make_dataset(tmp_path / "d", n=4, negatives=0, double_every=2))
    assert [(r.height, r.width) for r in recs] == [(48, 64), (96, 128)] * 2
    ds = cdata.CircleDataset(recs, (48, 64))
    for i in (1, 3):  # the 128x96 images, halved
        item = ds[i]
        assert item["image"].shape == (3, 64, 64) and ds.scale_of(i) == 0.5
        (cx, cy, r), = recs[i].circles
        np.testing.assert_allclose(item["radius"][0, 0] * STRIDE, r / 2, rtol=1e-6)
        y, x = divmod(int(item["cells"][0]), 16)
        got = grid_to_pixel(np.array([x, y]) + item["offset"][0])
        np.testing.assert_allclose(got, [(cx + 0.5) / 2 - 0.5, (cy + 0.5) / 2 - 0.5], atol=1e-5)
    image = np.zeros((96, 128, 3), np.uint8)
    image[::2, ::2] = 200
    fitted, s = fit_image(image, (48, 64))
    assert s == 0.5 and fitted.shape == (48, 64, 3) and set(np.unique(fitted)) <= {0, 200}


# ---------------------------------------------------------------- training

def test_a_tiny_model_overfits_eight_images(tmp_path):
    recs = cdata.read_dataset(make_dataset(tmp_path / "d", n=8, negatives=0))
    ds = cdata.CircleDataset(recs, (48, 64), augment=None)
    batch = torch.utils.data.default_collate([ds[i] for i in range(len(ds))])
    torch.manual_seed(0)
    model = CircleNet(CircleNetConfig(image_size=(48, 64), **TINY))
    opt = torch.optim.Adam(model.parameters(), lr=5e-3)
    x = batch["image"].float()
    losses = []
    for _ in range(60):
        loss, _ = circlenet_loss(model.forward_stages(x), batch)
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(float(loss.detach()))
    assert np.mean(losses[-5:]) < 0.3 * np.mean(losses[:5])
    # and the best peak of each image lies on its ball
    model.eval()
    with torch.no_grad():
        found = decode(*model(x), top_k=1, image_size=(48, 64))[:, 0].numpy()
    gt = np.array([r.circles[0] for r in recs])
    assert np.median(np.hypot(*(found[:, :2] - gt[:, :2]).T)) < 3.0


def test_narrow_models_train_on_contiguous_tensors_on_the_cpu():
    """A width-8 backbone's strided 1x1 convolutions take 8 channels: torch 2.13's CPU backward of
    those on channels-last tensors aborts the process at the model's image size, so training keeps
    them contiguous (in a child process: the failure is a crash, not an exception)."""
    assert ctrain.memory_format(CircleNet(CircleNetConfig(resnet_width=8)), "cpu") == torch.contiguous_format
    assert ctrain.memory_format(CircleNet(CircleNetConfig(resnet_width=32)), "cpu") == torch.channels_last
    step = ("import torch\n"
            "from spherebench.baselines.circlenet.model import CircleNet, CircleNetConfig\n"
            "from spherebench.baselines.circlenet.train import memory_format\n"
            "model = CircleNet(CircleNetConfig(resnet_width=8))\n"
            "layout = memory_format(model, 'cpu')\n"
            "model = model.to(memory_format=layout)\n"
            "x = torch.randn(1, 3, 256, 448).contiguous(memory_format=layout)\n"
            "sum(t.sum() for t in model(x)).backward()\n")
    done = subprocess.run([sys.executable, "-c", step], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]


def test_coco_circle_map_on_known_cases():
    gt = {1: np.array([[10.0, 10.0, 5.0]]), 2: np.zeros((0, 3)), 3: np.array([[30.0, 20.0, 8.0]])}
    perfect = {1: np.array([[10.0, 10.0, 5.0, 0.9]]), 3: np.array([[30.0, 20.0, 8.0, 0.8]])}
    assert ctrain.coco_circle_map(gt, perfect)["mAP"] == pytest.approx(1.0)
    # a circle shifted by 2 px of r = 5 (IoU ~0.6): counts at IoU 0.5, not at 0.75
    # (at 0.75 recall stops at 0.5 with precision 1: 51 of the 101 recall points)
    shifted = {1: np.array([[12.0, 10.0, 5.0, 0.7]]), 3: np.array([[30.0, 20.0, 8.0, 0.8]])}
    m = ctrain.coco_circle_map(gt, shifted)
    assert m["mAP50"] == pytest.approx(1.0) and m["mAP75"] == pytest.approx(51 / 101)
    # a confident false positive on the negative image ranks above one true positive
    fp = {**perfect, 2: np.array([[5.0, 5.0, 3.0, 0.95]])}
    assert ctrain.coco_circle_map(gt, fp)["mAP50"] < 1.0
    assert ctrain.coco_circle_map(gt, {})["mAP"] == 0.0


def _weights(path):
    return torch.load(path, map_location="cpu", weights_only=True)["model"]


def test_train_writes_everything_and_resume_gives_the_same_model(tmp_path, tiny_data, monkeypatch):
    card = ctrain.train(tiny_data, tmp_path / "full", tiny_config(), seed=3, progress=False)
    for name in ("checkpoint.pt", "history.json", "training_curve.png", "model.onnx", "model_card.json", "model_card.md"):
        assert (tmp_path / "full" / name).is_file(), name
    assert card["seed"] == 3 and card["epochs"] == 2 and card["data"]["val_images"] == 1
    assert card["data"]["train_images"] == 9 and card["data"]["preset"] == "test"
    assert 0.0 <= card["val_onnx"]["mAP50"] <= 1.0 and len(json.loads((tmp_path / "full/history.json").read_text())["val"]) == 2
    assert cv2.imread(str(tmp_path / "full" / "training_curve.png")) is not None

    # interrupted in the middle of epoch 2 (checkpoints after every batch), then resumed
    calls = {"n": 0}
    real = ctrain._learning_rate

    def crash_at_iteration_3(cfg, it, total):
        calls["n"] += 1
        if calls["n"] == 4:
            raise KeyboardInterrupt
        return real(cfg, it, total)

    monkeypatch.setattr(ctrain, "_learning_rate", crash_at_iteration_3)
    with pytest.raises(KeyboardInterrupt):
        ctrain.train(tiny_data, tmp_path / "cut", tiny_config(checkpoint_minutes=0), seed=3, progress=False)
    monkeypatch.setattr(ctrain, "_learning_rate", real)
    # what --resume reads, and nothing else of the run's (the history travels in the checkpoint)
    assert sorted(p.name for p in (tmp_path / "cut").iterdir() if not p.name.startswith(".")) == ["checkpoint.pt"]
    state = torch.load(tmp_path / "cut" / "checkpoint.pt", map_location="cpu", weights_only=True)
    assert (state["epoch"], state["batch_pos"]) == (1, 1)
    with pytest.raises(SphereBenchError, match="already holds a training run"):
        ctrain.train(tiny_data, tmp_path / "cut", tiny_config(), seed=3, progress=False)
    with pytest.raises(SphereBenchError, match="other settings"):
        ctrain.train(tiny_data, tmp_path / "cut", tiny_config(lr=1e-2), seed=3, resume=True, progress=False)
    ctrain.train(tiny_data, tmp_path / "cut", None, seed=3, resume=True, progress=False)
    a, b = _weights(tmp_path / "full" / "checkpoint.pt"), _weights(tmp_path / "cut" / "checkpoint.pt")
    assert all(torch.equal(a[k], b[k]) for k in a)


def test_training_on_two_folders_keeps_their_scenes_apart(tmp_path, tiny_data):
    other = make_dataset(tmp_path / "other", n=6, double_every=3, seed=5)
    one, both = ctrain.read_datasets(tiny_data), ctrain.read_datasets([tiny_data, other])
    assert [r.scene_id for r in one] == [r.scene_id for r in ctrain.read_datasets([tiny_data])]
    assert len(both) == 16 and len({r.image_id for r in both}) == 16  # same scene names, told apart
    assert len({r.scene_id for r in both}) == 16 and {r.path for r in both} == {r.path for r in one} | {
        r.path for r in ctrain.read_datasets(other)}
    with pytest.raises(SphereBenchError, match="given twice"):
        ctrain.read_datasets([tiny_data, tiny_data])
    card = ctrain.train([tiny_data, other], tmp_path / "run", tiny_config(epochs=1), seed=3, progress=False)
    assert card["data"]["train_images"] + card["data"]["val_images"] == 16
    assert [d["train_dir"] for d in card["data"]["datasets"]] == [str(tiny_data), str(other)]
    assert f"`{other}` (preset test, seed 5)" in (tmp_path / "run" / "model_card.md").read_text()


# ---------------------------------------------------------------- ONNX

@pytest.mark.parametrize("backbone", ["resnet18", "hourglass"])
def test_onnx_and_torch_heads_agree(tmp_path, tiny_data, backbone):
    torch.manual_seed(0)
    model = CircleNet(CircleNetConfig(backbone=backbone, image_size=(48, 64), **TINY))
    with torch.no_grad():  # non-trivial weights and batch-norm statistics, as after training
        for p in model.parameters():
            p.add_(0.05 * torch.randn_like(p))
        for m in model.modules():
            if isinstance(m, torch.nn.BatchNorm2d):
                m.running_mean.uniform_(-0.2, 0.2)
                m.running_var.uniform_(0.5, 2.0)
    model.eval()
    det = CircleNetDetector(export_onnx(model, tmp_path / "m.onnx"))
    assert det.image_size == (48, 64)
    image = cv2.cvtColor(cv2.imread(str(tiny_data / "scenes/0002/image.png")), cv2.COLOR_BGR2RGB)
    onnx_heads = det.heads(image[None])
    x = torch.zeros(1, 3, 64, 64)
    x[0, :, :48, :] = torch.from_numpy(image).permute(2, 0, 1).float()
    with torch.no_grad():
        torch_heads = [t.numpy() for t in model(x)]
    for a, b in zip(onnx_heads, torch_heads):
        assert a.shape == b.shape and float(np.abs(a - b).max()) <= 1e-4
    np.testing.assert_allclose(det.detect(image, top_k=5),
                               decode(*map(torch.from_numpy, torch_heads), top_k=5, image_size=(48, 64))[0].numpy(),
                               atol=1e-3)
    # the same image in a 2x sensor mode: scaled to the model's size, the circles mapped back
    double = cv2.resize(image, (0, 0), fx=2, fy=2, interpolation=cv2.INTER_NEAREST_EXACT)
    np.testing.assert_allclose(det.detect(double, top_k=5), scale_circles(det.detect(image, top_k=5), 2.0), atol=1e-6)


def test_float16_weights_halve_the_file_and_keep_the_heads(tmp_path, tiny_data):
    import onnx
    torch.manual_seed(0)
    model = CircleNet(CircleNetConfig(image_size=(48, 64), **TINY)).eval()
    full = export_onnx(model, tmp_path / "f32.onnx")
    half = export_onnx(model, tmp_path / "f16.onnx", weights="float16")
    assert half.stat().st_size < 0.6 * full.stat().st_size
    inits = onnx.load(str(half)).graph.initializer
    assert not any(i.data_type == onnx.TensorProto.FLOAT for i in inits)
    a, b = CircleNetDetector(full), CircleNetDetector(half)
    assert b.metadata["weights"] == "float16" and "weights" not in a.metadata
    image = cv2.cvtColor(cv2.imread(str(tiny_data / "scenes/0002/image.png")), cv2.COLOR_BGR2RGB)
    for x, y in zip(a.heads(image[None]), b.heads(image[None])):  # float32 arithmetic, rounded weights only
        assert x.dtype == y.dtype == np.float32 and float(np.abs(x - y).max()) < 1e-2
    with pytest.raises(SphereBenchError, match="weights must be"):
        export_onnx(model, tmp_path / "x.onnx", weights="int8")


# ---------------------------------------------------------------- the command line

def _cli(monkeypatch, capsys, *argv):
    monkeypatch.setattr(sys, "argv", ["spherebench", *argv])
    rc = main(list(argv))
    return rc, capsys.readouterr()


def test_cli_train_then_detect_2d(tmp_path, tiny_data, monkeypatch, capsys):
    out = tmp_path / "run"
    rc, cap = _cli(monkeypatch, capsys, "train", "--data", str(tiny_data), "--out", str(out), "--epochs", "1",
                   "--batch-size", "4", "--seed", "1", "--image-size", "64x48", "--quiet")
    assert rc == 0, cap.err
    assert "validation mAP" in cap.out
    card = json.loads((out / "model_card.json").read_text())
    assert card["command"].startswith("spherebench train --data") and card["config"]["model"]["backbone"] == "resnet18"
    rc, cap = _cli(monkeypatch, capsys, "detect-2d", str(tiny_data / "scenes/0002"),
                   str(tiny_data / "scenes/0004/image.png"), "--model", str(out / "model.onnx"), "--json",
                   "--min-score", "0", "--top-k", "3")
    assert rc == 0, cap.err
    lines = [json.loads(s) for s in cap.out.strip().splitlines()]
    assert [d["input"] for d in lines] == [str(tiny_data / "scenes/0002"), str(tiny_data / "scenes/0004/image.png")]
    for d in lines:
        assert len(d["detections"]) == 3 and d["ms"] > 0
        c = d["detections"][0]
        assert len(c["circle_px"]["center"]) == 2 and c["circle_px"]["radius"] >= 0 and 0 < c["score"] < 1
        assert c["center_m"] is None and c["radius_m"] is None  # a 2D detector knows no metres
        assert [x["score"] for x in d["detections"]] == sorted((x["score"] for x in d["detections"]), reverse=True)
    rc, cap = _cli(monkeypatch, capsys, "detect-2d", str(tiny_data / "scenes/0002"), "--model", str(out / "model.onnx"))
    assert rc == 0 and cap.out.startswith(str(tiny_data / "scenes/0002") + ": ")
    # resuming takes the run's settings (batch size 4, 1 epoch); a finished run is only re-exported
    rc, cap = _cli(monkeypatch, capsys, "train", "--data", str(tiny_data), "--out", str(out), "--seed", "1",
                   "--resume", "--quiet", "--workers", "0")
    assert rc == 0, cap.err
    _one_line_error(monkeypatch, capsys, "train", "--data", str(tiny_data), "--out", str(out), "--seed", "1",
                    "--resume", "--epochs", "5", match="other settings (epochs)")


# ---------------------------------------------------------------- bad input

def _one_line_error(monkeypatch, capsys, *argv, match):
    rc, cap = _cli(monkeypatch, capsys, *argv)
    assert rc == 2
    assert len(cap.err.strip().splitlines()) == 1 and match in cap.err, cap.err


def test_cli_train_options_reach_the_config(monkeypatch, capsys, tmp_path):
    seen = []

    def fake_train(data, out, config, **kw):
        seen.append(config)
        return {"val_onnx": {"mAP": 0.0, "mAP50": 0.0, "mAP75": 0.0}, "epochs": config.epochs, "train_seconds": 0.0}

    monkeypatch.setattr(ctrain, "train", fake_train)
    base = ("train", "--data", str(tmp_path), "--out", str(tmp_path / "o"))
    assert _cli(monkeypatch, capsys, *base)[0] == 0
    assert _cli(monkeypatch, capsys, *base, "--resnet-width", "64", "--onnx-weights", "float16")[0] == 0
    default, full = seen
    assert (default.model.resnet_width, default.onnx_weights) == (32, "float32")  # `make train`'s model
    assert (full.model.backbone, full.model.resnet_width, full.onnx_weights) == ("resnet18", 64, "float16")
    _one_line_error(monkeypatch, capsys, *base, "--resnet-width", "0", match="--resnet-width 0: give 1 to 256")
    _one_line_error(monkeypatch, capsys, *base, "--backbone", "hourglass", "--resnet-width", "64",
                    match="no effect on --backbone hourglass")


@pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has a GPU")
def test_training_on_cuda_without_a_gpu_is_a_clear_error(tmp_path, tiny_data, monkeypatch, capsys):
    _one_line_error(monkeypatch, capsys, "train", "--data", str(tiny_data), "--out", str(tmp_path / "o"),
                    "--device", "cuda", "--epochs", "1", match="no CUDA device")


def test_bad_models_are_clear_errors(tmp_path, tiny_data, monkeypatch, capsys):
    img = str(tiny_data / "scenes/0001/image.png")
    _one_line_error(monkeypatch, capsys, "detect-2d", img, "--model", str(tmp_path / "none.onnx"), match="not found")
    (tmp_path / "bad.onnx").write_bytes(b"\x08\x07garbage" * 100)
    _one_line_error(monkeypatch, capsys, "detect-2d", img, "--model", str(tmp_path / "bad.onnx"), match="not a valid ONNX")
    # an ONNX file that is not ours
    with warnings.catch_warnings():  # the legacy exporter warns that it is legacy
        warnings.simplefilter("ignore")
        torch.onnx.export(torch.nn.Conv2d(3, 1, 1), (torch.zeros(1, 3, 8, 8),), str(tmp_path / "other.onnx"),
                          dynamo=False, opset_version=17)
    _one_line_error(monkeypatch, capsys, "detect-2d", img, "--model", str(tmp_path / "other.onnx"),
                    match="not a SphereBench CircleNet")


def test_bad_images_are_clear_errors(tmp_path, tiny_data, monkeypatch, capsys):
    model = export_onnx(CircleNet(CircleNetConfig(image_size=(48, 64), **TINY)).eval(), tmp_path / "m.onnx")
    cv2.imwrite(str(tmp_path / "big.png"), np.zeros((240, 424, 3), np.uint8))
    cv2.imwrite(str(tmp_path / "depth.png"), np.zeros((48, 64), np.uint16))
    (tmp_path / "text.png").write_text("not an image")
    (tmp_path / "empty_scene").mkdir()
    for name, match in (("depth.png", "depth image"), ("text.png", "not a readable image"),
                        ("missing.png", "not found"), ("empty_scene", "without image.png")):
        _one_line_error(monkeypatch, capsys, "detect-2d", str(tmp_path / name), "--model", str(model), match=match)
    for focal in ("0", "nan", "-3"):  # any image size runs (tests/test_circlenet_sizes.py), a focal length must be one
        _one_line_error(monkeypatch, capsys, "detect-2d", str(tmp_path / "big.png"), "--model", str(model),
                        "--focal-px", focal, match="--focal-px must be a positive number")
    _one_line_error(monkeypatch, capsys, "detect-2d", str(tmp_path / "big.png"), "--model", str(model),
                    "--focal-px", "0.001", match="is the focal length in pixels?")
    det = CircleNetDetector(model)
    with pytest.raises(SphereBenchError, match="uint8"):
        det.detect(np.zeros((48, 64, 3), np.float32))


def test_bad_training_folders_are_clear_errors(tmp_path, tiny_data, monkeypatch, capsys):
    (tmp_path / "empty").mkdir()
    _one_line_error(monkeypatch, capsys, "train", "--data", str(tmp_path / "empty"), "--out", str(tmp_path / "o"),
                    match="no coco_gt.json")
    (tmp_path / "noimg").mkdir()
    (tmp_path / "noimg" / "coco_gt.json").write_text(json.dumps({"images": [], "annotations": []}))
    _one_line_error(monkeypatch, capsys, "train", "--data", str(tmp_path / "noimg"), "--out", str(tmp_path / "o"),
                    match="no images")
    (tmp_path / "broken").mkdir()
    (tmp_path / "broken" / "coco_gt.json").write_text("{")
    _one_line_error(monkeypatch, capsys, "train", "--data", str(tmp_path / "broken"), "--out", str(tmp_path / "o"),
                    match="coco_gt.json: not valid JSON")
    (tmp_path / "broken" / "coco_gt.json").write_text("[]")
    _one_line_error(monkeypatch, capsys, "train", "--data", str(tmp_path / "broken"), "--out", str(tmp_path / "o"),
                    match="not a COCO file")
    one = make_dataset(tmp_path / "one", n=1, negatives=0)
    _one_line_error(monkeypatch, capsys, "train", "--data", str(one), "--out", str(tmp_path / "o"), match="at least 2")
    _one_line_error(monkeypatch, capsys, "train", "--data", str(tiny_data), "--out", str(tmp_path / "o2"), "--resume",
                    match="nothing to resume")
    assert not (tmp_path / "o").exists()
