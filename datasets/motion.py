"""Moving balls for the simulator's recordings: a ball's centre over time under the physics of its
motion, sampled at a stream's frame times.

- ``thrown``: a ballistic arc under gravity, its bounces on the floor (the vertical speed kept by
  the ball's coefficient of restitution, the horizontal by the contact's grip), then rolling once
  a bounce would rise less than ``SETTLE_HEIGHT_M``;
- ``rolling``: along the floor, slowing at the rolling resistance's constant deceleration to rest;
- ``carried``: held in a hand at a walking pace, a smooth path between two points at hand height.

Coordinates are the camera's (x right, y down, z forward; metres) for a level camera, whose floor
is the plane y = ``floor_y_m`` (the camera's height above it): gravity points along +y. Every
function is a pure function of its arguments (a carried path of its ``rng``), so that a sequence
is the same from the same seed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

#: Standard gravity, m/s^2.
GRAVITY_M_S2 = 9.81
#: A basketball's coefficient of restitution on a hard floor: FIBA's drop test (from 1.80 m, the
#: bounce's top 1.20-1.40 m) gives sqrt(1.2/1.8)-sqrt(1.4/1.8) = 0.82-0.88; a worn ball or a softer
#: floor gives less.
RESTITUTION = (0.75, 0.88)
#: Rolling resistance of an inflated ball on a hard floor: its deceleration over g.
ROLLING_RESISTANCE = (0.01, 0.03)
#: The share of its horizontal speed that a ball keeps through a bounce (the contact's friction).
BOUNCE_GRIP = 0.9
#: A bounce that would rise less than this (m) ends the bouncing: the ball rolls on.
SETTLE_HEIGHT_M = 0.005
#: A walking person's pace when carrying a ball, m/s.
CARRY_SPEED_M_S = (0.5, 1.2)


@dataclass(frozen=True)
class Track:
    """One ball over a sequence: its centre (T, 3) m at each frame time (T,) s, its radius (m), its
    track id and the motion that moved it (``thrown``, ``rolling``, ``carried``, ...)."""

    times_s: np.ndarray
    centres_m: np.ndarray
    radius_m: float
    track_id: int
    kind: str


def frame_times(fps: float, duration_s: float) -> np.ndarray:
    """The frame times (T,) s of a stream of ``fps`` frames a second over ``duration_s``, from 0."""
    if not (fps > 0 and duration_s > 0):
        raise ValueError(f"fps {fps} and duration {duration_s} s must be > 0")
    return np.arange(int(math.floor(duration_s * fps + 1e-9))) / float(fps)


def rolling(start_m, velocity_m_s, floor_y_m: float, radius_m: float, resistance: float,
            times_s: np.ndarray) -> np.ndarray:
    """Centres (T, 3) m of a ball rolling on the floor from ``start_m`` (its x, z; the height is the
    floor's) at ``velocity_m_s`` (its x, z components are used), slowing at ``resistance`` g to rest."""
    t = np.asarray(times_s, np.float64)
    start = np.asarray(start_m, np.float64)
    v = np.array([velocity_m_s[0], 0.0, velocity_m_s[2]], np.float64)
    speed = float(np.linalg.norm(v))
    out = np.tile(np.array([start[0], floor_y_m - radius_m, start[2]]), (len(t), 1))
    if speed == 0.0:
        return out
    decel = resistance * GRAVITY_M_S2
    moving = np.minimum(t, speed / decel) if decel > 0 else t
    travelled = speed * moving - 0.5 * decel * moving ** 2
    return out + travelled[:, None] * (v / speed)[None, :]


def thrown(start_m, velocity_m_s, floor_y_m: float, radius_m: float, restitution: float, resistance: float,
           times_s: np.ndarray) -> np.ndarray:
    """Centres (T, 3) m of a ball thrown from ``start_m`` at ``velocity_m_s`` (camera frame): flights
    under gravity between bounces on the floor, each bounce keeping ``restitution`` of the vertical
    speed and ``BOUNCE_GRIP`` of the horizontal, then ``rolling`` once a bounce would rise less than
    ``SETTLE_HEIGHT_M``. The ball starts above the floor (its lowest point at most on it)."""
    t = np.asarray(times_s, np.float64)
    contact_y = floor_y_m - radius_m  # the centre's height when the ball touches the floor
    p = np.asarray(start_m, np.float64).copy()
    v = np.asarray(velocity_m_s, np.float64).copy()
    if p[1] > contact_y + 1e-9:
        raise ValueError(f"the ball starts below the floor (centre y {p[1]:.3f} > {contact_y:.3f} m)")
    out = np.empty((len(t), 3))
    t0, done = 0.0, np.zeros(len(t), bool)
    g = np.array([0.0, GRAVITY_M_S2, 0.0])
    for _bounce in range(1000):
        # the flight's contact: y0 + vy s + g s^2 / 2 = contact_y, the root s > 0
        drop = contact_y - p[1]
        s_hit = (-v[1] + math.sqrt(v[1] ** 2 + 2.0 * GRAVITY_M_S2 * drop)) / GRAVITY_M_S2
        now = ~done & (t < t0 + s_hit)
        s = t[now] - t0
        out[now] = p[None, :] + v[None, :] * s[:, None] + 0.5 * g[None, :] * s[:, None] ** 2
        done |= now
        t0 += s_hit
        p = p + v * s_hit + 0.5 * g * s_hit ** 2
        p[1] = contact_y
        vy_in = v[1] + GRAVITY_M_S2 * s_hit
        v = np.array([v[0] * BOUNCE_GRIP, -restitution * vy_in, v[2] * BOUNCE_GRIP])
        if done.all() or v[1] ** 2 / (2.0 * GRAVITY_M_S2) < SETTLE_HEIGHT_M:
            break
    rest = ~done
    if rest.any():
        out[rest] = rolling(p, v, floor_y_m, radius_m, resistance, t[rest] - t0)
    return out


def carried(rng: np.random.Generator, start_m, end_m, times_s: np.ndarray, speed_m_s: float | None = None,
            sway_m: float = 0.03) -> np.ndarray:
    """Centres (T, 3) m of a ball carried by hand from ``start_m`` to ``end_m`` at a walking pace
    (``speed_m_s``, else drawn from ``CARRY_SPEED_M_S``), then held there: eased in and out (a
    smoothstep of the distance), with the hand's sway (``sway_m``, a few cm of slow sinusoids drawn
    from ``rng``) on every axis."""
    t = np.asarray(times_s, np.float64)
    a, b = np.asarray(start_m, np.float64), np.asarray(end_m, np.float64)
    speed = float(rng.uniform(*CARRY_SPEED_M_S)) if speed_m_s is None else float(speed_m_s)
    duration = max(float(np.linalg.norm(b - a)) / speed, 1e-6)
    u = np.clip(t / duration, 0.0, 1.0)
    eased = u * u * (3.0 - 2.0 * u)
    out = a[None, :] + eased[:, None] * (b - a)[None, :]
    freq = rng.uniform(0.3, 1.2, size=(2, 3))  # Hz: a hand's slow sway and the gait's bob
    phase = rng.uniform(0.0, 2.0 * math.pi, size=(2, 3))
    amp = rng.uniform(0.3, 1.0, size=(2, 3)) * sway_m / 2.0
    sway = (amp[None] * np.sin(2.0 * math.pi * freq[None] * t[:, None, None] + phase[None])).sum(axis=1)
    return out + sway
