"""Circle IoU against hand-computed cases and a fine-grid numerical integration."""

import math

import numpy as np
import pytest

from spherebench.errors import SphereBenchError
from spherebench.eval.metrics.circle_iou import circle_intersection_area, circle_iou, circle_iou_matrix


def test_identical_disjoint_tangent():
    assert circle_iou((5, 5, 3), (5, 5, 3)) == pytest.approx(1.0)
    assert circle_iou((0, 0, 1), (10, 0, 1)) == 0.0
    assert circle_iou((0, 0, 1), (2, 0, 1)) == 0.0  # externally tangent: no area in common


def test_contained():
    # r=1 inside r=3: intersection pi, union 9 pi -> 1/9, also when internally tangent (d = 2)
    assert circle_iou((0, 0, 3), (1, 0, 1)) == pytest.approx(1 / 9)
    assert circle_iou((0, 0, 3), (2, 0, 1)) == pytest.approx(1 / 9)
    assert circle_intersection_area((0, 0, 3), (1, 0, 1)) == pytest.approx(math.pi)


def test_lens_equal_radii_by_hand():
    # r = 1, d = 1: lens = 2 acos(1/2) - (1/2) sqrt(4 - 1) = 2 pi / 3 - sqrt(3) / 2 = 1.228370
    lens = 2 * math.pi / 3 - math.sqrt(3) / 2
    assert circle_intersection_area((0, 0, 1), (1, 0, 1)) == pytest.approx(1.2283696986, abs=1e-9)
    assert circle_iou((0, 0, 1), (1, 0, 1)) == pytest.approx(lens / (2 * math.pi - lens))  # 0.243016


def test_lens_unequal_radii_by_hand():
    # r1 = 2, r2 = 1, d = 2: x1 = 7/8, x2 = 1/4, Heron term sqrt(1 * 3 * 1 * 5) = sqrt(15)
    # area = 4 acos(7/8) + acos(1/4) - sqrt(15)/2 = 2.0214420 + 1.3181161 - 1.9364917 = 1.4030664
    area = circle_intersection_area((0, 0, 2), (0, 2, 1))
    assert area == pytest.approx(1.4030664, abs=1e-7)
    assert circle_iou((0, 0, 2), (0, 2, 1)) == pytest.approx(area / (5 * math.pi - area))


def test_zero_radius():
    assert circle_iou((0, 0, 0), (0, 0, 0)) == 0.0
    assert circle_iou((0, 0, 0), (0, 0, 2)) == 0.0
    assert circle_iou_matrix([[0, 0, 0]], [[0, 0, 0], [0, 0, 1]]).tolist() == [[0.0, 0.0]]


def test_matrix_matches_scalar_and_grid_integration():
    rng = np.random.default_rng(3)
    dets = np.column_stack([rng.uniform(0, 20, 7), rng.uniform(0, 20, 7), rng.uniform(0.5, 8, 7)])
    gts = np.column_stack([rng.uniform(0, 20, 5), rng.uniform(0, 20, 5), rng.uniform(0.5, 8, 5)])
    m = circle_iou_matrix(dets, gts)
    assert m.shape == (7, 5)
    for i in range(7):
        for j in range(5):
            assert m[i, j] == pytest.approx(circle_iou(dets[i], gts[j]), abs=1e-12)
    assert circle_iou_matrix(gts, dets) == pytest.approx(m.T)
    # independent check: areas by counting cells of a fine grid
    step = 0.02
    ys, xs = np.mgrid[-10:30:step, -10:30:step]
    for (a, b) in [(dets[0], gts[0]), (dets[1], gts[2]), ((0, 0, 2), (1.5, 0.5, 1.2))]:
        ina = (xs - a[0]) ** 2 + (ys - a[1]) ** 2 <= a[2] ** 2
        inb = (xs - b[0]) ** 2 + (ys - b[1]) ** 2 <= b[2] ** 2
        union = np.count_nonzero(ina | inb)
        assert circle_iou(a, b) == pytest.approx(np.count_nonzero(ina & inb) / union, abs=2e-3)


def test_matrix_empty_and_bad_input():
    assert circle_iou_matrix(np.zeros((0, 3)), [[1, 1, 1]]).shape == (0, 1)
    assert circle_iou_matrix([[1, 1, 1]], []).shape == (1, 0)
    with pytest.raises(SphereBenchError):
        circle_iou((0, 0, -1), (0, 0, 1))
    with pytest.raises(SphereBenchError):
        circle_iou_matrix([[0, 0, np.nan]], [[0, 0, 1]])
    with pytest.raises(SphereBenchError):
        circle_iou_matrix([[0, 0]], [[0, 0, 1]])
