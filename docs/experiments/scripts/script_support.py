"""What the experiment scripts share: a dataset's scenes with a depth frame, its ball radius, the
detector's configuration with `--set` overrides, the common options and the JSON output.

Not a command. The scripts beside it import it (``python docs/experiments/scripts/NAME.py`` puts
this folder on ``sys.path``); everything else comes from the installed ``spherebench``.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

from spherebench import options
from spherebench.datasets import inout
from spherebench.eval.bench.tasks import SceneInfo, dataset_scenes
from spherebench.eval.bench.sweep import read_settings
from spherebench.method import config_for
from spherebench.method.config import DetectorConfig
from spherebench.method.detector import prepare_frame
from spherebench.method.noise import noise_a


def parser(doc: str) -> argparse.ArgumentParser:
    """A script's parser (its description the docstring's first paragraph) with the dataset folder and
    which of its scenes to run: --limit, --family."""
    p = argparse.ArgumentParser(description=doc.split("\n\n")[0])
    p.add_argument("dataset", help="a dataset folder (spherebench generate --preset NAME --out DIR)")
    p.add_argument("--limit", type=options.count, default=None, help="the first N scenes only (quick runs)")
    p.add_argument("--family", action="append", default=[], metavar="NAME",
                   help="only scenes of this family (repeatable), e.g. --family far --family occluded")
    return p


def add_ab_arguments(p: argparse.ArgumentParser) -> None:
    """Configurations A and B: --method, --set (A), --method-b, --set-b (B); ``args.a``, ``args.b``."""
    p.add_argument("--method", default="improved", help="configuration A's detector preset")
    p.add_argument("--set", dest="a", action="append", default=[], metavar="NAME=VALUE",
                   help="configuration A: a detector setting overridden, by its path (repeatable)")
    p.add_argument("--method-b", default=None, help="configuration B's detector preset (default: --method)")
    p.add_argument("--set-b", dest="b", action="append", default=[], metavar="NAME=VALUE",
                   help="configuration B: a detector setting overridden, by its path (repeatable)")


def add_json_argument(p: argparse.ArgumentParser) -> None:
    p.add_argument("--json", type=options.out_path, default=None, metavar="PATH",
                   help="also write the whole result (every row) to PATH as JSON")


def add_holes_argument(p: argparse.ArgumentParser) -> None:
    p.add_argument("--holes", choices=("only", "none"), default=None,
                   help="only the scenes whose balls have a hole in their depth (gt.json meta hole_fraction), "
                        "or only those without")


def frame_scenes(dataset: str | Path, limit: int | None = None, families: list[str] | None = None,
                 holes: str | None = None) -> list[SceneInfo]:
    """The dataset's scenes with a depth frame (``SceneInfo.has_frame``), in scene-id order, their
    indices those of the whole dataset (so that ``detection_seed(seed, index)`` is the benchmark's);
    ``families``: of those families only; ``holes``: "only" the scenes with a holed ball, "none" those without."""
    scenes = [s for s in dataset_scenes(dataset, limit) if s.has_frame]
    if families:
        scenes = [s for s in scenes if s.family in families]
    if holes is not None:
        holed = {s.scene_id: any(f is not None for f in inout.read_scene_gt(s.path)["meta"].get("hole_fraction", []))
                 for s in scenes}
        scenes = [s for s in scenes if holed[s.scene_id] == (holes == "only")]
    return scenes


def dataset_radius(dataset: str | Path) -> float:
    """The dataset's ball radius (m): dataset.json's ``ball_radius_m``, else a basketball's."""
    meta = inout.read_dataset_meta(dataset) if (Path(dataset) / "dataset.json").is_file() else {}
    return float((meta or {}).get("ball_radius_m", 0.12))


def settings(items: list[str], script: str) -> dict:
    """--set NAME=VALUE items as {path: value} (``eval.bench.sweep.read_settings``: a bare name of
    before the configuration's groups is read as its path, with one deprecation line)."""
    return read_settings(items, script)


def detector_config(dataset: str | Path, overrides: dict, method: str = "improved") -> DetectorConfig:
    """The detector preset ``method`` at the dataset's radius with the ``--set`` overrides."""
    return config_for(method, **{"radius_m": dataset_radius(dataset), **overrides})


def add_noise_argument(p: argparse.ArgumentParser) -> None:
    p.add_argument("--frame-noise", action="store_true",
                   help="one pixel's noise by the frame's own A (what the kernels use), not the nominal model's")


def scene_noise_a(scene: SceneInfo, config: DetectorConfig, frame: bool = False) -> float:
    """sigma_z / z^2 (1/m) of a scene: the configuration's nominal model (``improved.noise_a``), or with
    ``frame`` the prepared frame's (``PreparedFrame.noise_a``: its own measured A where it differs from
    the model's by more than ``noise_model_tolerance``, as the kernels take it). NaN without intrinsics."""
    if not (scene.path / "intrinsics.json").is_file():
        return math.nan
    if frame:
        return float(prepare_frame(inout.load_cloud(scene.path), config).noise_a)
    return noise_a(config, float(inout.read_intrinsics(scene.path / "intrinsics.json").fx))


def noise_over_r(a: float, centre_m, config: DetectorConfig) -> float:
    """One pixel's depth noise at the ball, sigma_z = A z^2, over R: how noisy the ball looks to the
    detector's tolerances."""
    return a * float(centre_m[2]) ** 2 / config.radius_m


def noise_bin(value: float, edges: list[float]) -> str:
    """The bin label of ``value`` among ``edges`` (ascending): "0-0.1", ..., "1+"."""
    if not math.isfinite(value):
        return "unknown"
    for lo, hi in zip(edges, edges[1:]):
        if lo <= value < hi:
            return f"{lo:g}-{hi:g}"
    return f"{edges[-1]:g}+" if value >= edges[-1] else f"<{edges[0]:g}"


def parse_edges(text: str) -> list[float]:
    """"0,0.1,0.2" -> [0.0, 0.1, 0.2] (ascending)."""
    edges = [float(x) for x in text.split(",") if x.strip()]
    if len(edges) < 2 or edges != sorted(edges):
        raise argparse.ArgumentTypeError(f"{text!r}: give two or more ascending numbers, e.g. 0,0.25,0.5,1")
    return edges


def row(*cells) -> str:
    """A Markdown table row; True and False read yes and no, None a dash."""
    return "| " + " | ".join("-" if c is None else ("yes" if c else "no") if isinstance(c, bool) else str(c)
                             for c in cells) + " |"


def write_json(path: str | None, result: dict) -> None:
    if path is not None:
        Path(path).write_text(json.dumps(result, indent=1, default=float) + "\n")
