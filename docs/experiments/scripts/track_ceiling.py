"""The detector's and the tracker's ceilings on moving-ball recordings (docs/experiments/2026-12-06-tracking.md,
2026-12-06-target-ceilings.md). Per depth mode, on the ball-frames within 2.5 m (a quarter or more of the
ball seen):

- the detector's ceiling: the share whose verification started from the true centre accepts the ball
  within 2 cm (``eval.bench.oracle``): what a tracker whose every prediction were the truth would find
  from its verifications;
- with ``--tracked``, the tracker's ceiling: ``tracking.Tracker`` fed, in every frame, the verification
  from each ball's true centre where the detector would accept it (whatever its error), and scored as
  ``make track-bench`` scores the tracks it reports (``eval.metrics.tracking``): the share of those
  ball-frames whose reported track lies within 2 cm. No search can give a tracker better detections than
  its verification started from the truth.

    python docs/experiments/scripts/track_ceiling.py data/motion-stereo-train --every 2
    python docs/experiments/scripts/track_ceiling.py data/motion-stereo --tracked --resolution 424x240
"""

from __future__ import annotations

import argparse
from types import SimpleNamespace

import numpy as np

from spherebench.datasets import depth_frames, sequences
from spherebench.eval.bench.oracle import CEILING_M, truth_best
from spherebench.eval.bench.tracks import truth_frames
from spherebench.eval.metrics import tracking as T
from spherebench.method import compiled, config_for, stream, warm_up
from spherebench.method.detector import prepare_frame
from spherebench.method.tracking import Tracker


def sequence_ceiling(folder, config, every: int, tracked: bool) -> dict:
    """One sequence's counts: ``hit``/``n`` (the detector's ceiling on the ball-frames within 2.5 m, every
    ``every``-th frame) and, with ``tracked``, the tracker's counts (``tracking.sequence_counts``)."""
    doc = sequences.read_truth(folder)
    truth = truth_frames(doc)
    tracker = Tracker(radius_m=config.radius_m)
    answers = [T.Answers(np.zeros(0, np.int64), np.zeros((0, 3))) for _ in truth]
    hit = n = 0
    rays = None
    for frame in depth_frames.recording_frames(folder / "recording.bag"):
        balls = doc["frames"][frame.number]["balls"]
        scored = [b["visible_fraction"] >= T.SEEN_FRACTION and np.linalg.norm(b["center_m"]) <= T.NEAR_M
                  for b in balls]
        if not tracked and (frame.index % every or not any(scored)):
            continue
        rays = stream.image_rays(frame.intrinsics) if rays is None else rays
        prepared = prepare_frame(stream.depth_cloud(frame.depth, frame.intrinsics, rays), config)
        buf = compiled.workspace("inliers", (prepared.index_image.size + 1,), np.int64)
        detections = []
        for b, counted in zip(balls, scored):
            v, err = truth_best(prepared, b["center_m"], config, buf)
            accepted = v is not None and v.size_ok and v.score >= config.verification.accept_score
            if counted and frame.index % every == 0:
                hit += accepted and err <= CEILING_M
                n += 1
            if accepted:
                # the sphere as the stream hands it to the tracker (its centre, score, free radius, error)
                detections.append(stream.detection_of(SimpleNamespace(
                    centre_m=v.centre_m, score=v.score, free_radius_m=v.free_radius_m, evidence=v.stats)))
        if tracked:
            said = [t for t in tracker.update(float(frame.timestamp_ms) / 1e3, detections) if t.reported]
            answers[frame.number] = T.Answers(np.array([t.track_id for t in said], np.int64),
                                              np.array([t.centre_m for t in said], np.float64).reshape(-1, 3),
                                              np.array([t.confirmed for t in said], bool))
    counts = T.sequence_counts(truth, answers, config.radius_m) if tracked else None
    return {"mode": f"{doc['intrinsics']['width']}x{doc['intrinsics']['height']}", "hit": hit, "n": n,
            "counts": counts}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("dataset")
    p.add_argument("--every", type=int, default=2, help="the detector's ceiling on every k-th frame")
    p.add_argument("--tracked", action="store_true", help="also the tracker fed from the truth (every frame)")
    p.add_argument("--resolution", action="append", default=[], metavar="WxH", help="only this depth mode")
    args = p.parse_args(argv)
    config = config_for("improved")
    warm_up(config)
    by_mode: dict[str, list[dict]] = {}
    for folder in sequences.sequence_folders(args.dataset):
        doc = sequences.read_truth(folder)
        if args.resolution and f"{doc['intrinsics']['width']}x{doc['intrinsics']['height']}" not in args.resolution:
            continue
        r = sequence_ceiling(folder, config, args.every, args.tracked)
        by_mode.setdefault(r["mode"], []).append(r)
        line = f"{folder.name} {r['mode']}: the detector's ceiling {r['hit']} of {r['n']}"
        if r["counts"]:
            c = r["counts"]
            line += f"; tracked from the truth {c['found_near']} of {c['near']} within 2.5 m, {c['found']} of {c['balls']} in all"
        print(line, flush=True)
    for mode, rows in sorted(by_mode.items()):
        hit, n = sum(r["hit"] for r in rows), sum(r["n"] for r in rows)
        print(f"{args.dataset} {mode}: the detector's ceiling within 2.5 m {hit} of {n} ball-frames "
              f"({100 * hit / max(n, 1):.1f} %)")
        if args.tracked:
            c = T.add_counts([r["counts"] for r in rows])
            s = T.summary(c)
            print(f"{args.dataset} {mode}: the tracker fed from the truth: within 2 cm on {c['found_near']} of "
                  f"{c['near']} ball-frames within 2.5 m ({100 * s['found_near_share']:.1f} %), {c['found']} of "
                  f"{c['balls']} in all ({100 * s['found_share']:.1f} %)")

    return 0


if __name__ == "__main__":
    raise SystemExit(main())
