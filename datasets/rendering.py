"""The simulator's rendering: a scene is a layout (``layouts``, drawn by its family) ray-cast
through the camera (``primitives``), passed through a sensor model (the analytic ``sensor`` or
the rendered infrared pair matched by ``stereo``), with the ground truth of every ball of the
dataset's radius: its 3D centre, its visible mask (the ball is the first surface hit and the depth
is valid), its full silhouette, and their circles (``spherebench.circles``).

``simulate_scene`` builds one scene of a preset from its arguments alone: its seed
(``presets.generation_seed``) draws the layout, and streams of that seed of their own draw the
scene's sensor (``SENSOR_STREAM``) and a preset's holes (``HOLE_STREAM``).
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from spherebench.camera import Intrinsics, image_rays
from spherebench.circles import sphere_circle_amodal, sphere_silhouette_mask
from spherebench.datasets.families import FAMILIES, draw_hole, punch_hole
from spherebench.datasets.layouts import Layout
from spherebench.datasets.presets import BASKETBALL_RADIUS_M, PRESETS, RESOLUTIONS, Preset, generation_seed
from spherebench.datasets.primitives import raycast, surface_map
from spherebench.datasets.scene import Ball, Scene
from spherebench.datasets.sensor import D435Sensor, SensorRanges, apply_sensor, draw_sensor
from spherebench.datasets.stereo import StereoSensor, draw_stereo, stereo_depth

#: Enters the seed of a scene's sensor draws beside the scene seed (a stream apart from the scene's).
SENSOR_STREAM = 0x5E4502
#: The stream a preset's hole draws come from (``Preset.holes``): apart from the layout's and the
#: sensor's, so that a scene left whole is the scene it was before the preset had holes.
HOLE_STREAM = 0x401E


def _full_silhouette_px(intr: Intrinsics, centre: np.ndarray, radius: float, in_frame: np.ndarray) -> int:
    """Pixels of the whole silhouette, counting the part outside the frame (bigger canvas)."""
    circ = sphere_circle_amodal(intr, centre, radius)
    if circ is not None and circ[0] - circ[2] > 1 and circ[0] + circ[2] < intr.width - 2 \
            and circ[1] - circ[2] > 1 and circ[1] + circ[2] < intr.height - 2:
        return int(in_frame.sum())
    big = Intrinsics(width=3 * intr.width, height=3 * intr.height, ppx=intr.ppx + intr.width,
                     ppy=intr.ppy + intr.height, fx=intr.fx, fy=intr.fy, model=intr.model, coeffs=intr.coeffs)
    return int(sphere_silhouette_mask(big, centre, radius).sum())


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
