"""Scoring prediction sets: one set (``eval.bench.cache``, written by ``eval.bench.tasks``) against a
dataset's ground truth, into the figures of the tables.

``score_set`` gives COCO metrics with circle IoU (overall and per scene family), 3D metrics for
methods with a 3D centre, the figures of a sensor grid's cells, detection statistics of scenes
without ground truth, and the time per frame; ``metrics_json`` gathers them as metrics.json holds
them.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np

from spherebench.eval.bench.cache import read_predictions
from spherebench.eval.bench.registry import PAPER_CIRCLE, at_operating_point
from spherebench.eval.bench.tasks import SceneInfo
from spherebench.eval.metrics.coco_eval import evaluate_circles, load_ground_truth, scalar_metrics
from spherebench.eval.metrics.metrics3d import MATCH_GATE_M, found_by_band, found_far_rule, match_scene, summarize_3d
from spherebench.eval.metrics.sensor_grid import (GRID_AXES, band_of, detection_rates, grid_key, grid_rows,
                                                  map50_by_group, surface_distance_m)
from spherebench.provenance import json_safe


@dataclass
class ScoredSet:
    """One prediction set on one dataset, scored.

    metrics: JSON-ready figures (see ``score_set``). pr50, pr75: (101,) interpolated precision at
    recall 0:0.01:1 (NaN = undefined) at IoU .50 and .75. distance_m, centre_error_m: (G,) per
    ground-truth ball (NaN error = missed), 3D methods only. ms: (S,) time per frame.
    scenes: the meta file's per-scene records. results: the COCO results list. config,
    extra_fingerprint: the method's settings and model file hash, as the meta file holds them.
    """

    output: str
    method: str
    kind: str
    rule: str | None
    note: str
    metrics: dict
    pr50: np.ndarray | None = None
    pr75: np.ndarray | None = None
    distance_m: np.ndarray | None = None
    centre_error_m: np.ndarray | None = None
    ms: np.ndarray = field(default_factory=lambda: np.zeros(0))
    scenes: list = field(default_factory=list)
    results: list = field(default_factory=list)
    config: dict | None = None
    extra_fingerprint: str = ""


def _stats_ms(ms: np.ndarray) -> dict:
    if ms.size == 0:
        return {"n": 0, "median": None, "p95": None, "mean": None}
    return {"n": int(ms.size), "median": float(np.median(ms)), "p95": float(np.percentile(ms, 95)),
            "mean": float(np.mean(ms))}


def score_set(pred_path: str | Path, coco_gt: dict, scenes: Sequence[SceneInfo]) -> ScoredSet:
    """Score one prediction set against a dataset's ground truth (restricted to the scenes it ran on).

    metrics: mAP, mAP50, mAP75, mAR (and COCO's other summary figures) over the annotated images
    that were run; "families" {family: {mAP, mAP50, mAP75, mAR, n_images, n_gt}}; "3d" (3D
    methods: ``summarize_3d`` over the scenes with known centres, gate one ball radius; radius
    error only where the method estimates a radius); "ms" (median, p95, mean) and
    "ms_by_resolution"; ms_median / ms_p95; n_scenes_run; "unannotated" detection statistics for
    scenes without ground truth; on a grid preset (scenes with a sensor cell) "sensor_cells", the
    3D detection rate within 2 cm and mAP.50 per cell and range band, and "sensor_levels", the same
    per subpixel pooled over the other axes (``sensor_rows``).
    """
    results, meta = read_predictions(pred_path)
    by_id = {s.scene_id: s for s in scenes}
    records = meta["scenes"]
    run_images = sorted({r["image_id"] for r in records if r.get("image_id") is not None})
    ms = np.asarray([r["ms"] for r in records], dtype=np.float64)
    m: dict = {"n_scenes_run": len(records), "note": meta.get("note", "")}
    out = ScoredSet(output=meta["output"], method=meta["method"], kind=meta["kind"], rule=meta.get("rule"),
                    note=meta.get("note", ""), metrics=m, ms=ms, scenes=records, results=results,
                    config=meta.get("config"), extra_fingerprint=meta.get("extra_fingerprint") or "")
    gt = _score_circles(out, coco_gt, run_images)
    ball_errors = _score_3d(out, scenes) if meta["kind"] == "3d" and _centres_known(scenes) else None
    cells = {r["scene_id"]: r.get("sensor_cell") or by_id[r["scene_id"]].sensor_cell for r in records}
    if any(cells.values()):
        for key, axes in (("sensor_cells", GRID_AXES), ("sensor_levels", ("subpixel",))):
            m[key] = json_safe(sensor_rows(cells, by_id, gt, results, ball_errors, axes))
    m["ms"] = _stats_ms(ms)
    m["ms_median"], m["ms_p95"] = m["ms"]["median"], m["ms"]["p95"]
    res_groups: dict[str, list[float]] = {}
    for r in records:
        res_groups.setdefault(r.get("resolution") or "unknown", []).append(r["ms"])
    m["ms_by_resolution"] = {k: _stats_ms(np.asarray(v)) for k, v in sorted(res_groups.items(), key=_res_order)}
    unannotated = [r for r in records if not by_id[r["scene_id"]].annotated]
    if unannotated:
        # what a user gets: the detections at the method's operating point
        m["unannotated"] = detection_stats([{**r, "detections": at_operating_point(r["detections"], out.config or {})}
                                            for r in unannotated],
                                           [by_id[r["scene_id"]].reference_centre_m for r in unannotated])
    errors = Counter(r["error"] for r in records if r.get("error"))
    if errors:
        m["scenes_refused"] = sum(errors.values())
        m["refused_reason"] = errors.most_common(1)[0][0]
    return out


def _score_circles(out: ScoredSet, coco_gt: dict, run_images: list[int]):
    """The COCO circle metrics of a set over the annotated images run, overall and per family, into
    ``out``; returns the ground truth as a COCO object (None: nothing to score in 2D)."""
    if not run_images or coco_gt.get("annotations") is None:
        return None
    m, results = out.metrics, out.results
    gt = load_ground_truth(coco_gt)
    ev = evaluate_circles(gt, results, image_ids=run_images)
    m.update(scalar_metrics(ev))
    out.pr50 = np.asarray(ev["pr_precision"][0], dtype=np.float64)
    out.pr75 = np.asarray(ev["pr_precision"][int(np.argmin(np.abs(ev["iou_thresholds"] - 0.75)))], dtype=np.float64)
    families: dict[str, list[int]] = {}
    for img in coco_gt["images"]:
        if img["id"] in set(run_images):
            families.setdefault(str(img.get("family", "unknown")), []).append(img["id"])
    m["families"] = {}
    for fam in sorted(families):
        f = scalar_metrics(evaluate_circles(gt, results, image_ids=families[fam]))
        m["families"][fam] = {k: f.get(k) for k in ("mAP", "mAP50", "mAP75", "mAR", "n_images", "n_gt",
                                                    "n_detections")}
    return gt


def _score_3d(out: ScoredSet, scenes: Sequence[SceneInfo]) -> list:
    """The 3D metrics of a 3D method's set over the annotated scenes whose balls all have a known
    centre, into ``out``, at the method's operating point (``registry.operating_score``: the ranked
    output below it is scored in 2D only); returns [(SceneInfo, its balls' centre errors (m), NaN = missed)]."""
    by_id = {s.scene_id: s for s in scenes}
    matches, ball_errors, gates = [], [], []
    for r in out.scenes:
        s = by_id.get(r["scene_id"])
        if s is None or not s.annotated or len(s.gt_centres_m) != s.n_balls:
            continue
        dets = at_operating_point(r["detections"], out.config or {})
        pc = np.asarray([d["center_m"] for d in dets], np.float64).reshape(-1, 3)
        ps = np.asarray([d["score"] for d in dets], np.float64)
        pr = np.asarray([np.nan if d.get("radius_m") is None else d["radius_m"] for d in dets], np.float64)
        gate = max(s.gt_radii_m) if s.gt_radii_m else MATCH_GATE_M  # one radius of the scene's ball
        gates.append(gate)
        matches.append(match_scene(pc, ps, s.gt_centres_m, gate_m=gate, pred_radii_m=pr,
                                   gt_radii_m=s.gt_radii_m))
        ball_errors.append((s, matches[-1].centre_error_m))
    if matches:
        m = out.metrics
        m["3d"] = json_safe(summarize_3d(matches))
        m["3d"]["gate_m"] = float(max(gates))
        depths = np.concatenate([np.asarray(s.gt_centres_m, np.float64).reshape(-1, 3)[:, 2] for s, _ in ball_errors])
        errors = np.concatenate([e for _, e in ball_errors])
        m["3d"]["found_far_rule"] = json_safe(found_far_rule(errors, depths))
        distances = [surface_distance_m(c, r) for s, _ in ball_errors for c, r in zip(s.gt_centres_m, s.gt_radii_m)]
        m["3d"]["found_by_band"] = json_safe(found_by_band(errors, depths, distances))
        m["3d"]["scenes_without_centre"] = sum(1 for s in scenes if s.annotated and len(s.gt_centres_m) != s.n_balls)
        out.distance_m = np.concatenate([mm.gt_distance_m for mm in matches])
        out.centre_error_m = np.concatenate([mm.centre_error_m for mm in matches])
    return ball_errors


def sensor_rows(cells: dict, by_id: dict, gt, results: list, ball_errors: list | None,
                axes: Sequence[str] = GRID_AXES) -> list[dict]:
    """``sensor_grid.grid_rows`` of one prediction set: groups by the levels of ``axes`` of each
    scene's sensor cell (cells: scene id -> cell, in record order) and range band.

    ball_errors: [(SceneInfo, its balls' centre errors (m), NaN = missed)] of a 3D method, else None;
    gt: the ground truth as a COCO object (None: no mAP); results: the COCO results."""
    scene_keys = [grid_key(cell, axes) for cell in cells.values()]
    rates = None
    if ball_errors is not None:
        keys, errors = [], []
        for scene, errs in ball_errors:
            key = grid_key(cells.get(scene.scene_id), axes)
            for centre, radius, err in zip(scene.gt_centres_m, scene.gt_radii_m, errs):
                band = band_of(surface_distance_m(centre, radius))
                keys.append(None if key is None or band is None else key + (band,))
                errors.append(err)
        rates = detection_rates(keys, errors)
    maps = None
    if gt is not None:
        image_keys = {by_id[sid].image_id: grid_key(cell, axes) for sid, cell in cells.items()
                      if by_id[sid].image_id is not None}
        radius = {s.image_id: s.gt_radii_m[0] for s in by_id.values() if s.gt_radii_m}

        def ann_band(a: dict) -> str | None:
            c, r = a.get("center_m"), radius.get(a["image_id"])
            return None if c is None or r is None else band_of(surface_distance_m(c, r))

        if image_keys:
            maps = map50_by_group(gt, results, image_keys, ann_band)
    return grid_rows(scene_keys, rates, maps, axes)


def not_run(s: ScoredSet) -> str | None:
    """Why a set has no result at all (the method refused every scene it was given), or None."""
    n = s.metrics.get("n_scenes_run", 0)
    return s.metrics.get("refused_reason") if n and s.metrics.get("scenes_refused") == n else None


def _centres_known(scenes: Sequence[SceneInfo]) -> bool:
    """3D metrics need known centres: simulated data's true ones, a recording's mask-fit references. They
    are scored when some annotated ball has one, over the annotated scenes whose visible balls all have
    one (a recorded ball whose fit failed leaves its scene out; a negative scene is always in)."""
    annotated = [s for s in scenes if s.annotated]
    return bool(annotated) and (all(len(s.gt_centres_m) == s.n_balls for s in annotated)
                                or any(s.gt_centres_m for s in annotated))


def _res_order(item) -> tuple:
    k = item[0]
    try:
        w, h = (int(x) for x in k.split("x"))
        return (0, w * h)
    except ValueError:
        return (1, 0)


def detection_stats(records: Sequence[dict], references: Sequence | None = None) -> dict:
    """Statistics of detections on scenes without ground truth: how many scenes have one, the
    count per scene, the best score, the best detection's radius (m) where the method estimates
    it, and, where a scene carries a reference centre (another tool's fit, not ground truth), the
    distance (m) of the best detection from it."""
    n = len(records)
    counts = np.asarray([len(r["detections"]) for r in records])
    best = [max(r["detections"], key=lambda d: d["score"]) if r["detections"] else None for r in records]
    top = [b["score"] for b in best if b is not None]
    radii = np.asarray([b["radius_m"] for b in best if b is not None and b.get("radius_m") is not None], np.float64)
    refs = list(references) if references is not None else [None] * n
    dist = np.asarray([np.linalg.norm(np.asarray(b["center_m"]) - np.asarray(ref)) for b, ref in zip(best, refs)
                       if b is not None and ref is not None and b.get("center_m") is not None], np.float64)
    # a reference centre is 3D: 2D methods (no centre_m) are not compared with it
    is_3d = any(b is not None and b.get("center_m") is not None for b in best)
    n_ref = sum(1 for ref in refs if ref is not None) if is_3d else 0
    out = {"n_scenes": n, "scenes_with_detection": int(np.count_nonzero(counts)),
           "fraction_with_detection": float(np.count_nonzero(counts) / n) if n else None,
           "detections_per_scene": float(counts.mean()) if n else None,
           "top_score_median": float(np.median(top)) if top else None,
           "radius_m_median": float(np.median(radii)) if radii.size else None,
           "radius_m_p05": float(np.percentile(radii, 5)) if radii.size else None,
           "radius_m_p95": float(np.percentile(radii, 95)) if radii.size else None,
           "n_radii": int(radii.size), "n_reference": n_ref}
    if n_ref:
        out["reference_distance_m_median"] = float(np.median(dist)) if dist.size else None
        out["within_5cm_of_reference"] = float(np.count_nonzero(dist <= 0.05) / n_ref)
    return out


def metrics_json(per_dataset: dict[str, Sequence[ScoredSet]]) -> dict:
    """{method output: {dataset: metrics}}."""
    out: dict = {}
    for label, sets in per_dataset.items():
        for s in sets:
            out.setdefault(s.output, {})[label] = s.metrics
    return json_safe(out)


def sensor_rows_by_method(metrics: dict, label: str) -> dict[str, list[dict]]:
    """{method: its per-cell rows on ``label``} from metrics.json's content (``metrics_json``): the
    exact-rule sets (a 3D method's paper-circle set repeats its 3D figures), in the file's order."""
    return {name: by[label]["sensor_cells"] for name, by in metrics.items()
            if not name.endswith(PAPER_CIRCLE) and (by.get(label) or {}).get("sensor_cells")
            and not (by[label].get("scenes_refused") and by[label]["scenes_refused"] == by[label].get("n_scenes_run"))}
