"""Streaming latency of `spherebench detect`: per-frame time and frames dropped on RealSense
recordings of simulated scenes (``make stream-bench``).

For each depth mode (424x240, 848x480 by default) it renders --scenes simulated scenes of the
`default` preset (clean and cluttered, seed 0), writes them as one ROS1 recording of --frames
frames at --fps (the scenes in turn; ``datasets.bagwrite``) in a temporary folder, and plays it
back twice through ``method.stream``, as `detect` does: offline (every frame read) and in real
time (frames arriving while the detector is busy are dropped). Per-frame time: the deprojection
and the detection (``stream.detect_stream``'s ms), not the reading. Prints a table; writes
OUT.md and OUT.json. Thin driver: the work is in ``spherebench.method.stream``.

    python -m spherebench.scripts.stream_bench --out results/stream_bench
"""

from __future__ import annotations

import argparse
import platform
import sys
import tempfile
from pathlib import Path

import numpy as np

from spherebench import options
from spherebench.datasets import depth_frames, outputs, rendering
from spherebench.datasets.bagwrite import write_realsense_bag
from spherebench.method import config_for, stream, warm_up


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", type=options.out_path, default=None, metavar="OUT",
                   help="write OUT.md and OUT.json (default: print only)")
    p.add_argument("--sizes", nargs="+", default=["424x240", "848x480"], metavar="WxH", help="depth modes")
    p.add_argument("--frames", type=options.count, default=180, help="frames per recording (default 180)")
    p.add_argument("--scenes", type=options.count, default=12, help="distinct simulated scenes (default 12)")
    p.add_argument("--fps", type=options.count, default=90, help="the recordings' frame rate (default 90)")
    p.add_argument("--seed", type=options.seed, default=0, help="scenes' and detector's seed")


def _recording(folder: Path, size: str, n_frames: int, n_scenes: int, fps: int, seed: int) -> Path:

    families = ("clean", "cluttered")
    scenes = [rendering.simulate_scene("default", k, families[k % 2], seed, size) for k in range(n_scenes)]
    frames = [scenes[k % n_scenes].depth for k in range(n_frames)]
    return write_realsense_bag(folder / f"sim_{size}.bag", frames, scenes[0].intrinsics, fps=fps)


def measure(path: Path, real_time: bool, seed: int = 0) -> dict:
    """One playback of a recording through the streaming detector: per-frame ms, drops."""

    config = config_for("improved")
    warm_up(config)
    stats = depth_frames.StreamStats()
    ms = [r.ms for r in stream.detect_stream(depth_frames.recording_frames(path, real_time=real_time, stats=stats),
                                             config, seed, stats)]
    return {**stream.latency_summary(np.asarray(ms)), "dropped": stats.dropped, "missing": stats.missing}


def run(args: argparse.Namespace) -> int:

    if args.out:
        outputs.check_report_out(args.out, "stream-bench")
    rows = []
    with tempfile.TemporaryDirectory(prefix="spherebench-stream-") as tmp:
        for size in args.sizes:
            path = _recording(Path(tmp), size, args.frames, args.scenes, args.fps, args.seed)
            for real_time in (False, True):
                r = {"size": size, "playback": "real time" if real_time else "offline", "fps": args.fps,
                     "recorded": args.frames, **measure(path, real_time, args.seed)}
                rows.append(r)
                print(f"{size} {r['playback']:>9}: {r['frames']} of {r['recorded']} frames detected, "
                      f"median {r['median_ms']:.1f} ms, p95 {r['p95_ms']:.1f} ms per frame, "
                      f"{r['dropped']} dropped", flush=True)
    md = ["# Streaming latency (`make stream-bench`)", "",
          f"`detect` on recordings of {args.scenes} simulated `default` scenes (seed {args.seed}), {args.frames} "
          f"frames at {args.fps} fps, improved detector; time per frame = deprojection + detection. "
          f"Machine: {platform.machine()}, {platform.python_implementation()} {platform.python_version()}.", "",
          "| depth mode | playback | frames detected | median ms | p95 ms | dropped |", "|---|---|---|---|---|---|"]
    md += [f"| {r['size']} | {r['playback']} | {r['frames']} / {r['recorded']} | {r['median_ms']:.1f} | "
           f"{r['p95_ms']:.1f} | {r['dropped']} |" for r in rows]
    if args.out:
        paths = outputs.write_report(args.out, "\n".join(md) + "\n", {"seed": args.seed, "rows": rows}, "stream-bench")
        print("wrote {} and {}".format(*paths), file=sys.stderr)
    return 0


if __name__ == "__main__":
    from spherebench.scripts.cli import run_module

    sys.exit(run_module("stream_bench", sys.modules[__name__]))
