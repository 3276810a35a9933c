"""Analytic primitives ray-cast from a camera at the origin: planes, boxes, cylinders, spheres.

Rays are (M, 3) with z = 1 (``spherebench.camera.pixel_rays``), so the ray parameter t of a hit
is its depth z along the optical axis, in metres; ``intersect`` returns t, or inf where the ray
misses; ``planar_face`` says which planar face a surface point lies on (CURVED if none). Everything is in the camera frame: x right, y down, z forward, metres.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from spherebench.camera import Intrinsics, project
from spherebench.circles import norm3

_MISS = np.inf
#: ``planar_face`` of a point on a curved surface; planar faces are 0 .. FACES_PER_OBJECT - 2.
CURVED = -1
FACES_PER_OBJECT = 7


def _nearest(*ts: np.ndarray) -> np.ndarray:
    """Elementwise smallest positive t of several candidates (inf if none)."""
    best = np.full(ts[0].shape, _MISS)
    for t in ts:
        ok = (t > 1e-9) & (t < best)
        best[ok] = t[ok]
    return best


@dataclass
class Plane:
    """Infinite plane through ``point_m`` with normal ``normal`` (walls, floors)."""

    point_m: np.ndarray
    normal: np.ndarray

    def intersect(self, rays: np.ndarray) -> np.ndarray:
        n = np.asarray(self.normal, np.float64)
        denom = rays @ n
        with np.errstate(divide="ignore", invalid="ignore"):
            t = np.where(np.abs(denom) > 1e-12, (np.asarray(self.point_m) @ n) / denom, _MISS)
        return np.where(t > 0, t, _MISS)

    def corners(self) -> None:
        return None  # unbounded: every ray may hit it

    def planar_face(self, points_m: np.ndarray) -> np.ndarray:
        return np.zeros(len(points_m), np.int32)


@dataclass
class SolidSphere:
    centre_m: np.ndarray
    radius_m: float

    def intersect(self, rays: np.ndarray) -> np.ndarray:
        c = np.asarray(self.centre_m, np.float64)
        a = np.einsum("ij,ij->i", rays, rays)
        b = rays @ c
        disc = b * b - a * (c @ c - self.radius_m ** 2)
        hit = disc >= 0
        root = np.sqrt(np.where(hit, disc, 0.0))
        t_near = (b - root) / a
        t_far = (b + root) / a
        return np.where(hit, _nearest(t_near, t_far), _MISS)

    def corners(self) -> np.ndarray:
        return _box_corners(np.asarray(self.centre_m, np.float64), np.eye(3), np.full(3, self.radius_m))

    def planar_face(self, points_m: np.ndarray) -> np.ndarray:
        return np.full(len(points_m), CURVED, np.int32)


@dataclass
class Box:
    """Oriented box: centre, rotation (columns = the box's axes in the camera frame), half sizes."""

    centre_m: np.ndarray
    half_size_m: np.ndarray
    rotation: np.ndarray = field(default_factory=lambda: np.eye(3))

    def intersect(self, rays: np.ndarray) -> np.ndarray:
        rot = np.asarray(self.rotation, np.float64)
        origin = -rot.T @ np.asarray(self.centre_m, np.float64)  # camera origin in box frame
        d = rays @ rot  # ray directions in box frame, (M, 3)
        h = np.asarray(self.half_size_m, np.float64)
        with np.errstate(divide="ignore", invalid="ignore"):
            t1 = (-h - origin) / d
            t2 = (h - origin) / d
        t1 = np.where(np.isnan(t1), -_MISS, t1)
        t2 = np.where(np.isnan(t2), _MISS, t2)
        t_enter = np.minimum(t1, t2).max(axis=1)
        t_exit = np.maximum(t1, t2).min(axis=1)
        hit = t_exit >= np.maximum(t_enter, 0.0)
        return np.where(hit, _nearest(t_enter, t_exit), _MISS)

    def corners(self) -> np.ndarray:
        return _box_corners(np.asarray(self.centre_m, np.float64), np.asarray(self.rotation, np.float64),
                            np.asarray(self.half_size_m, np.float64))

    def planar_face(self, points_m: np.ndarray) -> np.ndarray:
        """Face 2 a + (side > 0) of the box axis a whose face each surface point lies on."""
        local = (np.asarray(points_m, np.float64) - np.asarray(self.centre_m, np.float64)) \
            @ np.asarray(self.rotation, np.float64)
        ratio = local / np.asarray(self.half_size_m, np.float64)
        axis = np.argmax(np.abs(ratio), axis=1)
        return (2 * axis + (ratio[np.arange(len(axis)), axis] > 0)).astype(np.int32)


@dataclass
class Cylinder:
    """Finite capped cylinder: base centre, unit axis, radius, height (legs, poles, bins)."""

    base_m: np.ndarray
    axis: np.ndarray
    radius_m: float
    height_m: float

    def intersect(self, rays: np.ndarray) -> np.ndarray:
        a = np.asarray(self.axis, np.float64)
        a = a / norm3(a)
        w = -np.asarray(self.base_m, np.float64)  # origin relative to the base
        ra = rays @ a
        r_perp = rays - ra[:, None] * a
        w_perp = w - (w @ a) * a
        qa = np.einsum("ij,ij->i", r_perp, r_perp)
        qb = r_perp @ w_perp
        qc = w_perp @ w_perp - self.radius_m ** 2
        disc = qb * qb - qa * qc
        ok = (disc >= 0) & (qa > 1e-15)
        root = np.sqrt(np.where(ok, disc, 0.0))
        with np.errstate(divide="ignore", invalid="ignore"):
            sides = []
            for sign in (-1.0, 1.0):
                t = np.where(ok, (-qb + sign * root) / qa, _MISS)
                s = (w @ a) + t * ra  # axial coordinate of the hit
                sides.append(np.where((s >= 0) & (s <= self.height_m), t, _MISS))
            caps = []
            for s_cap in (0.0, self.height_m):
                t = np.where(np.abs(ra) > 1e-15, (s_cap - w @ a) / ra, _MISS)
                p = t[:, None] * rays + w[None, :] - s_cap * a[None, :]  # hit relative to the cap centre
                caps.append(np.where(np.einsum("ij,ij->i", p, p) <= self.radius_m ** 2, t, _MISS))
        return _nearest(*sides, *caps)

    def corners(self) -> np.ndarray:
        a = np.asarray(self.axis, np.float64) / norm3(self.axis)
        b = np.asarray(self.base_m, np.float64)
        centre = b + 0.5 * self.height_m * a
        half = np.array([self.radius_m, self.radius_m, 0.5 * self.height_m])
        u = np.cross(a, [1.0, 0.0, 0.0] if abs(a[0]) < 0.9 else [0.0, 1.0, 0.0])
        u /= norm3(u)
        return _box_corners(centre, np.stack([u, np.cross(a, u), a], axis=1), half)

    def planar_face(self, points_m: np.ndarray) -> np.ndarray:
        """0 on the base cap, 1 on the top cap, CURVED on the side (a point of the rim: a cap)."""
        a = np.asarray(self.axis, np.float64) / norm3(self.axis)
        s = (np.asarray(points_m, np.float64) - np.asarray(self.base_m, np.float64)) @ a
        tol = 1e-7 * max(1.0, self.height_m)  # a cap hit's axial coordinate is the cap's up to rounding
        return np.where(np.abs(s) <= tol, 0, np.where(np.abs(s - self.height_m) <= tol, 1, CURVED)).astype(np.int32)


def rotated(obj, rotation: np.ndarray):
    """The primitive turned about the camera origin: every point p goes to ``rotation`` @ p (3x3,
    orthonormal), e.g. a scene built in a level frame seen by a pitched and rolled camera."""
    rot = np.asarray(rotation, np.float64)
    if isinstance(obj, Plane):
        return replace(obj, point_m=rot @ np.asarray(obj.point_m, np.float64), normal=rot @ np.asarray(obj.normal, np.float64))
    if isinstance(obj, SolidSphere):
        return replace(obj, centre_m=rot @ np.asarray(obj.centre_m, np.float64))
    if isinstance(obj, Box):
        return replace(obj, centre_m=rot @ np.asarray(obj.centre_m, np.float64),
                       rotation=rot @ np.asarray(obj.rotation, np.float64))
    return replace(obj, base_m=rot @ np.asarray(obj.base_m, np.float64), axis=rot @ np.asarray(obj.axis, np.float64))


#: The procedural patterns of ``Texture``.
TEXTURE_PATTERNS = ("stripes", "checks", "noise")


@dataclass(frozen=True)
class Texture:
    """A surface's albedo pattern as a function of the 3D point (camera frame, m): a factor from
    1 - contrast to 1 that multiplies the surface's albedo. stripes: a sinusoid of period
    ``scale_m`` along ``direction``; checks: the product of such sinusoids along the three axes;
    noise: value noise on a lattice of spacing ``scale_m`` (trilinear, values hashed from ``seed``)."""

    pattern: str
    scale_m: float
    contrast: float
    direction: tuple[float, float, float] = (1.0, 0.0, 0.0)
    seed: int = 0

    def factor(self, points_m: np.ndarray) -> np.ndarray:
        q = np.asarray(points_m, np.float64) / self.scale_m
        if self.pattern == "stripes":
            value = 0.5 + 0.5 * np.sin(2 * np.pi * (q @ (np.asarray(self.direction) / norm3(self.direction))))
        elif self.pattern == "checks":
            # scaled and clipped: a product of three sines is small over most of a surface
            value = np.clip(0.5 + 1.5 * np.prod(np.sin(2 * np.pi * q), axis=1), 0.0, 1.0)
        else:
            value = _value_noise(q, self.seed)
        return 1.0 - self.contrast * value


def _value_noise(q: np.ndarray, seed: int) -> np.ndarray:
    """Trilinear value noise at lattice coordinates q (N, 3): values in [0, 1) hashed per lattice node."""
    base = np.floor(q)
    f = q - base
    f = f * f * (3 - 2 * f)  # smoothstep: no creases along the lattice planes
    i = base.astype(np.int64)
    out = np.zeros(len(q))
    for corner in range(8):
        d = np.array([(corner >> a) & 1 for a in range(3)])
        node = (i + d).astype(np.uint64)
        h = node[:, 0] * np.uint64(0x9E3779B97F4A7C15) ^ node[:, 1] * np.uint64(0xC2B2AE3D27D4EB4F) \
            ^ node[:, 2] * np.uint64(0x165667B19E3779F9) ^ np.uint64(seed)
        h ^= h >> np.uint64(31)
        h *= np.uint64(0xBF58476D1CE4E5B9)
        h ^= h >> np.uint64(29)
        w = np.prod(np.where(d == 1, f, 1 - f), axis=1)
        out += w * (h >> np.uint64(11)).astype(np.float64) / 2.0 ** 53
    return out


def _box_corners(center: np.ndarray, rot: np.ndarray, half: np.ndarray) -> np.ndarray:
    signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], np.float64)
    return center[None, :] + (signs * half[None, :]) @ rot.T


def pixel_box(intr: Intrinsics, corners: np.ndarray | None, pad_px: int = 2):
    """Image box (v0, v1, u0, u1) (end-exclusive) that a primitive with these bounding-box
    corners can cover; the whole image when unbounded or reaching behind the camera."""
    if corners is None or np.any(corners[:, 2] <= 0.05):
        return 0, intr.height, 0, intr.width
    uv = project(intr, corners)
    u0 = int(np.clip(np.floor(uv[:, 0].min()) - pad_px, 0, intr.width))
    u1 = int(np.clip(np.ceil(uv[:, 0].max()) + pad_px + 1, 0, intr.width))
    v0 = int(np.clip(np.floor(uv[:, 1].min()) - pad_px, 0, intr.height))
    v1 = int(np.clip(np.ceil(uv[:, 1].max()) + pad_px + 1, 0, intr.height))
    return v0, v1, u0, u1


def raycast(objects: list, rays: np.ndarray, intr: Intrinsics) -> tuple[np.ndarray, np.ndarray]:
    """Depth of the first surface and which object it belongs to.

    objects: primitives with ``intersect`` and ``corners``. rays: (H, W, 3) from image_rays.
    Returns z (H, W) float64 metres (inf = nothing hit) and label (H, W) int32: index into
    ``objects`` + 1, 0 where nothing is hit. Each primitive is tested only on the pixels of
    its projected bounding box.
    """
    z = np.full(intr.shape, _MISS)
    label = np.zeros(intr.shape, np.int32)
    for k, obj in enumerate(objects):
        v0, v1, u0, u1 = pixel_box(intr, obj.corners())
        if v0 >= v1 or u0 >= u1:
            continue
        sub = rays[v0:v1, u0:u1].reshape(-1, 3)
        t = obj.intersect(sub).reshape(v1 - v0, u1 - u0)
        zs, ls = z[v0:v1, u0:u1], label[v0:v1, u0:u1]
        closer = t < zs
        zs[closer] = t[closer]
        ls[closer] = k + 1
    return z, label


def surface_map(objects: list, label: np.ndarray, z_m: np.ndarray, rays: np.ndarray, intr: Intrinsics,
                include_curved: tuple[int, ...] = ()) -> np.ndarray:
    """(H, W) int32: which surface each pixel sees, from ``raycast``'s label and depth.

    1 + FACES_PER_OBJECT k + f where the pixel sees planar face f of object k; 0 where nothing is
    hit or the surface is curved, except on the objects whose indices are in ``include_curved``,
    whose curved surface counts as one more face (FACES_PER_OBJECT - 1)."""
    out = np.zeros(intr.shape, np.int32)
    for k, obj in enumerate(objects):
        v0, v1, u0, u1 = pixel_box(intr, obj.corners())
        if v0 >= v1 or u0 >= u1:
            continue
        hit = label[v0:v1, u0:u1] == k + 1
        if not hit.any():
            continue
        points = rays[v0:v1, u0:u1][hit] * z_m[v0:v1, u0:u1][hit][:, None]
        face = obj.planar_face(points)
        if k in include_curved:
            face = np.where(face == CURVED, FACES_PER_OBJECT - 1, face)
        out[v0:v1, u0:u1][hit] = np.where(face == CURVED, 0, 1 + FACES_PER_OBJECT * k + face)
    return out
