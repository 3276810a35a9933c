"""Outputs that load anywhere: one JSON schema for `detect` and `detect-2d` (docs/formats.md), and the
drawings of detections (`detect --out-png`, `show --predictions`)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from spherebench.scripts import cli
from spherebench.datasets import inout

NUMBER = (int, float)


def check_detection(d: dict, three_d: bool) -> None:
    """One detection of the schema: every field present, with its type and unit."""
    assert set(d) == {"score", "center_m", "radius_m", "circle_px", "bbox", "inliers", "visible_fraction", "raw_score"}
    assert isinstance(d["score"], NUMBER) and math.isfinite(d["score"])
    if three_d:
        assert len(d["center_m"]) == 3 and all(isinstance(v, NUMBER) for v in d["center_m"]) and d["center_m"][2] > 0
        assert isinstance(d["radius_m"], NUMBER) and 0 < d["radius_m"] < 1  # metres, not pixels
        assert isinstance(d["inliers"], int) and d["inliers"] > 0
        assert d["visible_fraction"] is None or 0.0 <= d["visible_fraction"] <= 1.0
        assert 0.0 < d["raw_score"] <= 1.0 and 0.0 < d["score"] <= 1.0
    else:
        assert d["center_m"] is None and d["radius_m"] is None and d["inliers"] is None
        assert d["visible_fraction"] is None and d["raw_score"] is None
    c = d["circle_px"]
    if c is None:
        assert d["bbox"] is None
        return
    assert set(c) == {"center", "radius"} and len(c["center"]) == 2 and c["radius"] > 0
    (cx, cy), r = c["center"], c["radius"]
    assert d["bbox"] == pytest.approx([cx - r, cy - r, 2 * r, 2 * r], abs=2e-3)


def check_record(rec: dict, three_d: bool) -> None:
    assert list(rec)[:3] == ["input", "frame", "timestamp_ms"] and list(rec)[-2:] == ["detections", "ms"]
    assert isinstance(rec["input"], str) and rec["ms"] > 0
    assert (rec["frame"] is None) == (rec["timestamp_ms"] is None)
    for d in rec["detections"]:
        check_detection(d, three_d)
    scores = [d["score"] for d in rec["detections"]]
    assert scores == sorted(scores, reverse=True)


def _lines(capsys, *argv) -> list[dict]:
    assert cli.main([str(a) for a in argv]) == 0
    return [json.loads(x) for x in capsys.readouterr().out.strip().splitlines()]


def test_detect_and_detect_2d_print_one_schema(small_default, capsys):
    scenes = inout.list_scenes(small_default)[:2]
    three = _lines(capsys, "detect", *scenes, "--json")
    two = _lines(capsys, "detect-2d", *scenes, "--json", "--min-score", "0.1")
    assert len(three) == len(two) == 2
    for rec3, rec2, scene in zip(three, two, scenes):
        check_record(rec3, three_d=True)
        check_record(rec2, three_d=False)
        assert rec3["frame"] is None and rec3["radius_source"] == "dataset"
        # the same ball, in the same pixels: the circles of both detectors agree
        gt = inout.read_json(scene / "gt.json")["balls"][0]["circle"]
        for rec in (rec3, rec2):
            c = rec["detections"][0]["circle_px"]
            assert np.hypot(c["center"][0] - gt[0], c["center"][1] - gt[1]) < 4


def test_out_png_draws_every_sphere_with_its_score(small_default, tmp_path, capsys):
    scene = inout.list_scenes(small_default)[0]
    png = tmp_path / "d.png"
    assert cli.main(["detect", str(scene), "--out-png", str(png)]) == 0
    capsys.readouterr()
    drawn, image = inout.read_image(png), inout.read_image(scene / "image.png")
    changed = np.any(drawn != image, axis=2)
    magenta = (drawn[..., 0] > 200) & (drawn[..., 1] < 80) & (drawn[..., 2] > 200)
    assert changed.sum() > 100 and magenta.sum() > 50


def test_show_draws_a_methods_predictions(small_default, tmp_path, capsys):
    scene = inout.list_scenes(small_default)[0]
    det = _lines(capsys, "detect", scene, "--json")[0]["detections"]
    c = det[0]["circle_px"]
    preds = tmp_path / "results" / "predictions" / small_default.name / "mine.json"
    preds.parent.mkdir(parents=True)
    preds.write_text(json.dumps([{"image_id": 0, "category_id": 1, "circle_center": c["center"],
                                  "circle_radius": c["radius"], "score": det[0]["score"], "scene_id": scene.name},
                                 {"image_id": 1, "category_id": 1, "circle_center": [5, 5], "circle_radius": 3,
                                  "score": 0.9, "scene_id": "another"}]))
    gt_only, with_method = tmp_path / "gt.png", tmp_path / "mine.png"
    assert cli.main(["show", str(scene), "--out-png", str(gt_only), "--out-ply", str(tmp_path / "a.ply")]) == 0
    assert cli.main(["show", str(scene), "--method", "mine", "--results", str(tmp_path / "results"),
                     "--out-png", str(with_method), "--out-ply", str(tmp_path / "b.ply")]) == 0
    out = capsys.readouterr().out
    assert "1 detection(s)" in out and f"score {det[0]['score']:.2f}" in out
    assert np.any(inout.read_image(gt_only) != inout.read_image(with_method))
    assert cli.main(["show", str(scene), "--predictions", str(preds), "--out-png", str(tmp_path / "p.png"),
                     "--out-ply", str(tmp_path / "c.ply")]) == 0
    assert np.any(inout.read_image(tmp_path / "p.png") != inout.read_image(gt_only))
    capsys.readouterr()
    assert cli.main(["show", str(scene), "--method", "absent", "--results", str(tmp_path / "results"),
                     "--out-png", str(tmp_path / "x.png")]) == 2
    assert "not found" in capsys.readouterr().err and not (tmp_path / "x.png").exists()
    # a circle that is no finite pixel circle: one line, nothing drawn
    for centre, radius in (([5, 5], float("nan")), ([5, 5], 1e308), ([float("inf"), 5], 3)):
        bad = tmp_path / "bad.json"
        bad.write_text(json.dumps([{"image_id": 0, "category_id": 1, "circle_center": centre, "circle_radius": radius,
                                    "score": 0.9, "scene_id": scene.name}]))
        assert cli.main(["show", str(scene), "--predictions", str(bad), "--out-png", str(tmp_path / "y.png")]) == 2
        err = capsys.readouterr().err
        assert ("not a finite pixel circle" in err or "finite number" in err) and len(err.strip().splitlines()) == 1
        assert not (tmp_path / "y.png").exists()


def test_provider_and_missing_models_are_one_line_errors(small_default, tmp_path, capsys, monkeypatch):
    import onnxruntime as ort

    from spherebench.eval.bench import registry

    scene = inout.list_scenes(small_default)[0]
    if "CUDAExecutionProvider" not in ort.get_available_providers():
        assert cli.main(["detect-2d", str(scene), "--provider", "cuda"]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and "onnxruntime-gpu" in err
    # a CircleNet asked for by name whose model is not there stops the run before anything is written
    monkeypatch.setitem(registry.CIRCLENET_MODELS, "circlenet-hg", ("absent/model.onnx", "make train-hg"))
    assert cli.main(["evaluate", "--data", str(small_default), "--out", str(tmp_path / "res"),
                     "--methods", "circlenet-hg"]) == 2
    err = capsys.readouterr().err
    assert "circlenet-hg" in err and "not there" in err and not (tmp_path / "res").exists()
