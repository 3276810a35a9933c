"""The fitted verdict: its features, the shipped model, and the fit that makes it (make train-verifier)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from spherebench.method.config import IMPROVED
from spherebench.method.verdict import FEATURE_NAMES, MODEL_PATH, N_FEATURES, FittedVerdict, load_verdict, verdict_features

pytest.importorskip("sklearn")
pytest.importorskip("skl2onnx")

from spherebench.eval.bench import verdict_fit  # noqa: E402

R = 0.12


def ball_stats(**changes) -> dict:
    """A verified ball's measurements at 1.2 m as ``improved._verify_once`` records them."""
    s = {"valid_disc": 400.0, "inlier": 380.0, "front": 4.0, "front_near": 2.0, "behind": 6.0, "invalid_disc": 20.0,
         "ring": 60.0, "ring_continued": 3.0, "ring_front": 1.0, "valid_inner": 150.0, "behind_inner": 1.0,
         "edge_n": 50.0, "edge_behind": 4.0, "ring_spread": 0.0, "inner_n": 150.0, "inner_sum": 0.0,
         "outer_h_n": 80.0, "outer_h_sum": 0.0, "outer_v_n": 80.0, "outer_v_sum": 0.0, "pixels_per_sample": 2.0,
         "sigma_m": 0.003, "sigma_measured_m": 0.003, "eps_m": 0.009, "visible_fraction": 0.99, "depth_m": 1.2,
         "n_inliers": 380.0, "rmse_m": 0.003, "free_radius_m": 0.121, "free_radius_se_m": 0.002, "noise_ratio": 1.0}
    s.update(changes)
    return s


def test_features_are_the_named_shares_and_ratios():
    x = verdict_features(ball_stats(), R)
    assert x.shape == (N_FEATURES,) and x.dtype == np.float32 and np.all(np.isfinite(x))
    f = dict(zip(FEATURE_NAMES, x.tolist()))
    assert f["coverage"] == pytest.approx(380 / 400)
    assert f["invalid_share"] == pytest.approx(20 / 420)
    assert f["edge_behind"] == pytest.approx(4 / 50)
    assert f["size_r"] == pytest.approx(0.001 / R, rel=1e-4)
    assert f["size_z"] == pytest.approx(0.5, rel=1e-4)
    assert f["log_depth"] == pytest.approx(math.log(1.2), rel=1e-6)
    # a flatter surface: the inner zone's residuals behind the outer zones' -> relief > 0
    flat = dict(zip(FEATURE_NAMES, verdict_features(ball_stats(inner_sum=150 * 0.01), R).tolist()))
    assert flat["relief_r"] == pytest.approx(0.01 / R, rel=1e-4) and flat["relief_t"] > 5


def test_features_of_a_candidate_without_free_radius_are_finite():
    x = verdict_features(ball_stats(free_radius_m=float("nan"), free_radius_se_m=float("nan"), inner_n=0.0,
                                    valid_disc=0.0, ring=0.0, edge_n=0.0, valid_inner=0.0), R)
    assert np.all(np.isfinite(x))


def test_the_shipped_model_loads_and_ranks_a_ball_above_a_wall():
    v = load_verdict()
    ball = v.probability(ball_stats(), R)
    wall = v.probability(ball_stats(ring_continued=55.0, inner_sum=150 * 0.02, coverage=0.5, inlier=150.0,
                                    free_radius_m=0.16, free_radius_se_m=0.01), R)
    assert 0.0 <= wall < ball <= 1.0 and ball > 0.67
    assert np.all(np.diff(v.knots_p) >= 0) and np.all(np.diff(v.knots_score) >= 0)


def test_a_batch_scores_each_candidate_as_alone():
    """FittedVerdict.batch_scores: one run of the model for several candidates, each row's (raw,
    probability) equal to ``scores``' on it alone; ``verdicts`` of the same measurements as rows gives
    the same, and of none none."""
    from spherebench.method.verdict import measurement_row, verdicts

    model = load_verdict()
    batch = [ball_stats(), ball_stats(inner_sum=150 * 0.01), ball_stats(free_radius_m=0.105, behind=120.0),
             ball_stats(depth_m=3.1, sigma_m=0.02)]
    together = model.batch_scores(batch, R)
    raw, p = verdicts(np.stack([measurement_row(s) for s in batch]), R)
    assert together == [model.scores(s, R) for s in batch] == list(zip(raw.tolist(), p.tolist()))
    assert len({t[0] for t in together}) > 1  # the rows differ: no row took another's answer
    assert [len(a) for a in verdicts(np.zeros((0, len(batch[0]) + 1)), R)] == [0, 0]
    assert model.batch_scores(batch[:1], R) == [model.scores(batch[0], R)]


def test_a_record_lacking_a_measurement_the_features_read_is_refused():
    """``measurement_row``: a measurement the features read is required (those of older records take
    their neutral value); one they do not read may be missing."""
    from spherebench.method.verdict import measurement_row

    stats = ball_stats()
    del stats["eps_m"], stats["front"], stats["noise_ratio"]
    assert np.array_equal(verdict_features(stats, R), verdict_features({**stats, "noise_ratio": 1.0}, R))
    del stats["rmse_m"]
    with pytest.raises(KeyError):
        measurement_row(stats)


def test_a_detection_scores_as_its_evidence_does():
    """What the detector scores (its measurements, compiled) and what the verdict's fit reads (a
    sphere's evidence by name, ``verdict_features``) are the same features: a clear ball's raw score
    is the model's on its evidence."""
    from spherebench.camera import Intrinsics, image_rays
    from spherebench.cloud import cloud_from_depth
    from spherebench.method import detect

    intr = Intrinsics.d435(160, 120)
    u = image_rays(intr)
    u = u / np.linalg.norm(u, axis=-1, keepdims=True)
    c = np.array([0.1, -0.05, 1.0])
    tc = u @ c
    m2 = c @ c - tc * tc
    depth = np.where(m2 < R * R, (tc - np.sqrt(np.maximum(R * R - m2, 0.0))) * u[..., 2], 1.8)
    depth += np.random.default_rng(0).normal(0.0, 0.002, depth.shape)
    spheres = detect(cloud_from_depth(depth, intr), IMPROVED, seed=0)
    assert len(spheres) == 1 and "score_single" not in spheres[0].evidence  # scored once, not rescored
    raw, _ = load_verdict().scores(spheres[0].evidence, R)
    assert raw == spheres[0].raw_score


def test_the_shipped_model_never_rises_with_what_a_ball_would_not_show():
    """Monotone in the physical facts (``verdict_fit.MONOTONE``): more of the silhouette seen behind
    the sphere, through it or on its edge band never makes a candidate more probable."""
    v = load_verdict()
    base = ball_stats()
    for key, total in (("behind", "valid_disc"), ("behind_inner", "valid_inner"), ("edge_behind", "edge_n"),
                       ("ring_continued", "ring")):
        probs = [v.probability({**base, key: share * base[total]}, R) for share in np.linspace(0.0, 0.9, 10)]
        assert all(b <= a + 1e-9 for a, b in zip(probs, probs[1:])), key


def test_the_card_beside_the_model_names_its_features():
    card = json.loads(MODEL_PATH.with_name("verdict_card.json").read_text())
    assert card["features"] == list(FEATURE_NAMES) and card["model"] in verdict_fit.MODELS


def synthetic_candidates(n_scenes: int = 200, seed: int = 0):
    """Candidates of two 'sensors' whose label depends on two features (pandas DataFrame)."""
    import pandas as pd

    rng = np.random.default_rng(seed)
    rows = []
    for dataset in ("train", "train-stereo"):
        for k in range(n_scenes):
            for _ in range(3):
                x = rng.normal(size=N_FEATURES).astype(np.float32)
                logit = 2.5 * x[7] - 2.0 * x[19] + (0.5 if dataset == "train" else -0.5)
                row = {"dataset": dataset, "index": k, "label": bool(rng.random() < 1 / (1 + math.exp(-logit))),
                       "ambient_e_per_ms": float(rng.uniform(10, 300)) if dataset == "train-stereo" else math.nan}
                row.update(zip(FEATURE_NAMES, x.tolist()))
                rows.append(row)
    return pd.DataFrame(rows)


def test_folds_judge_each_fit_on_scenes_of_a_sensor_it_has_not_seen():
    df = synthetic_candidates(50)
    cal = verdict_fit._is_calibration(df)
    for name, fit_rows, judged in verdict_fit.folds(df):
        assert not np.any(fit_rows & judged) and not np.any((fit_rows | judged) & cal)
        assert judged.sum() > 0
    # the stereo halves split by ambient light: no scene of the judged half is fitted on
    low_fit, high_judged = verdict_fit.folds(df)[0][1], verdict_fit.folds(df)[0][2]
    assert np.all(df["ambient_e_per_ms"][high_judged] >= verdict_fit.AMBIENT_SPLIT_E_PER_MS)
    assert np.all((df["dataset"][low_fit] == "train") | (df["ambient_e_per_ms"][low_fit] < verdict_fit.AMBIENT_SPLIT_E_PER_MS))


def test_fit_exports_a_calibrated_onnx_model_the_detector_loads(tmp_path):
    df = synthetic_candidates()
    a = verdict_fit.fit(df, "logistic", seed=3)
    assert a.onnx_bytes == verdict_fit.fit(df, "logistic", seed=3).onnx_bytes  # same seed, same model
    import onnx

    domains = [o.domain for o in onnx.load_model_from_string(a.onnx_bytes).opset_import]
    assert domains == sorted(domains)  # not the exporter's set order, which varies between runs
    path = tmp_path / "verdict.onnx"
    path.write_bytes(a.onnx_bytes)
    v = FittedVerdict(path)
    x = df[list(FEATURE_NAMES)].to_numpy(np.float32)
    s = v.model_scores(x[:50])
    assert np.all((s >= 0) & (s <= 1))
    p = np.interp(s, v.knots_score, v.knots_p)
    # the calibrated probability follows the label's rate on the held-apart scenes
    assert abs(float(np.mean(p)) - float(df["label"][:50].mean())) < 0.2
    assert set(a.calibration) == {"train", "train-stereo"} and all(c["ece"] < 0.1 for c in a.calibration.values())


def test_the_lightgbm_export_gives_the_fitted_probabilities(tmp_path):
    df = synthetic_candidates(80)
    a = verdict_fit.fit(df, "lgbm-300-monotone", seed=1)
    assert a.onnx_bytes == verdict_fit.fit(df, "lgbm-300-monotone", seed=1).onnx_bytes
    path = tmp_path / "verdict.onnx"
    path.write_bytes(a.onnx_bytes)
    x = df[list(FEATURE_NAMES)].to_numpy(np.float32)
    model = verdict_fit.MODELS["lgbm-300-monotone"](1).fit(x[~verdict_fit._is_calibration(df)],
                                                         df["label"][~verdict_fit._is_calibration(df)].astype(int))
    np.testing.assert_allclose(FittedVerdict(path).model_scores(x[:40]), model.predict_proba(x[:40])[:, 1], atol=1e-5)


def test_a_model_of_other_features_is_refused(tmp_path):
    import onnx

    model = onnx.load_model_from_string(verdict_fit.fit(synthetic_candidates(60), "logistic", seed=0).onnx_bytes)
    for entry in model.metadata_props:
        if entry.key == "feature_names":
            entry.value = json.dumps(list(FEATURE_NAMES)[:-1])
    path = tmp_path / "other.onnx"
    path.write_bytes(model.SerializeToString())
    with pytest.raises(ValueError, match="train-verifier"):
        FittedVerdict(path)


def test_choose_compares_every_model_on_each_fold():
    out = verdict_fit.choose(synthetic_candidates(60), seed=0)
    assert out["chosen"] in verdict_fit.MODELS
    assert set(out) == set(verdict_fit.MODELS) | {"chosen"}
    assert all(len(out[m]) == 3 for m in verdict_fit.MODELS)


def test_collect_labels_every_candidate_of_a_dataset(small_default):
    df = verdict_fit.collect([small_default], [0], workers=1)
    assert len(df) >= 6 and set(FEATURE_NAMES) <= set(df.columns)
    assert df["label"].sum() >= 5  # the balls of six clean and cluttered scenes
    assert np.all(np.isfinite(df[list(FEATURE_NAMES)].to_numpy()))


def test_the_fitted_verdict_scores_detections_with_its_probability(small_default):
    from spherebench.datasets import inout
    from spherebench.method.detector import detect

    cloud = inout.load_cloud(inout.list_scenes(small_default)[0])
    spheres = detect(cloud, IMPROVED, seed=0)
    verdict = load_verdict()
    assert spheres and all(0.67 <= s.score <= 1.0 for s in spheres)
    assert all(s.score == pytest.approx(float(np.interp(s.raw_score, verdict.knots_score, verdict.knots_p)))
               for s in spheres)


def test_a_refitted_verdict_invalidates_the_benchmarks_cached_predictions():
    from spherebench.eval.bench.registry import detector_spec
    from spherebench.provenance import file_sha256

    assert detector_spec("improved").extra_fingerprint == file_sha256(MODEL_PATH)
    assert detector_spec("paper").extra_fingerprint == ""
