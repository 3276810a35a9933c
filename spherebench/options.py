"""argparse types shared by the subcommands: each turns bad text into argparse's one-line usage error."""

from __future__ import annotations

import argparse
import json

from spherebench.errors import SphereBenchError
from spherebench.parallel import check_engine


def _integer(text: str, least: int, what: str, too_small: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not an integer{what}") from None
    if value < least:
        raise argparse.ArgumentTypeError(f"{value}: {too_small}")
    return value


def seed(text: str) -> int:
    """A run seed: an integer from 0 (numpy's SeedSequence takes no negative seed)."""
    return _integer(text, 0, " seed", "a seed is an integer from 0 up")


def count(text: str) -> int:
    """A positive count (scenes, passes): an integer from 1."""
    return _integer(text, 1, "", "give 1 or more")


def out_path(text: str) -> str:
    """An output path: never empty (an unset shell variable in `--out "$OUT"` would mean the current
    folder)."""
    if not text.strip():
        raise argparse.ArgumentTypeError("is empty (an unset shell variable?): give the path to write")
    return text


def add_executor_arguments(p: argparse.ArgumentParser, workers_help: str = "worker processes") -> None:
    """--workers, --engine and --address: where a command's tasks run (``spherebench.parallel.executor``)."""
    p.add_argument("--workers", type=int, default=2,
                   help=f"{workers_help} (with --engine ray and no --address: the local cluster's CPUs)")
    p.add_argument("--engine", choices=("local", "ray"), default="local",
                   help="local processes (default) or a Ray cluster (the `distributed` extra)")
    p.add_argument("--address", default=None, metavar="ADDR",
                   help="the Ray cluster to join, e.g. ray://head:10001 or auto (with --engine ray; "
                        "default: start a local one)")


def parse_seeds(text: str) -> list[int]:
    """"0-3" -> [0, 1, 2, 3]; "0,2,5" -> [0, 2, 5] (ranges and lists mix: "0-2,7"): a --seeds value."""
    seeds: list[int] = []
    try:
        for part in (p.strip() for p in text.split(",") if p.strip()):
            lo, _, hi = part.partition("-")
            seeds += list(range(int(lo), int(hi) + 1)) if hi else [int(lo)]
    except ValueError:
        seeds = []
    if not seeds or any(s < 0 for s in seeds):
        raise SphereBenchError(f"--seeds {text!r}: give non-negative seeds, e.g. 0-3 or 0,1,5")
    return sorted(set(seeds))


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
            out[name.strip()] = json.loads(value)
        except json.JSONDecodeError:
            infinite = value.strip().lower().lstrip("+-") in ("inf", "infinity")
            out[name.strip()] = float(value.strip()) if infinite else value
    return out


def check_executor(args: argparse.Namespace) -> None:
    """--workers, --engine and --address (``add_executor_arguments``), checked before anything is written."""
    check_engine(args.workers, args.engine, args.address)
