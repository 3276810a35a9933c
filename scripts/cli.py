"""The ``spherebench`` command: one program, one subcommand per step of the benchmark.

Each subcommand is a thin driver in ``scripts/`` (import name ``spherebench.scripts``) with
``add_arguments(parser)`` and ``run(args) -> int``; it is imported only when chosen, so that
``spherebench detect`` never pays for importing torch. Bad input raises SphereBenchError, printed
here as one line with a non-zero exit (``run_guarded``: also failed writes, signals, closed pipes).
"""

from __future__ import annotations

import argparse
import contextlib
import errno
import importlib
import os
import re
import signal
import sys
import threading
from pathlib import Path

from spherebench import __version__, caches
from spherebench.errors import SphereBenchError

#: (subcommand, driver module under spherebench.scripts, one-line help)
COMMANDS = [
    ("generate", "generate", "build a simulated D435 dataset (a preset) with exact ground truth"),
    ("prepare", "prepare", "turn recorded depth data (.bag, PNG, PLY/PCD/XYZ, raw) into a dataset"),
    ("show", "show", "draw a scene's ground truth: a PNG with circles and a PLY with the ball in red"),
    ("annotate", "annotate", "ball masks of recorded frames from their colour (LabelMe files to review)"),
    ("detect", "detect", "find spheres of known radius in point clouds or scene folders"),
    ("detect-2d", "detect_2d", "run the CircleNet-style 2D detector on reprojected images"),
    ("train", "train", "train the CircleNet-style 2D baseline on the train preset"),
    ("train-verifier", "train_verifier", "fit the 3D detector's verdict on the candidates of the training presets"),
    ("evaluate", "evaluate", "run methods on a dataset and score them (COCO circle mAP, 3D errors)"),
    ("eval", "benchmark", "the benchmark (make eval): every method on every benchmark preset; Table 2 on paper"),
    ("bench", "bench", "the 3D detector's accuracy and speed per configuration, beside pyransac3d"),
    ("sweep", "sweep", "the 3D detector's detections over several seeds"),
    ("robustness", "robustness", "the improved detector across sensor conditions, against its targets"),
]


def _load(module: str):
    """A driver of this package, by its module name."""
    return importlib.import_module(f"{__package__}.{module}")


class OneLineParser(argparse.ArgumentParser):
    """argparse with a usage error on one line, like every other error of the tool (subcommands'
    parsers are of the same class)."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")

    def _print_message(self, message, file=None):
        # argparse drops a failed write (a help sent to a full disk would be lost with status 0):
        # let it reach main, which says so in one line
        if message:
            (file or sys.stderr).write(message)


def build_parser(wanted: str | None = None) -> argparse.ArgumentParser:
    """The whole command line; only ``wanted``'s driver is imported and given its arguments (start-up
    stays fast: `spherebench detect` never imports torch)."""
    parser = OneLineParser(prog="spherebench", description=__doc__.splitlines()[0])
    parser.add_argument("--version", action="version", version=f"spherebench {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, module, help_text in COMMANDS:
        p = sub.add_parser(name, help=help_text, description=help_text)
        if name == wanted:
            driver = _load(module)
            driver.add_arguments(p)
            p.set_defaults(_driver=driver)
    return parser


class Terminated(KeyboardInterrupt):
    """SIGTERM or SIGHUP (timeout, kill, a batch scheduler, a closed terminal), raised like Ctrl-C so
    that every cleanup that handles an interrupt (temporary folders, worker pools) runs for it too."""

    def __init__(self, signum: int):
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


#: The signals received while a command runs, in order: a library that catches the interrupt and
#: raises an error of its own (numpy's import an ImportError, Ray's ray.get a plain
#: KeyboardInterrupt) loses that it was one, and which.
_received: list[int] = []


def _raise_terminated(signum, frame):
    _received.append(signum)
    raise Terminated(signum)


def _raise_interrupt(signum, frame):
    _received.append(signum)
    raise KeyboardInterrupt


@contextlib.contextmanager
def _signals_as_interrupts():
    """SIGTERM and SIGHUP handled as SIGINT for the duration, and each signal recorded in
    ``_received`` (restored after: tests call main). An ignored SIGINT stays ignored."""
    wanted = [s for s in (signal.SIGTERM, getattr(signal, "SIGHUP", None)) if s is not None]
    if threading.current_thread() is not threading.main_thread():
        yield  # only the main thread may set handlers
        return
    _received.clear()
    saved = {s: signal.signal(s, _raise_terminated) for s in wanted}
    if signal.getsignal(signal.SIGINT) is signal.default_int_handler:
        saved[signal.SIGINT] = signal.signal(signal.SIGINT, _raise_interrupt)
    try:
        yield
    finally:
        for s, handler in saved.items():
            signal.signal(s, handler)


#: What to do about an OSError, by errno.
_OS_ADVICE = {
    errno.ENOSPC: "the disk is full: free space or write somewhere else",
    errno.EDQUOT: "the disk quota is exceeded: free space or write somewhere else",
    errno.EROFS: "the file system is read-only: write somewhere else",
    errno.EACCES: "permission denied: choose a path you can write (or read)",
    errno.EPERM: "operation not permitted: choose another path",
    errno.EISDIR: "it is a folder: give a file name",
    errno.ENOTDIR: "a part of the path is a file, not a folder: fix the path",
    errno.ENOENT: "no such file or folder: check the path",
    errno.ENAMETOOLONG: "the name is too long: use a shorter path",
    errno.ELOOP: "a symbolic link that leads back to itself: fix or remove the link",
}


def _real_name(path) -> str:
    """``path`` with each temporary name (.tmp-<name>.<suffix>, outputs' atomic writes) as the name it
    stands for: a message names what the user asked for, never a file that is gone when it is read."""
    return os.sep.join(_TMP_NAME.sub(r"\1", part) for part in str(path).split(os.sep))


_TMP_NAME = re.compile(r"^\.tmp-(.+)\.[^.]+$")


def _file_above(path) -> str | None:
    """The first part of ``path`` that exists and is not a folder (mkdir says "File exists" of it)."""
    parts = Path(path).parts
    for k in range(1, len(parts) + 1):
        part = Path(*parts[:k])
        if not part.exists():
            return None
        if not part.is_dir():
            return str(part)
    return None


class StdoutError(OSError):
    """A failed write to standard output (a full disk under `> FILE`, /dev/full): no input's fault."""


class _Stdout:
    """sys.stdout for the length of a command: its failed writes raised as StdoutError, since the
    OSError of a write names no file and the one line must say it was standard output. A closed
    pipe stays a BrokenPipeError (run_guarded ends quietly on it)."""

    def __init__(self, stream):
        self._stream = stream

    def __getattr__(self, name):
        return getattr(self._stream, name)

    def _call(self, fn, *args):
        try:
            return fn(*args)
        except BrokenPipeError:
            raise
        except OSError as exc:
            # named, so that no caller names the error after a file of its own
            raise StdoutError(exc.errno, exc.strerror or str(exc), "<stdout>") from None

    def write(self, text: str) -> int:
        return self._call(self._stream.write, text)

    def flush(self) -> None:
        self._call(self._stream.flush)


def os_error_message(exc: OSError) -> str:
    """One line for a failed read or write: the path, what the system said, what to do."""
    where = " -> ".join(_real_name(f) for f in (exc.filename, exc.filename2) if f is not None) or "a file"
    if isinstance(exc, StdoutError):
        where = "cannot write to standard output"
    advice = _OS_ADVICE.get(exc.errno, exc.strerror or str(exc))
    if exc.errno in (errno.ENOTDIR, errno.EEXIST) and exc.filename is not None:
        part = _file_above(_real_name(exc.filename))
        if part is not None:
            advice = f"{part} is a file, not a folder: give a path under a folder (or move the file)"
    return f"{where}: {advice}"


class BadInputs:
    """The bad inputs of a batch (detect, detect-2d): each gets its one line on stderr, ``PROG: error:
    what is wrong``, and is skipped, the others go on; ``status`` is then 2."""

    def __init__(self, prog: str):
        self.prog, self.failed = prog, []

    def skip(self, raw: str, exc: Exception) -> None:
        if isinstance(exc, (BrokenPipeError, StdoutError)):  # stdout's reader has gone or it failed: stop
            raise exc
        self.failed.append(raw)
        text = os_error_message(exc) if isinstance(exc, OSError) else str(exc)
        print(f"{self.prog}: error: {text}", file=sys.stderr, flush=True)

    @contextlib.contextmanager
    def each(self, raw: str):
        """The block of one input: bad input (SphereBenchError) or a failed read (OSError) skips it."""
        try:
            yield
        except (SphereBenchError, OSError) as exc:
            self.skip(raw, exc)

    @property
    def status(self) -> int:
        return 2 if self.failed else 0


def run_guarded(prog: str, work) -> int:
    """Run ``work()`` as a command: bad input (SphereBenchError) and failed reads or writes (OSError)
    as one line on stderr with exit 2; Ctrl-C, SIGTERM and SIGHUP as one "interrupted" line with exit
    128 + the signal (the work's own cleanup has removed its partial output, or the exception's
    ``kept`` says what it kept for a rerun); a closed pipe on stdout (`| head`) quietly; stdout closed
    (`>&-`) refused before any work, since the next file opened would take its descriptor and receive
    what is printed (a one-line error; none if stderr is closed too)."""
    if sys.stdout is None:
        return _stdout_closed(prog)
    stdout, sys.stdout = sys.stdout, _Stdout(sys.stdout)
    try:
        return _run_guarded(prog, work)
    finally:
        sys.stdout = stdout


def _run_guarded(prog: str, work) -> int:
    with _signals_as_interrupts():
        try:
            status = int(work() or 0)
            sys.stdout.flush()  # here, not at exit, so that a closed pipe is caught below
            return status
        except SphereBenchError as exc:
            print(f"{prog}: error: {exc}{_kept(exc)}", file=sys.stderr)
            return 2
        except KeyboardInterrupt as exc:
            return _interrupted(prog, exc)
        except BrokenPipeError:
            # the reader has gone (e.g. `| head`): send what is still buffered nowhere, exit as by SIGPIPE
            with contextlib.suppress(OSError):
                devnull = os.open(os.devnull, os.O_WRONLY)
                os.dup2(devnull, sys.stdout.fileno())
            return 128 + int(getattr(signal, "SIGPIPE", 13))
        except OSError as exc:
            print(f"{prog}: error: {os_error_message(exc)}{_kept(exc)}", file=sys.stderr)
            return 2
        except ImportError as exc:  # an interrupt inside a library's import, re-raised as its ImportError
            interrupt = _interrupt_behind(exc)
            if interrupt is None:
                raise
            return _interrupted(prog, interrupt)
        except RuntimeError as exc:  # pathlib's resolve() of a link that leads back to itself
            looped = _SYMLINK_LOOP.match(str(exc))
            if looped is None:
                raise
            print(f"{prog}: error: {looped[1]}: {_OS_ADVICE[errno.ELOOP]}{_kept(exc)}", file=sys.stderr)
            return 2


#: What Python 3.11's pathlib raises for a symbolic link loop (RuntimeError, not OSError).
_SYMLINK_LOOP = re.compile(r"^Symlink loop from '(.*)'$")


def _stdout_closed(prog: str) -> int:
    """Stdout closed (`>&-`, Python's sys.stdout is None): one line (none if stderr is closed too) and
    status 2, before anything is printed or opened."""
    if sys.stderr is not None:
        with contextlib.suppress(OSError, ValueError):
            print(f"{prog}: error: stdout is closed: run with stdout open, or send it to a file "
                  "(> FILE, > /dev/null)", file=sys.stderr)
    return 2


def _flushed(status: int) -> int:
    """``status`` once what was printed has reached stdout; a full disk there (the help sent to
    /dev/full) is one line and status 2 (``_unwritten``), not a lost help with status 0."""
    try:
        sys.stdout.flush()
    except OSError as exc:
        return _unwritten(exc)
    return status


def _unwritten(exc: OSError) -> int:
    """The help or usage could not be written: one line on stderr (none if stderr fails too) and
    status 2; a closed pipe (`| head`) quietly, as by SIGPIPE. What is left in stdout's buffer goes
    nowhere, not into the interpreter's exit."""
    with contextlib.suppress(OSError, ValueError):
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
    if isinstance(exc, BrokenPipeError):
        return 128 + int(getattr(signal, "SIGPIPE", 13))
    with contextlib.suppress(OSError, ValueError):
        print(f"spherebench: error: cannot write to standard output ({exc.strerror or exc}): free space or write "
              "somewhere else", file=sys.stderr)
    return 2


def _interrupt_behind(exc: BaseException) -> KeyboardInterrupt | None:
    """The interrupt (Ctrl-C, or a terminating signal raised as one) behind an exception, if any:
    one it was raised in handling, or, where a library's C code dropped that (numpy's import of
    datetime), any signal received meanwhile."""
    if _received:
        return Terminated(_received[0]) if _received[0] != signal.SIGINT else KeyboardInterrupt()
    seen = set()
    while exc is not None and id(exc) not in seen:
        if isinstance(exc, KeyboardInterrupt):
            return exc
        seen.add(id(exc))
        exc = exc.__cause__ or exc.__context__
    return None


def _interrupted(prog: str, exc: KeyboardInterrupt) -> int:
    """Ctrl-C or a terminating signal: one line, and exit status 128 + the signal."""
    signum = exc.signum if isinstance(exc, Terminated) else _received[0] if _received else signal.SIGINT
    what = "interrupted" if signum == signal.SIGINT else f"stopped by {signal.Signals(signum).name}"
    with contextlib.suppress(OSError, ValueError):  # stderr closed: the status says it
        print(f"{prog}: {what}; {getattr(exc, 'kept', 'no partial output is left')}", file=sys.stderr)
    return 128 + int(signum)


def _kept(exc: BaseException) -> str:
    """What a failed command kept for a rerun (``exc.kept``, set by outputs.output_run), as the end of
    its one line."""
    kept = getattr(exc, "kept", None)
    return f"; {kept}" if kept else ""


def run_module(name: str, driver, argv: list[str] | None = None) -> int:
    """Run a driver module (its ``add_arguments`` and ``run``) on its own, as the benchmark scripts are
    (``python -m spherebench.scripts.NAME``), with the same one-line errors and exit statuses."""
    p = OneLineParser(prog=f"spherebench-{name}", description=(driver.__doc__ or name).splitlines()[0])
    driver.add_arguments(p)
    try:
        args = p.parse_args(argv)
    except SystemExit as exc:  # --help, or a usage error already printed
        return int(exc.code or 0)
    return run_guarded(name, lambda: driver.run(args))


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    caches.use_cache_folder()  # before numba, matplotlib or torch is imported
    if sys.stdout is None:  # before argparse writes a help, a version or a usage error
        known = argv and argv[0] in {name for name, _, _ in COMMANDS}
        return _stdout_closed(f"spherebench {argv[0]}" if known else "spherebench")
    # a signal from the first moment on is one line: the drivers' imports (numpy, OpenCV, torch) take a
    # few tenths of a second, in which Ctrl-C would otherwise print a traceback
    with _signals_as_interrupts():
        try:
            parser = build_parser(argv[0] if argv else None)
            try:
                args = parser.parse_args(argv)
            except SystemExit as exc:  # --help, --version, or a usage error already printed
                return _flushed(int(exc.code or 0))
            except OSError as exc:  # the help or the usage could not be written
                return _unwritten(exc)
        except KeyboardInterrupt as exc:
            return _interrupted(f"spherebench {argv[0]}" if argv else "spherebench", exc)
        except ImportError as exc:  # numpy turns an interrupt inside its import into an ImportError
            interrupt = _interrupt_behind(exc)
            if interrupt is None:
                raise
            return _interrupted(f"spherebench {argv[0]}" if argv else "spherebench", interrupt)
        if args.command is None:
            parser.print_help()
            return 2
        return run_guarded(f"spherebench {args.command}", lambda: args._driver.run(args))


if __name__ == "__main__":
    sys.exit(main())
