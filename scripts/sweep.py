"""`spherebench sweep` (`make sweep`): the 3D detector's detections over several seeds (``eval.bench.sweep``).

    spherebench sweep data/default data/hard --seeds 0-7 --out results/sweep
    spherebench sweep data/train --seeds 0-3 --set verification.verify_candidates_if_none=10
"""

from __future__ import annotations

import argparse
import sys

from spherebench import options
from spherebench.scripts.cli import run_module
from spherebench.datasets import inout, outputs
from spherebench.eval.bench.sweep import markdown, read_settings, sweep


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("datasets", nargs="+", help="dataset folders")
    p.add_argument("--seeds", default="0-3", help="run seeds: a range, a list, or both (e.g. 0-3, 0,2,5)")
    p.add_argument("--method", default="improved", help="detector preset (improved, paper, paper-lstsq)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="NAME=VALUE",
                   help="override a detector setting by its path (repeatable), e.g. --set verification.min_score=0.3")
    options.add_executor_arguments(p, "processes (each single-threaded)")
    p.add_argument("--limit", type=options.count, default=None, help="at most this many scenes per dataset (quick runs)")
    p.add_argument("--out", default=None, metavar="OUT",
                   help="write the report to OUT.md and OUT.json, atomically (OUT: a path without its suffix, e.g. "
                        "results/sweep; not a folder)")


def run(args: argparse.Namespace) -> int:
    options.check_executor(args)
    for ds in args.datasets:
        inout.list_scenes(ds)  # a clear error for a missing dataset before any work
    if args.out is not None:
        outputs.check_report_out(args.out, "sweep")
    result = sweep(args.datasets, options.parse_seeds(args.seeds), args.method, read_settings(args.overrides, "sweep"),
                   args.workers, args.limit, engine=args.engine, address=args.address)
    md = markdown(result)
    print(md, flush=True)  # before the report's files: stdout that fails leaves none
    if args.out is not None:
        print("wrote {} and {}".format(*outputs.write_report(args.out, md, result, "sweep")), file=sys.stderr)
    return 0


def main(argv: list[str] | None = None) -> int:
    return run_module("sweep", sys.modules[__name__], argv)


if __name__ == "__main__":
    sys.exit(main())
