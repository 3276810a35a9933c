"""The improved pipeline, stage by stage: the frame (``frame``, with its noise: ``noise``), the search
(``search``), verification (``verification``), the verdict (``verdict``) and the outline
(``outline``); unorganised clouds take ``unorganised``'s search and verification.

``run_improved`` verifies the search's hypotheses best first, at most ``verify_candidates``, or
``verify_candidates_if_none`` while none is accepted, and none whose search score is far below an
accepted one's (``VERIFY_SCORE_MARGIN``). A candidate at least ``accept_score`` probable is taken
as a ball: the budget narrows and the retries stop. Below it, every candidate that passes the size
check and is at least ``rank_floor`` probable is ranked, and the search goes on as if it were not
there. Duplicates are suppressed, best first, and the reported spheres are re-centred on their
outline where the noise nears R.
"""

from __future__ import annotations

import contextlib
import math
import threading
from collections.abc import Callable, Iterator

import numba
import numpy as np

from spherebench.method import outline, search, unorganised, verification
from spherebench.method import frame_kernels as FK
from spherebench.method import verification_kernels as VK
from spherebench.method.compiled import workspace
from spherebench.method.config import DetectorConfig
from spherebench.method.deadline import Deadline
from spherebench.method.frame import PreparedFrame
from spherebench.method.verification import Candidate

VERIFY_SCORE_MARGIN = 6.0  # once one is accepted, skip hypotheses whose search score is this far below it
RETRY_NEW_FRACTION = 0.25  # a retry's hypothesis this near (* R) a verified start is not verified again


def _verify_candidates(points: np.ndarray, frame: PreparedFrame | None, cands: np.ndarray, quals: np.ndarray,
                       occluded: np.ndarray, config: DetectorConfig, buf: np.ndarray | None,
                       found: list[Candidate], ranked: list[Candidate], limit_none: int | None = None,
                       multistart: bool = True, deadline: Deadline | None = None) -> list[np.ndarray]:
    """Verify the search's candidates (M, 3) m, best first, appending the accepted ones
    (``accept_score``) to ``found`` and the others that pass the size check and may rank
    (``rank_floor``) to ``ranked``; returns the starts verified. While none is accepted, an
    organised frame verifies up to
    ``verify_candidates_if_none`` (or ``limit_none``), and the hypotheses that passed the search's
    pretest only by an occluded side: a frame with a ball pays nothing for either. multistart: a
    noisy hypothesis is verified from several starts while none is accepted, several such hypotheses
    at once at more than one numba thread (``verification.verify_noisy``). deadline: none is
    verified once it has passed."""
    if limit_none is None:
        ver = config.verification
        limit_none = max(ver.verify_candidates, ver.verify_candidates_if_none if frame is not None else 0)
    q_accepted = -math.inf  # the best search score among the accepted
    verified: list[np.ndarray] = []
    noise_a = 0.0 if frame is None else frame.prm[FK.P_NOISE_A]  # one pixel's depth noise at z: noise_a z^2
    noisy_m = verification.MULTISTART_NOISE_FRACTION * config.radius_m  # beyond this, several starts
    ahead: dict[int, Candidate | None] = {}  # noisy hypotheses verified before their turn, by index
    ahead_n = 1  # how many noisy hypotheses the next call verifies
    for k, (c0, q) in enumerate(zip(cands, quals)):
        if k >= (config.verification.verify_candidates if found else limit_none):
            break
        if found and occluded[k]:
            continue
        # organised: hypotheses are sorted by score; those far below every accepted sphere's are clutter
        if frame is not None and q < q_accepted - VERIFY_SCORE_MARGIN:
            break
        # unorganised: candidates far below the best cannot win, verifying them would only cost time
        if frame is None and q < unorganised.VERIFY_QUALITY_FRACTION * quals[0]:
            break
        # a start within R of a sphere already accepted converges onto it, and would be suppressed; its
        # score is an accepted sphere's (one accepted from a tracker's hint has no search score)
        if any(math.dist(c0, v.centre_m) < config.radius_m for v in found):
            q_accepted = max(q_accepted, float(q))
            continue
        if deadline is not None and deadline.passed():
            break
        verified.append(c0)
        if frame is None:
            v = unorganised.verify_unorganised(points, c0, config)
        elif multistart and not found and noise_a * c0[2] ** 2 > noisy_m:
            # only while none is accepted: a frame with a ball pays nothing, and gets no second sphere this way
            if k not in ahead:
                # while none is accepted, every noisy hypothesis up to the limit is verified in turn: this
                # one and the next are verified together, their number doubling each time, as one call
                # shares their starts between the threads better than several; if one is accepted, those
                # after it were verified for nothing (one at a time at one thread or under a deadline)
                group = np.flatnonzero(noise_a * cands[k:limit_none, 2] ** 2 > noisy_m)[:ahead_n] + k
                ahead.update(zip(group.tolist(), verification.verify_noisy(frame, cands[group], config, buf)))
                ahead_n *= 2 if deadline is None and numba.get_num_threads() > 1 else 1
            v = ahead.pop(k)
        else:
            # a hypothesis with an occluded side (verified only while none is accepted): pushed back too
            v = (verification.verify_pushed(frame, np.asarray(c0, np.float64), config, buf) if occluded[k]
                 else verification.verify_organised(frame, c0, config, buf))
            if v is not None and abs(v.score - config.verification.accept_score) < verification.RESCORE_BAND:
                v = verification.rescore(frame, v, config, buf)
        if v is None or not v.size_ok or v.score < config.verification.rank_floor:
            continue
        if v.score < config.verification.accept_score:
            ranked.append(v)  # ranked, but the search goes on as if it were not there
            continue
        found.append(v)
        q_accepted = max(q_accepted, float(q))
    return verified


def run_improved(points: np.ndarray, frame: PreparedFrame | None, config: DetectorConfig,
                 seed: int, min_score: float | None = None, max_spheres: int | None = None,
                 deadline: Deadline | None = None, hints_m: np.ndarray | None = None,
                 search_all: bool = True) -> list[Candidate]:
    """Search, verify the best candidates, drop the failed ones, suppress duplicates. Best first.

    frame: the prepared organised cloud, or None to treat ``points`` (N, 3) as unorganised.
    The search and its verdicts are the same whatever is reported: the distinct verified spheres
    whose score is at least min_score (default ``verification.min_score``, never below ``rank_floor``),
    at most max_spheres (default ``verification.max_spheres``), are returned. deadline: the
    verifications and retries stop once it has passed (``deadline``); what was verified by then is
    reported. hints_m (K, 3): centres where balls are expected (a tracker's predictions), verified
    first, each from its own start (an organised frame's only); where one is accepted, the frame's
    search looks only for balls apart from it; with search_all False, a frame whose every hint is
    verified (accepted, or ranked below that) is not searched at all (a window about one ball).
    """
    ver = config.verification
    least = max(ver.min_score if min_score is None else min_score, ver.rank_floor)
    most = ver.max_spheres if max_spheres is None else max_spheres
    found: list[Candidate] = []
    ranked: list[Candidate] = []
    hinted: list[np.ndarray] = []
    # gather_window's index buffer: one silhouette's pixels at most. Sized by the image, not the cloud,
    # so that frames of one stream reuse it (a fresh 7 MB buffer per 1280x720 frame cost more in page
    # faults than the detection)
    buf = None if frame is None else workspace("inliers", (frame.index_image.size + 1,), np.int64)
    if frame is not None and hints_m is not None and len(hints_m):
        hints_m = np.asarray(hints_m, np.float64).reshape(-1, 3)
        # a tracker's prediction is within millimetres of its ball: one start each, no multistart
        hinted = _verify_candidates(points, frame, hints_m, np.zeros(len(hints_m)), np.zeros(len(hints_m), bool),
                                    config, buf, found, ranked, limit_none=len(hints_m), multistart=False,
                                    deadline=deadline)
        # a window about one ball: its hint verified (accepted, or ranked below that) is the answer; a
        # search of the window would only verify the same ball again from other starts
        if not search_all and len(found) + len(ranked) >= len(hints_m):
            return _reported(frame, config, found, ranked, least, most, buf)
    if frame is not None:
        cands, quals, occluded = search.search_frame(frame, config, seed)
    else:
        cands, quals = unorganised.search_unorganised(points, config, seed)
        occluded = np.zeros(len(cands), bool)
    verified = hinted + _verify_candidates(points, frame, cands, quals, occluded, config, buf, found, ranked,
                                           deadline=deadline)
    # organised frames where none is accepted: search again, the descent past occluders, then the
    # stencil stretched off the axis, then for discs standing out of their background, then for holes
    # ringed by a ball's face, and verify the hypotheses not verified before
    retries = [] if frame is None else (
        ([lambda: search.relief_search(frame, config, seed)] if config.retry.retry_relief else [])
        + ([lambda: search.search_frame(frame, config, seed, occluder_bound=True)]
           if config.retry.retry_occluder else [])
        + ([lambda: search.search_frame(frame, config, seed, off_axis=True)] if config.retry.retry_off_axis else [])
        + ([lambda: search.disc_search(frame, config)] if config.retry.retry_disc else [])
        + ([lambda: search.hole_search(frame, config)] if config.retry.retry_hole else []))
    if found or not retries:  # a frame with a ball found pays nothing for the retries
        return _reported(frame, config, found, ranked, least, most, buf)
    with searched_ahead(retries, deadline is None) as searches:
        for _ in retries:
            if found or (deadline is not None and deadline.passed()):
                break
            cands, quals, occluded = next(searches)
            apart = np.linalg.norm(cands[:, None, :] - np.reshape(verified, (1, -1, 3)), axis=2)
            new = np.flatnonzero((apart > RETRY_NEW_FRACTION * config.radius_m).all(axis=1))
            # the best verify_candidates of a retry's new hypotheses, each verified from one start: on `train`
            # 16, or the multistart of noisy ones, found about as many balls, at twice the time on an empty frame
            verified += _verify_candidates(points, frame, cands[new], quals[new], occluded[new], config, buf,
                                           found, ranked, limit_none=config.verification.verify_candidates,
                                           multistart=False, deadline=deadline)
    return _reported(frame, config, found, ranked, least, most, buf)


@contextlib.contextmanager
def searched_ahead(searches: list[Callable[[], tuple]], ahead: bool) -> Iterator[Iterator[tuple]]:
    """The results of searches, in turn, as an iterator; the caller stops taking them where it likes.
    With ahead (and more than one numba thread), a thread runs the searches one after the other
    while the caller verifies the hypotheses of those before: a frame where nothing is found runs
    every retry, whose searches took a fifth of its time. On leaving, no further search is started
    and the one running is waited for (a frame pays for its searches). The searches read the frame
    and write nothing that the verifications read, so the results are the same either way."""
    if not ahead or len(searches) < 2 or numba.get_num_threads() < 2:
        yield (fn() for fn in searches)
        return
    results: list[tuple | BaseException | None] = [None] * len(searches)
    ready = [threading.Event() for _ in searches]
    stop = threading.Event()

    def run() -> None:
        for k, fn in enumerate(searches):
            if stop.is_set():
                break
            try:
                results[k] = fn()
            except BaseException as e:  # handed to the caller, which raises it where it takes this result
                results[k] = e
            ready[k].set()

    def taken() -> Iterator[tuple]:
        for k in range(len(searches)):
            ready[k].wait()
            if isinstance(results[k], BaseException):
                raise results[k]
            yield results[k]

    worker = threading.Thread(target=run, name="spherebench-retries", daemon=True)
    worker.start()
    try:
        yield taken()
    finally:
        stop.set()
        worker.join()


def _reported(frame: PreparedFrame | None, config: DetectorConfig, found: list[Candidate], ranked: list[Candidate],
              least: float, most: int, buf: np.ndarray | None) -> list[Candidate]:
    """The distinct spheres reported, best first: at least ``least`` probable, at most ``most``, each
    re-centred on its outline where the noise nears R, with all its inliers."""
    # suppression before the cut, so that the spheres reported at any threshold are those above it at
    # the floor: a sphere is only ever suppressed by a better one
    kept: list[Candidate] = []
    min_sep = config.verification.nms_distance_fraction * 2.0 * config.radius_m
    for v in sorted(found + ranked, key=lambda v: -v.score):
        if v.score < least or len(kept) == most:
            break
        if all(math.dist(v.centre_m, k.centre_m) >= min_sep for k in kept):
            kept.append(v)
    if frame is not None:
        for v in kept:
            # where the noise nears R, the outline places the centre across the line of sight
            if frame.noise_a * float(v.centre_m[2]) ** 2 >= config.outline.outline_noise_fraction * config.radius_m:
                v.centre_m = outline.outline_centre(frame, v.centre_m, config)
            # verification visited strided windows: collect every inlier of the reported ones
            n, v.rmse_m = VK.final_inliers(frame.points, frame.index_image, v.centre_m, frame.prm, v.eps_m, buf)
            v.inliers = buf[:n].copy()
    return kept
