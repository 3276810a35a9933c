"""The detector's centre and radius errors on moving-ball recordings, against what the tracker assumes
of them (docs/experiments/2026-12-06-tracking.md).

For every detection on a target ball (within R of its true centre) of every --every-th frame of a
motion dataset's sequences (whole frames searched, no budget), it compares the centre's error per
axis with the standard error of the mean of its inliers' depth noise (sigma_m / sqrt(n_inliers),
the variance inflated by the frame's measured noise correlation, ``noise.mean_variance_inflation``)
and prints their ratio (the tracker's ``stream.CENTRE_ERROR_FACTOR``), then the spread of each
sequence's mean free radius about the true one (the tracker's ``tracking.RADIUS_BIAS_M``).

    python docs/experiments/scripts/track_errors.py data/motion-train data/motion-stereo-train --every 3
"""

from __future__ import annotations

import argparse

import numpy as np

from spherebench.datasets import depth_frames, sequences
from spherebench.method import config_for, stream, warm_up
from spherebench.method.noise import mean_variance_inflation


def detections(dataset: str, every: int) -> dict[str, np.ndarray]:
    """Per detection on a target: error (3,) m, predicted standard error m, free radius m, sequence."""
    config = config_for("improved")
    warm_up(config)
    err, se, radius, seq = [], [], [], []
    for k, folder in enumerate(sequences.sequence_folders(dataset)):
        truth = sequences.read_truth(folder)
        for r in stream.detect_stream(depth_frames.recording_frames(folder / "recording.bag"), config, 0):
            if r.frame.index % every:
                continue
            balls = truth["frames"][r.frame.number]["balls"]
            for s in r.spheres:
                if not balls:
                    break
                d = [np.linalg.norm(s.centre_m - np.asarray(b["center_m"])) for b in balls]
                b = balls[int(np.argmin(d))]
                if min(d) >= b["radius_m"] or "sigma_m" not in s.evidence:
                    continue
                e = s.evidence
                err.append(s.centre_m - np.asarray(b["center_m"]))
                se.append(e["sigma_m"] * np.sqrt(mean_variance_inflation(e.get("noise_corr_px", 0.0)) / e["n_inliers"]))
                radius.append(s.free_radius_m - b["radius_m"])
                seq.append(k)
        print(f"{dataset} {folder.name}: {len(err)} detections so far", flush=True)
    return {"err": np.array(err).reshape(-1, 3), "se": np.array(se), "radius": np.array(radius), "seq": np.array(seq)}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("datasets", nargs="+")
    p.add_argument("--every", type=int, default=3, help="every k-th frame")
    args = p.parse_args()
    for dataset in args.datasets:
        d = detections(dataset, args.every)
        ratio = np.sqrt(np.mean(np.mean(d["err"] ** 2, axis=1) / d["se"] ** 2))
        means = [np.nanmean(d["radius"][d["seq"] == q]) for q in np.unique(d["seq"])]
        print(f"{dataset}: {len(d['se'])} detections; centre error per axis / predicted standard error: rms "
              f"{ratio:.2f}; sequences' mean free radius - R: rms {1e3 * np.sqrt(np.mean(np.square(means))):.1f} mm "
              f"over {len(means)} sequences")


if __name__ == "__main__":
    main()
