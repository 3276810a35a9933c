"""Tracking by detection: balls followed over a stream from each frame's detections.

Each track is a Kalman filter over the ball's centre and velocity (metres, m/s, the camera's frame)
under a constant-velocity model whose white acceleration noise (``ACCEL_NOISE_M_S2``) covers a
thrown ball's arc and a bounce's turn; where the camera's gravity is known (``gravity_m_s2``: a
level camera's is +y), it is the model's known acceleration. A frame's detections are assigned to
the predicted tracks by the least total Mahalanobis distance (Hungarian assignment), each within a
gate that a true match passes with probability ``1 - GATE_MISS_RATE``; a detection left over
takes over a track that matched nothing if it lies within ``REACQUIRE_M`` of it (a bounce's turn),
else starts a tentative track, which is confirmed once ``CONFIRM_HITS`` of its last ``CONFIRM_WINDOW``
frames matched and its radius is the ball's, and a track unmatched for ``MAX_MISSED_S`` ends. A
track fuses its detections' evidence: its probability that it is the ball (the mean of its
detections' scores in log-odds: the frames of one ball are not independent evidence, so they are
averaged, not summed) and its radius (the mean of its detections' free radii). Where the tracker is
given the ball's radius, a track whose fused radius is off it by more than ``RADIUS_SIGMAS``
standard errors (its radii's scatter over their count, and ``RADIUS_BIAS_M``, the part that no
count of frames averages out) is another ball: followed, so that its detections take no other
track, but not confirmed; none is confirmed before ``SIZE_MIN_FRAMES`` radii are in. A detection's
centre error is its own where the detector gives it (``Detection.sigma_m``).

Arrays in, tracks out: the tracker knows nothing of files or of the detector's internals.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.stats import chi2

#: White acceleration noise of the motion model, m/s^2, where gravity is unknown: a ball in flight
#: falls at one g away from constant velocity (a bounce's turn is taken up by ``REACQUIRE_M``) ...
ACCEL_NOISE_M_S2 = 10.0
#: ... and where it is known (in the model): what is left, a carried ball's sway, air drag.
ACCEL_NOISE_GRAVITY_KNOWN_M_S2 = 3.0
#: A detection's centre error, m, per axis (the detector's lateral error at 2-3 m on the stereo
#: model is 1-3 cm; the range error of a face-fit centre is of the same order).
MEASUREMENT_SIGMA_M = 0.02
#: The share of true matches the gate may refuse (chi-square, 3 degrees of freedom).
GATE_MISS_RATE = 1e-3
#: A tentative track is confirmed when this many of its last ``CONFIRM_WINDOW`` frames matched.
CONFIRM_HITS = 3
CONFIRM_WINDOW = 5
#: A track that matched nothing for this long ends, s.
MAX_MISSED_S = 0.3
#: A detection outside every gate but this near (m) to a track that matched nothing takes that track
#: over, its velocity started again: a bounce or a catch turns the ball within a frame, beyond any
#: constant-velocity model's gate.
REACQUIRE_M = 0.5
#: A detection's score is clipped to this distance from 0 and 1 before it counts as evidence.
SCORE_CLIP = 1e-3
#: The error of a track's mean free radius that no count of frames averages out, m: the RMS of the
#: sequences' mean free radius about the true one over the motion training recordings of both sensor
#: models (1.3 mm over 24 analytic, 3.2 mm over 8 stereo; docs/experiments/2026-12-06-tracking.md).
RADIUS_BIAS_M = 0.002
#: A track's radius is another ball's beyond this many standard errors (a true ball fails 0.3 %).
RADIUS_SIGMAS = 3.0
#: A track is confirmed only once this many of its detections' radii are in (the size test's
#: scatter is measured, not assumed).
SIZE_MIN_FRAMES = 5


@dataclass
class Detection:
    """One detection of a frame: centre (3,) m, its score (a probability that it is the ball), its
    free radius (m; None where unmeasured) and its centre's standard error per axis (m; None: the
    tracker's ``MEASUREMENT_SIGMA_M``)."""

    centre_m: np.ndarray
    score: float
    radius_m: float | None = None
    sigma_m: float | None = None


@dataclass
class Track:
    """A followed ball, as the tracker keeps it: its filter state (centre, velocity; 6,) and covariance
    (6, 6), its id, when it was last predicted and last matched, its recent matches (True/False per
    frame), and its fused evidence as running sums (bounded over an hour-long stream)."""

    track_id: int
    state: np.ndarray
    covariance: np.ndarray
    last_time_s: float
    last_match_s: float
    hits: list[bool] = field(default_factory=list)
    seen: bool = False  # it has once matched CONFIRM_HITS of CONFIRM_WINDOW frames
    confirmed: bool = False  # seen, and its radius may be the ball's
    log_odds_sum: float = 0.0
    n_scores: int = 0
    radius_sum_m: float = 0.0
    radius_sq_sum_m2: float = 0.0
    n_radii: int = 0
    matched: int | None = None  # the index of this frame's detection it took, None: none

    @property
    def centre_m(self) -> np.ndarray:
        return self.state[:3]

    @property
    def velocity_m_s(self) -> np.ndarray:
        return self.state[3:]

    @property
    def probability(self) -> float:
        """The fused probability that the track is the ball: its detections' mean log-odds."""
        return 1.0 / (1.0 + math.exp(-self.log_odds_sum / self.n_scores)) if self.n_scores else 0.5

    @property
    def radius_m(self) -> float | None:
        return self.radius_sum_m / self.n_radii if self.n_radii else None

    @property
    def radius_se_m(self) -> float | None:
        """The mean radius's standard error, m: its radii's scatter over their count, with
        ``RADIUS_BIAS_M``; None below two radii."""
        if self.n_radii < 2:
            return None
        mean = self.radius_sum_m / self.n_radii
        var = max(self.radius_sq_sum_m2 / self.n_radii - mean * mean, 0.0) * self.n_radii / (self.n_radii - 1)
        return math.sqrt(var / self.n_radii + RADIUS_BIAS_M ** 2)

    def size_ok(self, radius_m: float | None) -> bool:
        """Whether its radius may be ``radius_m`` (None: any ball will do); with fewer than
        ``SIZE_MIN_FRAMES`` radii in, not yet, unless its detections measure none."""
        if radius_m is None or (self.n_radii == 0 and self.n_scores >= SIZE_MIN_FRAMES):
            return True
        if self.n_radii < SIZE_MIN_FRAMES:
            return False
        return abs(self.radius_m - radius_m) <= RADIUS_SIGMAS * self.radius_se_m

    @property
    def reported(self) -> bool:
        """Whether the tracker answers with it this frame: confirmed, or new (fewer than
        ``SIZE_MIN_FRAMES`` detections taken, so neither confirmed nor shown to be another ball yet)
        and matched in this frame: a new ball is answered from its first frame, as a detector answers."""
        return self.confirmed or (self.matched is not None and self.n_scores < SIZE_MIN_FRAMES)

    def state_now(self) -> "TrackState":
        return TrackState(self.track_id, self.confirmed, self.state[:3].copy(), self.state[3:].copy(),
                          self.covariance.copy(), self.probability, self.radius_m, self.radius_se_m, self.matched,
                          self.reported)


class TrackState(NamedTuple):
    """A track as it stood after one frame (a copy: the tracker goes on): its id, whether it is
    confirmed, its filtered centre (3,) m and velocity (3,) m/s, camera frame, their covariance (6, 6),
    its fused probability and radius (m; None where unmeasured) with the radius's standard error (m;
    None below two radii), the index of the frame's detection it took (None: none), and whether it is
    the tracker's answer in this frame (``Track.reported``)."""

    track_id: int
    confirmed: bool
    centre_m: np.ndarray
    velocity_m_s: np.ndarray
    covariance: np.ndarray
    probability: float
    radius_m: float | None
    radius_se_m: float | None
    matched: int | None
    reported: bool


def _log_odds(score: float) -> float:
    p = min(max(float(score), SCORE_CLIP), 1.0 - SCORE_CLIP)
    return math.log(p / (1.0 - p))


class Tracker:
    """Tracks over a stream: ``update(time_s, detections)`` once per frame, in time order; it returns
    the live tracks after the frame (``TrackState``s, confirmed and tentative; ``matched`` says which
    detection each took)."""

    def __init__(self, gravity_m_s2=None, accel_noise_m_s2: float | None = None,
                 measurement_sigma_m: float = MEASUREMENT_SIGMA_M, radius_m: float | None = None):
        """gravity_m_s2: the camera frame's gravity (3,) m/s^2 where known (a level camera's is
        (0, 9.81, 0)), for balls in flight only: every track then falls, which a rolled, carried or
        resting ball does not; accel_noise_m_s2: default ``ACCEL_NOISE_M_S2``, or with gravity known
        ``ACCEL_NOISE_GRAVITY_KNOWN_M_S2``; measurement_sigma_m: a detection's centre error where it
        gives none; radius_m: the ball's radius (m), which a confirmed track's must match (None: any)."""
        self.radius_m = None if radius_m is None else float(radius_m)
        self.gravity = np.zeros(3) if gravity_m_s2 is None else np.asarray(gravity_m_s2, np.float64).reshape(3)
        if accel_noise_m_s2 is None:
            accel_noise_m_s2 = ACCEL_NOISE_M_S2 if gravity_m_s2 is None else ACCEL_NOISE_GRAVITY_KNOWN_M_S2
        self.q = float(accel_noise_m_s2) ** 2
        self.r = float(measurement_sigma_m) ** 2 * np.eye(3)
        self.gate = float(chi2.ppf(1.0 - GATE_MISS_RATE, df=3))
        self.tracks: list[Track] = []
        self.next_id = 0
        self.time_s: float | None = None

    def predict(self, time_s: float) -> list[TrackState]:
        """Every track still live at ``time_s``, advanced to it: where to look for its ball in that
        frame (its centre and covariance); ``update`` at the same time goes on from there."""
        self._check_time(time_s)
        # a track unmatched for too long by now has ended, before it can take anything (after a gap in
        # the stream its prediction would spread over the whole room)
        self.tracks = [t for t in self.tracks if time_s - t.last_match_s <= MAX_MISSED_S]
        for t in self.tracks:
            self._predict(t, time_s)
        return [t.state_now() for t in self.tracks]

    def _check_time(self, time_s: float) -> None:
        if self.time_s is not None and time_s < self.time_s:
            raise ValueError(f"frame time {time_s} s is before the previous one ({self.time_s} s): frames "
                             "must come in time order")

    def _predict(self, track: Track, time_s: float) -> None:
        dt = time_s - track.last_time_s
        if dt <= 0:
            return
        f = np.eye(6)
        f[:3, 3:] = dt * np.eye(3)
        # white acceleration: the discrete noise of a constant-velocity model
        q = self.q * np.block([[dt ** 4 / 4 * np.eye(3), dt ** 3 / 2 * np.eye(3)],
                               [dt ** 3 / 2 * np.eye(3), dt ** 2 * np.eye(3)]])
        track.state = f @ track.state + np.concatenate([0.5 * dt * dt * self.gravity, dt * self.gravity])
        track.covariance = f @ track.covariance @ f.T + q
        track.last_time_s = time_s

    def _noise(self, d: Detection) -> np.ndarray:
        """A detection's centre covariance (3, 3), m^2."""
        return self.r if d.sigma_m is None else float(d.sigma_m) ** 2 * np.eye(3)

    def _distances(self, detections: list[Detection]) -> np.ndarray:
        """Squared Mahalanobis distances (tracks, detections) of each detection from each prediction."""
        out = np.full((len(self.tracks), len(detections)), np.inf)
        for i, t in enumerate(self.tracks):
            for j, d in enumerate(detections):
                e = np.asarray(d.centre_m, np.float64) - t.centre_m
                out[i, j] = float(e @ np.linalg.solve(t.covariance[:3, :3] + self._noise(d), e))
        return out

    def _correct(self, track: Track, detection: Detection) -> None:
        h = np.hstack([np.eye(3), np.zeros((3, 3))])
        s = h @ track.covariance @ h.T + self._noise(detection)
        gain = track.covariance @ h.T @ np.linalg.inv(s)
        track.state = track.state + gain @ (np.asarray(detection.centre_m, np.float64) - track.centre_m)
        track.covariance = (np.eye(6) - gain @ h) @ track.covariance

    def update(self, time_s: float, detections: list[Detection]) -> list[TrackState]:
        """Advance every track to ``time_s``, assign this frame's detections, start, confirm and end
        tracks; returns the live tracks."""
        self.predict(time_s)
        self.time_s = time_s
        for t in self.tracks:
            t.matched = None
        taken: set[int] = set()
        if self.tracks and detections:
            d2 = self._distances(detections)
            cost = np.where(d2 <= self.gate, d2, 1e9)
            for i, j in zip(*linear_sum_assignment(cost)):
                if d2[i, j] <= self.gate:
                    self._correct(self.tracks[i], detections[j])
                    self._take(self.tracks[i], time_s, detections[j], int(j))
                    taken.add(int(j))
        self._reacquire(time_s, detections, taken)
        for t in self.tracks:
            t.hits = (t.hits + [t.matched is not None])[-CONFIRM_WINDOW:]
            t.seen = t.seen or sum(t.hits) >= CONFIRM_HITS
            t.confirmed = t.seen and t.size_ok(self.radius_m)  # for as long as its radius may be the ball's
        self.tracks = [t for t in self.tracks if time_s - t.last_match_s <= MAX_MISSED_S]
        for j, d in enumerate(detections):
            if j not in taken:
                self.tracks.append(self._start(time_s, d, j))
        return [t.state_now() for t in self.tracks]

    def _take(self, track: Track, time_s: float, d: Detection, index: int) -> None:
        """``track`` takes detection ``index``: its evidence joins the track's."""
        track.matched, track.last_match_s = index, time_s
        track.log_odds_sum += _log_odds(d.score)
        track.n_scores += 1
        if d.radius_m is not None:
            track.radius_sum_m += float(d.radius_m)
            track.radius_sq_sum_m2 += float(d.radius_m) ** 2
            track.n_radii += 1

    def _reacquire(self, time_s: float, detections: list[Detection], taken: set[int]) -> None:
        """Detections left over take the nearest unmatched track within ``REACQUIRE_M``, whose state
        starts again from the detection (its velocity unknown)."""
        free_tracks = [t for t in self.tracks if t.matched is None]
        free = [j for j in range(len(detections)) if j not in taken]
        if not free_tracks or not free:
            return
        dist = np.array([[np.linalg.norm(np.asarray(detections[j].centre_m, np.float64) - t.centre_m) for j in free]
                         for t in free_tracks])
        for i, k in zip(*linear_sum_assignment(np.where(dist <= REACQUIRE_M, dist, 1e9))):
            if dist[i, k] <= REACQUIRE_M:
                t, j = free_tracks[i], free[k]
                t.state = np.concatenate([np.asarray(detections[j].centre_m, np.float64), np.zeros(3)])
                t.covariance = self._initial_covariance(detections[j])
                self._take(t, time_s, detections[j], j)
                taken.add(j)

    def _initial_covariance(self, d: Detection) -> np.ndarray:
        # the centre as the detection's; the velocity unknown: a walking or throwing pace's spread (3 m/s)
        return np.diag([*np.diag(self._noise(d)), 9.0, 9.0, 9.0])

    def _start(self, time_s: float, d: Detection, index: int) -> Track:
        track = Track(self.next_id, np.concatenate([np.asarray(d.centre_m, np.float64), np.zeros(3)]),
                      self._initial_covariance(d), time_s, time_s, hits=[True])
        self._take(track, time_s, d, index)
        self.next_id += 1
        return track
