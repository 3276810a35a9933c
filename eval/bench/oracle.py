"""Ceilings on a scene with known ball centres.

**The own-pixel fit** (``own_pixel_fit``): a sphere of the known radius fitted from the true centre
on the ball's own pixels (its mask, where the frame has depth): what the ball's depth itself says
of its centre, whatever any detector's search and verdict do. The benchmark scores these fits as a
method (``registry``'s ``own-pixel-fit``): the share within 2 cm per range band, and their circles'
mAP.

**The detector's ceiling** (``ceiling``): verification started from the truth, so that the search
cannot lose the ball.

For each true ball, the detector's own verification (``verification.verify_organised``: refinement,
evidence, free-radius size check; ``verification.rescore`` near the threshold) runs on the same prepared
frame (the frame's measured noise included) from the true centre and from the six starts about it
that ``rescore`` uses (``verification.RESCORE_STARTS``): where the noise is a good part of R, the
refinement's optima lie a cm or two apart and one start's end is a draw. The ball is within the
**ceiling** when one of them accepts it as the detector would (size check passed, score at least
``min_score``) with its refined centre within 2 cm of the truth: a detector whose search always
started there would find it (the best score of those is the ball's score). The **separable** ceiling
drops the score threshold: the ball's score from the truth beats every clutter sphere the detector
verifies in the frame (its ranked output with ``rank_floor`` and ``min_score`` 0: every verified sphere
that passes the size check), so that some threshold would take it and no false detection of that frame.
Both are upper bounds of what the detector can reach on the data, not of what the data allow:
the verification's evidence is the detector's.
"""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np

from spherebench.cloud import Cloud
from spherebench.method import detect
from spherebench.method import compiled, verification
from spherebench.method.config import DetectorConfig
from spherebench.method.detector import prepare_frame

#: A ball is within the ceiling when its verification from the truth ends within this (m).
CEILING_M = 0.02


#: The own-pixel fit: at least this many pixels with depth, Gauss-Newton rounds, and the trim (robust
#: sigmas) of each round: a stereo ball's mask holds background depth along its outline.
OWN_PIXELS_MIN, OWN_FIT_ROUNDS, OWN_FIT_TRIM_SIGMAS = 20, 4, 3.0


def _ray_geometry(u: np.ndarray, c: np.ndarray, radius_m: float) -> tuple[np.ndarray, np.ndarray]:
    """(b, q) of unit rays u (N, 3) against the sphere (c, R): b = u.c, and q = R^2 - |c|^2 + b^2, which
    is positive where the ray meets the sphere; it enters at the range b - sqrt(q)."""
    b = u @ c
    return b, radius_m * radius_m - c @ c + b * b


def _ray_fit(t: np.ndarray, u: np.ndarray, c: np.ndarray, radius_m: float,
             iterations: int = 15) -> np.ndarray | None:
    """Gauss-Newton with R fixed on the range residuals along each pixel's ray (the depth noise lies along
    the rays): ranges t (N,) m, unit rays u (N, 3), start c (3,) m; None where fewer than 10 rays meet
    the sphere."""
    c = np.asarray(c, np.float64).copy()
    for _ in range(iterations):
        b, q = _ray_geometry(u, c, radius_m)
        hit = q > 1e-10
        if np.count_nonzero(hit) < 10:
            return None
        s = np.sqrt(q[hit])
        res = t[hit] - (b[hit] - s)  # the pixel's range less its ray's entry into the sphere
        jac = u[hit] + (c - b[hit, None] * u[hit]) / s[:, None]
        step = np.linalg.lstsq(jac, res, rcond=None)[0]
        c += step
        if float(np.linalg.norm(step)) < 1e-6:
            break
    return c


def own_pixel_fit(points_m: np.ndarray, centre_m, radius_m: float) -> np.ndarray | None:
    """The centre (3,) m of a sphere of radius R fitted on a ball's own pixels (N, 3) m from its true centre:
    ``OWN_FIT_ROUNDS`` rounds, each keeping the pixels within ``OWN_FIT_TRIM_SIGMAS`` robust sigmas of the
    median range residual. None with fewer than ``OWN_PIXELS_MIN`` pixels, or where it runs more than R
    from the truth (the depth does not hold a sphere there)."""
    p = np.asarray(points_m, np.float64).reshape(-1, 3)
    p = p[np.all(np.isfinite(p), axis=1) & (np.linalg.norm(p, axis=1) > 0)]
    if len(p) < OWN_PIXELS_MIN:
        return None
    t = np.linalg.norm(p, axis=1)
    u = p / t[:, None]
    c0 = np.asarray(centre_m, np.float64)
    c, keep = c0, np.ones(len(p), bool)
    for _ in range(OWN_FIT_ROUNDS):
        c = _ray_fit(t[keep], u[keep], c, radius_m)
        if c is None or float(np.linalg.norm(c - c0)) > radius_m:
            return None
        b, q = _ray_geometry(u, c, radius_m)
        res = t - (b - np.sqrt(np.maximum(q, 0.0)))  # a ray that misses: its range past the closest approach
        med = float(np.median(res[keep]))
        sigma = 1.4826 * float(np.median(np.abs(res[keep] - med)))
        keep = np.abs(res - med) <= OWN_FIT_TRIM_SIGMAS * max(sigma, 1e-4)
        if np.count_nonzero(keep) < OWN_PIXELS_MIN:
            return None
    return c


def truth_verifications(frame, centre_m, config: DetectorConfig, buf):
    """The verifications of one ball from its true centre ``centre_m`` (3,) m and from the rescoring
    starts around it, each rescored where its score lies near the threshold: Candidates, or None
    where a start verifies nothing, in the order of the starts."""
    c = np.asarray(centre_m, np.float64)
    for off in ((0.0, 0.0, 0.0),) + verification.RESCORE_STARTS:
        v = verification.verify_organised(frame, c + config.radius_m * np.asarray(off), config, buf, frame.no_gate)
        if v is not None and abs(v.score - config.verification.accept_score) < verification.RESCORE_BAND:
            v = verification.rescore(frame, v, config, buf)
        yield v


def beats(best: dict, score: float, size_ok: bool, error_m: float) -> bool:
    """Whether a sphere (score, size check, distance to the truth m) replaces ``best`` (the same keys):
    the best-scoring one that ends near the truth with its size passed; failing that, the nearest
    (diagnostics)."""
    there = error_m <= CEILING_M and size_ok
    best_there = best["size_ok"] and best["error_m"] <= CEILING_M
    return (there and (not best_there or score > best["score"])) or (not best_there and error_m < best["error_m"])


def truth_best(frame, centre_m, config: DetectorConfig, buf):
    """The best of a ball's verifications from its true centre ``centre_m`` (3,) m (``truth_verifications``,
    kept by ``beats``) and its distance to the truth (m): (Candidate, error) or (None, inf)."""
    c = np.asarray(centre_m, np.float64)
    best = {"score": 0.0, "size_ok": False, "error_m": math.inf}
    kept = None
    for v in truth_verifications(frame, c, config, buf):
        if v is None:
            continue
        err = float(np.linalg.norm(v.centre_m - c))
        if beats(best, v.score, v.size_ok, err):
            best, kept = {"score": float(v.score), "size_ok": bool(v.size_ok), "error_m": err}, v
    return kept, best["error_m"]


def ceiling(cloud: Cloud, centres_m: Sequence, config: DetectorConfig, seed: int = 0,
            separable: bool = True) -> list[dict]:
    """Per true ball (``centres_m``: (B, 3) metres): {score, size_ok, error_m, within (the ceiling),
    separable (None unless asked)}. The cloud must be organised (a depth frame)."""
    frame = prepare_frame(cloud, config)
    buf = compiled.workspace("inliers", (frame.index_image.size + 1,), np.int64)
    out = []
    for c in centres_m:
        v, err = truth_best(frame, c, config, buf)
        out.append({"score": 0.0, "size_ok": False, "error_m": math.inf, "within": False, "separable": None}
                   if v is None else
                   {"score": float(v.score), "size_ok": bool(v.size_ok), "error_m": err,
                    "within": bool(err <= CEILING_M and v.size_ok and v.score >= config.verification.accept_score),
                    "separable": None})
    if separable and out:
        every = detect(cloud, config.override({"verification.rank_floor": 0.0}), seed=seed, min_score=0.0,
                       max_spheres=1000)
        clutter = [s for s in every
                   if all(np.linalg.norm(s.centre_m - np.asarray(c)) > CEILING_M for c in centres_m)]
        best_clutter = max((s.score for s in clutter), default=0.0)
        for r in out:
            r["separable"] = bool(r["size_ok"] and r["error_m"] <= CEILING_M and r["score"] > best_clutter)
    return out
