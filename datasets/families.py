"""The simulator's scene families: layout builders of a grammar, each with the visibility rule its
drawn layouts must meet, registered here (``register_family``), so that a new family is one entry,
not a branch of the rendering.

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
from dataclasses import dataclass
from functools import partial
from typing import Callable

import numpy as np

from spherebench.camera import Intrinsics, project
from spherebench.circles import sphere_circle_amodal
from spherebench.datasets import wide_scenes
from spherebench.datasets.layouts import (DISTRACTOR_RADII_M, Layout, ball_in_view, ball_partly_out, bookcase,
                                          chair, floor_box, room, table, tripod)
from spherebench.datasets.primitives import Box, Cylinder, SolidSphere

HARD_FAMILIES = ("distractor", "negative", "cylinder", "occluded", "out_of_frame", "far", "two")


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
