"""Scores of a stream's answers against a moving-ball sequence's truth, frame by frame: the CLEAR-MOT
counts (balls missed, false answers, identity switches, fragmentations; MOTA), the share of balls
found within 2 cm, the centre's RMS error, and the frames where a distractor ball was taken for
the target. The answers are a tracker's confirmed tracks (each with its id) or a per-frame
detector's spheres (no id: identities are not scored).

Per frame, answers and the balls counted in it are paired by the least total distance, each pair
within ``SAME_BALL_FRACTION`` of the radius (the answer is on that ball). A ball counts in a frame
where ``SEEN_FRACTION`` of its silhouette is seen; an answer on a ball seen less is neither right
nor wrong (MOT's ignored regions). Short pure functions of arrays: the runner that makes the answers
is ``eval.bench.tracks``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import linear_sum_assignment

#: An answer within this share of the radius of a ball's centre is on that ball (their silhouettes
#: overlap by more than half).
SAME_BALL_FRACTION = 1.0
#: A ball is found when an answer's centre is this near, m (the benchmark's accuracy criterion).
FOUND_M = 0.02
#: A ball counts in a frame where at least this share of its silhouette is seen.
SEEN_FRACTION = 0.25
#: A distractor this near the camera (m) must not be taken for the target.
DISTRACTOR_RANGE_M = 3.0
#: The stereo model's accuracy target is scored on balls this near the camera, m.
NEAR_M = 2.5


@dataclass
class FrameTruth:
    """One frame's truth: the targets (track ids (G,), centres (G, 3) m, visible fractions (G,)) and
    the other balls' centres (D, 3) m."""

    track_ids: np.ndarray
    centres_m: np.ndarray
    visible: np.ndarray
    distractors_m: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))


@dataclass
class Answers:
    """One frame's answers: ids (K,) (-1: none, a per-frame detector's), centres (K, 3) m, and
    whether each is confirmed (K,) bool (None: all are; a detector's answers are its claims)."""

    ids: np.ndarray
    centres_m: np.ndarray
    confirmed: np.ndarray | None = None


def pair(truth_m: np.ndarray, answers_m: np.ndarray, gate_m: float) -> list[tuple[int, int, float]]:
    """(ball, answer, distance m) pairs of least total distance, each within gate_m."""
    if not len(truth_m) or not len(answers_m):
        return []
    d = np.linalg.norm(truth_m[:, None, :] - answers_m[None, :, :], axis=-1)
    rows, cols = linear_sum_assignment(np.where(d <= gate_m, d, 1e6))
    return [(int(i), int(j), float(d[i, j])) for i, j in zip(rows, cols) if d[i, j] <= gate_m]


def sequence_counts(truth: list[FrameTruth], answers: list[Answers], radius_m: float) -> dict:
    """The counts of one sequence (summable over sequences; ``summary`` makes the rates):
    balls (ball-frames counted), found (within ``FOUND_M``), matched (an answer on the ball),
    sq_error_m2 (their squared centre errors summed), misses, false (answers on no ball), switches
    (a ball's answer id changed), fragments (a ball's answers broken off and taken up again), near
    and found_near (the balls within ``NEAR_M``), distractor_frames (a distractor within
    ``DISTRACTOR_RANGE_M`` with a confirmed answer on it)."""
    if len(truth) != len(answers):
        raise ValueError(f"{len(answers)} frames of answers for {len(truth)} frames of truth")
    gate = SAME_BALL_FRACTION * radius_m
    c = dict.fromkeys(("balls", "found", "matched", "misses", "false", "switches", "fragments", "near",
                       "found_near", "distractor_frames"), 0)
    c["sq_error_m2"] = 0.0
    last_id: dict[int, int] = {}  # a ball's answer id when last matched
    ever: set[int] = set()  # the balls answered before
    broken: dict[int, bool] = {}  # whether a ball's answers broke off since
    for t, a in zip(truth, answers):
        counted = t.visible >= SEEN_FRACTION
        pairs = pair(t.centres_m, a.centres_m, gate)
        on_ball = {j for _, j, _ in pairs}
        c["false"] += sum(1 for j in range(len(a.ids)) if j not in on_ball)
        matched = {i: (j, d) for i, j, d in pairs}
        for i in range(len(t.track_ids)):
            if not counted[i]:  # an answer on it was paired: neither right nor wrong
                continue
            ball = int(t.track_ids[i])
            near = float(np.linalg.norm(t.centres_m[i])) <= NEAR_M
            c["balls"] += 1
            c["near"] += near
            if i not in matched:
                c["misses"] += 1
                broken[ball] = ball in ever
                continue
            j, d = matched[i]
            c["matched"] += 1
            c["sq_error_m2"] += d * d
            c["found"] += d <= FOUND_M
            c["found_near"] += near and d <= FOUND_M
            answer_id = int(a.ids[j])
            if answer_id >= 0:
                c["switches"] += ball in last_id and last_id[ball] != answer_id
                last_id[ball] = answer_id
            c["fragments"] += broken.pop(ball, False)
            ever.add(ball)
        near_distractors = t.distractors_m[np.linalg.norm(t.distractors_m, axis=-1) <= DISTRACTOR_RANGE_M] \
            if len(t.distractors_m) else t.distractors_m
        sure = a.centres_m if a.confirmed is None else a.centres_m[a.confirmed]
        c["distractor_frames"] += bool(pair(near_distractors, sure, gate))
    return c


def add_counts(counts: list[dict]) -> dict:
    """The sum of several sequences' counts."""
    total: dict = {}
    for c in counts:
        for k, v in c.items():
            total[k] = total.get(k, 0) + v
    return total


def summary(c: dict) -> dict:
    """Rates of summed counts: found_share (of the ball-frames), found_near_share (of those within
    ``NEAR_M``), rmse_m (of the matched), mota, switches_per_100 (identity switches per 100 matched
    frames)."""
    balls = max(c["balls"], 1)
    return {"found_share": c["found"] / balls if c["balls"] else float("nan"),
            "found_near_share": c["found_near"] / c["near"] if c["near"] else float("nan"),
            "rmse_m": float(np.sqrt(c["sq_error_m2"] / c["matched"])) if c["matched"] else float("nan"),
            "mota": 1.0 - (c["misses"] + c["false"] + c["switches"]) / balls if c["balls"] else float("nan"),
            "switches_per_100": 100.0 * c["switches"] / c["matched"] if c["matched"] else 0.0}
