"""The detector's ranked output: every distinct verified sphere down to ``rank_floor``, the search the same
whatever is reported; and the benchmark's one protocol for every method (``registry.ranked``)."""

from __future__ import annotations

import numpy as np
import pytest

from spherebench.eval.bench import registry
from spherebench.method import IMPROVED, config_for, detect
from test_method_detector import R, _far_frames, cylinder_scene, scene


def _frames():
    yield scene(ball_c=(0.1, -0.05, 1.0))
    yield scene(ball_c=(0.0, 0.0, 0.9), ball_r=0.11)
    for top_y in (-0.05, 0.1):
        yield cylinder_scene(top_y)
    for _, cloud in _far_frames(2):
        yield cloud


def test_a_lower_min_score_adds_spheres_below_the_others_and_changes_none():
    """detect at the default min_score is the ranked output (min_score 0.01) cut at 0.67: the same
    spheres, scores and order; the ranked output is best first, at least rank_floor, and it holds
    spheres the default does not report (a cylinder of the ball's radius scores about 0.03)."""
    below = 0
    for cloud in _frames():
        default = detect(cloud, seed=0)
        ranked = detect(cloud, seed=0, min_score=0.01, max_spheres=100)
        scores = [s.score for s in ranked]
        assert scores == sorted(scores, reverse=True) and all(p >= IMPROVED.verification.rank_floor for p in scores)
        top = [s for s in ranked if s.score >= IMPROVED.verification.min_score]
        assert [s.score for s in default] == [s.score for s in top]
        assert all(np.array_equal(a.centre_m, b.centre_m) for a, b in zip(default, top))
        below += len(ranked) - len(top)
    assert below >= 2


def test_the_ranked_cylinder_is_no_detection_at_the_default():
    cloud = cylinder_scene(0.05)
    assert detect(cloud, seed=0) == []
    low = detect(cloud, seed=0, min_score=0.01)
    assert low and all(s.score < 0.5 for s in low)  # ranked, far below a ball's probability
    # a floor above it ranks nothing more; min_score below the floor reports no more than the floor
    assert detect(cloud, config_for("improved", {"verification.rank_floor": 0.5}), seed=0, min_score=0.01) == []
    assert len(detect(cloud, seed=0, min_score=0.0)) == len(low)


@pytest.mark.parametrize("accept", [0.5, 0.9])
def test_acceptance_and_not_the_report_steers_the_search(accept):
    """A ball found at any acceptance is reported by score; the same frame at min_score 0.01 ranks it first."""
    cloud = scene(ball_c=(0.1, -0.05, 1.0))
    cfg = config_for("improved", {"verification.accept_score": accept})
    best = detect(cloud, cfg, seed=0, min_score=0.01)
    assert best and np.linalg.norm(best[0].centre_m - np.array([0.1, -0.05, 1.0])) < 0.01


def test_the_benchmark_ranks_every_method_alike():
    dets = [{"score": s} for s in (0.2, 0.005, 0.9, 0.01)] + [{"score": 0.5}] * 200
    out = registry.ranked(dets)
    assert len(out) == registry.MAX_DETECTIONS and out[0]["score"] == 0.9
    assert [d["score"] for d in out] == sorted((d["score"] for d in out), reverse=True)
    assert all(d["score"] >= registry.SCORE_FLOOR for d in registry.ranked(dets[:4]))
    assert len(registry.ranked(dets[:4])) == 3


def test_the_3d_figures_are_at_the_operating_point():
    improved = registry.detector_spec("improved").config
    paper = registry.detector_spec("paper").config
    assert registry.operating_score(improved) == IMPROVED.verification.min_score
    assert registry.operating_score(paper) == 0.0
    assert registry.operating_score(registry.hough_spec(registry.HoughConfig()).config) == 0.0
    dets = [{"score": 0.9}, {"score": 0.3}]
    assert registry.at_operating_point(dets, improved) == [{"score": 0.9}]
    assert registry.at_operating_point(dets, paper) == dets


@pytest.mark.parametrize("bad", [{"min_score": 1.5}, {"min_score": -0.1}, {"max_spheres": 0}, {"max_spheres": 2.5},
                                 {"max_spheres": True}])
def test_the_report_arguments_are_checked(bad):
    from spherebench.errors import SphereBenchError
    with pytest.raises(SphereBenchError, match=next(iter(bad))):
        detect(cylinder_scene(0.05), seed=0, **bad)


def test_the_frames_depth_lookup_reads_what_the_depth_image_holds():
    from spherebench.method.detector import FrameDepth, prepare_frame
    cloud = cylinder_scene(0.05)
    cloud = cloud.subset(np.arange(0, len(cloud.points), 2))  # pixels without depth
    depth = np.full(cloud.intrinsics.shape, np.nan, np.float32)
    depth[cloud.rows, cloud.cols] = cloud.points[:, 2]
    v, u = np.nonzero(np.ones(cloud.intrinsics.shape, bool))
    got = FrameDepth(prepare_frame(cloud, IMPROVED))[v, u]
    assert np.array_equal(got, depth[v, u].astype(np.float64), equal_nan=True) and np.isnan(got).any()


def test_the_3d_table_counts_only_what_the_user_gets():
    """A ranked sphere below the operating point is no false detection in 3D (it is scored in 2D)."""
    from pathlib import Path

    from spherebench.eval.bench import scoring
    from spherebench.eval.bench.tasks import SceneInfo

    scene = SceneInfo(index=0, scene_id="s", path=Path("."), image_id=None, family="clean", resolution=None,
                      annotated=True, has_cloud=True, has_image=False, gt_centres_m=[[0.0, 0.0, 1.0]],
                      gt_radii_m=[0.12], n_balls=1)
    dets = [{"score": 0.9, "center_m": [0.0, 0.0, 1.005], "radius_m": 0.12},
            {"score": 0.2, "center_m": [0.5, 0.0, 2.0], "radius_m": 0.12}]
    for config, false in ((registry.detector_spec("improved").config, 0), (registry.detector_spec("paper").config, 1)):
        s = scoring.ScoredSet(output="m", method="m", kind="3d", rule=None, note="", metrics={}, config=config,
                              scenes=[{"scene_id": "s", "detections": dets}])
        scoring._score_3d(s, [scene])
        assert s.metrics["3d"]["false_detections"] == false and s.metrics["3d"]["within_2cm"] == 1.0


def test_the_relief_search_ranks_a_near_cap_above_bumps_of_noise():
    """The relief retry's score (``_kernels._relief_llr``): before a wall whose correlated noise makes
    cap-like bumps, the pretest scores the bumps within 3 % of a ball at 0.9 m, the relief a hundred
    times below it."""
    from scipy.ndimage import gaussian_filter

    from spherebench.cloud import cloud_from_depth
    from spherebench.method import search as search_stage
    from spherebench.method.detector import prepare_frame

    c = np.array([0.2, 0.05, 0.9])
    cloud = scene(ball_c=tuple(c), wall_z=2.5, noise=0.0, width=424, height=240)
    z = np.full(cloud.intrinsics.shape, np.nan, np.float32)
    z[cloud.rows, cloud.cols] = cloud.points[:, 2]
    bumps = gaussian_filter(np.random.default_rng(0).normal(size=z.shape), 4.0)  # correlated over about 5 px
    z += (0.08 / bumps.std() * bumps).astype(np.float32) * (z > 2.0)
    frame = prepare_frame(cloud_from_depth(z, cloud.intrinsics), IMPROVED)
    for relief in (False, True):
        search = search_stage.relief_search if relief else search_stage.search_frame
        centres, scores, _ = search(frame, IMPROVED, 0)
        assert len(centres) == search_stage.SEARCH_CANDIDATES and np.linalg.norm(centres[0] - c) < 0.5 * R
        assert (scores[1] < 0.01 * scores[0]) if relief else (scores[1] > 0.97 * scores[0]), (relief, scores[:3])
