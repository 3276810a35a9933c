"""The reading of the results: sentences computed from the scored sets (no number typed in by hand).

Which method or preset a sentence is about comes from the registries, by role, not by name: the
3D detector, the paper's method and the learned 2D baselines (``registry.ROLE_*``), the preset of
the paper's protocol, the hard one and a sensor grid's (``datasets.presets``), with the words each
registry gives them.
"""

from __future__ import annotations

from typing import Sequence

from spherebench.datasets.presets import PRESET_HARD, PRESET_PROTOCOL, PRESETS, preset_with_role
from spherebench.eval.bench.paper_numbers import PAPER_TABLE2, PAPER_TABLE3
from spherebench.eval.bench.registry import (PAPER_CIRCLE, ROLE_CEILING, ROLE_DETECTOR, ROLE_LEARNED_2D, ROLE_PAPER,
                                             method_with_role,
                                             methods_with_role)
from spherebench.eval.bench.scoring import ScoredSet, not_run
from spherebench.eval.bench.tables import fmt
from spherebench.eval.metrics.sensor_grid import RANGE_BANDS_M, band_label, level_label


def _get(sets: Sequence[ScoredSet], output: str) -> ScoredSet | None:
    return next((s for s in sets if s.output == output), None)


def _level_rate(levels: Sequence[dict], subpixel, bands: Sequence[str]) -> str:
    """'98.4' (% found within 2 cm) over a subpixel level's rows in ``bands``, '–' without balls."""
    rows = [r for r in levels if r["subpixel"] == subpixel and r["band"] in bands and r.get("found_2cm") is not None]
    n = sum(r["n_balls"] for r in rows)
    return f"{100 * sum(r['found_2cm'] for r in rows) / n:.1f}" if n else "–"


def _grid_description(label: str) -> str:
    """What a grid dataset is: its preset's description, else that of the first registered grid preset."""
    own = PRESETS.get(label)
    if own is not None and own.description:
        return own.description
    return next((p.description for p in PRESETS.values() if p.sensor is not None and p.sensor.grid and p.description),
                "a grid of sensor conditions")


def _is_grid(sets: Sequence[ScoredSet]) -> bool:
    """A grid preset's sets (per-cell figures): read after the protocol's and the hard preset's."""
    return any(s.metrics.get("sensor_levels") for s in sets)


def robust_reading(label: str, sets: Sequence[ScoredSet], protocol: Sequence[ScoredSet] | None) -> list[str]:
    """The reading of a grid preset (``robust``): the best mAP, and the 3D detector's rate (beside its rate
    on the protocol's preset) and the best 2D method's mAP.50 per subpixel level (pooled over the other
    axes), as the figure shows them."""
    out = []
    scored = [s for s in sets if s.metrics.get("mAP") is not None and not not_run(s)]
    if scored:
        best = max(scored, key=lambda s: s.metrics["mAP"])
        out.append(f"On `{label}` ({_grid_description(label)}) the best circle mAP is {best.output}'s, "
                   f"{best.metrics['mAP']:.3f} (mAP.50 {best.metrics['mAP50']:.3f}).")
    near = [band_label(b) for b in RANGE_BANDS_M if b[1] <= 2.0]
    far = [band_label(b) for b in RANGE_BANDS_M if b[0] >= 2.0]
    detector = method_with_role(ROLE_DETECTOR)
    i = _get(sets, detector)
    if i is not None and i.metrics.get("3d") and i.metrics.get("sensor_levels"):
        levels = i.metrics["sensor_levels"]
        subs = list(dict.fromkeys(r["subpixel"] for r in levels))
        d = i.metrics["3d"]
        ref = _get(protocol or [], detector)
        ref_txt = (f" ({100 * ref.metrics['3d']['within_2cm']:.1f} % on `{preset_with_role(PRESET_PROTOCOL)}`)"
                   if ref is not None and ref.metrics.get("3d") else "")
        out.append(f"On `{label}`, `{detector}` finds {100 * d['within_2cm']:.1f} % of the balls within 2 cm{ref_txt}, "
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


def dataset_reading(label: str, sets: Sequence[ScoredSet]) -> list[str]:
    """The reading of a dataset of no role (a recording, another simulated preset): its best mAP, and on
    scenes without ground truth what each method reports."""
    out = []
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
    return out


def protocol_reading(label: str, sets: Sequence[ScoredSet]) -> list[str]:
    """The reading of the paper's protocol: the best mAP, the paper's method against the paper's printed
    numbers, the 2D rules of the 3D detector, the learned 2D baselines, the 3D detection rates."""
    out = []
    detector, paper = method_with_role(ROLE_DETECTOR), method_with_role(ROLE_PAPER)
    scored = [s for s in sets if s.metrics.get("mAP") is not None]
    if scored:
        best = max(scored, key=lambda s: s.metrics["mAP"])
        out.append(f"On `{label}` ({PRESETS[label].description}) the best circle "
                   f"mAP is {best.output}'s, {best.metrics['mAP']:.3f} (mAP.50 {best.metrics['mAP50']:.3f}, "
                   f"mAP.75 {best.metrics['mAP75']:.3f}).")
    p = _get(sets, f"{paper}{PAPER_CIRCLE}")
    if p is not None and p.metrics.get("mAP") is not None:
        out.append(f"The paper's own pipeline with its own projection rule (`{paper}{PAPER_CIRCLE}`) scores "
                   f"{p.metrics['mAP']:.3f} / {p.metrics['mAP50']:.3f} / {p.metrics['mAP75']:.3f} here, against "
                   f"{PAPER_TABLE3[0][1]:.3f} / {PAPER_TABLE3[0][2]:.3f} / {PAPER_TABLE3[0][3]:.3f} printed in the "
                   "paper. The scenes are not the paper's (its 200 hand-masked images are not public), so the two "
                   "rows share a protocol, not data.")
    i, ip = _get(sets, detector), _get(sets, f"{detector}{PAPER_CIRCLE}")
    if i is not None and ip is not None and i.metrics.get("mAP") is not None and ip.metrics.get("mAP") is not None:
        out.append(f"The 2D rule matters at the strict IoU thresholds: the improved detector's circles score "
                   f"mAP {i.metrics['mAP']:.3f} with the exact silhouette and {ip.metrics['mAP']:.3f} with the "
                   "paper's projection (mAP.75 "
                   f"{i.metrics['mAP75']:.3f} vs {ip.metrics['mAP75']:.3f}); the paper's rule ignores that a "
                   "sphere's outline is an ellipse off the optical axis and that the ground truth is the visible "
                   "mask's enclosing circle.")
    nets = [(m, c) for m, c in ((m, _get(sets, m.name)) for m in methods_with_role(ROLE_LEARNED_2D))
            if c is not None and c.metrics.get("mAP") is not None]
    if nets:
        out.append("CircleNet (trained here on the training splits only: its note says which) scores "
                   + "; ".join(f"{c.metrics['mAP']:.3f} / {c.metrics['mAP50']:.3f} / {c.metrics['mAP75']:.3f} "
                               f"as {m.description}" for m, c in nets)
                   + f" (paper's CircleNet-HG: {PAPER_TABLE3[1][1]:.3f} / {PAPER_TABLE3[1][2]:.3f} / "
                   f"{PAPER_TABLE3[1][3]:.3f}).")
    if i is not None and i.metrics.get("3d"):
        d, pp = i.metrics["3d"], _get(sets, paper)
        out.append(f"In 3D, `{detector}` finds {100 * d['within_2cm']:.1f} % of the `{label}` balls within 2 cm "
                   f"(median centre error {1000 * (d['centre_error_m']['median'] or float('nan')):.1f} mm)"
                   + (f"; `{paper}` finds {100 * pp.metrics['3d']['within_2cm']:.1f} %"
                      if pp is not None and pp.metrics.get("3d") else "")
                   + ".")
    return out


def hard_reading(label: str, sets: Sequence[ScoredSet]) -> list[str]:
    """The reading of the hard preset: the detections on its negative scenes, and its best mAP."""
    out = []
    parts = []
    for s in sets:
        d = s.metrics.get("3d")
        if d and s.rule != "paper" and d.get("n_negative_scenes"):
            parts.append(f"{s.method} {d['negative_detections']}")
    if parts:
        out.append(f"On `{label}`, detections reported on the negative scenes (no basketball; soccer balls, cylinders "
                   "of the ball's radius, box corners): " + ", ".join(parts) + ".")
    scored = [s for s in sets if s.metrics.get("mAP") is not None]
    if scored:
        best = max(scored, key=lambda s: s.metrics["mAP"])
        out.append(f"The best `{label}` mAP is {best.output}'s, {best.metrics['mAP']:.3f}; see the per-family table "
                   "for where each method fails.")
    return out


def table2_reading(t2: Sequence[dict]) -> list[str]:
    """The reading of Table 2: the barycentre against the RANSAC centre on E1 at its lowest z, and the
    scenes where the paper's configuration found nothing."""
    out = []
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
    return out


def reading(per_dataset: dict[str, Sequence[ScoredSet]], t2: Sequence[dict] | None, skipped: dict[str, str],
            about: dict[str, list[str]] | None = None) -> list[str]:
    """A short reading of the results, computed from them (no number here is typed in by hand): each
    dataset of no role, then the protocol's preset, the hard one, the grid presets, Table 2 and the
    methods skipped.

    about: {dataset label: sentences said first about it} (what a recorded dataset is, ``eval.bench.recorded``)."""
    protocol, hard = preset_with_role(PRESET_PROTOCOL), preset_with_role(PRESET_HARD)
    # a ceiling is read beside the detector in its tables, never as a method that wins
    ceilings = {m.name for m in methods_with_role(ROLE_CEILING)}
    per_dataset = {label: [s for s in sets if s.method not in ceilings] for label, sets in per_dataset.items()}
    out = []
    for label, sets in per_dataset.items():
        out += (about or {}).get(label, [])
        if label not in (protocol, hard) and not _is_grid(sets):
            out += dataset_reading(label, sets)
    if per_dataset.get(protocol):
        out += protocol_reading(protocol, per_dataset[protocol])
    if per_dataset.get(hard):
        out += hard_reading(hard, per_dataset[hard])
    for label, sets in per_dataset.items():
        if label not in (protocol, hard) and _is_grid(sets):
            out += robust_reading(label, sets, per_dataset.get(protocol))
    if t2:
        out += table2_reading(t2)
    for name, why in skipped.items():
        out.append(f"`{name}` is not in these tables: {why}.")
    return out
