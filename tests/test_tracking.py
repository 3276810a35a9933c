"""Tracking by detection (``method.tracking``) on detections drawn from true motions: one id per
ball through missed frames and crossings, a filtered centre better than one frame's, flickering
false detections never confirmed, and the evidence fused over a track."""

from __future__ import annotations

import numpy as np
import pytest

from spherebench.datasets import motion
from spherebench.method.tracking import CONFIRM_HITS, MAX_MISSED_S, Detection, Tracker

FPS = 90.0
FLOOR_Y_M, R = 0.8, 0.12


def _throw(duration_s=3.0):
    t = motion.frame_times(FPS, duration_s)
    return t, motion.thrown([-1.0, FLOOR_Y_M - R - 0.9, 2.5], [1.2, -2.5, 0.1], FLOOR_Y_M, R, 0.8, 0.02, t)


@pytest.mark.parametrize("gravity, better", [(None, 0.95), ((0.0, motion.GRAVITY_M_S2, 0.0), 0.7)])
def test_a_thrown_ball_keeps_one_track_through_its_bounces_and_missed_frames(gravity, better):
    rng = np.random.default_rng(0)
    t, truth = _throw()
    tracker = Tracker(gravity_m_s2=gravity)
    raw, filtered, ids = [], [], set()
    for k, (time_s, c) in enumerate(zip(t, truth)):
        dets = []
        if rng.random() > 0.2:  # a fifth of the frames miss the ball
            dets.append(Detection(c + rng.normal(0, 0.02, 3), 0.9, 0.12 + rng.normal(0, 0.004)))
        tracks = tracker.update(float(time_s), dets)
        confirmed = [tr for tr in tracks if tr.confirmed]
        if k > 10:
            assert len(confirmed) == 1, k
            ids.add(confirmed[0].track_id)
            filtered.append(np.linalg.norm(confirmed[0].centre_m - c))
            if dets:
                raw.append(np.linalg.norm(dets[0].centre_m - c))
    assert ids == {0}  # no id switch, through bounces and misses
    rms = lambda e: float(np.sqrt(np.mean(np.square(e))))  # noqa: E731
    assert rms(filtered) < better * rms(raw)  # the track is better than one frame's centre, much with gravity
    final = tracker.tracks[0]  # the tracker's own Track
    assert final.radius_m == pytest.approx(0.12, abs=0.002) and final.probability == pytest.approx(0.9, abs=1e-6)


def test_two_crossing_balls_keep_their_ids():
    t = motion.frame_times(FPS, 3.0)
    paths = {"a": motion.rolling([-1.2, 0.0, 2.0], [0.9, 0.0, 0.0], FLOOR_Y_M, R, 0.0, t),
             "b": motion.rolling([1.2, 0.0, 2.25], [-0.9, 0.0, 0.0], FLOOR_Y_M, R, 0.0, t)}  # they cross at 1.33 s
    rng = np.random.default_rng(1)
    tracker = Tracker()
    ball_of = {}
    for k, time_s in enumerate(t):
        dets = [Detection(paths[name][k] + rng.normal(0, 0.01, 3), 0.9) for name in ("a", "b")]
        tracks = tracker.update(float(time_s), dets[::-1] if rng.random() < 0.5 else dets)
        if k == 0:  # which ball each track began on
            ball_of = {tr.track_id: min(paths, key=lambda n: np.linalg.norm(tr.centre_m - paths[n][0])) for tr in tracks}
    assert sorted(tr.track_id for tr in tracks) == [0, 1] and sorted(ball_of.values()) == ["a", "b"]
    for tr in tracks:  # each id still follows its own ball, past the crossing
        assert np.linalg.norm(tr.centre_m - paths[ball_of[tr.track_id]][-1]) < 0.05


def test_flickering_false_detections_are_never_confirmed_and_a_lost_track_ends():
    rng = np.random.default_rng(2)
    tracker = Tracker()
    t = motion.frame_times(FPS, 2.0)
    for time_s in t:
        # clutter: a false detection somewhere new every few frames
        dets = [Detection(rng.uniform([-2, -1, 1], [2, 1, 5]), 0.7)] if rng.random() < 0.3 else []
        tracks = tracker.update(float(time_s), dets)
        assert not any(tr.confirmed for tr in tracks)
    ball = np.array([0.0, 0.5, 2.0])
    for k in range(CONFIRM_HITS):
        tracks = tracker.update(2.0 + k / FPS, [Detection(ball, 0.9)])
    assert [tr.confirmed for tr in tracks if np.allclose(tr.centre_m, ball, atol=0.05)] == [True]
    later = 2.0 + CONFIRM_HITS / FPS + MAX_MISSED_S + 0.05
    assert tracker.update(later, []) == [] or all(not np.allclose(tr.centre_m, ball, atol=0.05)
                                                  for tr in tracker.tracks)
    with pytest.raises(ValueError, match="time order"):
        tracker.update(later - 1.0, [])


def test_a_gap_in_the_clock_ends_the_tracks_and_a_new_one_starts():
    tracker = Tracker()
    ball = np.array([0.0, 0.5, 2.0])
    for k in range(CONFIRM_HITS):
        tracks = tracker.update(k / FPS, [Detection(ball, 0.9)])
    assert [tr.track_id for tr in tracks if tr.confirmed] == [0]
    # two seconds without a frame (a recording's gap): the ball is met again elsewhere
    tracks = tracker.update(2.0 + CONFIRM_HITS / FPS, [Detection(ball + [1.0, 0.0, 0.0], 0.9)])
    assert [(tr.track_id, tr.confirmed) for tr in tracks] == [(1, False)]
