"""The 2D reprojection every 2D method gets (the paper's Figure 21b): the depth image colourised.

One function, ``colourise_depth``, renders it, for training and evaluation alike.
Colour map: OpenCV's JET, blue = near, red = far, as the paper's Figures 2 and 5. The depth
range is fixed, not per image, so that a colour means the same distance in every scene:
DEPTH_RANGE_M = (0.2, 5.0) metres, linear in depth, clipped at both ends. Invalid pixels
(no depth) are black.
"""

from __future__ import annotations

import cv2
import numpy as np

#: Depth (metres) mapped to the two ends of the colour map.
DEPTH_RANGE_M = (0.2, 5.0)
COLORMAP = cv2.COLORMAP_JET


def colourise_depth(depth_m: np.ndarray, depth_range_m: tuple[float, float] = DEPTH_RANGE_M) -> np.ndarray:
    """(H, W) float depth in metres (NaN or <= 0 = invalid) -> (H, W, 3) uint8 BGR image."""
    z = np.asarray(depth_m, dtype=np.float32)
    valid = np.isfinite(z) & (z > 0)
    near, far = depth_range_m
    level = np.zeros(z.shape, dtype=np.uint8)
    level[valid] = np.round(np.clip((z[valid] - near) / (far - near), 0.0, 1.0) * 255.0).astype(np.uint8)
    image = cv2.applyColorMap(level, COLORMAP)
    image[~valid] = 0
    return image
