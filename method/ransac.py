"""The generic RANSAC sampling loop: sample, estimate, check, visit; nothing here knows spheres.

Samples are drawn and models estimated in vectorised batches, then visited one by one in the
order they were drawn, so the result is that of the plain sequential loop (same seed, same output)
at numpy speed. The visitor keeps whatever state the pipeline needs (the paper's list of
candidate centres, a best model...) and may stop the loop early.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np


def draw_distinct(rng: np.random.Generator, n_items: int, count: int, size: int) -> np.ndarray:
    """``count`` samples of ``size`` distinct indices in [0, n_items): (count, size) int64."""
    out = rng.integers(0, n_items, size=(count, size))
    # redraw the rows with a repeated index (rare for large n_items)
    while True:
        srt = np.sort(out, axis=1)
        dup = np.any(srt[:, 1:] == srt[:, :-1], axis=1)
        if not dup.any():
            return out
        out[dup] = rng.integers(0, n_items, size=(int(dup.sum()), size))


def sample_loop(iterations: int,
                sample: Callable[[np.random.Generator, int], np.ndarray],
                estimate: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]],
                check: Callable[[np.ndarray], np.ndarray],
                visit: Callable[[int, np.ndarray, np.ndarray], bool],
                rng: np.random.Generator, batch: int = 512) -> int:
    """Run ``iterations`` RANSAC draws; returns how many were drawn.

    sample(rng, k) -> (k, s) sample indices; estimate(samples) -> (models (k, d), valid (k,));
    check(models) -> (k,) bool, the model test (e.g. |r - R| <= eps); visit(iteration, model,
    sample) is called for each model that passed, in draw order, and returns True to stop.
    """
    done = 0
    while done < iterations:
        k = min(batch, iterations - done)
        samples = sample(rng, k)
        models, valid = estimate(samples)
        ok = np.asarray(valid, bool).copy()
        if ok.any():
            ok[ok] = check(models[ok])
        for j in np.flatnonzero(ok):
            if visit(done + int(j) + 1, models[j], samples[j]):
                return done + int(j) + 1
        done += k
    return done
