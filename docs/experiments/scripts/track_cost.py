"""Where a tracked stream's slow frames come from, and the bound on its 99th percentile
(docs/experiments/2026-12-06-target-ceilings.md): per frame of a motion preset's sequences (one depth
mode), ``stream.track_stream`` with no budget at one thread: the frame's CPU ms (thread time), whether
it was searched whole or in windows, whether a confirmed track was there before it, whether a ball was
in view (a quarter seen) and whether anything was reported. Printed per class of frame, with the
stream's percentiles and the same with every frame's time halved (both cores shared perfectly by the
same computation: no scheduling of it does better).

    python docs/experiments/scripts/track_cost.py data/motion --resolution 424x240
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from spherebench.datasets import depth_frames, sequences
from spherebench.eval.metrics.tracking import SEEN_FRACTION
from spherebench.method import config_for, stream, warm_up


def frame_costs(dataset: str, resolution: str, config) -> list[dict]:
    """One row per frame of the dataset's sequences of ``resolution`` (WxH)."""
    rows = []
    for folder in sequences.sequence_folders(dataset):
        doc = sequences.read_truth(folder)
        if f"{doc['intrinsics']['width']}x{doc['intrinsics']['height']}" != resolution:
            continue
        frames = stream.track_stream(depth_frames.recording_frames(folder / "recording.bag"), config, 0)
        had_track = False
        while True:
            t0 = time.thread_time()
            r = next(frames, None)
            ms = 1e3 * (time.thread_time() - t0)
            if r is None:
                break
            seen = any(b["visible_fraction"] >= SEEN_FRACTION for b in doc["frames"][r.frame.number]["balls"])
            rows.append({"sequence": folder.name, "frame": r.frame.number, "ms": ms, "search": r.search,
                         "had_track": had_track, "ball_seen": seen, "reported": bool(r.spheres)})
            had_track = any(t.confirmed for t in r.tracks)
    return rows


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("dataset")
    p.add_argument("--resolution", default="424x240", metavar="WxH")
    args = p.parse_args(argv)
    import cv2
    import numba

    numba.set_num_threads(1)
    cv2.setNumThreads(1)
    config = config_for("improved")
    warm_up(config)
    rows = frame_costs(args.dataset, args.resolution, config)
    ms = np.array([r["ms"] for r in rows])
    print(f"{args.dataset} {args.resolution}, no budget, one thread: {len(ms)} frames, CPU ms median "
          f"{np.median(ms):.2f}, p95 {np.percentile(ms, 95):.2f}, p99 {np.percentile(ms, 99):.2f}; every frame "
          f"halved: p99 {np.percentile(ms / 2, 99):.2f}")
    print("| search | track before | ball in view | reported | frames | median ms | p95 ms | over 10 ms |")
    print("|---|---|---|---|---|---|---|---|")
    classes: dict[tuple, list[float]] = {}
    for r in rows:
        classes.setdefault((r["search"], r["had_track"], r["ball_seen"], r["reported"]), []).append(r["ms"])
    for (search, had, seen, said), v in sorted(classes.items(), key=lambda kv: -len(kv[1])):
        v = np.array(v)
        print(f"| {search} | {'yes' if had else 'no'} | {'yes' if seen else 'no'} | {'yes' if said else 'no'} | "
              f"{len(v)} | {np.median(v):.2f} | {np.percentile(v, 95):.2f} | {(v > 10).sum()} |")

    return 0


if __name__ == "__main__":
    raise SystemExit(main())
