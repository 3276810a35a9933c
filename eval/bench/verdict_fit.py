"""Fitting the detector's verdict (``method/verdict.py``) on the candidates of both sensor models.

1. ``collect``: the improved detector runs on every scene of `train` and `train-stereo` with no
   verdict (``verdict.unscored``: every candidate scores the same, nothing is accepted, every search
   and retry runs; ``COLLECT_OVERRIDES``: every distinct verified sphere that passes the size check is
   reported), so that no earlier model steers what the next one sees. Each candidate becomes a row: its
   ``verdict_features``, its
   label (a ball's centre within 2 cm, 3 cm beyond 3 m: ``eval.metrics.calibration`` 's rule, any
   ball), its scene, family and the sensor's parameters.
2. ``choose``: each candidate model is fitted across sensors and judged on a sensor it has not seen:
   `train` plus the stereo scenes of low ambient light, judged on those of high ambient light; the
   reverse; and `train-stereo` alone, judged on `train`. The model of the least mean log loss over the
   three folds is kept (the verdict is a probability: a proper score of probabilities).
3. ``fit``: the kept model refitted on every scene but the held-apart ones (scene index = 4 mod 5,
   both sensor models), its output calibrated on those by isotonic regression, exported to ONNX
   with the feature names and the calibration knots in its metadata, and a model card.

Same seed, same model: the detector's runs are seeded per scene (``detection_seed``) and the
fits' randomness is the seed's.
"""

from __future__ import annotations

import functools
import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from spherebench.datasets import inout
from spherebench.eval.bench.seeds import detection_seed
from spherebench.eval.metrics.calibration import expected_calibration_error
from spherebench.eval.metrics.metrics3d import found_limit_m
from spherebench.method.config import DetectorConfig, config_for
from spherebench.method.detector import detect
from spherebench.method.verdict import unscored
from spherebench.method.verdict import FEATURE_NAMES, verdict_features
from spherebench.parallel import executor
from spherebench.provenance import dist_version

#: the collection's detector (with ``verdict.unscored``): nothing accepted, every verified candidate that passes
#: the size check kept and reported, duplicates (centres within 1.2 cm) suppressed
COLLECT_OVERRIDES = {"verification.accept_score": 1.0, "verification.rank_floor": 0.0, "verification.min_score": 0.0,
                     "verification.max_spheres": 100, "verification.nms_distance_fraction": 0.05}
#: the score every candidate gets in the collection (``verdict.unscored``)
COLLECT_SCORE = 0.5
#: scenes whose index is this modulo CALIBRATION_EVERY are held apart from the fit, for the calibration
CALIBRATION_EVERY, CALIBRATION_REST = 5, 4
#: the stereo scenes' split for the cross-sensor folds: their ambient light (electrons per ms)
AMBIENT_SPLIT_E_PER_MS = 150.0
SENSOR_COLUMNS = ("ambient_e_per_ms", "dot_sigma_mrad", "read_noise_e", "subpixel")


def collect_config(radius_m: float, overrides: dict | None = None) -> DetectorConfig:
    """The improved detector's configuration for the collection (``COLLECT_OVERRIDES``, then overrides) at radius_m."""
    return config_for("improved", {**COLLECT_OVERRIDES, **(overrides or {})}, radius_m=radius_m)


def _scene_rows(job: tuple) -> list[dict]:
    """One scene's candidate rows (in a worker): job (dataset name, scene dir, index, seed, radius_m, overrides)."""
    dataset, scene_dir, index, seed, radius_m, overrides = job
    gt = inout.read_scene_gt(Path(scene_dir))
    cloud = inout.load_cloud(Path(scene_dir))
    config = collect_config(radius_m, overrides)
    with unscored(COLLECT_SCORE):
        spheres = detect(cloud, config, seed=detection_seed(seed, index), min_score=0.0, max_spheres=100)
    balls = np.asarray([b["center_m"] for b in gt.get("balls", []) if b.get("center_m") is not None],
                       np.float64).reshape(-1, 3)
    limit_m = found_limit_m(balls[:, 2])
    sensor = gt.get("meta", {}).get("sensor", {})
    rows = []
    for rank, s in enumerate(spheres):
        d = np.linalg.norm(balls - s.centre_m, axis=1)
        row = {"dataset": dataset, "scene": gt["scene_id"], "index": index, "family": gt.get("family", ""),
               "seed": seed, "rank": rank, "z_m": float(s.centre_m[2]),
               "label": bool(np.any(d <= limit_m)),
               "ball_z_m": float(balls[np.argmin(d), 2]) if len(d) else math.nan}
        row.update({k: float(sensor.get(k, math.nan)) for k in SENSOR_COLUMNS})
        row.update(zip(FEATURE_NAMES, verdict_features(s.evidence, radius_m).tolist()))
        rows.append(row)
    return rows


def collect(datasets: list[Path], seeds: list[int], workers: int, limit: int | None = None,
            overrides: dict | None = None) -> pd.DataFrame:
    """Every candidate of every scene with a ground truth in datasets, at each run seed (rows: ``_scene_rows``)."""
    jobs = []
    for data in datasets:
        radius_m = float(inout.read_dataset_meta(data).get("ball_radius_m", 0.12))
        scenes = inout.list_scenes(data)[:limit]
        jobs += [(data.name, str(p), k, seed, radius_m, overrides) for seed in seeds for k, p in enumerate(scenes)]
    with executor(workers) as ex:
        rows = [r for part in ex.map(_scene_rows, jobs) for r in part]
    return pd.DataFrame(rows)


#: the models compared across sensors (``choose``): name -> a function of the seed giving an unfitted
#: classifier with the scikit-learn interface
def _logistic(seed: int):
    from sklearn.linear_model import LogisticRegression
    from sklearn.pipeline import make_pipeline
    from sklearn.preprocessing import StandardScaler

    return make_pipeline(StandardScaler(), LogisticRegression(C=1.0, max_iter=5000, random_state=seed))


#: the direction each feature may move the probability in (LightGBM's monotone constraints): +1 up, -1
#: down, 0 either. Physical facts of a ball: its silhouette's pixels are its own (no more seen behind it,
#: through it or hugging it than the noise leaves), its outline stands free, its residuals are the noise's
MONOTONE = {"coverage": 1, "behind_share": -1, "hug_share": -1, "ring_continued": -1, "ring_front": -1,
            "ring_spread": -1, "see_through": -1, "edge_behind": -1, "log_rmse_noise": -1}


def _boosted(seed: int, monotone: bool = True):
    from lightgbm import LGBMClassifier

    cst = [MONOTONE.get(name, 0) if monotone else 0 for name in FEATURE_NAMES]
    # one thread and LightGBM's deterministic mode: the same seed gives the same trees on any machine
    return LGBMClassifier(n_estimators=300, learning_rate=0.05, num_leaves=15, min_child_samples=40, reg_lambda=1.0,
                          monotone_constraints=cst, monotone_constraints_method="advanced", deterministic=True,
                          force_row_wise=True, n_jobs=1, random_state=seed, verbose=-1)


# scikit-learn's exact gradient boosting (200 trees of depth 4) was compared too, at one run seed: a
# mean log loss of 0.095 against 0.085, ten times slower (docs/experiments/2026-12-06-fitted-verdict.md)
MODELS = {
    "logistic": _logistic,
    "lgbm-300": functools.partial(_boosted, monotone=False),
    "lgbm-300-monotone": _boosted,
}


def _is_calibration(df: pd.DataFrame) -> np.ndarray:
    return (df["index"].to_numpy() % CALIBRATION_EVERY) == CALIBRATION_REST


def folds(df: pd.DataFrame) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """The cross-sensor folds (name, fit rows, judged rows) over the fit scenes (calibration's left out)."""
    fit = ~_is_calibration(df)
    analytic = df["dataset"].to_numpy() == "train"
    stereo = df["dataset"].to_numpy() == "train-stereo"
    low = stereo & (df["ambient_e_per_ms"].to_numpy() < AMBIENT_SPLIT_E_PER_MS)
    high = stereo & ~low
    return [("train + stereo low ambient -> stereo high ambient", fit & (analytic | low), fit & high),
            ("train + stereo high ambient -> stereo low ambient", fit & (analytic | high), fit & low),
            ("train-stereo -> train", fit & stereo, fit & analytic)]


def _judge(y: np.ndarray, p: np.ndarray) -> dict:
    from sklearn.metrics import average_precision_score, log_loss, roc_auc_score

    return {"ap": float(average_precision_score(y, p)), "auc": float(roc_auc_score(y, p)),
            "log_loss": float(log_loss(y, np.clip(p, 1e-6, 1 - 1e-6))), "n": int(len(y)), "positives": int(y.sum())}


def choose(df: pd.DataFrame, seed: int) -> dict:
    """Each model of MODELS judged on each cross-sensor fold: {model: {fold: _judge's figures}, "chosen": the model of the least mean log loss}."""
    x = df[list(FEATURE_NAMES)].to_numpy(np.float32)
    y = df["label"].to_numpy(np.int64)
    out: dict = {}
    for name, make in MODELS.items():
        out[name] = {}
        for fold, fit_rows, judged in folds(df):
            model = make(seed).fit(x[fit_rows], y[fit_rows])
            out[name][fold] = _judge(y[judged], model.predict_proba(x[judged])[:, 1])
    # the verdict is a probability: chosen by a proper score of probabilities, over sensors it has not seen
    mean_loss = {name: float(np.mean([f["log_loss"] for f in out[name].values()])) for name in MODELS}
    out["chosen"] = min(mean_loss, key=mean_loss.get)
    return out


@dataclass
class FittedModel:
    """A verdict model fitted and calibrated: the ONNX bytes and what its card reports."""

    onnx_bytes: bytes
    knots: tuple[list[float], list[float]]
    calibration: dict


def fit(df: pd.DataFrame, name: str, seed: int) -> FittedModel:
    """The model ``name`` fitted on the fit scenes of both sensor models, calibrated on the held-apart
    ones (isotonic regression of the label on the model's output), exported to ONNX."""
    from sklearn.isotonic import IsotonicRegression

    x = df[list(FEATURE_NAMES)].to_numpy(np.float32)
    y = df["label"].to_numpy(np.int64)
    cal = _is_calibration(df)
    model = MODELS[name](seed).fit(x[~cal], y[~cal])
    s_cal = model.predict_proba(x[cal])[:, 1]
    iso = IsotonicRegression(y_min=0.0, y_max=1.0, out_of_bounds="clip").fit(s_cal, y[cal])
    knots = ([0.0] + iso.X_thresholds_.tolist() + [1.0], _bounded(iso, s_cal, y[cal]))
    onx = _to_onnx(model)
    onx.graph.name = "verdict"  # onnxmltools names the graph by a random uuid
    # the exporter lists the opsets from a set, in an order that varies between runs: sorted, the same
    # seed writes the same bytes
    opsets = sorted(((o.domain, o.version) for o in onx.opset_import))
    del onx.opset_import[:]
    for domain, version in opsets:
        onx.opset_import.add(domain=domain, version=version)
    for key, value in (("feature_names", json.dumps(list(FEATURE_NAMES))), ("calibration_knots", json.dumps(knots)),
                       ("model", name), ("seed", str(seed))):
        entry = onx.metadata_props.add()
        entry.key, entry.value = key, value
    p_cal = np.interp(s_cal, knots[0], knots[1])
    per_set = {}
    for dataset in sorted(set(df["dataset"][cal])):
        rows = df["dataset"].to_numpy()[cal] == dataset
        per_set[dataset] = {**_judge(y[cal][rows], p_cal[rows]),
                            "ece": float(expected_calibration_error(p_cal[rows], y[cal][rows], n_bins=10))}
    return FittedModel(onnx_bytes=onx.SerializeToString(), knots=knots, calibration=per_set)


def _bounded(iso, scores: np.ndarray, labels: np.ndarray) -> list[float]:
    """The isotonic map's probabilities at its knots (with one more at each end), its lowest and
    highest blocks at Laplace's rule, (k + 1) / (n + 2), so that no candidate is ever certain (a block
    of n held-apart candidates, k correct, all or none, says p is within about 1 / n of 0 or 1, not
    that it is 0 or 1); the map stays non-decreasing."""
    fitted = iso.predict(scores)
    p = np.concatenate([[iso.y_thresholds_[0]], iso.y_thresholds_, [iso.y_thresholds_[-1]]]).astype(np.float64)
    for level in (p.min(), p.max()):
        block = fitted == level
        p = np.where(p == level, (labels[block].sum() + 1.0) / (block.sum() + 2.0), p)
    return np.maximum.accumulate(np.minimum.accumulate(p[::-1])[::-1]).tolist()


def _to_onnx(model):
    """The fitted classifier as an ONNX model whose "probabilities" output is (B, 2) (no ZipMap)."""
    if type(model).__name__ == "LGBMClassifier":
        from onnxmltools import convert_lightgbm
        from onnxmltools.convert.common.data_types import FloatTensorType

        # opset 15: the highest onnxmltools 1.16 converts to
        return convert_lightgbm(model, initial_types=[("X", FloatTensorType([None, len(FEATURE_NAMES)]))],
                                zipmap=False, target_opset=15)
    from skl2onnx import to_onnx

    final = model.steps[-1][1] if hasattr(model, "steps") else model
    return to_onnx(model, np.zeros((1, len(FEATURE_NAMES)), np.float32), options={id(final): {"zipmap": False}},
                   target_opset={"": 17, "ai.onnx.ml": 3})


def _versions() -> dict:
    return {name: dist_version(name) for name in ("scikit-learn", "lightgbm", "skl2onnx", "onnxmltools", "onnx",
                                                  "onnxruntime", "numpy")}


def model_card(df: pd.DataFrame, comparison: dict, model: FittedModel, seed: int, seeds: list[int],
               datasets: list[Path], command: str) -> tuple[dict, str]:
    """The model card as JSON and Markdown: the data, the seed, the recipe, the cross-sensor comparison
    and the calibration on the held-apart scenes."""
    cal = _is_calibration(df)
    data = {name: {"scenes": int(df[df.dataset == name]["index"].nunique()), "candidates": int((df.dataset == name).sum()),
                   "positives": int(df[df.dataset == name]["label"].sum()),
                   "held_apart_candidates": int(((df.dataset == name) & cal).sum())} for name in sorted(set(df.dataset))}
    card = {"model": comparison["chosen"], "seed": seed, "collection_seeds": seeds,
            "datasets": [str(d) for d in datasets], "data": data, "features": list(FEATURE_NAMES),
            "collection_overrides": COLLECT_OVERRIDES, "collection_score": COLLECT_SCORE,
            "held_apart": f"scenes whose index is {CALIBRATION_REST} mod {CALIBRATION_EVERY}",
            "cross_sensor": {k: v for k, v in comparison.items() if k != "chosen"},
            "calibration": model.calibration, "knots": len(model.knots[0]), "command": command,
            "versions": _versions()}
    lines = [f"# Model card: the fitted verdict ({comparison['chosen']})", "",
             "The probability that a verified sphere's centre lies within 2 cm (3 cm beyond 3 m) of a ball's, "
             "from the quantities verification measures on it (`method/verdict.py`, FEATURE_NAMES).", "",
             "- Data: the improved detector's candidates, collected with no verdict (nothing accepted, every search "
             "and retry run, every distinct verified sphere that passes the size check) on "
             + ", ".join(f"`{d}` ({v['scenes']} scenes, {v['candidates']} candidates, {v['positives']} positive)"
                         for d, v in data.items())
             + f", run seeds {', '.join(map(str, seeds))}.",
             f"- Fit: every scene but the held-apart ones ({card['held_apart']}); calibration: isotonic regression "
             f"on the held-apart ones ({len(model.knots[0])} knots, in the ONNX metadata).",
             f"- Recipe: `{comparison['chosen']}` (`eval/bench/verdict_fit.py`, MODELS: its library, settings and "
             f"monotone constraints), seed {seed}; chosen by the least mean log loss over the folds below.",
             f"- Command: `{command}`",
             "- Versions: " + ", ".join(f"{k} {v}" for k, v in card["versions"].items()) + ".", "",
             "## Chosen across sensors", "",
             "Each model fitted on one part and judged on a sensor it has not seen (average precision, ROC AUC, "
             "log loss of the uncalibrated output).", "",
             "| model | " + " | ".join(f for f in next(iter(card["cross_sensor"].values()))) + " |",
             "|---|" + "---|" * len(next(iter(card["cross_sensor"].values())))]
    for name, per_fold in card["cross_sensor"].items():
        lines.append(f"| {name} | " + " | ".join(f"AP {v['ap']:.3f}, AUC {v['auc']:.3f}, log loss {v['log_loss']:.3f}"
                                                  for v in per_fold.values()) + " |")
    lines += ["", "## Calibrated, on the held-apart scenes", "",
              "| set | candidates | positive | AP | ECE |", "|---|---|---|---|---|"]
    lines += [f"| {d} | {v['n']} | {v['positives']} | {v['ap']:.3f} | {v['ece']:.3f} |" for d, v in model.calibration.items()]
    return card, "\n".join(lines) + "\n"


def train_verifier(datasets: list[Path], out: Path, seed: int, seeds: list[int], workers: int, command: str,
                   progress=print) -> dict:
    """Collect, choose, fit and write out/verdict.onnx, out/verdict_card.json and out/verdict_card.md
    (all or none); returns the card."""
    from spherebench.datasets.outputs import replace_files
    from spherebench.datasets.inout import json_bytes

    progress(f"collecting candidates on {', '.join(map(str, datasets))} (seeds {seeds})")
    df = collect(datasets, seeds, workers)
    progress(f"{len(df)} candidates, {int(df['label'].sum())} positive; comparing {', '.join(MODELS)} across sensors")
    comparison = choose(df, seed)
    progress(f"chosen: {comparison['chosen']}; fitting and calibrating")
    model = fit(df, comparison["chosen"], seed)
    card, md = model_card(df, comparison, model, seed, seeds, datasets, command)
    out.mkdir(parents=True, exist_ok=True)
    replace_files({out / "verdict.onnx": model.onnx_bytes, out / "verdict_card.json": json_bytes(card),
                   out / "verdict_card.md": md.encode()})
    return card
