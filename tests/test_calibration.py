"""The score's calibration (eval.metrics.calibration) on hand-checked cases."""

import math

import numpy as np
import pytest
from conftest import markdown_cells  # tests/ is on sys.path under pytest

from spherebench.errors import SphereBenchError
from spherebench.eval.metrics.calibration import (detection_correct, expected_calibration_error,
                                                  maximum_calibration_error, reliability)

NEAR = [0.0, 0.0, 2.0]   # a ball 2 m deep: the 2 cm rule
FAR = [1.0, 0.0, 3.5]    # a ball 3.5 m deep: the 3 cm rule


def _gt(*centres, distractors=()):
    return {"balls": [{"center_m": list(c), "radius_m": 0.12} for c in centres],
            "meta": {"distractors": [{"center_m": list(c), "radius_m": 0.14} for c in distractors]}}


def _off(c, dx):
    return [c[0] + dx, c[1], c[2]]


def test_within_two_cm_or_three_beyond_three_metres():
    dets = [_off(NEAR, 0.019), _off(FAR, 0.025), [5.0, 5.0, 5.0]]
    assert detection_correct(dets, [0.9, 0.8, 0.7], _gt(NEAR, FAR)).tolist() == [True, True, False]
    # 2.5 cm off the near ball: out (2 cm); 3.5 cm off the far one: out (3 cm)
    dets = [_off(NEAR, 0.025), _off(FAR, 0.035)]
    assert detection_correct(dets, [0.9, 0.8], _gt(NEAR, FAR)).tolist() == [False, False]


def test_a_distractor_is_not_the_ball():
    soccer = [0.5, 0.0, 1.5]
    dets = [soccer, _off(NEAR, 0.005)]
    assert detection_correct(dets, [0.99, 0.5], _gt(NEAR, distractors=[soccer])).tolist() == [False, True]


def test_one_correct_detection_per_ball_the_best_scored():
    # the closer detection scores lower: it is the duplicate
    dets = [_off(NEAR, 0.001), _off(NEAR, 0.015), _off(NEAR, 0.010)]
    assert detection_correct(dets, [0.3, 0.6, 0.5], _gt(NEAR)).tolist() == [False, True, False]
    # equal scores: the first given wins
    assert detection_correct(dets[:2], [0.5, 0.5], _gt(NEAR)).tolist() == [True, False]
    # two balls, one detection each, in either order
    assert detection_correct([_off(FAR, 0.01), NEAR], [0.2, 0.4], _gt(NEAR, FAR)).tolist() == [True, True]


def test_empty_scenes():
    assert detection_correct(np.zeros((0, 3)), [], _gt(NEAR)).tolist() == []
    assert detection_correct([NEAR], [0.9], {"balls": []}).tolist() == [False]  # a negative scene
    # a ball without a known centre is ignored
    gt = {"balls": [{"center_m": None, "radius_m": 0.12}]}
    assert detection_correct([NEAR], [0.9], gt).tolist() == [False]
    with pytest.raises(SphereBenchError):
        detection_correct([NEAR], [0.9, 0.8], _gt(NEAR))


def test_reliability_bins():
    r = reliability([0.0, 0.05, 0.15, 0.95, 1.0], [False, True, True, True, False], n_bins=10)
    assert r.edges.tolist() == pytest.approx(np.linspace(0, 1, 11).tolist())
    assert r.count.tolist() == [2, 1, 0, 0, 0, 0, 0, 0, 0, 2]  # empty bins kept; 1.0 in the last
    assert r.mean_score[[0, 1, 9]] == pytest.approx([0.025, 0.15, 0.975])
    assert r.fraction_correct[[0, 1, 9]] == pytest.approx([0.5, 1.0, 0.5])
    assert np.isnan(r.mean_score[2]) and np.isnan(r.fraction_correct[2]) and r.n == 5
    with pytest.raises(SphereBenchError, match=r"\[0, 1\]"):
        reliability([1.2], [True])
    with pytest.raises(SphereBenchError, match=r"\[0, 1\]"):
        reliability([np.nan], [True])


def test_perfectly_calibrated_samples():
    # 20 detections at each bin centre (k + 0.5) / 10, of which 2k + 1 correct: exactly calibrated
    scores = np.repeat((np.arange(10) + 0.5) / 10, 20)
    correct = np.concatenate([np.arange(20) < 2 * k + 1 for k in range(10)])
    assert expected_calibration_error(scores, correct) == pytest.approx(0.0, abs=1e-12)
    assert maximum_calibration_error(scores, correct) == pytest.approx(0.0, abs=1e-12)
    # drawn: correct with probability its score; the ECE is sampling noise only
    rng = np.random.default_rng(0)
    s = rng.uniform(size=20000)
    assert expected_calibration_error(s, rng.uniform(size=s.size) < s) < 0.02


def test_miscalibrated_by_hand():
    # bin 9: scores 0.9, 0.9, 0.9, 0.9, 1.0 (conf 0.92), 2 of 5 correct (acc 0.4): gap 0.52
    # bin 2: scores 0.2, 0.2 (conf 0.2), both correct (acc 1.0): gap 0.8
    # bin 5: score 0.5, correct: gap 0.5
    scores = [0.9, 0.9, 0.9, 0.9, 1.0, 0.2, 0.2, 0.5]
    correct = [True, True, False, False, False, True, True, True]
    ece = 5 / 8 * 0.52 + 2 / 8 * 0.8 + 1 / 8 * 0.5
    assert ece == pytest.approx(0.5875)
    assert expected_calibration_error(scores, correct) == pytest.approx(ece)
    assert maximum_calibration_error(scores, correct) == pytest.approx(0.8)
    # one bin: the gap of the means
    assert expected_calibration_error(scores, correct, n_bins=1) == pytest.approx(abs(5 / 8 - 5.5 / 8))


def test_no_detections_have_no_calibration():
    assert math.isnan(expected_calibration_error([], []))
    assert math.isnan(maximum_calibration_error([], []))
    assert reliability([], []).count.tolist() == [0] * 10


# ---------------------------------------------------------------- the bench: files in, table and figure out

@pytest.fixture(scope="module")
def evaluated(tmp_path_factory):
    """Four `default` scenes in data/default and `spherebench evaluate --methods improved` on them."""
    from spherebench.scripts.cli import main
    from spherebench.datasets import simulate
    root = tmp_path_factory.mktemp("calib")
    data = simulate.generate_dataset("default", root / "data" / "default", n=4, progress=False)
    assert main(["evaluate", "--data", str(data), "--out", str(root / "results"), "--methods", "improved",
                 "--workers", "1", "--quiet"]) == 0
    return root


def test_evaluate_writes_the_calibration_table_and_figure(evaluated):
    results = evaluated / "results"
    md = markdown_cells((results / "tables" / "calibration.md").read_text())
    assert "| default | improved | " in md and "ECE" in md
    assert (results / "tables" / "calibration.csv").read_text().startswith("preset,method,detections,correct,ECE")
    assert (results / "figures" / "reliability.png").stat().st_size > 10_000
    assert "figures/reliability.png" in (results / "README.md").read_text()


def test_read_from_files_as_the_report_did(evaluated):
    from spherebench.eval.bench import calibration as bench
    frame = bench.read_calibration(evaluated / "data", evaluated / "results")
    assert list(frame.columns) == bench.COLUMNS
    assert set(frame["preset"]) == {"default"} and set(frame["method"]) == {"improved"}  # one row per run
    assert len(frame) == 10 and frame["count"].sum() == frame["detections"].iloc[0]
    # the improved detector finds the four balls within 2 cm (tests/test_eval_pipeline.py): four correct
    assert frame["correct"].iloc[0] == 4
    full = frame[frame["count"] > 0]
    gaps = (full["fraction_correct"] - full["mean_score"]).abs()
    assert frame["ece"].iloc[0] == pytest.approx(float((full["count"] * gaps).sum() / full["count"].sum()))
    text = (evaluated / "results" / "tables" / "calibration.csv").read_text()
    assert bench.calibration_table(frame).csv() == text


def test_scores_that_are_no_probabilities_are_named_not_binned():
    from spherebench.eval.bench import calibration as bench
    frame = bench._frame({("p", "good"): (np.array([0.2, 0.9]), np.array([False, True])),
                          ("p", "counts"): (np.array([3.0]), np.array([True]))}, 10)
    assert set(frame["method"]) == {"good"} and frame.attrs["not_probabilities"] == ["counts on `p`"]
    table = bench.calibration_table(frame)
    from spherebench.eval.metrics.calibration import ece_floor
    assert table.rows[0][:7] == ["p", "good", 2, 1, "0.150", f"{ece_floor([0.2, 0.9]):.3f}", "0.200"]
    assert "counts on `p`" in table.notes[-1]
    assert bench.calibration_table(bench._frame({}, 10)) is None


def test_the_ece_floor_is_the_sampling_noise_of_a_calibrated_score():
    from spherebench.eval.metrics.calibration import ece_floor

    assert ece_floor(np.ones(50)) == 0.0 and np.isnan(ece_floor([]))
    # one bin, N detections at 0.5: ECE = |k/N - 1/2|, k ~ Binomial(N, 1/2); its median is about
    # 0.6745 x 0.5 / sqrt(N) (the normal's quartile)
    for n in (100, 400, 1600):
        assert ece_floor(np.full(n, 0.5)) == pytest.approx(0.6745 * 0.5 / np.sqrt(n), rel=0.2), n
    scores = np.random.default_rng(1).uniform(0.4, 1.0, 60)
    assert ece_floor(scores) == ece_floor(scores)  # seeded
    assert ece_floor(scores) > 2 * ece_floor(np.tile(scores, 16))  # 16x the detections: a quarter of it


def test_the_ece_floor_of_repeated_trials_is_that_of_the_trials():
    from spherebench.errors import SphereBenchError
    from spherebench.eval.metrics.calibration import ece_floor

    scores = np.random.default_rng(2).uniform(0.4, 1.0, 60)
    pooled, trial = np.tile(scores, 4), np.tile(np.arange(60), 4)  # one scene's ball at 4 run seeds
    assert ece_floor(pooled, groups=trial) == pytest.approx(ece_floor(scores), abs=1e-12)  # one draw per trial
    assert ece_floor(pooled) < 0.75 * ece_floor(scores)  # counted as 240 trials, it would look sharper
    assert ece_floor(scores, groups=np.arange(60)) == ece_floor(scores)
    with pytest.raises(SphereBenchError, match="labels"):
        ece_floor(scores, groups=np.arange(3))
