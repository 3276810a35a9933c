"""A stream followed in time: the compiled deprojection is cloud_from_depth's, a window's cloud is
the frame's own points, a deadline cuts the detection short and says so, and track_stream searches
windows about its tracks once they are confirmed, with the frame's pixels and point indices."""

from __future__ import annotations

import numpy as np
import pytest

from spherebench.camera import Intrinsics, image_rays
from spherebench.cloud import cloud_from_depth, depth_to_metres
from spherebench.datasets import sequences
from spherebench.method import config_for, detect, stream, tracking
from spherebench.method.deadline import Deadline
from spherebench.scripts import cli


@pytest.fixture(scope="module")
def rolling():
    return sequences.build_sequence("rolling", 11, fps=90, duration_s=0.3)


class _Frame:
    def __init__(self, index, time_s, depth, intr):
        self.index = self.number = index
        self.timestamp_ms = 1000.0 * time_s
        self.depth, self.intrinsics = depth, intr


def _frames(seq):
    return [_Frame(k, t, d, seq.intrinsics) for k, (t, d) in enumerate(zip(seq.times_s, seq.depth))]


def test_the_compiled_deprojection_is_cloud_from_depth_and_a_window_is_the_frames_points(rolling):
    intr, depth = rolling.intrinsics, rolling.depth[0]
    rays = image_rays(intr)
    ref = cloud_from_depth(depth_to_metres(depth, intr), intr, rays)
    got = stream.depth_cloud(depth, intr, rays)
    assert np.array_equal(got.points, ref.points) and np.array_equal(got.rows, ref.rows)
    assert np.array_equal(got.cols, ref.cols) and got.intrinsics == intr
    v0, v1, u0, u1 = 30, 90, 100, 180
    win = stream.depth_cloud(depth, intr, rays, (v0, v1, u0, u1))
    inside = (ref.rows >= v0) & (ref.rows < v1) & (ref.cols >= u0) & (ref.cols < u1)
    assert np.array_equal(win.points, ref.points[inside])
    assert np.array_equal(win.rows + v0, ref.rows[inside]) and np.array_equal(win.cols + u0, ref.cols[inside])
    assert win.intrinsics.shape == (60, 80) and win.intrinsics.ppx == intr.ppx - u0
    with pytest.raises(ValueError, match="not within"):
        intr.window(0, 10, 400, 500)


def test_a_passed_deadline_cuts_the_detection_short_and_a_far_one_changes_nothing(rolling):
    intr = rolling.intrinsics
    cloud = stream.depth_cloud(rolling.depth[0], intr, image_rays(intr))
    config = config_for("improved")
    free = detect(cloud, config, seed=3)
    assert len(free) == 1
    far = Deadline.after_ms(60_000.0)
    same = detect(cloud, config, seed=3, deadline=far)
    assert not far.cut_short and np.array_equal(same[0].centre_m, free[0].centre_m)
    passed = Deadline(0.0)
    assert detect(cloud, config, seed=3, deadline=passed) == [] and passed.cut_short
    for bad in (0.0, -1.0, float("nan")):
        with pytest.raises(ValueError, match="positive"):
            Deadline.after_ms(bad)


def test_track_stream_searches_windows_about_a_confirmed_ball(rolling):
    config = config_for("improved")
    out = list(stream.track_stream(_frames(rolling), config, seed=0))
    first = tracking.SIZE_MIN_FRAMES - 1  # confirmed once its radius is measured
    assert [r.search for r in out[:first + 1]] == ["full"] * (first + 1)  # none confirmed: the whole frame
    assert all(r.search == "local" for r in out[first + 1:]) and not any(r.cut_short for r in out)
    rays = image_rays(rolling.intrinsics)
    for r, truth in zip(out[first:], rolling.truth[first:]):
        (track,) = [t for t in r.tracks if t.confirmed]
        assert track.track_id == 0 and np.linalg.norm(track.centre_m - truth[0]["center_m"]) < 0.02
        (sphere,) = r.spheres
        assert np.linalg.norm(np.subtract(sphere.circle_exact[:2], truth[0]["circle_px"][:2])) < 2.0
        # a window's inliers index the whole frame's cloud: its points on the ball's shell
        whole = stream.depth_cloud(r.frame.depth, r.frame.intrinsics, rays)
        shell = np.linalg.norm(whole.points[sphere.inlier_indices] - sphere.centre_m, axis=1)
        assert len(shell) > 50 and np.all(np.abs(shell - 0.12) <= sphere.evidence["eps_m"] + 1e-6)
    # the same seed, the same stream (no budget)
    again = list(stream.track_stream(_frames(rolling), config, seed=0))
    assert [r.tracks[0].centre_m.tolist() for r in again] == [r.tracks[0].centre_m.tolist() for r in out]


def test_a_deadline_starts_no_step_longer_than_the_time_left():
    import time

    deadline = Deadline.after_ms(80.0)
    assert not deadline.passed()  # the first look: no step measured yet
    time.sleep(0.045)  # a 45 ms step: another would end past the 80 ms
    assert deadline.passed() and deadline.cut_short
    assert not Deadline.after_ms(float("inf")).passed()


@pytest.mark.parametrize("value", ["0", "-5", "nan", "soon"])
def test_a_budget_that_is_no_time_is_one_line(value, capsys, tmp_path):
    assert cli.main(["detect", str(tmp_path / "r.bag"), "--budget-ms", value]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--budget-ms" in err[0]


def test_a_budget_is_for_streams(capsys, tmp_path):
    cloud = tmp_path / "c.xyz"
    cloud.write_text("0 0 1\n0 1 1\n1 0 1\n")
    assert cli.main(["detect", str(cloud), "--budget-ms", "5"]) == 2
    assert "--budget-ms is for the frames of a recording or the camera" in capsys.readouterr().err
