"""`spherebench train-verifier`: fit the 3D detector's verdict on the candidates of training datasets.

    spherebench train-verifier --data data/train --data data/train-stereo --out checkpoints/verdict [--seed 0]

Writes verdict.onnx, verdict_card.json and verdict_card.md to --out (see
spherebench.eval.bench.verdict_fit); `make train-verifier` installs them beside the detector
(method/). Never fit on the benchmark's scenes.
"""

from __future__ import annotations

import shlex
import sys
from pathlib import Path

from spherebench import options
from spherebench.errors import require


def add_arguments(parser) -> None:
    parser.add_argument("--data", required=True, action="append", metavar="DIR",
                        help="a training dataset folder (train, train-stereo); repeat for several")
    parser.add_argument("--out", type=options.out_path, required=True, metavar="DIR",
                        help="folder for verdict.onnx and its card")
    parser.add_argument("--seed", type=options.seed, default=0, metavar="N", help="the fits' seed (default 0)")
    parser.add_argument("--seeds", default="0", metavar="LIST",
                        help="the detector's run seeds whose candidates are collected, e.g. 0-1 (default 0)")
    parser.add_argument("--workers", type=options.workers, default=2, metavar="N", help="worker processes (default 2)")


def run(args) -> int:
    require("sklearn", "train", "fitting the verdict")
    require("skl2onnx", "train", "fitting the verdict")
    require("lightgbm", "train", "fitting the verdict")
    require("onnxmltools", "train", "fitting the verdict")
    from spherebench.eval.bench.evaluate import check_dataset
    from spherebench.eval.bench.verdict_fit import train_verifier

    for d in args.data:
        check_dataset(Path(d))
    card = train_verifier([Path(d) for d in args.data], Path(args.out), args.seed, options.parse_seeds(args.seeds),
                          args.workers, "spherebench " + shlex.join(sys.argv[1:]),
                          progress=lambda m: print(m, file=sys.stderr))
    cal = ", ".join(f"{d} AP {v['ap']:.3f} ECE {v['ece']:.3f}" for d, v in card["calibration"].items())
    print(f"{args.out}/verdict.onnx: {card['model']}; held apart: {cal}")
    return 0
