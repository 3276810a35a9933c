"""The D435 depth sensor model: what the camera makes of the true depth of a scene.

All parameters live in ``D435Sensor``, with the D435's values as defaults (METHOD_NOTES.md):
- depth noise, Intel's stereo RMS model: sigma_z = z^2 * subpixel / (f_px * baseline), with
  f_px the focal length at the stream's resolution (so 424x240 is noisier than 1280x720);
- the invalid "shadow" band left of foreground objects: background the right imager cannot see
  (the depth is in the left imager's frame, the right imager is ``baseline_m`` to its right);
- flying pixels at depth edges: depths between the foreground and the background;
- holes: isolated invalid pixels and small invalid blobs;
- valid range limits, and 1 mm quantisation (z16 counts of depth_scale), invalid = 0.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from spherebench.camera import Intrinsics


@dataclass(frozen=True)
class D435Sensor:
    """Sensor parameters (metres, pixels, probabilities); defaults are the D435's."""

    baseline_m: float = 0.050          # stereo baseline
    subpixel: float = 0.08             # disparity RMS error, pixels (0.05-0.1 typical)
    depth_scale_m: float = 0.001       # metres per z16 count
    min_depth_m: float = 0.11          # nearest valid depth (Table 1: ~0.11 m)
    max_depth_m: float = 10.0          # farthest valid depth
    shadow: bool = True                # invalidate the occlusion band left of foreground edges
    flying_edge_jump: float = 0.05     # relative depth jump that makes an edge (5 %)
    flying_probability: float = 0.3    # chance that an edge pixel becomes a flying pixel
    hole_probability: float = 0.003    # isolated invalid pixels
    hole_blobs_per_mpx: float = 40.0   # small invalid blobs per million pixels
    hole_blob_radius_px: tuple[float, float] = (1.0, 4.0)

    def sigma_z_m(self, z_m: np.ndarray, fx_px: float) -> np.ndarray:
        """Depth noise RMS (metres) at depth z (metres) for focal length fx (pixels)."""
        return np.asarray(z_m) ** 2 * self.subpixel / (fx_px * self.baseline_m)


def shadow_mask(z_m: np.ndarray, fx_px: float, baseline_m: float) -> np.ndarray:
    """(H, W) bool: pixels the right imager cannot see (occluded by something to their right).

    A pixel at column c with disparity d = f B / z reappears at column c - d in the right image;
    a pixel c' > c hides it there if d' - (c' - c) > d. Scanning each row right to left keeps
    the running maximum of d' - (c' - c).
    """
    with np.errstate(divide="ignore"):
        disp = np.where(np.isfinite(z_m) & (z_m > 0), fx_px * baseline_m / z_m, 0.0)
    h, w = disp.shape
    reach = np.full(h, -np.inf)
    hidden = np.zeros((h, w), dtype=bool)
    for c in range(w - 2, -1, -1):
        reach = np.maximum(reach, disp[:, c + 1]) - 1.0
        hidden[:, c] = reach > disp[:, c] + 0.5
    return hidden


def apply_sensor(z_true_m: np.ndarray, intr: Intrinsics, sensor: D435Sensor,
                 rng: np.random.Generator) -> np.ndarray:
    """True depth (H, W) metres (inf = no surface) -> D435 depth (H, W) uint16 counts, 0 = invalid."""
    z = np.array(z_true_m, dtype=np.float64)
    h, w = z.shape
    finite = np.isfinite(z)
    invalid = ~finite
    if sensor.shadow:
        invalid |= shadow_mask(z, intr.fx, sensor.baseline_m)

    # flying pixels: where a 4-neighbour is much farther, mix the two depths
    zf = np.where(finite, z, 1e6)
    far = np.full_like(zf, -np.inf)
    for dv, du in ((0, 1), (0, -1), (1, 0), (-1, 0)):
        shifted = np.full_like(zf, -np.inf)
        shifted[max(dv, 0):h + min(dv, 0), max(du, 0):w + min(du, 0)] = \
            zf[max(-dv, 0):h + min(-dv, 0), max(-du, 0):w + min(-du, 0)]
        far = np.maximum(far, shifted)
    edge = finite & (far > zf * (1.0 + sensor.flying_edge_jump)) & (far < 1e5)
    fly = edge & (rng.random((h, w)) < sensor.flying_probability)
    mix = rng.uniform(0.1, 0.9, size=(h, w))
    z = np.where(fly, zf + mix * (far - zf), z)

    noisy = z + rng.standard_normal((h, w)) * sensor.sigma_z_m(np.where(finite, z, 0.0), intr.fx)

    invalid |= rng.random((h, w)) < sensor.hole_probability
    n_blobs = rng.poisson(sensor.hole_blobs_per_mpx * h * w / 1e6)
    if n_blobs:
        blobs = np.zeros((h, w), np.uint8)
        lo, hi = sensor.hole_blob_radius_px
        for cu, cv_, ra, rb, ang in zip(rng.uniform(0, w, n_blobs), rng.uniform(0, h, n_blobs),
                                        rng.uniform(lo, hi, n_blobs), rng.uniform(lo, hi, n_blobs),
                                        rng.uniform(0, 180, n_blobs)):
            cv2.ellipse(blobs, (int(cu), int(cv_)), (int(round(ra)), int(round(rb))), float(ang), 0, 360, 1, -1)
        invalid |= blobs.astype(bool)

    invalid |= ~np.isfinite(noisy) | (noisy < sensor.min_depth_m) | (noisy > sensor.max_depth_m)
    counts = np.round(np.where(invalid, 0.0, noisy) / sensor.depth_scale_m)
    return np.clip(counts, 0, np.iinfo(np.uint16).max).astype(np.uint16)
