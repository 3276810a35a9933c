"""Runs beside the prediction sets, on the same task loop's executor and seeding rule: Table 2 on
the paper preset (``table2_rows``) and the oracle's ceiling of the improved detector on a dataset
with known centres (``oracle_balls``)."""

from __future__ import annotations

import hashlib
import json
import time
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from spherebench.datasets import inout
from spherebench.datasets.fingerprint import dataset_fingerprint
from spherebench.errors import SphereBenchError
from spherebench.eval.bench.oracle import ceiling
from spherebench.eval.bench.paper_numbers import PAPER_DEFAULT_ITERATIONS, PAPER_ITERATIONS, PAPER_TABLE2
from spherebench.eval.bench.seeds import detection_seed
from spherebench.eval.bench.tasks import dataset_scenes
from spherebench.eval.metrics.sensor_grid import band_of, surface_distance_m
from spherebench.eval.metrics.table2 import table2_row
from spherebench.method import IMPROVED, DetectorConfig, config_for, detect, warm_up
from spherebench.parallel import executor
from spherebench.method.verdict import MODEL_PATH as VERDICT_MODEL
from spherebench.provenance import code_version, file_sha256, json_safe
from spherebench.reading import read_json

#: The modules whose source defines the oracle's rows (with the detector's configuration and the data).
ORACLE_MODULES = ("spherebench.eval.bench.oracle", "spherebench.method", "spherebench.eval.metrics.sensor_grid",
                  "spherebench.datasets.inout", "spherebench.cloud")
TABLE2_THRESHOLDS = (3.0, 2.0, 1.5)


# --------------------------------------------------------------------------- the oracle's ceiling

def oracle_balls(data_dir: str | Path, cache_path: str | Path, seed: int = 0, workers: int = 2,
                 log: Callable[[str], None] = print, engine: str = "local",
                 address: str | None = None) -> list[dict]:
    """Per true ball of a dataset with known centres: the improved detector's ceiling there
    (``eval.bench.oracle.ceiling``: its verification started from the true centre), cached.

    Rows {scene_id, ball (index in gt.json), cell (the scene's sensor_cell or None), band
    (``sensor_grid.band_of``), within, separable, score}; scene k's clutter search uses the seed
    ``detection_seed(seed, k)``. The cache (JSON at ``cache_path``) is reused while its key (the
    dataset's fingerprint, the configuration, the seed and ``ORACLE_MODULES``' code) is unchanged.
    """
    data_dir, cache_path = Path(data_dir), Path(cache_path)
    radius = float((inout.read_dataset_meta(data_dir) or {}).get("ball_radius_m", 0.12))
    config = config_for("improved", radius_m=radius).flat()
    key = hashlib.sha256(json.dumps({"dataset": dataset_fingerprint(data_dir), "config": config, "seed": int(seed),
                                     "code": code_version(ORACLE_MODULES), "verdict": file_sha256(VERDICT_MODEL)},
                                    sort_keys=True).encode()).hexdigest()
    if cache_path.is_file():
        try:
            cached = read_json(cache_path)
            if cached.get("key") == key:
                log(f"oracle: ceiling rows reused from {cache_path}")
                return cached["balls"]
        except (SphereBenchError, TypeError, KeyError, AttributeError):
            pass
    t0 = time.perf_counter()
    scenes = dataset_scenes(data_dir)
    log(f"oracle: the improved detector's verification from the true centres of {len(scenes)} scenes")
    tasks = [(json.dumps(config), str(s.path), detection_seed(seed, s.index)) for s in scenes if s.has_cloud]
    with executor(workers, engine, address) as ex:
        parts = list(ex.map(oracle_scene, tasks))
    balls = [b for part in parts for b in part]
    inout.write_json(cache_path, json_safe({"key": key, "dataset": str(data_dir), "seed": int(seed), "balls": balls,
                                            "seconds": round(time.perf_counter() - t0, 1)}))
    return balls


def oracle_scene(task: tuple) -> list[dict]:
    """``oracle_balls``' rows of one scene (in a worker): task (config JSON, scene folder, seed)."""
    config_json, scene_dir, seed = task
    config = DetectorConfig.from_flat(json.loads(config_json))
    gt = inout.read_scene_gt(scene_dir)
    balls = [(k, b) for k, b in enumerate(gt.get("balls", [])) if b.get("center_m") is not None]
    if not balls:
        return []
    found = ceiling(inout.load_cloud(scene_dir), [b["center_m"] for _, b in balls], config, seed=seed)
    cell = (gt.get("meta") or {}).get("sensor_cell")
    return [{"scene_id": str(gt.get("scene_id", Path(scene_dir).name)), "ball": k, "cell": cell,
             "band": band_of(surface_distance_m(b["center_m"], b.get("radius_m", config.radius_m))),
             "within": bool(o["within"]), "separable": o.get("separable"), "score": o.get("score")}
            for (k, b), o in zip(balls, found)]


# --------------------------------------------------------------------------- Table 2 (paper preset)

def table2_rows(paper_dir: str | Path, seed: int = 0, thresholds: Sequence[float] = TABLE2_THRESHOLDS,
                iterations: int | None = None, workers: int = 1, engine: str = "local",
                address: str | None = None) -> list[dict]:
    """Table 2 on the paper preset (E1, E2, E3): one row per scene and z threshold.

    The paper configuration (``PAPER``; 1,000 iterations, 10,000 for E2, or ``iterations`` for
    all) runs once per threshold with the scene's seed, so every threshold filters the same
    RANSAC draw (the draw does not depend on the threshold; checked). Each row holds
    ``eval.metrics.table2.table2_row`` (RMSEs in metres, true centre errors), the centre error of the
    least-squares refinement of the same kept points (R fixed), that of the whole improved
    detector, and the paper's values where it reports the row (``eval.bench.paper_numbers``).
    """
    tasks = [(str(s.path), s.scene_id, detection_seed(seed, s.index),
              s.gt_centres_m[0] if s.gt_centres_m else None, tuple(float(z) for z in thresholds),
              int(iterations or PAPER_ITERATIONS.get(s.scene_id, PAPER_DEFAULT_ITERATIONS)))
             for s in dataset_scenes(paper_dir)]
    with executor(workers, engine, address) as ex:
        return [row for rows in ex.map(table2_scene, tasks) for row in rows]


def table2_scene(task: tuple) -> list[dict]:
    """Table 2's rows of one scene (in a worker): task (scene folder, scene id, seed, true centre or
    None, thresholds, iterations)."""
    scene_dir, scene_id, s_seed, truth, thresholds, its = task
    cloud = inout.load_cloud(scene_dir)
    truth = None if truth is None else np.asarray(truth, np.float64)
    improved = detect(cloud, IMPROVED, seed=s_seed)
    err_improved = (min(float(np.linalg.norm(np.asarray(s.centre_m) - truth)) for s in improved)
                    if improved and truth is not None else None)
    ransac_centre, rows = None, []
    # the paper pipeline's kernels loaded before the first timed row (a fresh checkout's first call
    # otherwise reads 1.1 s there, not 30 ms)
    warm_up(config_for("paper", search={"iterations": int(its)}))
    for z in thresholds:
        cfg = config_for("paper", paper={"zscore_threshold": float(z)}, search={"iterations": int(its)})
        t0 = time.perf_counter()
        found = detect(cloud, cfg, seed=s_seed)
        ms = 1000.0 * (time.perf_counter() - t0)
        refined = detect(cloud, cfg.override({"paper.refine": "least_squares"}), seed=s_seed)
        row = {"scene": scene_id, "z": float(z), "iterations": int(its), "seed": s_seed, "ms": ms}
        if found and refined:
            tr = found[0].trace
            if ransac_centre is not None and not np.allclose(tr.ransac_centre_m, ransac_centre):
                raise SphereBenchError("the paper pipeline's RANSAC draw changed with the z threshold")
            ransac_centre = tr.ransac_centre_m
            pts = cloud.points.astype(np.float64)
            row.update(table2_row(pts[tr.ransac_indices], pts[tr.kept_indices], tr.ransac_centre_m, IMPROVED.radius_m,
                                  barycentre_m=tr.barycentre_m, refined_centre_m=refined[0].centre_m,
                                  true_centre_m=truth))
        row["error_improved_m"] = err_improved
        paper = PAPER_TABLE2.get((scene_id, float(z)))
        row["paper"] = None if paper is None else dict(zip(
            ("rmse_ransac", "rmse_ransac_filtered", "rmse_barycentre"), paper))
        rows.append(row)
    return rows
