"""The D435 scene simulator: presets of scenes with exact ground truth, built from a seed.

A scene is a layout (``layouts``) ray-cast through the camera (``primitives``), passed through
the sensor model (``sensor``), with the ground truth of every ball of the dataset's radius:
its 3D centre, its visible mask (the ball is the first surface hit and the depth is valid), its
full silhouette, and their circles (``spherebench.circles``).

Each scene has its own seed, drawn from (preset, --seed, index) by numpy's SeedSequence, so a
scene does not depend on the others (workers can build them in any order) and the presets'
seed streams are disjoint: the train split never repeats an evaluation scene.

Presets and scene families are registered here (``register_preset``, ``register_family``):
a preset names its families, a family of a grammar is a layout builder with its visibility rule,
so a new preset or family is one entry, not a branch of ``simulate_scene``. A variant preset
(``hard-sensor``) is another preset's scenes with sensor settings of its own, built and recorded
exactly as ``--preset BASE --sensor ...`` would be.

A preset may draw each scene's sensor (``SensorRanges``: ranges, a grid of conditions), from a
stream of the scene's seed of its own, and ``--sensor`` settings override any parameter; a
scene's gt.json then records its sensor (and its grid cell), the dataset.json the ranges.

The ``holed`` family (presets ``holes`` and its stereo twin ``holes-stereo``, not benchmark
presets) is a ball in clear view 0.7-4 m away, in a bare or a cluttered room, whose depth is
missing over 30-70 % of its visible face, as where a glossy ball saturates the infrared imager:
a slightly irregular blob around the ball's specular point (for a light at the camera, the point
on the ray through its centre), jittered, leaving a ring of valid depth (``Hole``). Both sensor
models set the hole's pixels to 0 after their own depth (the analytic noise, the stereo match):
the same drawn share of the ball's valid pixels in either. In the stereo model this stands for
the depth the unit loses where its imagers saturate: a cap rendered bright enough to saturate
the 10-bit imagers still matches (SGBM carries the disparity into the flat patch from its
edges), so the hole is not left to the matcher. The hole is a sensor effect, not the ball's
outline: the ball's mask stays its first-surface pixels of valid depth before the hole (the
hole's pixels stay in it), and its circles and centre are those of the ball without the hole;
gt.json's meta records per ball the share of its valid pixels the hole took, measured on the
depth (``hole_fraction``; None: no hole). A preset may also give holes to a share of its other
families' scenes (``Preset.holes``: ``train`` and its twin, a fifth of their clean and cluttered
scenes), drawn from a stream of the scene's seed of its own, so that the scenes left whole are
byte for byte the scenes they were.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from functools import partial
from pathlib import Path
from typing import Callable

import numpy as np

from spherebench import __version__
from spherebench.camera import Intrinsics, image_rays, project
from spherebench.circles import sphere_circle_amodal, sphere_silhouette_mask
from spherebench.datasets import inout, outputs, wide_scenes
from spherebench.datasets.layouts import (DISTRACTOR_RADII_M, Layout, ball_in_view, ball_partly_out, bookcase,
                                          chair, floor_box, room, table, tripod)
from spherebench.datasets.primitives import Box, Cylinder, SolidSphere, raycast, surface_map
from spherebench.datasets.scene import Ball, Scene
from spherebench.datasets.sensor import D435Sensor, SensorRanges, apply_sensor, check_setting, draw_sensor
from spherebench.datasets.stereo import StereoSensor, check_stereo, check_stereo_ranges, draw_stereo, stereo_depth
from spherebench.errors import SphereBenchError
from spherebench.parallel import pool_size, process_pool, usable_cpus
from spherebench.progress import bar as progress_bar

BASKETBALL_RADIUS_M = 0.12
RESOLUTIONS = {"424x240": (424, 240), "848x480": (848, 480), "1280x720": (1280, 720)}
HARD_FAMILIES = ("distractor", "negative", "cylinder", "occluded", "out_of_frame", "far", "two")
#: Enters the seed of a scene's sensor draws beside the scene seed (a stream apart from the scene's).
SENSOR_STREAM = 0x5E4502
#: The stream a preset's hole draws come from (``Preset.holes``): apart from the layout's and the
#: sensor's, so that a scene left whole is the scene it was before the preset had holes.
HOLE_STREAM = 0x401E
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


def _assign(shares: tuple[tuple[str, float], ...], n: int) -> list[str]:
    """Deterministic split of n items by shares, in blocks (largest remainder)."""
    raw = [s * n for _, s in shares]
    counts = [int(math.floor(x)) for x in raw]
    for k in sorted(range(len(raw)), key=lambda k: counts[k] - raw[k])[: n - sum(counts)]:
        counts[k] += 1
    return [name for (name, _), c in zip(shares, counts) for _ in range(c)]


# --------------------------------------------------------------------------- scene families

def _ball_support(rng, layout: Layout, centre: np.ndarray, radius: float, how: str) -> None:
    if how == "tripod":
        tripod(rng, layout, centre, radius)
    elif how == "table":
        table(rng, layout, centre[0] + rng.uniform(-0.1, 0.1), centre[2] + rng.uniform(-0.1, 0.1),
              layout.floor_y_m - (centre[1] + radius))


def _place_floor_for(rng, centre: np.ndarray, radius: float, how: str) -> float:
    """Floor height (camera height, m) that suits how the ball is held."""
    bottom = centre[1] + radius
    if how == "floor":
        return bottom
    if how == "table":
        return bottom + rng.uniform(0.45, 0.9)
    return max(bottom + rng.uniform(0.3, 1.0), 0.6)  # tripod or held in the air


def family_clean(rng, intr: Intrinsics, radius: float) -> Layout:
    """Flat wall behind, floor, one unoccluded ball 0.25-3 m away (to its nearest surface)."""
    centre = ball_in_view(rng, intr, radius, (0.25, 3.0))
    how = "floor" if rng.random() < 0.25 else "air"
    layout = Layout(floor_y_m=_place_floor_for(rng, centre, radius, how))
    room(rng, layout, wall_z_m=centre[2] + radius + rng.uniform(0.15, 2.0))
    layout.add(SolidSphere(centre, radius), "target")
    return layout


def _clutter_room(rng, intr: Intrinsics, layout: Layout, keep_clear: list[np.ndarray], wall_z: float) -> None:
    """Bookcase against the wall, boxes and furniture on the floor, away from ``keep_clear``."""
    room(rng, layout, wall_z)
    bookcase(rng, layout, rng.uniform(-0.8, 0.8) * wall_z * 0.5, wall_z - 0.01)
    for _ in range(int(rng.integers(2, 6))):
        z = rng.uniform(0.8, wall_z - 0.3)
        x = rng.uniform(-0.9, 0.9) * z * intr.width / (2 * intr.fx)
        if all(math.hypot(x - c[0], z - c[2]) > 0.55 for c in keep_clear):
            (chair if rng.random() < 0.3 else floor_box)(rng, layout, x, z)


def family_cluttered(rng, intr: Intrinsics, radius: float) -> Layout:
    """A bookcase with objects at several depths, the ball on a tripod or a table, boxes, furniture."""
    centre = ball_in_view(rng, intr, radius, (0.4, 3.0))
    how = "tripod" if rng.random() < 0.5 else "table"
    layout = Layout(floor_y_m=_place_floor_for(rng, centre, radius, how))
    wall_z = max(centre[2] + radius + rng.uniform(0.5, 2.0), 2.0)
    _clutter_room(rng, intr, layout, [centre], wall_z)
    _ball_support(rng, layout, centre, radius, how)
    layout.add(SolidSphere(centre, radius), "target")
    return layout


def family_paper(name: str, intr: Intrinsics, radius: float) -> Layout:
    """The paper's experiments E1-E3 (fixed scenes; their own fixed seeds for the clutter)."""
    rng = np.random.default_rng({"E1": 101, "E2": 102, "E3": 103}[name])
    if name == "E1":  # ball 25 cm in front of the camera (to its surface), flat wall behind
        centre = np.array([0.02, 0.01, 0.25 + radius])
        layout = Layout(floor_y_m=0.9)
        room(rng, layout, wall_z_m=0.85)
    elif name == "E2":  # bookcase ~2 m away, brown ball on a tripod before it
        centre = np.array([-0.05, 0.05, 1.5])
        layout = Layout(floor_y_m=1.1)
        room(rng, layout, 2.2)
        bookcase(rng, layout, 0.0, 2.19)
        tripod(rng, layout, centre, radius)
    else:  # E3: the ball farther away, on a table, several depth levels
        centre = np.array([0.25, 0.2, 2.4])
        layout = Layout(floor_y_m=0.2 + radius + 0.75)
        room(rng, layout, 3.6)
        bookcase(rng, layout, -0.7, 3.59)
        table(rng, layout, 0.3, 2.45, 0.75, (1.0, 0.6))
        floor_box(rng, layout, -0.6, 1.4)
        chair(rng, layout, 0.9, 1.8)
        floor_box(rng, layout, 0.5, 3.0)
    layout.add(SolidSphere(centre, radius), "target")
    return layout


def _distractor_ball(rng, intr, layout: Layout, dist=(0.5, 2.5)) -> np.ndarray:
    r = float(rng.choice(DISTRACTOR_RADII_M))
    c = ball_in_view(rng, intr, r, dist)
    layout.add(SolidSphere(c, r), "distractor")
    return c


def family_hard(family: str, rng, intr: Intrinsics, radius: float) -> Layout:
    """The hard preset's families (HARD_FAMILIES)."""
    n_targets = {"negative": 0, "two": 2}.get(family, 1)
    if family == "far":
        centres = [ball_in_view(rng, intr, radius, (3.0, 5.0))]
    elif family == "out_of_frame":
        centres = [ball_partly_out(rng, intr, radius, (0.5, 2.5))]
    else:
        centres = [ball_in_view(rng, intr, radius, (0.4, 2.5)) for _ in range(n_targets)]
    how = "tripod" if rng.random() < 0.5 else "air"
    bottom = max([c[1] + radius for c in centres], default=0.0)
    layout = Layout(floor_y_m=max(bottom + rng.uniform(0.3, 1.0), 0.8))
    far_z = max([c[2] for c in centres], default=2.0)
    wall_z = far_z + radius + rng.uniform(0.4, 2.0)
    _clutter_room(rng, intr, layout, centres, max(wall_z, 2.0))
    for c in centres:
        _ball_support(rng, layout, c, radius, how)
        layout.add(SolidSphere(c, radius), "target")
    if family in ("distractor", "negative"):
        for _ in range(int(rng.integers(1, 3))):
            _distractor_ball(rng, intr, layout)
    if family in ("cylinder", "negative"):
        for _ in range(int(rng.integers(1, 3))):  # bins and poles of the ball's radius, standing on the floor
            z = rng.uniform(0.8, 3.0)
            x = rng.uniform(-0.8, 0.8) * z * intr.width / (2 * intr.fx)
            layout.add(Cylinder(np.array([x, layout.floor_y_m, z]), np.array([0.0, -1.0, 0.0]), radius,
                                rng.uniform(0.3, 1.5)), "cylinder")
    return layout


def _occlude(rng, intr: Intrinsics, layout: Layout, centre: np.ndarray, radius: float) -> None:
    """A box between the camera and the ball, slid sideways to cover part of it."""
    z = rng.uniform(0.35, 0.8) * (centre[2] - radius)
    half = np.array([rng.uniform(0.1, 0.3), rng.uniform(0.2, 0.5), 0.05]) * max(z, 0.3)
    side = rng.choice([-1.0, 1.0])
    scale = z / centre[2]
    # shift so that the box edge crosses the ball's image at a random fraction of its width
    cover = rng.uniform(0.3, 0.7)
    edge_x = (centre[0] + side * radius * (1 - 2 * cover)) * scale
    layout.add(Box(np.array([edge_x + side * half[0], centre[1] * scale, z]), half), "clutter")


# --------------------------------------------------------------------------- rendering

def _full_silhouette_px(intr: Intrinsics, centre: np.ndarray, radius: float, in_frame: np.ndarray) -> int:
    """Pixels of the whole silhouette, counting the part outside the frame (bigger canvas)."""
    circ = sphere_circle_amodal(intr, centre, radius)
    if circ is not None and circ[0] - circ[2] > 1 and circ[0] + circ[2] < intr.width - 2 \
            and circ[1] - circ[2] > 1 and circ[1] + circ[2] < intr.height - 2:
        return int(in_frame.sum())
    big = Intrinsics(width=3 * intr.width, height=3 * intr.height, ppx=intr.ppx + intr.width,
                     ppy=intr.ppy + intr.height, fx=intr.fx, fy=intr.fy, model=intr.model, coeffs=intr.coeffs)
    return int(sphere_silhouette_mask(big, centre, radius).sum())


# --------------------------------------------------------------------------- families

@dataclass(frozen=True)
class Family:
    """A scene family of a grammar: ``build(rng, intr, radius_m) -> Layout`` and ``accept(visible
    fractions of its balls) -> bool``, the rule a drawn layout must meet (else it is drawn again).
    fixed: one named scene (the paper's experiments): its layout stands as built and its scene id
    is the family's name."""

    build: Callable
    accept: Callable[[list[float]], bool]
    fixed: bool = False


#: (grammar, family name) -> Family.
FAMILIES: dict[tuple[str, str], Family] = {}


def register_family(grammar: str, name: str, accept: Callable[[list[float]], bool], fixed: bool = False):
    """A decorator: enter the layout builder it wraps as family ``name`` of ``grammar``."""
    def enter(build: Callable) -> Callable:
        if (grammar, name) in FAMILIES:
            raise ValueError(f"family {name} of the {grammar} grammar is registered already")
        FAMILIES[(grammar, name)] = Family(build, accept, fixed)
        return build
    return enter


def _in_full_view(vis: list[float]) -> bool:
    return all(v >= 0.85 for v in vis)  # a tripod cup or table may hide the ball's lowest rim


register_family("classic", "clean", _in_full_view)(family_clean)
register_family("classic", "cluttered", _in_full_view)(family_cluttered)
for _name in ("E1", "E2", "E3"):
    register_family("classic", _name, lambda vis: True, fixed=True)(
        lambda rng, intr, radius, _name=_name: family_paper(_name, intr, radius))
for _name in HARD_FAMILIES:
    if _name not in ("occluded", "out_of_frame"):
        register_family("classic", _name, _in_full_view)(partial(family_hard, _name))


@register_family("classic", "occluded", lambda vis: 0.4 <= vis[0] <= 0.7)  # 30-60 % hidden
def family_occluded(rng, intr: Intrinsics, radius: float) -> Layout:
    layout = family_hard("occluded", rng, intr, radius)
    _occlude(rng, intr, layout, np.asarray(layout.targets[0].centre_m), radius)
    return layout


@dataclass(frozen=True)
class Hole:
    """Missing depth over part of a ball's face: the ``fraction`` of its valid pixels nearest the
    hole's centre, the image of the ball's specular point shifted by ``offset`` (ball image radii,
    (du, dv)), nearness measured along an edge that wobbles by ``wobble`` (the relative amplitudes
    and phases of its 2nd and 3rd angular harmonics: a slightly irregular blob)."""

    fraction: float
    offset: tuple[float, float]
    wobble: tuple[float, float, float, float]


#: The share of a holed ball's valid pixels its hole takes, and the most its centre is shifted
#: from the specular point (ball image radii).
HOLE_FRACTION = (0.3, 0.7)
HOLE_JITTER = 0.3


def draw_hole(rng: np.random.Generator) -> Hole:
    """A hole of HOLE_FRACTION, shifted by up to HOLE_JITTER, less where a disc of its area so
    shifted would reach within 5 % of the rim: a ring of valid depth stays around it."""
    fraction = float(rng.uniform(*HOLE_FRACTION))
    wobble = (float(rng.uniform(0.0, 0.1)), float(rng.uniform(0.0, 2 * math.pi)),
              float(rng.uniform(0.0, 0.06)), float(rng.uniform(0.0, 2 * math.pi)))
    reach = min(HOLE_JITTER, max(0.0, 0.95 - math.sqrt(fraction) * (1.0 + wobble[0] + wobble[2])))
    rho, phi = reach * math.sqrt(rng.uniform()), rng.uniform(0.0, 2 * math.pi)
    return Hole(fraction, (rho * math.cos(phi), rho * math.sin(phi)), wobble)


def punch_hole(depth: np.ndarray, mask: np.ndarray, intr: Intrinsics, centre: np.ndarray, radius: float,
               hole: Hole) -> float:
    """Set the hole's pixels of ``mask`` (the ball's valid pixels) to 0 in ``depth`` (in place);
    returns the fraction of them it took, measured on the depth (1 - valid after / valid before)."""
    before = int(mask.sum())
    circle = sphere_circle_amodal(intr, centre, radius)
    if before == 0 or circle is None:
        return 0.0
    specular = project(intr, centre * (1.0 - radius / float(np.linalg.norm(centre))))[0]
    hx, hy = specular + np.asarray(hole.offset) * circle[2]
    vs, us = np.nonzero(mask)
    dx, dy = us - hx, vs - hy
    theta = np.arctan2(dy, dx)
    a2, p2, a3, p3 = hole.wobble
    nearness = np.hypot(dx, dy) / (1.0 + a2 * np.cos(2 * theta + p2) + a3 * np.cos(3 * theta + p3))
    taken = np.argsort(nearness, kind="stable")[: int(round(hole.fraction * before))]
    depth[vs[taken], us[taken]] = 0
    return 1.0 - int((mask & (depth > 0)).sum()) / before


@register_family("classic", "holed", _in_full_view)
def family_holed(rng, intr: Intrinsics, radius: float) -> Layout:
    """A ball 0.7-4 m away in clear view, in a bare room or a cluttered one, with a Hole."""
    centre = ball_in_view(rng, intr, radius, (0.7, 4.0))
    cluttered = rng.random() < 0.5
    how = ("tripod" if rng.random() < 0.5 else "table") if cluttered else ("floor" if rng.random() < 0.25 else "air")
    layout = Layout(floor_y_m=_place_floor_for(rng, centre, radius, how))
    wall_z = centre[2] + radius + rng.uniform(0.5, 2.0)
    if cluttered:
        _clutter_room(rng, intr, layout, [centre], max(wall_z, 2.0))
    else:
        room(rng, layout, wall_z)
    _ball_support(rng, layout, centre, radius, how)
    layout.add(SolidSphere(centre, radius), "target").hole = draw_hole(rng)
    return layout


register_family("classic", "out_of_frame", lambda vis: 0.3 <= vis[0] <= 0.85)(partial(family_hard, "out_of_frame"))
for _name, _share in wide_scenes.SHARES:  # furniture beside it and a pitched view may hide some of it
    register_family("wide", _name, lambda vis: all(v >= 0.5 for v in vis))(wide_scenes.FAMILIES[_name])


def render(layout: Layout, intr: Intrinsics, sensor: D435Sensor | StereoSensor, rng: np.random.Generator,
           rays: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, list[Ball]]:
    """Ray-cast a layout and apply the sensor (either model): depth (H, W) uint16, true z (H, W) m,
    target balls."""
    if rays is None:
        rays = image_rays(intr)
    shapes = [it.shape for it in layout.items]
    z_true, label = raycast(shapes, rays, intr)
    if isinstance(sensor, StereoSensor):
        depth = stereo_depth(layout, intr, sensor, rng, rays)  # the items' own albedos and textures
    else:
        surfaces = None
        if sensor.dropouts:  # planar surfaces may be low-texture, the balls only if asked
            balls_too = tuple(k for k, it in enumerate(layout.items) if it.kind == "target") if sensor.dropout_ball else ()
            surfaces = surface_map(shapes, label, z_true, rays, intr, balls_too)
        depth = apply_sensor(z_true, intr, sensor, rng, surfaces)
    balls = []
    for k, item in enumerate(layout.items):
        if item.kind != "target":
            continue
        c, r = np.asarray(item.shape.centre_m, float), float(item.shape.radius_m)
        silhouette = sphere_silhouette_mask(intr, c, r)
        mask = (label == k + 1) & (depth > 0)
        full = _full_silhouette_px(intr, c, r, silhouette)
        balls.append(Ball(radius_m=r, mask=mask, silhouette=silhouette, centre_m=tuple(float(x) for x in c),
                          amodal_circle_px=sphere_circle_amodal(intr, c, r),
                          visible_fraction=float(mask.sum()) / full if full else 0.0))
    return depth, z_true, balls


def scene_sensor(preset_name: str, seed: int, index: int, sensor: D435Sensor = D435Sensor(),
                 overrides: Mapping | None = None) -> tuple[D435Sensor, dict | None]:
    """The sensor of one scene and its grid cell ({"cell": k, axis: level, ...} or None).

    ``sensor`` with the preset's values applied, then the scene's grid cell's, then ``overrides``
    (parameter -> value or (lo, hi)); ranges are drawn from the scene seed's own sensor stream."""
    preset = PRESETS[preset_name]
    spec = preset.sensor or SensorRanges()
    settings = dict(spec.values)
    cell = spec.cell(index)
    if cell is not None:
        settings.update(cell[2])
    settings.update(overrides or {})
    if not settings:
        return sensor, None
    rng = np.random.default_rng([generation_seed(preset, seed, index), SENSOR_STREAM])
    return draw_sensor(sensor, settings, rng), None if cell is None else {"cell": cell[0], **cell[1]}


def scene_stereo(preset_name: str, seed: int, index: int, sensor: StereoSensor = StereoSensor()) -> StereoSensor:
    """The stereo sensor of one scene: ``sensor`` with the preset's stereo ranges drawn from the
    scene seed's sensor stream (``sensor`` itself where the preset draws none)."""
    preset = PRESETS[preset_name]
    if not preset.stereo:
        return sensor
    rng = np.random.default_rng([generation_seed(preset, seed, index), SENSOR_STREAM])
    return draw_stereo(sensor, preset.stereo, rng)


def _overlay_holes(preset: Preset, family: str, scene_seed: int, layout: Layout) -> None:
    """Give every ball of the layout a Hole (drawn from HOLE_STREAM) in the preset's share of its
    family's scenes (``Preset.holes``); a ball that has one keeps it."""
    share = dict(preset.holes).get(family, 0.0)
    if share <= 0.0:
        return
    rng = np.random.default_rng([scene_seed, HOLE_STREAM])
    if rng.random() >= share:
        return
    for item in layout.items:
        if item.kind == "target" and item.hole is None:
            item.hole = draw_hole(rng)


def simulate_scene(preset_name: str, index: int, family: str, seed: int, resolution: str,
                   radius_m: float = BASKETBALL_RADIUS_M, sensor: D435Sensor = D435Sensor(),
                   sensor_overrides: Mapping | None = None) -> Scene:
    """One scene of a preset, fully determined by its arguments (``scene_sensor`` for the analytic
    sensor; a StereoSensor with the preset's per-scene stereo draws, ``scene_stereo``)."""
    preset = PRESETS[preset_name]
    s = generation_seed(preset, seed, index)
    rng = np.random.default_rng(s)
    if isinstance(sensor, StereoSensor):
        varied, cell = True, None
        sensor = scene_stereo(preset_name, seed, index, sensor)
    else:
        varied = preset.sensor is not None or bool(sensor_overrides) or sensor != D435Sensor()
        sensor, cell = scene_sensor(preset_name, seed, index, sensor, sensor_overrides)
    w, h = RESOLUTIONS[resolution]
    intr = Intrinsics.d435(w, h)
    intr = Intrinsics(**{**intr.to_dict(), "depth_scale": sensor.depth_scale_m})
    rays = image_rays(intr)
    kind = FAMILIES[(preset.grammar, family)]
    for _attempt in range(40):
        layout = kind.build(rng, intr, radius_m)
        depth, _z, balls = render(layout, intr, sensor, rng, rays)
        if kind.fixed or kind.accept([b.visible_fraction for b in balls]):
            break
    else:
        raise RuntimeError(f"{preset_name} scene {index} ({family}): no layout met the visibility rule")
    _overlay_holes(preset, family, s, layout)
    holes = [it.hole for it in layout.items if it.kind == "target"]
    hole_fraction = [None if hole is None else punch_hole(depth, b.mask, intr, np.asarray(b.centre_m), b.radius_m, hole)
                     for b, hole in zip(balls, holes)]
    distractors = [{"kind": it.kind, "center_m": [float(x) for x in it.shape.centre_m],
                    "radius_m": float(it.shape.radius_m)} for it in layout.items if it.kind == "distractor"]
    cylinders = [{"base_m": [float(x) for x in it.shape.base_m], "radius_m": float(it.shape.radius_m),
                  "height_m": float(it.shape.height_m)} for it in layout.items if it.kind == "cylinder"]
    scene_id = family if kind.fixed else f"{family}_{index:04d}"
    meta = {"preset": preset_name, "index": index, "resolution": resolution,
            "distractors": distractors, "cylinders": cylinders}
    if varied:  # a nominal-sensor dataset's scenes read as before; dataset.json holds its sensor
        meta["sensor"] = sensor.to_dict()
    if isinstance(sensor, StereoSensor):
        meta["sensor_model"] = "stereo"
    if cell is not None:
        meta["sensor_cell"] = cell
    if any(f is not None for f in hole_fraction):  # the scenes of the other families read as before
        meta["hole_fraction"] = hole_fraction
    meta.update(layout.meta)  # the grammar's record: the camera's pose, the support
    return Scene(scene_id=scene_id, family=family, intrinsics=intr, depth=depth, balls=balls, seed=s, meta=meta)


# --------------------------------------------------------------------------- datasets

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
    families = _assign(preset.families, n)
    if preset.sensor is not None and preset.sensor.grid:
        # by shares within each (grid cell, family), so that every cell has the same mix
        groups: dict[tuple[int, str], list[int]] = {}
        for i, f in enumerate(families):
            groups.setdefault((i % preset.sensor.n_cells, f), []).append(i)
        resolutions = [""] * n
        for members in groups.values():
            for i, r in zip(members, _assign(preset.resolutions, len(members))):
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
                     sensor_overrides: Mapping | None = None, sensor_model: str | None = None) -> Path:
    """Build a preset into ``out_dir`` (replaced atomically when complete); returns the path. A variant
    preset builds its base's scenes with its sensor settings (``resolve_preset``), recorded as its base.

    sensor: the base analytic sensor (the preset's sensor values, grid cells and ``sensor_overrides``,
    parameter -> value or (lo, hi), apply over it; see ``scene_sensor``).
    sensor_model: a name of SENSOR_MODELS (default: the preset's); ``stereo`` renders every scene
    through ``StereoSensor()`` with the preset's stereo draws (the analytic sensor's settings and
    ranges do not apply to it, and are refused). A stereo preset takes no other model.
    clouds: write each scene's cloud.ply (default: the preset's: yes, except for the training
    splits, whose 2D consumers read image.png only: 2,000 clouds would take several GB)."""
    preset_name, overrides = resolve_preset(preset_name, sensor_overrides)
    preset = PRESETS[preset_name]
    if sensor_model is None:
        sensor_model = preset.sensor_model
    if clouds is None:
        clouds = preset.clouds
    inout.check_ball_radius(radius_m)
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
        bar = progress_bar(total=len(tasks), desc=f"generate {preset_name}", unit="scene", enabled=progress)
        processes = pool_size(workers, len(tasks))  # no more than the scenes or the CPUs
        if processes > 1:
            with process_pool(processes) as pool:
                for _ in pool.map(_build_one, tasks, chunksize=4):
                    bar.update()
        else:
            for t in tasks:
                _build_one(t)
                bar.update()
        bar.close()
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
    return out_dir


def default_workers() -> int:
    return min(4, usable_cpus())
