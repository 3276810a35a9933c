"""The image contract of the CircleNet-style baseline, shared by training and inference (no torch).

- Input: the benchmark's ``image.png`` (the depth colourised), 8-bit, 3 channels, read as RGB.
- Camera normalisation: the model was trained on D435 frames at 424x240 (fx = 213 px); the
  D435's other modes (848x480, 1280x720: the same field of view) are scaled to that size by
  ``fit_image`` in training. At inference an image of any size and camera is scaled by
  training focal / its own focal (``focal_scale``, ``scale_image``), so that a ball at a given
  distance covers as many pixels as in training, and runs at that scaled size: the network is
  fully convolutional. Without the camera's focal length the image is assumed to have the
  training camera's field of view (scaled to the model's width).
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

from spherebench.camera import D435_FOCAL_PER_WIDTH
from spherebench.datasets import inout
from spherebench.errors import SphereBenchError

# The exported model's contract (onnx_export writes it, infer checks it), here so that inference
# imports no torch.
METADATA_KEY = "spherebench.circlenet"
#: Bumped when the input/output contract changes; infer.py refuses other versions.
FORMAT_VERSION = 1
INPUT_NAME = "image"
OUTPUT_NAMES = ("heat", "offset", "radius")

#: Output stride of the heads, pixels per grid cell.
STRIDE = 4
#: Network input sides must be multiples of this (stride 32 at the deepest level of both backbones).
SIZE_DIVISOR = 32
#: Value of the padding and of the border that augmentation exposes (black, as invalid depth).
PAD_VALUE = 0


#: Training: an image whose aspect ratio is within this fraction of the model's is scaled to fit it
#: (the D435's 424x240, 848x480 and 1280x720 modes); any other size is refused. Inference takes any size.
ASPECT_TOLERANCE = 0.02
#: Inference: the largest side (px) of the scaled network input; beyond it the run would need
#: gigabytes (a focal length in the wrong unit, or a panorama).
MAX_INPUT_SIDE_PX = 4096


def check_size(shape: tuple[int, ...], image_size: tuple[int, int], what: str = "the image") -> None:
    """Training: raise SphereBenchError unless an image of shape (h, w, ...) can go to a model
    trained at (H, W) px: the same size, or the same aspect ratio (then ``fit_image`` scales it)."""
    h, w = shape[:2]
    mh, mw = image_size
    if (h, w) != (mh, mw) and abs((w / h) / (mw / mh) - 1) > ASPECT_TOLERANCE:
        raise SphereBenchError(f"{what} is {w}x{h} px but the model is trained on {mw}x{mh} px images (or that "
                               "aspect ratio, scaled); train on images of one camera")


def load_image(path, expected_size: tuple[int, int] | None = None) -> np.ndarray:
    """Read a colourised depth image (image.png) as RGB uint8 (h, w, 3).

    expected_size: (H, W) px of a model being trained; an image of another aspect ratio is an error
    (inference takes any size: leave it None).
    """
    path = Path(path)
    if not path.is_file():
        raise SphereBenchError(f"image {path} not found")
    raw = inout.read_image_as_stored(path)
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


def training_focal_px(image_size: tuple[int, int]) -> float:
    """Focal length (px) of the training images: the D435's at the model's (H, W) size."""
    return D435_FOCAL_PER_WIDTH * image_size[1]


def focal_scale(shape: tuple[int, ...], image_size: tuple[int, int], focal_px: float | None = None,
                model_focal_px: float | None = None) -> float:
    """The factor that brings an image of shape (h, w, ...) to the training camera's focal length.

    focal_px: the image's own focal length (px; sqrt(fx * fy) for non-square pixels). None: the
    camera is taken to have the training camera's field of view, and the image is scaled to the
    model's width (exact for every D435 mode). model_focal_px: the training images' focal length
    (default ``training_focal_px(image_size)``).
    """
    if focal_px is None:
        return image_size[1] / shape[1]
    f = float(focal_px)
    if not (math.isfinite(f) and f > 0):
        raise SphereBenchError(f"the focal length must be a positive number of pixels, got {focal_px}")
    return (model_focal_px or training_focal_px(image_size)) / f


def scale_image(image: np.ndarray, scale: float) -> tuple[np.ndarray, tuple[float, float]]:
    """Scale an image (h, w, 3) by ``scale`` to (round(h s), round(w s)) px, nearest neighbour as
    ``fit_image``; returns it and the exact per-axis scales (sx, sy) of that whole-pixel size."""
    h, w = image.shape[:2]
    hh, ww = max(1, round(h * scale)), max(1, round(w * scale))
    if (hh, ww) == (h, w):
        return image, (1.0, 1.0)
    if max(hh, ww) > MAX_INPUT_SIDE_PX:
        raise SphereBenchError(f"the {w}x{h} px image scaled by {scale:.3g} to the training focal length would be "
                               f"{ww}x{hh} px (at most {MAX_INPUT_SIDE_PX}); is the focal length in pixels?")
    out = cv2.resize(image, (ww, hh), interpolation=cv2.INTER_NEAREST_EXACT)
    return out, (ww / w, hh / h)


def unscale_circles(circles: np.ndarray, sx: float, sy: float) -> np.ndarray:
    """Circles (N, 3+) in an image scaled by (sx, sy) (``scale_image``) -> the original image's px."""
    c = np.array(circles, dtype=np.float64, copy=True)
    c[:, 0] = (c[:, 0] + 0.5) / sx - 0.5
    c[:, 1] = (c[:, 1] + 0.5) / sy - 0.5
    c[:, 2] /= math.sqrt(sx * sy)
    return c


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
