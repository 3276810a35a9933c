"""The simulator's datasets: a preset's scenes (``presets``), each rendered from its own seed
(``rendering.simulate_scene``), written as a dataset (``inout``), atomically, by one process or
several (the output is the same for any number).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from pathlib import Path

import numpy as np

from spherebench import __version__, reading
from spherebench.camera import Intrinsics
from spherebench.datasets import inout, outputs
from spherebench.datasets.families import FAMILIES
from spherebench.datasets.presets import (BASKETBALL_RADIUS_M, PRESETS, RESOLUTIONS, SENSOR_MODELS, assign_shares,
                                          resolve_preset)
from spherebench.datasets.rendering import scene_sensor, scene_stereo, simulate_scene
from spherebench.datasets.sensor import D435Sensor, check_setting
from spherebench.datasets.sequences import generate_sequences
from spherebench.datasets.stereo import StereoSensor, check_stereo, check_stereo_ranges
from spherebench.errors import SphereBenchError
from spherebench.parallel import each_with_progress, usable_cpus


def plan(preset_name: str, n: int | None = None, seed: int = 0) -> list[tuple[int, str, str]]:
    """(index, family, resolution) of every scene of a preset run (a variant's: its base's)."""
    preset_name, _overrides = resolve_preset(preset_name)
    preset = PRESETS[preset_name]
    n = preset.n_default if n is None else int(n)
    if n <= 0 or n > 1_000_000:
        raise SphereBenchError(f"--n {n}: the number of scenes must be between 1 and 1,000,000")
    unknown = [f for f, _share in preset.families if (preset.grammar, f) not in FAMILIES]
    if unknown:
        raise SphereBenchError(f"the {preset_name} preset names families that its {preset.grammar} grammar lacks: "
                               f"{', '.join(unknown)} (register_family)")
    if preset_name == "paper" and n != 3:
        raise SphereBenchError("the paper preset is its three fixed scenes E1-E3: leave --n out")
    families = assign_shares(preset.families, n)
    if preset.sensor is not None and preset.sensor.grid:
        # by shares within each (grid cell, family), so that every cell has the same mix
        groups: dict[tuple[int, str], list[int]] = {}
        for i, f in enumerate(families):
            groups.setdefault((i % preset.sensor.n_cells, f), []).append(i)
        resolutions = [""] * n
        for members in groups.values():
            for i, r in zip(members, assign_shares(preset.resolutions, len(members))):
                resolutions[i] = r
    else:
        res_rng = np.random.default_rng([preset.code, int(seed), 7])
        names, shares = zip(*preset.resolutions)
        resolutions = res_rng.choice(names, size=n, p=np.asarray(shares) / sum(shares))
    return [(i, f, str(r)) for i, (f, r) in enumerate(zip(families, resolutions))]


def _build_one(args) -> str:
    preset_name, index, family, seed, resolution, radius_m, sensor, overrides, scenes_dir, clouds = args
    scene = simulate_scene(preset_name, index, family, seed, resolution, radius_m, sensor, overrides)
    inout.write_scene(scenes_dir, scene, radius_m, write_cloud=clouds)
    return scene.scene_id


def generate_dataset(preset_name: str, out_dir: str | Path, n: int | None = None, seed: int = 0,
                     radius_m: float = BASKETBALL_RADIUS_M, sensor: D435Sensor = D435Sensor(),
                     workers: int = 1, progress: bool = True, clouds: bool | None = None,
                     sensor_overrides: Mapping | None = None, sensor_model: str | None = None,
                     before_commit: Callable[[Path], None] | None = None) -> Path:
    """Build a preset into ``out_dir`` (replaced atomically when complete); returns the path. A variant
    preset builds its base's scenes with its sensor settings (``resolve_preset``), recorded as its base.

    sensor: the base analytic sensor (the preset's sensor values, grid cells and ``sensor_overrides``,
    parameter -> value or (lo, hi), apply over it; see ``scene_sensor``).
    sensor_model: a name of SENSOR_MODELS (default: the preset's); ``stereo`` renders every scene
    through ``StereoSensor()`` with the preset's stereo draws (the analytic sensor's settings and
    ranges do not apply to it, and are refused). A stereo preset takes no other model.
    clouds: write each scene's cloud.ply (default: the preset's: yes, except for the training
    splits, whose 2D consumers read image.png only: 2,000 clouds would take several GB).
    before_commit: called with ``out_dir`` once the dataset is complete, before it replaces
    ``out_dir``: what fails there (the line that says so, on a full disk) leaves nothing."""
    preset_name, overrides = resolve_preset(preset_name, sensor_overrides)
    preset = PRESETS[preset_name]
    if preset.grammar == "motion":  # recordings of moving balls, not scenes
        if overrides or clouds or (sensor_model or preset.sensor_model) != preset.sensor_model or sensor != D435Sensor():
            raise SphereBenchError(f"the {preset_name} preset records sequences through its own sensor model: "
                                   "--sensor, --clouds and --sensor-model do not apply to it")
        reading.check_ball_radius(radius_m)
        return generate_sequences(preset_name, out_dir, n, seed, radius_m, workers, progress, before_commit)
    if sensor_model is None:
        sensor_model = preset.sensor_model
    if clouds is None:
        clouds = preset.clouds
    reading.check_ball_radius(radius_m)
    for name, value in overrides.items():
        check_setting(name, value)
    jobs = plan(preset_name, n, seed)
    if sensor_model not in SENSOR_MODELS:
        raise SphereBenchError(f"--sensor-model {sensor_model}: use one of {', '.join(SENSOR_MODELS)}")
    if preset.sensor_model != "analytic" and sensor_model != preset.sensor_model:
        raise SphereBenchError(f"--sensor-model {sensor_model}: the {preset_name} preset is the {preset.sensor_model} "
                               f"model's twin of {preset.twin_of}: use --preset {preset.twin_of} for the "
                               f"{sensor_model} model, or leave --sensor-model out")
    if sensor_model == "stereo":
        if overrides or preset.sensor is not None or sensor != D435Sensor():
            raise SphereBenchError(f"--sensor-model stereo: the {preset_name} preset or --sensor sets the analytic "
                                   "model's parameters, which the stereo model does not have: use a preset "
                                   "without a sensor grid (default, hard, train, paper, their -stereo twins) "
                                   "and no --sensor")
        sensor = StereoSensor()
        check_stereo_ranges(preset.stereo or {}, f"the {preset_name} preset's stereo ranges")
        for i, _f, resolution in jobs:  # every scene's sensor works at its stream before any work
            check_stereo(scene_stereo(preset_name, seed, i, sensor), Intrinsics.d435(*RESOLUTIONS[resolution]))
    else:
        for i, _f, _r in jobs:  # every scene's sensor is valid (e.g. drawn depth limits in order) before any work
            scene_sensor(preset_name, seed, i, sensor, overrides)
    out_dir = Path(out_dir)
    with outputs.atomic_directory(out_dir, outputs.replaceable_dataset) as tmp:
        scenes_dir = tmp / "scenes"
        scenes_dir.mkdir()
        tasks = [(preset_name, i, f, seed, r, radius_m, sensor, overrides, scenes_dir, clouds) for i, f, r in jobs]
        each_with_progress(_build_one, tasks, workers, f"generate {preset_name}", "scene", progress, chunksize=4)
        meta = {"name": out_dir.name, "preset": preset_name, "n": len(jobs), "seed": int(seed),
                "ball_radius_m": radius_m, "category": "basketball", "source": "simulated", "clouds": clouds,
                "sensor": sensor.to_dict(compact=True) if sensor_model == "analytic" else sensor.to_dict()}
        if sensor_model != "analytic":  # an analytic dataset's record reads as before the stereo model
            meta["sensor_model"] = sensor_model
        if preset.stereo:
            meta["stereo_ranges"] = {k: list(v) for k, v in preset.stereo.items()}
        if preset.twin_of:
            meta["twin_of"] = preset.twin_of
        if preset.grammar != "classic":  # the presets of the first grammar read as before
            meta["grammar"] = preset.grammar
        spec = PRESETS[preset_name].sensor
        if spec is not None:
            meta["sensor_ranges"] = spec.to_dict()
        if overrides:
            meta["sensor_overrides"] = {k: list(v) if isinstance(v, tuple) else v for k, v in overrides.items()}
        meta.update({"spherebench_version": __version__, "numpy_version": np.__version__})
        inout.finish_dataset(tmp, meta)
        if before_commit is not None:
            before_commit(out_dir)
    return out_dir


def default_workers() -> int:
    return min(4, usable_cpus())
