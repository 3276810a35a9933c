"""Moving balls (``datasets.motion``): the physics of a throw, its bounces and the roll after them,
checked against closed forms; carried paths from a seed."""

from __future__ import annotations

import math

import numpy as np
import pytest

from spherebench.datasets import motion

FLOOR_Y_M, R = 1.2, 0.12
CONTACT_Y = FLOOR_Y_M - R


def test_frame_times_step_by_the_period():
    t = motion.frame_times(90, 2.0)
    assert len(t) == 180 and t[0] == 0.0 and np.allclose(np.diff(t), 1 / 90)
    assert len(motion.frame_times(30, 4.0)) == 120
    with pytest.raises(ValueError):
        motion.frame_times(0, 1.0)


def test_a_dropped_ball_falls_as_gravity_says_and_bounces_to_e_squared_of_its_height():
    h, e = 1.0, 0.8
    t = motion.frame_times(20_000, 2.5)  # fine enough to find the apex within a micrometre
    c = motion.thrown([0.0, CONTACT_Y - h, 2.0], [0.0, 0.0, 0.0], FLOOR_Y_M, R, e, 0.02, t)
    assert c[:, 1].max() <= CONTACT_Y + 1e-12  # never below the floor
    hit = math.sqrt(2 * h / motion.GRAVITY_M_S2)
    before = t < hit
    assert np.allclose(c[before, 1], CONTACT_Y - h + 0.5 * motion.GRAVITY_M_S2 * t[before] ** 2)
    after = (t > hit) & (t < 3 * hit)
    apex = CONTACT_Y - c[after, 1].min()
    assert apex == pytest.approx(e * e * h, rel=1e-4)
    assert np.allclose(c[:, [0, 2]], [0.0, 2.0])  # straight down, straight up


def test_a_throw_keeps_the_grip_share_of_its_horizontal_speed_at_each_bounce_then_rolls_to_rest():
    v0 = np.array([1.0, -3.0, 0.5])
    t = motion.frame_times(1000, 12.0)
    c = motion.thrown([0.0, CONTACT_Y - 0.5, 2.0], v0, FLOOR_Y_M, R, 0.8, 0.02, t)
    vx = np.diff(c[:, 0]) / np.diff(t)
    speeds = sorted({round(v, 3) for v in vx if v > 1e-3})
    assert speeds[-1] == pytest.approx(1.0, abs=1e-3)  # the first flight's
    assert any(abs(v - 0.9) < 2e-3 for v in speeds)  # after one bounce (BOUNCE_GRIP)
    assert np.allclose(c[-200:, 1], CONTACT_Y)  # rolling on the floor at the end ...
    assert np.allclose(np.diff(c[-100:, [0, 2]], axis=0), 0.0)  # ... and at rest
    assert c[:, 1].max() <= CONTACT_Y + 1e-12


def test_a_rolling_ball_stops_where_its_speed_runs_out():
    t = motion.frame_times(100, 20.0)
    c = motion.rolling([0.0, 0.0, 2.0], [0.6, 0.0, 0.8], FLOOR_Y_M, R, 0.02, t)
    stop = 1.0 ** 2 / (2 * 0.02 * motion.GRAVITY_M_S2)  # speed 1 m/s along (0.6, 0.8)
    assert np.allclose(c[-1], [0.6 * stop, CONTACT_Y, 2.0 + 0.8 * stop])
    assert np.allclose(c[:, 1], CONTACT_Y) and np.all(np.diff(c[:, 0]) >= 0)


def test_a_carried_ball_walks_to_its_end_and_is_the_same_from_the_same_seed():
    t = motion.frame_times(90, 6.0)
    start, end = np.array([-0.8, 0.3, 2.5]), np.array([0.8, 0.2, 2.0])
    a = motion.carried(np.random.default_rng(4), start, end, t, speed_m_s=1.0)
    b = motion.carried(np.random.default_rng(4), start, end, t, speed_m_s=1.0)
    assert np.array_equal(a, b)
    assert np.linalg.norm(a[0] - start) <= 0.03 and np.linalg.norm(a[-1] - end) <= 0.03  # within the sway
    step = np.linalg.norm(np.diff(a, axis=0), axis=1) * 90
    assert step.max() < 2.0  # a walking pace (1.5 x the eased peak), no jumps between frames
