"""One configuration object for the sphere detector, in groups, with the paper's values as named presets.

Every length is in metres (``_m``), every image size in pixels (``_px``); a ``_fraction`` without
another unit is a fraction of the ball radius R (of the ball's disc radius r in the search's
stencil). ``DetectorConfig`` holds the model (R, eps, the pipeline) and one frozen group per stage:
``search``, ``paper``, ``noise``, ``retry``, ``verification``, ``refinement``, ``outline`` and
``input``. A setting is named by its path, ``verification.min_score`` (``--set
verification.min_score=0.4``); ``override`` and ``config_for`` take such paths. The settings are the
physical facts (R, the sensor's noise) and the error rates (the bound's confidence, the score
thresholds), with the switches an ablation needs; how a stage works is its module's constants
(``frame``, ``noise``, ``search``, ``verification``, ``outline`` and their kernels), and whether a
candidate is a ball is the fitted verdict's (``verdict``).

Presets: ``PAPER`` is section 2.5 of Roman-Rivera et al. (2023) as written (three points drawn from
the whole cloud, the known-radius minimal solver, eps = 1 cm, 1,000 iterations, the candidate-centre
list, choice by most points, z-score filter at 1.5 on the point-to-centre distance, barycentre);
``PAPER_LSTSQ`` the same with the literal least-squares reading of the printed Eq. (12) (rank-
deficient, see ``sphere_model``); ``IMPROVED`` (the default) local sampling, adaptive iterations,
noise-aware tolerances, least-squares refinement with R fixed, a size check, several spheres per
frame, ranked by the fitted verdict's probability (docs/detector.md). How the defaults were chosen:
docs/experiments/2026-12-04-config-history.md.

The flat form (``flat``/``from_flat``: every setting by its bare name, in one fixed order) is what
results and caches record and hash; it is unchanged by the grouping.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import operator
import typing
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

from spherebench.errors import SphereBenchError
from spherebench.reading import shown

PIPELINES = ("paper", "improved")
SAMPLINGS = ("global", "local")
SOLVERS = ("known_radius", "lstsq_eq12")
REFINES = ("barycentre", "least_squares")
ZSCORE_VARIABLES = ("distance", "residual", "x", "y", "z", "xyz")


# ------------------------------------------------------------------------------------------ checks
# A group's rules: {field: rule}. A rule is an interval "[0, 1]", "(0, 4]", a bound ">= 0", "> 0",
# an integer range "1-20", or a tuple of allowed strings; "inf" in a rule's note admits infinity.

def _bad_type(path: str, v, kind: str) -> str | None:
    if kind == "bool":
        return None if isinstance(v, bool) else f"{path}={shown(v, repr)} must be true or false"
    if kind == "str":
        return None if isinstance(v, str) else f"{path}={shown(v, repr)} must be a string"
    if isinstance(v, bool) or not isinstance(v, int if kind == "int" else (int, float)):
        return f"{path}={shown(v, repr)} must be {'an integer' if kind == 'int' else 'a number'}"
    return None


def _breaks(v, rule: str) -> bool:
    if "-" in rule and rule[0].isdigit():  # an integer range
        lo, hi = (int(x) for x in rule.split("-"))
        return not lo <= v <= hi
    if rule[0] in "[(":
        lo, hi = (float(x) for x in rule[1:-1].split(","))
        return not ((lo <= v if rule[0] == "[" else lo < v) and (v <= hi if rule[-1] == "]" else v < hi))
    op, bound = rule.split()
    return not (v >= float(bound) if op == ">=" else v > float(bound))


@functools.cache
def _hints(cls) -> dict:
    return typing.get_type_hints(cls)


def _bad_value(path: str, v, kind: str, rule, note: str) -> str | None:
    """A value of the right type against its rule; a float must be finite unless its note admits
    infinity ("inf for never"), and then positive."""
    tail = f" ({note})" if note else ""
    if kind == "float" and not math.isfinite(v) and not (v > 0 and "inf" in note):
        return f"{path}={shown(v, repr)} must be {rule}{tail}" if "inf" in note else f"{path}={shown(v, repr)} must be a finite number"
    if isinstance(rule, tuple):
        return None if v in rule else f"{path}={shown(v, repr)} is not one of {', '.join(rule)}"
    if rule is not None and _breaks(v, rule):
        return f"{path}={shown(v, repr)} must be {'within ' if rule[0] in '[(' else ''}{rule}{tail}"
    return None


def _group_problems(group, prefix: str, rules: Mapping[str, object], notes: Mapping[str, str]) -> list[str]:
    """The problems of one group: each field's type (from its annotation), then its rule; ``None``
    passes where the annotation allows it (``float | None``)."""
    out = []
    for f in dataclasses.fields(group):
        v, hint = getattr(group, f.name), _hints(type(group))[f.name]
        optional = typing.get_origin(hint) is not None
        if v is None and optional:
            continue
        kind = (typing.get_args(hint)[0] if optional else hint).__name__
        problem = _bad_type(prefix + f.name, v, kind) or _bad_value(prefix + f.name, v, kind, rules.get(f.name),
                                                                   notes.get(f.name, ""))
        if problem:
            out.append(problem)
    return out


class _Group:
    """A group's validation: ``RULES`` (see above), ``NOTES`` (a rule's explanation) and ``cross``
    (rules between its own fields)."""

    RULES: typing.ClassVar[dict] = {}
    NOTES: typing.ClassVar[dict] = {}

    def problems(self, prefix: str) -> list[str]:
        out = _group_problems(self, prefix, self.RULES, self.NOTES)
        return out or self.cross(prefix)

    def cross(self, prefix: str) -> list[str]:
        return []


# ------------------------------------------------------------------------------------------ groups

@dataclass(frozen=True)
class Search(_Group):
    """The search for hypotheses (organised clouds: a stratified search of the cell grid; unorganised:
    RANSAC on sampled triples)."""

    sampling: str = "local"  # "global" (3 points from the whole cloud) or "local" (2nd and 3rd near the 1st)
    sample_radius_m: float | None = None  # unorganised local sampling radius (m; None: 2R)
    solver: str = "known_radius"  # "known_radius" (the far of two centres) or "lstsq_eq12" (the printed Eq. 12)
    iterations: int = 20000  # iteration limit (organised: about the most strata drawn)
    adaptive: bool = True  # size the strata / stop early by the RANSAC bound
    confidence: float = 0.99  # the bound's probability of one all-inlier sample (an error rate: 1 % of balls missed)
    min_iterations: int = 300  # never fewer iterations (organised: strata)
    max_range_m: float = 6.0  # no ball is looked for beyond this depth (m)
    search_width_px: int = 424  # wider streams are searched on binned cells about this many across

    RULES: typing.ClassVar[dict] = {
        "sampling": SAMPLINGS, "sample_radius_m": "> 0", "solver": SOLVERS, "iterations": "1-10000000",
        "confidence": "(0, 1)", "min_iterations": ">= 0", "max_range_m": "> 0", "search_width_px": ">= 16"}


@dataclass(frozen=True)
class Paper(_Group):
    """The paper pipeline's choice and filter (section 2.5)."""

    candidate_merge_m: float | None = None  # a centre within this of a listed candidate joins it (m; None: eps)
    zscore_threshold: float = 1.5  # drop points whose |z| exceeds it
    zscore_variable: str = "distance"  # z-scored value: "distance", "residual", "x", "y", "z" or "xyz"
    refine: str = "least_squares"  # final centre: "barycentre" (the paper) or "least_squares" (R fixed)

    RULES: typing.ClassVar[dict] = {"candidate_merge_m": "> 0", "zscore_threshold": "> 0",
                                    "zscore_variable": ZSCORE_VARIABLES, "refine": REFINES}


@dataclass(frozen=True)
class Noise(_Group):
    """The depth noise: sigma_z = A z^2 (1/m), from the stereo model, the user or the frame."""

    noise_subpixel: float = 0.08  # stereo model: subpixel disparity RMS (px; Intel's figure; 0: no noise model)
    noise_baseline_m: float = 0.050  # stereo model: baseline (m; the D435's)
    noise_z2_per_m: float | None = None  # A given outright (1/m; None: the stereo model at the stream's fx)
    noise_estimate: bool = True  # organised: measure A on the frame (second differences of depth)
    noise_correlation: bool = True  # organised: measure the noise's correlation length on the frame
    noise_sigmas: float = 2.5  # inlier band: max(eps, noise_sigmas * sigma_z) (1.2 % of a ball's pixels out)

    RULES: typing.ClassVar[dict] = {"noise_subpixel": ">= 0", "noise_baseline_m": ">= 0", "noise_z2_per_m": ">= 0",
                                    "noise_sigmas": ">= 0"}
    NOTES: typing.ClassVar[dict] = {"noise_z2_per_m": "sigma_z / z^2 in 1/m, e.g. 0.0015"}


@dataclass(frozen=True)
class Retry(_Group):
    """Organised clouds, while no sphere is accepted: the searches again (ablations switch them off)."""

    retry_relief: bool = True  # search again ranking hypotheses by their cap's relief against the noise
    retry_occluder: bool = True  # ... leaving out side boxes more than R in front (occluders)
    retry_off_axis: bool = True  # ... then with the stencil stretched off the axis
    retry_disc: bool = True  # ... then for discs standing out of what is behind them
    retry_hole: bool = True  # ... then for holes in the depth ringed by a ball's face (a saturated cap)


@dataclass(frozen=True)
class Verification(_Group):
    """Which hypotheses are verified, and which spheres are reported."""

    verify_candidates: int = 6  # verify at most this many of the best hypotheses ...
    verify_candidates_if_none: int = 16  # ... or this many while none is accepted (organised)
    min_inliers: int = 30  # fewer inliers: no detection
    max_spheres: int = 4  # at most this many spheres per frame
    nms_distance_fraction: float = 0.75  # suppress a sphere within this fraction of 2R of a better one
    accept_score: float = 0.67  # a candidate this probable (below) is taken as a ball: the search narrows, the retries stop
    min_score: float = 0.67  # detect() reports the candidates at least this probable (the search is the same at any)
    rank_floor: float = 0.01  # candidates less probable than this are not ranked (the benchmark's floor, as CircleNet's)

    RULES: typing.ClassVar[dict] = {
        "verify_candidates": ">= 1", "verify_candidates_if_none": ">= 1", "min_inliers": ">= 3",
        "max_spheres": ">= 1", "nms_distance_fraction": "[0, 1]", "accept_score": "[0, 1]", "min_score": "[0, 1]",
        "rank_floor": "[0, 1]"}


@dataclass(frozen=True)
class Refinement(_Group):
    """The least-squares refinement (R fixed) and the free-radius size check."""

    refine_iterations: int = 4  # Gauss-Newton rounds, each re-selecting inliers
    size_check: bool = True  # compare the free-radius fit with R
    size_tolerance_m: float = 0.004  # the free radius may differ from R by the larger of this (m) ...
    size_tolerance_fraction: float = 0.04  # ... and this * R ...
    size_sigmas: float = 3.0  # ... plus this many standard errors (0.3 % of balls rejected)

    RULES: typing.ClassVar[dict] = {"size_tolerance_m": ">= 0", "size_tolerance_fraction": "[0, 1]",
                                    "size_sigmas": ">= 0"}


@dataclass(frozen=True)
class Outline(_Group):
    """Organised clouds at high noise: the centre and size from the ball's outline (depth steps)."""

    outline_noise_fraction: float = 0.25  # re-centre a reported sphere on its outline where noise >= this * R
    outline_evidence: bool = True  # verify a hypothesis again centred on its outline's ray where the noise is high
    outline_size: bool = True  # take the outline's radius for the size check where all four quarters are seen

    RULES: typing.ClassVar[dict] = {"outline_noise_fraction": ">= 0"}
    NOTES: typing.ClassVar[dict] = {"outline_noise_fraction": "a fraction of R; inf for never"}


@dataclass(frozen=True)
class Input(_Group):
    """What the detector takes of a cloud."""

    max_points: int = 2_000_000  # larger clouds are subsampled for the search
    mm_check: bool = True  # refuse clouds whose median |z| suggests millimetres (beyond 50 m)

    RULES: typing.ClassVar[dict] = {"max_points": ">= 1000"}


#: The groups: attribute name -> class, in order.
GROUPS = {"search": Search, "paper": Paper, "noise": Noise, "retry": Retry, "verification": Verification,
          "refinement": Refinement, "outline": Outline, "input": Input}


@dataclass(frozen=True)
class DetectorConfig:
    """All parameters of the detector: the model and one group per stage. Construct through
    ``config_for`` or ``override``."""

    radius_m: float = 0.12  # the known ball radius R (m; 0.12: a size-7 basketball)
    eps_m: float = 0.01  # the shell half-width: p is an inlier of c if | ||p - c|| - R | <= eps (m)
    pipeline: str = "improved"  # "paper" (section 2.5) or "improved"
    search: Search = field(default_factory=Search)
    paper: Paper = field(default_factory=Paper)
    noise: Noise = field(default_factory=Noise)
    retry: Retry = field(default_factory=Retry)
    verification: Verification = field(default_factory=Verification)
    refinement: Refinement = field(default_factory=Refinement)
    outline: Outline = field(default_factory=Outline)
    input: Input = field(default_factory=Input)

    def __post_init__(self) -> None:
        bad = self.problems()
        if bad:
            raise SphereBenchError("invalid detector configuration: " + "; ".join(bad))

    def problems(self) -> list[str]:
        """Every group's problems, then the rules across groups."""
        model = [(n, getattr(self, n)) for n in ("radius_m", "eps_m")]
        out = [f"{n}={shown(v, repr)} must be a finite number" for n, v in model
               if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v)]
        if not out and self.radius_m <= 0:
            out.append(f"radius_m={self.radius_m} must be > 0 (the ball radius in metres, e.g. 0.12)")
        elif not out and self.eps_m <= 0:
            out.append(f"eps_m={self.eps_m} must be > 0")
        elif not out and self.eps_m >= self.radius_m:
            out.append(f"eps_m={self.eps_m} must be smaller than the radius {self.radius_m} (e.g. 0.01)")
        if self.pipeline not in PIPELINES:
            out.append(f"pipeline={shown(self.pipeline, repr)} is not one of {', '.join(PIPELINES)}")
        for name, cls in GROUPS.items():
            group = getattr(self, name)
            if not isinstance(group, cls):
                out.append(f"{name} must be a {cls.__name__}, not {shown(group, repr)}")
            else:
                out += group.problems(name + ".")
        if self.pipeline == "paper" and getattr(self.search, "sampling", None) != "global":
            out.append("the paper pipeline samples globally: use search.sampling='global' (local sampling is "
                       "pipeline='improved')")
        return out

    @property
    def local_radius_m(self) -> float:
        """The local sampling radius: ``search.sample_radius_m`` or one ball diameter."""
        r = self.search.sample_radius_m
        return 2.0 * self.radius_m if r is None else float(r)

    @property
    def radius_tolerance_m(self) -> float:
        """The size check's tolerance before standard errors (m): the larger of
        ``refinement.size_tolerance_m`` and ``refinement.size_tolerance_fraction`` R."""
        return max(self.refinement.size_tolerance_m, self.refinement.size_tolerance_fraction * self.radius_m)

    @property
    def merge_m(self) -> float:
        """Distance under which two candidate centres are one (paper pipeline): eps by default."""
        m = self.paper.candidate_merge_m
        return self.eps_m if m is None else float(m)

    def get(self, path: str):
        """A setting by its path ("verification.min_score", or a model field such as "radius_m")."""
        if path not in PATHS:
            raise SphereBenchError(f"unknown detector parameter {path}")
        return operator.attrgetter(path)(self)

    def override(self, changes: Mapping[str, object]) -> DetectorConfig:
        """This configuration with settings changed: {path: value}, a path "group.field" or a model
        field; or {group: {field: value}}."""
        model, groups = {}, {}
        for key, value in changes.items():
            if key in GROUPS and isinstance(value, Mapping):
                groups.setdefault(key, {}).update(value)
                continue
            if key not in PATHS:
                hint = f" (now {FLAT_NAMES[key]})" if key in FLAT_NAMES else ""
                if key.rpartition(".")[2] in REMOVED:
                    hint = (" (no longer a setting: the verdict is fitted, and a stage's inner workings are its "
                            "module's constants; see docs/detector.md)")
                raise SphereBenchError(f"unknown detector parameter {key}{hint}")
            group, _, name = PATHS[key].rpartition(".")
            if group:
                groups.setdefault(group, {})[name] = value
            else:
                model[name] = value
        for group, values in groups.items():
            unknown = sorted(set(values) - {f.name for f in dataclasses.fields(GROUPS[group])})
            if unknown:
                raise SphereBenchError(f"unknown detector parameter(s) {', '.join(group + '.' + u for u in unknown)}")
            model[group] = dataclasses.replace(getattr(self, group), **values)
        return dataclasses.replace(self, **model)

    def flat(self) -> dict:
        """Every setting by its bare name, in the published order (results and caches hash this)."""
        return {name: self.get(FLAT_NAMES[name]) for name in FLAT_NAMES}

    @classmethod
    def from_flat(cls, values: Mapping[str, object]) -> DetectorConfig:
        """The configuration of a flat dict (``flat``'s form; other keys are ignored)."""
        return DEFAULT.override({FLAT_NAMES[k]: v for k, v in values.items() if k in FLAT_NAMES})


def _settings() -> dict[str, str]:
    model = {f.name: f.name for f in dataclasses.fields(DetectorConfig) if f.name not in GROUPS}
    grouped = {f.name: f"{g}.{f.name}" for g, cls in GROUPS.items() for f in dataclasses.fields(cls)}
    return {**model, **grouped}


_BY_NAME = _settings()
#: The published order of the flat form (results' and caches' JSON): the settings by bare name, in
#: the order of the configuration before it had groups; a new setting follows at the end.
_FLAT_ORDER = """
    radius_m eps_m pipeline sampling sample_radius_m solver iterations adaptive confidence min_iterations
    max_range_m search_width_px candidate_merge_m zscore_threshold zscore_variable refine noise_subpixel
    noise_baseline_m noise_z2_per_m noise_estimate noise_correlation noise_sigmas verify_candidates
    verify_candidates_if_none outline_noise_fraction outline_evidence outline_size refine_iterations
    min_inliers size_check size_tolerance_m size_tolerance_fraction size_sigmas max_spheres
    nms_distance_fraction min_score max_points mm_check retry_occluder retry_off_axis retry_disc retry_hole
    accept_score rank_floor retry_relief""".split()
#: The names of settings no longer kept: the hand-set verdict's allowances, exponents and floors (the
#: fitted verdict replaced them), and the stages' inner workings (their modules' constants now).
REMOVED = frozenset("""
    sample_success bound_noise_fraction hypothesis_min_range_m bound_visible_fraction pretest_slack
    search_candidates sample_retries noise_estimate_lag_px noise_estimate_samples noise_estimate_min_samples
    noise_estimate_min_depth_m noise_model_tolerance noise_correlation_min_px noise_correlation_max_px
    noise_from_data max_eps_fraction pretest_points pretest_min_fraction verify_score_margin rescore_band
    multistart_noise_fraction outline_evidence_noise_fraction outline_evidence_min_move_px
    outline_evidence_min_score outline_size_floor_px outline_gap_sigmas outline_band_px
    outline_band_fraction outline_min_side outline_max_shift_fraction outline_max_bias_px outline_iterations
    fit_max_points score_max_points mm_check_median_m noise_estimate_keep box_half_fraction
    box_offset_fraction search_off_axis retry_new_fraction occluded_push_fraction occluded_push_starts
    occluded_push_noise_fraction disc_noise_fraction disc_inner_fraction disc_side_offset_fraction
    disc_side_half_fraction disc_gap_fraction disc_gap_sigmas disc_min_behind disc_step_fraction
    ring_offset_fraction ring_half_fraction prefilter_offset_fraction descent_steps box_min_valid
    pretest_max_continued first_band_fraction first_steps coarse_band_fraction ray_s_min_fraction
    radius_se_s_min_fraction size_limit_fraction rescore_offset_xy rescore_offset_z verify_quality_fraction
    interior_bands ring_factor ring_front_min_fraction ring_front_max_fraction profile_inner_sq
    profile_outer_sq behind_power occlusion_discount occlusion_ring_max occlusion_min_visible
    occlusion_size_sigmas hug_power ring_continued_power ring_front_free ring_front_power see_through_free
    see_through_power see_through_sigmas edge_behind_free edge_behind_power edge_behind_sigmas
    relief_floor_fraction relief_free_sigmas ring_spread_free ring_spread_power interior_density_power
    calibrate_evidence hole_min_ring hole_min_fraction hole_step_fraction hole_min_range_m score_calibration
    calibration_slope calibration_offset fitted_verdict""".split())
#: Bare name -> path, in the flat form's order (bare names are unique across the groups).
FLAT_NAMES = {**{n: _BY_NAME[n] for n in _FLAT_ORDER}, **{n: p for n, p in _BY_NAME.items() if n not in _FLAT_ORDER}}
#: Every accepted path -> itself, and the model fields' bare names.
PATHS = {**{p: p for p in _BY_NAME.values()}, **{n: n for n, p in _BY_NAME.items() if "." not in p}}
assert len(FLAT_NAMES) == len(_BY_NAME) and set(_FLAT_ORDER) <= set(_BY_NAME), "a flat name is not a setting"


def dotted_overrides(overrides: Mapping[str, object], warn: Callable[[str], None]) -> dict:
    """--set's settings with the bare names of before the groups ("min_score") read as their paths
    ("verification.min_score"), ``warn`` told once which were (they go in a later release)."""
    old = [k for k in overrides if k not in PATHS and k in FLAT_NAMES]
    if old:
        warn("deprecated: name settings by their path: " + ", ".join(f"{k} -> {FLAT_NAMES[k]}" for k in old))
    return {FLAT_NAMES[k] if k in old else k: v for k, v in overrides.items()}


DEFAULT = DetectorConfig()
#: Section 2.5 of the paper, with the known-radius minimal solver.
PAPER = DEFAULT.override({"pipeline": "paper", "search": {"sampling": "global", "solver": "known_radius",
                                                          "iterations": 1000, "adaptive": False},
                          "paper.refine": "barycentre", "verification": {"max_spheres": 1, "min_inliers": 3,
                                                                         "min_score": 0.0}})
#: The ablation: the printed Eq. (12) solved by least squares (minimum-norm solution).
PAPER_LSTSQ = PAPER.override({"search.solver": "lstsq_eq12"})
#: The default: the paper's future work and the fixes of docs/detector.md.
IMPROVED = DEFAULT

PRESETS = {"paper": PAPER, "paper-lstsq": PAPER_LSTSQ, "improved": IMPROVED}


def config_for(name: str, changes: Mapping[str, object] | None = None, **groups) -> DetectorConfig:
    """A named preset ("paper", "paper-lstsq", "improved"; "_" works for "-") with settings changed:
    ``changes`` {path: value}, and keywords: a model field or a group's {field: value}.

    >>> config_for("paper", search={"iterations": 10000}).search.iterations
    10000
    >>> config_for("paper", {"search.iterations": 10000}, radius_m=0.2).radius_m
    0.2
    """
    key = str(name).lower().replace("_", "-")
    if key not in PRESETS:
        raise SphereBenchError(f"unknown detector method '{name}': use one of {', '.join(PRESETS)}")
    return PRESETS[key].override({**(changes or {}), **groups})
