"""The ``spherebench`` command: one program, one subcommand per step of the benchmark.

Each subcommand is a thin driver in ``scripts/`` (import name ``spherebench.scripts``) with
``add_arguments(parser)`` and ``run(args) -> int``; it is imported only when chosen, so that
``spherebench detect`` never pays for importing torch. Bad input raises SphereBenchError, printed
here as one line with a non-zero exit.
"""

from __future__ import annotations

import argparse
import importlib
import sys

from spherebench import __version__
from spherebench.errors import SphereBenchError

#: (subcommand, driver module under spherebench.scripts, one-line help)
COMMANDS = [
    ("generate", "generate", "build a simulated D435 dataset (a preset) with exact ground truth"),
    ("prepare", "prepare", "turn recorded depth data (.bag, PNG, PLY/PCD/XYZ, raw) into a dataset"),
    ("show", "show", "draw a scene's ground truth: a PNG with circles and a PLY with the ball in red"),
    ("detect", "detect", "find spheres of known radius in point clouds or scene folders"),
    ("detect-2d", "detect_2d", "run the CircleNet-style 2D detector on reprojected images"),
    ("train", "train", "train the CircleNet-style 2D baseline on the train preset"),
    ("evaluate", "evaluate", "run methods on a dataset and score them (COCO circle mAP, 3D errors)"),
]


def _load(module: str):
    try:
        return importlib.import_module(f"spherebench.scripts.{module}")
    except ModuleNotFoundError as exc:
        if exc.name == f"spherebench.scripts.{module}":
            return None  # a subcommand not built yet
        raise


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="spherebench", description=__doc__.splitlines()[0])
    parser.add_argument("--version", action="version", version=f"spherebench {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    wanted = sys.argv[1] if len(sys.argv) > 1 else None
    for name, module, help_text in COMMANDS:
        p = sub.add_parser(name, help=help_text, description=help_text)
        # only the chosen subcommand's driver is imported (keeps start-up fast)
        if name == wanted:
            driver = _load(module)
            if driver is None:
                parser.error(f"'{name}' is not available in this version")
            driver.add_arguments(p)
            p.set_defaults(_driver=driver)
    return parser


def run_module(name: str, driver, argv: list[str] | None = None) -> int:
    """Run a driver module (its ``add_arguments`` and ``run``) on its own, as the benchmark scripts are
    (``python -m spherebench.scripts.NAME``), with the same one-line errors and exit status 2."""
    p = argparse.ArgumentParser(prog=f"spherebench-{name}", description=(driver.__doc__ or name).splitlines()[0])
    driver.add_arguments(p)
    try:
        return int(driver.run(p.parse_args(argv)) or 0)
    except SphereBenchError as exc:
        print(f"{name}: error: {exc}", file=sys.stderr)
        return 2


def main(argv: list[str] | None = None) -> int:
    if argv is not None:
        sys.argv = [sys.argv[0], *argv]
    parser = build_parser()
    args = parser.parse_args()
    if args.command is None:
        parser.print_help()
        return 2
    try:
        return int(args._driver.run(args) or 0)
    except SphereBenchError as exc:
        print(f"spherebench {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"spherebench {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
