"""Stage 3, verification: a hypothesis refined into a sphere and measured, then scored by the verdict.

Gauss-Newton with R fixed, re-selecting the inliers each round: first on ||p - c|| - R (from a
start some cm to the side, the residuals along rays that miss the sphere hardly move the centre),
then on the residual along each pixel's ray, where the D435's noise lies
(``verification_kernels.verify_organised``). A free-radius fit is the size check, a hard gate (most
candidates stop there). Then the statistics of the whole silhouette and its outline ring
(``verification_kernels.window_stats``: the shares of pixels that are inliers, seen behind the
sphere, hugging it, continuing or attached at the outline, seen through the inner disc or the edge
band, the relief of the inner zone against the outer ones), which the verdict turns into a
probability (``verdict``). Where one pixel's noise nears R the hypothesis is verified from several
starts, and a candidate near the acceptance threshold takes the mean over six starts about it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np

from spherebench.circles import norm3
from spherebench.method import frame_kernels as FK
from spherebench.method import verification_kernels as VK
from spherebench.method.compiled import workspace
from spherebench.method.config import DetectorConfig
from spherebench.method.frame import PreparedFrame
from spherebench.method.outline import (
    OUTLINE_EVIDENCE_MIN_MOVE_PX, OUTLINE_EVIDENCE_MIN_SCORE, OUTLINE_EVIDENCE_NOISE_FRACTION, outline_centre,
    outline_size)
from spherebench.method.verdict import verdicts

# Where verification starts from; each chosen on the training splits
# (docs/experiments/2026-12-04-config-history.md and the records it points to).
RESCORE_BAND = 0.15  # a candidate within this of accept_score is verified again from six starts
RESCORE_OFFSET_XY = 0.2  # the six starts' offsets across the line of sight (* R) ...
RESCORE_OFFSET_Z = 0.33  # ... and along it (* R)
MULTISTART_NOISE_FRACTION = 0.5  # while none is accepted, seven starts where one pixel's noise exceeds this * R
OCCLUDED_PUSH_FRACTION = 0.5  # an occluded hypothesis is verified again pushed back by this * R ...
OCCLUDED_PUSH_STARTS = 4  # ... from up to this many starts ...
OCCLUDED_PUSH_NOISE_FRACTION = 0.25  # ... where one pixel's noise is below this * R
NOISE_FROM_DATA = True  # the final band narrows to a candidate's own residual spread where that is below the model's

#: ``rescore``'s six starts about a refined centre (units of R): across the line of sight (camera x and y)
#: and along it (z), where the refinement's optima lie a cm or two apart at 2-3 m
RESCORE_STARTS = ((RESCORE_OFFSET_XY, 0.0, 0.0), (-RESCORE_OFFSET_XY, 0.0, 0.0), (0.0, RESCORE_OFFSET_XY, 0.0),
                  (0.0, -RESCORE_OFFSET_XY, 0.0), (0.0, 0.0, RESCORE_OFFSET_Z), (0.0, 0.0, -RESCORE_OFFSET_Z))


@dataclass
class Candidate:
    """One verified sphere before it becomes a ``Sphere`` (indices into the searched points)."""

    centre_m: np.ndarray
    inliers: np.ndarray
    eps_m: float
    free_centre_m: np.ndarray
    free_radius_m: float
    free_radius_se_m: float
    rmse_m: float
    stats: dict
    score: float  # the probability of a ball (``verdict``)
    size_ok: bool
    raw_score: float  # the verdict's score before its calibration


def size_ok(free_r: float, free_se: float, config: DetectorConfig) -> bool:
    """The size check: the free radius free_r (m) within the tolerance plus ``size_sigmas`` of its
    standard error free_se (m; R standing in for an unknown one) of R, and never beyond
    ``verification_kernels.SIZE_LIMIT_FRACTION`` R whatever the error says; True without ``size_check``
    (compiled for many: ``verification_kernels.size_checks``)."""
    if not config.refinement.size_check:
        return True
    R = config.radius_m
    se = free_se if math.isfinite(free_se) else R
    d = abs(free_r - R)
    return bool(math.isfinite(free_r) and d <= config.radius_tolerance_m + config.refinement.size_sigmas * se
                and d <= VK.SIZE_LIMIT_FRACTION * R)


def verify_organised(frame: PreparedFrame, c0: np.ndarray, config: DetectorConfig, buf: np.ndarray,
                     gate: np.ndarray | None = None, hold_direction: bool = False) -> Candidate | None:
    """Refine one candidate of an organised cloud, measure its evidence, fit the free radius, score it
    (``verify_starts`` from the one start c0 (3,) m)."""
    return verify_starts(frame, np.asarray(c0, np.float64).reshape(1, 3), config, buf, gate, hold_direction)[0]


def verify_starts(frame: PreparedFrame, starts_m: np.ndarray, config: DetectorConfig, buf: np.ndarray,
                  gate: np.ndarray | None = None, hold_direction: bool = False) -> list[Candidate | None]:
    """Verify from each of starts_m (K, 3) m apart: refine, measure the evidence, fit the free radius,
    score; None where too few inliers remain or the kernel's size gate stops it (``verify_rows``)."""
    rows = verify_rows(frame, starts_m, config, buf, gate, hold_direction)
    return [rows.candidate(k, buf) for k in range(len(starts_m))]


@dataclass
class Verified:
    """The verifications of K starts as arrays, row k start k's (``verify_rows``). A ``Candidate`` is
    made only for the rows that are used as one (``candidate``): of a hypothesis's several starts,
    most give only their score and size check."""

    outs: np.ndarray  # (K, N_VOUT): the kernel's outputs (``verification_kernels.verify_organised``)
    measured: np.ndarray  # (K, N_MEASURED): the measurements (``verification_kernels.measurements``)
    kept: np.ndarray  # (K,) bool: enough inliers, a verified sphere
    raw: np.ndarray  # (K,): the verdict's raw score (0 where not kept)
    score: np.ndarray  # (K,): its probability (0 where not kept)
    size_ok: np.ndarray  # (K,) bool: the size check (False where not kept)

    def replace(self, at: list[int], other: Verified) -> None:
        """Rows ``at`` become other's rows, in order."""
        for name in ("outs", "measured", "kept", "raw", "score", "size_ok"):
            getattr(self, name)[at] = getattr(other, name)

    def candidate(self, k: int, buf: np.ndarray) -> Candidate | None:
        """Row k's verified sphere, or None where it kept too few inliers."""
        if not self.kept[k]:
            return None
        out = self.outs[k]
        stats = dict(zip(VK.MEASUREMENT_NAMES, self.measured[k].tolist()))
        # inliers: filled in for the reported spheres only (``verification_kernels.final_inliers``)
        return Candidate(centre_m=out[VK.V_CX:VK.V_CZ + 1].copy(), inliers=buf[:0].copy(), eps_m=float(out[VK.V_EPS]),
                         free_centre_m=out[VK.V_FCX:VK.V_FCZ + 1].copy(), free_radius_m=stats["free_radius_m"],
                         free_radius_se_m=stats["free_radius_se_m"], rmse_m=float(out[VK.V_RMSE]), stats=stats,
                         score=float(self.score[k]), size_ok=bool(self.size_ok[k]), raw_score=float(self.raw[k]))


def verify_rows(frame: PreparedFrame, starts_m: np.ndarray, config: DetectorConfig, buf: np.ndarray,
                gate: np.ndarray | None = None, hold_direction: bool = False) -> Verified:
    """Verify from each of starts_m (K, 3) m apart, as rows (``Verified``). The starts share one
    kernel call and one run of the verdict (several starts: ``verify_noisy``, ``rescore_all``).
    Where one pixel's noise at a refined centre is at least ``OUTLINE_EVIDENCE_NOISE_FRACTION`` R
    (``DetectorConfig.outline.outline_evidence``), that candidate is then re-centred on its outline and
    verified again from there with its direction held: the cap's relief leaves the refined centre a
    pixel or more beside the ball, and the evidence is taken where the outline says the ball is.
    gate: the kernel's early stop (default ``frame.gate``). hold_direction: no refinement, and the
    fits move the centre along its ray only (``fit_kernels.fit_range``)."""
    rows = _verify_batch(frame, starts_m, config, buf, gate, hold_direction)
    kept = np.flatnonzero(rows.kept).tolist()
    if hold_direction or not config.outline.outline_evidence or not kept:
        return rows
    score, z = rows.score.tolist(), rows.outs[:, VK.V_CZ].tolist()  # Python's floats: most batches hold one row
    loud = [k for k in kept if score[k] >= OUTLINE_EVIDENCE_MIN_SCORE
            and frame.noise_a * z[k] ** 2 >= OUTLINE_EVIDENCE_NOISE_FRACTION * config.radius_m]
    again = []  # (index, outline centre, outline size or None): verified again from the outline
    for k in loud:
        centre = rows.outs[k, VK.V_CX:VK.V_CZ + 1].copy()
        oc = outline_centre(frame, centre, config)
        size = outline_size(frame, oc, config) if config.outline.outline_size else None
        # a move within a fraction of a pixel reclassifies few of the silhouette's pixels
        if size is None and (float(np.linalg.norm(oc - centre)) * frame.prm[FK.P_FX] / float(oc[2])
                             < OUTLINE_EVIDENCE_MIN_MOVE_PX):
            continue
        again.append((k, oc, size))
    # one batch per gate: the kernel's early stop judges the depth fit's radius, which an outline's size replaces
    for sized in (False, True):
        group = [a for a in again if (a[2] is not None) == sized]
        if group:
            rows.replace([a[0] for a in group],
                         _verify_batch(frame, np.array([a[1] for a in group]), config, buf,
                                       frame.no_gate if sized else gate, True, [a[2] for a in group]))
    return rows


def _verify_batch(frame: PreparedFrame, starts_m: np.ndarray, config: DetectorConfig, buf: np.ndarray,
                  gate: np.ndarray | None, hold_direction: bool,
                  sizes: list[tuple[float, float] | None] | None = None) -> Verified:
    """One pass of the verification kernel (``verification_kernels.verify_organised``) from each start
    (K, 3) m, scored together. sizes: None, or per start None or the outline's angular radius and its
    standard error (``outline_size``), which then give the size check's radius in place of the depth
    fit's (at the verified centre's distance)."""
    outs = np.empty((len(starts_m), VK.N_VOUT))
    sts = np.empty((len(starts_m), VK.N_STATS))
    starts_m = np.ascontiguousarray(starts_m, np.float64)
    args = (frame.prm, config.refinement.refine_iterations, VK.FIT_MAX_POINTS, VK.RAY_S_MIN_FRACTION,
            NOISE_FROM_DATA, frame.gate if gate is None else gate, hold_direction)
    threads = 1 if len(starts_m) == 1 else numba.get_num_threads()
    if threads == 1:  # waking the thread pool for one start costs a third of its verification
        for c0, out, st in zip(starts_m, outs, sts):
            VK.verify_organised(frame.points, frame.index_image, c0, *args, buf, out, st)
    else:  # one inlier buffer per thread; the starts handed out one at a time (numba's default: in equal blocks)
        idx = workspace("inliers_per_thread", (threads, len(buf)), np.int64)
        saved = numba.set_parallel_chunksize(1)
        try:
            VK.verify_many(frame.points, frame.index_image, starts_m, *args, idx, outs, sts)
        finally:
            numba.set_parallel_chunksize(saved)
    measured = np.empty((len(starts_m), VK.N_MEASURED))
    VK.measurements(outs, sts, frame.prm, frame.noise_corr_px, frame.noise_ratio, config.verification.min_inliers,
                    measured)
    kept = outs[:, VK.V_N] >= config.verification.min_inliers
    at = np.flatnonzero(kept)
    raw, score, passed = np.zeros(len(starts_m)), np.zeros(len(starts_m)), np.zeros(len(starts_m), bool)
    if len(at):
        for k in at.tolist() if sizes is not None else ():
            if sizes[k] is not None:  # the outline's angular radius at the verified centre's distance
                rho = float(np.linalg.norm(outs[k, VK.V_CX:VK.V_CZ + 1]))
                measured[k, VK.M_FREE_R] = rho * math.sin(sizes[k][0])
                measured[k, VK.M_FREE_SE] = rho * math.cos(sizes[k][0]) * sizes[k][1]
        raw[at], score[at] = verdicts(measured[at], config.radius_m)
        VK.size_checks(measured, kept, frame.gate, config.radius_m, passed)
    return Verified(outs, measured, kept, raw, score, passed)


def verify_noisy(frame: PreparedFrame, c0s_m: np.ndarray, config: DetectorConfig,
                 buf: np.ndarray) -> list[Candidate | None]:
    """Hypotheses (H, 3) m whose depth noise is a good part of R (``MULTISTART_NOISE_FRACTION``), each
    verified from its centre and from each of ``RESCORE_STARTS`` about it; where one pixel's noise
    nears R, the refinement's end depends on its start by a few cm, and a hypothesis a few cm off
    converges off the ball's optimum. Each one's best-scoring verification that passes the size
    check is kept (the first of equals; None where none passes) and rescored (``rescore_all``): the
    best of several starts is a biased draw. The H hypotheses share two kernel calls and two runs
    of the verdict; each one's result is the same as when verified alone."""
    c0s_m = np.asarray(c0s_m, np.float64).reshape(-1, 3)
    offsets = config.radius_m * np.asarray(((0.0, 0.0, 0.0),) + RESCORE_STARTS)
    n = len(offsets)
    rows = verify_rows(frame, (c0s_m[:, None, :] + offsets[None]).reshape(-1, 3), config, buf)
    score = np.where(rows.size_ok, rows.score, -np.inf).reshape(-1, n)
    first = np.argmax(score, axis=1)  # the first of the best
    best = [rows.candidate(h * n + int(j), buf) if rows.size_ok[h * n + j] else None for h, j in enumerate(first)]
    rescore_all(frame, [b for b in best if b is not None], config, buf)
    return best


def verify_pushed(frame: PreparedFrame, c0: np.ndarray, config: DetectorConfig,
                  buf: np.ndarray) -> Candidate | None:
    """A hypothesis that passed the search's pretest by an occluded side, verified from its centre and,
    while that fails, from starts pushed back along its ray (``OCCLUDED_PUSH_FRACTION`` R each, at most
    ``OCCLUDED_PUSH_STARTS``, only where one pixel's noise is below ``OCCLUDED_PUSH_NOISE_FRACTION`` R):
    the occluder's pixels in its centre box pull the front range, and the start, towards the camera,
    by up to the occluder's gap. The first verification that passes the size check within
    ``RESCORE_BAND`` of accept_score is returned, else the best that passes it (the first of equals),
    else the last."""
    R = config.radius_m
    ray = c0 / max(norm3(c0), 1e-9)
    quiet = frame.prm[FK.P_NOISE_A] * c0[2] ** 2 < OCCLUDED_PUSH_NOISE_FRACTION * R
    v = best = None
    for j in range(1 + (OCCLUDED_PUSH_STARTS if quiet else 0)):
        v = verify_organised(frame, c0 + j * OCCLUDED_PUSH_FRACTION * R * ray, config, buf)
        if v is not None and v.size_ok:
            if v.score >= config.verification.accept_score - RESCORE_BAND:
                return v
            best = v if best is None or v.score > best.score else best
    return best if best is not None else v


def rescore(frame: PreparedFrame, cand: Candidate, config: DetectorConfig, buf: np.ndarray) -> Candidate:
    """A candidate near the score threshold, verified again from each of ``RESCORE_STARTS`` about its centre
    (without the kernel's early stop, so that each start's whole score and size verdict count): its
    score becomes the mean of all (a start left with too few inliers counts 0) and its size check
    the majority's. The centre, evidence and fits stay the first verification's; stats gets
    "score_single", the first score (see ``RESCORE_BAND``); the raw score is averaged alike."""
    return rescore_all(frame, [cand], config, buf)[0]


def rescore_all(frame: PreparedFrame, cands: list[Candidate], config: DetectorConfig,
                buf: np.ndarray) -> list[Candidate]:
    """``rescore`` of each of cands, in place: all their starts in one kernel call and one run of the verdict."""
    if not cands:
        return cands
    n = len(RESCORE_STARTS)
    offsets = config.radius_m * np.asarray(RESCORE_STARTS)
    centres = np.array([c.centre_m for c in cands], np.float64)
    rows = verify_rows(frame, (centres[:, None, :] + offsets[None]).reshape(-1, 3), config, buf, frame.no_gate)
    scores, raws = rows.score.reshape(-1, n).tolist(), rows.raw.reshape(-1, n).tolist()  # 0 with too few inliers
    passed = np.count_nonzero(rows.size_ok.reshape(-1, n), axis=1).tolist()
    for cand, s, r, p in zip(cands, scores, raws, passed):
        cand.stats["score_single"] = cand.score
        cand.score, cand.raw_score = float(np.mean([cand.score] + s)), float(np.mean([cand.raw_score] + r))
        cand.size_ok = 2 * (p + cand.size_ok) > n + 1
    return cands
