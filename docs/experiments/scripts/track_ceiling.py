"""The detector's ceiling on moving-ball recordings (docs/experiments/2026-12-06-tracking.md): per
depth mode, the share of the ball-frames within 2.5 m (a quarter or more of the ball seen) whose
verification started from the true centre accepts the ball within 2 cm (``eval.bench.oracle.ceiling``):
what a tracker whose every prediction were the truth would find from its verifications.

    python docs/experiments/scripts/track_ceiling.py data/motion-stereo-train --every 2
"""

from __future__ import annotations

import argparse

import numpy as np

from spherebench.datasets import depth_frames, sequences
from spherebench.eval.bench.oracle import ceiling
from spherebench.eval.metrics.tracking import NEAR_M, SEEN_FRACTION
from spherebench.method import config_for, stream, warm_up


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("dataset")
    p.add_argument("--every", type=int, default=2, help="every k-th frame")
    args = p.parse_args()
    config = config_for("improved")
    warm_up(config)
    counts: dict[str, list[int]] = {}
    for folder in sequences.sequence_folders(args.dataset):
        truth = sequences.read_truth(folder)
        mode = f"{truth['intrinsics']['width']}x{truth['intrinsics']['height']}"
        rays = None
        for frame in depth_frames.recording_frames(folder / "recording.bag"):
            if frame.index % args.every:
                continue
            balls = [b for b in truth["frames"][frame.number]["balls"]
                     if b["visible_fraction"] >= SEEN_FRACTION and np.linalg.norm(b["center_m"]) <= NEAR_M]
            if not balls:
                continue
            rays = stream.image_rays(frame.intrinsics) if rays is None else rays
            cloud = stream.depth_cloud(frame.depth, frame.intrinsics, rays)
            within = [r["within"] for r in ceiling(cloud, [b["center_m"] for b in balls], config, separable=False)]
            c = counts.setdefault(mode, [0, 0])
            c[0] += sum(within)
            c[1] += len(within)
        print(f"{folder.name} {mode}: {counts[mode][0]} of {counts[mode][1]} so far", flush=True)
    for mode, (hit, n) in sorted(counts.items()):
        print(f"{args.dataset} {mode}: the ceiling within 2.5 m {hit} of {n} ball-frames ({100 * hit / max(n, 1):.1f} %)")


if __name__ == "__main__":
    main()
