"""The 3D detector against PCL's sphere segmentation on the same clouds, in one run (``make pcl-bench``).

For each scene, in order: PCL's segmentation (``baselines.pcl_peer``: its own process, its own
clock around the segmentation) and the detector (one thread, wall time around ``detect``, the
cloud's reading untimed), one after the other, so that the shared machine's drift falls on both.
The detector's kernels are warmed before the first scene; each cloud is detected three times, the
first run timed right after PCL's and the fastest kept beside it. A ball counts as found by either where an answer's centre lies within ``FOUND_M`` of
its true centre; an answer within it of no ball is false.
"""

from __future__ import annotations

import math
import time

import numpy as np

from spherebench.baselines.pcl_peer import PclPeer
from spherebench.datasets import inout
from spherebench.eval.bench.seeds import detection_seed
from spherebench.eval.bench.tasks import SceneInfo
from spherebench.method import DetectorConfig, detect, warm_up
from spherebench.parallel import single_thread_here

FOUND_M = 0.02  # an answer finds a ball within this of its centre (the benchmark's 3D rule)


def found_and_false(centres_m: list, truth_m: list) -> tuple[int, int]:
    """(balls with an answer within FOUND_M, answers within FOUND_M of no ball); centres_m and
    truth_m: lists of (3,) m."""
    near = np.array([[math.dist(c, t) <= FOUND_M for t in truth_m] for c in centres_m], bool).reshape(
        len(centres_m), len(truth_m))
    return int(near.any(axis=0).sum()), int((~near.any(axis=1)).sum())


def compare(scenes: list[SceneInfo], peers: list[PclPeer], config: DetectorConfig, seed: int, passes: int = 3,
            progress=None) -> list[dict]:
    """Per scene: each side's time (ms), balls found and false answers; "pcl": one entry per peer. The
    detector runs ``passes`` times on each cloud: "ms" is its first run, right after PCL's (which
    leaves the caches holding PCL's data), and "best_ms" its fastest (its cost as a stream's frame
    with its buffers warm, as ``make bench``'s best of 3)."""
    rows = []
    with single_thread_here():
        warm_up(config)
        for k, scene in enumerate(scenes):
            cloud = inout.load_cloud(scene.path)
            truth = [np.asarray(c, float) for c in scene.gt_centres_m]
            answers = []
            for peer in peers:
                pcl = peer.segment(cloud.points)
                found, false = found_and_false([pcl.centre_m] if pcl.found else [], truth)
                answers.append({"ms": pcl.ms, "found": found, "false": false})
            times = []
            for _ in range(max(1, passes)):
                t0 = time.perf_counter()
                spheres = detect(cloud, config, seed=detection_seed(seed, scene.index))
                times.append(1e3 * (time.perf_counter() - t0))
            found, false = found_and_false([s.centre_m for s in spheres], truth)
            rows.append({"scene": scene.scene_id, "balls": len(truth), "points": int(len(cloud.points)),
                         "pcl": answers, "detector": {"ms": times[0], "best_ms": min(times), "found": found,
                                                      "false": false}})
            if progress is not None:
                progress(k, rows[-1])
    return rows


def _side(rows: list[dict], pick) -> dict:
    ms = np.array([pick(r)["ms"] for r in rows])
    return {"median_ms": float(np.median(ms)), "p95_ms": float(np.percentile(ms, 95)),
            "found": sum(pick(r)["found"] for r in rows), "false": sum(pick(r)["false"] for r in rows)}


def summary(rows: list[dict]) -> dict:
    """The detector's and each peer's median and 95th-percentile times and totals found and false; per
    peer, the ratio of its median time to the detector's (first runs: "ratio_of_medians"; best runs:
    "ratio_of_medians_best") and the median of the scenes' ratios ("median_ratio", first runs)."""
    ours = np.array([r["detector"]["ms"] for r in rows])
    best = np.array([r["detector"].get("best_ms", r["detector"]["ms"]) for r in rows])
    peers = []
    for j in range(len(rows[0]["pcl"]) if rows else 0):
        side = _side(rows, lambda r: r["pcl"][j])
        theirs = np.array([r["pcl"][j]["ms"] for r in rows])
        side.update(ratio_of_medians=float(np.median(theirs) / np.median(ours)),
                    median_ratio=float(np.median(theirs / ours)),
                    ratio_of_medians_best=float(np.median(theirs) / np.median(best)))
        peers.append(side)
    detector = _side(rows, lambda r: r["detector"])
    detector.update(best_median_ms=float(np.median(best)), best_p95_ms=float(np.percentile(best, 95)))
    return {"scenes": len(rows), "balls": sum(r["balls"] for r in rows), "detector": detector, "pcl": peers}
