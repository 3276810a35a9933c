"""The detector's configuration: its groups, presets, flat form, validation and the kernels' vector."""

from __future__ import annotations

import dataclasses
import math

import pytest

from spherebench.camera import Intrinsics
from spherebench.errors import SphereBenchError
from spherebench.method import IMPROVED, PAPER, PAPER_LSTSQ, config_for
from spherebench.method import frame_kernels, search_kernels, verification_kernels
from spherebench.method import frame as frame_stage
from spherebench.method.config import FLAT_NAMES, GROUPS, REMOVED, DetectorConfig

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
# ... and with every setting the vector then held changed, at 640x480, bin 2, strata (5, 6), far depth
# 2.5 m, A = 0.004 / m, a correlation length of 2 px (radius_m 0.11, eps_m 0.012, noise_sigmas 2.0; the
# other settings it held are the kernels' constants since)
CHANGED = {"radius_m": 0.11, "eps_m": 0.012, "noise.noise_sigmas": 2.0}
OLD_CHANGED_640 = [
    321.59999999999997, 321.59999999999997, 319.5, 239.5, 0.11, 0.012, 0.004, 2.0, 0.165, 5.0, 2.0,
    3.1158155324088104, 320.0, 0.1, 2.5, 6.0, 4.0, 0.25, 0.5, 1.5, 0.25, 2.0, 3.0, 0.3, 3.0, 1.3, 0.3, 0.8, 0.3,
    1.2, 0.5, 3.0, 0.25, 0.25, 0.3, 1.7726372048266517, 0.0, 0.0]
#: the old vector's slots that held a setting, now the kernels' constants (index -> constant)
BECAME_CONSTANTS = {13: "PRETEST_SLACK", 17: "BOX_HALF_FRACTION", 18: "BOX_OFFSET_FRACTION",
                    19: "RING_OFFSET_FRACTION", 20: "RING_HALF_FRACTION", 21: "PREFILTER_OFFSET_FRACTION",
                    22: "DESCENT_STEPS", 23: "BOX_MIN_VALID", 24: "PRETEST_MAX_CONTINUED", 25: "RING_FACTOR",
                    26: "PROFILE_INNER_SQ", 27: "PROFILE_OUTER_SQ", 28: "RING_FRONT_MIN_FRACTION",
                    29: "RING_FRONT_MAX_FRACTION", 30: "FIRST_BAND_FRACTION", 31: "FIRST_STEPS",
                    32: "COARSE_BAND_FRACTION", 33: "SIZE_LIMIT_FRACTION", 34: "RADIUS_SE_S_MIN_FRACTION"}


def _constant(name: str):
    """A stage constant of the kernels, from the module that holds it."""
    return next(getattr(m, name) for m in (search_kernels, verification_kernels) if hasattr(m, name))


def _less_constants(old: list) -> list:
    return [v for i, v in enumerate(old) if i not in BECAME_CONSTANTS]


@pytest.mark.parametrize("config", [IMPROVED, PAPER, PAPER_LSTSQ], ids=["improved", "paper", "paper-lstsq"])
def test_packed_vector_equals_the_hand_packed_one_less_the_constants(config):
    """The vector is the hand-packed one of 2cf5b07 without the slots that became the kernels'
    constants, each constant the value its slot held by default."""
    added = []  # the slots added since follow the old ones: none (the relief order's came and went)
    for (w, h, b), old in (((424, 240, 1), OLD_DEFAULT_424), ((848, 480, 2), OLD_DEFAULT_848)):
        prm = frame_stage.parameters(config, Intrinsics.d435(w, h), (7, 9), b, (h // b, w // b), 3.12, corr_px=1.5)
        assert prm.tolist() == _less_constants(old) + added, (w, h)
        assert all(_constant(name) == old[i] for i, name in BECAME_CONSTANTS.items())
    changed = config.override(CHANGED)
    prm = frame_stage.parameters(changed, Intrinsics.d435(640, 480), (5, 6), 2, (240, 320), 2.5, a=0.004, corr_px=2.0)
    assert prm.tolist() == _less_constants(OLD_CHANGED_640) + added


def test_slot_constants_follow_the_declared_list():
    assert frame_kernels.N_PRM == len(frame_kernels.PARAMETERS) == 19
    for index, name in enumerate(frame_kernels.PARAMETERS):
        assert getattr(frame_kernels, "P_" + name) == index and type(getattr(frame_kernels, "P_" + name)) is int
    assert (frame_kernels.P_FX, frame_kernels.P_CELL_PX, frame_kernels.P_MEAN_NOISE, frame_kernels.P_OCCLUDER_BOUND) == (0, 15, 16, 18)


def test_flat_form_keeps_the_published_names_and_order():
    flat = IMPROVED.flat()
    assert list(flat)[:5] == ["radius_m", "eps_m", "pipeline", "sampling", "sample_radius_m"]
    # the settings of before the groups keep their order (less those removed); those added since follow
    assert list(flat)[-5:] == ["retry_disc", "retry_hole", "accept_score", "rank_floor", "retry_relief"]
    assert len(flat) == len(FLAT_NAMES) == 45 and flat["min_score"] == 0.67
    assert not REMOVED & set(FLAT_NAMES) and len(REMOVED) == 101
    for preset in (IMPROVED, PAPER, PAPER_LSTSQ):
        assert DetectorConfig.from_flat({"engine": "detector", **preset.flat()}) == preset
    # a flat form of before (a cached result's) still reads: the removed names are left out
    assert DetectorConfig.from_flat({**IMPROVED.flat(), "ring_front_power": 4.0, "fitted_verdict": True}) == IMPROVED
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
    ({"outline.outline_noise_fraction": -1.0}, "outline.outline_noise_fraction=-1.0 must be >= 0 (a fraction of R; inf"),
    ({"verification.rank_floor": 1.5}, "verification.rank_floor=1.5 must be within"),
    ({"paper.zscore_threshold": 0.0}, "paper.zscore_threshold=0.0 must be > 0"),
    ({"eps_m": 0.2}, "eps_m=0.2 must be smaller than the radius 0.12"),
    ({"pipeline": "paper"}, "the paper pipeline samples globally"),
])
def test_each_group_checks_its_settings(bad, says):
    with pytest.raises(SphereBenchError, match="invalid detector configuration: .*" + says.replace("(", r"\(")
                       .replace(")", r"\)")):
        config_for("improved", bad)


def test_infinity_means_never_only_where_a_setting_says_so():
    never = {"outline.outline_noise_fraction": math.inf}
    assert config_for("improved", never).outline.outline_noise_fraction == math.inf
    with pytest.raises(SphereBenchError, match="refinement.size_sigmas=inf must be a finite number"):
        config_for("improved", {"refinement.size_sigmas": math.inf})
