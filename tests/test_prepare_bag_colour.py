"""RealSense recordings with a colour stream: `prepare` pairs each depth frame with the colour
frame nearest in time and keeps it aligned to the depth (colour.png), so that `annotate
--from-colour` and `prepare --labelme` work on a D435 recording as on the Kinect set.

The scenes are ray-cast twice, once in each camera, so the colour frame shows the ball where the
colour camera sees it; the bags are written by tests/bagwriter.py (ROS1) and by pyrealsense2's
own recorder (ROS2, .db3) and read back through pyrealsense2 playback.
"""

from __future__ import annotations


import cv2
import numpy as np
import pytest

rs = pytest.importorskip("pyrealsense2")

from spherebench.camera import Intrinsics, align_to_depth, image_rays, project  # noqa: E402

# a D435 at 424x240 depth; colour of another size, field of view and distortion, 15 mm to the side
DEPTH = Intrinsics(width=424, height=240, ppx=211.5, ppy=119.25, fx=213.0, fy=213.0, model="brown_conrady",
                   depth_scale=0.001)
COLOUR = Intrinsics(width=640, height=480, ppx=321.5, ppy=238.75, fx=615.0, fy=614.5,
                    model="inverse_brown_conrady", coeffs=(0.08, -0.05, 0.002, -0.001, 0.01))
_AY, _AX = np.radians(0.3), np.radians(-0.2)
ROTATION = (np.array([[np.cos(_AY), 0, np.sin(_AY)], [0, 1, 0], [-np.sin(_AY), 0, np.cos(_AY)]])
            @ np.array([[1, 0, 0], [0, np.cos(_AX), -np.sin(_AX)], [0, np.sin(_AX), np.cos(_AX)]]))
TRANSLATION = np.array([0.015, 0.0003, -0.0002])
RADIUS = 0.12
WALL = (np.array([-0.2, 0.0, 1.0]), 1.6)  # the plane n . p = d in the depth camera's frame: z = 1.6 + 0.2 x
YELLOW = (0, 220, 255)  # BGR
WALL_BGR = (90, 110, 130)
N_FRAMES = 3


def centre(i: int) -> np.ndarray:
    return np.array([0.04 + 0.03 * i, 0.02, 0.5 + 0.05 * i])


def ray_cast(rays: np.ndarray, ball_centre: np.ndarray, normal: np.ndarray, dist: float):
    """(depth z of the first hit (rays have z = 1), the ball is that hit) along each ray."""
    a = (rays * rays).sum(-1)
    b = rays @ ball_centre
    disc = b * b - a * (ball_centre @ ball_centre - RADIUS ** 2)
    ball = np.where(disc >= 0, (b - np.sqrt(np.maximum(disc, 0))) / a, np.inf)
    wall = dist / (rays @ normal)
    return np.minimum(ball, wall), ball < wall


def render(i: int, colour_intr: Intrinsics = COLOUR, rotation=ROTATION, translation=TRANSLATION):
    """Frame i: (depth counts (H, W) uint16 mm, the ball's silhouette in depth (H, W) bool,
    the colour camera's image (h, w, 3) uint8 BGR: a yellow ball on a brown-grey wall)."""
    z, ball = ray_cast(image_rays(DEPTH), centre(i), *WALL)
    depth = np.round(z * 1000).astype(np.uint16)
    # the same scene in the colour camera's frame: p_c = R p_d + t
    rot, trans = np.asarray(rotation), np.asarray(translation)
    normal = rot @ WALL[0]
    _, seen = ray_cast(image_rays(colour_intr), rot @ centre(i) + trans, normal, WALL[1] + normal @ trans)
    colour = np.empty(colour_intr.shape + (3,), np.uint8)
    colour[...] = WALL_BGR
    colour[seen] = YELLOW
    return depth, ball, colour


def yellow(image_bgr: np.ndarray) -> np.ndarray:
    return np.all(image_bgr == YELLOW, axis=-1)


def within_one_pixel(mask: np.ndarray, silhouette: np.ndarray) -> bool:
    """mask lies inside the silhouette grown by 1 px and covers it shrunk by 1 px."""
    k = np.ones((3, 3), np.uint8)
    grown = cv2.dilate(silhouette.astype(np.uint8), k).astype(bool)
    shrunk = cv2.erode(silhouette.astype(np.uint8), k).astype(bool)
    return bool(np.all(grown | ~mask) and np.all(mask | ~shrunk))


def rs_intrinsics(intr: Intrinsics):
    ri = rs.intrinsics()
    ri.width, ri.height, ri.ppx, ri.ppy, ri.fx, ri.fy = intr.width, intr.height, intr.ppx, intr.ppy, intr.fx, intr.fy
    ri.model, ri.coeffs = getattr(rs.distortion, intr.model), list(intr.coeffs)
    return ri


# --------------------------------------------------------------------------- the geometry

@pytest.mark.parametrize("model", ["none", "brown_conrady", "modified_brown_conrady", "inverse_brown_conrady"])
def test_projection_is_librealsenses(model):
    """The colour projection is rs2_project_point_to_pixel's, distortion model included."""
    intr = Intrinsics(width=640, height=480, ppx=321.5, ppy=238.75, fx=615.0, fy=614.5, model=model,
                      coeffs=(0.08, -0.05, 0.002, -0.001, 0.01))
    rng = np.random.default_rng(1)
    points = np.c_[rng.uniform(-0.4, 0.4, (300, 2)), rng.uniform(0.4, 3.0, 300)]
    theirs = np.array([rs.rs2_project_point_to_pixel(rs_intrinsics(intr), list(p)) for p in points])
    np.testing.assert_allclose(project(intr, points), theirs, atol=1e-3)  # px; librealsense is float32


def test_alignment_matches_librealsense_pixel_for_pixel():
    """Each coloured depth pixel holds the colour pixel that librealsense's deproject / transform /
    project functions find for it, rounded to the nearest (bar float32 ties at a half pixel)."""
    depth, ball, _ = render(0)
    rng = np.random.default_rng(2)
    noise = rng.integers(0, 256, COLOUR.shape + (3,), dtype=np.uint8)  # every pixel its own value
    aligned, counts = align_to_depth(depth * 0.001, DEPTH, noise, COLOUR, ROTATION, TRANSLATION)
    extrinsics = rs.extrinsics()
    extrinsics.rotation = list(ROTATION.T.ravel())  # column-major
    extrinsics.translation = list(TRANSLATION)
    rows, cols = np.nonzero(np.any(aligned > 0, axis=-1))
    pick = rng.choice(len(rows), 400, replace=False)
    agree = 0
    for r, c in zip(rows[pick], cols[pick]):
        p = rs.rs2_deproject_pixel_to_point(rs_intrinsics(DEPTH), [float(c), float(r)], float(depth[r, c]) * 0.001)
        q = rs.rs2_transform_point_to_point(extrinsics, p)
        u, v = rs.rs2_project_point_to_pixel(rs_intrinsics(COLOUR), q)
        agree += np.array_equal(aligned[r, c], noise[int(np.floor(v + 0.5)), int(np.floor(u + 0.5))])
    assert agree >= 398, agree
    assert counts["with_depth"] == DEPTH.width * DEPTH.height
    assert counts["coloured"] + counts["off_image"] + counts["occluded"] == counts["with_depth"]


def test_aligned_ball_is_the_depth_silhouette_and_the_shadow_stays_black():
    depth, ball, colour = render(0)
    aligned, counts = align_to_depth(depth * 0.001, DEPTH, colour, COLOUR, ROTATION, TRANSLATION)
    assert within_one_pixel(yellow(aligned), ball)
    # the wall beside the ball that the colour camera sees only behind the ball: black, not yellow
    assert counts["occluded"] > 100
    hidden = ~np.any(aligned > 0, axis=-1) & ~ball
    grown = cv2.dilate(ball.astype(np.uint8), np.ones((15, 15), np.uint8)).astype(bool)
    assert (hidden & grown).sum() > 100  # beside the ball (the rest of the black is off the colour image)
    # the test can tell: without the extrinsics the disc would sit several pixels off
    naive, _ = align_to_depth(depth * 0.001, DEPTH, colour, COLOUR, np.eye(3), np.zeros(3))
    assert not within_one_pixel(yellow(naive), ball)
    # where depth is missing the aligned colour is black
    holed = depth.copy()
    holed[100:110, 200:220] = 0
    aligned2, _ = align_to_depth(holed * 0.001, DEPTH, colour, COLOUR, ROTATION, TRANSLATION)
    assert not aligned2[100:110, 200:220].any()
    np.testing.assert_array_equal(aligned2[:90], aligned[:90])
