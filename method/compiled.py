"""The kernels' compilation, their random stream and their reused buffers.

Every stage keeps its hot loops as numba kernels beside its Python (``frame_kernels``, ``noise``,
``search_kernels``, ``verification_kernels``, ``fit_kernels``, ``outline``, ``unorganised``),
compiled for one thread and cached on disk. Each kernel has a readable counterpart that the tests
compare it with: the minimal solver and the fits in ``sphere_model``, the search loops and the
window statistics in ``tests/search_reference.py`` (test code, not shipped). Random numbers come
from splitmix64 (``next_u01``), which the reference replays in pure Python, so that the compiled
and the reference search draw the same samples.

Conventions: points (N, 3) float32 metres in the camera frame; an organised cloud comes with
``index_image`` (H, W) int32, the point index of each pixel or -1 where its depth is invalid.
"""

from __future__ import annotations

import math
import threading

import numpy as np
from numba import njit


#: Every kernel's compilation: cached on disk, and numpy's error model: a float division by zero
#: gives inf or nan (the kernels guard the divisors that can vanish) instead of a zero check and a
#: Python exception path per division, which cost a fifth of the search's and verification's time.
kernel = njit(cache=True, error_model="numpy")
#: The same, inlined into its callers by numba (``inline="always"``): for the named parts of a long
#: kernel, called per pixel or per sample, where a call's cost (its array arguments' reference counts)
#: would show in the caller's time.
part = njit(cache=True, error_model="numpy", inline="always")
#: The same, releasing the GIL while it runs: for the long kernels (a search, a verification) that
#: run on two threads at once (the retries' searches beside the verifications,
#: ``improved.searched_ahead``). The short ones keep it: releasing it on every call cost 1.5 % of a
#: typical frame (``docs/experiments/2026-12-06-slow-frames.md``).
long_kernel = njit(cache=True, error_model="numpy", nogil=True)
#: A long kernel over numba's threads (``prange``): for independent pieces of work large enough to pay
#: for waking a thread (several verifications of one candidate); at one thread it runs them in order.
threaded_kernel = njit(cache=True, error_model="numpy", nogil=True, parallel=True)

_GOLDEN = np.uint64(0x9E3779B97F4A7C15)
_MIX1 = np.uint64(0xBF58476D1CE4E5B9)
_MIX2 = np.uint64(0x94D049BB133111EB)
_INV53 = 1.0 / 9007199254740992.0  # 2^-53


@kernel
def next_u01(state):
    """splitmix64: advance state (uint64 array of 1) and return a float64 uniform in [0, 1)."""
    state[0] += _GOLDEN
    z = state[0]
    z = (z ^ (z >> np.uint64(30))) * _MIX1
    z = (z ^ (z >> np.uint64(27))) * _MIX2
    z = z ^ (z >> np.uint64(31))
    return float(z >> np.uint64(11)) * _INV53


_WORKSPACE: dict = {}


#: A scratch array smaller than this (bytes) is made afresh: its page faults cost little, and the
#: windows of a tracked stream, a new size each frame, would otherwise evict the whole frame's buffers.
WORKSPACE_MIN_BYTES = 1 << 18


def workspace(name: str, shape: tuple, dtype) -> np.ndarray:
    """A reused scratch array (contents undefined): a fresh multi-megabyte array per frame costs
    more in page faults than the kernels that fill it. One per (name, shape, dtype, thread)."""
    dtype = np.dtype(dtype)
    if math.prod(shape) * dtype.itemsize < WORKSPACE_MIN_BYTES:  # math's: numpy's costs 5 us a call
        return np.empty(shape, dtype)
    key = (name, shape, dtype.str, threading.get_ident())
    buf = _WORKSPACE.get(key)
    if buf is None:
        if len(_WORKSPACE) > 32:  # many resolutions or threads: start over rather than grow
            _WORKSPACE.clear()
        buf = _WORKSPACE[key] = np.empty(shape, dtype)
    return buf
