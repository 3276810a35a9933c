"""The simulator's presets: what each builds (its families with their shares, its resolutions, its
sensor), registered here (``register_preset``), and the seed of each of its scenes.

A preset names its families (``families``), so a new preset is one entry. A variant preset
(``hard-sensor``) is another preset's scenes with sensor settings of its own, built and recorded
exactly as ``--preset BASE --sensor ...`` would be. A preset may draw each scene's sensor
(``SensorRanges``: ranges, a grid of conditions), and ``--sensor`` settings override any
parameter; a scene's gt.json then records its sensor (and its grid cell), the dataset.json the
ranges.

Each scene has its own seed, drawn from (preset, --seed, index) by numpy's SeedSequence
(``generation_seed``), so a scene does not depend on the others (workers can build them in any
order) and the presets' seed streams are disjoint: the train split never repeats an evaluation
scene.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field, replace

import numpy as np

from spherebench.datasets import wide_scenes
from spherebench.datasets.families import HARD_FAMILIES
from spherebench.datasets.sensor import D435Sensor, SensorRanges
from spherebench.datasets.stereo import StereoSensor
from spherebench.errors import SphereBenchError

BASKETBALL_RADIUS_M = 0.12
RESOLUTIONS = {"424x240": (424, 240), "848x480": (848, 480), "1280x720": (1280, 720)}
#: The sensor models a scene can be rendered through: the analytic noise model (``sensor``) or the
#: rendered infrared pair matched by SGBM (``stereo``); the name selects the model's default parameters.
SENSOR_MODELS = {"analytic": D435Sensor, "stereo": StereoSensor}

#: The robust preset's grid: Intel's subpixel range x noise correlation x low-texture dropouts.
ROBUST_SENSOR = SensorRanges(grid=(
    ("subpixel", tuple((s, {"subpixel": s}) for s in (0.05, 0.08, 0.12, 0.16, 0.20))),
    ("correlation", (("none", {"correlation_px": 0.0}), ("1px", {"correlation_px": 1.0}))),
    ("dropouts", (("off", {"dropout_probability": 0.0}), ("on", {"dropout_probability": 0.5}))),
))

#: The train preset's per-scene sensor draws: wider than the robust grid on every axis, so that
#: everything chosen on train is chosen across sensor variation, not at the nominal unit.
TRAIN_SENSOR = SensorRanges(values={
    "subpixel": (0.04, 0.22), "correlation_px": (0.0, 1.5), "dropout_probability": (0.0, 0.6),
    "dropout_fraction": (0.1, 0.5), "flying_probability": (0.15, 0.45),
    "depth_scale_error": (-0.003, 0.003), "depth_bias_m": (-0.002, 0.002),
})

#: The train-stereo preset's per-scene stereo draws (the nominal values of StereoSensor inside each
#: range): ambient infrared from a dim room to one beside a window, the emitter's power (laser power
#: setting and unit spread), the dots' focus and power spread, the imager's read noise.
TRAIN_STEREO = {
    "dot_sigma_mrad": (0.9, 1.6), "dot_power_spread": (0.1, 0.35), "dot_peak_e_per_ms": (900.0, 2000.0),
    "ambient_e_per_ms": (10.0, 300.0), "read_noise_e": (2.0, 8.0),
}


@dataclass(frozen=True)
class Preset:
    """What a preset builds: its default size, its families (with shares) and resolutions."""

    name: str
    code: int                                   # enters every scene seed: one stream per preset (shared by its resolution_of renderings)
    n_default: int
    families: tuple[tuple[str, float], ...]
    resolutions: tuple[tuple[str, float], ...] = (("424x240", 1.0),)
    sensor: SensorRanges | None = None          # per-scene analytic sensor draws; None: the given sensor for all
    sensor_model: str = "analytic"              # a name of SENSOR_MODELS: what every scene is rendered through
    stereo: Mapping | None = None               # per-scene stereo draws, parameter -> (lo, hi) (stereo presets)
    clouds: bool = True                         # write cloud.ply per scene by default
    twin_of: str | None = None                  # the analytic preset whose families and sizes a stereo one repeats
    grammar: str = "classic"                    # the scene grammar its families come from (dataset.json says a new one)
    benchmark: bool = False                     # one of the presets `make eval` runs every method on
    role: str = ""                              # a PRESET_* role the results' reading looks it up by
    description: str = ""                       # what the reading says it is
    variant_of: str | None = None               # a variant: that preset's scenes with sensor_overrides
    sensor_overrides: Mapping = field(default_factory=dict)
    holes: tuple[tuple[str, float], ...] = ()   # family -> share of its scenes whose balls get a Hole (HOLE_STREAM)
    resolution_of: str | None = None            # the preset whose seed stream (layouts) this one renders at its resolutions


#: The roles the results' reading (``eval.bench.prose``) looks presets up by, rather than by name.
PRESET_PROTOCOL = "the paper's protocol"  # read first: the paper's rows, the 2D rules, the learned baselines
PRESET_HARD = "the hard cases"            # read for its negative scenes and its per-family table

PRESETS: dict[str, Preset] = {}


def register_preset(preset: Preset) -> Preset:
    """Enter a preset in PRESETS (its name must be new; a variant's base must be there)."""
    if preset.name in PRESETS:
        raise ValueError(f"preset {preset.name} is registered already")
    if preset.variant_of is not None and preset.variant_of not in PRESETS:
        raise ValueError(f"preset {preset.name}: its base {preset.variant_of} is not registered")
    PRESETS[preset.name] = preset
    return preset


def preset_with_role(role: str) -> str | None:
    """The name of the first registered preset of a role, or None."""
    return next((name for name, p in PRESETS.items() if p.role == role), None)


def benchmark_presets() -> tuple[str, ...]:
    """The presets `make eval` reads under its data folder: the analytic ones, then their stereo
    twins, each in registration order."""
    chosen = [name for name, p in PRESETS.items() if p.benchmark]
    return tuple(n for n in chosen if PRESETS[n].twin_of is None) + tuple(n for n in chosen if PRESETS[n].twin_of)


def resolve_preset(preset_name: str, overrides: Mapping | None = None) -> tuple[str, dict]:
    """(the preset whose scenes are built, the sensor overrides): a variant's base and its settings,
    under those given; any other preset as it is."""
    if preset_name not in PRESETS:
        raise SphereBenchError(f"unknown preset '{preset_name}': use one of {', '.join(PRESETS)}")
    preset = PRESETS[preset_name]
    if preset.variant_of is None:
        return preset_name, dict(overrides or {})
    return preset.variant_of, {**preset.sensor_overrides, **(overrides or {})}


for _preset in (
    # the paper's protocol: 200 scenes, half clean, half cluttered, at 424x240
    Preset("default", 1, 200, (("clean", 0.5), ("cluttered", 0.5)), benchmark=True, role=PRESET_PROTOCOL,
           description="the paper's protocol: 200 scenes, half clean, half cluttered"),
    # the paper's three named experiments as fixed scenes
    Preset("paper", 2, 3, (("E1", 1 / 3), ("E2", 1 / 3), ("E3", 1 / 3))),
    # what the paper did not test: distractors, occlusion, range, negatives, holes in the ball's depth;
    # mixed resolutions (20 scenes a family; the holed ones last, so that the first 140 are as before)
    Preset("hard", 3, 160, tuple((f, 1 / (len(HARD_FAMILIES) + 1)) for f in HARD_FAMILIES + ("holed",)),
           (("424x240", 0.5), ("848x480", 0.3), ("1280x720", 0.2)), benchmark=True, role=PRESET_HARD),
    # training split for learned baselines and for every choice: the evaluation presets'
    # distributions, other seeds, each scene's sensor drawn from TRAIN_SENSOR; no clouds (its 2D
    # consumers read image.png only)
    Preset("train", 4, 2000, (("clean", 0.3), ("cluttered", 0.35))
           + tuple((f, 0.35 / len(HARD_FAMILIES)) for f in HARD_FAMILIES),
           (("424x240", 0.7), ("848x480", 0.15), ("1280x720", 0.15)), TRAIN_SENSOR, clouds=False,
           holes=(("clean", 0.2), ("cluttered", 0.2))),  # a fifth of its balls in view with a hole
    # default's families over a grid of sensor conditions (ROBUST_SENSOR): 20 cells x 20 scenes,
    # each cell half clean, half cluttered, 80 % at 424x240
    Preset("robust", 5, 400, (("clean", 0.5), ("cluttered", 0.5)), (("424x240", 0.8), ("848x480", 0.2)),
           ROBUST_SENSOR, benchmark=True,
           description="`default`'s scenes over a grid of sensor conditions: subpixel noise, its correlation, "
                       "low-texture dropouts"),
):
    register_preset(_preset)


def _stereo_twin(name: str, code: int, stereo: Mapping | None = None) -> Preset:
    """The stereo model's twin of an analytic preset: its families, sizes and resolutions, its own
    seed stream (``code``), every scene rendered through StereoSensor (with ``stereo`` drawn per scene);
    a benchmark preset if its base is one, with no role of its own."""
    base = PRESETS[name]
    return replace(base, name=f"{name}-stereo", code=code, sensor=None, sensor_model="stereo", stereo=stereo,
                   twin_of=name, role="", description="")


register_preset(_stereo_twin("default", 6))
register_preset(_stereo_twin("hard", 7))
# `default-stereo`'s scenes (its seed stream: the same layouts, within the few mm that the image's
# border moves a ball drawn in view) rendered at the D435's other depth modes: the resolution study
# of `make eval` (``eval.bench.resolution``)
for _res in ("848x480", "1280x720"):
    register_preset(replace(PRESETS["default-stereo"], name=f"default-stereo-{_res.split('x')[0]}",
                            resolutions=((_res, 1.0),), benchmark=False, resolution_of="default-stereo",
                            description=f"`default-stereo`'s scenes at {_res}"))
# train's twin: as train draws its analytic sensor per scene, this draws the unit's light and
# imager per scene (TRAIN_STEREO), so that choices made on it hold across units and rooms
register_preset(_stereo_twin("train", 8, TRAIN_STEREO))
# the wide grammar (``wide_scenes``): pitched and rolled cameras, the ball on every support among
# furniture, distractors, low-albedo and textured surfaces, negatives; 70 % at 424x240
register_preset(Preset("wide", 9, 200, wide_scenes.SHARES, (("424x240", 0.7), ("848x480", 0.3)), grammar="wide",
                       benchmark=True))
register_preset(_stereo_twin("wide", 10))
# a ball in clear view with its depth missing over 30-70 % of its face (the holed family)
register_preset(Preset("holes", 11, 100, (("holed", 1.0),), (("424x240", 0.7), ("848x480", 0.3)),
                       description="a ball in clear view whose depth is missing over 30-70 % of its face"))
register_preset(_stereo_twin("holes", 12))
# moving balls for streams (``sequences``): recordings of 2-6 s at the depth stream's rate (90 fps; 30 at
# 1280x720) with per-frame truth, the families of the motion grammar in equal shares; and its twin
register_preset(Preset("motion", 13, 24, tuple((f, 1 / 6) for f in ("rolling", "thrown", "crossing", "behind", "soccer",
                                                                  "carried")),
                       (("424x240", 0.5), ("848x480", 0.35), ("1280x720", 0.15)), clouds=False, grammar="motion",
                       description="recordings of moving balls with per-frame truth (rolling, thrown, crossing, "
                                   "behind a box, beside a soccer ball, carried by hand)"))
register_preset(_stereo_twin("motion", 14))
# hard's scenes (the same layouts, seeds and records) under the robust grid's span of sensors, drawn
# per scene: far and partly hidden balls on noisier, correlated units with low-texture dropouts
register_preset(replace(PRESETS["hard"], name="hard-sensor", benchmark=False, role="", variant_of="hard",
                        sensor_overrides={"subpixel": (0.05, 0.20), "correlation_px": (0.0, 1.0),
                                          "dropout_probability": (0.0, 0.5)}))


def generation_seed(preset: Preset, seed: int, index: int) -> int:
    """The seed from which the simulator builds scene ``index`` of a preset's dataset of seed ``seed``
    (its layout and sensor draw): SeedSequence((preset code, seed, index)), so that no two presets'
    scenes share one. Not the detector's seed on the built scene (``eval.bench.seeds.detection_seed``)."""
    return int(np.random.SeedSequence([preset.code, int(seed), int(index)]).generate_state(1, np.uint64)[0])


def assign_shares(shares: tuple[tuple[str, float], ...], n: int) -> list[str]:
    """Deterministic split of n items by shares, in blocks (largest remainder)."""
    raw = [s * n for _, s in shares]
    counts = [int(math.floor(x)) for x in raw]
    for k in sorted(range(len(raw)), key=lambda k: counts[k] - raw[k])[: n - sum(counts)]:
        counts[k] += 1
    return [name for (name, _), c in zip(shares, counts) for _ in range(c)]
