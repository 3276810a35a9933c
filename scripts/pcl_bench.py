"""The 3D detector against PCL's sphere segmentation on held-out clouds, in one run (``make pcl-bench``).

Builds the PCL peer (``baselines.pcl_peer``; needs the system's PCL: ``apt-get install libpcl-dev``)
in --build-dir, then on each scene of DATASET's --family at --resolution segments the cloud with
PCL and detects with the improved detector, one after the other (``eval.bench.pcl_ratio``). Prints
a table and writes OUT.md and OUT.json. Thin driver.

    python -m spherebench.scripts.pcl_bench data/default --family cluttered --out results/pcl_bench
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import platform
import sys
from pathlib import Path

from spherebench import __version__, options
from spherebench.baselines.pcl_peer import PclPeer, PclSettings, build_peer, pcl_version
from spherebench.datasets import outputs
from spherebench.errors import SphereBenchError
from spherebench.eval.bench import pcl_ratio
from spherebench.eval.bench.speed import subset
from spherebench.eval.bench.tasks import dataset_scenes
from spherebench.method import config_for
from spherebench.provenance import dist_version

#: PCL's iteration bounds (one peer each): the bound most sphere-fitting examples use, and ten times it
ITERATIONS = (1000, 10000)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("dataset", help="a simulated dataset folder (held out: not train), e.g. data/default")
    p.add_argument("--family", action="append", default=[], help="only this scene family (repeatable; default all)")
    p.add_argument("--resolution", default="424x240", metavar="WxH", help="only frames of this size (default 424x240)")
    p.add_argument("--limit", type=options.count, default=None, help="at most this many scenes, evenly spaced")
    p.add_argument("--iterations", type=options.count, nargs="+", default=list(ITERATIONS), metavar="N",
                   help="PCL's RANSAC iterations at most; one peer per value (default "
                        f"{' '.join(map(str, ITERATIONS))})")
    p.add_argument("--global-samples", action="store_true",
                   help="PCL draws a sample's points from the whole cloud (default: within 2 R of its first)")
    p.add_argument("--passes", type=options.count, default=3,
                   help="the detector's runs per cloud: the first right after PCL's, and the fastest (default 3)")
    p.add_argument("--build-dir", default="build", help="where the PCL peer is compiled (default build/)")
    p.add_argument("--seed", type=options.seed, default=0, help="the detector's seed (default 0)")
    p.add_argument("--out", type=options.out_path, default=None, metavar="OUT",
                   help="write OUT.md and OUT.json (default: print only)")


def run(args: argparse.Namespace) -> int:
    if args.out:
        outputs.check_report_out(args.out, "pcl-bench")
    scenes = [s for s in dataset_scenes(args.dataset) if s.has_frame and s.resolution == args.resolution
              and (not args.family or s.family in args.family)]
    if not scenes:
        raise SphereBenchError(f"{args.dataset}: no frame of {args.resolution}"
                               + (f" in family {', '.join(args.family)}" if args.family else "")
                               + ": check --family and --resolution against its dataset.json")
    if args.limit is not None:
        scenes = [scenes[k] for k in subset(len(scenes), args.limit)]
    config = config_for("improved")
    settings = [PclSettings(radius_m=config.radius_m, max_iterations=n,
                            samples_max_dist_m=0.0 if args.global_samples else 2.0 * config.radius_m)
                for n in args.iterations]
    binary = build_peer(Path(args.build_dir))

    def progress(k: int, row: dict) -> None:
        pcl = "; ".join(f"PCL {s.max_iterations} {a['ms']:.1f} ms, found {a['found']}"
                        for s, a in zip(settings, row["pcl"]))
        print(f"{k + 1}/{len(scenes)} {row['scene']}: {pcl}; detector {row['detector']['ms']:.2f} ms, found "
              f"{row['detector']['found']}", file=sys.stderr, flush=True)

    with contextlib.ExitStack() as stack:
        peers = [stack.enter_context(PclPeer(binary, st)) for st in settings]
        rows = pcl_ratio.compare(scenes, peers, config, args.seed, args.passes, progress)
    s = pcl_ratio.summary(rows)
    first = settings[0]
    sampling = "global" if args.global_samples else f"local (within {100 * first.samples_max_dist_m:g} cm)"
    d = s["detector"]
    md = ["# The detector against PCL's sphere segmentation (`make pcl-bench`)", "",
          f"{s['scenes']} scenes of `{Path(args.dataset).name}`"
          + (f" ({', '.join(args.family)})" if args.family else "") + f" at {args.resolution}, each cloud segmented by "
          f"PCL and then detected {args.passes} times, in one run; one thread each; the time of the segmentation "
          "(the k-d tree's build included) and of `detect`, not the reading. The detector's first run follows "
          "PCL's, which leaves the caches holding PCL's data; its best run is its cost as a stream's frame.", "",
          "| method | median ms | p95 ms | balls found (<= 2 cm) | false answers | PCL / improved: ratio of the "
          "medians (first run; best run); median of the scenes' ratios (first run) |", "|---|---|---|---|---|---|"]
    md += [f"| PCL, at most {st.max_iterations:,} iterations | {p['median_ms']:.1f} | {p['p95_ms']:.1f} | "
           f"{p['found']}/{s['balls']} | {p['false']} | {p['ratio_of_medians']:.0f}x ({p['ratio_of_medians_best']:.0f}x);"
           f" {p['median_ratio']:.0f}x |" for st, p in zip(settings, s["pcl"])]
    md += [f"| improved, first run | {d['median_ms']:.2f} | {d['p95_ms']:.2f} | {d['found']}/{s['balls']} | "
           f"{d['false']} | |",
           f"| improved, best of {args.passes} | {d['best_median_ms']:.2f} | {d['best_p95_ms']:.2f} | | | |", "",
           f"- PCL {pcl_version()}: SACSegmentation, SACMODEL_SPHERE, RANSAC (stopping early once a sample of inliers "
           f"is 99 % likely drawn), inliers within {100 * first.threshold_m:g} cm, radius {first.radius_m:g} m -/+ "
           f"{100 * first.tolerance_m:g} cm, {sampling} sampling, the sphere's coefficients refined on its inliers, "
           "PCL's fixed random seed; one sphere per cloud",
           f"- improved: seed {args.seed}, spherebench {__version__}, numba {dist_version('numba')}; machine "
           f"{platform.machine()}, {platform.python_implementation()} {platform.python_version()}"]
    print("\n".join(md))
    if args.out:
        data = {"dataset": str(args.dataset), "families": args.family, "resolution": args.resolution,
                "seed": args.seed, "pcl_version": pcl_version(), "pcl": [dataclasses.asdict(st) for st in settings], "summary": s,
                "rows": rows}
        paths = outputs.write_report(args.out, "\n".join(md) + "\n", data, "pcl-bench")
        print("wrote {} and {}".format(*paths), file=sys.stderr)
    return 0


if __name__ == "__main__":
    from spherebench.scripts.cli import run_module

    sys.exit(run_module("pcl_bench", sys.modules[__name__]))
