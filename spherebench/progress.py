"""Progress of a long stage on stderr, one helper for every stage (generate, prepare, runs, training).

On a terminal: tqdm's bar, redrawn in place. In a file or a pipe (the log of `make eval`, a batch
job) a redrawn bar would be a line per update, so there: at most one plain line every
``PLAIN_INTERVAL_S`` while a stage runs, and one when it is complete (none when it stops early:
the command's error or "interrupted" line says why, alone).
"""

from __future__ import annotations

import sys
import time
from typing import Iterable, Iterator

from tqdm import tqdm

#: The least time between two plain progress lines of one stage (stderr not a terminal), seconds.
PLAIN_INTERVAL_S = 30.0


def _terminal() -> bool:
    return sys.stderr is not None and sys.stderr.isatty()


def bar(iterable: Iterable | None = None, *, total: int | None = None, desc: str = "", unit: str = "it",
        enabled: bool | None = True, initial: int = 0, leave: bool = True):
    """A progress bar (tqdm's ``update``, ``set_postfix``, ``set_postfix_str``, ``close``, iteration)
    for a stage of ``total`` steps of ``unit``; nothing at all when not ``enabled``, and with None
    only on a terminal (a stage whose output already says what it did)."""
    if enabled is not False and _terminal():
        return tqdm(iterable, total=total, desc=desc, unit=unit, initial=initial, leave=leave,
                    dynamic_ncols=True, file=sys.stderr)
    return PlainProgress(iterable, total=total, desc=desc, unit=unit, enabled=bool(enabled) and sys.stderr is not None,
                         initial=initial)


def write(message: str) -> None:
    """A line on stderr that does not break a bar being drawn."""
    if _terminal():
        tqdm.write(message, file=sys.stderr)
    elif sys.stderr is not None:
        print(message, file=sys.stderr, flush=True)


class PlainProgress:
    """The bar's interface as a few plain lines (see the module docstring)."""

    def __init__(self, iterable: Iterable | None = None, *, total: int | None = None, desc: str = "",
                 unit: str = "it", enabled: bool = True, initial: int = 0):
        if total is None and iterable is not None and hasattr(iterable, "__len__"):
            total = len(iterable)
        self.iterable, self.total, self.desc, self.unit, self.enabled = iterable, total, desc, unit, enabled
        self.n, self.postfix, self.closed, self.complete = initial, "", False, False
        self.start = self.last = time.monotonic()

    def _line(self, note: str = "") -> None:
        if not self.enabled:
            return
        done = f"{self.n}/{self.total}" if self.total is not None else f"{self.n}"
        extra = ", ".join(x for x in (note, self.postfix) if x)
        print(f"{self.desc}: {self.unit} {done}, {time.monotonic() - self.start:.0f} s"
              + (f" ({extra})" if extra else ""), file=sys.stderr, flush=True)
        self.last = time.monotonic()

    def __iter__(self) -> Iterator:
        for item in self.iterable:
            yield item
            self.update()
        self.complete = True
        self.close()

    def update(self, n: int = 1) -> None:
        self.n += n
        if time.monotonic() - self.last >= PLAIN_INTERVAL_S:
            self._line()

    def set_postfix_str(self, text: str = "") -> None:
        self.postfix = text

    def set_postfix(self, **values) -> None:
        self.postfix = ", ".join(f"{k}={v}" for k, v in values.items())

    def close(self) -> None:
        if not self.closed:
            self.closed = True
            if self.complete or (self.total is not None and self.n >= self.total):
                self._line("done")
