"""A latency bound for one frame's detection: the time by which it must answer.

The detector looks at its ``Deadline`` between its steps (before each candidate's verification and
each retry of the search) and starts no step it would not finish in time: a step is expected to
cost as much as the longest one between two looks so far. Once it stops it reports the best
verified answer it has, and ``cut_short`` says that it did. The frame's preparation and first search
always run, and a step longer than any before it may still overrun the bound.
A detection under a deadline depends on the machine's speed; without one, on its seed alone.
"""

from __future__ import annotations

import math
import time


class Deadline:
    """The time (``time.perf_counter``'s clock, s) by which a detection must answer; ``cut_short``
    becomes True when a step was left out for it."""

    def __init__(self, at_s: float):
        self.at_s = float(at_s)
        self.cut_short = False
        self._last_s: float | None = None  # the time of the last look
        self._step_s = 0.0  # the longest time between two looks

    @classmethod
    def after_ms(cls, budget_ms: float, start_s: float | None = None) -> "Deadline":
        """The deadline ``budget_ms`` after ``start_s`` (default now); an infinite budget never passes."""
        if not budget_ms > 0:
            raise ValueError(f"a time budget must be positive, not {budget_ms} ms")
        start_s = time.perf_counter() if start_s is None else start_s
        return cls(math.inf if math.isinf(budget_ms) else start_s + budget_ms / 1e3)

    def passed(self) -> bool:
        """Whether the time is up for another step (the longest step so far would end past it); a
        True answer marks the detection as cut short."""
        now = time.perf_counter()
        if self._last_s is not None:
            self._step_s = max(self._step_s, now - self._last_s)
        self._last_s = now
        if now + self._step_s >= self.at_s:
            self.cut_short = True
            return True
        return False

    def left_ms(self) -> float:
        """Milliseconds left (negative: overrun)."""
        return (self.at_s - time.perf_counter()) * 1e3
