"""`spherebench eval` (what `make eval` runs): every method on the `default`, `hard` and `robust`
presets, Table 2 on `paper`, then the scores, tables, figures, README and provenance under results/
(``eval.bench.benchmark.run_benchmark``).

    spherebench eval [--data data] [--out results] [--seed 0] [--workers 2]
                     [--engine local|ray [--address ADDR]] [--force] [--methods ...]
"""

from __future__ import annotations

import argparse
import shlex
import time
from pathlib import Path

from spherebench import options
from spherebench.eval.bench.registry import method_names


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--data", default="data", help="folder holding default/, hard/, robust/, paper/ (and train-hough/)")
    p.add_argument("--out", type=options.out_path, default="results", help="results folder")
    p.add_argument("--seed", type=options.seed, default=0, help="run seed")
    options.add_executor_arguments(p)
    p.add_argument("--force", action="store_true", help="recompute every prediction set")
    p.add_argument("--methods", nargs="+", choices=method_names(), default=None, metavar="METHOD",
                   help="a subset of the methods (default: all)")
    p.add_argument("--quiet", action="store_true", help="no progress bars")


def command_line(args: argparse.Namespace) -> str:
    """The command that reproduces this run, for the provenance."""
    argv = ["--data", str(args.data), "--out", str(args.out), "--seed", str(args.seed), "--workers",
            str(args.workers)]
    argv += ["--engine", args.engine] + (["--address", args.address] if args.address else [])
    argv += (["--force"] if args.force else []) + (["--methods", *args.methods] if args.methods else [])
    return "spherebench eval " + shlex.join(argv)


def run(args: argparse.Namespace) -> int:
    # here, not at the top: the reports load pandas (and matplotlib to draw), and `spherebench eval --help` took
    # 2.0 s with them, about 1 s without
    from spherebench.eval.bench.benchmark import run_benchmark

    options.check_executor(args)
    t0 = time.perf_counter()
    run_benchmark(Path(args.data), Path(args.out), seed=args.seed, workers=args.workers, force=args.force,
                  methods=args.methods, progress=not args.quiet, command=command_line(args), engine=args.engine,
                  address=args.address)
    print(f"spherebench eval: results in {args.out}/ ({time.perf_counter() - t0:.0f} s)")
    return 0
