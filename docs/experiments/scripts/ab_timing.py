"""Interleaved A/B timing: two detector configurations (and optionally a control) on the same frames.

On each frame of the dataset the configurations take turns ``--passes`` times in this process, at
one thread, the turns' order reversed from one pass to the next (a run right after another
configuration's finds the caches holding that one's data); each keeps its fastest CPU time
(``time.thread_time``) on the frame. Timing the two side by side on every frame makes the shared
machine's drift fall on both alike, which separate runs do not (``make bench``'s figures move by
tens of per cent from one run to the next). Reported per resolution: the frames, each
configuration's median time, the median of the frames' ratios B/A (and A and B over the control),
the median and largest difference B - A, and on how many frames A and B gave the same detections
(centres and scores equal: a change meant to be bit-identical should read all). Scene k runs with
``detection_seed(--seed, k)``. Reading the frame is not timed; the first frame warms the kernels.

    python docs/experiments/scripts/ab_timing.py data/default --resolution 424x240 \\
        --set-b refinement.refine_iterations=3 --passes 5
    python docs/experiments/scripts/ab_timing.py data/hard --family negative \\
        --set-b retry.retry_hole=false --passes 5
    python docs/experiments/scripts/ab_timing.py data/default --resolution 424x240 \\
        --set-b outline.outline_evidence=false --control paper-lstsq --passes 5
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
from spherebench.parallel import single_thread_here


def same_detections(a, b) -> bool:
    return len(a) == len(b) and all(np.array_equal(x.centre_m, y.centre_m) and x.score == y.score
                                    for x, y in zip(a, b))


def time_frames(scenes, configs: list, passes: int, seed: int) -> list[dict]:
    """Per frame: each configuration's fastest CPU time (ms) over ``passes`` turns, and whether the first
    two gave the same detections."""
    rows = []
    with single_thread_here():
        for config in configs:
            warm_up(config)
        for scene in scenes:
            cloud = inout.load_cloud(scene.path)
            s = detection_seed(seed, scene.index)
            outputs = [detect(cloud, config, seed=s) for config in configs]  # untimed: this frame's buffers warm
            best = [math.inf] * len(configs)
            order = list(enumerate(configs))
            for p in range(passes):
                for j, config in (order if p % 2 == 0 else order[::-1]):
                    t0 = time.thread_time()
                    detect(cloud, config, seed=s)
                    best[j] = min(best[j], 1e3 * (time.thread_time() - t0))
            rows.append({"scene": scene.path.name, "family": scene.family, "resolution": scene.resolution,
                         "ms": best, "same_detections": same_detections(outputs[0], outputs[1])})
    return rows


def summarise(rows: list[dict], control: bool) -> list[dict]:
    """Per resolution: medians, the median of the frames' ratios and the differences B - A."""
    out = []
    for res in sorted({r["resolution"] for r in rows}, key=lambda s: int(s.split("x")[0])):
        t = np.array([r["ms"] for r in rows if r["resolution"] == res])
        a, b = t[:, 0], t[:, 1]
        s = {"resolution": res, "frames": len(t), "a_ms": float(np.median(a)), "b_ms": float(np.median(b)),
             "ratio_b_a": float(np.median(b / a)), "diff_median_ms": float(np.median(b - a)),
             "diff_max_ms": float(np.max(b - a)),
             "same_detections": sum(r["same_detections"] for r in rows if r["resolution"] == res)}
        if control:
            c = t[:, 2]
            s.update(control_ms=float(np.median(c)), ratio_a_control=float(np.median(a / c)),
                     ratio_b_control=float(np.median(b / c)))
        out.append(s)
    return out


def markdown(result: dict) -> str:
    names = result["configs"]
    lines = [f"ab_timing on {result['dataset']}: best of {result['passes']} per frame, order alternated; "
             f"A = {names[0]}, B = {names[1]}" + (f", control = {names[2]}" if len(names) > 2 else ""), "",
             "| resolution | frames | A ms | B ms | B/A (median of ratios) | B - A median ms | B - A max ms | "
             "same detections |" + (" control ms | A/control | B/control |" if len(names) > 2 else ""),
             "|---|---|---|---|---|---|---|---|" + ("---|---|---|" if len(names) > 2 else "")]
    for s in result["summary"]:
        line = (f"| {s['resolution']} | {s['frames']} | {s['a_ms']:.3f} | {s['b_ms']:.3f} | {s['ratio_b_a']:.3f} | "
                f"{s['diff_median_ms']:+.3f} | {s['diff_max_ms']:+.3f} | {s['same_detections']}/{s['frames']} |")
        if len(names) > 2:
            line += f" {s['control_ms']:.3f} | {s['ratio_a_control']:.3f} | {s['ratio_b_control']:.3f} |"
        lines.append(line)
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    p = support.parser(__doc__)
    support.add_ab_arguments(p)
    p.add_argument("--control", default=None, metavar="METHOD",
                   help="a third configuration timed in the same turns, e.g. paper-lstsq")
    p.add_argument("--resolution", action="append", default=[], metavar="WxH",
                   help="only frames of this resolution (repeatable), e.g. 424x240")
    p.add_argument("--passes", type=options.count, default=5, help="turns per frame; each keeps its best (default 5)")
    p.add_argument("--seed", type=options.seed, default=0, help="run seed (default 0)")
    support.add_json_argument(p)
    args = p.parse_args(argv)
    a = support.detector_config(args.dataset, support.settings(args.a, "ab_timing"), args.method)
    b = support.detector_config(args.dataset, support.settings(args.b, "ab_timing"), args.method_b or args.method)
    configs, names = [a, b], [f"{args.method} {args.a or ''}".strip(),
                              f"{args.method_b or args.method} {args.b or ''}".strip()]
    if args.control:
        configs.append(support.detector_config(args.dataset, {}, args.control))
        names.append(args.control)
    scenes = [s for s in support.frame_scenes(args.dataset, args.limit, args.family)
              if s.resolution and (not args.resolution or s.resolution in args.resolution)]
    if not scenes:
        p.error(f"{args.dataset}: no organised frame matches --resolution/--family")
    rows = time_frames(scenes, configs, max(1, args.passes), args.seed)
    result = {"dataset": str(args.dataset), "configs": names, "passes": args.passes, "frames": rows,
              "summary": summarise(rows, args.control is not None)}
    print(markdown(result))
    support.write_json(args.json, result)
    return 0


if __name__ == "__main__":
    sys.exit(main())
