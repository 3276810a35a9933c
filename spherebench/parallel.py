"""Worker processes for every parallel stage: one executor, one thread-pinning rule, stopping cleanly.

``executor(workers, engine, address)`` gives an object whose ``map(fn, items)`` yields ``fn(item)``
in input order, run by
- ``local`` (default): this process when ``workers <= 1``, else a pool of ``workers`` spawned
  processes (``process_pool``);
- ``ray``: the tasks of a Ray cluster (``--engine ray [--address ADDR]``; without an address a
  local one is started with ``workers`` CPUs; joining one is given up after
  ``RAY_CONNECT_TIMEOUT_S``). Ray is the optional extra ``distributed``. A local cluster keeps its
session folder in a temporary folder of the run's and its token in the run's environment
(``_local_session``): both go with it.
Every worker, local or Ray, is pinned to one thread (``SINGLE_THREAD_ENV``, ``pin_single_thread``):
the benchmark's times are single-threaded, and the output of a task depends on its arguments only,
so the results are the same whichever engine runs them.

No more processes are started than there are CPUs to run them (``usable_cpus``) or tasks to give
them. A local worker dies with its parent (``die_with_parent``): a parent killed outright (SIGKILL,
the OOM killer) leaves no worker running on into its abandoned temporary output.

Ctrl-C in a terminal signals the whole process group. Local workers ignore SIGINT, so that only
the parent reacts (one "interrupted" line, no worker tracebacks); when the parent's work stops
for any reason, pending tasks are cancelled and running workers terminated before the caller's
cleanup removes their temporary output.
"""

from __future__ import annotations

import contextlib
import importlib.util
import logging
import multiprocessing
import os
import secrets
import shutil
import signal
import sys
import tempfile
import threading
import time
from concurrent.futures import ProcessPoolExecutor
from typing import Callable, Iterable, Iterator

import cv2

from spherebench.errors import SphereBenchError
from spherebench.progress import bar as progress_bar

#: Environment variables that pin a worker to one thread (set before the worker starts).
SINGLE_THREAD_ENV = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1",
                     "NUMBA_NUM_THREADS": "1", "VECLIB_MAXIMUM_THREADS": "1"}
#: The executors of ``executor``.
ENGINES = ("local", "ray")
#: How long joining a Ray cluster (--address) may take before it is given up, seconds.
RAY_CONNECT_TIMEOUT_S = 30.0
#: Ray's variables of token authentication: where the user set one, a local cluster keeps to it.
RAY_AUTH_VARIABLES = ("RAY_AUTH_MODE", "RAY_AUTH_TOKEN", "RAY_AUTH_TOKEN_PATH")
#: How often a worker without a parent-death signal (not Linux) checks that its parent lives, seconds.
PARENT_POLL_S = 1.0
_PR_SET_PDEATHSIG = 1  # <linux/prctl.h>


def usable_cpus() -> int:
    """The CPUs this process may run on (its affinity mask, e.g. under taskset or a batch scheduler)."""
    with contextlib.suppress(AttributeError, OSError):
        return max(1, len(os.sched_getaffinity(0)))
    return max(1, os.cpu_count() or 1)


def pool_size(workers: int, tasks: int | None = None) -> int:
    """The processes worth starting for ``tasks`` tasks (None: unknown) on ``workers`` asked for:
    never more than the tasks or the CPUs (more only compete for the same cores)."""
    return max(1, min(workers, usable_cpus(), tasks if tasks is not None else workers))


def die_with_parent(parent_pid: int) -> None:
    """End this worker when the process ``parent_pid`` that started it ends, however it ends.

    Linux: the kernel's parent-death signal (SIGKILL; it fires when the thread that started this
    process exits, which for a pool is the parent's thread that lives as long as the pool). The
    parent may have died before the signal was set: then this process has already been reparented,
    and it exits now. Elsewhere: a daemon thread polls the parent's pid."""
    try:
        import ctypes  # here, not at the top: only a worker's start needs it
        libc = ctypes.CDLL(None, use_errno=True)
        armed = libc.prctl(_PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0) == 0
    except (OSError, AttributeError):
        armed = False
    if os.getppid() != parent_pid:
        os._exit(1)
    if armed:
        return

    def watch():
        while os.getppid() == parent_pid:
            time.sleep(PARENT_POLL_S)
        os._exit(1)

    threading.Thread(target=watch, name="die-with-parent", daemon=True).start()


def ignore_interrupts() -> None:
    """A worker's first step: the parent handles SIGINT and terminates the workers."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    # a forked worker inherits the CLI's SIGTERM handler: terminate() must simply end it
    signal.signal(signal.SIGTERM, signal.SIG_DFL)


def pin_single_thread() -> None:
    """Pin this (worker) process's libraries to one thread: BLAS/OpenMP and numba through the
    environment (each reads it when it loads), then OpenCV and numba directly."""
    for k, v in SINGLE_THREAD_ENV.items():
        if k != "NUMBA_NUM_THREADS" or "numba" not in sys.modules:  # numba: only before it loads
            os.environ[k] = v
    cv2.setNumThreads(1)
    import numba  # here, not at the top: numba reads NUMBA_NUM_THREADS once, when it loads (just set)
    with contextlib.suppress(ValueError):  # its pool already started with fewer threads
        numba.set_num_threads(1)


_PINNED = False


def _pinned_call(fn: Callable, item):
    """``fn(item)`` in a Ray worker, pinned to one thread at its first task."""
    global _PINNED
    if not _PINNED:
        pin_single_thread()
        _PINNED = True
    return fn(item)


@contextlib.contextmanager
def single_thread_here():
    """Numba and OpenCV at one thread in this process for a while (in-process runs), then restored."""
    import numba  # not at the top: a worker sets NUMBA_NUM_THREADS before numba loads (pin_single_thread)
    saved = cv2.getNumThreads(), numba.get_num_threads()
    cv2.setNumThreads(1)
    numba.set_num_threads(1)
    try:
        yield
    finally:
        cv2.setNumThreads(saved[0])
        numba.set_num_threads(saved[1])


def _worker_start(parent_pid: int, initializer: Callable | None, initargs: tuple) -> None:
    die_with_parent(parent_pid)
    ignore_interrupts()
    if initializer is not None:
        initializer(*initargs)


def each_with_progress(fn: Callable, tasks: list, workers: int, desc: str, unit: str, progress: bool,
                       chunksize: int = 1) -> None:
    """``fn(task)`` for every task, in a pool of worker processes (``process_pool``) where ``workers``
    (and the tasks, and the CPUs) allow more than one, advancing a progress bar (``desc``, ``unit``;
    shown when ``progress``) as each finishes. The tasks write what they make: nothing is returned."""
    bar = progress_bar(total=len(tasks), desc=desc, unit=unit, enabled=progress)
    processes = pool_size(workers, len(tasks))
    if processes > 1:
        with process_pool(processes) as pool:
            for _ in pool.map(fn, tasks, chunksize=chunksize):
                bar.update()
    else:
        for task in tasks:
            fn(task)
            bar.update()
    bar.close()


@contextlib.contextmanager
def process_pool(workers: int, initializer: Callable | None = None, initargs: tuple = (),
                 start_method: str | None = None):
    """A ProcessPoolExecutor of ``workers`` processes whose workers ignore SIGINT; on leaving the block
    by an exception (KeyboardInterrupt, SIGTERM turned into one by the CLI), pending tasks are
    cancelled and the workers terminated at once instead of finishing the queue. ``workers`` is
    capped at the CPUs (``pool_size``); each worker dies with this process (``die_with_parent``)."""
    context = multiprocessing.get_context(start_method) if start_method else None
    pool = ProcessPoolExecutor(max_workers=pool_size(workers), mp_context=context, initializer=_worker_start,
                               initargs=(os.getpid(), initializer, initargs))
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


class InProcess:
    """``map`` in this process, one thread (``workers <= 1``)."""

    workers = 1

    def map(self, fn: Callable, items: Iterable) -> Iterator:
        return map(fn, items)


class LocalPool:
    """``map`` over a pool of spawned, single-threaded worker processes."""

    def __init__(self, pool: ProcessPoolExecutor, workers: int):
        self.pool, self.workers = pool, workers

    def map(self, fn: Callable, items: Iterable) -> Iterator:
        return self.pool.map(fn, items, chunksize=1)


class RayTasks:
    """``map`` as Ray tasks of one CPU each, results in input order."""

    def __init__(self, ray, workers: int):
        self.ray, self.workers = ray, workers
        self.remote = ray.remote(num_cpus=1)(_pinned_call)

    def map(self, fn: Callable, items: Iterable) -> Iterator:
        fn_ref = self.ray.put(fn)
        refs = [self.remote.remote(fn_ref, item) for item in items]
        done = 0
        try:
            for ref in refs:
                yield self.ray.get(ref)
                done += 1
        finally:
            # stopped early (an error, Ctrl-C): the rest is not needed. Not after the cluster is shut
            # down: a Ray call would start a new one
            if done < len(refs) and self.ray.is_initialized():
                for ref in refs[done:]:
                    with contextlib.suppress(Exception):
                        self.ray.cancel(ref, force=True)


@contextlib.contextmanager
def _local(workers: int, isolated: bool = False):
    workers = pool_size(workers)  # spawned workers start as tasks come, so no more than the tasks
    if workers <= 1 and not isolated:
        with single_thread_here():
            yield InProcess()
        return
    # inherited by the workers before they import anything; NUMBA_NUM_THREADS is left to the
    # workers' initializer: numba rereads it in this process at its next compilation, and refuses
    # a value other than its running thread pool's
    child_env = {k: v for k, v in SINGLE_THREAD_ENV.items() if k != "NUMBA_NUM_THREADS"}
    with _environ(child_env), process_pool(workers, initializer=pin_single_thread, start_method="spawn") as pool:
        yield LocalPool(pool, workers)


@contextlib.contextmanager
def _environ(changes: dict, also=()):
    """This process's environment with ``changes`` (variable -> value) for the duration (its child
    processes inherit them), then as it was; so are the variables ``also``, which a library may set
    meanwhile."""
    saved = {k: os.environ.get(k) for k in (*changes, *also)}
    os.environ.update(changes)
    try:
        yield
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def _first_line(exc: BaseException) -> str:
    return (str(exc).strip().splitlines() or [type(exc).__name__])[0]


def check_reachable(address: str, timeout_s: float = RAY_CONNECT_TIMEOUT_S) -> None:
    """A Ray address (``ray://HOST:PORT`` or ``HOST:PORT``) whose port takes a TCP connection within
    ``timeout_s``: Ray itself retries a dead address for minutes. ``auto`` and ``local`` (found by
    Ray) are left to Ray."""
    if address.strip() in ("auto", "local"):
        return
    from urllib.parse import urlsplit  # here, not at the top: only --address needs it
    parts = urlsplit(address if "://" in address else f"//{address}")
    try:
        host, port = parts.hostname, parts.port
    except ValueError:  # a port that is not a number
        host = port = None
    if not host or port is None:
        raise SphereBenchError(f"--address {address}: give HOST:PORT or ray://HOST:PORT (or auto)")
    import socket  # here, not at the top: only --address needs it
    try:
        socket.create_connection((host, port), timeout=timeout_s).close()
    except OSError as exc:
        why = f"no answer within {timeout_s:g} s" if isinstance(exc, TimeoutError) else \
            (exc.strerror or _first_line(exc)).lower()
        raise SphereBenchError(f"--address {address}: no Ray cluster there ({why}): start it "
                               "(ray start --head) or check the address") from None


class _NotMainThreadNote(logging.Filter):
    """Ray's warning that a driver started outside the main thread sets no SIGTERM handler: the
    command's own handler is the one wanted."""

    def filter(self, record: logging.LogRecord) -> bool:
        return "not the main thread" not in record.getMessage()


@contextlib.contextmanager
def _logger_level(name: str, level: int):
    """A library's logger at ``level`` for the duration, then as it was."""
    logger = logging.getLogger(name)
    saved = logger.level
    logger.setLevel(level)
    try:
        yield
    finally:
        logger.setLevel(saved)


@contextlib.contextmanager
def _stderr_fd_silenced():
    """File descriptor 2 on the null device for a while: Ray's core (C++) logs its connection
    attempts there, "Failed to connect to GCS ...", before any log level of its own is read (it
    takes none from Python). Nothing else of this process writes meanwhile: the caller only waits."""
    with contextlib.suppress(AttributeError, ValueError, OSError):  # replaced or closed: nothing to flush
        sys.stderr.flush()
    try:
        saved = os.dup(2)
    except OSError:  # stderr closed: nothing to silence
        yield
        return
    null = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(null, 2)
        yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)
        os.close(null)


#: How long a join interrupted by a signal is waited for before it is shut down, seconds.
RAY_START_WAIT_S = 60.0
#: Ray's logger that warns of the token authentication it turns on for a new local cluster.
_RAY_AUTH_LOGGER = "ray._private.authentication.authentication_token_setup"


def _join_cluster(ray, address: str, runtime_env: dict, timeout_s: float = RAY_CONNECT_TIMEOUT_S) -> None:
    """``ray.init(address)``, given up after ``timeout_s``: a port that answers but is not a Ray
    cluster's (or a cluster that does not reply) is retried by Ray for minutes. It runs in a daemon
    thread, so that a connection given up on does not hold up the command's exit; a signal while it
    runs is the command's interrupt, and the connection is shut down once it returns. Ray's own log
    lines of the attempt (its Python loggers below ERROR, its core's on stderr, its notes of the
    thread and of token authentication) are left out: the command's one line says what went wrong."""
    failure: list[BaseException] = []

    def connect():
        try:
            ray.init(address=address, runtime_env=runtime_env, log_to_driver=False, logging_level=logging.ERROR)
        except BaseException as exc:  # re-raised in the caller's thread
            failure.append(exc)

    worker_log, note = logging.getLogger("ray._private.worker"), _NotMainThreadNote()
    worker_log.addFilter(note)
    thread = threading.Thread(target=connect, name="ray-connect", daemon=True)
    try:
        with _stderr_fd_silenced(), _logger_level(_RAY_AUTH_LOGGER, logging.ERROR):
            thread.start()
            try:
                thread.join(timeout_s)
            except BaseException:  # a signal: the attempt is let finish, then what it joined is left
                thread.join(RAY_START_WAIT_S)
                with contextlib.suppress(Exception):
                    ray.shutdown()
                raise
    finally:
        worker_log.removeFilter(note)
    if thread.is_alive():
        raise SphereBenchError(f"--address {address}: no answer from a Ray cluster within {timeout_s:g} s: "
                               "check that it runs there (ray status) and the address")
    if failure:
        raise failure[0]


@contextlib.contextmanager
def _signals_held(ray):
    """SIGINT and SIGTERM held back while a local cluster starts, then the first of them delivered to
    the command's own handler (as the start has returned, ``ray.shutdown`` reaches every process it
    started; cut short, the start leaves them running). Ray's start would set a SIGTERM handler of
    its own, which exits the process mid-start: it is left out. Only the main thread handles
    signals; elsewhere nothing is held."""
    utils = getattr(getattr(ray, "_private", None), "utils", None)
    if threading.current_thread() is not threading.main_thread() or not hasattr(utils, "set_sigterm_handler"):
        yield
        return
    held: list[int] = []
    saved = {s: signal.signal(s, lambda signum, frame: held.append(signum)) for s in (signal.SIGINT, signal.SIGTERM)
             if signal.getsignal(s) is not signal.SIG_IGN}  # an ignored signal stays ignored
    own = utils.set_sigterm_handler
    utils.set_sigterm_handler = lambda handler: None
    try:
        yield
    finally:
        utils.set_sigterm_handler = own
        for s, handler in saved.items():
            signal.signal(s, handler)
        if held:
            os.kill(os.getpid(), held[0])  # its handler raises where the start returned


#: the longest path Ray puts below a local cluster's folder in the temporary folder (a socket)
_RAY_SOCKET_TAIL = "/sbray-xxxxxxxx/session_YYYY-MM-DD_HH-MM-SS_UUUUUU_PPPPPPP/sockets/plasma_store"


@contextlib.contextmanager
def _local_session():
    """A temporary folder for a local cluster's session (its logs and sockets, which Ray keeps for
    good under $TMPDIR/ray), in /tmp where $TMPDIR is too deep for a socket's path, removed after
    it; and, unless the user set one of Ray's own (``RAY_AUTH_VARIABLES``), a token of the run's in
    the environment, where Ray's processes find it: Ray turns token authentication on for a new
    local cluster and would write a token to ~/.ray/auth_token."""
    here = tempfile.gettempdir()
    # Ray's sockets lie in the session folder, and a Unix socket's path has 107 bytes at most
    folder = tempfile.mkdtemp(prefix="sbray-", dir=here if len(here) + len(_RAY_SOCKET_TAIL) <= 107 else "/tmp")
    token = {} if any(os.environ.get(k) for k in RAY_AUTH_VARIABLES) else {"RAY_AUTH_TOKEN": secrets.token_hex(32)}
    try:
        with _environ(token, also=RAY_AUTH_VARIABLES):  # ray.init sets RAY_AUTH_MODE here
            yield folder
    finally:
        shutil.rmtree(folder, ignore_errors=True)


@contextlib.contextmanager
def _ray(workers: int, address: str | None):
    try:
        import ray  # here, not at the top: an optional dependency (the `distributed` extra), for this engine only
    except Exception as exc:  # found (check_engine) but broken: any error of its own import
        raise SphereBenchError(f"--engine ray: Ray is installed but does not load ({_first_line(exc)}): "
                               "reinstall it (pip install 'spherebench[distributed]')") from None
    started = not ray.is_initialized()
    with contextlib.ExitStack() as session:
        if started:
            if address:
                check_reachable(address)
            # every Ray worker starts single-threaded, as a local worker does
            runtime_env = {"env_vars": dict(SINGLE_THREAD_ENV)}
            try:
                if address:
                    _join_cluster(ray, address, runtime_env, RAY_CONNECT_TIMEOUT_S)  # read at the call, not at import
                else:
                    folder = session.enter_context(_local_session())
                    with _signals_held(ray), _logger_level(_RAY_AUTH_LOGGER, logging.ERROR):
                        ray.init(num_cpus=pool_size(workers), include_dashboard=False, runtime_env=runtime_env,
                                 log_to_driver=False, logging_level=logging.ERROR, _temp_dir=folder)
            except BaseException as exc:  # a failed start, or a signal held back during it
                with contextlib.suppress(Exception):  # what the start has started
                    ray.shutdown()
                if isinstance(exc, SphereBenchError) or not isinstance(exc, Exception):
                    raise
                # e.g. ConnectionError, ValueError (ray:// without ray[client]), RuntimeError
                where = f"--address {address}" if address else "--engine ray (a local cluster)"
                raise SphereBenchError(f"{where}: Ray did not start: {_first_line(exc)}") from None
        try:
            yield RayTasks(ray, max(1, int(ray.cluster_resources().get("CPU", workers))))
        finally:
            if started:
                ray.shutdown()


def check_engine(workers: int, engine: str, address: str | None) -> None:
    """``executor``'s arguments, checked (a command checks them before it writes anything)."""
    if workers < 1:
        raise SphereBenchError(f"--workers {workers}: give at least 1")
    if engine not in ENGINES:
        raise SphereBenchError(f"--engine {engine}: choose from {', '.join(ENGINES)}")
    if address and engine != "ray":
        raise SphereBenchError("--address is the Ray cluster's: give it with --engine ray")
    if engine == "ray" and importlib.util.find_spec("ray") is None:
        raise SphereBenchError("--engine ray needs Ray: pip install 'spherebench[distributed]'")


@contextlib.contextmanager
def executor(workers: int = 2, engine: str = "local", address: str | None = None, isolated: bool = False):
    """The executor of a run (see the module docstring): ``with executor(2) as ex: ex.map(fn, items)``.

    isolated: even one local worker is a spawned process (pinned before numpy and numba load, which
    this process cannot be), for timings that must be single-threaded throughout (``bench``)."""
    check_engine(workers, engine, address)
    with (_ray(workers, address) if engine == "ray" else _local(workers, isolated)) as ex:
        yield ex
