"""The wide scene grammar: pitched and rolled cameras in rooms, the ball on every kind of support.

Each family ``FAMILIES[name](rng, intr, radius_m) -> Layout`` puts the ball on one support: a
tripod, a shelf of a shelf unit, a table, a chair's seat, a box, the floor, or the floor against
the back wall; "negative" builds the same scenes with no ball of the dataset's radius (the support
holds a distractor ball or nothing). The ball is drawn in view in the camera frame (0.4-4 m to its
surface), the camera's pitch (-35 to +15 deg, up positive), roll (+-10 deg) and the room's yaw
(+-0.6 rad) turn it into the room frame, and the support's height under it gives the camera's
height (redrawn unless 0.3-2 m). The room, built in its own level frame (floor y = camera height,
back wall z = const), is then turned into the camera frame: ``Layout.floor_y_m`` is the camera
height, not the floor's y there. Rooms: the floor, a back wall 1.5-6 m away, in half the scenes a
side wall; furniture (chairs, boxes, tables, shelf units), one item a ball's diameter or less from
the ball in most scenes; distractor balls beside it in half the scenes; surfaces of low albedo or
textured for the stereo model. ``Layout.meta`` records the pose and the support.
"""

from __future__ import annotations

import math
from functools import partial

import numpy as np

from spherebench.camera import Intrinsics, pixel_rays, project
from spherebench.datasets.layouts import (SEAT_HALF_M, SHELF_BOARD_M, Item, Layout, _rot_y, bookcase, box_on_floor,
                                          chair_at, shelf_unit, table, tripod, ball_in_view)
from spherebench.datasets.primitives import TEXTURE_PATTERNS, Box, Plane, SolidSphere, Texture, pixel_box, rotated

PITCH_DEG = (-35.0, 15.0)
ROLL_DEG = (-10.0, 10.0)
HEIGHT_M = (0.3, 2.0)
BACK_WALL_M = (1.5, 6.0)
ROOM_YAW_RAD = (-0.6, 0.6)
BALL_DISTANCE_M = (0.4, 4.0)          # camera to the ball's nearest surface
NEAR_GAP_M = (0.02, 0.2)              # the near item's gap to the ball: under a ball's diameter (0.24 m)
NEAR_SHARE = 0.85                     # scenes with a near item placed beside the ball
DISTRACTOR_RADII_M = ((0.10, 0.11), (0.13, 0.15))
DISTRACTOR_SHARE = 0.5
LOW_ALBEDO = (0.05, 0.2)
TEXTURE_SCALE_M = (0.01, 0.10)
TEXTURE_CONTRAST = (0.3, 0.8)
#: (low-albedo, textured) shares of a surface: walls and floor, other items, the ball.
SURFACE_SHARES = {"room": (0.15, 0.5), "item": (0.2, 0.25), "target": (0.1, 0.0)}
#: A ball must show at least this fraction of its silhouette to the ray caster (before the sensor).
MIN_VISIBLE = 0.6
SUPPORTS = ("tripod", "shelf", "table", "chair", "box", "floor", "wall")
SHARES = (("tripod", 0.13), ("shelf", 0.13), ("table", 0.13), ("chair", 0.12), ("box", 0.12),
          ("floor", 0.13), ("wall", 0.12), ("negative", 0.12))
_TRIES = 200


def _rot_x(angle_rad: float) -> np.ndarray:
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def _rot_z(angle_rad: float) -> np.ndarray:
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


# --------------------------------------------------------------------------- floor footprints
# A footprint is an oriented rectangle on the floor, (x, z, half x, half z, yaw) in the room frame.

def _rect(fp) -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray]]:
    x, z, hx, hz, yaw = fp
    ax, az = np.array([math.cos(yaw), -math.sin(yaw)]), np.array([math.sin(yaw), math.cos(yaw)])  # _rot_y's axes
    return np.array([[x, z] + sx * hx * ax + sz * hz * az for sx in (-1, 1) for sz in (-1, 1)]), (ax, az)


def _overlap(a, b, margin_m: float = 0.02) -> bool:
    ca, axes_a = _rect(a)
    cb, axes_b = _rect(b)
    for axis in axes_a + axes_b:  # separating axis test
        pa, pb = ca @ axis, cb @ axis
        if pa.max() + margin_m < pb.min() or pb.max() + margin_m < pa.min():
            return False
    return True


def _footprint(items: list[Item]):
    """The axis-aligned footprint of some items' bounding boxes."""
    pts = np.concatenate([it.shape.corners() for it in items])
    (x0, z0), (x1, z1) = pts[:, [0, 2]].min(axis=0), pts[:, [0, 2]].max(axis=0)
    return ((x0 + x1) / 2, (z0 + z1) / 2, (x1 - x0) / 2, (z1 - z0) / 2, 0.0)


class _Room:
    """The room frame's walls and the footprints taken so far, for placing more on the floor."""

    def __init__(self, layout: Layout, taken: list):
        self.layout, self.taken = layout, taken
        self.back_m, self.side = math.inf, None  # side: (sign, |x| m) of a side wall

    def fits(self, fp) -> bool:
        corners, _ = _rect(fp)
        if corners[:, 1].max() > self.back_m - 0.005:
            return False
        if self.side is not None and (self.side[0] * corners[:, 0]).max() > self.side[1] - 0.005:
            return False
        return not any(_overlap(fp, other) for other in self.taken)

    def place(self, build) -> bool:
        """Add what ``build(layout)`` adds if its footprint fits, else nothing."""
        trial = Layout(floor_y_m=self.layout.floor_y_m)
        build(trial)
        fp = _footprint(trial.items)
        if not self.fits(fp):
            return False
        self.layout.items += trial.items
        self.taken.append(fp)
        return True


# --------------------------------------------------------------------------- the families

def _support_top(rng, support: str, radius: float) -> tuple[float, dict]:
    """How far above the floor a ball of ``radius`` rests (m), and the support's drawn sizes."""
    if support == "tripod":
        return rng.uniform(0.3, 1.3), {}
    if support == "table":
        return rng.uniform(0.45, 0.95), {}
    if support == "chair":
        seat_h = rng.uniform(0.42, 0.5)
        return seat_h + SEAT_HALF_M, {"seat_h": seat_h}
    if support == "box":
        top = rng.uniform(0.2, 0.6)
        return top, {}
    if support == "shelf":  # board k of evenly spaced boards (the gap above holds the ball)
        lo = max(0.3, 2 * radius + SHELF_BOARD_M + 0.04)  # room above a larger distractor too
        spacing, k = rng.uniform(lo, max(0.45, lo + 0.05)), int(rng.integers(0, 4))
        return k * spacing + SHELF_BOARD_M, {"spacing": spacing, "board": k}
    return 0.0, {}  # floor, wall


def _pose(rng, intr: Intrinsics, radius: float, support: str):
    """(camera -> room rotation, ball centre in the room frame, pitch deg, roll deg, yaw rad,
    camera height m, support top m, support sizes), redrawn until the height is in range."""
    for _ in range(_TRIES):
        pitch, roll, yaw = rng.uniform(*PITCH_DEG), rng.uniform(*ROLL_DEG), rng.uniform(*ROOM_YAW_RAD)
        to_room = _rot_y(yaw).T @ _rot_x(math.radians(pitch)) @ _rot_z(math.radians(roll))
        centre = to_room @ ball_in_view(rng, intr, radius, BALL_DISTANCE_M)
        top, sizes = _support_top(rng, support, radius)
        height = centre[1] + radius + top
        wall_ok = support != "wall" or BACK_WALL_M[0] <= centre[2] + radius <= BACK_WALL_M[1]
        if HEIGHT_M[0] <= height <= HEIGHT_M[1] and wall_ok and centre[2] > 0.2:
            return to_room, centre, pitch, roll, yaw, height, top, sizes
    raise RuntimeError(f"no camera pose for a ball on a {support} after {_TRIES} tries")


def _build_support(rng, layout: Layout, support: str, c: np.ndarray, r: float, top: float, sizes: dict):
    """Add the support under the ball; returns its footprint (None: nothing on the floor) and the
    rectangle of its top surface that can hold an object beside the ball (or None)."""
    if support == "tripod":
        tripod(rng, layout, c, r)
        return (c[0], c[2], 0.15, 0.15, 0.0), None  # the column: its legs may reach under a neighbour
    if support == "table":
        w, d = rng.uniform(0.6, 1.2), rng.uniform(0.5, 0.8)
        x, z = c[0] + rng.uniform(-1, 1) * (w / 2 - 0.15), c[2] + rng.uniform(-1, 1) * (d / 2 - 0.15)
        table(rng, layout, x, z, top, (w, d))
        return (x, z, w / 2, d / 2, 0.0), (x, z, w / 2, d / 2, 0.0)
    if support == "chair":
        w = rng.uniform(0.4, 0.5)
        yaw = math.atan2(c[0], c[2]) + rng.uniform(-0.8, 0.8)  # its back roughly away from the camera
        rot = _rot_y(yaw)
        seat = c - rot @ np.array([rng.uniform(-0.04, 0.04), 0.0, rng.uniform(-0.04, 0.04)])
        chair_at(layout, seat[0], seat[2], sizes["seat_h"], w, rot)
        return (seat[0], seat[2], w / 2, w / 2, yaw), None
    if support == "box":
        half = np.array([rng.uniform(0.15, 0.35), top / 2, rng.uniform(0.15, 0.35)])
        yaw = rng.uniform(0, math.pi / 2)
        rot = _rot_y(yaw)
        centre = c - rot @ np.array([rng.uniform(-1, 1) * (half[0] - 0.05), 0.0, rng.uniform(-1, 1) * (half[2] - 0.05)])
        box_on_floor(layout, centre[0], centre[2], half, rot, "support")
        fp = (centre[0], centre[2], half[0], half[2], yaw)
        return fp, fp
    if support == "shelf":
        t, k, spacing = SHELF_BOARD_M, sizes["board"], sizes["spacing"]
        n = k + 1 + int(rng.integers(0, 3))
        levels = spacing * np.arange(n + 1)
        lo = max(0.28, 2 * r + t + 0.01)
        width, depth = rng.uniform(0.8, 1.6), rng.uniform(lo, max(0.4, lo + 0.05))
        x = c[0] + rng.uniform(-1, 1) * (width / 2 - t - r - 0.05)
        z_back = c[2] + r + t + rng.uniform(0.0, depth - 2 * r - t)
        clear = (k, c[0] - r - rng.uniform(*NEAR_GAP_M), c[0] + r + rng.uniform(*NEAR_GAP_M))  # books beside it
        shelf_unit(rng, layout, x, z_back, width, levels[-1] + t, depth, levels, clear)
        return (x, z_back - depth / 2, width / 2, depth / 2, 0.0), None
    return None, None  # floor, wall


def _near_on_top(rng, room: _Room, c: np.ndarray, r: float, top_fp, top_m: float) -> bool:
    """An object standing on the support's top beside the ball, NEAR_GAP_M from it."""
    x, z, hx, hz, yaw = top_fp
    rot = _rot_y(yaw)
    local_c = rot.T @ (c - np.array([x, 0.0, z]))
    for _ in range(6):
        half = np.array([rng.uniform(0.03, 0.12), rng.uniform(r, 0.35) / 2, rng.uniform(0.03, 0.12)])
        side = rng.choice([-1.0, 1.0])
        u = local_c[0] + side * (r + rng.uniform(*NEAR_GAP_M) + half[0])
        w = local_c[2] + rng.uniform(-0.1, 0.1)
        if abs(u) + half[0] <= hx - 0.01 and abs(w) + half[2] <= hz - 0.01:
            centre = np.array([x, room.layout.floor_y_m - top_m - half[1], z]) + rot @ np.array([u, 0.0, w])
            room.layout.add(Box(centre, half, rot), "clutter")
            return True
    return False


def _near_on_floor(rng, room: _Room, c: np.ndarray, r: float, against_wall: bool) -> bool:
    """A cabinet or crate on the floor facing the ball, its near face NEAR_GAP_M from the ball and
    its top above the ball's centre (so that the gap is the distance); beside it along the back
    wall, against it, where the ball touches the wall."""
    centre_above_floor = room.layout.floor_y_m - c[1]
    for _ in range(24):
        theta = rng.choice([-0.5, 0.5]) * math.pi if against_wall else rng.uniform(0, 2 * math.pi)
        gap = rng.uniform(*NEAR_GAP_M)
        hx, hz = rng.uniform(0.15, 0.4), rng.uniform(0.12, 0.3)
        height = max(centre_above_floor + rng.uniform(0.0, 0.4), 0.15)
        x, z = c[0] + math.sin(theta) * (r + gap + hz), c[2] + math.cos(theta) * (r + gap + hz)
        if against_wall:  # turned a quarter: its local x along z, its back 6 mm off the wall
            z = room.back_m - 0.006 - hx
        fp = (x, z, hx, hz, theta)
        if room.fits(fp):
            box_on_floor(room.layout, x, z, np.array([hx, height / 2, hz]), _rot_y(theta), "furniture")
            room.taken.append(fp)
            return True
    return False


def _walls(rng, room: _Room, support: str, c: np.ndarray, r: float, taken_before: list) -> tuple[float, bool]:
    """The floor, the back wall (z = const in the room frame) and perhaps a side wall."""
    layout = room.layout
    layout.add(Plane(np.array([0.0, layout.floor_y_m, 0.0]), np.array([0.0, -1.0, 0.0])), "floor")
    if support == "wall":
        back = c[2] + r  # the ball touches it
    else:
        reach = max([c[2] + r + 0.05] + [_rect(fp)[0][:, 1].max() + 0.01 for fp in taken_before])
        lo = max(BACK_WALL_M[0], reach)
        back = rng.uniform(lo, max(lo, BACK_WALL_M[1]))
    layout.add(Plane(np.array([0.0, 0.0, back]), np.array([0.0, 0.0, -1.0])), "wall")
    room.back_m = back
    if rng.random() < 0.5:
        sign = rng.choice([-1.0, 1.0])
        reach = max([sign * c[0] + r, 0.3] + [(sign * _rect(fp)[0][:, 0]).max() for fp in taken_before])
        x = reach + rng.uniform(0.05, 1.5)
        layout.add(Plane(np.array([sign * x, 0.0, 0.0]), np.array([-sign, 0.0, 0.0])), "wall")
        room.side = (sign, x)
    return back, room.side is not None


def _furnish(rng, room: _Room, c: np.ndarray) -> None:
    """Two to five pieces of furniture about the room, where they fit."""
    for _ in range(int(rng.integers(2, 6))):
        x, z = c[0] + rng.uniform(-2.5, 2.5), rng.uniform(0.6, max(room.back_m - 0.2, 0.7))
        what = rng.random()
        if what < 0.3:
            w, seat_h, yaw = rng.uniform(0.4, 0.5), rng.uniform(0.42, 0.5), rng.uniform(-math.pi, math.pi)
            room.place(lambda lay: chair_at(lay, x, z, seat_h, w, _rot_y(yaw)))
        elif what < 0.6:
            half, yaw = rng.uniform(0.1, 0.3, size=3), rng.uniform(0, math.pi / 2)
            room.place(lambda lay: box_on_floor(lay, x, z, half, _rot_y(yaw)))
        elif what < 0.8:
            size, top = (rng.uniform(0.6, 1.2), rng.uniform(0.5, 0.8)), rng.uniform(0.45, 0.8)
            room.place(lambda lay: table(rng, lay, x, z, top, size))
        else:  # a bookcase against the back wall
            room.place(lambda lay: bookcase(rng, lay, x, room.back_m - 0.01))


def _distractors(rng, room: _Room, intr: Intrinsics, c: np.ndarray, to_cam: np.ndarray) -> None:
    """One or two balls of other radii on the floor beside the ball, in view."""
    floor = room.layout.floor_y_m
    for _ in range(int(rng.integers(1, 3))):
        lo, hi = DISTRACTOR_RADII_M[int(rng.integers(len(DISTRACTOR_RADII_M)))]
        rd = rng.uniform(lo, hi)
        for _ in range(10):
            theta, dist = rng.uniform(0, 2 * math.pi), rng.uniform(0.3, 1.0)
            centre = np.array([c[0] + dist * math.sin(theta), floor - rd, c[2] + dist * math.cos(theta)])
            fp = (centre[0], centre[2], rd, rd, 0.0)
            seen = to_cam @ centre
            if seen[2] > 0.3 and _in_image(intr, seen) and room.fits(fp):
                room.layout.add(SolidSphere(centre, rd), "distractor")
                room.taken.append(fp)
                break


def _in_image(intr: Intrinsics, point_m: np.ndarray) -> bool:
    u, v = project(intr, point_m[None, :])[0]
    return 0 <= u < intr.width and 0 <= v < intr.height


def _surfaces(rng, layout: Layout) -> None:
    """Low-albedo and textured surfaces (SURFACE_SHARES); the rest keeps the sensor's drawn albedo."""
    for it in layout.items:
        share = "room" if it.kind in ("wall", "floor") else "target" if it.kind == "target" else "item"
        low, textured = SURFACE_SHARES[share]
        x = rng.random()
        if x < low:
            it.albedo = float(rng.uniform(*LOW_ALBEDO))
        elif x < low + textured:
            d = rng.standard_normal(3)
            it.texture = Texture(str(rng.choice(TEXTURE_PATTERNS)), float(rng.uniform(*TEXTURE_SCALE_M)),
                                 float(rng.uniform(*TEXTURE_CONTRAST)), tuple(float(v) for v in d / np.linalg.norm(d)),
                                 int(rng.integers(2 ** 31)))


def visible_fraction(shapes: list, k: int, intr: Intrinsics, max_side_px: int = 48) -> float:
    """Fraction of primitive k's silhouette where it is the first surface hit (the ray caster's
    view, no sensor), on a grid of at most ``max_side_px`` rays a side over its image box."""
    v0, v1, u0, u1 = pixel_box(intr, shapes[k].corners(), 0)
    step = max(1, math.ceil(max(v1 - v0, u1 - u0) / max_side_px))
    vv, uu = np.mgrid[v0:v1:step, u0:u1:step]
    rays = pixel_rays(intr, uu.ravel().astype(np.float64), vv.ravel().astype(np.float64))
    own = shapes[k].intersect(rays)
    on = np.isfinite(own)
    if not on.any():
        return 0.0
    nearest = np.min([s.intersect(rays[on]) for s in shapes], axis=0)
    return float(np.mean(own[on] <= nearest))


def family(name: str, rng, intr: Intrinsics, radius_m: float) -> Layout:
    """A scene of the wide grammar: the ball (the dataset's radius) on support ``name``, or, for
    "negative", a support holding a distractor ball (60 %) or nothing; see the module's docstring."""
    negative = name == "negative"
    support = SUPPORTS[int(rng.integers(len(SUPPORTS)))] if negative else name
    ball_kind = "target"
    r = radius_m
    if negative:
        ball_kind = "distractor" if rng.random() < 0.6 else None
        lo, hi = DISTRACTOR_RADII_M[int(rng.integers(len(DISTRACTOR_RADII_M)))]
        r = rng.uniform(lo, hi)
    for _ in range(_TRIES):
        to_room, c, pitch, roll, yaw, height, top, sizes = _pose(rng, intr, r, support)
        layout = Layout(floor_y_m=height)
        support_fp, top_fp = _build_support(rng, layout, support, c, r, top, sizes)
        taken = [(0.0, 0.0, 0.3, 0.3, 0.0)] + ([support_fp] if support_fp is not None else [])  # the camera stands clear
        room = _Room(layout, taken)
        back, side_wall = _walls(rng, room, support, c, r, taken[1:])
        ball = len(layout.items)
        if ball_kind is not None:
            layout.add(SolidSphere(c, r), ball_kind)
        if rng.random() < NEAR_SHARE and support != "shelf":  # a shelf's books stand beside the ball
            if top_fp is None or not _near_on_top(rng, room, c, r, top_fp, top):
                _near_on_floor(rng, room, c, r, support == "wall")
        room.taken.append((c[0], c[2], r, r, 0.0))
        _furnish(rng, room, c)
        to_cam = to_room.T
        if rng.random() < DISTRACTOR_SHARE:
            _distractors(rng, room, intr, c, to_cam)
        _surfaces(rng, layout)
        layout.items = [Item(rotated(it.shape, to_cam), it.kind, it.albedo, it.texture) for it in layout.items]
        layout.meta = {"support": support, "camera_pitch_deg": float(pitch), "camera_roll_deg": float(roll),
                       "camera_height_m": float(height), "room_yaw_deg": float(math.degrees(yaw)),
                       "back_wall_m": float(back), "side_wall": bool(side_wall)}
        if negative:
            layout.meta["support_holds"] = ball_kind or "nothing"
        if ball_kind is None or visible_fraction([it.shape for it in layout.items], ball, intr) >= MIN_VISIBLE:
            return layout
    raise RuntimeError(f"no wide {name} scene with its ball in view after {_TRIES} tries")


FAMILIES = {name: partial(family, name) for name, _share in SHARES}
