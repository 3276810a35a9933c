"""`spherebench evaluate`: run the benchmark's methods on prepared datasets and score them.

    spherebench evaluate --data DIR [--data DIR2 ...] --out OUT [--methods improved paper ...] [--seed N]
                         [--workers 2] [--force] [--hough-config FILE] [--model FILE] [--no-figures]
                         [--beside METRICS [--beside-label default]]

DIR: a dataset of `spherebench generate` or `spherebench prepare`. Writes under OUT:
predictions/<dataset>/<method>.json (COCO results with CircleNet's fields) and .meta.json
(provenance, per-scene times), metrics.json, tables/, figures/, README.md, provenance.json.
Scenes with ground truth are scored (COCO circle mAP; 3D metrics where true centres are known);
unannotated scenes (annotated = false) get detection and radius statistics instead. An
interrupted run resumes: finished prediction sets with the same inputs are reused. A recorded
dataset's README says what its ground truth is (``eval.recorded``); --beside sets every Table 3
beside the same methods' on a dataset of another evaluation (its metrics.json), e.g. the
simulated `default` of results/ beside a recording's.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path
from typing import Sequence

from spherebench import options
from spherebench.errors import SphereBenchError


def add_arguments(p: argparse.ArgumentParser) -> None:
    from spherebench.eval.runner import METHOD_ORDER
    p.add_argument("--data", action="append", required=True, metavar="DIR",
                   help="dataset folder (repeat for several)")
    p.add_argument("--out", type=options.out_path, required=True, metavar="OUT", help="output folder")
    p.add_argument("--methods", nargs="+", choices=METHOD_ORDER, default=None, metavar="METHOD",
                   help=f"methods to run (default: all available: {', '.join(METHOD_ORDER)})")
    p.add_argument("--seed", type=options.seed, default=0, help="run seed; scene k uses SeedSequence((seed, k))")
    p.add_argument("--workers", type=int, default=2, help="worker processes (output identical for any number)")
    p.add_argument("--force", action="store_true", help="recompute predictions even when finished ones match")
    p.add_argument("--hough-config", metavar="FILE", default=None,
                   help="Hough configuration JSON (default: the tuned one in results/hough_config.json, else the "
                        "copy shipped with the package, else tuned now on a training subset built under OUT)")
    p.add_argument("--model", metavar="FILE", default=None,
                   help="the `circlenet` method's ONNX model (default: baselines/circlenet/model.onnx; skipped if "
                        "missing); circlenet-full and circlenet-hg use theirs under baselines/circlenet/")
    p.add_argument("--beside", metavar="METRICS", default=None,
                   help="another evaluation's metrics.json (e.g. results/metrics.json): each Table 3 is also set "
                        "beside the same methods' figures on its --beside-label dataset")
    p.add_argument("--beside-label", metavar="LABEL", default="default",
                   help="the dataset of --beside to compare with (default: default)")
    p.add_argument("--provider", default=None, metavar="NAME",
                   help="ONNX Runtime execution provider of the CircleNet methods: cpu (default), cuda (needs "
                        "onnxruntime-gpu), or a full name")
    p.add_argument("--no-figures", action="store_true", help="write no figures")
    p.add_argument("--quiet", action="store_true", help="no progress bars")


def load_hough_config(path: str | Path):
    """A HoughConfig from JSON: a tuning cache ({"config": {...}}) or the fields themselves."""
    from spherebench.baselines.hough import HoughConfig
    path = Path(path)
    try:
        d = json.loads(path.read_text())
    except OSError as exc:
        raise SphereBenchError(f"cannot read Hough configuration {path} ({exc.strerror})") from None
    except json.JSONDecodeError as exc:
        raise SphereBenchError(f"{path} is not valid JSON ({exc})") from None
    d = d.get("config", d) if isinstance(d, dict) else d
    try:
        return HoughConfig(**d)
    except TypeError as exc:
        raise SphereBenchError(f"{path} is not a Hough configuration ({exc})") from None


def resolve_hough(methods, hough_file, out: Path, seed: int, workers: int, progress: bool, log=print):
    """The Hough configuration to use: a given file, the repository's tuned cache, the package's copy, or
    a fresh tuning."""
    from spherebench.eval import runner
    if methods is not None and "hough" not in methods:
        return None
    if hough_file:
        return load_hough_config(hough_file)
    repo_cache = runner.REPO_ROOT / "results" / "hough_config.json"
    if repo_cache.is_file():
        try:
            if json.loads(repo_cache.read_text()).get("key") == runner._hough_key(runner.HOUGH_TRAIN_SCENES, 0):
                log(f"hough: tuned configuration from {repo_cache}")
                return load_hough_config(repo_cache)
        except (OSError, json.JSONDecodeError):
            pass
    from spherebench.baselines.hough import SHIPPED_CONFIG
    if SHIPPED_CONFIG.is_file():  # an installed package, or a clone whose results/ predate its code
        log(f"hough: the tuned configuration shipped with the package ({SHIPPED_CONFIG.name})")
        return load_hough_config(SHIPPED_CONFIG)
    return runner.tuned_hough_config(out / "hough_config.json", out / "train-hough", seed=0, workers=workers,
                                     progress=progress, log=log)


def check_dataset(data_dir: Path) -> float:
    """A dataset's ball radius (m), once the files that say what it holds (dataset.json, coco_gt.json,
    every gt.json) have been read: a damaged one is refused before any method runs."""
    from spherebench.datasets import inout
    from spherebench.eval import runner
    if not (data_dir / "scenes").is_dir():
        raise SphereBenchError(f"{data_dir}: not a dataset (no scenes/ folder); build one with "
                               "'spherebench generate' or 'spherebench prepare'")
    meta = inout.read_dataset_meta(data_dir) if (data_dir / "dataset.json").is_file() else {}
    radius = meta.get("ball_radius_m", 0.12) if isinstance(meta, dict) else None
    if not (isinstance(radius, (int, float)) and math.isfinite(radius) and radius > 0):
        raise SphereBenchError(f"{data_dir / 'dataset.json'}: ball_radius_m must be the ball's radius in metres, "
                               f"not {radius!r}; rebuild the dataset")
    runner.dataset_scenes(data_dir)
    return float(radius)


def evaluate(datasets: dict[str, Path], out: Path, methods: Sequence[str] | None = None, seed: int = 0,
             workers: int = 2, force: bool = False, hough_config=None, model: str | Path | None = None,
             table2_dir: Path | None = None, table2_iterations: int | None = None, figures: bool = True,
             progress: bool = True, title: str = "SphereBench results", intro: list[str] | None = None,
             paper_rows_for: Sequence[str] = ("default", "hard"), extra_provenance: dict | None = None,
             ceilings: dict[str, dict] | None = None, beside=None, log=print) -> dict:
    """Run, score and report ``datasets`` ({label: folder}) into ``out``. Returns metrics.json's content.

    ceilings: per-cell ceilings of the improved detector's 3D rate on a grid preset, {label:
    {(subpixel, correlation, dropouts, band label): rate}}, drawn in its robustness figure.
    beside: another evaluation (``recorded.Beside``, from ``recorded.load_beside``): each Table 3 is
    set beside that one's dataset."""
    from spherebench.datasets import inout
    from spherebench.eval import report, runner

    out = Path(out)
    skipped: dict[str, str] = {}
    per_dataset = {}
    configs: dict = {}
    fingerprints: dict = {}
    stage_s: dict = {}
    plans = {}
    for label, data_dir in datasets.items():  # every dataset and method checked before any runs
        radius = check_dataset(Path(data_dir))
        specs = runner.build_methods(methods, hough_config=hough_config, circlenet_model=model,
                                     table_note=lambda n, why: skipped.setdefault(n, why), radius_m=radius)
        if not specs:
            raise SphereBenchError("no method can run: " + "; ".join(f"{k}: {v}" for k, v in skipped.items()))
        plans[label] = (Path(data_dir), specs)
    for label, (data_dir, specs) in plans.items():
        for spec in specs:
            configs.setdefault(spec.name, {})[label] = {"config": spec.config, "note": spec.note}
        t0 = time.perf_counter()
        fingerprints[label] = runner.dataset_fingerprint(data_dir)
        paths = runner.run_methods(data_dir, out / "predictions" / label, specs, seed=seed, workers=workers,
                                   progress=progress, force=force, fingerprint=fingerprints[label], log=log)
        stage_s[f"run {label}"] = round(time.perf_counter() - t0, 1)
        t0 = time.perf_counter()
        scenes = runner.dataset_scenes(data_dir)
        coco = inout.read_coco_gt(data_dir)
        order = [o for spec in specs for o in spec.outputs if o in paths]
        per_dataset[label] = (data_dir, coco, [report.score_set(paths[o], coco, scenes) for o in order])
        stage_s[f"score {label}"] = round(time.perf_counter() - t0, 1)
    t2 = None
    if table2_dir is not None:
        t0 = time.perf_counter()
        log(f"table 2: the paper configuration on {table2_dir}")
        t2 = runner.table2_rows(table2_dir, seed=seed, iterations=table2_iterations)
        stage_s["table 2"] = round(time.perf_counter() - t0, 1)
    prov = report.provenance(runner.REPO_ROOT, seeds={"run_seed": seed, "scene_seed": "SeedSequence((seed, k))"},
                             configs=configs,
                             extra={"datasets": {k: {"path": str(v), "fingerprint": fingerprints[k]}
                                                 for k, v in datasets.items()},
                                    "skipped_methods": skipped, "workers": workers, "stage_seconds": stage_s,
                                    **(extra_provenance or {})})
    intro = list(intro or []) + [
        "",
        f"Generated by `spherebench evaluate` / `make eval` on {prov['date']} "
        f"(commit {prov['git']['commit'] or 'unknown'}{', with uncommitted changes' if prov['git']['dirty'] else ''}); "
        "machine, package versions, seeds and configurations in `provenance.json`; every figure in `metrics.json`; "
        "predictions (COCO results with CircleNet's fields) in `predictions/`."]
    t0 = time.perf_counter()
    report.write_results(out, per_dataset, t2, skipped, prov, title, intro, paper_rows_for=paper_rows_for,
                         figures=figures, ceilings=ceilings, beside=beside)
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


def _label(path: Path, taken: set) -> str:
    from spherebench.datasets import inout
    name = path.resolve().name
    if (path / "dataset.json").is_file():
        name = str(inout.read_dataset_meta(path).get("name") or name)
    label, k = name, 2
    while label in taken:
        label, k = f"{name}-{k}", k + 1
    taken.add(label)
    return label


def run(args: argparse.Namespace) -> int:
    if args.workers < 1:
        raise SphereBenchError("--workers must be at least 1")
    out = Path(args.out)
    taken: set = set()
    datasets = {}
    for d in args.data:
        path = Path(d)
        if not path.is_dir():
            raise SphereBenchError(f"{path}: dataset folder not found")
        datasets[_label(path, taken)] = path
    for path in datasets.values():
        check_dataset(path)
    if args.provider:  # the worker processes inherit it (infer.PROVIDER_VARIABLE)
        import os
        from spherebench.baselines.circlenet.infer import PROVIDER_VARIABLE, execution_provider
        os.environ[PROVIDER_VARIABLE] = execution_provider(args.provider)
    from spherebench.eval.runner import CIRCLENET_MODELS, circlenet_model_path
    for name in args.methods or ():  # a method asked for by name is run, or refused: never dropped quietly
        given = name == "circlenet" and args.model
        if name in CIRCLENET_MODELS and not given and not circlenet_model_path(name).is_file():
            raise SphereBenchError(f"--methods {name}: its model {circlenet_model_path(name)} is not there (train it "
                                   f"with `{CIRCLENET_MODELS[name][1]}`, or leave the method out)")
    if args.model and (args.methods is None or "circlenet" in args.methods):
        from spherebench.eval.runner import circlenet_spec
        circlenet_spec(args.model)  # a corrupt model is refused now, not after the other methods have run
    if args.beside:
        from spherebench.eval.recorded import load_beside
        beside, beside_record = load_beside(args.beside, args.beside_label)
    else:
        beside, beside_record = None, None
    from spherebench.eval.report import claim_results_dir  # deferred like the other eval imports: fast --help
    claim_results_dir(out)  # before anything is written under it (Hough tuning included)
    progress = not args.quiet
    hough = resolve_hough(args.methods, args.hough_config, out, args.seed, args.workers, progress)
    metrics = evaluate(datasets, out, methods=args.methods, seed=args.seed, workers=args.workers, force=args.force,
                       hough_config=hough, model=args.model, figures=not args.no_figures, progress=progress,
                       title="SphereBench evaluation", paper_rows_for=(), beside=beside,
                       extra_provenance={"beside": beside_record} if beside else None)
    for label in datasets:
        for method, by in metrics.items():
            line = console_line(method, by.get(label))
            if line:
                print(f"{label:>20s}  {method:<28s} {line}")
    print(f"wrote {out}/README.md, metrics.json, tables/" + ("" if args.no_figures else ", figures/"))
    return 0
