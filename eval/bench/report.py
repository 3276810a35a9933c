"""Scoring prediction sets and writing the benchmark's results: metrics, tables, README, provenance.

``score_set`` turns one prediction set (``eval.bench.cache``, written by ``eval.bench.tasks``) into the
figures of the tables: COCO metrics with circle IoU (overall and per scene family), 3D metrics for
methods with a 3D centre, and the time per frame. ``write_results`` writes, under an output folder:

    metrics.json          {method: {dataset: {...}}}, every figure of the tables
    tables/*.csv, *.md    (``eval.bench.tables``, written by pandas) Table 3 per dataset (beside the
                          paper's reported numbers; beside another evaluation's with ``beside``,
                          ``eval.bench.recorded``), per-family mAP, 3D metrics, timings, Table 2,
                          detection statistics of unannotated data
    figures/*.png         (``eval.bench.figures``)
    README.md             the tables, the figures, and a reading of them
    provenance.json       commit, package versions, seeds, configurations, machine, date

Every file is written atomically, and the tables and figures as whole folders (built under a
temporary name, then swapped in), so an interrupted run never leaves a half-written table.
"""

from __future__ import annotations

import contextlib
import json
import shutil
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np

from spherebench.datasets import inout
from spherebench.errors import SphereBenchError
from spherebench.eval.bench import figures as figs
from spherebench.eval.bench import recorded, transfer
from spherebench.eval.bench.cache import read_predictions
from spherebench.eval.bench.paper_numbers import PAPER_TABLE2, PAPER_TABLE3
from spherebench.eval.bench.registry import PAPER_CIRCLE
from spherebench.eval.bench.tables import Table, fmt, rule_label
from spherebench.eval.bench.tasks import SceneInfo
from spherebench.eval.metrics.coco_eval import evaluate_circles, load_ground_truth, scalar_metrics
from spherebench.eval.metrics.metrics3d import MATCH_GATE_M, found_far_rule, match_scene, summarize_3d
from spherebench.eval.metrics.sensor_grid import (GRID_AXES, RANGE_BANDS_M, band_label, band_of, detection_rates, grid_key,
                                                  grid_rows, level_label, map50_by_group, surface_distance_m)
from spherebench.provenance import json_safe

#: The CircleNet methods in the reading, with what each one is (``registry.CIRCLENET_MODELS``).
CIRCLENET_READING = {"circlenet": "`circlenet` (half-width ResNet-18, CPU-trained)",
                     "circlenet-analytic": "`circlenet-analytic` (the same, trained on the analytic `train` alone)",
                     "circlenet-full": "`circlenet-full` (ResNet-18 at its own widths, GPU-trained)",
                     "circlenet-hg": "`circlenet-hg` (2-stack hourglass, GPU-trained)"}

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
    gt = None
    if run_images and coco_gt.get("annotations") is not None:
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
    ball_errors = None
    if meta["kind"] == "3d" and _centres_known(scenes):
        matches, ball_errors, gates = [], [], []
        for r in records:
            s = by_id.get(r["scene_id"])
            if s is None or not s.annotated or len(s.gt_centres_m) != s.n_balls:
                continue
            dets = r["detections"]
            pc = np.asarray([d["center_m"] for d in dets], np.float64).reshape(-1, 3)
            ps = np.asarray([d["score"] for d in dets], np.float64)
            pr = np.asarray([np.nan if d.get("radius_m") is None else d["radius_m"] for d in dets], np.float64)
            gate = max(s.gt_radii_m) if s.gt_radii_m else MATCH_GATE_M  # one radius of the scene's ball
            gates.append(gate)
            matches.append(match_scene(pc, ps, s.gt_centres_m, gate_m=gate, pred_radii_m=pr,
                                       gt_radii_m=s.gt_radii_m))
            ball_errors.append((s, matches[-1].centre_error_m))
        if matches:
            m["3d"] = json_safe(summarize_3d(matches))
            m["3d"]["gate_m"] = float(max(gates))
            depths = np.concatenate([np.asarray(s.gt_centres_m, np.float64).reshape(-1, 3)[:, 2] for s, _ in ball_errors])
            m["3d"]["found_far_rule"] = json_safe(found_far_rule(np.concatenate([e for _, e in ball_errors]), depths))
            m["3d"]["scenes_without_centre"] = sum(1 for s in scenes if s.annotated and len(s.gt_centres_m) != s.n_balls)
            out.distance_m = np.concatenate([mm.gt_distance_m for mm in matches])
            out.centre_error_m = np.concatenate([mm.centre_error_m for mm in matches])
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
        m["unannotated"] = detection_stats(unannotated, [by_id[r["scene_id"]].reference_centre_m for r in unannotated])
    errors = Counter(r["error"] for r in records if r.get("error"))
    if errors:
        m["scenes_refused"] = sum(errors.values())
        m["refused_reason"] = errors.most_common(1)[0][0]
    return out


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


# --------------------------------------------------------------------------- tables

def table3(label: str, sets: Sequence[ScoredSet], with_paper: bool = True) -> Table:
    """Table 3: mAP, mAP.50, mAP.75 (and mAR) per prediction set, the paper's reported rows below."""
    rows = [[s.output, rule_label(s.kind, s.rule), fmt(s.metrics.get("mAP")), fmt(s.metrics.get("mAP50")),
             fmt(s.metrics.get("mAP75")), fmt(s.metrics.get("mAR")), s.metrics.get("n_images", "–"),
             s.note or ""] if not not_run(s) else
            [s.output, rule_label(s.kind, s.rule), "not run", "–", "–", "–", s.metrics.get("n_images", "–"),
             f"not run ({not_run(s)})"] for s in sets if "mAP" in s.metrics]
    notes = ["COCO protocol with circle IoU (CircleNet's): AP over IoU 0.50:0.05:0.95 (mAP), at 0.50 and 0.75; "
             "101-point interpolation, maxDets 1000, circle area = pi r^2.",
             "3D methods give two rows from one detection run: the circle of the exact silhouette (the ground "
             "truth's rule: smallest enclosing circle) and the paper's projection (centre and a point R to its left)."]
    if with_paper:
        for name, a, b, c in PAPER_TABLE3:
            rows.append([f"*{name}*", "(paper, Table 3)", f"*{a:.3f}*", f"*{b:.3f}*", f"*{c:.3f}*", "", "200 (theirs)",
                         "not measured here: the paper's own images, which are not public"])
        notes.append("Rows in italics are the numbers printed in the paper (Table 3), measured on its own 200 "
                     "hand-masked images; they are shown for reference, not reproduced here.")
    return Table(name=f"table3_{label}", title=f"Table 3 on `{label}`: circle mAP",
                 columns=["method", "2D rule", "mAP", "mAP.50", "mAP.75", "mAR", "images", "note"], rows=rows,
                 notes=notes)


def family_table(label: str, sets: Sequence[ScoredSet]) -> Table | None:
    fams = sorted({f for s in sets for f in s.metrics.get("families", {})})
    if not fams:
        return None
    rows = []
    for s in sets:
        if "families" not in s.metrics:
            continue
        row = [s.output]
        for f in fams:
            v = s.metrics["families"].get(f, {})
            row.append(f"{fmt(v.get('mAP50'))} / {fmt(v.get('mAP'))}")
        rows.append(row)
    counts = []
    for f in fams:
        v = next((s.metrics["families"][f] for s in sets if f in s.metrics.get("families", {})), {})
        counts.append(f"{f}: {v.get('n_images')} images, {v.get('n_gt')} balls")
    return Table(name=f"families_{label}", title=f"Per scene family on `{label}`: mAP.50 / mAP",
                 columns=["method"] + fams, rows=rows,
                 notes=["Each cell: mAP.50 / mAP (.50:.95). A family without any basketball (negatives) has no AP "
                        "('–'): its false positives lower the other families' precision only in the overall figure.",
                        "; ".join(counts) + "."])


def _found(r: dict) -> str:
    """'0.984 (63/64)' of a sensor row's 3D detection rate, '–' without one."""
    if r.get("within_2cm") is None:
        return "–"
    return f"{fmt(r['within_2cm'])} ({r['found_2cm']}/{r['n_balls']})"


def sensor_table(label: str, sets: Sequence[ScoredSet]) -> Table | None:
    """Per subpixel and range band, pooled over the grid's other axes: each method's 3D detection rate
    within 2 cm (found / balls) and mAP.50 (``sensor_levels``; the figure splits the other axes)."""
    rows, bands = [], []
    for s in sets:
        levels = s.metrics.get("sensor_levels")
        if not levels or s.rule == "paper" or not_run(s):
            continue
        bands = bands or list(dict.fromkeys(r["band"] for r in levels))
        for sub in dict.fromkeys(r["subpixel"] for r in levels):
            by_band = {r["band"]: r for r in levels if r["subpixel"] == sub}
            rows.append([s.method, level_label(sub)] + [_found(by_band.get(b, {})) for b in bands]
                        + [fmt(by_band.get(b, {}).get("mAP50")) for b in bands])
    if not rows:
        return None
    return Table(name=f"sensor_{label}", title=f"Per sensor noise level and range band on `{label}`",
                 columns=["method", "subpixel (px)"] + [f"matched <= 2 cm, {b}" for b in bands]
                 + [f"mAP.50, {b}" for b in bands], rows=rows,
                 notes=["Each subpixel level pools its cells over noise correlation (none, 1 px) and low-texture "
                        "dropouts (off, on); the robustness figure shows the cells apart. Bands: the ball's true "
                        "distance to its nearest surface.",
                        "Matched <= 2 cm: balls whose matched detection (`match_scene` of `eval/metrics/metrics3d.py`) is "
                        "within 2 cm of the true centre, over the band's balls. mAP.50: COCO AP at circle IoU 0.50 over the level's images, the balls of other bands "
                        "being COCO's ignored ground truth (a detection matched to one counts nowhere); a detection "
                        "matched to no ball is a false positive in every band.",
                        "Per-cell figures (all three axes) are in metrics.json under `sensor_cells`."])


def _estimates_radius(s: ScoredSet) -> bool:
    return any(d.get("radius_m") is not None for r in s.scenes for d in r["detections"])


def _median_radius(s: ScoredSet) -> float | None:
    radii = [d["radius_m"] for r in s.scenes for d in r["detections"] if d.get("radius_m") is not None]
    return float(np.median(radii)) if radii else None


def metrics3d_table(label: str, sets: Sequence[ScoredSet], reference: str | None = None) -> Table | None:
    """The 3D metrics of every 3D method (one row per detection run). reference: a note on what the
    centres are when they are not a simulator's true centres (a recording's mask fits), or None."""
    rows = []
    for s in sets:
        d = s.metrics.get("3d")
        if not d or s.rule == "paper":  # the 3D figures do not depend on the 2D rule
            continue
        ce, re_ = d["centre_error_m"], d["radius_error_m"]
        own = _estimates_radius(s)
        rows.append([s.method, d["n_gt"], fmt(d.get("within_1cm")), fmt(d.get("within_2cm")),
                     fmt(d.get("within_5cm")), fmt(ce.get("median"), 1, 1000), fmt(ce.get("rmse"), 1, 1000),
                     fmt(ce.get("p95"), 1, 1000),
                     fmt(re_.get("median"), 1, 1000) if own else "(R fixed)",
                     fmt(re_.get("median_abs"), 1, 1000) if own else "–",
                     fmt(_median_radius(s), 3) if own else "(R fixed)",
                     d["false_detections"],
                     f"{d['negative_detections']} in {d['n_negative_scenes']}" if d["n_negative_scenes"] else "–",
                     s.note or ""])
    if not rows:
        return None
    gate = next((s.metrics["3d"].get("gate_m") for s in sets if s.metrics.get("3d")), None) or MATCH_GATE_M
    true = "reference" if reference else "true"
    return Table(name=f"metrics3d_{label}", title=f"3D metrics on `{label}`" + (
                     " against its reference centres" if reference else ""),
                 columns=["method", "balls", "matched <= 1 cm", "<= 2 cm", "<= 5 cm", "centre error median (mm)",
                          "RMSE (mm)", "p95 (mm)", "radius error median (mm)", "radius |error| median (mm)",
                          "median radius of all detections (m)", "false detections",
                          "detections on negative scenes", "note"], rows=rows,
                 notes=([reference] if reference else []) + [
                        f"A prediction matches the nearest unmatched {true} ball centre within one radius "
                        f"({gate:g} m), best score first; centre-error statistics over the matched balls; detection "
                        "rates over all balls (missed balls count as failures).",
                        "Radius error: the method's own radius estimate minus R over the matched balls (improved: "
                        "its free-radius size check; pyransac3d: its fitted radius; '–' when none matched); the "
                        "paper's pipeline has R fixed. The median radius is over every detection, matched or not."])


def timing_table(per_dataset: dict[str, Sequence[ScoredSet]]) -> Table:
    rows = []
    for label, sets in per_dataset.items():
        for s in sets:
            if s.rule == "paper" or not_run(s):  # same run as the exact-rule row; a refusal's time is none
                continue
            for res, st in s.metrics.get("ms_by_resolution", {}).items():
                rows.append([s.method, label, res, st["n"], fmt(st["median"], 1), fmt(st["p95"], 1)])
    return Table(name="timings", title="Time per frame (ms, one thread)", columns=[
        "method", "dataset", "resolution", "frames", "median ms", "p95 ms"], rows=rows,
        notes=["Measured around the detection call only (no file reading), in worker processes pinned to one "
               "thread each (numba, BLAS/OpenMP, OpenCV, ONNX Runtime), two workers at a time on the machine "
               "named in provenance.json; a 3D method's time includes both of its 2D projections."])


def table2_table(rows: Sequence[dict]) -> Table:
    out = []
    for r in rows:
        p = r.get("paper") or {}
        out.append([r["scene"], fmt(r["z"], 1), r["iterations"], fmt(r.get("rmse_ransac"), 6),
                    fmt(r.get("rmse_ransac_filtered"), 6), fmt(r.get("rmse_barycentre"), 6),
                    fmt(p.get("rmse_ransac"), 6), fmt(p.get("rmse_ransac_filtered"), 6),
                    fmt(p.get("rmse_barycentre"), 6), r.get("n_inliers", "–"), r.get("n_filtered", "–"),
                    fmt(r.get("error_ransac_m"), 1, 1000), fmt(r.get("error_barycentre_m"), 1, 1000),
                    fmt(r.get("error_refined_m"), 1, 1000), fmt(r.get("error_improved_m"), 1, 1000)])
    return Table(name="table2", title="Table 2 on `paper` (E1, E2, E3): RMSE (m) before and after the z-score filter",
                 columns=["scene", "z", "iterations", "RMSE RANSAC", "RMSE RANSAC centre, z-filtered points",
                          "RMSE barycentre", "paper: RMSE RANSAC", "paper: RANSAC centre, filtered",
                          "paper: barycentre", "inliers", "kept", "centre error RANSAC (mm)",
                          "centre error barycentre (mm)", "centre error LSQ refinement (mm)",
                          "centre error improved detector (mm)"], rows=out,
                 notes=["RMSE(P, c) = sqrt(mean over p in P of (||p - c|| - R)^2), R = 0.12 m: the RMS distance of the "
                        "points from the sphere of radius R about c (the paper does not define its RMSE). RANSAC: "
                        "the points assigned to the chosen candidate (R +/- eps) about its centre; then the points "
                        "kept by the z-score filter (|z| <= threshold on the point-to-centre distance) about the same "
                        "centre; then about their barycentre.",
                        "Columns 'paper:' are the values printed in the paper's Table 2 (its own recordings; only "
                        "E1 at z 3, 2, 1.5 and E2, E3 at z 1.5 are printed).",
                        "Centre errors use the simulator's true centre: RANSAC centre, barycentre, least squares of "
                        "(||p - c|| - R) with R fixed over the same kept points, and the whole improved detector. "
                        "Each scene's thresholds filter one and the same RANSAC draw (same seed). '–': no sphere found."])


def detections_table(label: str, sets: Sequence[ScoredSet]) -> Table | None:
    rows = []
    for s in sets:
        u = s.metrics.get("unannotated")
        if not u or s.rule == "paper":
            continue
        if not_run(s):
            rows.append([s.method, u["n_scenes"], f"not run ({not_run(s)})", *["–"] * 8])
            continue
        rows.append([s.method, u["n_scenes"], u["scenes_with_detection"], fmt(u["detections_per_scene"], 2),
                     fmt(u["top_score_median"], 3), fmt(u["radius_m_median"], 4), fmt(u["radius_m_p05"], 4),
                     fmt(u["radius_m_p95"], 4),
                     f"{fmt(u.get('within_5cm_of_reference'), 2)} of {u['n_reference']}" if u["n_reference"] else "–",
                     fmt(u.get("reference_distance_m_median"), 3), fmt(s.metrics["ms"]["median"], 1)])
    if not rows:
        return None
    return Table(name=f"detections_{label}", title=f"Detections on the unannotated scenes of `{label}`",
                 columns=["method", "scenes", "scenes with a detection", "detections per scene", "median top score",
                          "median radius (m)", "radius p5 (m)", "radius p95 (m)", "within 5 cm of reference",
                          "median distance to reference (m)", "median ms"], rows=rows,
                 notes=["No ground truth: these are counts, not accuracies. Radius: the best detection's own radius "
                        "estimate, where the method makes one.",
                        "Reference: a centre shipped with the recording (e.g. the dataset authors' own fit), where "
                        "there is one; agreement with it is not accuracy."])


# --------------------------------------------------------------------------- writing

#: A results folder is ours if it has the owner marker or (written before the marker) provenance.json.
RESULTS_KIND, RESULTS_LEGACY_FILE = "results", "provenance.json"
is_results_dir = inout.owned_by_kind(RESULTS_KIND, RESULTS_LEGACY_FILE)


def claim_results_dir(out: str | Path) -> Path:
    """``out`` as a results folder (new, empty or a previous one of ours, not inside a dataset), or a
    one-line error."""
    inout.check_not_in_dataset(out)
    return inout.claim_output_dir(out, RESULTS_KIND, RESULTS_LEGACY_FILE)


#: What a rerun of an evaluation reuses: finished prediction sets, the Hough tuning and its training
#: subset, the oracle's balls.
RESULTS_RESUMABLE = ("predictions", "hough_config.json", "train-hough", "oracle_robust.json")


def results_run(out: str | Path):
    """claim_results_dir for the length of an evaluation (``inout.output_run``): a failed or stopped
    run removes a folder it made and holds nothing a rerun reuses (RESULTS_RESUMABLE), and says what
    it kept otherwise."""
    return inout.output_run(out, RESULTS_KIND, RESULTS_RESUMABLE, legacy=RESULTS_LEGACY_FILE)


def _in_results_dir(folder: Path) -> bool:
    """tables/ and figures/ are replaced whole, only inside a results folder of ours."""
    return is_results_dir(folder.parent)


#: In tables/ and figures/: the names of the files the report wrote there, the only ones a rerun replaces.
WRITTEN_LIST = ".spherebench-files.json"


@contextlib.contextmanager
def report_folder(folder: Path):
    """tables/ or figures/ built anew in a temporary folder that then replaces ``folder`` (atomic):
    the files the report wrote there before (WRITTEN_LIST; a folder without the list: the names it
    writes now) are replaced, anything else (a user's table, another tool's sub-folder such as
    `annotate --sheet`'s) is carried over, and one clashing with a name the report writes now is
    refused, naming it. Yields (the temporary folder, a list that holds the carried names after)."""
    kept: list[str] = []
    with inout.atomic_directory(folder, _in_results_dir) as tmp:
        yield tmp, kept
        ours = sorted(p.name for p in tmp.iterdir() if not p.name.startswith("."))
        before = set(ours)
        with contextlib.suppress(OSError, ValueError):
            listed = json.loads((folder / WRITTEN_LIST).read_text())
            before = set(listed) if isinstance(listed, list) else before
        for entry in sorted(folder.iterdir()) if folder.is_dir() else ():
            if entry.name in before or entry.name == WRITTEN_LIST:
                continue
            if (tmp / entry.name).exists():
                raise SphereBenchError(f"{entry} was not written by evaluate and this report writes that name: move "
                                       f"it out of {folder} (nothing was replaced)")
            if entry.is_dir() and not entry.is_symlink():
                shutil.copytree(entry, tmp / entry.name, symlinks=True)
            else:
                shutil.copy2(entry, tmp / entry.name, follow_symlinks=False)
            kept.append(entry.name)
        inout.write_json(tmp / WRITTEN_LIST, ours)


def write_tables(folder: Path, tables: Sequence[Table]) -> None:
    """Every table as CSV and Markdown, into ``folder`` (report_folder)."""
    with report_folder(folder) as (tmp, _):
        for t in tables:
            (tmp / f"{t.name}.csv").write_text(t.csv())
            (tmp / f"{t.name}.md").write_text(t.markdown())


def metrics_json(per_dataset: dict[str, Sequence[ScoredSet]]) -> dict:
    """{method output: {dataset: metrics}}."""
    out: dict = {}
    for label, sets in per_dataset.items():
        for s in sets:
            out.setdefault(s.output, {})[label] = s.metrics
    return json_safe(out)


def _get(sets: Sequence[ScoredSet], output: str) -> ScoredSet | None:
    return next((s for s in sets if s.output == output), None)


def _level_rate(levels: Sequence[dict], subpixel, bands: Sequence[str]) -> str:
    """'98.4' (% found within 2 cm) over a subpixel level's rows in ``bands``, '–' without balls."""
    rows = [r for r in levels if r["subpixel"] == subpixel and r["band"] in bands and r.get("found_2cm") is not None]
    n = sum(r["n_balls"] for r in rows)
    return f"{100 * sum(r['found_2cm'] for r in rows) / n:.1f}" if n else "–"


def robust_reading(label: str, sets: Sequence[ScoredSet], default: Sequence[ScoredSet] | None) -> list[str]:
    """The reading of a grid preset (``robust``): the best mAP, and the improved detector's rate and the
    best 2D method's mAP.50 per subpixel level (pooled over the other axes), as the figure shows them."""
    out = []
    scored = [s for s in sets if s.metrics.get("mAP") is not None and not not_run(s)]
    if scored:
        best = max(scored, key=lambda s: s.metrics["mAP"])
        out.append(f"On `{label}` (`default`'s scenes over a grid of sensor conditions: subpixel noise, its "
                   f"correlation, low-texture dropouts) the best circle mAP is {best.output}'s, "
                   f"{best.metrics['mAP']:.3f} (mAP.50 {best.metrics['mAP50']:.3f}).")
    near = [band_label(b) for b in RANGE_BANDS_M if b[1] <= 2.0]
    far = [band_label(b) for b in RANGE_BANDS_M if b[0] >= 2.0]
    i = _get(sets, "improved")
    if i is not None and i.metrics.get("3d") and i.metrics.get("sensor_levels"):
        levels = i.metrics["sensor_levels"]
        subs = list(dict.fromkeys(r["subpixel"] for r in levels))
        d = i.metrics["3d"]
        ref = _get(default or [], "improved")
        ref_txt = (f" ({100 * ref.metrics['3d']['within_2cm']:.1f} % on `default`)"
                   if ref is not None and ref.metrics.get("3d") else "")
        out.append(f"On `{label}`, `improved` finds {100 * d['within_2cm']:.1f} % of the balls within 2 cm{ref_txt}, "
                   f"with {d['false_detections']} false detections in {d['n_scenes']} scenes. By subpixel "
                   f"{' / '.join(level_label(v) for v in subs)} px (pooled over correlation and dropouts): "
                   f"{' / '.join(_level_rate(levels, v, near) for v in subs)} % of the balls within 2 m of the camera, "
                   f"{' / '.join(_level_rate(levels, v, far) for v in subs)} % at 2-3 m; the robustness figure splits "
                   "the cells.")
    nets = [s for s in scored if s.kind == "2d" and s.metrics.get("sensor_levels")]
    if nets:
        best2d = max(nets, key=lambda s: s.metrics["mAP50"])
        levels = best2d.metrics["sensor_levels"]
        subs = list(dict.fromkeys(r["subpixel"] for r in levels))
        per = {b: " / ".join(fmt(next((r["mAP50"] for r in levels if r["subpixel"] == v and r["band"] == b), None))
                             for v in subs) for b in (near + far)}
        out.append(f"The best 2D method on `{label}` at IoU 0.50, {best2d.output} (mAP.50 "
                   f"{best2d.metrics['mAP50']:.3f}), scores mAP.50 " + "; ".join(f"{v} at {b}" for b, v in per.items())
                   + " over the same subpixel levels.")
    return out


def _best_map(label: str, scored: Sequence[ScoredSet]) -> str:
    """'On `label` the best circle mAP is X's, 0.660 (mAP.50 0.943)', naming every set that ties it
    to three decimals."""
    best = max(scored, key=lambda s: s.metrics["mAP"])
    ties = [s for s in scored if s is not best and f"{s.metrics['mAP']:.3f}" == f"{best.metrics['mAP']:.3f}"]
    text = (f"On `{label}` the best circle mAP is {best.output}'s, {best.metrics['mAP']:.3f} "
            f"(mAP.50 {best.metrics['mAP50']:.3f})")
    if ties:
        text += "; " + ", ".join(f"{s.output}'s is the same to three decimals (mAP.50 {s.metrics['mAP50']:.3f})"
                                 for s in ties)
    return text + "."


def reading(per_dataset: dict[str, Sequence[ScoredSet]], t2: Sequence[dict] | None, skipped: dict[str, str],
            about: dict[str, list[str]] | None = None) -> list[str]:
    """A short reading of the results, computed from them (no number here is typed in by hand).

    about: {dataset label: sentences said first about it} (what a recorded dataset is, ``eval.bench.recorded``)."""
    out = []
    for label, sets in per_dataset.items():
        out += (about or {}).get(label, [])
        if label in ("default", "hard"):
            continue
        if any(s.metrics.get("sensor_levels") for s in sets):  # a grid preset: read after default and hard
            continue
        scored = [s for s in sets if s.metrics.get("mAP") is not None and not not_run(s)]
        if scored:
            out.append(_best_map(label, scored))
        for s in sets:
            u = s.metrics.get("unannotated")
            if u and s.rule != "paper" and not_run(s):
                out.append(f"`{label}` has no ground truth: {s.method} was not run: it refused "
                           f"{u['n_scenes']}/{u['n_scenes']} scenes ({not_run(s)}).")
            elif u and s.rule != "paper":
                ref = ""
                if u.get("n_reference"):
                    ref = (f"; its best detection lies within 5 cm of the recording's reference centre in "
                           f"{round(u['within_5cm_of_reference'] * u['n_reference'])} of the {u['n_reference']} "
                           "scenes that have one")
                refused = s.metrics.get("scenes_refused")
                if refused:
                    ref += f"; it could not run on {refused} scenes (see the predictions' meta file for why)"
                out.append(f"`{label}` has no ground truth: {s.method} reports a ball in {u['scenes_with_detection']} of "
                           f"{u['n_scenes']} scenes{ref}.")
    default = per_dataset.get("default")
    if default:
        scored = [s for s in default if s.metrics.get("mAP") is not None]
        if scored:
            best = max(scored, key=lambda s: s.metrics["mAP"])
            out.append(f"On `default` (the paper's protocol: 200 scenes, half clean, half cluttered) the best circle "
                       f"mAP is {best.output}'s, {best.metrics['mAP']:.3f} (mAP.50 {best.metrics['mAP50']:.3f}, "
                       f"mAP.75 {best.metrics['mAP75']:.3f}).")
        p = _get(default, "paper" + PAPER_CIRCLE)
        if p is not None and p.metrics.get("mAP") is not None:
            out.append(f"The paper's own pipeline with its own projection rule (`paper+paper-circle`) scores "
                       f"{p.metrics['mAP']:.3f} / {p.metrics['mAP50']:.3f} / {p.metrics['mAP75']:.3f} here, against "
                       f"{PAPER_TABLE3[0][1]:.3f} / {PAPER_TABLE3[0][2]:.3f} / {PAPER_TABLE3[0][3]:.3f} printed in the "
                       "paper. The scenes are not the paper's (its 200 hand-masked images are not public), so the two "
                       "rows share a protocol, not data.")
        i, ip = _get(default, "improved"), _get(default, "improved" + PAPER_CIRCLE)
        if i is not None and ip is not None and i.metrics.get("mAP") is not None and ip.metrics.get("mAP") is not None:
            out.append(f"The 2D rule matters at the strict IoU thresholds: the improved detector's circles score "
                       f"mAP {i.metrics['mAP']:.3f} with the exact silhouette and {ip.metrics['mAP']:.3f} with the "
                       "paper's projection (mAP.75 "
                       f"{i.metrics['mAP75']:.3f} vs {ip.metrics['mAP75']:.3f}); the paper's rule ignores that a "
                       "sphere's outline is an ellipse off the optical axis and that the ground truth is the visible "
                       "mask's enclosing circle.")
        nets = [(name, c) for name, c in ((n, _get(default, n)) for n in CIRCLENET_READING)
                if c is not None and c.metrics.get("mAP") is not None]
        if nets:
            out.append("CircleNet (trained here on the training splits only: its note says which) scores "
                       + "; ".join(f"{c.metrics['mAP']:.3f} / {c.metrics['mAP50']:.3f} / {c.metrics['mAP75']:.3f} "
                                   f"as {CIRCLENET_READING[name]}" for name, c in nets)
                       + f" (paper's CircleNet-HG: {PAPER_TABLE3[1][1]:.3f} / {PAPER_TABLE3[1][2]:.3f} / "
                       f"{PAPER_TABLE3[1][3]:.3f}).")
        if i is not None and i.metrics.get("3d"):
            d = i.metrics["3d"]
            out.append(f"In 3D, `improved` finds {100 * d['within_2cm']:.1f} % of the `default` balls within 2 cm "
                       f"(median centre error {1000 * (d['centre_error_m']['median'] or float('nan')):.1f} mm)"
                       + (f"; `paper` finds {100 * _get(default, 'paper').metrics['3d']['within_2cm']:.1f} %"
                          if _get(default, "paper") is not None and _get(default, "paper").metrics.get("3d") else "")
                       + ".")
    hard = per_dataset.get("hard")
    if hard:
        parts = []
        for s in hard:
            d = s.metrics.get("3d")
            if d and s.rule != "paper" and d.get("n_negative_scenes"):
                parts.append(f"{s.method} {d['negative_detections']}")
        if parts:
            out.append("On `hard`, detections reported on the negative scenes (no basketball; soccer balls, cylinders "
                       "of the ball's radius, box corners): " + ", ".join(parts) + ".")
        scored = [s for s in hard if s.metrics.get("mAP") is not None]
        if scored:
            best = max(scored, key=lambda s: s.metrics["mAP"])
            out.append(f"The best `hard` mAP is {best.output}'s, {best.metrics['mAP']:.3f}; see the per-family table "
                       "for where each method fails.")
    for label, sets in per_dataset.items():
        if label not in ("default", "hard") and any(s.metrics.get("sensor_levels") for s in sets):
            out += robust_reading(label, sets, default)
    if t2:
        e1 = [r for r in t2 if r["scene"] == "E1" and r.get("rmse_barycentre") is not None]
        if e1:
            r = min(e1, key=lambda r: r["z"])
            paper = PAPER_TABLE2.get(("E1", r["z"]))
            direction = "larger" if r["rmse_barycentre"] > r["rmse_ransac"] else "smaller"
            out.append(f"Table 2: on E1 at z {r['z']:g} the barycentre's RMSE is {r['rmse_barycentre']:.4f} m against "
                       f"{r['rmse_ransac']:.4f} m for the RANSAC centre ({direction}"
                       + (f"; the paper printed {paper[2]:.4f} against {paper[0]:.4f}" if paper else "") + "). "
                       f"The true centre error of the barycentre is {1000 * r['error_barycentre_m']:.1f} mm, against "
                       f"{1000 * r['error_ransac_m']:.1f} mm for the RANSAC centre and "
                       f"{1000 * r['error_refined_m']:.2f} mm for the least-squares refinement of the same points "
                       "(R fixed): the barycentre of a visible cap lies inside the ball, toward the camera, so it is "
                       "not the sphere's centre, and its points do not lie on a sphere of radius R about it.")
        missing = sorted({r["scene"] for r in t2 if r.get("rmse_ransac") is None})
        if missing:
            out.append(f"The paper's configuration found no sphere on {', '.join(missing)} ('–' in Table 2).")
    for name, why in skipped.items():
        out.append(f"`{name}` is not in these tables: {why}.")
    return out


def readme(title: str, intro: list[str], per_dataset: dict[str, Sequence[ScoredSet]], tables: Sequence[Table],
           figures: dict[str, str], t2: Sequence[dict] | None, skipped: dict[str, str],
           about: dict[str, list[str]] | None = None) -> str:
    """The results README: intro, the reading (``about``: sentences on a dataset, said first), every
    table, the figures embedded."""
    lines = [f"# {title}", ""] + intro + ["", "## Reading", ""]
    lines += [f"- {s}" for s in reading(per_dataset, t2, skipped, about)] + ["", "## Tables", ""]
    for t in tables:
        lines += [t.markdown(), f"(`tables/{t.name}.csv`, `tables/{t.name}.md`)", ""]
    if figures:
        lines += ["## Figures", ""]
        for caption, rel in figures.items():  # a long caption's first clause is the image's alt text
            lines += ([f"**{caption}**", "", f"![{caption.split(': ')[0]}]({rel})", ""] if rel is not None
                      else [f"- {caption}", ""])  # None: a folder of other figures, named only
    return "\n".join(lines)


def sensor_rows_by_method(metrics: dict, label: str) -> dict[str, list[dict]]:
    """{method: its per-cell rows on ``label``} from metrics.json's content (``metrics_json``): the
    exact-rule sets (a 3D method's paper-circle set repeats its 3D figures), in the file's order."""
    return {name: by[label]["sensor_cells"] for name, by in metrics.items()
            if not name.endswith(PAPER_CIRCLE) and (by.get(label) or {}).get("sensor_cells")
            and not (by[label].get("scenes_refused") and by[label]["scenes_refused"] == by[label].get("n_scenes_run"))}


TRANSFER_CAPTION = ("Transfer from the analytic sensor model to the stereo one: each method's circle mAP (top) and "
                    "3D found rate (bottom) on each analytic preset (solid) and its stereo twin (hatched), the change "
                    "written above")
ROBUSTNESS_CAPTION = ("Robustness on `{label}`: the 3D detection rate (matched centre within 2 cm) and the 2D mAP.50 "
                      "against the sensor's subpixel noise, one panel per range band of the ball's true distance; "
                      "line styles for noise correlation and dropouts; each point one cell of the grid (20 scenes, a "
                      "few balls per band: coarse). mAP.50 per cell and band scores the band's balls, those of other "
                      "bands ignored (COCO's rule); a detection matched to no ball is a false positive in every band")


def write_results(out: Path, per_dataset: dict[str, tuple[Path, dict, Sequence[ScoredSet]]], t2: Sequence[dict] | None,
                  skipped: dict[str, str], prov: dict, title: str, intro: list[str],
                  paper_rows_for: Sequence[str] = ("default", "hard"), figures: bool = True,
                  ceilings: dict[str, dict] | None = None,
                  beside=None) -> dict[str, Path]:
    """Tables, figures, metrics.json, README.md and provenance.json under ``out`` (all atomic).

    per_dataset: {label: (dataset folder, its coco_gt dict, scored sets)}. Returns the paths written.
    ceilings: {label: a per-cell ceiling of the improved detector's 3D rate, {(subpixel,
    correlation, dropouts, band label): rate}}, drawn in the robustness figure
    (``figures.robustness``), e.g. an oracle's; None: none.
    beside: another evaluation (``recorded.Beside``): each dataset's Table 3 is also set beside the
    same methods' on its dataset (``recorded.beside_table``).
    A recorded dataset (``recorded.facts``) gets sentences on what its ground truth is, and its
    3D table and figures say that its centres are references. Sub-folders of figures/ that other
    tools wrote (the annotation review sheets) are kept when figures/ is replaced.
    """
    out = Path(out)
    sets_by = {k: v[2] for k, v in per_dataset.items()}
    facts = {label: recorded.facts(data_dir) for label, (data_dir, _, _) in per_dataset.items()}
    about = {label: recorded.reading(label, f, per_dataset[label][2]) for label, f in facts.items() if f is not None}
    tables: list[Table] = []
    for label, (_, _, sets) in per_dataset.items():
        if any("mAP" in s.metrics for s in sets):
            tables.append(table3(label, sets, with_paper=label in paper_rows_for))
            if beside is not None and beside.label != label:
                t = recorded.beside_table(label, sets, beside)
                if t is not None:
                    tables.append(t)
                    about.setdefault(label, []).extend(recorded.beside_reading(label, sets, beside))
        reference = recorded.reference_note(facts[label]) if facts[label] is not None else None
        for t in (family_table(label, sets), metrics3d_table(label, sets, reference=reference),
                  sensor_table(label, sets), detections_table(label, sets)):
            if t is not None:
                tables.append(t)
    transfer_rows = transfer.transfer_rows(transfer.transfer_pairs({k: v[0] for k, v in per_dataset.items()}), sets_by)
    t = transfer.transfer_table(transfer_rows)
    if t is not None:
        tables.append(t)
        for label, said in transfer.transfer_reading(transfer_rows).items():
            about.setdefault(label, []).extend(said)
    tables.append(timing_table(sets_by))
    if t2:
        tables.append(table2_table(t2))
    metrics = metrics_json(sets_by)
    fig_paths: dict[str, str | None] = {}
    if figures:
        with report_folder(out / "figures") as (tmp, kept):
            for label, (data_dir, coco, sets) in per_dataset.items():
                f = facts[label]
                if any(s.pr50 is not None for s in sets):
                    figs.pr_curves(label, sets, tmp / f"pr_{label}.png")
                    fig_paths[f"Precision-recall on `{label}`"] = f"figures/pr_{label}.png"
                if any(s.distance_m is not None for s in sets):
                    figs.plot_error_vs_distance(label, sets, tmp / f"error_vs_distance_{label}.png",
                                           reference=f is not None)
                    fig_paths[f"Centre error against distance on `{label}`" + (
                        ": against the mask-fit reference centres, not a ground truth" if f is not None else "")] = \
                        f"figures/error_vs_distance_{label}.png"
                if coco.get("images") and any(s.pr50 is not None for s in sets):
                    figs.examples(label, data_dir, sets, coco, tmp / f"examples_{label}.png")
                    colour = f is not None and f["colour"] == f["n_scenes"]
                    fig_paths[f"Examples on `{label}`" + (
                        ": each frame's colour image with its mask's circle (green) and each method's best circle "
                        "with its score; the 2D methods were given the reprojected depth image, not the colour"
                        if colour else "")] = f"figures/examples_{label}.png"
            for label in per_dataset:  # drawn from metrics.json's content: a function of the stage files
                rows = sensor_rows_by_method(metrics, label)
                if rows:
                    ceiling = (ceilings or {}).get(label)
                    figs.robustness(label, rows, tmp / f"robustness_{label}.png", ceiling=ceiling)
                    caption = ROBUSTNESS_CAPTION.format(label=label) + (
                        "; grey markers beside `improved`'s 3D rate: its ceiling (an oracle's)" if ceiling else "")
                    fig_paths[caption] = f"figures/robustness_{label}.png"
            if transfer_rows:
                figs.transfer(transfer_rows, tmp / "transfer.png")
                fig_paths[TRANSFER_CAPTION] = "figures/transfer.png"
            figs.latency(sets_by, tmp / "latency.png")
            fig_paths["Latency per method"] = "figures/latency.png"
        for name in kept:
            link = f"figures/{name}" + ("/" if (out / "figures" / name).is_dir() else "")
            fig_paths[f"[`{link}`]({link}): kept from another tool (not drawn by `evaluate`)"] = None
    write_tables(out / "tables", tables)
    # the summary files together: a failed write leaves the earlier set, never a mix of two runs'
    inout.replace_files({out / "metrics.json": inout.json_bytes(metrics),
                         **({out / "table2.json": inout.json_bytes(json_safe(list(t2)))} if t2 else {}),
                         out / "README.md": readme(title, intro, sets_by, tables, fig_paths, t2, skipped,
                                                   about).encode(),
                         out / "provenance.json": inout.json_bytes(prov)})
    return {"metrics": out / "metrics.json", "tables": out / "tables", "figures": out / "figures",
            "readme": out / "README.md", "provenance": out / "provenance.json"}
