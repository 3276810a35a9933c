"""The robust preset's figures per sensor cell and range band (eval.metrics.sensor_grid, the report's rows and
the robustness figure), on synthetic rows and a few generated scenes."""

from __future__ import annotations

import math

import numpy as np
import pytest

from spherebench import provenance
from spherebench.baselines.hough import HoughConfig
from spherebench.datasets import simulate
from spherebench.eval.bench import cache, figures, registry, scoring, studies
from spherebench.eval.bench.evaluate import evaluate
from spherebench.eval.metrics import sensor_grid
from spherebench.eval.metrics.coco_eval import coco_from_circles, evaluate_circles, results_from_circles


def test_bands_keys_and_rates():
    assert [sensor_grid.band_of(d) for d in (0.0, 0.99, 1.0, 2.5, 3.0, 3.01, float("nan"))] == \
        ["0-1 m", "0-1 m", "1-2 m", "2-3 m", "2-3 m", None, None]
    assert sensor_grid.surface_distance_m([0.0, 0.6, 0.8], 0.12) == pytest.approx(0.88)
    cell = {"cell": 3, "subpixel": 0.05, "correlation": "1px", "dropouts": "on"}
    assert sensor_grid.grid_key(cell) == (0.05, "1px", "on")
    assert sensor_grid.grid_key(cell, ("subpixel",)) == (0.05,)
    assert sensor_grid.grid_key(None) is None and sensor_grid.grid_key({"subpixel": 0.05}) is None
    a, b = (0.05, "0-1 m"), (0.05, "2-3 m")
    rates = sensor_grid.detection_rates([a, a, b, None, b], [0.001, np.nan, 0.03, 0.0, 0.02])
    assert rates == {a: {"n_balls": 2, "found": 1, "rate": 0.5}, b: {"n_balls": 2, "found": 1, "rate": 0.5}}


def _two_band_gt():
    """Two images: image 0 a ball at 0.5 m (band 0-1), image 1 a ball at 2.5 m (band 2-3)."""
    gt = coco_from_circles([[(100, 100, 30)], [(300, 100, 10)]], image_size=(424, 240))
    for ann, z in zip(gt["annotations"], (0.62, 2.62)):
        ann["center_m"] = [0.0, 0.0, z]
    return gt


def test_map50_per_band_ignores_other_bands_and_keeps_false_positives():
    gt = _two_band_gt()
    near = lambda a: sensor_grid.band_of(sensor_grid.surface_distance_m(a["center_m"], 0.12))  # noqa: E731
    hits = results_from_circles([[(100, 100, 30, 0.9)], [(300, 100, 10, 0.8)]])
    # both balls found: each band scores its own ball, the other one is ignored, not a false positive
    maps = sensor_grid.map50_by_group(gt, hits, {0: ("x",), 1: ("x",)}, near)
    assert maps[("x", "0-1 m")] == {"n_images": 2, "n_gt": 1, "mAP50": pytest.approx(1.0)}
    assert maps[("x", "2-3 m")]["mAP50"] == pytest.approx(1.0) and maps[("x", "1-2 m")]["mAP50"] is None
    # a detection on no ball, scored above both hits, is a false positive in every band
    fp = hits + results_from_circles([[(400, 200, 12, 0.95)]])
    maps = sensor_grid.map50_by_group(gt, fp, {0: ("x",), 1: ("x",)}, near)
    assert maps[("x", "0-1 m")]["mAP50"] == pytest.approx(0.5) == maps[("x", "2-3 m")]["mAP50"]
    # a group is its images only; keep_gt leaves the whole-image figures as they were
    assert sensor_grid.map50_by_group(gt, fp, {0: ("a",), 1: ("b",)}, near)[("a", "2-3 m")]["mAP50"] is None
    whole = evaluate_circles(gt, fp)
    assert whole["n_gt"] == 2 and whole["mAP50"] == pytest.approx(2 / 3)


def _rows(method_rate, map50, three_d=True):
    rows = []
    for sub in (0.05, 0.12, 0.20):
        for corr in ("none", "1px"):
            for drop in ("off", "on"):
                for band in ("0-1 m", "1-2 m", "2-3 m"):
                    rate = method_rate(sub, corr, drop, band)
                    rows.append({"subpixel": sub, "correlation": corr, "dropouts": drop, "band": band,
                                 "n_images": 20, "n_balls": 8, "found_2cm": round(8 * rate) if three_d else None,
                                 "within_2cm": rate if three_d else None, "mAP50": map50})
    return rows


def test_robustness_figure_from_rows_with_a_ceiling(tmp_path):
    rows = {"improved": _rows(lambda s, c, d, b: 1.0 - s * (2 if d == "on" else 1), 0.9),
            "hough": _rows(lambda *a: 0.0, 0.4, three_d=False), "circlenet": []}
    ceiling = {sensor_grid.ceiling_key(r): 1.0 for r in rows["improved"] if r["band"] == "2-3 m"}
    path = tmp_path / "robustness.png"
    figures.robustness("robust", rows, path, ceiling=ceiling)
    assert path.stat().st_size > 10_000
    # an oracle's per-ball rows give the ceiling dict
    balls = [{"cell": {"subpixel": 0.05, "correlation": "none", "dropouts": "off"}, "band": "2-3 m", "separable": s}
             for s in (True, True, False, None)] + [{"cell": None, "band": "0-1 m", "separable": True}]
    assert sensor_grid.ceiling_by_cell(balls) == {(0.05, "none", "off", "2-3 m"): 0.5}
    # the figure's input is metrics.json's content: exact-rule sets with per-cell rows
    metrics = {"improved": {"robust": {"sensor_cells": rows["improved"]}},
               "improved+paper-circle": {"robust": {"sensor_cells": rows["improved"]}},
               "hough": {"robust": {"sensor_cells": rows["hough"]}, "default": {}}, "paper": {"default": {}}}
    assert list(scoring.sensor_rows_by_method(metrics, "robust")) == ["improved", "hough"]


@pytest.fixture(scope="module")
def tiny_robust(tmp_path_factory):
    """Four scenes of the robust preset: cells 0-3 (subpixel 0.05; correlation x dropouts)."""
    return simulate.generate_dataset("robust", tmp_path_factory.mktemp("robustdata") / "robust", n=4, progress=False)


def test_robust_cells_through_the_stage_files(tiny_robust, tmp_path):
    metrics = evaluate({"robust": tiny_robust}, tmp_path / "out", methods=["improved", "hough"], workers=1,
                       hough_config=HoughConfig(), progress=False, log=lambda m: None)
    # every scene record of the predictions carries its cell
    _, meta = cache.read_predictions(tmp_path / "out" / "predictions" / "robust" / "improved.json")
    assert [r["sensor_cell"]["cell"] for r in meta["scenes"]] == [0, 1, 2, 3]
    cells = metrics["improved"]["robust"]["sensor_cells"]
    assert [(r["correlation"], r["dropouts"]) for r in cells[::3]] == [("none", "off"), ("none", "on"),
                                                                        ("1px", "off"), ("1px", "on")]
    assert {r["band"] for r in cells} == {"0-1 m", "1-2 m", "2-3 m"} and all(r["n_images"] == 1 for r in cells)
    assert sum(r["n_balls"] for r in cells) == 4 and sum(r["found_2cm"] for r in cells) == 4
    levels = metrics["improved"]["robust"]["sensor_levels"]
    assert [(r["subpixel"], r["band"]) for r in levels] == [(0.05, "0-1 m"), (0.05, "1-2 m"), (0.05, "2-3 m")]
    assert [r["n_images"] for r in levels] == [4, 4, 4] and sum(r["n_balls"] for r in levels) == 4
    assert all(r["mAP50"] is None or 0 <= r["mAP50"] <= 1 for r in levels)
    hough = metrics["hough"]["robust"]["sensor_cells"]
    assert all(r["within_2cm"] is None for r in hough) and any(r["mAP50"] is not None for r in hough)
    readme = (tmp_path / "out" / "README.md").read_text()
    assert (tmp_path / "out" / "figures" / "robustness_robust.png").is_file()
    assert "figures/robustness_robust.png" in readme and "Per sensor noise level and range band" in readme
    assert "`improved` finds 100.0 % of the balls within 2 cm" in readme
    assert (tmp_path / "out" / "tables" / "sensor_robust.csv").read_text().startswith("method,subpixel (px),")


def test_oracle_ceiling_rows_are_cached(tiny_robust, tmp_path):
    pytest.importorskip("spherebench.eval.bench.oracle")
    logged = []
    balls = studies.oracle_balls(tiny_robust, tmp_path / "oracle.json", workers=1, log=logged.append)
    assert [(b["scene_id"], b["ball"], b["cell"]["cell"]) for b in balls] == \
        [(f"clean_{k:04d}", 0, k) for k in (0, 1)] + [(f"cluttered_{k:04d}", 0, k) for k in (2, 3)]
    assert all(b["band"] in ("0-1 m", "1-2 m", "2-3 m") and isinstance(b["within"], bool) for b in balls)
    assert studies.oracle_balls(tiny_robust, tmp_path / "oracle.json", workers=1, log=logged.append) == balls
    assert "reused" in logged[-1]
    assert set(sensor_grid.ceiling_by_cell(balls)) == {sensor_grid.grid_key(b["cell"]) + (b["band"],) for b in balls}


class _FakeDetector:
    """Records what CircleNetDetector.detect is given."""

    calls: list = []

    def __init__(self, path, threads=1):
        pass

    def detect(self, image, min_score=0.0, top_k=None, focal_px=None, scale=None):
        _FakeDetector.calls.append({"shape": image.shape, "focal_px": focal_px})
        return np.array([[10.0, 20.0, 5.0, 0.9]])


def test_circlenet_engine_scales_by_the_scene_focal_length(tiny_robust, monkeypatch):
    from spherebench.baselines.circlenet import infer
    monkeypatch.setattr(infer, "CircleNetDetector", _FakeDetector)
    scene = next(iter(sorted((tiny_robust / "scenes").iterdir())))
    config = {"engine": "circlenet", "min_score": 0.01, "top_k": 100, "scale": "focal_px"}
    engine = registry.CircleNetAdapter(config, tiny_robust / "absent.onnx")
    _FakeDetector.calls.clear()
    dets = engine.detect(engine.load(scene), 0)
    focal = infer.scene_focal_px(scene)
    assert focal is not None and math.isclose(_FakeDetector.calls[-1]["focal_px"], focal)
    assert dets == [{"score": 0.9, "circle": (10.0, 20.0, 5.0)}]
    # a configuration of before the rule keeps its width scaling (and another resume key)
    old = registry.CircleNetAdapter({k: v for k, v in config.items() if k != "scale"}, tiny_robust / "absent.onnx")
    old.detect(old.load(scene), 0)
    assert _FakeDetector.calls[-1]["focal_px"] is None


def test_circlenet_spec_key_covers_the_scaling_rule():
    path = registry.circlenet_model_path("circlenet")
    if not path.is_file():
        pytest.skip("no shipped CircleNet model")
    spec = registry.circlenet_spec(path)
    assert spec.config["scale"] == "focal_px" and "focal length" in spec.note
    assert "spherebench.eval.bench.registry" in spec.modules and "spherebench.baselines.circlenet" in spec.modules
    before = registry.MethodSpec(**{**spec.__dict__, "config": {k: v for k, v in spec.config.items() if k != "scale"}})
    args = ("circlenet", "fp", 0, provenance.code_version(spec.modules), ["s"])
    assert cache.prediction_key(spec, *args) != cache.prediction_key(before, *args)
