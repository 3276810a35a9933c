"""A latency bound for one frame's detection: the time by which it must answer.

The detector looks at its ``Deadline`` between its steps (before each candidate's verification and
each retry of the search); once the time has passed it stops and reports the best verified answer
it has, and ``cut_short`` says that it did. A step under way is finished: the bound is met to about
one verification's cost (0.1-1 ms), plus the frame's preparation and first search, which always run.
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

    @classmethod
    def after_ms(cls, budget_ms: float, start_s: float | None = None) -> "Deadline":
        """The deadline ``budget_ms`` after ``start_s`` (default now); an infinite budget never passes."""
        if not budget_ms > 0:
            raise ValueError(f"a time budget must be positive, not {budget_ms} ms")
        start_s = time.perf_counter() if start_s is None else start_s
        return cls(math.inf if math.isinf(budget_ms) else start_s + budget_ms / 1e3)

    def passed(self) -> bool:
        """Whether the time is up; a True answer marks the detection as cut short."""
        if time.perf_counter() >= self.at_s:
            self.cut_short = True
            return True
        return False

    def left_ms(self) -> float:
        """Milliseconds left (negative: overrun)."""
        return (self.at_s - time.perf_counter()) * 1e3
