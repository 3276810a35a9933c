"""Where the size check can tell a 0.11 m ball from the 0.12 m basketball, and whether its
free-radius standard error says so: per sensor model and depth band, the free radius of the
verification from the true centre (basketball configuration, R 0.12, every start of
``eval.bench.oracle.truth_verifications``, the best as the oracle keeps it: ``truth_best``) of the balls of a
dataset and of its ``--radius 0.11`` twin.

``collect`` writes one line per ball: its depth, true radius, visible share, the verification's
free radius, the standard error the detector gives it (``free_radius_se_m``), its centre error, and
whether the detector (run seed 0) reports a sphere within 2 cm of it (for a 0.11 m twin: the size
test failed). ``report`` takes the balls verified within 2 cm and at least 90 % visible and prints
per band: the median and sd of the free radius for each true radius, the median standard error, sd
over it (1: the error is right; above: it understates the scatter), d' = (median 0.12 - median
0.11) / the pooled sd, and the share of the 0.11 m balls the detector accepts.

    spherebench generate --preset train --n 600 --seed 0 --radius 0.11 --out data/train-r011
    spherebench generate --preset train-stereo --n 600 --seed 0 --radius 0.11 --out data/train-stereo-r011
    python docs/experiments/scripts/size_resolution.py collect data/train out/sz_train.jsonl --limit 600
    python docs/experiments/scripts/size_resolution.py collect data/train-r011 out/sz_train11.jsonl
    (and likewise train-stereo, train-stereo-r011)
    python docs/experiments/scripts/size_resolution.py report analytic=out/sz_train.jsonl:out/sz_train11.jsonl \\
        stereo=out/sz_ts.jsonl:out/sz_ts11.jsonl
"""

from __future__ import annotations

import argparse
import functools
import json
import sys
from pathlib import Path

import numpy as np

import script_support as support
from spherebench import options
from spherebench.datasets import inout
from spherebench.datasets.outputs import atomic_write_bytes
from spherebench.eval.bench.calibration import scene_truths
from spherebench.eval.bench.oracle import truth_best
from spherebench.eval.bench.seeds import detection_seed
from spherebench.method import compiled, config_for
from spherebench.method.detector import detect, prepare_frame
from spherebench.parallel import executor

#: Depth bands (m) of the report.
BANDS_M = ((0.0, 1.0), (1.0, 1.5), (1.5, 2.0), (2.0, 2.5), (2.5, 3.5), (3.5, 9.0))
#: A verification this close to the true centre counts, a ball this visible is whole.
WITHIN_M, MIN_VISIBLE = 0.02, 0.9
BASKETBALL_M = 0.12


def scene_balls(job: tuple) -> list[dict]:
    """One scene's lines (in a worker): job (scene dir, index, gt)."""
    scene_dir, index, gt = job
    config = config_for("improved", radius_m=BASKETBALL_M)  # a basketball detector, whatever the ball
    cloud = inout.load_cloud(Path(scene_dir))
    frame = prepare_frame(cloud, config)
    buf = compiled.workspace("inliers", (frame.index_image.size + 1,), np.int64)
    reported = [s.centre_m for s in detect(cloud, config, seed=detection_seed(0, index))]
    out = []
    for b in gt["balls"]:
        c = np.asarray(b["center_m"], np.float64)
        kept, err = truth_best(frame, c, config, buf)
        line = {"scene": Path(scene_dir).name, "z_m": float(c[2]), "true_radius_m": float(b.get("radius_m") or BASKETBALL_M),
                "visible": float(b.get("visible_fraction", 1.0)),
                "accepted": any(np.linalg.norm(np.asarray(r) - c) <= WITHIN_M for r in reported)}
        if kept is not None:
            line.update(free_radius_m=float(kept.free_radius_m), free_radius_se_m=float(kept.free_radius_se_m),
                        error_m=err, size_ok=bool(kept.size_ok))
        out.append(line)
    return out


def collect(args) -> int:
    truths = scene_truths(args.dataset)
    jobs = [(str(s.path), s.index, truths[s.scene_id]) for s in support.frame_scenes(args.dataset, args.limit)
            if s.scene_id in truths]
    with executor(args.workers) as ex:
        lines = [x for part in ex.map(functools.partial(scene_balls), jobs) for x in part]
    atomic_write_bytes(Path(args.out), "".join(json.dumps(x) + "\n" for x in lines).encode())
    print(f"{len(lines)} balls -> {args.out}")
    return 0


def _verified(path: str) -> list[dict]:
    lines = [json.loads(t) for t in Path(path).read_text().splitlines() if t]
    return [x for x in lines if "free_radius_m" in x and np.isfinite(x["free_radius_m"])
            and x["error_m"] <= WITHIN_M and x["visible"] >= MIN_VISIBLE]


def report(args) -> int:
    print("| sensor | band (m) | 0.12 m: n | median (mm) | sd (mm) | median SE (mm) | sd / SE | "
          "0.11 m: n | median (mm) | sd (mm) | d' | 0.11 m accepted |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for item in args.named:
        name, _, paths = item.partition("=")
        big_path, small_path = paths.split(":")
        big, small = _verified(big_path), _verified(small_path)
        for lo, hi in BANDS_M:
            a = [x for x in big if lo <= x["z_m"] < hi]
            b = [x for x in small if lo <= x["z_m"] < hi]
            if len(a) < 3 or len(b) < 3:
                continue
            ra, rb = (1000.0 * np.array([x["free_radius_m"] for x in s]) for s in (a, b))
            se = 1000.0 * np.median([x["free_radius_se_m"] for x in a])
            d = (np.median(ra) - np.median(rb)) / np.sqrt(0.5 * (ra.var() + rb.var()))
            print(support.row(name, f"{lo}-{hi}", len(a), f"{np.median(ra):.1f}", f"{ra.std():.1f}", f"{se:.2f}",
                              f"{ra.std() / se:.1f}", len(b), f"{np.median(rb):.1f}", f"{rb.std():.1f}", f"{d:.2f}",
                              f"{np.mean([x['accepted'] for x in b]):.2f}"))
    return 0


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    c = sub.add_parser("collect", help="one line per ball: the free radius from the truth, its SE")
    c.add_argument("dataset")
    c.add_argument("out")
    c.add_argument("--limit", type=int, default=None, help="the first LIMIT scenes only")
    c.add_argument("--workers", type=options.workers, default=2)
    r = sub.add_parser("report", help="per band: the free radius per true radius, SE, d'")
    r.add_argument("named", nargs="+", metavar="NAME=LINES_0.12:LINES_0.11")
    args = p.parse_args(argv)
    return collect(args) if args.cmd == "collect" else report(args)


if __name__ == "__main__":
    sys.exit(main())
