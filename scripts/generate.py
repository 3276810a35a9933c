"""`spherebench generate`: build a simulated D435 dataset (a preset) with exact ground truth."""

from __future__ import annotations

import argparse
import sys

from spherebench import options
from spherebench.datasets import outputs, presets, simulate
from spherebench.datasets.sensor import PARAMETERS, parse_settings


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--preset", choices=sorted(presets.PRESETS), default="default",
                   help="default: the paper's 200 scenes; paper: E1-E3; hard: distractors, occlusion, "
                        "range, negatives; hard-sensor: hard's scenes under the robust grid's span of sensors, drawn "
                        "per scene; robust: default's scenes over a grid of sensor conditions; "
                        "train: training split for learned baselines; wide: the wide grammar (pitched and rolled "
                        "cameras, the ball on tripods, shelves, tables, chairs, boxes, the floor, against walls, "
                        "among furniture and distractors; negatives); NAME-stereo: NAME's families and sizes "
                        "through the stereo sensor model, other seeds")
    p.add_argument("--out", type=options.out_path, required=True, help="dataset folder to write (replaced when complete)")
    p.add_argument("--n", type=int, default=None, help="number of scenes (default: the preset's)")
    p.add_argument("--seed", type=options.seed, default=0, help="run seed; scene k's seed derives from (preset, seed, k)")
    p.add_argument("--radius", type=float, default=presets.BASKETBALL_RADIUS_M, help="ball radius, metres")
    p.add_argument("--workers", type=options.workers, default=simulate.default_workers(),
                   help="processes (output is identical for any number)")
    p.add_argument("--clouds", action=argparse.BooleanOptionalAction, default=None,
                   help="write cloud.ply per scene (default: yes, except for the train preset)")
    p.add_argument("--sensor", action="append", default=[], metavar="NAME=VALUE",
                   help="set a sensor parameter for every scene, overriding the preset: a number, a range "
                        "LO:HI drawn per scene (a pair parameter's own range), 0/1 for a switch; repeatable. "
                        f"Parameters: {', '.join(PARAMETERS)} (docs/data.md)")
    p.add_argument("--sensor-model", choices=sorted(presets.SENSOR_MODELS), default=None,
                   help="analytic: the noise model of datasets/sensor.py; stereo: both infrared images rendered "
                        "and matched by semi-global matching (datasets/stereo.py, docs/data.md); default: the "
                        "preset's (stereo for the -stereo twins, else analytic)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    outputs.check_not_in_dataset(args.out)
    overrides = parse_settings(args.sensor)
    spec = presets.PRESETS[args.preset].sensor
    for name in sorted(set(overrides) & (spec.grid_parameters if spec else set())):
        print(f"spherebench generate: note: --sensor {name} replaces the {args.preset} grid's {name} in every "
              "cell (the scenes keep their cell labels; gt.json records the sensor used)", file=sys.stderr)
    simulate.generate_dataset(args.preset, args.out, n=args.n, seed=args.seed, radius_m=args.radius,
                              workers=args.workers, progress=not args.quiet, clouds=args.clouds,
                              sensor_overrides=overrides, sensor_model=args.sensor_model,
                              before_commit=lambda out: print(f"wrote {out}", flush=True))
    return 0
