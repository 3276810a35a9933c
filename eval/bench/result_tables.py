"""The results' tables, from scored prediction sets (``eval.bench.scoring``): Table 3 beside the
paper's numbers, per scene family, per sensor level and range band, the 3D metrics, the timings,
Table 2, and the detection statistics of unannotated scenes (each a ``tables.Table``).
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from spherebench.eval.bench.paper_numbers import PAPER_TABLE3
from spherebench.eval.bench.scoring import ScoredSet, not_run
from spherebench.eval.bench.tables import Table, fmt, rule_label
from spherebench.eval.metrics.metrics3d import DISTANCE_BANDS_M, MATCH_GATE_M, band_name
from spherebench.eval.metrics.sensor_grid import level_label


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
    band_names = [band_name(b) for b in DISTANCE_BANDS_M]
    balls_in = {}
    for s in sets:
        d = s.metrics.get("3d")
        if not d or s.rule == "paper":  # the 3D figures do not depend on the 2D rule
            continue
        ce, re_ = d["centre_error_m"], d["radius_error_m"]
        own = _estimates_radius(s)
        bands = d.get("found_by_band") or {}
        balls_in = {b: v["balls"] for b, v in bands.items()} or balls_in  # the same balls for every method
        rows.append([s.method, d["n_gt"], fmt(d.get("within_1cm")), fmt(d.get("within_2cm")),
                     fmt(d.get("within_5cm"))]
                    + [fmt(bands[b]["found"]) if bands.get(b, {}).get("balls") else "–" for b in band_names]
                    + [fmt(ce.get("median"), 1, 1000), fmt(ce.get("rmse"), 1, 1000),
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
                 columns=["method", "balls", "matched <= 1 cm", "<= 2 cm", "<= 5 cm"]
                         + [f"found {b} ({balls_in.get(b, 0)})" for b in band_names] + ["centre error median (mm)",
                          "RMSE (mm)", "p95 (mm)", "radius error median (mm)", "radius |error| median (mm)",
                          "median radius of all detections (m)", "false detections",
                          "detections on negative scenes", "note"], rows=rows,
                 notes=([reference] if reference else []) + [
                        f"A prediction matches the nearest unmatched {true} ball centre within one radius "
                        f"({gate:g} m), best score first; centre-error statistics over the matched balls; detection "
                        "rates over all balls (missed balls count as failures).",
                        "Found per band of surface distance |c| - R (balls in brackets): the matched detection within "
                        "2 cm of the centre, 3 cm for a centre deeper than 3 m. The 3D figures are at each method's "
                        "operating point (improved: score >= 0.67). `own-pixel-fit` is the ceiling of the data, not a "
                        "detector: a sphere of radius R fitted from each ball's true centre on its own pixels.",
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
