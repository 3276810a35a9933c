"""Recorded datasets in `spherebench evaluate`: Table 3 and the 3D figures against mask-fit reference
centres, what the README says they are, the example figure on the colour frames, --beside, and the
figure folders of other tools kept when figures/ is replaced."""

from __future__ import annotations

import json
import shutil
import sys

import cv2
import numpy as np
import pytest

from spherebench.baselines.hough import HoughConfig
from spherebench.circles import sphere_silhouette_mask
from spherebench.scripts.cli import main
from spherebench.datasets import frame_sources, inout
from spherebench.datasets import prepare as prep
from spherebench.datasets.annotate import labelme_from_mask, labelme_text
from spherebench.eval.bench import figures, recorded, registry, report, scoring, tasks
from spherebench.eval.bench import evaluate as ev
from conftest import markdown_cells  # noqa: E402  (tests/ is on sys.path under pytest)

from test_annotate_colour import CAM, R, sphere_depth

CENTRES = [(0.05, -0.02, 1.6), (-0.12, 0.04, 2.0)]
#: The masks are drawn from a ball this much larger than R, as a sensor that sees the ball larger
#: than its stated size (the Kinect set: about 6 %) would give them.
MASK_SCALE = 1.06
DESCRIPTION = "drawn by the test from a 6 % larger ball"


@pytest.fixture(scope="module")
def rec(tmp_path_factory):
    """Two recorded frames of a ball of R = 0.2 m before a wall, colour registered to depth, each
    annotated by a LabelMe polygon on colour.jpg; prepared with mask-fit reference centres."""
    root = tmp_path_factory.mktemp("recorded")
    labelme = root / "labelme"
    labelme.mkdir()
    frames = []
    for i, centre in enumerate(CENTRES):
        mask = sphere_silhouette_mask(CAM, centre, MASK_SCALE * R)
        colour = np.full((CAM.height, CAM.width, 3), (140, 120, 110), np.uint8)
        colour[mask] = (0, 220, 230)  # a yellow ball
        src = root / "src" / f"frame_{i}"
        src.mkdir(parents=True)
        cv2.imwrite(str(src / "colour.jpg"), colour, [cv2.IMWRITE_JPEG_QUALITY, 98])
        (labelme / f"frame_{i}.json").write_text(labelme_text(labelme_from_mask(mask, "colour.jpg", "ball", DESCRIPTION)))
        depth = np.round(sphere_depth(centre=centre) / CAM.depth_scale).astype(np.uint16)
        frames.append(frame_sources.RecordedFrame(f"frame_{i}", f"frame_{i}.png", CAM, depth=depth, colour=src / "colour.jpg"))
    plan = frame_sources.Plan(iter(frames), len(frames), {"kind": "test", "camera": "a test camera"})
    out = root / "rec"
    prep.prepare(plan, out, prep.PrepareOptions(ball_radius_m=R, labelme_dir=labelme, name="rec"), log=lambda m: None)
    return out


def _quiet(_):
    pass


def test_facts_of_a_recording_and_none_for_simulated_data(rec, paper_dataset):
    f = recorded.facts(rec)
    assert (f["n_scenes"], f["annotated"], f["n_balls"], f["mask_fit"], f["colour"]) == (2, 2, 2, 2, 2)
    assert f["camera"] == "a test camera" and f["resolution"] == "160x120" and f["radius_m"] == R
    assert f["annotations"]["descriptions"] == {DESCRIPTION: 2} and f["annotations"]["set"] is None
    # exact depth: the fit is the true sphere, and the masks' circles are the larger ball's
    assert f["se_median_m"] < 0.002
    assert f["fit_circle_ratio"] == pytest.approx(MASK_SCALE, abs=0.02) and f["fit_circle_offset_px"] < 1.0
    assert recorded.facts(paper_dataset) is None


def test_evaluate_scores_a_recording_against_its_reference_centres(rec, tmp_path):
    out = tmp_path / "results"
    report.claim_results_dir(out)
    sheets = out / "figures" / "annotation"
    sheets.mkdir(parents=True)
    (sheets / "overview_01.png").write_bytes(b"a review sheet")
    other = {"improved": {"default": {"mAP": 0.966, "mAP50": 0.99, "mAP75": 0.99}},
             "hough": {"default": {"mAP": 0.391, "mAP50": 0.529, "mAP75": 0.45}}}
    metrics = ev.evaluate({"rec": rec}, out, methods=["improved", "hough"], workers=1, hough_config=HoughConfig(),
                          progress=False, paper_rows_for=(), beside=recorded.Beside(other, "default", "a test's results"),
                          log=_quiet)
    m = metrics["improved"]["rec"]
    assert m["n_images"] == 2 and m["mAP50"] == 1.0  # IoU about 1 / 1.06^2 = 0.89 with the larger masks
    d = m["3d"]
    assert (d["n_gt"], d["within_1cm"], d["false_detections"], d["gate_m"]) == (2, 1.0, 0, R)
    assert d["scenes_without_centre"] == 0
    text = (out / "README.md").read_text()
    for said in ("`rec` is a recording, not a simulation", "from a test camera at 160x120", "not a RealSense D435",
                 "reference centre, not a ground truth", f"'{DESCRIPTION}'", "looks about 0.21",
                 "Table 3 on `rec` beside `default` (mAP / mAP.50 / mAP.75): improved",
                 "Hough's parameters were tuned on `train`", "In 3D, balls of `rec` matched within 2 cm of the reference "
                 "centre, of 2: improved 2"):
        assert said in text, said
    beside = markdown_cells((out / "tables" / "table3_rec_beside_default.md").read_text())
    assert "| improved | exact silhouette |" in beside and "| 0.966 | 0.990 | 0.990 |" in beside
    assert "a test's results" in beside
    m3d = (out / "tables" / "metrics3d_rec.md").read_text()
    assert "against its reference centres" in m3d and "within one radius (0.2 m)" in m3d
    # the scores' calibration against the reference centres, which the table names as such
    calib = (out / "tables" / "calibration.md").read_text()
    assert "| rec | improved | 2 | 2 |" in markdown_cells(calib) and "`rec` (recorded)" in calib
    # the review sheets of another tool are kept, and named; the examples are drawn on colour
    assert (sheets / "overview_01.png").read_bytes() == b"a review sheet"
    assert "figures/annotation/" in text and (out / "figures" / "examples_rec.png").is_file()
    coco = inout.read_coco_gt(rec)
    shown = figures._background(rec, coco["images"][0])
    colour = cv2.cvtColor(cv2.imread(str(rec / "scenes" / "frame_0" / "colour.jpg")), cv2.COLOR_BGR2RGB)
    np.testing.assert_array_equal(shown, colour)
    # a second run replaces figures/ again and still keeps them
    ev.evaluate({"rec": rec}, out, methods=["improved"], workers=1, progress=False, paper_rows_for=(), log=_quiet)
    assert (sheets / "overview_01.png").is_file()


def test_a_ball_without_a_reference_centre_leaves_its_scene_out_of_3d(rec, tmp_path):
    data = tmp_path / "rec"
    shutil.copytree(rec, data)
    gt_path = data / "scenes" / "frame_1" / "gt.json"
    gt = inout.read_json(gt_path)
    gt["balls"][0].pop("center_m")  # the fit failed there
    inout.write_json(gt_path, gt)
    paths = tasks.run_methods(data, tmp_path / "p", registry.build_methods(["improved"], radius_m=R), workers=1,
                               progress=False, log=_quiet)
    scored = scoring.score_set(paths["improved"], inout.read_coco_gt(data), tasks.dataset_scenes(data))
    d = scored.metrics["3d"]
    assert (d["n_scenes"], d["n_gt"], d["within_2cm"], d["scenes_without_centre"]) == (1, 1, 1.0, 1)
    assert scored.metrics["n_images"] == 2  # in 2D both frames are scored


def test_beside_marks_figures_of_another_model_or_configuration():
    class S:
        def __init__(self, output, mAP, config=None, extra=""):
            self.output, self.method, self.kind, self.rule = output, output, "2d", None
            self.metrics = {"mAP": mAP, "mAP50": mAP, "mAP75": mAP, "n_scenes_run": 3}
            self.config, self.extra_fingerprint = config, extra
    sets = [S("improved", 0.5, {"engine": "detector", "radius_m": 0.203}), S("circlenet", 0.4),
            S("paper", 0.0), S("hough", 0.1), S("circlenet-full", 0.6, {"engine": "circlenet"}, "ab12")]
    sets[3].metrics["note"] = "a model card"
    fig = {"mAP": 0.9, "mAP50": 0.9, "mAP75": 0.9}
    other = {"improved": {"default": fig}, "hough": {"default": {**fig, "note": "another model card"}},
             "circlenet-full": {"default": fig}}
    settings = {"improved": {"config": {"engine": "detector", "radius_m": 0.12}, "extra_fingerprint": ""},
                "circlenet-full": {"config": {"engine": "circlenet"}, "extra_fingerprint": "cd34"}}
    beside = recorded.Beside(other, "default", "x", settings)
    line, = recorded.beside_reading("rec", sets, beside)
    # the radius is the dataset's, not the method's; the note, or else the model hash, tells the method
    assert "improved 0.500 / 0.500 / 0.500 against 0.900 / 0.900 / 0.900;" in line and "circlenet " not in line
    assert "hough 0.100 / 0.100 / 0.100 against 0.900 / 0.900 / 0.900 (run with other settings" in line
    assert "circlenet-full 0.600 / 0.600 / 0.600 against 0.900 / 0.900 / 0.900 (run with other settings" in line
    table = recorded.beside_table("rec", sets, beside)
    assert [r[0] for r in table.rows] == ["improved", "circlenet", "paper", "hough", "circlenet-full"]
    assert table.rows[1][5] == "–" and table.rows[0][5] == "0.900" and table.rows[3][5] == "0.900 *"
    assert table.notes[-1].startswith("*: there")


@pytest.mark.parametrize("case, match", [("missing", "file not found"), ("label", "no circle mAP on a dataset `hard`"),
                                         ("not-metrics", "not a metrics.json")])
def test_beside_bad_input_is_one_line_and_writes_nothing(rec, tmp_path, monkeypatch, capsys, case, match):
    metrics = tmp_path / "metrics.json"
    metrics.write_text(json.dumps({"improved": {"default": {"mAP": 0.9}}} if case != "not-metrics" else [1, 2]))
    args = ["evaluate", "--data", str(rec), "--out", str(tmp_path / "out"), "--methods", "improved",
            "--beside", str(metrics if case != "missing" else tmp_path / "none.json")]
    if case == "label":
        args += ["--beside-label", "hard"]
    monkeypatch.setattr(sys, "argv", ["spherebench", *args])
    assert main(args) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and match in err and "Traceback" not in err, err
    assert not (tmp_path / "out").exists()
