"""`spherebench bench` (`make bench`): the 3D detector's accuracy and speed on simulated datasets,
beside pyransac3d (``eval.bench.speed``).

    spherebench bench data/default data/hard --out results/bench
"""

from __future__ import annotations

import argparse
import os
import sys

from spherebench import options
from spherebench.scripts.cli import run_module
from spherebench.datasets import inout, outputs
from spherebench.errors import SphereBenchError
from spherebench.eval.bench.speed import MIN_SCORES, bench, markdown, run_info
from spherebench.eval.bench.tasks import dataset_scenes


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("datasets", nargs="*", default=["data/default", "data/hard"], help="dataset folders")
    p.add_argument("--out", default=None, help="write OUT.md and OUT.json (atomically)")
    p.add_argument("--seed", type=options.seed, default=0, help="run seed (scene k: SeedSequence((seed, k)))")
    p.add_argument("--paper-subset", type=options.subset, default=-1,
                   help="scenes per dataset for paper and paper-lstsq (evenly spaced; 0: none, -1: all)")
    p.add_argument("--peer-subset", type=options.subset, default=12, help="scenes per dataset for pyransac3d (as above)")
    p.add_argument("--peer-points", type=options.count, default=10_000, help="pyransac3d's random subsample per cloud")
    p.add_argument("--peer-iterations", type=options.count, default=1000, help="pyransac3d's iterations")
    p.add_argument("--limit", type=options.count, default=None, help="at most this many scenes per dataset (quick runs)")
    p.add_argument("--min-scores", default=",".join(f"{t:g}" for t in MIN_SCORES),
                   help="improved's operating points: min_score thresholds, comma-separated ('' for none)")
    p.add_argument("--passes", type=options.count, default=3,
                   help="timing passes of improved over each dataset (>= 1; 'best of N' in the table)")


def run(args: argparse.Namespace) -> int:
    for ds in args.datasets:
        inout.list_scenes(ds)  # a clear error for a missing dataset before any work
        if not any(s.has_cloud for s in dataset_scenes(ds, args.limit)):
            raise SphereBenchError(f"{ds}: no scene has a cloud.ply, and bench times the 3D detector on clouds: "
                                   f"rebuild it with `spherebench generate ... --clouds` (the train presets write none)")
    if args.out is not None:
        outputs.check_report_out(args.out, "bench")
    try:
        min_scores = tuple(sorted({float(t) for t in args.min_scores.split(",") if t.strip()}))
    except ValueError:
        raise SphereBenchError(f"--min-scores {args.min_scores!r}: give thresholds in [0, 1] separated by commas, "
                               "e.g. 0.6,0.67,0.75") from None
    if not all(0.0 <= t <= 1.0 for t in min_scores):
        raise SphereBenchError(f"--min-scores {args.min_scores!r}: every threshold must be within [0, 1]")
    info = run_info()
    result = bench(args.datasets, seed=args.seed, paper_subset=args.paper_subset, peer_subset=args.peer_subset,
                   peer_points=args.peer_points, peer_iterations=args.peer_iterations, limit=args.limit,
                   passes=args.passes, min_scores=min_scores,
                   progress=lambda s: print(s, file=sys.stderr, flush=True))
    info["machine"]["load_end"] = [round(x, 2) for x in os.getloadavg()]
    result.update(info)
    md = markdown(result)
    print(md, flush=True)  # before the report's files: stdout that fails leaves none
    if args.out is not None:
        slim = {k: v for k, v in result.items() if k != "datasets"}
        slim["datasets"] = {ds: {k: v for k, v in d.items() if k != "rows"} for ds, d in result["datasets"].items()}
        slim["rows"] = {ds: d["rows"] for ds, d in result["datasets"].items()}
        print("wrote {} and {}".format(*outputs.write_report(args.out, md, slim, "bench")), file=sys.stderr)
    return 0


def main(argv: list[str] | None = None) -> int:
    return run_module("bench", sys.modules[__name__], argv)


if __name__ == "__main__":
    sys.exit(main())
