"""COCO evaluation with circle IoU on tiny hand-made sets whose AP is worked out by hand.

The 101-point interpolation (pycocotools): detections sorted by score give cumulative recall
rc_i and precision pr_i; precision is made non-increasing from the right; at each recall
threshold r in {0, 0.01, ..., 1} the precision is that of the first detection with rc_i >= r,
or 0 when no detection reaches r. AP is the mean over the 101 thresholds.
"""

import copy
import json
import math

import numpy as np
import pytest

from spherebench.errors import SphereBenchError
from spherebench.eval.metrics.coco_eval import (coco_from_circles, evaluate_by_family, evaluate_circles, load_results,
                                                load_ground_truth, results_from_circles, scalar_metrics)

R = 10.0  # every ground-truth circle: area 100 pi < 32^2, COCO 'small'


def _gt():
    # images 0, 1, 2 hold one ball each; image 3 is a negative (no annotation)
    gt = coco_from_circles([[(50, 50, R)], [(100, 60, R)], [(30, 30, R)], np.zeros((0, 3))], image_size=(160, 120))
    for img, fam in zip(gt["images"], ["a", "a", "b", "b"]):
        img["family"] = fam
    return gt


def test_perfect_detections_give_one():
    gt = _gt()
    res = results_from_circles([[(50, 50, R, 0.9)], [(100, 60, R, 0.8)], [(30, 30, R, 0.7)], []])
    m = evaluate_circles(gt, res)
    for key in ("mAP", "mAP50", "mAP75", "mAR", "mAP_small"):
        assert m[key] == pytest.approx(1.0)
    assert math.isnan(m["mAP_large"]) and math.isnan(m["mAP_medium"])
    assert (m["n_images"], m["n_gt"], m["n_detections"]) == (4, 3, 3)
    assert m["precision"].shape == (10, 101, 1, 4, 3)
    assert np.allclose(m["pr_precision"], 1.0)


def test_hits_misses_and_false_positives_by_hand():
    # d1: image 0, exact, score .9            -> TP at every IoU threshold
    # d2: image 3 (negative), score .8        -> FP
    # d3: image 1, same centre, r = sqrt(62): IoU = 62/100 = 0.62, score .7
    #     -> TP at IoU .50, .55, .60; FP at .65 ... .95
    # image 2: missed. 3 ground truths.
    # IoU .50-.60: TP FP TP: rc = 1/3, 1/3, 2/3; pr = 1, 1/2, 2/3 -> interpolated 1, 2/3, 2/3.
    #   r = 0.00..0.33 (34 points) -> 1; r = 0.34..0.66 (33) -> 2/3; r >= 0.67 (34) -> 0.
    #   AP = (34 + 33 * 2/3) / 101 = 56/101 = 0.554455
    # IoU .65-.95: TP FP FP: rc = 1/3 throughout -> 34 points at precision 1: AP = 34/101.
    # mAP = (3 * 56 + 7 * 34) / 1010 = 406/1010; AR = (3 * 2/3 + 7 * 1/3) / 10 = 13/30.
    gt = _gt()
    res = results_from_circles([[(50, 50, R, 0.9)], [(100, 60, math.sqrt(62.0), 0.7)], [], [(10, 10, R, 0.8)]])
    m = evaluate_circles(gt, res)
    assert m["mAP50"] == pytest.approx(56 / 101)
    assert m["mAP75"] == pytest.approx(34 / 101)
    assert m["mAP"] == pytest.approx(406 / 1010)
    assert m["mAR"] == pytest.approx(13 / 30)
    assert m["pr_precision"][0, :34] == pytest.approx(1.0)
    assert m["pr_precision"][0, 34:67] == pytest.approx(2 / 3)
    assert m["pr_precision"][0, 67:] == pytest.approx(0.0)


def test_false_positive_on_a_negative_image_ranked_first():
    # FP (score .95, negative image) then three TPs: pr = 0, 1/2, 2/3, 3/4 -> interpolated 3/4 at
    # every recall up to 1: AP = 0.75 at every IoU threshold.
    gt = _gt()
    res = results_from_circles([[(50, 50, R, 0.9)], [(100, 60, R, 0.8)], [(30, 30, R, 0.7)], [(80, 80, R, 0.95)]])
    m = evaluate_circles(gt, res)
    assert m["mAP"] == pytest.approx(0.75)
    assert m["mAR"] == pytest.approx(1.0)


def test_empty_results_and_subsets():
    gt = _gt()
    m = evaluate_circles(gt, [])
    assert m["mAP"] == 0.0 and m["mAR"] == 0.0 and m["n_detections"] == 0
    res = results_from_circles([[(50, 50, R, 0.9)], [(100, 60, math.sqrt(62.0), 0.7)], [], [(10, 10, R, 0.8)]])
    # the negative image alone has no ground truth: AP undefined
    neg = evaluate_circles(gt, res, image_ids=[3])
    assert math.isnan(neg["mAP"]) and neg["n_detections"] == 1
    assert scalar_metrics(neg)["mAP"] is None
    fam = evaluate_by_family(gt, res)
    assert set(fam) == {"all", "a", "b"}
    # family a: d1 TP, d3 TP below IoU .65 else FP; 2 gts.
    #   IoU .50-.60: AP 1; .65-.95: TP FP, rc = 1/2 -> 51 points at 1: AP 51/101
    assert fam["a"]["mAP"] == pytest.approx((3 + 7 * 51 / 101) / 10)
    # family b: the ball of image 2 missed, the FP on image 3: AP 0
    assert fam["b"]["mAP"] == 0.0
    assert fam["all"]["mAP"] == pytest.approx(406 / 1010)
    with pytest.raises(SphereBenchError):
        evaluate_circles(gt, res, image_ids=[])
    with pytest.raises(SphereBenchError):
        evaluate_circles(gt, res, image_ids=[42])


def test_inputs_untouched_and_ids_renumbered(tmp_path):
    gt = _gt()
    for ann in gt["annotations"]:
        ann["id"] = 0  # pycocotools would read a match with gt id 0 as "no match"
        del ann["bbox"], ann["area"]
    del gt["annotations"][2]["id"]  # a missing id is numbered too
    res = results_from_circles([[(50, 50, R, 0.9)], [(100, 60, R, 0.8)], [(30, 30, R, 0.7)], []])
    gt_before, res_before = copy.deepcopy(gt), copy.deepcopy(res)
    path = tmp_path / "coco_gt.json"
    path.write_text(json.dumps(gt))
    assert evaluate_circles(str(path), res)["mAP"] == pytest.approx(1.0)
    assert gt == gt_before and res == res_before
    coco_dt = load_results(load_ground_truth(gt), res)
    assert all(a["area"] == pytest.approx(math.pi * R * R) for a in coco_dt.dataset["annotations"])


def test_crowd_region_absorbs_detections():
    # a crowd GT (iscrowd 1) with a detection inside it ranked first: ignored, not a false positive
    gt = coco_from_circles([[(50, 50, R), (120, 60, 30)]])
    gt["annotations"][1]["iscrowd"] = 1
    res = results_from_circles([[(120, 60, 5, 0.99), (50, 50, R, 0.5)]])
    assert evaluate_circles(gt, res)["mAP"] == pytest.approx(1.0)
    gt["annotations"][1]["iscrowd"] = 0  # the same as a plain ball: now a miss (IoU 1/36) and a FP
    assert evaluate_circles(gt, res)["mAP50"] == pytest.approx(0.5 * 51 / 101)


def test_large_circles_fall_in_the_large_range():
    gt = coco_from_circles([[(200, 200, 60)]])  # area 3600 pi > 96^2
    m = evaluate_circles(gt, results_from_circles([[(200, 200, 60, 1.0)]]))
    assert m["mAP_large"] == pytest.approx(1.0) and math.isnan(m["mAP_small"])


def test_bad_results_raise():
    gt = _gt()
    good = {"image_id": 0, "category_id": 1, "circle_center": [1, 2], "circle_radius": 3, "score": 0.5}
    for bad in ({**good, "image_id": 99}, {**good, "category_id": 7}, {**good, "circle_radius": -1},
                {k: v for k, v in good.items() if k != "circle_center"}, {**good, "score": "high"}):
        with pytest.raises(SphereBenchError):
            evaluate_circles(gt, [bad])
    with pytest.raises(SphereBenchError):
        evaluate_circles({"images": []}, [])
