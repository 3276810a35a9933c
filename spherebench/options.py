"""argparse types shared by the subcommands: each turns bad text into argparse's one-line usage error."""

from __future__ import annotations

import argparse
import os

from spherebench.errors import SphereBenchError
from spherebench.parallel import check_engine, check_reachable
from spherebench.reading import parse_json


def _integer(text: str, least: int, what: str, too_small: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not an integer{what}") from None
    if value < least:
        raise argparse.ArgumentTypeError(f"{value}: {too_small}")
    return value


#: The largest seed: a uint64's, what numpy's streams take whole and what a dataset.json or a
#: result records (the reading gate reads no integer of more than 20 digits back).
MAX_SEED = 2 ** 64 - 1


def seed(text: str) -> int:
    """A run seed: an integer from 0 (numpy's SeedSequence takes no negative seed) to MAX_SEED."""
    value = _integer(text, 0, " seed", "a seed is an integer from 0 up")
    if value > MAX_SEED:
        raise argparse.ArgumentTypeError(f"{text if len(text) <= 30 else text[:27] + '...'}: a seed is at most "
                                         f"2^64 - 1 ({MAX_SEED})")
    return value


def count(text: str) -> int:
    """A positive count (scenes, passes): an integer from 1."""
    return _integer(text, 1, "", "give 1 or more")


def threads(text: str) -> int:
    """CPU threads for one process: an integer from 1 to four per CPU of this machine (and at least
    64): more only queue (999,999 asked ONNX Runtime for a pool that hung the process)."""
    most = max(64, 4 * (os.cpu_count() or 1))
    value = _integer(text, 1, "", "give 1 or more threads")
    if value > most:
        raise argparse.ArgumentTypeError(f"{value}: give at most {most} threads (four per CPU of this machine)")
    return value


def workers(text: str) -> int:
    """A number of worker processes: an integer from 1 (more than the CPUs or the tasks are not
    started, ``spherebench.parallel.pool_size``)."""
    return _integer(text, 1, "", "give 1 or more worker processes")


def loader_workers(text: str) -> int:
    """Data-loading processes: 0 (load in the main process) or more."""
    return _integer(text, 0, "", "give 0 (load in the main process) or more processes")


def subset(text: str) -> int:
    """A number of scenes to take: a count, 0 for none or -1 for all."""
    return _integer(text, -1, "", "give a count of scenes, 0 for none or -1 for all")


def fraction(text: str) -> float:
    """A score threshold: a number from 0 to 1 (NaN would compare false with every score)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not 0.0 <= value <= 1.0:
        raise argparse.ArgumentTypeError(f"{text}: give a score from 0 to 1")
    return value


def length(text: str) -> float:
    """A distance in metres: a finite number from 0 (NaN would compare false with every distance)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not 0.0 <= value < float("inf"):
        raise argparse.ArgumentTypeError(f"{text}: give a distance in metres, a finite number from 0")
    return value


def budget_ms(text: str) -> float:
    """A time budget in milliseconds: a positive finite number, or "none" for no bound (inf)."""
    if text.strip().lower() in ("none", "off", "inf"):
        return float("inf")
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number: give milliseconds, or none") from None
    if not 0.0 < value < float("inf"):
        raise argparse.ArgumentTypeError(f"{text}: give a time in milliseconds above 0, or none for no bound")
    return value


def out_path(text: str) -> str:
    """An output path: never empty (an unset shell variable in `--out "$OUT"` would mean the current
    folder)."""
    if not text.strip():
        raise argparse.ArgumentTypeError("is empty (an unset shell variable?): give the path to write")
    return text


def add_executor_arguments(p: argparse.ArgumentParser, workers_help: str = "worker processes") -> None:
    """--workers, --engine and --address: where a command's tasks run (``spherebench.parallel.executor``)."""
    p.add_argument("--workers", type=workers, default=2,
                   help=f"{workers_help} (with --engine ray and no --address: the local cluster's CPUs)")
    p.add_argument("--engine", choices=("local", "ray"), default="local",
                   help="local processes (default) or a Ray cluster (the `distributed` extra)")
    p.add_argument("--address", default=None, metavar="ADDR",
                   help="the Ray cluster to join, e.g. ray://head:10001 or auto (with --engine ray; "
                        "default: start a local one)")


#: The most run seeds one --seeds may name: every seed is a run over every scene (the benchmark
#: takes 4 to 8, a minute or more each on a small preset), so a thousand is days of work and more
#: is a typo (0-99999999), refused before the list is built.
MAX_SEEDS = 1000


def parse_seeds(text: str) -> list[int]:
    """"0-3" -> [0, 1, 2, 3]; "0,2,5" -> [0, 2, 5] (ranges and lists mix: "0-2,7"): a --seeds value."""
    bounds: list[tuple[int, int]] = []
    try:
        for part in (p.strip() for p in text.split(",") if p.strip()):
            lo, dash, hi = part.partition("-")
            if dash and not hi.strip():  # "1-": an open range says no last seed
                raise SphereBenchError(f"--seeds {text!r}: the range {part} has no end: give both, e.g. {lo}-{lo}")
            bounds.append((int(lo), int(hi) if dash else int(lo)))
    except ValueError:
        bounds = []
    if not bounds or any(lo < 0 or hi < 0 for lo, hi in bounds):
        raise SphereBenchError(f"--seeds {text!r}: give non-negative seeds, e.g. 0-3 or 0,1,5")
    if any(hi > MAX_SEED for _lo, hi in bounds):
        raise SphereBenchError(f"--seeds {text!r}: a seed is at most 2^64 - 1 ({MAX_SEED})")
    reversed_range = next(((lo, hi) for lo, hi in bounds if hi < lo), None)
    if reversed_range is not None:
        lo, hi = reversed_range
        raise SphereBenchError(f"--seeds {text!r}: the range {lo}-{hi} is reversed: give {hi}-{lo}")
    if sum(hi - lo + 1 for lo, hi in bounds) > MAX_SEEDS:
        raise SphereBenchError(f"--seeds {text!r}: more than {MAX_SEEDS} seeds, each a run over every "
                               "scene: give fewer, e.g. 0-7")
    return sorted({s for lo, hi in bounds for s in range(lo, hi + 1)})


def parse_overrides(items: list[str]) -> dict:
    """["min_score=0.3", "adaptive=false"] -> {"min_score": 0.3, "adaptive": False}: --set values, each
    read as JSON (numbers, true/false, null), or as infinity ("inf", "-inf": the fields whose
    meaning says "inf for never"), else kept as a string."""
    out = {}
    for item in items:
        name, sep, value = item.partition("=")
        if not sep or not name.strip():
            raise SphereBenchError(f"--set {item!r}: give NAME=VALUE, e.g. --set min_score=0.3")
        try:
            out[name.strip()] = parse_json(value, f"--set {name.strip()}")
        except SphereBenchError:  # a word (or an absurd number): a string, for the configuration to refuse
            infinite = value.strip().lower().lstrip("+-") in ("inf", "infinity")
            out[name.strip()] = float(value.strip()) if infinite else value
    return out


def check_executor(args: argparse.Namespace) -> None:
    """--workers, --engine and --address (``add_executor_arguments``), checked before anything is written
    or run (the cluster's port too: a dead address fails now, not after the first stages)."""
    check_engine(args.workers, args.engine, args.address)
    if args.engine == "ray" and args.address:
        check_reachable(args.address)
