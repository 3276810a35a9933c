"""The transfer table: how far each method's figures carry from the analytic sensor model to the
physical one (``datasets.stereo``), preset by preset.

A stereo dataset names the analytic preset it repeats (dataset.json's ``twin_of``: the same
families, sizes and resolutions, other seeds); every such pair in one evaluation gets a row per
method with its Table 3 figures and its 3D found rate (``metrics3d.found_far_rule``) on both, and
the drop (analytic minus stereo: positive where the method loses on the stereo model).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

from spherebench.datasets import inout
from spherebench.eval.bench.tables import Table, fmt

#: The figures compared, as (metrics key, column heading); "found" is the 3D found rate.
FIGURES = (("mAP", "mAP"), ("mAP50", "mAP.50"), ("mAP75", "mAP.75"), ("found", "3D found"))


def _meta(data_dir: Path) -> dict:
    return inout.read_dataset_meta(data_dir) if (Path(data_dir) / "dataset.json").is_file() else {}


def transfer_pairs(data_dirs: Mapping[str, Path]) -> list[tuple[str, str]]:
    """(analytic label, stereo label) of every stereo dataset whose ``twin_of`` preset is the
    preset of another dataset of the evaluation, in the order of ``data_dirs``."""
    metas = {label: _meta(d) for label, d in data_dirs.items()}
    pairs = []
    for label, meta in metas.items():
        if meta.get("sensor_model") not in (None, "analytic") or meta.get("sensor_overrides") or not meta.get("preset"):
            continue
        twins = [t for t, m in metas.items() if m.get("twin_of") == meta["preset"] and m.get("sensor_model") == "stereo"]
        pairs += [(label, t) for t in twins]
    return pairs


def _value(metrics: dict, key: str):
    if key == "found":
        return (metrics.get("3d") or {}).get("found_far_rule")
    return metrics.get(key)


def transfer_rows(pairs: Sequence[tuple[str, str]], sets_by: Mapping[str, Sequence]) -> list[dict]:
    """One row per pair and method output scored on both datasets (a 3D method's exact-silhouette
    row only: the 3D found rate does not depend on the 2D rule): {"output", "analytic", "stereo",
    key: (analytic value, stereo value, drop)} for each key of FIGURES (None where unknown)."""
    rows = []
    for a, b in pairs:
        on_b = {s.output: s for s in sets_by[b] if s.rule != "paper"}
        for s in sets_by[a]:
            t = on_b.get(s.output)
            if t is None or s.metrics.get("mAP") is None or t.metrics.get("mAP") is None:
                continue
            row = {"output": s.output, "analytic": a, "stereo": b}
            for key, _ in FIGURES:
                va, vb = _value(s.metrics, key), _value(t.metrics, key)
                row[key] = (va, vb, va - vb if va is not None and vb is not None else None)
            rows.append(row)
    return rows


def transfer_table(rows: Sequence[dict]) -> Table | None:
    """The transfer table of ``transfer_rows``."""
    if not rows:
        return None
    columns = ["method", "analytic preset", "stereo twin"]
    for _, head in FIGURES:
        columns += [f"{head} analytic", f"{head} stereo", f"{head} drop"]
    cells = [[r["output"], f"`{r['analytic']}`", f"`{r['stereo']}`"]
             + [fmt(x) for key, _ in FIGURES for x in r[key]] for r in rows]
    return Table(name="transfer", title="Transfer: each method on the analytic sensor model and on its stereo twin",
                 columns=columns, rows=cells, notes=[
                     "The stereo twin repeats the analytic preset's families, sizes and resolutions with other seeds, "
                     "its depth made by the physical sensor model (both infrared images rendered, semi-global "
                     "matching; docs/data.md). Drop: analytic minus stereo (positive: the method loses on the "
                     "stereo model).",
                     "3D found: the share of balls whose matched detection (one radius gate, best score first) lies "
                     "within 2 cm of the true centre, or 3 cm for a centre deeper than 3 m; 2D methods have none.",
                     "A 3D method's row is its exact-silhouette circle; the paper's projection rule moves its 2D "
                     "figures, not its detections (Table 3 of each preset)."])


def transfer_reading(rows: Sequence[dict]) -> dict[str, list[str]]:
    """{stereo label: one sentence per pair}: every method's mAP and 3D found rate on the analytic
    preset and on its twin, from the rows (no number typed in by hand)."""
    out: dict[str, list[str]] = {}
    for pair in dict.fromkeys((r["analytic"], r["stereo"]) for r in rows):
        mine = [r for r in rows if (r["analytic"], r["stereo"]) == pair]
        parts = []
        for r in mine:
            a, s, _ = r["mAP"]
            text = f"{r['output']} {a:.3f} -> {s:.3f}"
            fa, fs, _ = r["found"]
            if fa is not None and fs is not None:
                text += f" (3D found {100 * fa:.1f} % -> {100 * fs:.1f} %)"
            parts.append(text)
        out.setdefault(pair[1], []).append(
            f"`{pair[1]}` is `{pair[0]}` through the stereo sensor model (other seeds); circle mAP from the analytic "
            "preset to its twin: " + "; ".join(parts) + " (the transfer table and figure).")
    return out
