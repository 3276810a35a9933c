"""Worker processes that stop cleanly: one pool for every parallel stage.

Ctrl-C in a terminal signals the whole process group. The workers ignore SIGINT, so that only the
parent reacts (one "interrupted" line, no worker tracebacks); when the parent's work stops for any
reason, pending tasks are cancelled and running workers terminated before the caller's cleanup
removes their temporary output.
"""

from __future__ import annotations

import contextlib
import multiprocessing
import signal
from concurrent.futures import ProcessPoolExecutor
from typing import Callable


def ignore_interrupts() -> None:
    """A worker's first step (also a multiprocessing.Pool initializer): the parent handles SIGINT
    and terminates the workers."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    # a forked worker inherits the CLI's SIGTERM handler: terminate() must simply end it
    signal.signal(signal.SIGTERM, signal.SIG_DFL)


def _worker_start(initializer: Callable | None, initargs: tuple) -> None:
    ignore_interrupts()
    if initializer is not None:
        initializer(*initargs)


@contextlib.contextmanager
def process_pool(workers: int, initializer: Callable | None = None, initargs: tuple = (),
                 start_method: str | None = None):
    """A ProcessPoolExecutor of ``workers`` processes whose workers ignore SIGINT; on leaving the block
    by an exception (KeyboardInterrupt, SIGTERM turned into one by the CLI), pending tasks are
    cancelled and the workers terminated at once instead of finishing the queue."""
    context = multiprocessing.get_context(start_method) if start_method else None
    pool = ProcessPoolExecutor(max_workers=workers, mp_context=context, initializer=_worker_start,
                               initargs=(initializer, initargs))
    try:
        yield pool
    except BaseException:
        processes = list((getattr(pool, "_processes", None) or {}).values())  # no public handle on them
        pool.shutdown(wait=False, cancel_futures=True)
        for p in processes:
            p.terminate()
        for p in processes:
            p.join(timeout=10)
        raise
    else:
        pool.shutdown(wait=True)

