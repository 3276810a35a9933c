"""`spherebench evaluate`: run the benchmark's methods on prepared datasets and score them.

    spherebench evaluate --data DIR [--data DIR2 ...] --out OUT [--methods improved paper ...] [--seed N]
                         [--workers 2] [--engine local|ray [--address ADDR]] [--force] [--hough-config FILE]
                         [--model FILE] [--no-figures] [--beside METRICS [--beside-label default]]

DIR: a dataset of `spherebench generate` or `spherebench prepare`. Writes under OUT:
predictions/<dataset>/<method>.json (COCO results with CircleNet's fields) and .meta.json
(provenance, per-scene times), metrics.json, tables/, figures/, README.md, provenance.json.
Scenes with ground truth are scored (COCO circle mAP; 3D metrics where true centres are known);
unannotated scenes (annotated = false) get detection and radius statistics instead. An
interrupted run resumes: finished prediction sets with the same inputs are reused. A recorded
dataset's README says what its ground truth is (``eval.bench.recorded``); --beside sets every Table 3
beside the same methods' on a dataset of another evaluation (its metrics.json), e.g. the
simulated `default` of results/ beside a recording's.
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

from spherebench import options
from spherebench.baselines.hough_tuning import hough_config_for_run
from spherebench.errors import SphereBenchError
from spherebench.eval.bench.registry import CIRCLENET_MODELS, circlenet_model_path, method_names, circlenet_spec


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--data", action="append", required=True, metavar="DIR",
                   help="dataset folder (repeat for several)")
    p.add_argument("--out", type=options.out_path, required=True, metavar="OUT", help="output folder")
    p.add_argument("--methods", nargs="+", choices=method_names(), default=None, metavar="METHOD",
                   help=f"methods to run (default: all available: {', '.join(method_names())})")
    p.add_argument("--seed", type=options.seed, default=0, help="run seed; scene k uses SeedSequence((seed, k))")
    options.add_executor_arguments(p, "worker processes (output identical for any number)")
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


def run(args: argparse.Namespace) -> int:
    # here, not at the top: the reports load pandas (and matplotlib to draw), and `spherebench evaluate --help`
    # took 2.4 s with them, about 1 s without
    from spherebench.eval.bench.evaluate import check_dataset, console_line, dataset_label, evaluate
    from spherebench.eval.bench.recorded import load_beside
    from spherebench.eval.bench.report import results_run

    options.check_executor(args)
    out = Path(args.out)
    taken: set = set()
    datasets = {}
    for d in args.data:
        path = Path(d)
        if not path.is_dir():
            raise SphereBenchError(f"{path}: dataset folder not found")
        datasets[dataset_label(path, taken)] = path
    for path in datasets.values():
        check_dataset(path)
    if args.provider:  # the worker processes inherit it (infer.PROVIDER_VARIABLE)
        # here, not at the top: infer loads onnxruntime, which only a provider's check needs
        from spherebench.baselines.circlenet.infer import PROVIDER_VARIABLE, execution_provider
        os.environ[PROVIDER_VARIABLE] = execution_provider(args.provider)
    for name in args.methods or ():  # a method asked for by name is run, or refused: never dropped quietly
        given = name == "circlenet" and args.model
        if name in CIRCLENET_MODELS and not given and not circlenet_model_path(name).is_file():
            raise SphereBenchError(f"--methods {name}: its model {circlenet_model_path(name)} is not there (train it "
                                   f"with `{CIRCLENET_MODELS[name][1]}`, or leave the method out)")
    if args.model and (args.methods is None or "circlenet" in args.methods):
        circlenet_spec(args.model)  # a corrupt model is refused now, not after the other methods have run
    beside, beside_record = load_beside(args.beside, args.beside_label) if args.beside else (None, None)
    progress = not args.quiet
    with results_run(out, inputs=tuple(datasets.values())):  # claimed before anything is written (Hough tuning too)
        hough = hough_config_for_run(args.methods, args.hough_config, out, args.workers, progress,
                                     engine=args.engine, address=args.address)
        metrics = evaluate(datasets, out, methods=args.methods, seed=args.seed, workers=args.workers,
                           force=args.force, hough_config=hough, model=args.model, figures=not args.no_figures,
                           progress=progress, title="SphereBench evaluation", paper_rows_for=(), beside=beside,
                           extra_provenance={"beside": beside_record} if beside else None,
                           engine=args.engine, address=args.address)
        # said inside the run: stdout that fails (a full disk) fails the run, as any other write
        for label in datasets:
            for method, by in metrics.items():
                line = console_line(method, by.get(label))
                if line:
                    print(f"{label:>20s}  {method:<28s} {line}")
        print(f"wrote {out}/README.md, metrics.json, tables/" + ("" if args.no_figures else ", figures/"), flush=True)
    return 0
