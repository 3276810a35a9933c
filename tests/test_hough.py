"""The Hough baseline on small synthetic colourised-depth images with drawn filled circles."""

import cv2
import numpy as np
import pytest

from spherebench.baselines.hough import HoughConfig, depth_level, detect_circles, edge_support, grid_scores, tune
from spherebench.errors import SphereBenchError

H, W = 120, 200


def _image(circles, background=170, ball=60, seed=0) -> np.ndarray:
    """JET-colourised level image (H, W, 3) uint8: a sloped wall and filled nearer discs."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:H, 0:W]
    level = background + 0.1 * (yy - H / 2) + rng.normal(0, 1.0, (H, W))
    for cx, cy, r in circles:
        level[(xx - cx) ** 2 + (yy - cy) ** 2 <= r * r] = ball
    return cv2.applyColorMap(np.clip(np.rint(level), 0, 255).astype(np.uint8), cv2.COLORMAP_JET)


def test_colormap_inversion():
    levels = np.tile(np.arange(256, dtype=np.uint8), (10, 1))
    img = cv2.applyColorMap(levels, cv2.COLORMAP_JET)
    img[0, :5] = 0  # invalid depth
    back = depth_level(img)
    assert back[0, :5].tolist() == [0] * 5
    assert np.abs(back[1:].astype(int) - levels[1:]).max() <= 1  # JET repeats a few colours
    assert np.array_equal(cv2.applyColorMap(back[1:], cv2.COLORMAP_JET), img[1:])


def test_detects_drawn_circles_best_first():
    truth = [(50.0, 60.0, 30.0), (150.0, 50.0, 14.0)]
    dets = detect_circles(_image(truth))
    assert len(dets) >= 2
    scores = [d[3] for d in dets]
    assert scores == sorted(scores, reverse=True)
    for cx, cy, r in truth:
        best = min(dets, key=lambda d: np.hypot(d[0] - cx, d[1] - cy))
        assert np.hypot(best[0] - cx, best[1] - cy) <= 1.5
        assert abs(best[2] - r) <= 1.5
        assert best[3] >= 0.6
    # each true circle is among the two top-scored detections
    top = dets[:2]
    for cx, cy, _ in truth:
        assert any(np.hypot(d[0] - cx, d[1] - cy) <= 1.5 for d in top)


def test_edge_support_score():
    cfg = HoughConfig()
    grey = cv2.medianBlur(depth_level(_image([(100.0, 60.0, 25.0)])), 5)
    s = edge_support(grey, np.array([[100, 60, 25], [40, 30, 12], [100, 60, 15], [0, 60, 25]]), cfg)
    assert s[0] >= 0.9          # the drawn circle
    assert s[1] == 0.0          # flat wall
    assert s[2] <= 0.1          # inside the disc, no edge
    assert s[3] <= 0.1          # no edge there either, and half of it outside the image
    half = edge_support(cv2.medianBlur(depth_level(_image([(0.0, 60.0, 25.0)])), 5),
                        np.array([[0, 60, 25]]), cfg)
    assert 0.3 <= half[0] <= 0.55  # half the circle is outside the image: at most about half


def test_tune_picks_the_radius_range_that_fits():
    rng = np.random.default_rng(5)
    truth = [np.array([[rng.uniform(40, 160), rng.uniform(35, 85), rng.uniform(15, 30)]]) for _ in range(5)]
    truth.append(np.zeros((0, 3)))  # a negative image
    images = [_image(t, seed=i) for i, t in enumerate(truth)]
    grid = {"max_radius_px": [10, 40], "param2": [15.0, 200.0]}
    scored = grid_scores(images, truth, grid)
    assert [(c.max_radius_px, c.param2) for c, _ in scored] == [(10, 15.0), (10, 200.0), (40, 15.0), (40, 200.0)]
    assert scored[0][1]["mAP50"] == 0.0      # radius range too small for every ball
    assert scored[2][1]["mAP50"] >= 0.9
    best = tune(images, truth, grid)
    assert (best.max_radius_px, best.param2) == (40, 15.0)
    assert tune(images, truth, grid) == best  # deterministic


def test_bad_input():
    with pytest.raises(SphereBenchError):
        detect_circles(np.zeros((H, W, 3), np.float32))
    with pytest.raises(SphereBenchError):
        detect_circles(np.zeros((H, W, 4), np.uint8))
    with pytest.raises(SphereBenchError):
        HoughConfig(method="gradient_alt", param2=5.0)
    with pytest.raises(SphereBenchError):
        HoughConfig(min_radius_px=50, max_radius_px=10)
    img = _image([(50.0, 60.0, 30.0)])
    with pytest.raises(SphereBenchError):
        tune([img], [np.array([[50, 60, 30]])], {"radius": [1, 2]})
    with pytest.raises(SphereBenchError):
        tune([img], [np.array([[50, 60, 30]])], [])
    with pytest.raises(SphereBenchError):
        tune([img, img], [np.array([[50, 60, 30]])])
    assert detect_circles(np.full((H, W, 3), 90, np.uint8)) == []  # nothing to find
