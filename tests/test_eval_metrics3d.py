"""3D metrics on small arrays with hand-checked answers."""

import math

import numpy as np
import pytest

from spherebench.errors import SphereBenchError
from spherebench.eval.metrics.metrics3d import (detection_rates, error_stats, error_vs_distance, match_scene,
                                                summarize_3d)

GT = np.array([[0.0, 0.0, 2.0], [0.5, 0.0, 3.0]])


def test_match_by_score_and_gate():
    pred = np.array([[0.0, 0.005, 2.0],    # 5 mm from ball 0
                     [0.53, 0.0, 3.0],     # 3 cm from ball 1
                     [1.0, 1.0, 1.0]])     # nowhere near: a false detection
    m = match_scene(pred, [0.9, 0.5, 0.8], GT, pred_radii_m=[0.121, 0.118, 0.12], gt_radii_m=[0.12, 0.12])
    assert m.gt_to_pred.tolist() == [0, 1]
    assert m.pred_to_gt.tolist() == [0, 1, -1]
    assert m.centre_error_m == pytest.approx([0.005, 0.03])
    assert m.radius_error_m == pytest.approx([0.001, -0.002])
    assert m.gt_distance_m == pytest.approx([2.0, math.hypot(0.5, 3.0)])
    assert m.n_false == 1


def test_higher_score_takes_the_ball_first():
    # two predictions for ball 0: the confident one (2 cm off) wins over the closer one (1 mm off)
    pred = np.array([[0.0, 0.0, 2.001], [0.02, 0.0, 2.0]])
    m = match_scene(pred, [0.1, 0.9], GT[:1])
    assert m.gt_to_pred.tolist() == [1] and m.pred_to_gt.tolist() == [-1, 0]
    assert m.centre_error_m == pytest.approx([0.02])
    # outside the gate: no match
    far = match_scene([[0.0, 0.0, 2.2]], [1.0], GT[:1], gate_m=0.12)
    assert far.gt_to_pred.tolist() == [-1] and math.isnan(far.centre_error_m[0])


def test_stats_and_rates():
    s = error_stats([0.003, 0.004, np.nan])
    assert s["n"] == 2
    assert s["median"] == pytest.approx(0.0035)
    assert s["rmse"] == pytest.approx(math.sqrt((0.003 ** 2 + 0.004 ** 2) / 2))
    assert s["p95"] == pytest.approx(0.003 + 0.95 * 0.001)
    assert error_stats([])["n"] == 0
    r = detection_rates([0.005, 0.03, np.nan, 0.015])
    assert r == {"within_1cm": 0.25, "within_2cm": 0.5, "within_5cm": 0.75}


def test_summary_over_scenes_with_negatives():
    s1 = match_scene([[0.0, 0.005, 2.0], [0.53, 0.0, 3.0], [1.0, 1.0, 1.0]], [0.9, 0.5, 0.8], GT)
    s2 = match_scene(np.zeros((0, 3)), [], GT[:1])                       # a missed ball
    neg1 = match_scene([[0.0, 0.0, 1.5]], [0.3], np.zeros((0, 3)))       # negative with a detection
    neg2 = match_scene(np.zeros((0, 3)), [], np.zeros((0, 3)))           # clean negative
    out = summarize_3d([s1, s2, neg1, neg2])
    assert (out["n_scenes"], out["n_gt"], out["n_pred"], out["n_matched"]) == (4, 3, 4, 2)
    assert out["within_1cm"] == pytest.approx(1 / 3)
    assert out["within_5cm"] == pytest.approx(2 / 3)
    assert out["centre_error_m"]["median"] == pytest.approx(0.0175)
    assert out["false_detections"] == 2 and out["false_per_scene"] == 0.5
    assert out["n_negative_scenes"] == 2 and out["negative_detections"] == 1
    assert out["negative_scenes_with_detection"] == 0.5
    dist, err = error_vs_distance([s1, s2])
    assert dist.shape == err.shape == (3,) and np.isnan(err[2])


def test_bad_input():
    with pytest.raises(SphereBenchError):
        match_scene([[0, 0, np.inf]], [1.0], GT)
    with pytest.raises(SphereBenchError):
        match_scene([[0, 0, 1]], [1.0, 2.0], GT)
    with pytest.raises(SphereBenchError):
        match_scene([[0, 0, 1]], [1.0], GT, gate_m=0)
    with pytest.raises(SphereBenchError):
        summarize_3d([])


def test_scene_counts_and_their_totals():
    from spherebench.eval.metrics.metrics3d import FOUND_M, detection_counts, scene_counts
    gt = {"balls": [{"center_m": [0.0, 0.0, 2.0]}, {"center_m": [0.5, 0.0, 3.0]}],
          "meta": {"distractors": [{"center_m": [-0.5, 0.0, 1.0], "radius_m": 0.11}]}}
    # one detection 1.5 cm from the first ball, one on the distractor, none near the second ball
    row = scene_counts([[0.015, 0.0, 2.0], [-0.5, 0.01, 1.0]], gt)
    assert row["errs"][0] == pytest.approx(0.015) and row["errs"][1] > FOUND_M
    assert row["false"] == 1 and row["distractors"] == [{"radius_m": 0.11, "z_m": 1.0, "accepted": True}]
    assert row["clutter"] == 1  # the distractor is far from both balls
    empty = scene_counts([], {"balls": []})
    assert empty == {"errs": [], "z": [], "false": 0, "clutter": 0, "distractors": []}
    # a ball's detection 4 cm off: a false detection of the 2 cm rate, but no clutter
    off = scene_counts([[0.04, 0.0, 2.0]], gt)
    assert off["false"] == 1 and off["clutter"] == 0 and off["errs"][0] == pytest.approx(0.04)
    neg = {**scene_counts([[1.0, 1.0, 1.0]], {"balls": []}), "family": "negative"}
    tot = detection_counts([{**row, "family": "clean"}, neg, {**off, "family": "clean"}])
    assert tot == {"balls": 4, "found": 1, "found_far_rule": 1, "false_detections": 3, "clutter_detections": 2,
                   "detections_on_negatives": 1, "negative_scenes": 1, "distractors": 2, "distractors_rejected": 1}


def test_the_far_rule_takes_3_cm_only_beyond_3_m():
    from spherebench.eval.metrics.metrics3d import detection_counts, scene_counts
    gt = {"balls": [{"center_m": [0.0, 0.0, 2.9]}, {"center_m": [0.5, 0.0, 3.2]}, {"center_m": [-0.5, 0.0, 4.5]}]}
    # 2.5 cm off each ball; 3.5 cm off the farthest too
    near = scene_counts([[0.025, 0.0, 2.9], [0.5, 0.025, 3.2], [-0.5, 0.0, 4.535]], gt)
    c = detection_counts([{**near, "family": "far"}])
    assert c["found"] == 0 and c["found_far_rule"] == 1  # the 3.2 m ball only: 2.9 m is not beyond 3 m
    exact = scene_counts([[0.0, 0.0, 2.9], [0.5, 0.0, 3.2], [-0.5, 0.0, 4.5]], gt)
    assert detection_counts([{**exact, "family": "far"}])["found_far_rule"] == 3
