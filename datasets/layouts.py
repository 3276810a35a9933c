"""Scene layouts of the simulator: rooms, furniture, supports, balls, drawn from a seeded RNG.

A layout is a list of ``Item`` (a primitive and what it is). Kinds: "wall", "floor", "furniture",
"clutter", "support" (tripods, tables), "cylinder", "distractor" (a ball of another radius) and
"target" (a ball of the dataset's radius, the object to detect). Frame: camera at the origin,
x right, y down, z forward, metres; the floor is the plane y = camera height.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from spherebench.camera import Intrinsics, pixel_rays
from spherebench.circles import norm3, sphere_circle_amodal
from spherebench.datasets.primitives import Box, Cylinder, Plane, SolidSphere, Texture

#: Radii (m) of the balls the hard preset puts beside the basketball: soccer ball (size 5),
#: two smaller balls and a larger one.
DISTRACTOR_RADII_M = (0.11, 0.09, 0.065, 0.15)


@dataclass
class Item:
    """A primitive and what it is; albedo (infrared, 0-1) and texture set its surface for the
    stereo model (None: the model draws the albedo, untextured); the analytic model ignores both.
    hole: a target ball's missing depth over part of its face (``families.Hole``), applied by
    either sensor model to its depth; None: none."""

    shape: object
    kind: str
    albedo: float | None = None
    texture: Texture | None = None
    hole: object | None = None


@dataclass
class Layout:
    items: list[Item] = field(default_factory=list)
    floor_y_m: float = 1.2
    meta: dict = field(default_factory=dict)  # what a grammar records of the scene (gt.json meta)

    def add(self, shape, kind: str) -> Item:
        item = Item(shape, kind)
        self.items.append(item)
        return item

    @property
    def targets(self) -> list[SolidSphere]:
        return [it.shape for it in self.items if it.kind == "target"]


def _rot_y(angle_rad: float) -> np.ndarray:
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


# --------------------------------------------------------------------------- rooms and furniture

def room(rng: np.random.Generator, layout: Layout, wall_z_m: float) -> None:
    """Floor and a back wall (slightly turned), as the paper's scenes."""
    layout.add(Plane(np.array([0.0, layout.floor_y_m, 0.0]), np.array([0.0, -1.0, 0.0])), "floor")
    yaw = rng.uniform(-0.25, 0.25)
    layout.add(Plane(np.array([0.0, 0.0, wall_z_m]), _rot_y(yaw) @ np.array([0.0, 0.0, -1.0])), "wall")


#: Board thickness of a shelf unit, m.
SHELF_BOARD_M = 0.02


def bookcase(rng: np.random.Generator, layout: Layout, x_m: float, z_back_m: float) -> None:
    """A bookcase standing on the floor, its back at ``z_back_m``: panels, shelves, books, jars."""
    width = rng.uniform(0.8, 1.6)
    height = rng.uniform(1.2, 2.0)
    depth = rng.uniform(0.28, 0.4)
    n_shelves = int(rng.integers(3, 6))
    shelf_unit(rng, layout, x_m, z_back_m, width, height, depth,
               np.linspace(0.0, height - SHELF_BOARD_M, n_shelves + 1))


def shelf_unit(rng: np.random.Generator, layout: Layout, x_m: float, z_back_m: float, width: float, height: float,
               depth: float, levels, clear: tuple[int, float, float] | None = None) -> None:
    """A shelf unit on the floor, its back at ``z_back_m``: back and side panels, boards, books and jars.

    levels: the boards' heights above the floor (m, their bottoms; the top board's: height - board).
    clear: (board index, x0, x1): no book or jar on that board between x0 and x1 (m)."""
    floor = layout.floor_y_m
    zc = z_back_m - depth / 2
    t = SHELF_BOARD_M
    layout.add(Box(np.array([x_m, floor - height / 2, z_back_m - t / 2]), np.array([width / 2, height / 2, t / 2])),
               "furniture")
    for side in (-1, 1):
        layout.add(Box(np.array([x_m + side * (width / 2 - t / 2), floor - height / 2, zc]),
                       np.array([t / 2, height / 2, depth / 2])), "furniture")
    for k, level in enumerate(levels):
        y = floor - level - t / 2
        layout.add(Box(np.array([x_m, y, zc]), np.array([width / 2, t / 2, depth / 2])), "furniture")
        if k == len(levels) - 1:
            break
        gap = levels[k + 1] - level - t
        u = x_m - width / 2 + t
        while u < x_m + width / 2 - t - 0.03:  # books and jars along the shelf, at several depths
            if rng.random() < 0.15:
                u += rng.uniform(0.05, 0.2)
                continue
            if rng.random() < 0.8:
                bw = rng.uniform(0.02, 0.06)
                bh = min(gap * rng.uniform(0.55, 0.95), gap - 0.005)
                bd = rng.uniform(0.15, depth - 0.02)
                front = z_back_m - t - bd / 2 - rng.uniform(0.0, depth - bd - t)
                if clear is not None and clear[0] == k and u < clear[2] and u + bw > clear[1]:
                    u = clear[2]
                    continue
                layout.add(Box(np.array([u + bw / 2, y - t / 2 - bh / 2, front]), np.array([bw / 2, bh / 2, bd / 2])),
                           "clutter")
                u += bw + 0.002
            else:
                r = rng.uniform(0.03, 0.07)
                hh = min(gap * rng.uniform(0.4, 0.9), gap - 0.005)
                if clear is not None and clear[0] == k and u < clear[2] and u + 2 * r > clear[1]:
                    u = clear[2]
                    continue
                layout.add(Cylinder(np.array([u + r, y - t / 2, zc + rng.uniform(-0.05, 0.05)]),
                                    np.array([0.0, -1.0, 0.0]), r, hh), "clutter")
                u += 2 * r + 0.01


def floor_box(rng: np.random.Generator, layout: Layout, x_m: float, z_m: float, size_m=(0.2, 0.6)) -> None:
    """A box resting on the floor (its corners are a trap for sphere fits)."""
    half = rng.uniform(*size_m, size=3) / 2
    box_on_floor(layout, x_m, z_m, half, _rot_y(rng.uniform(0, math.pi / 2)))


def box_on_floor(layout: Layout, x_m: float, z_m: float, half_m: np.ndarray, rot: np.ndarray,
                 kind: str = "clutter") -> Item:
    """A box of half sizes ``half_m`` resting on the floor at (x, z), turned by ``rot``."""
    return layout.add(Box(np.array([x_m, layout.floor_y_m - half_m[1], z_m]), half_m, rot), kind)


def chair(rng: np.random.Generator, layout: Layout, x_m: float, z_m: float) -> None:
    seat_h, w = rng.uniform(0.42, 0.5), rng.uniform(0.4, 0.5)
    chair_at(layout, x_m, z_m, seat_h, w, _rot_y(rng.uniform(-0.6, 0.6)))


#: Half thickness of a chair's seat, m (its top is this above the seat height given to ``chair_at``).
SEAT_HALF_M = 0.02


def chair_at(layout: Layout, x_m: float, z_m: float, seat_h: float, w: float, rot: np.ndarray) -> None:
    """A chair of seat width ``w`` whose seat's mid-plane is ``seat_h`` above the floor at (x, z),
    its back on its local +z side, turned by ``rot``."""
    floor = layout.floor_y_m
    centre = np.array([x_m, floor - seat_h, z_m])
    layout.add(Box(centre, np.array([w / 2, SEAT_HALF_M, w / 2]), rot), "furniture")
    layout.add(Box(centre + rot @ np.array([0.0, -0.22, w / 2]), np.array([w / 2, 0.22, 0.015]), rot), "furniture")
    for sx in (-1, 1):
        for sz in (-1, 1):
            foot = centre + rot @ np.array([sx * (w / 2 - 0.03), 0.0, sz * (w / 2 - 0.03)])
            layout.add(Cylinder(np.array([foot[0], floor, foot[2]]), np.array([0.0, -1.0, 0.0]), 0.015, seat_h - 0.02),
                       "furniture")


def table(rng: np.random.Generator, layout: Layout, x_m: float, z_m: float, top_height_m: float,
          size_m: tuple[float, float] | None = None) -> None:
    """A table whose top surface is ``top_height_m`` above the floor, centred at (x, z)."""
    floor = layout.floor_y_m
    w, d = size_m if size_m is not None else (rng.uniform(0.6, 1.2), rng.uniform(0.5, 0.8))
    t = 0.03
    layout.add(Box(np.array([x_m, floor - top_height_m + t / 2, z_m]), np.array([w / 2, t / 2, d / 2])), "support")
    for sx in (-1, 1):
        for sz in (-1, 1):
            layout.add(Cylinder(np.array([x_m + sx * (w / 2 - 0.04), floor, z_m + sz * (d / 2 - 0.04)]),
                                np.array([0.0, -1.0, 0.0]), 0.02, top_height_m - t), "support")


def tripod(rng: np.random.Generator, layout: Layout, ball_centre_m: np.ndarray, ball_radius_m: float) -> None:
    """A tripod from the floor to just under the ball, with a small cup that the ball sits in."""
    floor = layout.floor_y_m
    bottom = ball_centre_m + np.array([0.0, ball_radius_m * 0.92, 0.0])  # cup rim a little up the ball
    cup_r = 0.045
    layout.add(Cylinder(bottom + np.array([0.0, 0.05, 0.0]), np.array([0.0, -1.0, 0.0]), cup_r, 0.05), "support")
    head = bottom + np.array([0.0, 0.05, 0.0])
    layout.add(Cylinder(head + np.array([0.0, 0.25, 0.0]), np.array([0.0, -1.0, 0.0]), 0.015, 0.25), "support")
    spread = rng.uniform(0.25, 0.4)
    phase = rng.uniform(0, 2 * math.pi)
    top = head + np.array([0.0, 0.25, 0.0])
    for k in range(3):
        a = phase + 2 * math.pi * k / 3
        foot = np.array([top[0] + spread * math.cos(a), floor, top[2] + spread * math.sin(a)])
        axis = top - foot
        length = norm3(axis)
        if length > 0.05:
            layout.add(Cylinder(foot, axis / length, 0.012, length), "support")


# --------------------------------------------------------------------------- balls in view

def ball_in_view(rng: np.random.Generator, intr: Intrinsics, radius_m: float, dist_m: tuple[float, float],
                 margin_px: float = 3.0, inside: bool = True, tries: int = 200) -> np.ndarray:
    """A ball centre whose nearest surface is ``dist_m`` away (uniform in the range), seen at a
    random image position; wholly inside the image (``inside``) by ``margin_px``."""
    for _ in range(tries):
        d = rng.uniform(*dist_m)
        u, v = rng.uniform(0, intr.width), rng.uniform(0, intr.height)
        ray = pixel_rays(intr, np.array([u]), np.array([v]))[0]
        centre = ray / norm3(ray) * (d + radius_m)
        if not inside:
            return centre
        circ = sphere_circle_amodal(intr, centre, radius_m)
        if circ is None:
            continue
        cx, cy, r = circ
        if margin_px <= cx - r and cx + r <= intr.width - 1 - margin_px and margin_px <= cy - r \
                and cy + r <= intr.height - 1 - margin_px:
            return centre
    raise RuntimeError(f"no in-view position for a {radius_m} m ball at {dist_m} m after {tries} tries")


def ball_partly_out(rng: np.random.Generator, intr: Intrinsics, radius_m: float, dist_m: tuple[float, float],
                    out_fraction: tuple[float, float] = (0.2, 0.5)) -> np.ndarray:
    """A ball centre whose amodal circle sticks out of one image border by the given fraction
    of its diameter."""
    d = rng.uniform(*dist_m)
    side = int(rng.integers(4))
    frac = rng.uniform(*out_fraction)
    # first place it centred, to know its image radius at that depth, then slide it to the border
    centre = np.array([0.0, 0.0, d + radius_m])
    r_px = sphere_circle_amodal(intr, centre, radius_m)[2]
    offset = r_px * (1 - 2 * frac)  # centre this far inside the border
    if side == 0:
        u, v = -0.5 + offset, rng.uniform(r_px, intr.height - r_px)
    elif side == 1:
        u, v = intr.width - 0.5 - offset, rng.uniform(r_px, intr.height - r_px)
    elif side == 2:
        u, v = rng.uniform(r_px, intr.width - r_px), -0.5 + offset
    else:
        u, v = rng.uniform(r_px, intr.width - r_px), intr.height - 0.5 - offset
    ray = pixel_rays(intr, np.array([u]), np.array([v]))[0]
    return ray / norm3(ray) * (d + radius_m)
