"""The tracking benchmark (``make track-bench``): `detect --track` and the per-frame detector on the
moving-ball recordings of the motion presets, per sequence family and depth mode: frames found
(2 cm), the centre's RMSE, identity switches and track breaks, MOTA, the distractor taken, latency
median / p95 / p99 under the frame period's budget, frames dropped in real time. Prints a line per
sequence as it goes; writes OUT.md, OUT.json and a latency histogram (--figure). Thin driver: the
work is in ``spherebench.eval.bench.tracks``.

    python -m spherebench.scripts.track_bench data/motion data/motion-stereo --out results/track_bench
"""

from __future__ import annotations

import argparse
import platform
import sys
from pathlib import Path

import numpy as np

from spherebench import __version__, options
from spherebench.datasets import outputs, sequences
from spherebench.errors import SphereBenchError
from spherebench.eval.bench import figures, tracks
from spherebench.method import config_for, warm_up
from spherebench.reading import read_json


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("datasets", nargs="+", metavar="DIR", help="datasets of the motion presets (generate --preset motion)")
    p.add_argument("--out", type=options.out_path, default=None, metavar="OUT",
                   help="write OUT.md and OUT.json (default: print only)")
    p.add_argument("--figure", default=None, metavar="PNG",
                   help="write the latency histogram here (a file SphereBench did not write is refused)")
    p.add_argument("--seed", type=options.seed, default=0, help="the detector's seed")
    p.add_argument("--budget-ms", type=options.budget_ms, default=None, metavar="MS",
                   help="each frame's latency bound (default: its stream's frame period; none: no bound, the "
                        "answers then the seed's alone)")
    p.add_argument("--no-real-time", dest="real_time", action="store_false",
                   help="skip the real-time playbacks (no frames-dropped figure; half the time)")


def _dataset(path: str) -> tuple[str, dict, list[Path]]:
    meta = read_json(Path(path) / "dataset.json") if (Path(path) / "dataset.json").is_file() else None
    if not isinstance(meta, dict) or meta.get("kind") != "sequences":
        raise SphereBenchError(f"{path}: not a dataset of moving-ball recordings: give one written by "
                               "spherebench generate --preset motion (or motion-stereo)")
    return Path(path).name, meta, sequences.sequence_folders(path)


def _budget_words(budget_ms: float | None) -> str:
    if budget_ms is None:
        return "its stream's frame period"
    return "none (every frame to its end)" if budget_ms == float("inf") else f"{budget_ms:g} ms"


def run(args: argparse.Namespace) -> int:
    if args.out:
        outputs.check_report_out(args.out, "track-bench")
    if args.figure:
        outputs.check_output_file(args.figure, "--figure", inputs=args.datasets)
    found = [_dataset(p) for p in args.datasets]  # every dataset checked before any work
    by_dataset, rows_by_dataset, stereo = {}, {}, set()
    for name, meta, folders in found:
        config = config_for("improved", radius_m=float(meta["ball_radius_m"]))
        warm_up(config)
        rows = []
        for folder in folders:
            for r in tracks.bench_sequence(folder, config, float(meta["ball_radius_m"]), args.real_time, args.seed,
                                           args.budget_ms):
                rows.append(r)
                c = r["counts"]
                print(f"{name} {r['sequence']} {r['resolution']} {r['method']:>6}: found {c['found']} of {c['balls']}, "
                      f"{c['switches']} id switches, median {np.median(r['ms']):.2f} ms, p99 "
                      f"{np.percentile(r['ms'], 99):.2f} ms, dropped {r['dropped']}", flush=True)
        rows_by_dataset[name], by_dataset[name] = rows, tracks.groups(rows)
        if meta.get("sensor_model") == "stereo":
            stereo.add(name)
    checks = tracks.targets(by_dataset, stereo)
    md = ["# Tracking benchmark (`make track-bench`)", "",
          f"`detect --track` (track) and the detector frame by frame (detect) on moving-ball recordings; each frame "
          f"under a budget of {_budget_words(args.budget_ms)}. Scored on balls at least "
          f"{int(100 * tracks.T.SEEN_FRACTION)} % seen; found: centre within {100 * tracks.T.FOUND_M:.0f} cm. "
          f"Latency: deprojection, detection and tracking, every frame read; dropped: a second playback in real "
          f"time. Seed {args.seed}; spherebench {__version__}, numpy {np.__version__}, "
          f"{platform.python_implementation()} {platform.python_version()} on {platform.machine()}.", ""]
    for name, g in by_dataset.items():
        md += [f"## {name}", ""] + tracks.table(g) + [""]
    md += ["## Targets", "", "| target | measured | met |", "|---|---|---|"]
    md += [f"| {t} | {m} | {'yes' if ok else 'no'} |" for t, m, ok in checks]
    for t, m, ok in checks:
        print(f"{'met' if ok else 'NOT MET'}: {t}: {m}")
    series = {f"{name} {r} / {m}": (np.concatenate([np.asarray(x["ms"]) for x in rows if x["resolution"] == r and x["method"] == m]),
                                     1000.0 / next(x["fps"] for x in rows if x["resolution"] == r))
              for name, rows in rows_by_dataset.items() for r in sorted({x["resolution"] for x in rows})
              for m in tracks.METHODS}
    if args.figure:  # marked as ours: the next run may replace it
        outputs.atomic_write_bytes(args.figure, outputs.mark_png(figures.track_latency(series)))
    if args.out:
        data = {"seed": args.seed, "version": __version__,
                "groups": {name: [{"family": f, "resolution": r, "method": m, **a} for (f, r, m), a in g.items()]
                           for name, g in by_dataset.items()},
                "targets": [{"target": t, "measured": m, "met": ok} for t, m, ok in checks],
                "sequences": [{k: v for k, v in r.items() if k != "ms"} for rows in rows_by_dataset.values() for r in rows]}
        paths = outputs.write_report(args.out, "\n".join(md) + "\n", data, "track-bench")
        print("wrote {} and {}".format(*paths), file=sys.stderr)
    return 0


if __name__ == "__main__":
    from spherebench.scripts.cli import run_module

    sys.exit(run_module("track_bench", sys.modules[__name__]))
