"""The Hough baseline's parameters, chosen on the training split and cached (``tuned_hough_config``).

The benchmark's scenes are never seen: a training subset (`spherebench generate --preset train
--n 200`, whose seeds are disjoint from the evaluation presets') is built if absent, and
``hough.DEFAULT_GRID`` is searched on it by mAP.50, ties to mAP (``hough.tune``'s rule), the grid
shared among the executor's workers. The cache is a JSON file ({"key", "config", the grid's
scores, ...}) reused while its key (``hough_key``: the subset, the grid, the code of the Hough
baseline, the scoring and the simulator) is unchanged.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import time
from pathlib import Path
from typing import Callable

import numpy as np

from spherebench.baselines import hough
from spherebench.baselines.hough import DEFAULT_GRID, HoughConfig
from spherebench.datasets import inout, simulate
from spherebench.datasets.fingerprint import dataset_fingerprint
from spherebench.errors import SphereBenchError
from spherebench.parallel import executor
from spherebench.provenance import REPO_ROOT, code_version, json_safe

#: The training subset the Hough parameters are chosen on: `spherebench generate --preset train --n 200`.
HOUGH_TRAIN_SCENES = 200
#: The repository's tuned configuration (written by `make eval`), reused while its key matches.
REPO_HOUGH_CONFIG = REPO_ROOT / "results" / "hough_config.json"


def hough_key(n: int = HOUGH_TRAIN_SCENES, seed: int = 0) -> str:
    """The cache key of a tuning on ``n`` training scenes of seed ``seed``."""
    blob = json.dumps({"train": {"preset": "train", "n": int(n), "seed": int(seed)}, "grid": DEFAULT_GRID,
                       "base": dataclasses.asdict(HoughConfig()),
                       "code": code_version(("spherebench.baselines.hough", "spherebench.eval.metrics.coco_eval",
                                             "spherebench.datasets"))}, sort_keys=True)
    return hashlib.sha256(blob.encode()).hexdigest()


def load_hough_config(path: str | Path) -> HoughConfig:
    """A HoughConfig from JSON: a tuning cache ({"config": {...}}) or the fields themselves."""
    path = Path(path)
    try:
        d = inout.read_json(path)
    except OSError as exc:
        raise SphereBenchError(f"cannot read Hough configuration {path} ({exc.strerror})") from None
    d = d.get("config", d) if isinstance(d, dict) else d
    try:
        return HoughConfig(**d)
    except TypeError as exc:
        raise SphereBenchError(f"{path} is not a Hough configuration ({exc})") from None


def _cached(cache_path: Path, key: str) -> HoughConfig | None:
    if cache_path.is_file():
        try:
            cached = inout.read_json(cache_path)
            if cached.get("key") == key:
                return HoughConfig(**cached["config"])
        except (OSError, SphereBenchError, TypeError, KeyError, AttributeError):
            pass
    return None


def tuned_hough_config(cache_path: str | Path, train_dir: str | Path, n: int = HOUGH_TRAIN_SCENES, seed: int = 0,
                       workers: int = 2, progress: bool = True, log: Callable[[str], None] = print,
                       engine: str = "local", address: str | None = None) -> HoughConfig:
    """The Hough configuration with the best mAP.50 on the training split, cached at ``cache_path``;
    the subset is built in ``train_dir`` if absent (see the module docstring)."""
    cache_path, train_dir = Path(cache_path), Path(train_dir)
    key = hough_key(n, seed)
    best = _cached(cache_path, key)
    if best is not None:
        log(f"hough: tuned configuration reused from {cache_path}")
        return best
    meta = inout.read_dataset_meta(train_dir) if (train_dir / "dataset.json").is_file() else None
    if meta is None or meta.get("preset") != "train" or meta.get("n") != n or meta.get("seed") != seed:
        if meta is not None and meta.get("preset") != "train":
            raise SphereBenchError(f"{train_dir} holds the '{meta.get('preset')}' preset: the Hough baseline is tuned "
                                   "on the training split only")
        log(f"hough: building the training subset ({n} scenes of the train preset) in {train_dir}")
        simulate.generate_dataset("train", train_dir, n=n, seed=seed, workers=workers, progress=progress)
    t0 = time.perf_counter()
    grid = DEFAULT_GRID
    log(f"hough: searching {len(grid)} settings on the {n} training images")
    k = max(1, workers)
    with executor(workers, engine, address) as ex:
        scored_parts = list(ex.map(grid_part, [(str(train_dir), grid[i::k]) for i in range(k)]))
    # back to grid order: part i holds entries i, i + k, ...
    scored = [None] * len(grid)
    for i, part in enumerate(scored_parts):
        for j, item in enumerate(part):
            scored[i + j * k] = item
    # hough.tune's rule: best mAP.50, ties to mAP, then to the earlier grid entry
    best, best_metrics = scored[0]
    for cfg, m in scored[1:]:
        if (np.nan_to_num(m["mAP50"], nan=-1.0), np.nan_to_num(m["mAP"], nan=-1.0)) > \
                (np.nan_to_num(best_metrics["mAP50"], nan=-1.0), np.nan_to_num(best_metrics["mAP"], nan=-1.0)):
            best, best_metrics = cfg, m
    record = {"key": key, "config": dataclasses.asdict(best),
              "chosen_by": "mAP.50 (circle IoU, COCO protocol) on the training subset, ties to mAP",
              "train": {"path": str(train_dir), "preset": "train", "n": n, "seed": seed,
                        "fingerprint": dataset_fingerprint(train_dir)},
              "train_metrics": {k: best_metrics.get(k) for k in ("mAP", "mAP50", "mAP75", "mAR")},
              "grid": [{"overrides": {k: v for k, v in dataclasses.asdict(c).items()
                                      if v != getattr(HoughConfig(), k)},
                        "mAP": m.get("mAP"), "mAP50": m.get("mAP50")} for c, m in scored],
              "seconds": round(time.perf_counter() - t0, 1)}
    inout.write_json(cache_path, json_safe(record))
    return best


def grid_part(task: tuple[str, list[dict]]) -> list:
    """``hough.grid_scores`` of part of the grid on a training dataset's images (in a worker)."""
    train_dir, grid = task
    root = Path(train_dir)
    coco = inout.read_coco_gt(root)
    circles: dict[int, list] = {img["id"]: [] for img in coco["images"]}
    for a in coco["annotations"]:
        circles[a["image_id"]].append([*a["circle_center"], a["circle_radius"]])
    images = [inout.read_image(root / img["file_name"]) for img in coco["images"]]
    gts = [np.asarray(circles[img["id"]], np.float64).reshape(-1, 3) for img in coco["images"]]
    return hough.grid_scores(images, gts, grid)


def hough_config_for_run(methods, hough_file, out: Path, workers: int, progress: bool, log=print,
                         engine: str = "local", address: str | None = None) -> HoughConfig | None:
    """The Hough configuration of an evaluation: None when hough is not among ``methods``; else a given
    file, the repository's tuned one (``REPO_HOUGH_CONFIG``, while its key matches), the copy shipped
    with the package (``hough.SHIPPED_CONFIG``), or a fresh tuning under ``out``."""
    if methods is not None and "hough" not in methods:
        return None
    if hough_file:
        return load_hough_config(hough_file)
    repo = _cached(REPO_HOUGH_CONFIG, hough_key())
    if repo is not None:
        log(f"hough: tuned configuration from {REPO_HOUGH_CONFIG}")
        return repo
    if hough.SHIPPED_CONFIG.is_file():  # an installed package, or a clone whose results/ predate its code
        log(f"hough: the tuned configuration shipped with the package ({hough.SHIPPED_CONFIG.name})")
        return load_hough_config(hough.SHIPPED_CONFIG)
    return tuned_hough_config(out / "hough_config.json", out / "train-hough", seed=0, workers=workers,
                              progress=progress, log=log, engine=engine, address=address)
