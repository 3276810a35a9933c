"""One configuration object for the sphere detector, with the paper's values as named presets.

Every length is in metres (``_m``), every image size in pixels (``_px``). Three presets:

- ``PAPER``: section 2.5 of Roman-Rivera et al. (2023) as written: three points drawn from the
  whole cloud, the known-radius minimal solver (the printed Eq. (12) is rank-deficient; see
  ``sphere_model``), eps = 1 cm, 1,000 iterations, the list of candidate centres, assignment of
  every point within R +/- eps, choice by most points, z-score filter at 1.5 on the point-to-centre
  distance, barycentre as the final centre.
- ``PAPER_LSTSQ``: the same pipeline with the literal least-squares reading of Eq. (12) (the
  minimum-norm solution of the rank-2 system): an ablation showing what the printed equations do.
- ``IMPROVED`` (default): local sampling, adaptive iteration count, windowed scoring, noise-aware
  tolerance, least-squares refinement with R fixed, a free-radius size check, several spheres per
  frame with non-maximum suppression, and a confidence score.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

from spherebench.errors import SphereBenchError

PIPELINES = ("paper", "improved")
SAMPLINGS = ("global", "local")
SOLVERS = ("known_radius", "lstsq_eq12")
REFINES = ("barycentre", "least_squares")
ZSCORE_VARIABLES = ("distance", "residual", "x", "y", "z", "xyz")


@dataclass(frozen=True)
class DetectorConfig:
    """All parameters of the detector. Construct through ``config_for`` or ``dataclasses.replace``.

    Model:
        radius_m: the known ball radius R (0.12 m: a size-7 basketball).
        eps_m: shell half-width: a point p is an inlier of centre c if | ||p - c|| - R | <= eps.
    Search:
        pipeline: "paper" (candidate-centre list, section 2.5) or "improved".
        sampling: "global" (3 points from the whole cloud) or "local" (2nd and 3rd point near the
            1st: the paper's future work).
        sample_radius_m: unorganised clouds: the 2nd and 3rd points come from the grid cells within
            this radius (default 2R) of the 1st point. (Organised clouds: the search's boxes scale
            with the ball's image radius at the first pixel's depth.)
        solver: "known_radius" (two centres from three points; the far one) or "lstsq_eq12".
        iterations: the iteration limit (the paper: 1,000; 10,000 for its cluttered scene E2);
            organised clouds: about the most strata (first cells) the search draws.
        adaptive: organised clouds: strata sized by the standard RANSAC bound for the smallest ball
            the frame can hold (``improved.strata``), one first cell drawn in each, at most about
            ``iterations`` of them (without it: ``iterations`` strata); unorganised clouds: stop
            early by the bound once a sphere is found.
        confidence: the probability of having drawn one all-inlier sample, for the bound.
        min_iterations: never stop before this many iterations (organised: never fewer strata).
        sample_success: organised clouds: the probability that an iteration whose first pixel is on
            the ball yields a hypothesis that passes the pretest (the descent from anywhere on the
            ball's disc reaches its front point unless the first pixel is on the rim); unorganised
            clouds: unused (the bound there follows the best candidate's support).
        bound_noise_fraction: the bound provides for balls up to the depth where one pixel's depth
            noise reaches this fraction of R (3.5 m at 424x240 for the D435 model)...
        max_range_m: ... or up to this depth, whichever is nearer.
        hypothesis_min_range_m: the search keeps hypotheses of balls up to the bound's depth with a
            25 % margin, and on a noisy unit (whose bound is nearer) never short of this depth: there
            they are not provided for, only kept when drawn (the nominal unit's bound at 424x240).
        bound_visible_fraction: ... of which at least this fraction is visible.
        search_width_px: organised search: streams wider than this are searched on cells of
            width // search_width_px pixels (binned sums), so that the search costs the same at
            every resolution; verification uses every pixel.
        pretest_slack: organised search: a fraction of R added to the pretest's noise tolerances
            (the box-mean relief model's error).
        search_candidates: organised search: hypotheses kept (distinct in the image, by score).
        sample_retries: unorganised search: draws allowed for the 2nd and 3rd local point before
            giving up an iteration.
    Paper pipeline:
        candidate_merge_m: a new centre within this distance of a listed candidate joins it.
        zscore_threshold: drop points whose |z| exceeds it (the paper: 1.5; Table 2 also 2, 3).
        zscore_variable: the value z-scored per point: "distance" (||p - c||, the default reading
            of Figure 19), "residual" (| ||p - c|| - R |), "x", "y", "z" (a coordinate) or "xyz"
            (each coordinate; a point is dropped if any exceeds the threshold).
        refine: "barycentre" (the paper) or "least_squares" (Gauss-Newton on ||p - c|| - R, R fixed).
    Improved pipeline:
        noise_subpixel, noise_baseline_m: Intel's stereo depth RMS model
            sigma_z = z^2 * subpixel / (fx * baseline), used to widen eps with depth when the
            cloud's intrinsics are known (0 subpixel disables it). The default is the D435's.
        noise_z2_per_m: another sensor's noise as sigma_z = noise_z2_per_m * z^2 (1/m), in place of
            the stereo model (None: the stereo model with the stream's fx). For a sensor noisier
            than the D435 model at its fx, set it: the search's tolerances and the largest band
            follow it. E.g. a first-generation Kinect quantises disparity to 1/8 pixel, a depth
            step of z^2 / (8 f b) = 0.0029 z^2 (f 580 px, b 7.5 cm): sigma about 0.0029 / sqrt(12)
            = 0.00083 plus noise (Khoshelham and Elberink, Sensors 2012, report about 0.0015).
        noise_estimate: organised clouds: sigma_z = A z^2 with A measured on the frame itself
            (``improved.frame_noise_a``: second differences of depth along rows) in place of the
            stereo model, which describes one nominal unit; the model where too few pixels qualify.
            ``noise_z2_per_m`` (``--depth-noise``) overrides both.
        noise_estimate_lag_px: the second differences' lag, pixels at 424 px wide (scaled with the
            width): beyond the stereo matcher's noise correlation (about 1-2 px).
        noise_estimate_samples: at most this many pixels sampled, evenly spread.
        noise_estimate_min_samples: fewer qualifying pixels: the model's A.
        noise_estimate_min_depth_m: pixels nearer than this are left out (1 mm counts dominate there).
        noise_model_tolerance: the measured A replaces the model's only when the two differ by more
            than this fraction: the estimate scatters by about +/- 4 % (10th-90th percentile), so a
            frame within it cannot tell its unit from the nominal one and keeps the model.
        noise_correlation: organised clouds: measure the depth noise's correlation length on the
            frame (``improved.frame_noise_correlation_px``: second differences at lag 1 against the
            estimate's lag), and count the evidence tests' pixels as effective samples
            (``improved.mean_variance_inflation``: a stereo matcher's window correlates neighbours'
            errors, and zone means then vary as over fewer pixels).
        noise_correlation_min_px, noise_correlation_max_px: the shortest correlation length it takes
            for one (pixels at 424 wide; shorter reads 0: on simulated independent noise the
            estimate reads up to 0.75, surfaces' curvature adding to the long lag) and the longest.
        noise_from_data: organised verification narrows the band to noise_sigmas times the robust
            spread (MAD) of the candidate's own ray residuals where that is below the model's: the
            model is the most noise expected; a quieter sensor keeps the outline's mixed pixels and
            a holder out of the fits (they bias the free radius upward).
        noise_sigmas: the shell half-width is max(eps, noise_sigmas * sigma_z) ...
        max_eps_fraction: ... capped at this fraction of R.
        pretest_points: unorganised search: points near a candidate checked before scoring it fully.
        pretest_min_fraction: fraction of those that must be inliers.
        verify_candidates: verify at most this many of the best search candidates ...
        verify_candidates_if_none: ... or this many, if more (organised clouds), while none has
            been accepted: a ball whose hypothesis ranks below clutter (one on a floor beside the image
            border, a partly hidden one) is then still verified, and a frame with a ball pays nothing
            for it. 16: every kept hypothesis (``search_candidates``).
        verify_score_margin: organised clouds: once a sphere is accepted, hypotheses whose search
            score (``_kernels.front_hypothesis``: 2 per agreeing side box of the cap, 1 per ring box
            on background, ...) is more than this below the best accepted one's are not verified.
            6 is three agreeing sides: more than the second of two balls scores below the first.
        rescore_band: organised clouds: a candidate scoring within this of min_score is verified
            again from ``improved.rescore_starts`` about its refined centre and takes the
            mean score (the size check: the majority). At 2-3 m the refinement's inlier selection
            has several optima a cm apart, whose scores differ by 0.1 or more: one start's score is
            a noisy draw. 0 disables it.
        outline_noise_fraction: organised clouds: a reported sphere whose depth noise (one pixel's
            sigma_z at its centre) is at least this fraction of R is re-centred across the line of
            sight on its outline (``improved.outline_centre``): where the noise nears R the cap's
            relief places the centre laterally to several mm, the outline's depth step to about one.
            Below it the depth fit is the better (on `train`). inf: never.
        outline_evidence: organised clouds: a hypothesis verified where one pixel's depth noise is at
            least outline_evidence_noise_fraction R is measured again on its outline: re-centred
            there (``improved.outline_centre``) and verified with its centre held on that ray (range,
            and for the size check range and radius, fitted along it: ``_kernels.fit_range``); that
            verification is its evidence and score. At such noise the cap's relief drifts the centre
            by a pixel or more, and the silhouette, ring and size tests then look beside the ball.
        outline_evidence_noise_fraction: see outline_evidence (a fraction of R; a nominal unit's
            frames reach 0.5 beyond 2.8 m). inf: never.
        outline_evidence_min_move_px: ... not where the outline moves the centre by less than this
            many pixels (few of the silhouette's pixels change class).
        outline_evidence_min_score: ... nor where the first verification scores below this (clutter
            far below min_score; half the re-verifications of `train` are saved).
        outline_size: ... and where all four quarters of its outline are seen, the size check takes the
            outline's radius (``improved.outline_size``: its angular radius at the centre's distance)
            for the depth fit's: where one pixel's noise is half of R or more the outline places
            the silhouette's size to a few mm, the cap's relief to several cm.
        outline_size_floor_px: the outline radius's standard error is never below this many pixels
            (mixed pixels and the pixel grid), added in quadrature to the residuals' own.
        outline_gap_sigmas: an outline is a step to a pixel farther than max(this * sigma_z, R) behind
            the centre from one within this * sigma_z of the ball's depths.
        outline_band_px, outline_band_fraction: the outline's pixels are taken within this many pixels
            plus this fraction of the disc's radius of the current silhouette's outline.
        outline_min_side: an image axis is re-centred only where at least this many outline pixels lie
            on each of its two sides (a one-sided arc cannot tell a shift from a silhouette a pixel
            smaller than the sphere's, as mixed pixels make it).
        outline_max_shift_fraction: a re-centring that moves the centre by more than this fraction of
            R is not taken.
        outline_max_bias_px: an image axis is not re-centred where the outline's two sides, on average,
            lie more than this many pixels outside (or inside) the sphere's silhouette: mixed pixels
            make it a pixel at most, and more means one side's depth steps are not the ball's outline
            (a surface it rests on, seen behind it at a grazing angle). inf: never held back.
        outline_iterations: rounds of re-centring (each re-collects the outline about the moved centre).
        multistart_noise_fraction: organised clouds, while no sphere is accepted: a hypothesis whose
            depth noise (one pixel's sigma_z) exceeds this fraction of R is verified from its centre
            and the six ``rescore_starts`` about it, the best kept and its score then taken as the
            mean (``improved.verify_multistart``): where the noise nears R the refinement's end
            depends on its start by a few cm. inf: never.
        fit_max_points: organised verification: every fit uses at most about this many inliers
            (evenly strided), and every window visit about 4 times as many pixels (strided); the
            reported spheres' inliers are then collected from every pixel.
        score_max_points: unorganised search: scoring visits at most about this many points per
            candidate, bounding the cost for balls near the camera.
        refine_iterations: Gauss-Newton rounds (each re-selects inliers); organised clouds then take
            2 more steps on the final inliers.
        min_inliers: fewer inliers than this: no detection.
        size_check: compare the free-radius fit with R.
        size_tolerance_m, size_tolerance_fraction: the free radius may differ from R by the larger of
            size_tolerance_m and size_tolerance_fraction * R, plus size_sigmas standard errors. The
            relative part: a real ball is not its nominal size (a size-7 basketball's circumference
            may be 749-780 mm, +/- 2 %; inflation; a calibration target's radius is often a
            nominal figure) and a sensor's scale is a percent or two off; balls of other sizes
            differ by more (a soccer ball is 8 % smaller than a basketball).
        size_sigmas: see size_tolerance_m.
        max_spheres: at most this many spheres per frame.
        nms_distance_fraction: a sphere whose centre is within this fraction of 2R of a better
            one is suppressed (two real balls' centres are at least 2R apart).
        min_score: detections with a lower confidence are not reported.
        max_points: clouds larger than this are randomly subsampled for the search (final inliers
            still come from the whole cloud), bounding time and memory.
        mm_check: refuse clouds whose median |z| exceeds ``mm_check_median_m`` (millimetres).
        noise_estimate_keep: ``improved.frame_noise_a`` averages the smallest this share of the
            squared second differences (edges and flying pixels are the rest), rescaled to a normal's.
    Search geometry (organised clouds; fractions of the ball's disc radius r at the box's depth):
        box_half_fraction: half-side of the stencil's boxes.
        box_offset_fraction: offset of the four side boxes from the centre box.
        search_off_axis: stretch the stencil's offsets (side boxes, ring boxes, prefilter) along each
            image axis as the ball's silhouette is off the optical axis (1 / cos^2 of its angle radially,
            1 / cos tangentially). Off: the first search's stencil is square, as on the axis (on `train`
            a stretched first search loses partly hidden balls); ``retry_off_axis`` stretches it.
        retry_occluder: while no sphere is accepted, search the frame again with the descent leaving
            out side boxes more than R in front of the centre box (an occluder pulls the descent off a
            partly hidden ball; beside a ball the ball's own box is nearer by as much, so the first
            search keeps them), and verify the hypotheses not verified before. A frame with a ball found
            pays nothing for it.
        retry_off_axis: ... then, while still none is accepted, search again with the stencil stretched
            off the axis (``search_off_axis``'s), likewise.
        retry_new_fraction: a retry's hypothesis within this fraction of R of a start already verified
            is not verified again; of the others, the best ``verify_candidates`` are, each from one start.
        retry_disc: ... then, while still none is accepted, look for discs that stand out of what is
            behind them (``_kernels.disc_hypotheses``: a far ball whose cap's relief is below the noise
            is lost by the descent and its pretest), likewise.
        occluded_push_fraction, occluded_push_starts, occluded_push_noise_fraction: a hypothesis that
            passed the pretest by an occluded side (verified only while none is accepted) whose
            verification fails is verified again from up to occluded_push_starts starts pushed back
            along its ray by occluded_push_fraction R each, where one pixel's depth noise there is below
            occluded_push_noise_fraction R (``improved.verify_pushed``: the occluder's pixels in the
            centre box pull its front range towards the camera). 0 starts: off. On `train` 4 starts
            found 2.25 more balls per seed than none, and 0.5 more than 2; without the noise bound a
            far frame's clutter sphere was accepted.
        disc_noise_fraction: the disc search starts where one pixel's depth noise reaches this
            fraction of R (2 m at 424x240 for the D435 model; on `train` 0.25 found more balls than
            0.35 and 0.5, with no more clutter).
        disc_inner_fraction, disc_side_offset_fraction, disc_side_half_fraction: its inner box's
            half-side, and its four side boxes' offset and half-side (fractions of the disc radius r).
        disc_gap_fraction, disc_gap_sigmas, disc_min_behind: a side box is behind the disc when its
            mean range exceeds the inner box's by this fraction of R and this many standard errors;
            at least this many of the four.
        disc_step_fraction: the disc search visits every k-th cell, k this fraction of the disc
            radius of a ball at ``max_range_m``.
        ring_offset_fraction, ring_half_fraction: offset and half-side of the 8 outline-ring boxes.
        prefilter_offset_fraction: the plane prefilter's boxes lie this far from the first cell.
        descent_steps: steps from the first cell toward the range's local minimum (the front point).
        box_min_valid: a box with fewer valid pixels than this share of its area is invalid.
        pretest_max_continued: at most this many ring boxes may continue the surface at the ball's depth.
    Refinement (organised):
        first_band_fraction: the first round's inlier band (fraction of R; a box-mean start can be
            4-5 cm off) ...
        first_steps: ... and its 3D Gauss-Newton steps.
        coarse_band_fraction: later rounds' band: at least twice the last move, at most this * R.
        ray_s_min_fraction: ray fits floor s = sqrt(r^2 - m^2) at this fraction of r.
        radius_se_s_min_fraction: the free radius's standard error floors s at this fraction of r.
        size_limit_fraction: the size check never accepts a free radius further than this * R from R.
        rescore_offset_xy, rescore_offset_z: ``improved.rescore``'s six starts about a refined centre,
            in units of R across the line of sight and along it.
        verify_quality_fraction: unorganised clouds: candidates below this share of the best one's
            search quality are not verified.
        interior_bands: unorganised clouds: the interior counted against a ball is its inner half and
            at least this many shell half-widths under its surface.
    Evidence (``improved.confidence``; each factor in [0, 1], see docs/detector.md for calibration):
        ring_factor: the outline ring spans rays passing the centre at R to ring_factor * R.
        ring_front_min_fraction, ring_front_max_fraction: a ring pixel this far (fractions of R) in
            front of where its ray passes the centre is a surface attached in front of the ball.
        profile_inner_sq, profile_outer_sq: the relief profile's inner zone holds rays passing the
            centre within sqrt(profile_inner_sq) R, its outer zone those up to sqrt(profile_outer_sq) R
            (short of the outline's mixed pixels; beyond it lies the edge band).
        behind_power, hug_power, ring_continued_power: exponents of (1 - share) for the silhouette's
            pixels behind the sphere, those hugging it just in front, and the outline ring continued
            at the ball's depth.
        occlusion_discount, occlusion_ring_max: the coverage is taken over the visible share of the
            silhouette (``visible_fraction``) to this power (1: a pixel hidden by a nearer surface counts
            neither for nor against; 0: against, as a missing inlier), where at most this share of the
            outline ring continues at the ball's depth (a ball standing free; a sphere fit into a wall
            or a corner keeps the full penalty) ...
        occlusion_min_visible: ... and at least this share of the silhouette is visible (a sphere
            fit to a small patch behind a nearer object is all inliers where it is seen) ...
        occlusion_size_sigmas: ... and the free radius lies within the size tolerance and this many
            standard errors of R (a partly hidden smaller ball, which the coverage rejected, has only
            its size left against it).
        ring_front_free, ring_front_power: the ring's share attached in front of the ball that costs
            nothing (a floor, a holder, a hand), and the exponent of (1 - excess) beyond it.
        see_through_free, see_through_power, see_through_sigmas: ``improved.see_through_excess``'s
            allowance beyond the noise's share (flying pixels), its exponent, and the binomial
            standard errors allowed beside.
        edge_behind_free, edge_behind_power, edge_behind_sigmas: ``improved.edge_behind_excess``'s
            allowed share of the edge band seen behind the sphere, its exponent, its standard errors.
        relief_floor_fraction: the relief test's tolerated zone-mean difference (fraction of R) ...
        relief_free_sigmas: ... and standard errors without penalty (``improved.relief_agreement``).
        ring_spread_free, ring_spread_power: the ring spread (attached outside the half ring holding
            most of it) that costs nothing, and the exponent of (1 - excess) beyond it.
        interior_density_power: unorganised clouds: exponent of (1 - inner / shell density).
        calibrate_evidence: take the coverage and the share seen behind against what the band's cap
            costs a true ball (``improved.noise_shares``): where the noise nears R the band (capped
            at ``max_eps_fraction`` R) holds only part of a ball's pixels.
    """

    radius_m: float = 0.12
    eps_m: float = 0.01
    pipeline: str = "improved"
    sampling: str = "local"
    sample_radius_m: float | None = None
    solver: str = "known_radius"
    iterations: int = 20000
    adaptive: bool = True
    confidence: float = 0.99
    min_iterations: int = 300
    sample_success: float = 0.8
    bound_noise_fraction: float = 0.75
    hypothesis_min_range_m: float = 3.5
    max_range_m: float = 6.0
    bound_visible_fraction: float = 1.0
    search_width_px: int = 424
    pretest_slack: float = 0.1
    search_candidates: int = 16
    sample_retries: int = 4
    candidate_merge_m: float | None = None
    zscore_threshold: float = 1.5
    zscore_variable: str = "distance"
    refine: str = "least_squares"
    noise_subpixel: float = 0.08
    noise_baseline_m: float = 0.050
    noise_z2_per_m: float | None = None
    noise_estimate: bool = True
    noise_estimate_lag_px: int = 3
    noise_estimate_samples: int = 1024
    noise_estimate_min_samples: int = 128
    noise_estimate_min_depth_m: float = 0.6
    noise_model_tolerance: float = 0.10
    noise_correlation: bool = True
    noise_correlation_min_px: float = 0.8
    noise_correlation_max_px: float = 3.0
    noise_from_data: bool = True
    noise_sigmas: float = 2.5
    max_eps_fraction: float = 1.5
    pretest_points: int = 12
    pretest_min_fraction: float = 0.5
    verify_candidates: int = 6
    verify_candidates_if_none: int = 16
    verify_score_margin: float = 6.0
    rescore_band: float = 0.15
    multistart_noise_fraction: float = 0.5
    outline_noise_fraction: float = 0.25
    outline_evidence: bool = True
    outline_evidence_noise_fraction: float = 0.5
    outline_evidence_min_move_px: float = 0.25
    outline_evidence_min_score: float = 0.05
    outline_size: bool = True
    outline_size_floor_px: float = 0.25
    outline_gap_sigmas: float = 3.0
    outline_band_px: float = 2.0
    outline_band_fraction: float = 0.15
    outline_min_side: int = 4
    outline_max_shift_fraction: float = 0.5
    outline_max_bias_px: float = 1.0
    outline_iterations: int = 3
    fit_max_points: int = 400
    score_max_points: int = 400
    refine_iterations: int = 4
    min_inliers: int = 30
    size_check: bool = True
    size_tolerance_m: float = 0.004
    size_tolerance_fraction: float = 0.04
    size_sigmas: float = 3.0
    max_spheres: int = 4
    nms_distance_fraction: float = 0.75
    min_score: float = 0.35
    max_points: int = 2_000_000
    mm_check: bool = True
    mm_check_median_m: float = 50.0
    noise_estimate_keep: float = 0.9
    # search geometry (organised)
    box_half_fraction: float = 0.25
    box_offset_fraction: float = 0.5
    search_off_axis: bool = False
    retry_occluder: bool = True
    retry_off_axis: bool = True
    retry_new_fraction: float = 0.25
    retry_disc: bool = True
    occluded_push_fraction: float = 0.5
    occluded_push_starts: int = 4
    occluded_push_noise_fraction: float = 0.25
    disc_noise_fraction: float = 0.25
    disc_inner_fraction: float = 0.5
    disc_side_offset_fraction: float = 1.7
    disc_side_half_fraction: float = 0.35
    disc_gap_fraction: float = 1.0
    disc_gap_sigmas: float = 3.0
    disc_min_behind: int = 3
    disc_step_fraction: float = 0.5
    ring_offset_fraction: float = 1.5
    ring_half_fraction: float = 0.25
    prefilter_offset_fraction: float = 2.0
    descent_steps: int = 3
    box_min_valid: float = 0.3
    pretest_max_continued: int = 3
    # refinement
    first_band_fraction: float = 0.5
    first_steps: int = 3
    coarse_band_fraction: float = 0.25
    ray_s_min_fraction: float = 0.03
    radius_se_s_min_fraction: float = 0.3
    size_limit_fraction: float = 0.25
    rescore_offset_xy: float = 0.2
    rescore_offset_z: float = 0.33
    verify_quality_fraction: float = 0.15
    interior_bands: float = 3.0
    # evidence
    ring_factor: float = 1.3
    ring_front_min_fraction: float = 0.3
    ring_front_max_fraction: float = 1.2
    profile_inner_sq: float = 0.3
    profile_outer_sq: float = 0.8
    behind_power: float = 2.0
    occlusion_discount: float = 1.0
    occlusion_ring_max: float = 0.05
    occlusion_min_visible: float = 0.35
    occlusion_size_sigmas: float = 0.5
    hug_power: float = 2.0
    ring_continued_power: float = 2.0
    ring_front_free: float = 0.15
    ring_front_power: float = 4.0
    see_through_free: float = 0.03
    see_through_power: float = 4.0
    see_through_sigmas: float = 3.0
    edge_behind_free: float = 0.4
    edge_behind_power: float = 4.0
    edge_behind_sigmas: float = 2.0
    relief_floor_fraction: float = 0.03
    relief_free_sigmas: float = 1.0
    ring_spread_free: float = 0.04
    ring_spread_power: float = 16.0
    interior_density_power: float = 2.0
    calibrate_evidence: bool = True

    def __post_init__(self) -> None:
        bad = _problems(self)
        if bad:
            raise SphereBenchError("invalid detector configuration: " + "; ".join(bad))

    @property
    def local_radius_m(self) -> float:
        """The local sampling radius: ``sample_radius_m`` or one ball diameter."""
        return 2.0 * self.radius_m if self.sample_radius_m is None else float(self.sample_radius_m)

    @property
    def merge_m(self) -> float:
        """Distance under which two candidate centres are one (paper pipeline): eps by default."""
        return self.eps_m if self.candidate_merge_m is None else float(self.candidate_merge_m)


def _problems(c: DetectorConfig) -> list[str]:
    # a switch is true or false: --set retry_disc=maybe (a string, truthy) must not pass as on
    out = [f"{f.name}={getattr(c, f.name)!r} must be true or false" for f in dataclasses.fields(c)
           if f.type in ("bool", bool) and not isinstance(getattr(c, f.name), bool)]

    def finite(name):
        v = getattr(c, name)
        ok = isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
        if not ok:
            out.append(f"{name}={v!r} must be a finite number")
        return ok

    if finite("radius_m") and c.radius_m <= 0:
        out.append(f"radius_m={c.radius_m} must be > 0 (the ball radius in metres, e.g. 0.12)")
    if finite("eps_m") and finite("radius_m"):
        if c.eps_m <= 0:
            out.append(f"eps_m={c.eps_m} must be > 0")
        elif c.eps_m >= c.radius_m > 0:
            out.append(f"eps_m={c.eps_m} must be smaller than the radius {c.radius_m} (e.g. 0.01)")
    for name, allowed in (("pipeline", PIPELINES), ("sampling", SAMPLINGS), ("solver", SOLVERS),
                          ("refine", REFINES), ("zscore_variable", ZSCORE_VARIABLES)):
        if getattr(c, name) not in allowed:
            out.append(f"{name}={getattr(c, name)!r} is not one of {', '.join(allowed)}")
    for name in ("iterations", "min_iterations", "sample_retries", "pretest_points", "score_max_points",
                 "refine_iterations", "min_inliers", "max_spheres", "max_points", "search_width_px",
                 "verify_candidates", "verify_candidates_if_none", "fit_max_points", "search_candidates",
                 "noise_estimate_lag_px", "noise_estimate_samples", "noise_estimate_min_samples", "descent_steps",
                 "pretest_max_continued", "first_steps", "outline_min_side", "outline_iterations",
                 "disc_min_behind", "occluded_push_starts"):
        v = getattr(c, name)
        if isinstance(v, bool) or not isinstance(v, int):
            out.append(f"{name}={v!r} must be an integer")
    if not out:
        if not 1 <= c.iterations <= 10_000_000:
            out.append(f"iterations={c.iterations} must be between 1 and 10,000,000")
        if c.min_iterations < 0 or c.sample_retries < 1 or c.score_max_points < 50:
            out.append("min_iterations must be >= 0, sample_retries >= 1, score_max_points >= 50")
        if c.max_spheres < 1 or c.min_inliers < 3 or c.max_points < 1000:
            out.append("max_spheres must be >= 1, min_inliers >= 3, max_points >= 1000")
        if (c.search_width_px < 16 or c.verify_candidates < 1 or c.fit_max_points < 10 or c.pretest_points < 1
                or c.search_candidates < 1 or c.verify_candidates_if_none < 1):
            out.append("search_width_px must be >= 16, verify_candidates and verify_candidates_if_none >= 1, "
                       "fit_max_points >= 10, pretest_points >= 1, search_candidates >= 1")
        if not (1 <= c.noise_estimate_lag_px <= 32 and 1 <= c.noise_estimate_min_samples <= c.noise_estimate_samples
                <= 1_000_000):
            out.append("noise_estimate_lag_px must be 1-32 and 1 <= noise_estimate_min_samples <= "
                       "noise_estimate_samples <= 1,000,000")
        if not (0 <= c.descent_steps <= 20 and 0 <= c.pretest_max_continued <= 8 and 1 <= c.first_steps <= 20):
            out.append("descent_steps must be 0-20, pretest_max_continued 0-8 (of the 8 ring boxes), first_steps 1-20")
        if not 1 <= c.disc_min_behind <= 4:
            out.append(f"disc_min_behind={c.disc_min_behind} must be 1-4 (of the disc search's four side boxes)")
    if finite("max_eps_fraction") and not 0.0 < c.max_eps_fraction <= 2.0:
        out.append(f"max_eps_fraction={c.max_eps_fraction} must be within (0, 2] (the band's cap over R)")
    for name in ("pretest_min_fraction", "min_score", "nms_distance_fraction",
                 "bound_visible_fraction", "size_tolerance_fraction", "box_min_valid", "ring_front_free",
                 "see_through_free", "edge_behind_free", "ring_spread_free", "verify_quality_fraction",
                 "occlusion_discount", "occlusion_ring_max", "occlusion_min_visible",
                 "ray_s_min_fraction", "outline_evidence_min_score"):
        if finite(name) and not 0.0 <= getattr(c, name) <= 1.0:
            out.append(f"{name}={getattr(c, name)} must be within [0, 1]")
    for name in ("confidence", "sample_success"):
        if finite(name) and not 0.0 < getattr(c, name) < 1.0:
            out.append(f"{name}={getattr(c, name)} must be within (0, 1)")
    if finite("bound_visible_fraction") and c.bound_visible_fraction <= 0:
        out.append("bound_visible_fraction must be > 0")
    for name in ("max_range_m", "bound_noise_fraction", "hypothesis_min_range_m"):
        if finite(name) and getattr(c, name) <= 0:
            out.append(f"{name}={getattr(c, name)} must be > 0")
    for name in ("zscore_threshold", "noise_sigmas", "pretest_slack", "size_tolerance_m", "size_sigmas",
                 "noise_subpixel", "noise_baseline_m", "mm_check_median_m", "verify_score_margin", "rescore_band",
                 "noise_estimate_min_depth_m", "noise_model_tolerance", "noise_correlation_min_px",
                 "noise_correlation_max_px",
                 "behind_power", "hug_power",
                 "ring_continued_power", "ring_front_power", "see_through_power", "edge_behind_power",
                 "ring_spread_power", "interior_density_power", "relief_floor_fraction", "relief_free_sigmas",
                 "rescore_offset_xy", "rescore_offset_z", "interior_bands", "see_through_sigmas",
                 "edge_behind_sigmas", "occlusion_size_sigmas", "disc_noise_fraction", "disc_gap_fraction",
                 "disc_gap_sigmas", "occluded_push_noise_fraction", "outline_evidence_min_move_px",
                 "outline_size_floor_px"):
        if finite(name) and getattr(c, name) < 0:
            out.append(f"{name}={getattr(c, name)} must be >= 0")
    for name in ("box_half_fraction", "box_offset_fraction", "ring_offset_fraction", "ring_half_fraction",
                 "prefilter_offset_fraction", "first_band_fraction", "coarse_band_fraction", "size_limit_fraction",
                 "noise_estimate_keep", "radius_se_s_min_fraction", "disc_inner_fraction", "disc_side_offset_fraction",
                 "disc_side_half_fraction", "disc_step_fraction", "occluded_push_fraction"):
        if finite(name) and not 0.0 < getattr(c, name) <= 4.0:
            out.append(f"{name}={getattr(c, name)} must be within (0, 4] (a fraction of the radius)")
    if finite("noise_estimate_keep") and c.noise_estimate_keep > 1.0:
        out.append(f"noise_estimate_keep={c.noise_estimate_keep} must be within (0, 1]")
    if all(finite(n) for n in ("profile_inner_sq", "profile_outer_sq")) and not (
            0.0 < c.profile_inner_sq < c.profile_outer_sq < 1.0):
        out.append(f"profile_inner_sq={c.profile_inner_sq}, profile_outer_sq={c.profile_outer_sq}: need "
                   "0 < inner < outer < 1 (squared fractions of R)")
    if all(finite(n) for n in ("ring_front_min_fraction", "ring_front_max_fraction")) and not (
            0.0 <= c.ring_front_min_fraction < c.ring_front_max_fraction):
        out.append("ring_front_min_fraction must be >= 0 and below ring_front_max_fraction")
    if finite("ring_factor") and not 1.0 < c.ring_factor <= 3.0:
        out.append(f"ring_factor={c.ring_factor} must be within (1, 3] (the outline ring's outer radius / R)")
    v = c.multistart_noise_fraction
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not v > 0:  # inf: never
        out.append(f"multistart_noise_fraction={v!r} must be > 0 (a fraction of R; inf for never)")
    for name in ("outline_noise_fraction", "outline_evidence_noise_fraction"):
        v = getattr(c, name)
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not v >= 0:  # 0: always; inf: never
            out.append(f"{name}={v!r} must be >= 0 (a fraction of R; inf for never)")
    if isinstance(c.occluded_push_starts, int) and not 0 <= c.occluded_push_starts <= 10:
        out.append(f"occluded_push_starts={c.occluded_push_starts!r} must be 0-10 (0: off)")
    if finite("retry_new_fraction") and not 0.0 <= c.retry_new_fraction <= 2.0:
        out.append(f"retry_new_fraction={c.retry_new_fraction} must be within [0, 2] (a fraction of R)")
    v = c.outline_max_bias_px
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not v > 0:  # inf: never held back
        out.append(f"outline_max_bias_px={v!r} must be > 0 (pixels; inf for never)")
    for name in ("outline_gap_sigmas", "outline_band_px", "outline_band_fraction", "outline_max_shift_fraction"):
        if finite(name) and not getattr(c, name) > 0:
            out.append(f"{name}={getattr(c, name)} must be > 0")
    if isinstance(c.outline_min_side, int) and not 1 <= c.outline_min_side <= 1000:
        out.append(f"outline_min_side={c.outline_min_side} must be 1-1000 (outline pixels on each side of an axis)")
    if isinstance(c.outline_iterations, int) and not 1 <= c.outline_iterations <= 20:
        out.append(f"outline_iterations={c.outline_iterations} must be 1-20")
    if finite("zscore_threshold") and c.zscore_threshold == 0:
        out.append("zscore_threshold must be > 0 (the paper uses 1.5)")
    if c.pipeline == "paper" and c.sampling != "global":
        out.append("the paper pipeline samples globally: use sampling='global' (local sampling is pipeline='improved')")
    if c.sample_radius_m is not None and not (finite("sample_radius_m") and c.sample_radius_m > 0):
        out.append(f"sample_radius_m={c.sample_radius_m} must be > 0")
    if c.noise_z2_per_m is not None and not (finite("noise_z2_per_m") and c.noise_z2_per_m >= 0):
        out.append(f"noise_z2_per_m={c.noise_z2_per_m} must be >= 0 (sigma_z / z^2 in 1/m, e.g. 0.0015)")
    if c.candidate_merge_m is not None and not (finite("candidate_merge_m") and c.candidate_merge_m > 0):
        out.append(f"candidate_merge_m={c.candidate_merge_m} must be > 0")
    return out


#: Section 2.5 of the paper, with the known-radius minimal solver.
PAPER = DetectorConfig(pipeline="paper", sampling="global", solver="known_radius", iterations=1000,
                       adaptive=False, refine="barycentre", max_spheres=1, min_inliers=3, min_score=0.0)
#: The ablation: the printed Eq. (12) solved by least squares (minimum-norm solution).
PAPER_LSTSQ = dataclasses.replace(PAPER, solver="lstsq_eq12")
#: The default: the paper's future work and the fixes of METHOD_NOTES.
IMPROVED = DetectorConfig()

PRESETS = {"paper": PAPER, "paper-lstsq": PAPER_LSTSQ, "improved": IMPROVED}


def config_for(name: str, **overrides) -> DetectorConfig:
    """A named preset ("paper", "paper-lstsq", "improved"; "_" works for "-") with fields overridden.

    >>> config_for("paper", iterations=10000).iterations
    10000
    """
    key = str(name).lower().replace("_", "-")
    if key not in PRESETS:
        raise SphereBenchError(f"unknown detector method '{name}': use one of {', '.join(PRESETS)}")
    fields = {f.name for f in dataclasses.fields(DetectorConfig)}
    unknown = sorted(set(overrides) - fields)
    if unknown:
        raise SphereBenchError(f"unknown detector parameter(s) {', '.join(unknown)}")
    return dataclasses.replace(PRESETS[key], **overrides)
