"""The benchmark pipeline (eval.bench.tasks, eval.bench.report, `spherebench evaluate`) on tiny generated data."""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest

from spherebench import provenance
from spherebench.baselines.hough import HoughConfig
from spherebench.datasets import inout, outputs, presets, simulate
from spherebench.datasets import fingerprint
from spherebench.errors import SphereBenchError
from spherebench.eval.bench import cache, prose, registry, report, result_tables, scoring, seeds, studies, tables, tasks

RESULT_KEYS = {"image_id", "category_id", "circle_center", "circle_radius", "bbox", "score", "scene_id"}


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    """Four scenes of the default preset (two clean, two cluttered)."""
    return simulate.generate_dataset("default", tmp_path_factory.mktemp("evaldata") / "tiny", n=4, progress=False)


def _specs(names=("improved", "paper", "pyransac3d", "hough")):
    specs = registry.build_methods(list(names), hough_config=HoughConfig())
    # keep the peer cheap in tests
    return [registry.pyransac3d_spec(points=800, iterations=60) if s.name == "pyransac3d" else s for s in specs]


def test_runner_writes_schema_and_two_rules(tiny, tmp_path):
    paths = tasks.run_methods(tiny, tmp_path, _specs(), seed=0, workers=1, progress=False, log=lambda m: None)
    assert set(paths) == {"improved", "improved+paper-circle", "paper", "paper+paper-circle", "pyransac3d",
                          "pyransac3d+paper-circle", "hough"}
    coco = inout.read_coco_gt(tiny)
    image_ids = {img["id"] for img in coco["images"]}
    for name, path in paths.items():
        results, meta = cache.read_predictions(path)
        assert isinstance(results, list)
        assert meta["output"] == name and meta["seed"] == 0 and len(meta["scenes"]) == 4
        assert meta["predictions_sha256"] == provenance.file_sha256(path)
        assert all(r["ms"] >= 0 for r in meta["scenes"])
        for r in results:
            assert RESULT_KEYS <= set(r) and r["image_id"] in image_ids and r["category_id"] == 1
            assert len(r["circle_center"]) == 2 and r["circle_radius"] > 0 and math.isfinite(r["score"])
            if meta["kind"] == "3d":
                assert len(r["center_m"]) == 3
        assert all("center_m" not in r for r in results) or meta["kind"] == "3d"
    # one detection run, two rules: same centres and scores, different circles
    exact, _ = cache.read_predictions(paths["improved"])
    paper_rule, _ = cache.read_predictions(paths["improved+paper-circle"])
    assert [r["center_m"] for r in exact] == [r["center_m"] for r in paper_rule]
    assert exact and any(a["circle_radius"] != b["circle_radius"] for a, b in zip(exact, paper_rule))
    # the improved detector finds the four simulated balls within 2 cm, and scores them
    gt = {img["id"]: img for img in coco["images"]}
    scored = scoring.score_set(paths["improved"], coco, tasks.dataset_scenes(tiny))
    assert scored.metrics["3d"]["within_2cm"] == 1.0 and scored.metrics["mAP50"] == 1.0
    assert set(scored.metrics["families"]) == {gt[i]["family"] for i in gt}
    # a predictions file loads in plain pycocotools (its bbox: the circle's box), and dropping the bbox
    # (files written before it) scores the same
    from pycocotools.coco import COCO
    from spherebench.eval.metrics.coco_eval import evaluate_circles
    plain = COCO()
    plain.dataset = json.loads(json.dumps(coco))
    for ann in plain.dataset["annotations"]:
        ann.setdefault("bbox", [0, 0, 1, 1])
    plain.createIndex()
    loaded = plain.loadRes(str(paths["improved"]))
    assert len(loaded.getAnnIds()) == len(exact)
    for r in exact:
        (cx, cy), rad = r["circle_center"], r["circle_radius"]
        assert r["bbox"] == pytest.approx([cx - rad, cy - rad, 2 * rad, 2 * rad], abs=2e-3)
    without = [{k: v for k, v in r.items() if k != "bbox"} for r in exact]
    assert evaluate_circles(coco, without)["mAP"] == evaluate_circles(coco, exact)["mAP"] == scored.metrics["mAP"]
    # pyransac3d's radius is its own and is compared against R
    py = scoring.score_set(paths["pyransac3d"], coco, tasks.dataset_scenes(tiny))
    assert all(d["radius_m"] is not None for s in py.scenes for d in s["detections"])


def test_deterministic_across_workers_and_resume(tiny, tmp_path):
    specs = _specs(("improved", "paper"))
    a = tasks.run_methods(tiny, tmp_path / "a", specs, seed=3, workers=1, progress=False, log=lambda m: None)
    b = tasks.run_methods(tiny, tmp_path / "b", specs, seed=3, workers=2, progress=False, log=lambda m: None)
    for name in a:
        assert a[name].read_bytes() == b[name].read_bytes()
    # a second run reuses the finished files
    before = {n: p.stat().st_mtime_ns for n, p in a.items()}
    logged = []
    tasks.run_methods(tiny, tmp_path / "a", specs, seed=3, workers=1, progress=False, log=logged.append)
    assert {n: p.stat().st_mtime_ns for n, p in a.items()} == before
    assert sum("reused" in m for m in logged) == 2
    # another seed: recomputed (the paper pipeline's global sampling changes with it)
    tasks.run_methods(tiny, tmp_path / "a", specs, seed=4, workers=1, progress=False, log=logged.append)
    assert all(p.stat().st_mtime_ns != before[n] for n, p in a.items())
    assert cache.read_predictions(a["paper"])[1]["seed"] == 4
    # a damaged predictions file is not reused
    a["improved"].write_text("[]")
    logged.clear()
    tasks.run_methods(tiny, tmp_path / "a", specs, seed=4, workers=1, progress=False, log=logged.append)
    assert sum("reused" in m for m in logged) == 1
    assert json.loads(a["improved"].read_text()) != []


def test_scene_seed_and_fingerprint(tiny, tmp_path):
    assert seeds.detection_seed(0, 1) == seeds.detection_seed(0, 1) != seeds.detection_seed(0, 2) != seeds.detection_seed(1, 2)
    fp = fingerprint.dataset_fingerprint(tiny)
    assert fp == fingerprint.dataset_fingerprint(tiny)
    with pytest.raises(SphereBenchError):
        fingerprint.dataset_fingerprint(tmp_path)
    with pytest.raises(SphereBenchError, match="unknown method"):
        registry.build_methods(["nope"])


def test_circlenet_skipped_when_model_missing(tmp_path):
    skipped = {}
    specs = registry.build_methods(["circlenet"], circlenet_model=tmp_path / "absent.onnx",
                                 table_note=skipped.__setitem__)
    assert specs == [] and "not found" in skipped["circlenet"]


def test_a_registered_method_joins_the_benchmark(tiny, tmp_path, monkeypatch):
    """One decorated adapter is a method: listed last, built, run by the task loop, scored."""
    monkeypatch.setattr(registry, "METHODS", dict(registry.METHODS))
    monkeypatch.setattr(registry, "ADAPTERS", dict(registry.ADAPTERS))

    @registry.register_method("centre-guess", description="`centre-guess` (the image's centre)")
    class CentreGuess:
        kind = "2d"

        def __init__(self, config, resource=None):
            pass

        def load(self, scene_dir):
            return inout.read_image(scene_dir / "image.png")

        def detect(self, image, seed):
            h, w = image.shape[:2]
            return [{"score": 0.5, "circle": (w / 2, h / 2, h / 4)}]

    assert registry.method_names()[-1] == "centre-guess" and registry.METHODS["centre-guess"].needs == "image.png"
    with pytest.raises(ValueError, match="registered already"):
        registry.register_method("centre-guess", CentreGuess)
    specs = registry.build_methods(["centre-guess"])
    assert specs[0].config == {"engine": "centre-guess"} and specs[0].kind == "2d"
    paths = tasks.run_methods(tiny, tmp_path, specs, seed=0, workers=1, progress=False, log=lambda m: None)
    results, meta = cache.read_predictions(paths["centre-guess"])
    assert len(results) == 4 and meta["method"] == "centre-guess"


def test_gpu_trained_circlenets_are_methods_and_skipped_when_missing(monkeypatch):
    assert registry.method_names()[-4:] == ("circlenet", "circlenet-analytic", "circlenet-full", "circlenet-hg")
    for name in ("circlenet-full", "circlenet-hg"):
        monkeypatch.setitem(registry.CIRCLENET_MODELS, name, (f"absent/{name}.onnx", f"make train-{name[10:]}, on a CUDA machine"))
    skipped = {}
    assert registry.build_methods(["circlenet-full", "circlenet-hg"], table_note=skipped.__setitem__) == []
    assert set(skipped) == {"circlenet-full", "circlenet-hg"}
    assert "not found" in skipped["circlenet-full"] and "`make train-full, on a CUDA machine`" in skipped["circlenet-full"]
    with pytest.raises(SphereBenchError, match="make train-hg"):
        registry.build_methods(["circlenet-hg"])


def test_shipped_gpu_circlenets_are_found(tmp_path):
    shipped = [n for n in ("circlenet-full", "circlenet-hg") if registry.circlenet_model_path(n).is_file()]
    if not shipped:
        pytest.skip("no GPU-trained CircleNet model in baselines/circlenet/")
    # --model replaces the `circlenet` file only; the others keep their own
    specs = registry.build_methods(shipped, circlenet_model=tmp_path / "absent.onnx")
    assert [s.name for s in specs] == shipped
    for s in specs:
        assert s.resource == str(registry.circlenet_model_path(s.name).resolve())
        assert s.extra_fingerprint == provenance.file_sha256(s.resource) and "on GPU" in s.note


def test_evaluate_cli(tiny, tmp_path):
    from spherebench.scripts.cli import main
    hough_file = tmp_path / "hough.json"
    hough_file.write_text(json.dumps({"param2": 15.0}))
    out = tmp_path / "out"
    rc = main(["evaluate", "--data", str(tiny), "--out", str(out), "--methods", "improved", "hough",
               "--hough-config", str(hough_file), "--workers", "1", "--quiet", "--no-figures"])
    assert rc == 0
    metrics = json.loads((out / "metrics.json").read_text())
    assert set(metrics) == {"improved", "improved+paper-circle", "hough"}
    m = metrics["improved"]["tiny"]
    assert 0.0 <= m["mAP"] <= 1.0 and m["mAP50"] >= m["mAP75"] and m["ms_median"] > 0
    assert m["3d"]["n_gt"] == 4
    for name in ("table3_tiny", "families_tiny", "metrics3d_tiny", "timings"):
        assert (out / "tables" / f"{name}.csv").is_file() and (out / "tables" / f"{name}.md").is_file()
    assert "Table 3" in (out / "README.md").read_text()
    prov = json.loads((out / "provenance.json").read_text())
    assert {"git", "packages", "machine", "seeds", "configurations", "date"} <= set(prov)
    # bad input: a one-line error, exit status 2
    assert main(["evaluate", "--data", str(tmp_path / "none"), "--out", str(out)]) == 2


def test_unannotated_scenes_get_detection_statistics(tiny, tmp_path):
    # a copy of the dataset whose scenes nobody annotated (as a raw recording)
    import shutil
    data = tmp_path / "rec"
    shutil.copytree(tiny, data)
    for scene in inout.list_scenes(data):
        gt = inout.read_json(scene / "gt.json")
        gt["annotated"], gt["balls"] = False, []
        gt["meta"] = {"reference_center_m": [0.0, 0.0, 1.0]}
        inout.write_json(scene / "gt.json", gt)
    inout.write_json(data / "coco_gt.json", inout.build_coco_gt(data))
    paths = tasks.run_methods(data, tmp_path / "p", _specs(("improved",)), workers=1, progress=False,
                               log=lambda m: None)
    assert cache.read_predictions(paths["improved"])[0] == []  # nothing to score in 2D
    scored = scoring.score_set(paths["improved"], inout.read_coco_gt(data), tasks.dataset_scenes(data))
    u = scored.metrics["unannotated"]
    assert "mAP" not in scored.metrics and "3d" not in scored.metrics
    assert u["n_scenes"] == 4 and u["scenes_with_detection"] == 4 and u["n_reference"] == 4
    assert 0.115 <= u["radius_m_median"] <= 0.125
    table = result_tables.detections_table("rec", [scored])
    assert table is not None and table.rows[0][2] == 4


def test_tables_are_never_half_written(tmp_path, monkeypatch):
    good = tables.Table("t", "T", ["a", "b"], [["1", "2"]])
    report.claim_results_dir(tmp_path)  # tables/ is replaced only inside a results folder of ours
    report.write_tables(tmp_path / "tables", [good])
    before = (tmp_path / "tables" / "t.md").read_text()

    class Broken(tables.Table):
        def markdown(self, heading=True):
            raise RuntimeError("injected failure")

    with pytest.raises(RuntimeError, match="injected"):
        report.write_tables(tmp_path / "tables", [tables.Table("t", "T", ["a"], [["changed"]]),
                                                  Broken("u", "U", ["a"], [["x"]])])
    # the old set is intact, the new one absent, and no temporary folder is left
    assert (tmp_path / "tables" / "t.md").read_text() == before
    assert not (tmp_path / "tables" / "u.csv").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == [outputs.OWNER_MARKER, "tables"]


def test_table_formats():
    t = tables.Table("x", "X", ["method", "mAP"], [["a,b", tables.fmt(0.5)], ["c", tables.fmt(None)]], ["n1"])
    assert t.csv().splitlines() == ["method,mAP", '"a,b",0.500', "c,–"]
    md = t.markdown().splitlines()  # pandas' Markdown (tabulate's pipe table), columns padded to one width
    assert md[:2] == ["### X", ""] and md[2].split("|")[1:3] == [" method   ", " mAP   "]
    assert [c.strip() for c in md[5].split("|")[1:3]] == ["c", "–"] and md[-1] == "- n1"
    assert tables.fmt(-1e-9, 1, 1000) == "0.0"


def test_table2_on_the_paper_preset(paper_dataset):
    rows = studies.table2_rows(paper_dataset, seed=0, iterations=300)
    assert [(r["scene"], r["z"]) for r in rows] == [(s, z) for s in ("E1", "E2", "E3") for z in (3.0, 2.0, 1.5)]
    assert all(r["iterations"] == 300 for r in rows)
    e1 = [r for r in rows if r["scene"] == "E1"]
    assert all("rmse_ransac" in r for r in e1)  # the ball fills E1: the paper's pipeline finds it
    # one RANSAC draw per scene: the thresholds share the inliers and the RANSAC RMSE
    assert len({r["rmse_ransac"] for r in e1}) == 1 and len({r["n_inliers"] for r in e1}) == 1
    assert e1[0]["n_filtered"] >= e1[1]["n_filtered"] >= e1[2]["n_filtered"]
    # the barycentre of the visible cap is not the centre; least squares with R fixed is
    for r in e1:
        assert r["error_refined_m"] < 0.005 < r["error_barycentre_m"]
        assert r["paper"]["rmse_ransac"] == pytest.approx(0.007343368)
    table = result_tables.table2_table(rows)
    assert len(table.rows) == 9 and table.rows[0][6] == "0.007343"


def test_reading_and_readme_from_scores(tiny, tmp_path):
    paths = tasks.run_methods(tiny, tmp_path, _specs(("improved",)), workers=1, progress=False, log=lambda m: None)
    coco = inout.read_coco_gt(tiny)
    scenes = tasks.dataset_scenes(tiny)
    sets = [scoring.score_set(paths[o], coco, scenes) for o in ("improved", "improved+paper-circle")]
    text = prose.reading({"default": sets}, None, {"circlenet": "model file not found"})
    assert any("improved" in s and f"{sets[0].metrics['mAP']:.3f}" in s for s in text)
    assert any("circlenet" in s and "not found" in s for s in text)
    t3 = result_tables.table3("default", sets)
    assert [r[0] for r in t3.rows][:2] == ["improved", "improved+paper-circle"]
    cells = [str(c) for r in t3.rows for c in r]
    assert any("0.512" in c for c in cells) and any("0.843" in c for c in cells)
    assert np.isfinite(sets[0].pr50).any()


def test_the_reading_names_presets_and_methods_by_their_registered_roles(tiny, tmp_path, monkeypatch):
    """The protocol's sentences follow the preset and the method that hold its roles, not their names."""
    paths = tasks.run_methods(tiny, tmp_path, _specs(("improved",)), workers=1, progress=False, log=lambda m: None)
    coco, scenes = inout.read_coco_gt(tiny), tasks.dataset_scenes(tiny)
    sets = [scoring.score_set(paths[o], coco, scenes) for o in ("improved", "improved+paper-circle")]
    protocol = presets.PRESETS["default"]
    monkeypatch.setitem(presets.PRESETS, "default", dataclasses.replace(protocol, role=""))
    monkeypatch.setitem(presets.PRESETS, "mine", dataclasses.replace(protocol, name="mine", description="my protocol"))
    text = prose.reading({"mine": sets}, None, {})
    assert text[0].startswith("On `mine` (my protocol) the best circle mAP is improved's")
    assert any(s.startswith("In 3D, `improved` finds") and "of the `mine` balls" in s for s in text)
    monkeypatch.setattr(registry, "METHODS", {n: dataclasses.replace(m, role="") for n, m in registry.METHODS.items()})
    assert not any(s.startswith("In 3D") for s in prose.reading({"mine": sets}, None, {}))


def test_circlenet_runs_from_an_onnx_file(tiny, tmp_path):
    torch = pytest.importorskip("torch")
    from spherebench.baselines.circlenet.model import CircleNet, CircleNetConfig
    from spherebench.baselines.circlenet.onnx_export import export_onnx
    torch.manual_seed(0)  # an untrained small model: the pipeline is under test, not its accuracy
    model = export_onnx(CircleNet(CircleNetConfig(resnet_width=8, neck_channels=16, head_channels=16)),
                        tmp_path / "m.onnx")
    specs = registry.build_methods(["circlenet"], circlenet_model=model)
    assert [s.name for s in specs] == ["circlenet"] and specs[0].extra_fingerprint == provenance.file_sha256(model)
    paths = tasks.run_methods(tiny, tmp_path / "p", specs, workers=1, progress=False, log=lambda m: None)
    results, meta = cache.read_predictions(paths["circlenet"])
    assert meta["kind"] == "2d" and len(meta["scenes"]) == 4
    assert all(RESULT_KEYS <= set(r) and "center_m" not in r for r in results)
    assert all(registry.SCORE_FLOOR <= r["score"] <= 1.0 for r in results)
    assert all(len(s["detections"]) <= registry.MAX_DETECTIONS for s in meta["scenes"])


def test_transfer_table_pairs_a_preset_with_its_stereo_twin(tiny, tmp_path):
    from spherebench.scripts.cli import main
    from spherebench.eval.bench import transfer
    from spherebench.eval.metrics import metrics3d

    twin = simulate.generate_dataset("default-stereo", tmp_path / "tiny-stereo", n=4, progress=False)
    other = simulate.generate_dataset("hard", tmp_path / "hardish", n=2, progress=False)  # nobody's twin
    assert transfer.transfer_pairs({"tiny": tiny, "hardish": other, "tiny-stereo": twin}) == [("tiny", "tiny-stereo")]
    assert transfer.transfer_pairs({"tiny-stereo": twin}) == []
    out = tmp_path / "out"
    assert main(["evaluate", "--data", str(tiny), "--data", str(twin), "--out", str(out), "--methods", "improved",
                 "--workers", "1", "--quiet"]) == 0
    metrics = json.loads((out / "metrics.json").read_text())
    md = (out / "tables" / "transfer.md").read_text()
    a, s = metrics["improved"]["tiny"], metrics["improved"]["tiny-stereo"]
    row = next(line for line in md.splitlines() if line.startswith("| improved "))
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert cells[:3] == ["improved", "`tiny`", "`tiny-stereo`"] and len(cells) == 15
    assert cells[3:6] == [f"{a['mAP']:.3f}", f"{s['mAP']:.3f}", tables.fmt(a["mAP"] - s["mAP"])]
    assert cells[12:14] == [f"{a['3d']['found_far_rule']:.3f}", f"{s['3d']['found_far_rule']:.3f}"]
    assert not any(line.startswith("| improved+paper-circle") for line in md.splitlines())
    assert (out / "figures" / "transfer.png").is_file()
    assert "`tiny-stereo` is `tiny` through the stereo sensor model" in (out / "README.md").read_text()
    # the far rule: 3 cm counts beyond 3 m deep, a miss never
    assert metrics3d.found_far_rule([0.025, 0.025, float("nan"), 0.01], [2.0, 3.5, 1.0, 1.0]) == 0.5
