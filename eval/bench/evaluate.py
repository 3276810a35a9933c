"""``evaluate`` (`spherebench evaluate`, and the benchmark's last step): methods run on datasets,
then scored and reported: metrics.json, tables/, figures/, README.md and provenance.json under
its output folder. ``check_dataset`` refuses a damaged dataset before any method runs;
``dataset_label`` names each dataset in the results.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Sequence

from spherebench.datasets import inout
from spherebench.datasets.fingerprint import dataset_fingerprint
from spherebench.errors import SphereBenchError
from spherebench.eval.bench.registry import build_methods
from spherebench.eval.bench.report import write_results
from spherebench.eval.bench.scoring import score_set
from spherebench.eval.bench.seeds import DETECTION_SEED_RULE
from spherebench.eval.bench.studies import table2_rows
from spherebench.eval.bench.tasks import dataset_scenes, run_methods
from spherebench.provenance import REPO_ROOT, provenance

#: What `make eval` writes into the checkout: an evaluation run after it (`make eval-real`) is not
#: "with uncommitted changes" for them, only for changed code.
BENCHMARK_OUTPUTS = (REPO_ROOT / "results", REPO_ROOT / "baselines" / "hough_config.json")


def check_dataset(data_dir: Path) -> float:
    """A dataset's ball radius (m), once the files that say what it holds (dataset.json, coco_gt.json,
    every gt.json, intrinsics.json, the size of every image.png) have been read: a damaged one is
    refused before any method runs."""
    if not (data_dir / "scenes").is_dir():
        raise SphereBenchError(f"{data_dir}: not a dataset (no scenes/ folder); build one with "
                               "'spherebench generate' or 'spherebench prepare'")
    meta = inout.read_dataset_meta(data_dir) if (data_dir / "dataset.json").is_file() else {}
    for s in dataset_scenes(data_dir):
        # a 2D method's input must be the image its circles are scored in
        if s.image_id is not None or (s.has_image and s.resolution is not None):
            inout.check_scene_image(s.path, inout.read_intrinsics(s.path))
    return float(meta.get("ball_radius_m") or 0.12)


def evaluate(datasets: dict[str, Path], out: Path, methods: Sequence[str] | None = None, seed: int = 0,
             workers: int = 2, force: bool = False, hough_config=None, model: str | Path | None = None,
             table2_dir: Path | None = None, table2_iterations: int | None = None, figures: bool = True,
             progress: bool = True, title: str = "SphereBench results", intro: list[str] | None = None,
             paper_rows_for: Sequence[str] = ("default", "hard"), extra_provenance: dict | None = None,
             ceilings: dict[str, dict] | None = None, beside=None, log=print, engine: str = "local",
             address: str | None = None, extra_tables: Sequence = ()) -> dict:
    """Run, score and report ``datasets`` ({label: folder}) into ``out``. Returns metrics.json's content.

    ceilings: per-cell ceilings of the improved detector's 3D rate on a grid preset, {label:
    {(subpixel, correlation, dropouts, band label): rate}}, drawn in its robustness figure.
    beside: another evaluation (``recorded.Beside``, from ``recorded.load_beside``): each Table 3 is
    set beside that one's dataset. extra_tables: tables of other studies (``tables.Table``), written
    and listed after the others."""
    out = Path(out)
    skipped: dict[str, str] = {}
    per_dataset = {}
    configs: dict = {}
    fingerprints: dict = {}
    stage_s: dict = {}
    plans = {}
    for label, data_dir in datasets.items():  # every dataset and method checked before any runs
        radius = check_dataset(Path(data_dir))
        specs = build_methods(methods, hough_config=hough_config, circlenet_model=model,
                              table_note=lambda n, why: skipped.setdefault(n, why), radius_m=radius)
        if not specs:
            raise SphereBenchError("no method can run: " + "; ".join(f"{k}: {v}" for k, v in skipped.items()))
        plans[label] = (Path(data_dir), specs)
    for label, (data_dir, specs) in plans.items():
        for spec in specs:
            configs.setdefault(spec.name, {})[label] = {"config": spec.config, "note": spec.note}
        t0 = time.perf_counter()
        fingerprints[label] = dataset_fingerprint(data_dir)
        paths = run_methods(data_dir, out / "predictions" / label, specs, seed=seed, workers=workers,
                            progress=progress, force=force, fingerprint=fingerprints[label], log=log,
                            engine=engine, address=address)
        stage_s[f"run {label}"] = round(time.perf_counter() - t0, 1)
        t0 = time.perf_counter()
        scenes = dataset_scenes(data_dir)
        coco = inout.read_coco_gt(data_dir)
        order = [o for spec in specs for o in spec.outputs if o in paths]
        per_dataset[label] = (data_dir, coco, [score_set(paths[o], coco, scenes) for o in order])
        stage_s[f"score {label}"] = round(time.perf_counter() - t0, 1)
    t2 = None
    if table2_dir is not None:
        t0 = time.perf_counter()
        log(f"table 2: the paper configuration on {table2_dir}")
        t2 = table2_rows(table2_dir, seed=seed, iterations=table2_iterations, workers=workers, engine=engine,
                         address=address)
        stage_s["table 2"] = round(time.perf_counter() - t0, 1)
    prov = provenance(REPO_ROOT, seeds={"run_seed": seed, "detection_seed": DETECTION_SEED_RULE},
                      configs=configs,
                      extra={"datasets": {k: {"path": str(v), "fingerprint": fingerprints[k]}
                                          for k, v in datasets.items()},
                             "skipped_methods": skipped, "workers": workers, "engine": engine,
                             "stage_seconds": stage_s, **(extra_provenance or {})},
                      outputs=(out, *BENCHMARK_OUTPUTS))
    intro = list(intro or []) + [
        "",
        f"Generated by `spherebench evaluate` / `make eval` on {prov['date']} "
        f"(commit {prov['git']['commit'] or 'unknown'}{', with uncommitted changes' if prov['git']['dirty'] else ''}); "
        "machine, package versions, seeds and configurations in `provenance.json`; every figure in `metrics.json`; "
        "predictions (COCO results with CircleNet's fields) in `predictions/`."]
    t0 = time.perf_counter()
    write_results(out, per_dataset, t2, skipped, prov, title, intro, paper_rows_for=paper_rows_for,
                  figures=figures, ceilings=ceilings, beside=beside, extra_tables=extra_tables)
    stage_s["report"] = round(time.perf_counter() - t0, 1)
    return json.loads((out / "metrics.json").read_text())


def console_line(method: str, m: dict | None) -> str | None:
    """A prediction set's figures on one dataset, for the console (None: nothing to say)."""
    if m is None:
        return None
    n, refused = m.get("n_scenes_run", 0), m.get("scenes_refused", 0)
    if refused and refused == n:  # nothing ran: no score, no time
        return None if method.endswith("+paper-circle") else f"refused {refused}/{n}: {m.get('refused_reason')}"
    tail = f"  refused {refused}/{n}: {m.get('refused_reason')}" if refused else ""
    if m.get("mAP") is not None:
        return (f"mAP {m['mAP']:.3f}  mAP.50 {m['mAP50']:.3f}  mAP.75 {m['mAP75']:.3f}  {m['ms_median']:.1f} ms"
                + tail)
    if m.get("unannotated") and not method.endswith("+paper-circle"):
        u = m["unannotated"]
        return (f"detections in {u['scenes_with_detection']}/{u['n_scenes']} unannotated scenes  "
                f"{m['ms_median']:.1f} ms" + tail)
    return None


def dataset_label(path: Path, taken: set) -> str:
    """A dataset's label in the results (its dataset.json name, else its folder's), made unique
    among ``taken`` (which it joins)."""
    name = path.resolve().name
    if (path / "dataset.json").is_file():
        name = str(inout.read_dataset_meta(path).get("name") or name)
    label, k = name, 2
    while label in taken:
        label, k = f"{name}-{k}", k + 1
    taken.add(label)
    return label
