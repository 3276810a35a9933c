"""The resume cache of prediction sets: keys, the meta file, and the atomic write of a set.

A prediction set is ``<out>/<name>.json``, a COCO results list with CircleNet's fields
(image_id, category_id, circle_center [x, y], circle_radius (px), score) plus scene_id and, for
3D methods, center_m (m) and radius_m (m, only where the method estimates a radius). Beside it
``<name>.meta.json``: the provenance (dataset fingerprint, configuration, seed, code version: the
resume key), the per-scene records (time per frame, detections in 3D, resolution) and what the
scoring needs. Both are written atomically, the meta file last: a set whose meta file is present,
readable and carries the same key and the same predictions hash is finished and is reused, so an
interrupted run redoes no finished work.
"""

from __future__ import annotations

import hashlib
import json
import math
from pathlib import Path

from spherebench.circles import circle_bbox
from spherebench.datasets import inout
from spherebench.errors import SphereBenchError
from spherebench.eval.bench.registry import PAPER_CIRCLE, MethodSpec
from spherebench.eval.bench.seeds import DETECTION_SEED_RULE
from spherebench.provenance import file_sha256, machine_info, now_utc

#: Format version of the predictions' meta files (part of the resume key).
FORMAT_VERSION = 1


def prediction_key(spec: MethodSpec, output: str, fingerprint: str, seed: int, version: str,
                   scene_ids: list[str]) -> str:
    """The resume key of one prediction set: everything its content depends on."""
    blob = json.dumps({"format": FORMAT_VERSION, "output": output, "config": spec.config, "seed": int(seed),
                       "dataset": fingerprint, "code": version, "extra": spec.extra_fingerprint,
                       "scenes": scene_ids}, sort_keys=True)
    return hashlib.sha256(blob.encode()).hexdigest()


def meta_path(pred_path: Path) -> Path:
    return pred_path.with_name(pred_path.name[:-len(".json")] + ".meta.json")


def is_finished(pred_path: Path, key: str) -> bool:
    """A prediction set is finished when its meta file carries ``key`` and the predictions' hash."""
    meta_file = meta_path(pred_path)
    if not pred_path.is_file() or not meta_file.is_file():
        return False
    try:
        meta = inout.read_json(meta_file)
    except (OSError, SphereBenchError):
        return False
    if not isinstance(meta, dict):
        return False
    return meta.get("key") == key and meta.get("predictions_sha256") == file_sha256(pred_path)


def read_predictions(pred_path: str | Path) -> tuple[list[dict], dict]:
    """(COCO results list, meta dict) of a prediction set."""
    pred_path = Path(pred_path)
    return inout.read_json(pred_path), inout.read_json(meta_path(pred_path))


def _rounded(x, nd: int):
    return None if x is None or not math.isfinite(float(x)) else round(float(x), nd)


def _circle(c) -> list[float] | None:
    return None if c is None else [round(float(v), 3) for v in c]


def results_and_records(spec: MethodSpec, output: str, scenes: list, records: list[dict],
                        category_id: int) -> tuple[list[dict], list[dict]]:
    """The COCO results list and the per-scene records of one prediction set (scenes: the runner's
    ``SceneInfo`` of each record)."""
    circle_key = "circle_paper" if output.endswith(PAPER_CIRCLE) else "circle"
    results, scene_records = [], []
    for scene, rec in zip(scenes, records):
        dets3d = []
        for d in rec["detections"]:
            circle = d.get(circle_key)
            entry = {"score": round(float(d["score"]), 6), "circle": _circle(circle)}
            if spec.kind == "3d":
                entry["center_m"] = [round(float(v), 6) for v in d["center_m"]]
                entry["radius_m"] = _rounded(d.get("radius_m"), 6)
            dets3d.append(entry)
            if scene.image_id is not None and circle is not None and circle[2] > 0:
                r = {"image_id": scene.image_id, "category_id": category_id,
                     "circle_center": entry["circle"][:2], "circle_radius": entry["circle"][2],
                     "bbox": circle_bbox(*entry["circle"], decimals=3), "score": entry["score"], "scene_id": scene.scene_id}
                if spec.kind == "3d":
                    r["center_m"] = entry["center_m"]
                    if entry["radius_m"] is not None:
                        r["radius_m"] = entry["radius_m"]
                results.append(r)
        scene_records.append({"scene_id": scene.scene_id, "image_id": scene.image_id, "index": scene.index,
                              "seed": rec["seed"], "resolution": scene.resolution, "ms": round(rec["ms"], 4),
                              "detections": dets3d, **({"error": rec["error"]} if rec.get("error") else {}),
                              **({"sensor_cell": scene.sensor_cell} if scene.sensor_cell else {})})
    return results, scene_records


def write_prediction_set(pred: Path, spec: MethodSpec, output: str, scenes: list, records: list[dict],
                         category_id: int, key: str, version: str, seed: int, dataset: dict,
                         workers: int, engine: str = "local") -> None:
    """Write one prediction set and then its meta file (the mark of a finished set).

    dataset: {path, fingerprint, preset, name, n_scenes} of the dataset it ran on."""
    res, scene_records = results_and_records(spec, output, scenes, records, category_id)
    inout.write_json(pred, res, indent=None)
    meta = {"format": FORMAT_VERSION, "output": output, "method": spec.name, "kind": spec.kind,
            "rule": ("paper" if output.endswith(PAPER_CIRCLE) else "exact") if spec.kind == "3d" else None,
            "key": key, "predictions_sha256": file_sha256(pred), "config": spec.config,
            "note": spec.note, "seed": int(seed), "seeding": DETECTION_SEED_RULE,
            "dataset": {**dataset, "n_run": len(scenes)},
            "code_version": version, "modules": list(spec.modules), "extra_fingerprint": spec.extra_fingerprint,
            "workers": int(max(1, workers)), "engine": engine,
            "timing": "ms around the detection call only (no file reading), 1 thread per worker process",
            "machine": machine_info(), "created": now_utc(), "scenes": scene_records}
    inout.write_json(meta_path(pred), meta, indent=None)
