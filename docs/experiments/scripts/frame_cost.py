"""Where a frame's time goes, and what the second core gives: per frame, the detector at one thread
(CPU time, ``time.thread_time``) with the share spent inside the verification kernel
(``verification_kernels.verify_organised`` and ``verify_many``), and the detector at ``--threads``
numba threads (wall time), the two taken in turns on each frame, best of ``--passes`` each. Reported
per resolution: medians and 95th percentiles of both; the kernel's share of all frames' time and of the
slowest tenth's; the bound on a frame's time were all its verification kernels shared perfectly
between two cores (one thread's time less half its kernel time), which no scheduling of the same
verifications can beat; the slowest frame's time over the median at each thread count; and whether
both thread counts gave the same detections (they must).
Scene k runs with ``detection_seed(--seed, k)``; the first frame warms the kernels.

    python docs/experiments/scripts/frame_cost.py data/hard --resolution 424x240 --passes 3
"""

from __future__ import annotations

import math
import sys
import time

import numpy as np

import script_support as support
from spherebench import options
from spherebench.datasets import inout
from spherebench.eval.bench.seeds import detection_seed
from spherebench.method import detect, warm_up
from spherebench.method import verification_kernels as VK


class KernelClock:
    """Adds the calling thread's CPU time inside the verification kernels to ``seconds`` while installed
    (``with``): the kernels are wrapped where ``verification`` looks them up."""

    NAMES = ("verify_organised", "verify_many")

    def __init__(self):
        self.seconds = 0.0
        self._saved = {}

    def _wrap(self, fn):
        def timed(*args):
            t0 = time.thread_time()
            try:
                return fn(*args)
            finally:
                self.seconds += time.thread_time() - t0
        return timed

    def __enter__(self) -> KernelClock:
        for name in self.NAMES:
            self._saved[name] = getattr(VK, name)
            setattr(VK, name, self._wrap(self._saved[name]))
        return self

    def __exit__(self, *exc) -> None:
        for name, fn in self._saved.items():
            setattr(VK, name, fn)


def same_detections(a, b) -> bool:
    return len(a) == len(b) and all(np.array_equal(x.centre_m, y.centre_m) and x.score == y.score
                                    for x, y in zip(a, b))


def time_frames(scenes, config, passes: int, threads: int, seed: int) -> list[dict]:
    """Per frame: one thread's best CPU ms and its kernel ms in that run, ``threads``' best wall ms, and
    whether the two gave the same detections."""
    import cv2
    import numba

    saved = numba.get_num_threads(), cv2.getNumThreads()
    cv2.setNumThreads(1)
    rows = []
    try:
        warm_up(config)
        for scene in scenes:
            cloud = inout.load_cloud(scene.path)
            s = detection_seed(seed, scene.index)
            one = many = None
            best_one, best_many = (math.inf, 0.0), math.inf
            for p in range(passes):
                for n in ((1, threads) if p % 2 == 0 else (threads, 1)):
                    numba.set_num_threads(n)
                    if n == 1:
                        with KernelClock() as clock:
                            t0 = time.thread_time()
                            one = detect(cloud, config, seed=s)
                            ms = 1e3 * (time.thread_time() - t0)
                        best_one = min(best_one, (ms, 1e3 * clock.seconds))
                    else:
                        t0 = time.perf_counter()
                        many = detect(cloud, config, seed=s)
                        best_many = min(best_many, 1e3 * (time.perf_counter() - t0))
            rows.append({"scene": scene.path.name, "family": scene.family, "resolution": scene.resolution,
                         "one_thread_ms": best_one[0], "kernel_ms": best_one[1], "threads_ms": best_many,
                         "same_detections": same_detections(one, many)})
    finally:
        numba.set_num_threads(saved[0])
        cv2.setNumThreads(saved[1])
    return rows


def summarise(rows: list[dict]) -> list[dict]:
    out = []
    for res in sorted({r["resolution"] for r in rows}, key=lambda s: int(s.split("x")[0])):
        sel = [r for r in rows if r["resolution"] == res]
        one = np.array([r["one_thread_ms"] for r in sel])
        kern = np.array([r["kernel_ms"] for r in sel])
        many = np.array([r["threads_ms"] for r in sel])
        slow = one >= np.percentile(one, 90)
        bound = one - kern / 2
        out.append({"resolution": res, "frames": len(sel),
                    "one_median_ms": float(np.median(one)), "one_p95_ms": float(np.percentile(one, 95)),
                    "threads_median_ms": float(np.median(many)), "threads_p95_ms": float(np.percentile(many, 95)),
                    "kernel_share": float(kern.sum() / one.sum()),
                    "kernel_share_slowest_tenth": float(kern[slow].sum() / one[slow].sum()),
                    "bound_median_ms": float(np.median(bound)), "bound_p95_ms": float(np.percentile(bound, 95)),
                    "one_max_over_median": float(one.max() / np.median(one)),
                    "threads_max_over_median": float(many.max() / np.median(many)),
                    "threads_slowest": sel[int(np.argmax(many))]["scene"],
                    "same_detections": sum(r["same_detections"] for r in sel)})
    return out


def markdown(result: dict) -> str:
    t = result["threads"]
    lines = [f"frame_cost on {result['dataset']}: best of {result['passes']} per frame, one thread (CPU) and "
             f"{t} threads (wall) in turns", "",
             f"| resolution | frames | 1 thread median / p95 ms | {t} threads median / p95 ms | verification kernels' "
             f"share (all; slowest tenth) | kernels halved: median / p95 ms | slowest / median (1; {t} threads) "
             "| same detections |",
             "|---|---|---|---|---|---|---|---|"]
    for s in result["summary"]:
        lines.append(f"| {s['resolution']} | {s['frames']} | {s['one_median_ms']:.2f} / {s['one_p95_ms']:.2f} | "
                     f"{s['threads_median_ms']:.2f} / {s['threads_p95_ms']:.2f} | {100 * s['kernel_share']:.0f} %; "
                     f"{100 * s['kernel_share_slowest_tenth']:.0f} % | {s['bound_median_ms']:.2f} / "
                     f"{s['bound_p95_ms']:.2f} | {s['one_max_over_median']:.1f}x; {s['threads_max_over_median']:.1f}x "
                     f"({s['threads_slowest']}) | {s['same_detections']}/{s['frames']} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    p = support.parser(__doc__)
    p.add_argument("--resolution", action="append", default=[], metavar="WxH",
                   help="only frames of this resolution (repeatable), e.g. 424x240")
    p.add_argument("--passes", type=options.count, default=3, help="turns per frame; each keeps its best (default 3)")
    p.add_argument("--threads", type=options.count, default=2, help="numba threads of the second run (default 2)")
    p.add_argument("--seed", type=options.seed, default=0, help="run seed (default 0)")
    support.add_json_argument(p)
    args = p.parse_args(argv)
    import numba

    if args.threads > numba.config.NUMBA_NUM_THREADS:
        p.error(f"--threads {args.threads}: numba has {numba.config.NUMBA_NUM_THREADS} here")
    config = support.detector_config(args.dataset, {})
    scenes = [s for s in support.frame_scenes(args.dataset, args.limit, args.family)
              if s.resolution and (not args.resolution or s.resolution in args.resolution)]
    if not scenes:
        p.error(f"{args.dataset}: no organised frame matches --resolution")
    rows = time_frames(scenes, config, max(1, args.passes), args.threads, args.seed)
    result = {"dataset": str(args.dataset), "passes": args.passes, "threads": args.threads, "frames": rows,
              "summary": summarise(rows)}
    print(markdown(result))
    support.write_json(args.json, result)
    return 0


if __name__ == "__main__":
    sys.exit(main())
