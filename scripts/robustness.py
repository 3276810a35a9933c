"""`spherebench robustness` (`make robustness`): the improved detector across sensor conditions,
against the robustness targets (``eval.bench.robustness``, ``eval.metrics.targets``).

    spherebench robustness data/robust --default data/default --hard data/hard --seeds 0-3 \
        --out results/robustness

Prints Markdown; --out writes OUT.md and OUT.json (atomically).
"""

from __future__ import annotations

import argparse
import sys

from spherebench import options
from spherebench.scripts.cli import run_module
from spherebench.datasets import inout, outputs
from spherebench.errors import SphereBenchError
from spherebench.eval.bench.robustness import markdown, robustness
from spherebench.eval.bench.sweep import read_settings
from spherebench.method import config_for


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("robust", help="the robust preset's folder (spherebench generate --preset robust)")
    p.add_argument("--default", default=None, help="the default preset's folder: its rate, error and the timing")
    p.add_argument("--hard", default=None, help="the hard preset's folder: negatives and distractors")
    p.add_argument("--seeds", default="0-3", help="run seeds, e.g. 0-3 or 0,2")
    p.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                   help="override a detector setting by its path (repeatable), as in sweep")
    options.add_executor_arguments(p, "processes")
    p.add_argument("--limit", type=options.count, default=None,
                   help="at most this many scenes per dataset (quick runs)")
    p.add_argument("--no-timing", action="store_true", help="skip the timing against paper-lstsq")
    p.add_argument("--out", type=options.out_path, default=None, help="write OUT.md and OUT.json")


def run(args: argparse.Namespace) -> int:
    seeds = options.parse_seeds(args.seeds)
    overrides = read_settings(args.set, "robustness")
    config_for("improved", **overrides)  # a bad override: one line before any work
    options.check_executor(args)
    for ds in (args.robust, args.default, args.hard):
        if ds:
            inout.list_scenes(ds)
    if args.out is not None:
        outputs.check_report_out(args.out, "robustness")
    if not ((inout.read_dataset_meta(args.robust).get("sensor_ranges") or {}).get("grid")):
        raise SphereBenchError(f"{args.robust}: no grid of sensor cells in its dataset.json: give the robust "
                               "preset's folder (spherebench generate --preset robust)")
    res = robustness(args.robust, seeds, args.default, args.hard, overrides, args.workers, args.limit,
                     not args.no_timing, progress=lambda s: print(s, file=sys.stderr, flush=True),
                     engine=args.engine, address=args.address)
    md = markdown(res)
    print(md, flush=True)  # before the report's files: stdout that fails leaves none
    if args.out is not None:
        print("wrote {} and {}".format(*outputs.write_report(args.out, md, res, "robustness")), file=sys.stderr)
    return 0


def main(argv: list[str] | None = None) -> int:
    return run_module("robustness", sys.modules[__name__], argv)


if __name__ == "__main__":
    sys.exit(main())
