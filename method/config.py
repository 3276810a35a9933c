"""One configuration object for the sphere detector, in groups, with the paper's values as named presets.

Every length is in metres (``_m``), every image size in pixels (``_px``); a ``_fraction`` without
another unit is a fraction of the ball radius R (of the ball's disc radius r in the search's
stencil). ``DetectorConfig`` holds the model (R, eps, the pipeline) and one frozen group per stage:
``search``, ``paper``, ``noise``, ``stencil``, ``retry``, ``verification``, ``refinement``,
``outline``, ``evidence`` and ``input``. A setting is named by its path, ``verification.min_score``
(``--set verification.min_score=0.4``); ``override`` and ``config_for`` take such paths.

Presets: ``PAPER`` is section 2.5 of Roman-Rivera et al. (2023) as written (three points drawn from
the whole cloud, the known-radius minimal solver, eps = 1 cm, 1,000 iterations, the candidate-centre
list, choice by most points, z-score filter at 1.5 on the point-to-centre distance, barycentre);
``PAPER_LSTSQ`` the same with the literal least-squares reading of the printed Eq. (12) (rank-
deficient, see ``sphere_model``); ``IMPROVED`` (the default) local sampling, adaptive iterations,
noise-aware tolerances, least-squares refinement with R fixed, a size check, several spheres per
frame and a confidence score (docs/detector.md). How the defaults were chosen:
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
        return None if isinstance(v, bool) else f"{path}={v!r} must be true or false"
    if kind == "str":
        return None if isinstance(v, str) else f"{path}={v!r} must be a string"
    if isinstance(v, bool) or not isinstance(v, int if kind == "int" else (int, float)):
        return f"{path}={v!r} must be {'an integer' if kind == 'int' else 'a number'}"
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
        return f"{path}={v!r} must be {rule}{tail}" if "inf" in note else f"{path}={v!r} must be a finite number"
    if isinstance(rule, tuple):
        return None if v in rule else f"{path}={v!r} is not one of {', '.join(rule)}"
    if rule is not None and _breaks(v, rule):
        return f"{path}={v!r} must be {'within ' if rule[0] in '[(' else ''}{rule}{tail}"
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
    confidence: float = 0.99  # the bound's probability of one all-inlier sample
    min_iterations: int = 300  # never fewer iterations (organised: strata)
    sample_success: float = 0.8  # organised: chance a draw on the ball passes the pretest
    bound_noise_fraction: float = 0.75  # the bound provides for balls to where one pixel's noise is this * R ...
    hypothesis_min_range_m: float = 3.5  # hypotheses are kept to at least this depth (m)
    max_range_m: float = 6.0  # ... or to this depth (m), whichever is nearer
    bound_visible_fraction: float = 1.0  # ... of which at least this share is visible
    search_width_px: int = 424  # wider streams are searched on binned cells about this many across
    pretest_slack: float = 0.1  # organised pretest: added tolerance (fraction of R)
    search_candidates: int = 16  # organised: hypotheses kept, by score
    sample_retries: int = 4  # unorganised: draws for the 2nd and 3rd point before giving up
    pretest_points: int = 12  # unorganised: points checked before scoring a candidate fully
    pretest_min_fraction: float = 0.5  # ... of which this share must be inliers
    score_max_points: int = 400  # unorganised: at most about this many points scored per candidate

    RULES: typing.ClassVar[dict] = {
        "sampling": SAMPLINGS, "sample_radius_m": "> 0", "solver": SOLVERS, "iterations": "1-10000000",
        "confidence": "(0, 1)", "min_iterations": ">= 0", "sample_success": "(0, 1)",
        "bound_noise_fraction": "> 0", "hypothesis_min_range_m": "> 0", "max_range_m": "> 0",
        "bound_visible_fraction": "(0, 1]", "search_width_px": ">= 16", "pretest_slack": ">= 0",
        "search_candidates": ">= 1", "sample_retries": ">= 1", "pretest_points": ">= 1",
        "pretest_min_fraction": "[0, 1]", "score_max_points": ">= 50"}


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
    """The depth noise model: sigma_z = A z^2 (1/m), from the stereo model, the user or the frame."""

    noise_subpixel: float = 0.08  # stereo model: subpixel disparity RMS (px; 0: no noise model)
    noise_baseline_m: float = 0.050  # stereo model: baseline (m)
    noise_z2_per_m: float | None = None  # A given outright (1/m; None: the stereo model at the stream's fx)
    noise_estimate: bool = True  # organised: measure A on the frame (second differences of depth)
    noise_estimate_lag_px: int = 3  # ... at this lag (px at 424 wide)
    noise_estimate_samples: int = 1024  # ... on at most this many pixels
    noise_estimate_min_samples: int = 128  # ... fewer qualifying: the model's A
    noise_estimate_min_depth_m: float = 0.6  # ... pixels nearer than this left out (m)
    noise_estimate_keep: float = 0.9  # ... averaging the smallest this share of squared differences
    noise_model_tolerance: float = 0.10  # the measured A replaces the model's when they differ by more
    noise_correlation: bool = True  # organised: measure the noise's correlation length on the frame
    noise_correlation_min_px: float = 0.8  # ... shorter reads 0 (px at 424 wide)
    noise_correlation_max_px: float = 3.0  # ... the longest taken (px at 424 wide)
    noise_from_data: bool = True  # organised: narrow the band to the candidate's own residual spread
    noise_sigmas: float = 2.5  # the band half-width: max(eps, noise_sigmas * sigma_z) ...
    max_eps_fraction: float = 1.5  # ... capped at this * R

    RULES: typing.ClassVar[dict] = {
        "noise_subpixel": ">= 0", "noise_baseline_m": ">= 0", "noise_z2_per_m": ">= 0",
        "noise_estimate_lag_px": "1-32", "noise_estimate_samples": "1-1000000",
        "noise_estimate_min_samples": ">= 1", "noise_estimate_min_depth_m": ">= 0",
        "noise_estimate_keep": "(0, 1]", "noise_model_tolerance": ">= 0", "noise_correlation_min_px": ">= 0",
        "noise_correlation_max_px": ">= 0", "noise_sigmas": ">= 0", "max_eps_fraction": "(0, 2]"}
    NOTES: typing.ClassVar[dict] = {"noise_z2_per_m": "sigma_z / z^2 in 1/m, e.g. 0.0015",
                                    "max_eps_fraction": "the band's cap over R"}

    def cross(self, prefix: str) -> list[str]:
        if self.noise_estimate_min_samples > self.noise_estimate_samples:
            return [f"{prefix}noise_estimate_min_samples={self.noise_estimate_min_samples} must not exceed "
                    f"{prefix}noise_estimate_samples={self.noise_estimate_samples}"]
        return []


_FRACTION_OF_R = "(0, 4]"


@dataclass(frozen=True)
class Stencil(_Group):
    """The organised search's stencil of boxes (fractions of the ball's disc radius r at the box's depth)."""

    box_half_fraction: float = 0.25  # half-side of the stencil's boxes
    box_offset_fraction: float = 0.5  # offset of the four side boxes from the centre box
    search_off_axis: bool = False  # stretch the stencil with the silhouette off the optical axis
    ring_offset_fraction: float = 1.5  # offset of the 8 outline-ring boxes
    ring_half_fraction: float = 0.25  # their half-side
    prefilter_offset_fraction: float = 2.0  # the plane prefilter's boxes' distance from the first cell
    descent_steps: int = 3  # steps from the first cell toward the front point
    box_min_valid: float = 0.3  # a box with a smaller valid share of its area is invalid
    pretest_max_continued: int = 3  # most ring boxes continuing the surface at the ball's depth

    RULES: typing.ClassVar[dict] = {
        "box_half_fraction": _FRACTION_OF_R, "box_offset_fraction": _FRACTION_OF_R,
        "ring_offset_fraction": _FRACTION_OF_R, "ring_half_fraction": _FRACTION_OF_R,
        "prefilter_offset_fraction": _FRACTION_OF_R, "descent_steps": "0-20", "box_min_valid": "[0, 1]",
        "pretest_max_continued": "0-8"}
    NOTES: typing.ClassVar[dict] = {"pretest_max_continued": "of the 8 ring boxes"}


@dataclass(frozen=True)
class Retry(_Group):
    """Organised clouds, while no sphere is accepted: the searches again, the disc search, the hole search."""

    retry_relief: bool = True  # search again ranking hypotheses by their cap's relief against the noise
    retry_occluder: bool = True  # ... leaving out side boxes more than R in front (occluders)
    retry_off_axis: bool = True  # ... then with the stencil stretched off the axis
    retry_disc: bool = True  # ... then for discs standing out of what is behind them
    retry_new_fraction: float = 0.25  # a retry's hypothesis this near (fraction of R) a verified start is skipped
    disc_noise_fraction: float = 0.25  # the disc search starts where one pixel's noise reaches this * R
    disc_inner_fraction: float = 0.5  # its inner box's half-side (fraction of r)
    disc_side_offset_fraction: float = 1.7  # its four side boxes' offset (fraction of r)
    disc_side_half_fraction: float = 0.35  # their half-side (fraction of r)
    disc_gap_fraction: float = 1.0  # a side box is behind when farther than the inner box by this * R ...
    disc_gap_sigmas: float = 3.0  # ... and this many standard errors
    disc_min_behind: int = 3  # at least this many of the four side boxes behind
    disc_step_fraction: float = 0.5  # visit every k-th cell, k this * the disc radius at max_range_m
    retry_hole: bool = True  # ... then for holes in the depth ringed by a ball's face (a saturated cap)
    hole_min_ring: int = 6  # of the eight directions from a hole cell, at least this many reach its ring
    hole_min_fraction: float = 0.45  # the hole's mean radius at least this fraction of r (smaller: blobs of dropout)
    hole_step_fraction: float = 0.25  # visit every k-th cell, k this * the disc radius at max_range_m
    hole_min_range_m: float = 0.3  # its ring is looked for within the disc radius of a ball this near (m)

    RULES: typing.ClassVar[dict] = {
        "retry_new_fraction": "[0, 2]", "disc_noise_fraction": ">= 0", "disc_inner_fraction": _FRACTION_OF_R,
        "disc_side_offset_fraction": _FRACTION_OF_R, "disc_side_half_fraction": _FRACTION_OF_R,
        "disc_gap_fraction": ">= 0", "disc_gap_sigmas": ">= 0", "disc_min_behind": "1-4",
        "disc_step_fraction": _FRACTION_OF_R, "hole_min_ring": "1-8", "hole_min_fraction": "[0, 1]",
        "hole_step_fraction": _FRACTION_OF_R, "hole_min_range_m": "> 0"}
    NOTES: typing.ClassVar[dict] = {"retry_new_fraction": "a fraction of R",
                                    "disc_min_behind": "of the disc search's four side boxes",
                                    "hole_min_ring": "of the hole search's eight directions"}


@dataclass(frozen=True)
class Verification(_Group):
    """Which hypotheses are verified, from which starts, and which spheres are reported."""

    verify_candidates: int = 6  # verify at most this many of the best hypotheses ...
    verify_candidates_if_none: int = 16  # ... or this many while none is accepted (organised)
    verify_score_margin: float = 6.0  # once one is accepted, skip hypotheses scoring this far below it
    verify_quality_fraction: float = 0.15  # unorganised: skip candidates below this share of the best's quality
    rescore_band: float = 0.15  # re-verify from six starts a candidate scoring within this of min_score
    rescore_offset_xy: float = 0.2  # the six starts' offsets across the line of sight (fraction of R)
    rescore_offset_z: float = 0.33  # ... and along it (fraction of R)
    multistart_noise_fraction: float = 0.5  # while none is accepted, seven starts where noise exceeds this * R
    occluded_push_fraction: float = 0.5  # an occluded hypothesis failing: verified again pushed back by this * R ...
    occluded_push_starts: int = 4  # ... from up to this many starts (0: off) ...
    occluded_push_noise_fraction: float = 0.25  # ... where one pixel's noise is below this * R
    interior_bands: float = 3.0  # unorganised: the interior lies at least this many bands under the surface
    min_inliers: int = 30  # fewer inliers: no detection
    max_spheres: int = 4  # at most this many spheres per frame
    nms_distance_fraction: float = 0.75  # suppress a sphere within this fraction of 2R of a better one
    accept_score: float = 0.67  # a candidate this probable (below) is taken as a ball: the search narrows, the retries stop
    min_score: float = 0.67  # detect() reports the candidates at least this probable (the search is the same at any)
    rank_floor: float = 0.01  # candidates less probable than this are not ranked (the benchmark's floor, as CircleNet's)
    fitted_verdict: bool = True  # organised clouds: the score is the fitted verdict's (method/verdict.py); False: the factors'
    score_calibration: bool = True  # score: the probability of a ball within 2 cm (3 beyond 3 m); False: the raw product
    calibration_slope: float = 2.102  # probability = sigmoid(slope logit(raw) + offset), fitted on train + train-stereo
    calibration_offset: float = 2.018  # ... (see docs/detector.md, "What the score means")

    RULES: typing.ClassVar[dict] = {
        "verify_candidates": ">= 1", "verify_candidates_if_none": ">= 1", "verify_score_margin": ">= 0",
        "verify_quality_fraction": "[0, 1]", "rescore_band": ">= 0", "rescore_offset_xy": ">= 0",
        "rescore_offset_z": ">= 0", "multistart_noise_fraction": "> 0", "occluded_push_fraction": _FRACTION_OF_R,
        "occluded_push_starts": "0-10", "occluded_push_noise_fraction": ">= 0", "interior_bands": ">= 0",
        "min_inliers": ">= 3", "max_spheres": ">= 1", "nms_distance_fraction": "[0, 1]",
        "accept_score": "[0, 1]", "min_score": "[0, 1]", "rank_floor": "[0, 1]", "calibration_slope": "> 0"}
    NOTES: typing.ClassVar[dict] = {"multistart_noise_fraction": "a fraction of R; inf for never",
                                    "occluded_push_starts": "0: off",
                                    "calibration_slope": "the map must rise with the evidence"}

    def probability(self, raw: float) -> float:
        """A detection's score from its raw score: with ``fitted_verdict`` the score is already the
        probability, else ``factor_probability``."""
        return float(raw) if self.fitted_verdict else self.factor_probability(raw)

    def factor_probability(self, raw: float) -> float:
        """The probability of a raw evidence product in [0, 1]: the calibration map (strictly
        increasing, 0 and 1 fixed), or the product itself without ``score_calibration``."""
        if not self.score_calibration or raw <= 0.0 or raw >= 1.0:
            return float(raw)
        return 1.0 / (1.0 + math.exp(-(self.calibration_slope * math.log(raw / (1.0 - raw)) + self.calibration_offset)))

    def raw(self, p: float) -> float:
        """The raw evidence product whose probability is p: the map's inverse, which the decisions inside
        the detector compare the product with."""
        if self.fitted_verdict or not self.score_calibration or p <= 0.0 or p >= 1.0:
            return float(p)
        return 1.0 / (1.0 + math.exp(-(math.log(p / (1.0 - p)) - self.calibration_offset) / self.calibration_slope))

    @property
    def accept_raw_score(self) -> float:
        """``accept_score`` on the raw evidence product."""
        return self.raw(self.accept_score)

    @property
    def floor_raw_score(self) -> float:
        """``rank_floor`` on the raw evidence product, never above ``accept_raw_score``."""
        return min(self.raw(self.rank_floor), self.accept_raw_score)


@dataclass(frozen=True)
class Refinement(_Group):
    """The least-squares refinement (R fixed) and the free-radius size check."""

    refine_iterations: int = 4  # Gauss-Newton rounds, each re-selecting inliers
    fit_max_points: int = 400  # organised: every fit uses at most about this many inliers
    first_band_fraction: float = 0.5  # organised: the first round's inlier band (fraction of R) ...
    first_steps: int = 3  # ... and its 3D Gauss-Newton steps
    coarse_band_fraction: float = 0.25  # later rounds' band: at most this * R
    ray_s_min_fraction: float = 0.03  # ray fits floor s = sqrt(r^2 - m^2) at this fraction of r
    radius_se_s_min_fraction: float = 0.3  # the free radius's standard error floors s at this fraction of r
    size_check: bool = True  # compare the free-radius fit with R
    size_tolerance_m: float = 0.004  # the free radius may differ from R by the larger of this (m) ...
    size_tolerance_fraction: float = 0.04  # ... and this * R ...
    size_sigmas: float = 3.0  # ... plus this many standard errors
    size_limit_fraction: float = 0.25  # and never by more than this * R

    RULES: typing.ClassVar[dict] = {
        "fit_max_points": ">= 10", "first_band_fraction": _FRACTION_OF_R,
        "first_steps": "1-20", "coarse_band_fraction": _FRACTION_OF_R, "ray_s_min_fraction": "[0, 1]",
        "radius_se_s_min_fraction": _FRACTION_OF_R, "size_tolerance_m": ">= 0",
        "size_tolerance_fraction": "[0, 1]", "size_sigmas": ">= 0", "size_limit_fraction": _FRACTION_OF_R}


@dataclass(frozen=True)
class Outline(_Group):
    """Organised clouds at high noise: the centre and size from the ball's outline (depth steps)."""

    outline_noise_fraction: float = 0.25  # re-centre a reported sphere on its outline where noise >= this * R
    outline_evidence: bool = True  # verify a hypothesis again centred on its outline's ray ...
    outline_evidence_noise_fraction: float = 0.5  # ... where one pixel's noise is at least this * R ...
    outline_evidence_min_move_px: float = 0.25  # ... not where the outline moves the centre less (px)
    outline_evidence_min_score: float = 0.05  # ... nor where the first verification scores below this
    outline_size: bool = True  # take the outline's radius for the size check where all four quarters are seen
    outline_size_floor_px: float = 0.25  # the outline radius's least standard error (px)
    outline_gap_sigmas: float = 3.0  # an outline is a step farther than max(this * sigma_z, R)
    outline_band_px: float = 2.0  # outline pixels within this (px) ...
    outline_band_fraction: float = 0.15  # ... plus this share of the disc radius of the silhouette's outline
    outline_min_side: int = 4  # re-centre an axis with at least this many outline pixels on each side
    outline_max_shift_fraction: float = 0.5  # a re-centring moving the centre more than this * R is not taken
    outline_max_bias_px: float = 1.0  # nor on an axis whose sides lie on average this far off the silhouette (px)
    outline_iterations: int = 3  # rounds of re-centring

    RULES: typing.ClassVar[dict] = {
        "outline_noise_fraction": ">= 0", "outline_evidence_noise_fraction": ">= 0",
        "outline_evidence_min_move_px": ">= 0", "outline_evidence_min_score": "[0, 1]",
        "outline_size_floor_px": ">= 0", "outline_gap_sigmas": "> 0", "outline_band_px": "> 0",
        "outline_band_fraction": "> 0", "outline_min_side": "1-1000", "outline_max_shift_fraction": "> 0",
        "outline_max_bias_px": "> 0", "outline_iterations": "1-20"}
    NOTES: typing.ClassVar[dict] = {"outline_noise_fraction": "a fraction of R; inf for never",
                                    "outline_evidence_noise_fraction": "a fraction of R; inf for never",
                                    "outline_min_side": "outline pixels on each side of an axis",
                                    "outline_max_bias_px": "pixels; inf for never"}


@dataclass(frozen=True)
class Evidence(_Group):
    """The confidence score's factors (``improved.confidence``; each in [0, 1], docs/detector.md)."""

    ring_factor: float = 1.3  # the outline ring: rays passing the centre at R to this * R
    ring_front_min_fraction: float = 0.3  # a ring pixel this far (* R) in front of its ray's pass ...
    ring_front_max_fraction: float = 1.2  # ... to this far is a surface attached in front
    profile_inner_sq: float = 0.3  # the relief's inner zone: rays within sqrt(this) R
    profile_outer_sq: float = 0.8  # its outer zone: rays up to sqrt(this) R
    behind_power: float = 2.0  # exponent of (1 - share) of the silhouette behind the sphere
    hug_power: float = 2.0  # ... of those hugging it just in front
    ring_continued_power: float = 2.0  # ... of the ring continued at the ball's depth
    occlusion_discount: float = 1.0  # coverage over the visible share to this power (1: hidden pixels neutral) ...
    occlusion_ring_max: float = 0.05  # ... where at most this share of the ring continues at the ball's depth ...
    occlusion_min_visible: float = 0.35  # ... at least this share of the silhouette is visible ...
    occlusion_size_sigmas: float = 0.5  # ... and the free radius is within the tolerance and this many SEs
    ring_front_free: float = 0.15  # the ring's share attached in front that costs nothing ...
    ring_front_power: float = 4.0  # ... and the exponent of (1 - excess) beyond it
    see_through_free: float = 0.03  # see-through allowance beyond the noise's share ...
    see_through_power: float = 4.0  # ... its exponent ...
    see_through_sigmas: float = 3.0  # ... and binomial standard errors allowed
    edge_behind_free: float = 0.4  # the edge band's share seen behind allowed ...
    edge_behind_power: float = 4.0  # ... its exponent ...
    edge_behind_sigmas: float = 2.0  # ... and standard errors allowed
    relief_floor_fraction: float = 0.03  # the relief's tolerated zone-mean difference (* R) ...
    relief_free_sigmas: float = 1.0  # ... and standard errors without penalty
    ring_spread_free: float = 0.04  # the ring spread that costs nothing ...
    ring_spread_power: float = 16.0  # ... and the exponent of (1 - excess) beyond it
    interior_density_power: float = 2.0  # unorganised: exponent of (1 - inner / shell density)
    calibrate_evidence: bool = True  # take coverage and behind share against what the band's cap costs a ball

    RULES: typing.ClassVar[dict] = {
        "ring_factor": "(1, 3]", "ring_front_min_fraction": ">= 0", "ring_front_max_fraction": ">= 0",
        "profile_inner_sq": "(0, 1)", "profile_outer_sq": "(0, 1)", "occlusion_discount": "[0, 1]",
        "occlusion_ring_max": "[0, 1]", "occlusion_min_visible": "[0, 1]", "ring_front_free": "[0, 1]",
        "see_through_free": "[0, 1]", "edge_behind_free": "[0, 1]", "ring_spread_free": "[0, 1]",
        **{name: ">= 0" for name in ("behind_power", "hug_power", "ring_continued_power", "ring_front_power",
                                     "see_through_power", "edge_behind_power", "ring_spread_power",
                                     "interior_density_power", "relief_floor_fraction", "relief_free_sigmas",
                                     "see_through_sigmas", "edge_behind_sigmas", "occlusion_size_sigmas")}}
    NOTES: typing.ClassVar[dict] = {"ring_factor": "the outline ring's outer radius / R"}

    def cross(self, prefix: str) -> list[str]:
        out = []
        if not self.profile_inner_sq < self.profile_outer_sq:
            out.append(f"{prefix}profile_inner_sq={self.profile_inner_sq}, {prefix}profile_outer_sq="
                       f"{self.profile_outer_sq}: need 0 < inner < outer < 1 (squared fractions of R)")
        if not self.ring_front_min_fraction < self.ring_front_max_fraction:
            out.append(f"{prefix}ring_front_min_fraction={self.ring_front_min_fraction} must be below "
                       f"{prefix}ring_front_max_fraction={self.ring_front_max_fraction}")
        return out


@dataclass(frozen=True)
class Input(_Group):
    """What the detector takes of a cloud."""

    max_points: int = 2_000_000  # larger clouds are subsampled for the search
    mm_check: bool = True  # refuse clouds whose median |z| suggests millimetres ...
    mm_check_median_m: float = 50.0  # ... above this (m)

    RULES: typing.ClassVar[dict] = {"max_points": ">= 1000", "mm_check_median_m": ">= 0"}


#: The groups: attribute name -> class, in order.
GROUPS = {"search": Search, "paper": Paper, "noise": Noise, "stencil": Stencil, "retry": Retry,
          "verification": Verification, "refinement": Refinement, "outline": Outline, "evidence": Evidence,
          "input": Input}


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
    stencil: Stencil = field(default_factory=Stencil)
    retry: Retry = field(default_factory=Retry)
    verification: Verification = field(default_factory=Verification)
    refinement: Refinement = field(default_factory=Refinement)
    outline: Outline = field(default_factory=Outline)
    evidence: Evidence = field(default_factory=Evidence)
    input: Input = field(default_factory=Input)

    def __post_init__(self) -> None:
        bad = self.problems()
        if bad:
            raise SphereBenchError("invalid detector configuration: " + "; ".join(bad))

    def problems(self) -> list[str]:
        """Every group's problems, then the rules across groups."""
        model = [(n, getattr(self, n)) for n in ("radius_m", "eps_m")]
        out = [f"{n}={v!r} must be a finite number" for n, v in model
               if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v)]
        if not out and self.radius_m <= 0:
            out.append(f"radius_m={self.radius_m} must be > 0 (the ball radius in metres, e.g. 0.12)")
        elif not out and self.eps_m <= 0:
            out.append(f"eps_m={self.eps_m} must be > 0")
        elif not out and self.eps_m >= self.radius_m:
            out.append(f"eps_m={self.eps_m} must be smaller than the radius {self.radius_m} (e.g. 0.01)")
        if self.pipeline not in PIPELINES:
            out.append(f"pipeline={self.pipeline!r} is not one of {', '.join(PIPELINES)}")
        for name, cls in GROUPS.items():
            group = getattr(self, name)
            if not isinstance(group, cls):
                out.append(f"{name} must be a {cls.__name__}, not {group!r}")
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
    sample_success bound_noise_fraction hypothesis_min_range_m max_range_m bound_visible_fraction search_width_px
    pretest_slack search_candidates sample_retries candidate_merge_m zscore_threshold zscore_variable refine
    noise_subpixel noise_baseline_m noise_z2_per_m noise_estimate noise_estimate_lag_px noise_estimate_samples
    noise_estimate_min_samples noise_estimate_min_depth_m noise_model_tolerance noise_correlation
    noise_correlation_min_px noise_correlation_max_px noise_from_data noise_sigmas max_eps_fraction pretest_points
    pretest_min_fraction verify_candidates verify_candidates_if_none verify_score_margin rescore_band
    multistart_noise_fraction outline_noise_fraction outline_evidence outline_evidence_noise_fraction
    outline_evidence_min_move_px outline_evidence_min_score outline_size outline_size_floor_px outline_gap_sigmas
    outline_band_px outline_band_fraction outline_min_side outline_max_shift_fraction outline_max_bias_px
    outline_iterations fit_max_points score_max_points refine_iterations min_inliers size_check size_tolerance_m
    size_tolerance_fraction size_sigmas max_spheres nms_distance_fraction min_score max_points mm_check
    mm_check_median_m noise_estimate_keep box_half_fraction box_offset_fraction search_off_axis retry_occluder
    retry_off_axis retry_new_fraction retry_disc occluded_push_fraction occluded_push_starts
    occluded_push_noise_fraction disc_noise_fraction disc_inner_fraction disc_side_offset_fraction
    disc_side_half_fraction disc_gap_fraction disc_gap_sigmas disc_min_behind disc_step_fraction
    ring_offset_fraction ring_half_fraction prefilter_offset_fraction descent_steps box_min_valid
    pretest_max_continued first_band_fraction first_steps coarse_band_fraction ray_s_min_fraction
    radius_se_s_min_fraction size_limit_fraction rescore_offset_xy rescore_offset_z verify_quality_fraction
    interior_bands ring_factor ring_front_min_fraction ring_front_max_fraction profile_inner_sq profile_outer_sq
    behind_power occlusion_discount occlusion_ring_max occlusion_min_visible occlusion_size_sigmas hug_power
    ring_continued_power ring_front_free ring_front_power see_through_free see_through_power see_through_sigmas
    edge_behind_free edge_behind_power edge_behind_sigmas relief_floor_fraction relief_free_sigmas
    ring_spread_free ring_spread_power interior_density_power calibrate_evidence retry_hole hole_min_ring
    hole_min_fraction hole_step_fraction hole_min_range_m score_calibration calibration_slope calibration_offset
    accept_score rank_floor retry_relief""".split()
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
                                                                         "min_score": 0.0,
                                                                         "score_calibration": False,
                                                                         "fitted_verdict": False}})
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
