"""Writing the benchmark's results: metrics, tables, figures, README, provenance.

``write_results`` writes, under an output folder, from the scored sets (``eval.bench.scoring``):

    metrics.json          {method: {dataset: {...}}}, every figure of the tables
    tables/*.csv, *.md    (``eval.bench.result_tables``, written by pandas) Table 3 per dataset (beside
                          the paper's reported numbers; beside another evaluation's with ``beside``,
                          ``eval.bench.recorded``), per-family mAP, 3D metrics, timings, Table 2,
                          detection statistics of unannotated data, the calibration of the 3D
                          methods' scores (``eval.bench.calibration``)
    figures/*.png         (``eval.bench.figures``)
    README.md             the tables, the figures, and a reading of them (``eval.bench.prose``)
    provenance.json       commit, package versions, seeds, configurations, machine, date

Every file is written atomically, and the tables and figures as whole folders (built under a
temporary name, then swapped in), so an interrupted run never leaves a half-written table.
"""

from __future__ import annotations

import contextlib
import shutil
from pathlib import Path
from typing import Sequence

from spherebench.datasets import inout, outputs
from spherebench.errors import SphereBenchError
from spherebench.eval.bench import figures as figs
from spherebench.eval.bench import calibration, recorded, transfer
from spherebench.eval.bench.prose import reading
from spherebench.eval.bench.registry import ROLE_DETECTOR, method_with_role
from spherebench.eval.bench.result_tables import (detections_table, family_table, metrics3d_table, sensor_table,
                                                  table2_table, table3, timing_table)
from spherebench.eval.bench.scoring import ScoredSet, metrics_json, sensor_rows_by_method
from spherebench.eval.bench.tables import Table
from spherebench.provenance import json_safe
from spherebench.reading import read_json


# --------------------------------------------------------------------------- writing

#: A results folder is ours if it has the owner marker or (written before the marker) provenance.json.
RESULTS_KIND, RESULTS_LEGACY_FILE = "results", "provenance.json"
is_results_dir = outputs.owned_by_kind(RESULTS_KIND, RESULTS_LEGACY_FILE)


def claim_results_dir(out: str | Path) -> Path:
    """``out`` as a results folder (new, empty or a previous one of ours, not inside a dataset), or a
    one-line error."""
    outputs.check_not_in_dataset(out)
    return outputs.claim_output_dir(out, RESULTS_KIND, RESULTS_LEGACY_FILE)


#: What a rerun of an evaluation reuses: finished prediction sets, the Hough tuning and its training
#: subset, the oracle's balls.
RESULTS_RESUMABLE = ("predictions", "hough_config.json", "train-hough", "oracle_robust.json")


def results_run(out: str | Path, inputs=()):
    """claim_results_dir for the length of an evaluation (``outputs.output_run``): a failed or stopped
    run removes a folder it made and holds nothing a rerun reuses (RESULTS_RESUMABLE), and says what
    it kept otherwise. inputs: the folders read (the data), which the results may not lie in or above."""
    return outputs.output_run(out, RESULTS_KIND, RESULTS_RESUMABLE, legacy=RESULTS_LEGACY_FILE, inputs=inputs)


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
    with outputs.atomic_directory(folder, _in_results_dir) as tmp:
        yield tmp, kept
        ours = sorted(p.name for p in tmp.iterdir() if not p.name.startswith("."))
        before = set(ours)
        with contextlib.suppress(SphereBenchError):
            listed = read_json(folder / WRITTEN_LIST)
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


TRANSFER_CAPTION = ("Transfer from the analytic sensor model to the stereo one: each method's circle mAP (top) and "
                    "3D found rate (bottom) on each analytic preset (solid) and its stereo twin (hatched), the change "
                    "written above")
ROBUSTNESS_CAPTION = ("Robustness on `{label}`: the 3D detection rate (matched centre within 2 cm) and the 2D mAP.50 "
                      "against the sensor's subpixel noise, one panel per range band of the ball's true distance; "
                      "line styles for noise correlation and dropouts; each point one cell of the grid (20 scenes, a "
                      "few balls per band: coarse). mAP.50 per cell and band scores the band's balls, those of other "
                      "bands ignored (COCO's rule); a detection matched to no ball is a false positive in every band")


RELIABILITY_CAPTION = ("Reliability of the 3D methods' scores: per preset, each method's detections binned by score "
                       "(0.1 wide), the bin's fraction correct (within 2 cm of a ball, 3 cm beyond 3 m deep, one per "
                       "ball) against its mean score; on the diagonal a score is the probability it claims to be")


def write_results(out: Path, per_dataset: dict[str, tuple[Path, dict, Sequence[ScoredSet]]], t2: Sequence[dict] | None,
                  skipped: dict[str, str], prov: dict, title: str, intro: list[str],
                  paper_rows_for: Sequence[str] = ("default", "hard"), figures: bool = True,
                  ceilings: dict[str, dict] | None = None,
                  beside=None, extra_tables: Sequence[Table] = ()) -> dict[str, Path]:
    """Tables, figures, metrics.json, README.md and provenance.json under ``out`` (all atomic).

    per_dataset: {label: (dataset folder, its coco_gt dict, scored sets)}. Returns the paths written.
    ceilings: {label: a per-cell ceiling of the improved detector's 3D rate, {(subpixel,
    correlation, dropouts, band label): rate}}, drawn in the robustness figure
    (``figures.robustness``), e.g. an oracle's; None: none.
    beside: another evaluation (``recorded.Beside``): each dataset's Table 3 is also set beside the
    same methods' on its dataset (``recorded.beside_table``). extra_tables: tables of other studies
    (the resolution study's), written and listed after the others.
    A recorded dataset (``recorded.facts``) gets sentences on what its ground truth is, and its
    3D table and figures say that its centres are references. Sub-folders of figures/ that other
    tools wrote (the annotation review sheets) are kept when figures/ is replaced.
    """
    out = Path(out)
    sets_by = {k: v[2] for k, v in per_dataset.items()}
    facts = {label: recorded.facts(data_dir) for label, (data_dir, _, _) in per_dataset.items()}
    about = {label: recorded.reading(label, f, per_dataset[label][2]) for label, f in facts.items() if f is not None}
    calib = calibration.sets_calibration({label: (data_dir, sets) for label, (data_dir, _, sets) in per_dataset.items()},
                                         references=[label for label, f in facts.items() if f is not None])
    tables, transfer_rows = _tables(per_dataset, facts, about, t2, paper_rows_for, beside, calib)
    tables += list(extra_tables)
    metrics = metrics_json(sets_by)
    fig_paths = _figures(out, per_dataset, facts, metrics, transfer_rows, ceilings, calib) if figures else {}
    write_tables(out / "tables", tables)
    # the summary files together: a failed write leaves the earlier set, never a mix of two runs'
    outputs.replace_files({out / "metrics.json": inout.json_bytes(metrics),
                           **({out / "table2.json": inout.json_bytes(json_safe(list(t2)))} if t2 else {}),
                           out / "README.md": readme(title, intro, sets_by, tables, fig_paths, t2, skipped,
                                                   about).encode(),
                           out / "provenance.json": inout.json_bytes(prov)})
    return {"metrics": out / "metrics.json", "tables": out / "tables", "figures": out / "figures",
            "readme": out / "README.md", "provenance": out / "provenance.json"}


def _tables(per_dataset: dict, facts: dict, about: dict[str, list[str]], t2: Sequence[dict] | None,
            paper_rows_for: Sequence[str], beside, calib) -> tuple[list[Table], list]:
    """Every table of the results, in the README's order, and the transfer table's rows; the sentences
    the beside and transfer tables give are added to ``about``. calib: ``calibration.sets_calibration``."""
    sets_by = {k: v[2] for k, v in per_dataset.items()}
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
    t = calibration.calibration_table(calib)
    if t is not None:
        tables.append(t)
    tables.append(timing_table(sets_by))
    if t2:
        tables.append(table2_table(t2))
    return tables, transfer_rows


def _figures(out: Path, per_dataset: dict, facts: dict, metrics: dict, transfer_rows: list,
             ceilings: dict[str, dict] | None, calib) -> dict[str, str | None]:
    """Draw every figure into figures/ (replaced whole); {caption: its path, or None for a sub-folder
    another tool wrote, kept}. calib: ``calibration.sets_calibration``."""
    sets_by = {k: v[2] for k, v in per_dataset.items()}
    fig_paths: dict[str, str | None] = {}
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
                    f"; grey markers beside `{method_with_role(ROLE_DETECTOR)}`'s 3D rate: its ceiling (an oracle's)"
                    if ceiling else "")
                fig_paths[caption] = f"figures/robustness_{label}.png"
        if transfer_rows:
            figs.transfer(transfer_rows, tmp / "transfer.png")
            fig_paths[TRANSFER_CAPTION] = "figures/transfer.png"
        if not calib.empty:
            figs.reliability_diagram(calib, tmp / "reliability.png")
            fig_paths[RELIABILITY_CAPTION] = "figures/reliability.png"
        figs.latency(sets_by, tmp / "latency.png")
        fig_paths["Latency per method"] = "figures/latency.png"
    for name in kept:
        link = f"figures/{name}" + ("/" if (out / "figures" / name).is_dir() else "")
        fig_paths[f"[`{link}`]({link}): kept from another tool (not drawn by `evaluate`)"] = None
    return fig_paths
