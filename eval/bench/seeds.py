"""The benchmark's one seeding rule for detectors: scene k of a run with seed s is detected with
``detection_seed(s, k)``.

Scenes are numbered 0, 1, ... in scene-id order (``eval.bench.tasks.dataset_scenes``); the seed of
each depends only on (run seed, index), never on the worker, the engine or the order in which
scenes are run, so a run's predictions are byte-identical for any number of workers, locally or
on Ray. Every run of a detector goes through it: the prediction sets of ``evaluate`` and ``make
eval``, Table 2, the oracle's ceiling, ``bench``, ``sweep`` and ``robustness`` (their seeds are
run seeds).

Not to be confused with ``datasets.presets.generation_seed(preset, seed, index)``, the seed from
which the simulator builds a scene (layout, sensor draw): it includes the preset, so that the
presets' scenes never share a seed; this one is the detector's random stream on a built scene.
"""

from __future__ import annotations

import numpy as np

#: How the meta files and provenance.json describe the rule.
DETECTION_SEED_RULE = "scene k: SeedSequence((seed, k))"


def detection_seed(run_seed: int, index: int) -> int:
    """The detector's seed for scene ``index`` (0-based, scene-id order) of a run: the first 63 bits of
    numpy's SeedSequence((run_seed, index))."""
    return int(np.random.SeedSequence([int(run_seed), int(index)]).generate_state(1, np.uint64)[0] >> 1)
