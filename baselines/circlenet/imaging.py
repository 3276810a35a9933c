"""The image contract of the CircleNet-style baseline, shared by training and inference (no torch).

- Input: the benchmark's ``image.png`` (the depth colourised), 8-bit, 3 channels, read as RGB.
  The model takes one size (424x240); the D435's other modes (848x480, 1280x720: the same
  aspect ratio) are scaled to it by ``fit_image`` in training and inference alike.
- The network takes the image padded at the bottom and right to a multiple of ``SIZE_DIVISOR``
  (424x240 -> 448x256) with ``PAD_VALUE``: padding only there leaves pixel coordinates unchanged.
  Pixel values stay in [0, 255]; the normalisation lives inside the network (``model.py``), so the
  ONNX file and the PyTorch model take exactly the same array.
- Output grid: stride ``STRIDE`` (4). With pixel centres at integer coordinates (u = column,
  v = row; ``spherebench.camera``), grid cell j covers pixels 4j .. 4j+3, and the continuous grid
  coordinate of pixel coordinate u is g = (u + 0.5) / 4. A centre is encoded as its cell
  floor(g) plus the sub-cell offset g - floor(g) in [0, 1); the radius in grid units, r / 4.
"""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
from scipy.ndimage import maximum_filter

from spherebench.errors import SphereBenchError

#: Output stride of the heads, pixels per grid cell.
STRIDE = 4
#: Network input sides must be multiples of this (stride 32 at the deepest level of both backbones).
SIZE_DIVISOR = 32
#: Value of the padding and of the border that augmentation exposes (black, as invalid depth).
PAD_VALUE = 0


#: An image whose aspect ratio is within this fraction of the model's is scaled to fit it (the
#: D435's 424x240, 848x480 and 1280x720 modes); any other size is refused.
ASPECT_TOLERANCE = 0.02


def check_size(shape: tuple[int, ...], image_size: tuple[int, int], what: str = "the image") -> None:
    """Raise SphereBenchError unless an image of shape (h, w, ...) can go to a model taking (H, W) px:
    the same size, or the same aspect ratio (then ``fit_image`` scales it)."""
    h, w = shape[:2]
    mh, mw = image_size
    if (h, w) != (mh, mw) and abs((w / h) / (mw / mh) - 1) > ASPECT_TOLERANCE:
        raise SphereBenchError(f"{what} is {w}x{h} px but the model takes {mw}x{mh} px images (or that aspect "
                               "ratio, scaled); use a model trained on this image size")


def load_image(path, expected_size: tuple[int, int] | None = None) -> np.ndarray:
    """Read a colourised depth image (image.png) as RGB uint8 (h, w, 3).

    expected_size: (H, W) px the model takes; an image of another aspect ratio is an error.
    """
    path = Path(path)
    if not path.is_file():
        raise SphereBenchError(f"image {path} not found")
    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if raw is None:
        raise SphereBenchError(f"{path} is not a readable image; pass a scene's colourised image.png")
    if raw.dtype != np.uint8 or raw.ndim != 3 or raw.shape[2] != 3:
        kind = f"{raw.dtype} with {1 if raw.ndim == 2 else raw.shape[2]} channel(s)"
        hint = " (a depth image? pass the colourised image.png)" if raw.dtype == np.uint16 else ""
        raise SphereBenchError(f"{path} is {kind}, expected an 8-bit 3-channel colour image{hint}")
    if expected_size is not None:
        check_size(raw.shape, expected_size, str(path))
    return cv2.cvtColor(raw, cv2.COLOR_BGR2RGB)


def fit_image(image: np.ndarray, image_size: tuple[int, int]) -> tuple[np.ndarray, float]:
    """Scale an image (h, w, 3) uniformly to fit (H, W) px, pad bottom/right; returns it and the scale.

    Nearest neighbour (OpenCV's exact variant: pixel centres map as u' = (u + 0.5) * s - 0.5),
    so that every pixel keeps a colour of the colour map and "no depth" stays black. The same
    rule in training and inference; ``scale_circles`` maps circles along.
    """
    h, w = image.shape[:2]
    if (h, w) == tuple(image_size):
        return image, 1.0
    s = min(image_size[0] / h, image_size[1] / w)
    small = cv2.resize(image, (0, 0), fx=s, fy=s, interpolation=cv2.INTER_NEAREST_EXACT)
    out = np.full((*image_size, 3), PAD_VALUE, dtype=image.dtype)
    hh, ww = min(small.shape[0], image_size[0]), min(small.shape[1], image_size[1])
    out[:hh, :ww] = small[:hh, :ww]
    return out, s


def scale_circles(circles: np.ndarray, scale: float) -> np.ndarray:
    """Circles (N, 3+) (cx, cy, r, ...) px in an image scaled by ``scale`` (``fit_image``); extra columns kept."""
    c = np.array(circles, dtype=np.float64, copy=True)
    c[:, :2] = (c[:, :2] + 0.5) * scale - 0.5
    c[:, 2] *= scale
    return c


def input_size(image_size: tuple[int, int]) -> tuple[int, int]:
    """Network input (height, width) px for images of (height, width) px: rounded up to SIZE_DIVISOR."""
    return tuple(int(math.ceil(s / SIZE_DIVISOR) * SIZE_DIVISOR) for s in image_size)


def pad_image(image: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Pad an image (H, W, 3) at the bottom and right to size (Hp, Wp) with PAD_VALUE."""
    h, w = image.shape[:2]
    out = np.full((size[0], size[1], 3), PAD_VALUE, dtype=image.dtype)
    out[:h, :w] = image
    return out


def to_network_input(images: np.ndarray) -> np.ndarray:
    """Padded RGB images (B, Hp, W, 3) uint8 -> float32 (B, 3, Hp, Wp) in [0, 255], the network input."""
    return np.ascontiguousarray(np.asarray(images, dtype=np.float32).transpose(0, 3, 1, 2))


def pixel_to_grid(uv: np.ndarray) -> np.ndarray:
    """Continuous grid coordinates of pixel coordinates (..., 2) px."""
    return (np.asarray(uv, dtype=np.float64) + 0.5) / STRIDE


def grid_to_pixel(g: np.ndarray) -> np.ndarray:
    """Pixel coordinates of continuous grid coordinates (..., 2): the inverse of pixel_to_grid."""
    return np.asarray(g, dtype=np.float64) * STRIDE - 0.5


def decode_numpy(heat: np.ndarray, offset: np.ndarray, radius: np.ndarray, top_k: int = 100,
                 min_score: float = 0.0, image_size: tuple[int, int] | None = None) -> list[np.ndarray]:
    """Circles from the heads: 3x3 max-pool peaks, the top_k best, in input pixels.

    heat: (B, 1, h, w) centre probabilities. offset: (B, 2, h, w) sub-cell (dx, dy), grid units.
    radius: (B, 1, h, w) grid units. image_size: (H, W) px; peaks in the padding are dropped.
    Returns per image an array (K, 4) of (cx, cy, r, score), px, by decreasing score.
    Same rule as ``model.decode`` (torch), which the tests compare with this one.
    """
    heat = np.asarray(heat, dtype=np.float32)
    b, _, h, w = heat.shape
    # a peak is a cell equal to the max of its 3x3 neighbourhood (the border padded with -inf)
    pooled = maximum_filter(heat, size=(1, 1, 3, 3), mode="constant", cval=-np.inf)
    peaks = np.where(heat == pooled, heat, 0.0).reshape(b, -1)
    if image_size is not None:  # cells whose centre pixel lies in the padding cannot hold a centre
        rows = grid_to_pixel(np.arange(h) + 0.5) <= image_size[0] - 0.5
        cols = grid_to_pixel(np.arange(w) + 0.5) <= image_size[1] - 0.5
        peaks *= (rows[:, None] & cols[None, :]).reshape(1, -1)
    k = min(top_k, h * w)
    out = []
    for i in range(b):
        idx = np.argpartition(-peaks[i], k - 1)[:k]
        idx = idx[np.argsort(-peaks[i][idx], kind="stable")]
        score = peaks[i][idx]
        idx, score = idx[score > min_score], score[score > min_score]
        ys, xs = np.divmod(idx, w)
        cx = grid_to_pixel(xs + offset[i, 0, ys, xs])
        cy = grid_to_pixel(ys + offset[i, 1, ys, xs])
        r = np.maximum(radius[i, 0, ys, xs], 0.0) * STRIDE
        out.append(np.stack([cx, cy, r, score], axis=1).astype(np.float64).reshape(-1, 4))
    return out
