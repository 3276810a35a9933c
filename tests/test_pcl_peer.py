"""The PCL peer (``baselines.pcl_peer``) and the comparison's scoring (``eval.bench.pcl_ratio``).

PCL has no wheel: the peer's own tests run where the system's PCL is installed (libpcl-dev) and are
skipped elsewhere; the refusals and the scoring are tested everywhere."""

from __future__ import annotations

import numpy as np
import pytest

from spherebench.baselines import pcl_peer
from spherebench.errors import SphereBenchError
from spherebench.eval.bench.pcl_ratio import found_and_false, summary

R = 0.12


def test_found_and_false_count_balls_and_stray_answers():
    truth = [np.array([0.0, 0.0, 1.0]), np.array([0.5, 0.0, 2.0])]
    assert found_and_false([], truth) == (0, 0)
    assert found_and_false([np.array([0.0, 0.015, 1.0])], truth) == (1, 0)
    # two answers on one ball find it once; an answer 3 cm off finds nothing and is false
    assert found_and_false([np.array([0.0, 0.0, 1.01]), np.array([0.0, 0.0, 0.99]), np.array([0.53, 0, 2])],
                           truth) == (1, 1)
    assert found_and_false([np.array([0.0, 0.0, 1.0])], []) == (0, 1)


def test_summary_ratios_are_the_peers_time_over_the_detectors():
    rows = [{"balls": 1, "detector": {"ms": ms, "found": 1, "false": 0},
             "pcl": [{"ms": 100 * ms, "found": 0, "false": 1}, {"ms": 1000.0, "found": 1, "false": 0}]}
            for ms in (1.0, 2.0, 4.0)]
    s = summary(rows)
    assert s["detector"]["median_ms"] == 2.0 and s["detector"]["found"] == 3
    assert s["pcl"][0]["ratio_of_medians"] == pytest.approx(100) and s["pcl"][0]["median_ratio"] == pytest.approx(100)
    assert s["pcl"][1]["ratio_of_medians"] == pytest.approx(500) and s["pcl"][1]["median_ratio"] == pytest.approx(500)
    assert (s["pcl"][0]["false"], s["pcl"][1]["found"]) == (3, 3)


def test_build_refuses_in_one_line_without_pcl(tmp_path, monkeypatch):
    monkeypatch.setattr(pcl_peer, "pcl_version", lambda: None)
    with pytest.raises(SphereBenchError, match="libpcl-dev") as err:
        pcl_peer.build_peer(tmp_path / "build")
    assert "\n" not in str(err.value) and not (tmp_path / "build").exists()


needs_pcl = pytest.mark.skipif(pcl_peer.pcl_version() is None, reason="the system's PCL (libpcl-dev) is not installed")


def _ball_on_floor(seed: int) -> tuple[np.ndarray, np.ndarray]:
    """(points (N, 3) m, centre (3,) m): a ball's visible cap over a floor, with 2 mm noise."""
    rng = np.random.default_rng(seed)
    c = np.array([0.1, 0.2, 1.5])
    d = rng.normal(size=(4000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    cap = c + R * d[d[:, 2] < -0.2]  # the half facing the camera
    floor = np.column_stack([rng.uniform(-1, 1, 6000), np.full(6000, c[1] + R), rng.uniform(1.0, 3.0, 6000)])
    pts = np.vstack([cap, floor]) + rng.normal(scale=0.002, size=(len(cap) + len(floor), 3))
    return pts.astype(np.float32), c


@needs_pcl
def test_peer_builds_finds_a_ball_and_answers_the_same_twice(tmp_path):
    binary = pcl_peer.build_peer(tmp_path)
    assert pcl_peer.build_peer(tmp_path) == binary  # built once
    pts, c = _ball_on_floor(0)
    with pcl_peer.PclPeer(binary, pcl_peer.PclSettings(radius_m=R, max_iterations=2000)) as peer:
        first, again = peer.segment(pts), peer.segment(pts)
        empty = peer.segment(np.zeros((0, 3), np.float32))
    assert first.found and np.linalg.norm(first.centre_m - c) < 0.01 and abs(first.radius_m - R) <= 0.01
    assert first.ms > 0 and np.array_equal(first.centre_m, again.centre_m)  # PCL's fixed seed
    assert not empty.found and empty.inliers == 0
