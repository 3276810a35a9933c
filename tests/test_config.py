"""The detector's configuration: its groups, presets, flat form, validation and the kernels' vector."""

from __future__ import annotations

import dataclasses
import math

import pytest

from spherebench.camera import Intrinsics
from spherebench.errors import SphereBenchError
from spherebench.method import IMPROVED, PAPER, PAPER_LSTSQ, config_for
from spherebench.method import _kernels as K
from spherebench.method import improved as I
from spherebench.method.config import FLAT_NAMES, GROUPS, PATHS, DetectorConfig

# The kernels' parameter vector as the hand-packed ``improved.parameters`` of 2cf5b07 (before the
# declared slot list) made it: the default configuration (the paper presets give the same vector:
# they differ only in settings the vector does not hold) at 424x240, bin 1, and at 848x480, bin 2,
# strata (7, 9), far depth 3.12 m, the model's noise, a correlation length of 1.5 px.
OLD_DEFAULT_424 = [
    213.05999999999997, 213.05999999999997, 211.5, 119.5, 0.12, 0.01, 0.007509621702806722, 2.5, 0.18, 7.0, 1.0,
    5.843931428571428, 424.0, 0.1, 3.12, 9.0, 1.0, 0.25, 0.5, 1.5, 0.25, 2.0, 3.0, 0.3, 3.0, 1.3, 0.3, 0.8, 0.3,
    1.2, 0.5, 3.0, 0.25, 0.25, 0.3, 2.658680777563778, 0.0, 0.0]
OLD_DEFAULT_848 = [
    426.11999999999995, 426.11999999999995, 423.5, 239.5, 0.12, 0.01, 0.003754810851403361, 2.5, 0.18, 7.0, 2.0,
    4.177783527182805, 424.0, 0.1, 3.12, 9.0, 4.0, 0.25, 0.5, 1.5, 0.25, 2.0, 3.0, 0.3, 3.0, 1.3, 0.3, 0.8, 0.3,
    1.2, 0.5, 3.0, 0.25, 0.25, 0.3, 1.3396588315535125, 0.0, 0.0]
# ... and with every setting the vector holds changed, at 640x480, bin 2, strata (5, 6), far depth
# 2.5 m, A = 0.004 / m, a correlation length of 2 px
CHANGED = {"radius_m": 0.11, "eps_m": 0.012, "noise.noise_sigmas": 2.0, "noise.max_eps_fraction": 1.2,
           "search.pretest_slack": 0.15, "stencil.box_half_fraction": 0.3, "stencil.box_offset_fraction": 0.55,
           "stencil.ring_offset_fraction": 1.4, "stencil.ring_half_fraction": 0.2,
           "stencil.prefilter_offset_fraction": 2.2, "stencil.descent_steps": 4, "stencil.box_min_valid": 0.35,
           "stencil.pretest_max_continued": 2, "evidence.ring_factor": 1.35, "evidence.profile_inner_sq": 0.25,
           "evidence.profile_outer_sq": 0.75, "evidence.ring_front_min_fraction": 0.2,
           "evidence.ring_front_max_fraction": 1.1, "refinement.first_band_fraction": 0.6,
           "refinement.first_steps": 2, "refinement.coarse_band_fraction": 0.3,
           "refinement.size_limit_fraction": 0.2, "refinement.radius_se_s_min_fraction": 0.35,
           "stencil.search_off_axis": True}
OLD_CHANGED_640 = [
    321.59999999999997, 321.59999999999997, 319.5, 239.5, 0.11, 0.012, 0.004, 2.0, 0.132, 5.0, 2.0,
    3.1158155324088104, 320.0, 0.15, 2.5, 6.0, 4.0, 0.3, 0.55, 1.4, 0.2, 2.2, 4.0, 0.35, 2.0, 1.35, 0.25, 0.75,
    0.2, 1.1, 0.6, 2.0, 0.3, 0.2, 0.35, 1.7726372048266517, 1.0, 0.0]


@pytest.mark.parametrize("config", [IMPROVED, PAPER, PAPER_LSTSQ], ids=["improved", "paper", "paper-lstsq"])
def test_packed_vector_equals_the_hand_packed_one(config):
    # the slots added since follow the old ones: P_ORDER_RELIEF (0: the pretest's order, set by a retry)
    added = [0.0]
    for (w, h, b), old in (((424, 240, 1), OLD_DEFAULT_424), ((848, 480, 2), OLD_DEFAULT_848)):
        prm = I.parameters(config, Intrinsics.d435(w, h), (7, 9), b, (h // b, w // b), 3.12, corr_px=1.5)
        assert prm.tolist() == old + added, (w, h)
    changed = config.override(CHANGED)
    prm = I.parameters(changed, Intrinsics.d435(640, 480), (5, 6), 2, (240, 320), 2.5, a=0.004, corr_px=2.0)
    assert prm.tolist() == OLD_CHANGED_640 + added
    assert set(CHANGED) == {path for _, path in K.PARAMETERS if path} | {"noise.max_eps_fraction"}


def test_slot_constants_follow_the_declared_list():
    assert K.N_PRM == len(K.PARAMETERS) == 39
    for index, (name, path) in enumerate(K.PARAMETERS):
        assert getattr(K, "P_" + name) == index and type(getattr(K, "P_" + name)) is int
        assert path is None or path in PATHS, path
    assert (K.P_FX, K.P_CELL_PX, K.P_H_FRAC, K.P_SE_S_MIN, K.P_MEAN_NOISE, K.P_OCCLUDER_BOUND) == (0, 16, 17, 34, 35, 37)


def test_flat_form_keeps_the_published_names_and_order():
    flat = IMPROVED.flat()
    assert list(flat)[:5] == ["radius_m", "eps_m", "pipeline", "sampling", "sample_radius_m"]
    # the 134 settings of before the groups keep their order; those added since follow them
    assert list(flat)[131:134] == ["ring_spread_power", "interior_density_power", "calibrate_evidence"]
    assert list(flat)[134:] == ["retry_hole", "hole_min_ring", "hole_min_fraction", "hole_step_fraction",
                                "hole_min_range_m", "score_calibration", "calibration_slope", "calibration_offset",
                                "accept_score", "rank_floor", "retry_relief", "fitted_verdict"]
    assert len(flat) == len(FLAT_NAMES) == 146 and flat["min_score"] == 0.67
    for preset in (IMPROVED, PAPER, PAPER_LSTSQ):
        assert DetectorConfig.from_flat({"engine": "detector", **preset.flat()}) == preset
    grouped = sum(len(dataclasses.fields(cls)) for cls in GROUPS.values())
    assert grouped + 3 == len(FLAT_NAMES)  # every setting once: the model's three and the groups'


def test_presets_and_overrides():
    assert (PAPER.pipeline, PAPER.search.sampling, PAPER.search.iterations, PAPER.search.adaptive) == (
        "paper", "global", 1000, False)
    assert (PAPER.paper.refine, PAPER.verification.max_spheres, PAPER.verification.min_inliers,
            PAPER.verification.min_score) == ("barycentre", 1, 3, 0.0)
    assert PAPER_LSTSQ.search.solver == "lstsq_eq12" and PAPER_LSTSQ.override({"search.solver": "known_radius"}) == PAPER
    a = config_for("improved", {"verification.min_score": 0.4}, radius_m=0.2, search={"iterations": 500})
    assert (a.verification.min_score, a.radius_m, a.search.iterations) == (0.4, 0.2, 500)
    assert a.get("verification.min_score") == 0.4 and a.get("radius_m") == 0.2
    assert IMPROVED.verification.min_score == 0.67  # presets are not changed
    with pytest.raises(SphereBenchError, match=r"unknown detector parameter min_score \(now verification.min_score\)"):
        config_for("improved", min_score=0.4)
    with pytest.raises(SphereBenchError, match="unknown detector parameter"):
        config_for("improved", {"search.nothing": 1})
    with pytest.raises(SphereBenchError, match="unknown detector method"):
        config_for("hough")


@pytest.mark.parametrize("bad, says", [
    ({"search.iterations": 0}, "search.iterations=0 must be 1-10000000"),
    ({"search.iterations": 2.5}, "search.iterations=2.5 must be an integer"),
    ({"search.confidence": 1.0}, "search.confidence=1.0 must be within (0, 1)"),
    ({"refinement.size_check": "yes"}, "refinement.size_check='yes' must be true or false"),
    ({"noise.noise_z2_per_m": math.nan}, "noise.noise_z2_per_m=nan must be a finite number"),
    ({"noise.noise_estimate_min_samples": 2000}, "noise.noise_estimate_min_samples=2000 must not exceed"),
    ({"outline.outline_max_bias_px": 0.0}, "outline.outline_max_bias_px=0.0 must be > 0 (pixels; inf for never)"),
    ({"evidence.ring_front_min_fraction": 2.0}, "evidence.ring_front_min_fraction=2.0 must be below"),
    ({"paper.zscore_threshold": 0.0}, "paper.zscore_threshold=0.0 must be > 0"),
    ({"eps_m": 0.2}, "eps_m=0.2 must be smaller than the radius 0.12"),
    ({"pipeline": "paper"}, "the paper pipeline samples globally"),
    ({"verification.calibration_slope": 0.0}, "verification.calibration_slope=0.0 must be > 0 (the map must rise"),
])
def test_each_group_checks_its_settings(bad, says):
    with pytest.raises(SphereBenchError, match="invalid detector configuration: .*" + says.replace("(", r"\(")
                       .replace(")", r"\)")):
        config_for("improved", bad)


def test_infinity_means_never_only_where_a_setting_says_so():
    never = {"verification.multistart_noise_fraction": math.inf, "outline.outline_noise_fraction": math.inf,
             "outline.outline_evidence_noise_fraction": math.inf, "outline.outline_max_bias_px": math.inf}
    assert config_for("improved", never).outline.outline_max_bias_px == math.inf
    with pytest.raises(SphereBenchError, match="evidence.ring_factor=inf must be a finite number"):
        config_for("improved", {"evidence.ring_factor": math.inf})


def test_the_score_map_is_increasing_and_raw_its_inverse():
    """score = sigmoid(a logit(raw) + b): strictly increasing, 0 and 1 fixed; accept_score and rank_floor
    (probabilities) are compared inside the detector as their inverse images on the raw product; off,
    the two are one (the hand-set verdict's map: the fitted verdict's score is its probability)."""
    v = IMPROVED.override({"verification.fitted_verdict": False}).verification
    raws = [0.0, 1e-9, 0.1, 0.3, 0.35, 0.5, 0.9, 1.0 - 1e-6, 1.0]
    probs = [v.probability(r) for r in raws]
    assert probs[0] == 0.0 and probs[-1] == 1.0 and all(a < b for a, b in zip(probs, probs[1:]))
    assert v.probability(v.accept_raw_score) == pytest.approx(v.accept_score, abs=1e-12)
    assert v.accept_raw_score == pytest.approx(0.349, abs=1e-3)  # the raw threshold of before the map
    assert v.probability(v.floor_raw_score) == pytest.approx(v.rank_floor, abs=1e-12)
    for p in (0.0, 0.2, 0.9, 1.0):
        w = config_for("improved", {"verification.accept_score": p}).verification
        assert w.probability(w.accept_raw_score) == pytest.approx(p, abs=1e-12)
    # the floor never lies above acceptance: every accepted candidate ranks
    high = config_for("improved", {"verification.rank_floor": 0.9}).verification
    assert high.floor_raw_score == high.accept_raw_score
    off = config_for("improved", {"verification.score_calibration": False}).verification
    assert off.probability(0.42) == 0.42 and off.accept_raw_score == off.accept_score
    assert not PAPER.verification.score_calibration and PAPER.verification.probability(0.42) == 0.42
