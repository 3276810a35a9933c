"""The physical D435 sensor model: both infrared images rendered, depth by semi-global matching.

From the scene's primitives (the ray caster of ``primitives``), render what the D435's two
infrared imagers see: the left imager is the depth frame's camera, the right one ``baseline_m``
to its right (a rectified pair: same intrinsics, pure x offset). The emitter between them
projects a fixed pseudo-random dot pattern; a surface point's irradiance is the pattern where
the point projects into the emitter, times the cosine of the incidence angle, over the squared
distance, plus ambient infrared light; a point the emitter cannot see gets ambient only. Each
primitive has its own infrared albedo (Lambertian). The imager adds shot and read noise and
quantises to 10 bits. OpenCV's ``StereoSGBM`` matches the pair (subpixel, left-right check,
speckle filter) over the D435's disparity search range; depth = f B / d in the unit's depth
counts, 0 where invalid. No noise formula is added on top: the depth noise, its correlation,
edge fattening, flying pixels, the occlusion band and holes are the matcher's.

The dot pattern is the unit's hardware: the default pattern is the package file
``d435_pattern.npz``, drawn once by ``draw_pattern`` from its seed, so that it stays the same
whatever numpy's generators do later; another seed or dot count is drawn at run time.
"""

from __future__ import annotations

import functools
import io
import math
from collections.abc import Mapping
from dataclasses import dataclass, field, fields, replace
from pathlib import Path

import cv2
import numpy as np
from scipy.special import ndtr

from spherebench.camera import Intrinsics, image_rays
from spherebench.datasets.outputs import atomic_write_bytes
from spherebench.datasets.primitives import CURVED, Box, Cylinder, Plane, SolidSphere, raycast
from spherebench.errors import SphereBenchError

#: The shipped pattern (``draw_pattern(PATTERN_SEED, PATTERN_DOTS)``).
PATTERN_FILE = Path(__file__).with_name("d435_pattern.npz")
PATTERN_SEED = 435
PATTERN_DOTS = 5000
#: 10-bit imager counts.
FULL_SCALE = 1023
#: OpenCV's StereoSGBM modes by name.
SGBM_MODES = {"sgbm": cv2.STEREO_SGBM_MODE_SGBM, "hh": cv2.STEREO_SGBM_MODE_HH,
              "hh4": cv2.STEREO_SGBM_MODE_HH4}
#: Fewest pattern dots a matching window must hold on average. SGM's smoothing fills a wall
#: between sparse dots, but measured at 848x480 with 9x9 windows: 0.17 dots a window (700 dots)
#: gives gross mismatches at 4 m and a disparity noise of 0.3 px at every range.
MIN_DOTS_PER_WINDOW = 0.2
#: A point is lit when the emitter's ray there reaches this close (relative depth) to it.
LIT_TOLERANCE = 0.005
#: Steps of the auto-exposure loop (each: exposure x target / mean); 8 settle within 1 %.
AE_STEPS = 8
#: Gaussian smoothing (px) of the pair before the subpixel refinement.
REFINE_BLUR_PX = 0.8


def _param(default, lo, hi, doc: str, kind: str = "scalar"):
    """A stereo parameter: default, valid range [lo, hi] (each value of a pair), meaning and source."""
    return field(default=default, metadata={"range": (lo, hi), "doc": doc, "kind": kind})


@dataclass(frozen=True)
class StereoSensor:
    """The D435 as rendered infrared stereo plus semi-global matching (metres, pixels, electrons).

    Signals are in electrons per millisecond of exposure for a white (albedo 1) Lambertian
    surface facing the emitter 1 m away; a pixel's value is the mean irradiance over its
    footprint (the pattern is integrated over each pixel box at the stream's resolution).
    Matcher lengths (block, speckle window) are pixels of the stream.
    """

    # geometry
    baseline_m: float = _param(0.050, 0.01, 0.5, "left-right imager distance, m (D435 datasheet: 50 mm)")
    emitter_x_m: float = _param(0.025, -0.1, 0.6, "emitter's x from the left imager, m (between the imagers: "
                                "Intel projector white paper, Fig. 1; the middle assumed)")
    emitter_hfov_deg: float = _param(86.0, 30.0, 120.0, "emitter horizontal field of projection, deg (D435: 86 +-3)")
    emitter_vfov_deg: float = _param(57.0, 20.0, 100.0, "emitter vertical field of projection, deg (D435: 57 +-3)")
    # the pattern
    pattern_dots: int = _param(PATTERN_DOTS, 100, 200_000, "dots over the field of projection "
                               "(D435: ~5000, Intel projector white paper)", "int")
    pattern_seed: int = _param(PATTERN_SEED, 0, 2 ** 31 - 1, "seed of the dot positions (the default: the "
                               "shipped pattern file)", "int")
    dot_sigma_mrad: float = _param(1.2, 0.05, 10.0, "a dot's Gaussian radius (sigma), mrad, with the lens blur "
                                   "(calibrated: dots ~2 px wide at 848x480)")
    dot_power_spread: float = _param(0.2, 0.0, 1.0, "relative RMS of the dots' powers (VCSEL emitters differ)")
    # light
    dot_peak_e_per_ms: float = _param(1500.0, 0.0, 1e6, "a dot's peak signal, e-/ms (calibrated)")
    ambient_e_per_ms: float = _param(40.0, 0.0, 1e6, "ambient infrared signal, e-/ms (indoor, calibrated)")
    albedo: tuple[float, float] = _param((0.3, 0.9), 0.0, 1.0, "infrared albedo range, each primitive's "
                                         "drawn uniformly (indoor surfaces at 850 nm)", "pair")
    # imager (OmniVision OV2740-class global shutter)
    exposure_ms: float = _param(8.5, 0.02, 166.0, "exposure without auto-exposure, ms (librealsense's 8500 us)")
    auto_exposure: bool = _param(True, 0, 1, "set the exposure per frame from the left image's mean "
                                 "(the D435's default)", "bool")
    ae_mean_counts: float = _param(400.0, 10.0, 1000.0, "auto-exposure's target mean, 10-bit counts "
                                   "(librealsense advanced mode meanIntensitySetPoint, 400)")
    ae_max_exposure_ms: float = _param(33.0, 0.02, 166.0, "auto-exposure's longest exposure, ms (a 30 fps frame)")
    gain: float = _param(1.0, 1.0, 16.0, "analogue gain, x (D435 gain 16 = 1x, Intel tuning paper)")
    counts_per_e: float = _param(0.25, 1e-3, 10.0, "10-bit counts per electron at gain 1 (full well ~4000 e-)")
    read_noise_e: float = _param(4.0, 0.0, 100.0, "read noise, e- RMS (typical of the class)")
    # matcher (OpenCV StereoSGBM)
    block_size_px: int = _param(9, 3, 21, "matching window side, px, odd (calibrated)", "int")
    p1: float = _param(8.0, 0.0, 1000.0, "SGBM penalty of a 1-px disparity change, per window pixel "
                       "(P1 = p1 x block^2; OpenCV's suggestion 8)")
    p2: float = _param(32.0, 0.0, 4000.0, "SGBM penalty of a larger change, per window pixel (> p1; OpenCV: 32)")
    uniqueness_ratio: int = _param(10, 0, 100, "% by which the best cost must beat the second (5-15 usual)", "int")
    speckle_window_px: int = _param(100, 0, 10000, "largest speckle region removed, px (0 = off)", "int")
    speckle_range_px: int = _param(1, 0, 64, "disparity spread within a speckle region, px", "int")
    disp12_max_diff_px: int = _param(1, -1, 64, "left-right check tolerance, px (-1 = off)", "int")
    pre_filter_cap: int = _param(31, 1, 63, "x-derivative clip of SGBM's prefilter", "int")
    mode: str = _param("sgbm", 0, 0, "SGBM mode: sgbm (5 paths), hh (8 paths) or hh4", "choice")
    refine_iterations: int = _param(1, 0, 10, "Gauss-Newton steps of subpixel refinement on the 10-bit pair "
                                    "(0 = SGBM's own parabola, which locks to whole pixels)", "int")
    disparity_range_px: int = _param(126, 16, 256, "disparities searched (D4 ASIC: 126; MinZ = f B / 126, "
                                     "Intel tuning paper)", "int")
    disparity_shift_px: int = _param(0, 0, 512, "the search's first disparity, px (Intel's disparity shift)", "int")
    # output
    depth_scale_m: float = _param(0.001, 1e-4, 0.01, "metres per z16 count (the D435's 1 mm)")
    min_depth_m: float = _param(0.11, 0.0, 5.0, "nearest valid depth, m")
    max_depth_m: float = _param(10.0, 0.2, 65.0, "farthest valid depth, m (D435: ~10 m)")

    def __post_init__(self) -> None:
        for f in fields(self):
            _check(f, getattr(self, f.name))
        if self.p2 <= self.p1:
            raise SphereBenchError(f"stereo sensor p2={self.p2:g} must exceed p1={self.p1:g} "
                                   "(SGBM penalises large disparity jumps more than 1-px steps)")
        if self.min_depth_m >= self.max_depth_m:
            raise SphereBenchError(f"stereo sensor min_depth_m={self.min_depth_m:g} must be below "
                                   f"max_depth_m={self.max_depth_m:g} (the valid depth range would be empty)")

    def to_dict(self) -> dict:
        return {f.name: list(v) if isinstance(v := getattr(self, f.name), tuple) else v for f in fields(self)}


STEREO_PARAMETERS = {f.name: f for f in fields(StereoSensor)}


def check_stereo_ranges(ranges: Mapping, where: str = "stereo sensor ranges") -> None:
    """One-line SphereBenchError unless every entry of ``ranges`` (parameter -> (lo, hi)) names a
    numeric stereo parameter and both bounds are valid values of it, lo <= hi."""
    for name, value in ranges.items():
        f = STEREO_PARAMETERS.get(name)
        if f is None or f.metadata["kind"] not in ("scalar", "int"):
            raise SphereBenchError(f"{where}: {name!r} is not a numeric stereo parameter; use one of "
                                   + ", ".join(n for n, g in STEREO_PARAMETERS.items()
                                               if g.metadata["kind"] in ("scalar", "int")))
        if not (isinstance(value, tuple) and len(value) == 2 and value[0] <= value[1]):
            raise SphereBenchError(f"{where}: {name}={value!r} must be a range (LO, HI) with LO <= HI")
        for x in value:
            _check(f, x)


def draw_stereo(base: StereoSensor, ranges: Mapping, rng: np.random.Generator) -> StereoSensor:
    """``base`` with each parameter of ``ranges`` (parameter -> (lo, hi)) drawn uniformly from
    ``rng``, in the dataclass's field order (an integer parameter rounded), so that the draws
    depend only on the ranges and the rng; the result is checked as any StereoSensor."""
    changes = {}
    for name, f in STEREO_PARAMETERS.items():
        if name in ranges:
            lo, hi = ranges[name]
            x = lo if lo == hi else float(rng.uniform(lo, hi))
            changes[name] = int(round(x)) if f.metadata["kind"] == "int" else x
    return replace(base, **changes)


def _check(f, value) -> None:
    """One-line SphereBenchError unless ``value`` suits parameter ``f``'s kind and range."""
    meta = f.metadata
    kind, (lo, hi) = meta["kind"], meta["range"]
    bad = SphereBenchError(f"stereo sensor {f.name}={value!r}: must be "
                           + ({"choice": f"one of {', '.join(SGBM_MODES)}",
                               "pair": f"a range (LO, HI) with {lo:g} <= LO <= HI <= {hi:g}",
                               "bool": "True or False"}.get(kind)
                              or f"{'an integer' if kind == 'int' else 'a number'} from {lo:g} to {hi:g}")
                           + f" ({meta['doc']})")
    if kind == "choice":
        if value not in SGBM_MODES:
            raise bad
        return
    if kind == "bool":
        if not isinstance(value, (bool, np.bool_)):
            raise bad
        return
    values = tuple(value) if kind == "pair" and isinstance(value, (tuple, list)) and len(value) == 2 else (value,)
    if kind == "pair" and len(values) != 2:
        raise bad
    for x in values:
        number = isinstance(x, (int, np.integer)) if kind == "int" else isinstance(x, (int, float, np.floating, np.integer))
        if isinstance(x, (bool, np.bool_)) or not number or not math.isfinite(x) or not lo <= x <= hi:
            raise bad
    if kind == "pair" and values[0] > values[1]:
        raise bad
    if f.name == "block_size_px" and value % 2 == 0:
        raise bad


# --------------------------------------------------------------------------- the dot pattern

def draw_pattern(seed: int, n_dots: int) -> np.ndarray:
    """(n_dots, 3) float64: each dot's position in the emitter's field as fractions (0-1) of its
    width and height, and its relative power (mean 1 before ``dot_power_spread`` scales it).

    Jittered on a grid of about square cells, one dot per cell in a random order of cells, as
    a VCSEL array's emitters keep apart: no two dots merge and no window is far emptier than
    the mean (a uniform draw leaves holes of several mean spacings)."""
    rng = np.random.default_rng([int(seed), int(n_dots)])
    cols = max(1, round(math.sqrt(n_dots * 1.5)))  # about the 86 x 57 deg field's aspect
    rows = math.ceil(n_dots / cols)
    cells = rng.permutation(rows * cols)[:n_dots]
    jitter = rng.random((n_dots, 2))
    x = (cells % cols + jitter[:, 0]) / cols
    y = (cells // cols + jitter[:, 1]) / rows
    return np.stack([x, y, rng.standard_normal(n_dots)], axis=1)


def write_pattern_file(path: Path = PATTERN_FILE) -> None:
    """Write the shipped pattern, atomically (``make pattern``; the file is part of the package, and a
    test checks that it holds what its seed draws)."""
    buf = io.BytesIO()
    np.savez_compressed(buf, dots=draw_pattern(PATTERN_SEED, PATTERN_DOTS), seed=PATTERN_SEED)
    atomic_write_bytes(path, buf.getvalue())


@functools.lru_cache(maxsize=8)
def pattern_dots(seed: int, n_dots: int) -> np.ndarray:
    """The dots of a pattern: the shipped file's for its seed and count, else ``draw_pattern``."""
    if (seed, n_dots) == (PATTERN_SEED, PATTERN_DOTS):
        with np.load(PATTERN_FILE) as f:
            return f["dots"]
    return draw_pattern(seed, n_dots)


@dataclass(frozen=True)
class _Emitter:
    """The emitter as a pinhole projector at the stream's focal length: texture and cast grid."""

    intr: Intrinsics          # its ray-cast grid (one texel = one camera pixel), optical axis +z
    texture: np.ndarray       # (H, W) float64: mean dot irradiance over each texel, dot peak = 1
    oversample: int           # texture texels per grid pixel


def _emitter(sensor: StereoSensor, fx_px: float, fy_px: float) -> _Emitter:
    return _emitter_of(sensor.pattern_seed, sensor.pattern_dots, sensor.dot_sigma_mrad, sensor.dot_power_spread,
                       sensor.emitter_hfov_deg, sensor.emitter_vfov_deg, fx_px, fy_px)


@functools.lru_cache(maxsize=8)
def _emitter_of(seed: int, n_dots: int, sigma_mrad: float, spread: float, hfov_deg: float, vfov_deg: float,
                fx_px: float, fy_px: float) -> _Emitter:
    half_w = fx_px * math.tan(math.radians(hfov_deg) / 2)
    half_h = fy_px * math.tan(math.radians(vfov_deg) / 2)
    w, h = 2 * math.ceil(half_w) + 1, 2 * math.ceil(half_h) + 1
    intr = Intrinsics(width=w, height=h, ppx=(w - 1) / 2, ppy=(h - 1) / 2, fx=fx_px, fy=fy_px)
    k = 2  # texels a grid pixel: bilinear sampling then blurs the pixel-box integral only a little
    dots = pattern_dots(seed, n_dots)
    power = np.clip(1.0 + spread * dots[:, 2], 0.0, None)
    # dot centres in texels, the texel (i, j) covering [i - 0.5, i + 0.5) / k of grid pixels
    cu = (intr.ppx - half_w + 2 * half_w * dots[:, 0] + 0.5) * k - 0.5
    cv_ = (intr.ppy - half_h + 2 * half_h * dots[:, 1] + 0.5) * k - 0.5
    sx, sy = sigma_mrad * 1e-3 * fx_px * k, sigma_mrad * 1e-3 * fy_px * k
    reach = int(math.ceil(4 * max(sx, sy) + 1.5))
    offs = np.arange(-reach, reach + 1)
    iu, iv = np.round(cu).astype(np.int64)[:, None] + offs, np.round(cv_).astype(np.int64)[:, None] + offs
    # each texel holds the mean, over a camera pixel's box (k texels a side) centred on it, of
    # the dots' Gaussians of peak 1: sampled at a point, it is that pixel's mean irradiance
    half = 0.5 * k
    ax = (ndtr((iu + half - cu[:, None]) / sx) - ndtr((iu - half - cu[:, None]) / sx)) * sx * math.sqrt(2 * math.pi) / k
    ay = (ndtr((iv + half - cv_[:, None]) / sy) - ndtr((iv - half - cv_[:, None]) / sy)) * sy * math.sqrt(2 * math.pi) / k
    tex = np.zeros((h * k, w * k))
    vals = power[:, None, None] * ay[:, :, None] * ax[:, None, :]
    ok = (iv[:, :, None] >= 0) & (iv[:, :, None] < h * k) & (iu[:, None, :] >= 0) & (iu[:, None, :] < w * k)
    rows = np.broadcast_to(iv[:, :, None], vals.shape)[ok]
    cols = np.broadcast_to(iu[:, None, :], vals.shape)[ok]
    np.add.at(tex, (rows, cols), vals[ok])
    return _Emitter(intr, tex, k)


# --------------------------------------------------------------------------- rendering

def _shifted(obj, offset_m: np.ndarray):
    """The primitive in the frame of a camera at ``offset_m`` (same orientation)."""
    name = {Plane: "point_m", SolidSphere: "centre_m", Box: "centre_m", Cylinder: "base_m"}[type(obj)]
    return replace(obj, **{name: np.asarray(getattr(obj, name), np.float64) - offset_m})


def _normals(obj, points_m: np.ndarray) -> np.ndarray:
    """(N, 3) unit surface normals (either sign) at points on the primitive."""
    if isinstance(obj, Plane):
        n = np.broadcast_to(np.asarray(obj.normal, np.float64), points_m.shape)
    elif isinstance(obj, SolidSphere):
        n = points_m - np.asarray(obj.centre_m, np.float64)
    elif isinstance(obj, Box):
        face = obj.planar_face(points_m)
        n = np.asarray(obj.rotation, np.float64).T[face // 2]
    else:
        a = np.asarray(obj.axis, np.float64) / np.sqrt(np.sum(np.square(obj.axis)))
        rel = points_m - np.asarray(obj.base_m, np.float64)
        radial = rel - (rel @ a)[:, None] * a
        n = np.where((obj.planar_face(points_m) == CURVED)[:, None], radial, a)
    return n / np.maximum(np.linalg.norm(n, axis=1), 1e-12)[:, None]


def _bilinear(img: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """img sampled at (u, v) (column, row, texel centres at integers), 0 outside."""
    h, w = img.shape
    u0, v0 = np.floor(u).astype(np.int64), np.floor(v).astype(np.int64)
    fu, fv = u - u0, v - v0
    out = np.zeros(u.shape)
    for du, dv, wt in ((0, 0, (1 - fu) * (1 - fv)), (1, 0, fu * (1 - fv)), (0, 1, (1 - fu) * fv), (1, 1, fu * fv)):
        uu, vv = u0 + du, v0 + dv
        ok = (uu >= 0) & (uu < w) & (vv >= 0) & (vv < h)
        out[ok] += wt[ok] * img[vv[ok], uu[ok]]
    return out


def _irradiance(objects: list, z_m: np.ndarray, label: np.ndarray, rays: np.ndarray, origin_m: np.ndarray,
                sensor: StereoSensor, emitter: _Emitter, lit_z: np.ndarray, albedo: np.ndarray,
                textures: list | None = None) -> np.ndarray:
    """(H, W) signal, e- per ms, of the imager at ``origin_m`` (left imager's frame) seeing z, label.
    textures: per primitive, a ``primitives.Texture`` whose factor multiplies its albedo, or None."""
    out = np.zeros(z_m.shape)
    hit = label > 0
    if not hit.any():
        return out
    p = rays[hit] * z_m[hit][:, None] + origin_m  # points, left imager's frame
    lab = label[hit] - 1
    e = np.array([sensor.emitter_x_m, 0.0, 0.0])
    to_e = e - p
    dist2 = np.einsum("ij,ij->i", to_e, to_e)
    normals = np.empty_like(p)
    for k in np.unique(lab):
        sel = lab == k
        normals[sel] = _normals(objects[k], p[sel])
    cos = np.abs(np.einsum("ij,ij->i", normals, to_e)) / np.sqrt(dist2)
    # where the point lands in the emitter's grid, and whether the emitter sees it there
    ei = emitter.intr
    ue = ei.ppx + ei.fx * (p[:, 0] - e[0]) / p[:, 2]
    ve = ei.ppy + ei.fy * p[:, 1] / p[:, 2]
    # lit where one of the four grid rays around the point reaches it (a slanted surface's depth
    # changes across a grid pixel; a shadow edge moves by under half a pixel)
    u0, v0 = np.floor(ue).astype(np.int64), np.floor(ve).astype(np.int64)
    lit = np.zeros(len(p), bool)
    for du in (0, 1):
        for dv in (0, 1):
            uu, vv = u0 + du, v0 + dv
            inside = (uu >= 0) & (uu < ei.width) & (vv >= 0) & (vv < ei.height)
            lit[inside] |= lit_z[vv[inside], uu[inside]] >= p[inside, 2] * (1 - LIT_TOLERANCE)
    k = emitter.oversample
    dots = _bilinear(emitter.texture, (ue + 0.5) * k - 0.5, (ve + 0.5) * k - 0.5)
    signal = np.where(lit, sensor.dot_peak_e_per_ms * dots * cos / dist2, 0.0) + sensor.ambient_e_per_ms
    reflect = albedo[lab]
    for k, texture in enumerate(textures or ()):
        if texture is not None and (sel := lab == k).any():
            reflect[sel] *= texture.factor(p[sel])  # of the left frame's point: the same on both imagers
    out[hit] = reflect * signal
    return out


def exposure_ms(left_signal_e_per_ms: np.ndarray, sensor: StereoSensor) -> float:
    """The frame's exposure: fixed, or auto-exposure's, which brings the left image's mean (noise
    free, clipped at full scale as the imager clips) to ae_mean_counts within [0.02 ms,
    ae_max_exposure_ms], as the camera's loop settles over frames; both imagers share it."""
    if not sensor.auto_exposure:
        return sensor.exposure_ms
    counts_per_ms = left_signal_e_per_ms * (sensor.counts_per_e * sensor.gain)
    exposure = sensor.ae_max_exposure_ms
    for _ in range(AE_STEPS):
        mean = float(np.mean(np.minimum(counts_per_ms * exposure, FULL_SCALE)))
        if mean <= 0:
            break
        exposure = min(max(exposure * sensor.ae_mean_counts / mean, 0.02), sensor.ae_max_exposure_ms)
    return exposure


def _expose(signal_e_per_ms: np.ndarray, exposure: float, sensor: StereoSensor, rng: np.random.Generator) -> np.ndarray:
    """Electrons per ms -> 10-bit counts (uint16) over ``exposure`` ms: shot noise (Gaussian
    approximation of the Poisson count), read noise, gain, rounding and clipping to the full scale."""
    e = signal_e_per_ms * exposure
    noisy = e + np.sqrt(e) * rng.standard_normal(e.shape) + sensor.read_noise_e * rng.standard_normal(e.shape)
    counts = np.round(noisy * sensor.counts_per_e * sensor.gain)
    return np.clip(counts, 0, FULL_SCALE).astype(np.uint16)


@dataclass
class StereoFrame:
    """What the stereo model made of a scene: both infrared images (10-bit counts), the left
    imager's disparity (px, NaN = invalid) and depth (uint16 counts, 0 = invalid)."""

    left_ir: np.ndarray
    right_ir: np.ndarray
    disparity_px: np.ndarray
    depth: np.ndarray


def check_stereo(sensor: StereoSensor, intr: Intrinsics) -> None:
    """One-line SphereBenchError when ``sensor`` cannot work at this stream: its disparity search
    cannot reach the valid depth range, or its pattern is too sparse for the matching window."""
    fb = intr.fx * sensor.baseline_m
    near = fb / (sensor.disparity_shift_px + sensor.disparity_range_px)
    far = fb / sensor.disparity_shift_px if sensor.disparity_shift_px else math.inf
    if near > sensor.max_depth_m or far < sensor.min_depth_m:
        raise SphereBenchError(
            f"stereo sensor at {intr.width}x{intr.height}: disparities {sensor.disparity_shift_px}-"
            f"{sensor.disparity_shift_px + sensor.disparity_range_px} px see depths {near:.3g}-{far:.3g} m, "
            f"outside the valid range {sensor.min_depth_m:g}-{sensor.max_depth_m:g} m: "
            "lower disparity_shift_px or widen min_depth_m/max_depth_m")
    field_px = (2 * intr.fx * math.tan(math.radians(sensor.emitter_hfov_deg) / 2)
                * 2 * intr.fy * math.tan(math.radians(sensor.emitter_vfov_deg) / 2))
    per_window = sensor.pattern_dots * sensor.block_size_px ** 2 / field_px
    if per_window < MIN_DOTS_PER_WINDOW:
        raise SphereBenchError(
            f"stereo sensor at {intr.width}x{intr.height}: {sensor.pattern_dots} dots give {per_window:.2f} "
            f"per {sensor.block_size_px}x{sensor.block_size_px} matching window (at least "
            f"{MIN_DOTS_PER_WINDOW:g} needed to match a textureless wall): raise pattern_dots or block_size_px")


def _objects(scene) -> list:
    return [it.shape for it in scene.items] if hasattr(scene, "items") else list(scene)


def _surfaces(scene, albedo: np.ndarray) -> tuple[np.ndarray, list | None]:
    """The albedo per primitive (an item's own where it sets one, else the drawn ``albedo``) and the
    textures per primitive (None for a list of primitives)."""
    if not hasattr(scene, "items"):
        return albedo, None
    own = np.array([np.nan if it.albedo is None else it.albedo for it in scene.items])
    return np.where(np.isnan(own), albedo, own), [it.texture for it in scene.items]


def stereo_frame(scene, intr: Intrinsics, sensor: StereoSensor, rng: np.random.Generator,
                 rays: np.ndarray | None = None) -> StereoFrame:
    """Render a layout (or a list of primitives) through the stereo model (``stereo_depth``)."""
    check_stereo(sensor, intr)
    if intr.has_distortion:
        raise SphereBenchError("the stereo model renders a rectified pair: give intrinsics without distortion")
    objects = _objects(scene)
    if rays is None:
        rays = image_rays(intr)
    right_at = np.array([sensor.baseline_m, 0.0, 0.0])
    emitter = _emitter(sensor, float(intr.fx), float(intr.fy))
    e_at = np.array([sensor.emitter_x_m, 0.0, 0.0])
    lit_z, _ = raycast([_shifted(o, e_at) for o in objects], _rays(emitter.intr), emitter.intr)
    albedo, textures = _surfaces(scene, rng.uniform(*sensor.albedo, size=len(objects)))
    signals = []
    for origin in (np.zeros(3), right_at):
        z, label = raycast([_shifted(o, origin) for o in objects] if origin.any() else objects, rays, intr)
        signals.append(_irradiance(objects, z, label, rays, origin, sensor, emitter, lit_z, albedo, textures))
    exposure = exposure_ms(signals[0], sensor)
    images = [_expose(signal, exposure, sensor, rng) for signal in signals]
    disparity = match(images[0], images[1], sensor)
    fb = intr.fx * sensor.baseline_m
    with np.errstate(divide="ignore", invalid="ignore"):
        z = fb / disparity
    valid = np.isfinite(z) & (z >= sensor.min_depth_m) & (z <= sensor.max_depth_m)
    counts = np.round(np.where(valid, z, 0.0) / sensor.depth_scale_m)
    depth = np.clip(counts, 0, np.iinfo(np.uint16).max).astype(np.uint16)
    return StereoFrame(images[0], images[1], disparity, depth)


def stereo_depth(scene, intr: Intrinsics, sensor: StereoSensor, rng: np.random.Generator,
                 rays: np.ndarray | None = None) -> np.ndarray:
    """A layout (``layouts.Layout``) or a list of primitives -> D435 depth (H, W) uint16 counts of
    ``sensor.depth_scale_m``, 0 = invalid: the contract of ``sensor.apply_sensor`` on the ray-cast
    depth. Draws, in order, one albedo per primitive and the two images' noise from ``rng``; a
    layout's item that sets its own albedo keeps it (its draw is made all the same), its texture
    multiplies it."""
    return stereo_frame(scene, intr, sensor, rng, rays).depth


@functools.lru_cache(maxsize=4)
def _rays(intr: Intrinsics) -> np.ndarray:
    return image_rays(intr)


def match(left: np.ndarray, right: np.ndarray, sensor: StereoSensor) -> np.ndarray:
    """Disparity (H, W) float64 px of the left image (NaN = invalid) by OpenCV's StereoSGBM on the
    8 most significant of the 10 bits. Both images are padded on the left by the search range, so
    that the matcher searches every column; a match that falls outside the right image is invalid."""
    h, w = left.shape
    n_disp = 16 * math.ceil((sensor.disparity_range_px + 1) / 16)  # OpenCV's multiple of 16
    pad = sensor.disparity_shift_px + n_disp
    eight = [cv2.copyMakeBorder((im >> 2).astype(np.uint8), 0, 0, pad, 0, cv2.BORDER_CONSTANT, value=0)
             for im in (left, right)]
    area = sensor.block_size_px ** 2
    sgbm = cv2.StereoSGBM_create(
        minDisparity=sensor.disparity_shift_px, numDisparities=n_disp, blockSize=sensor.block_size_px,
        P1=int(round(sensor.p1 * area)), P2=int(round(sensor.p2 * area)), disp12MaxDiff=sensor.disp12_max_diff_px,
        preFilterCap=sensor.pre_filter_cap, uniquenessRatio=sensor.uniqueness_ratio,
        speckleWindowSize=sensor.speckle_window_px, speckleRange=sensor.speckle_range_px,
        mode=SGBM_MODES[sensor.mode])
    raw = sgbm.compute(eight[0], eight[1])[:, pad:]
    d = raw.astype(np.float64) / 16.0
    cols = np.arange(w)[None, :]
    ok = (raw > 16 * sensor.disparity_shift_px) & (d <= sensor.disparity_shift_px + sensor.disparity_range_px) \
        & (cols - d >= -0.5)
    d = np.where(ok, d, np.nan)
    return refine(left, right, d, sensor.block_size_px, sensor.refine_iterations)


def refine(left: np.ndarray, right: np.ndarray, disparity_px: np.ndarray, block_px: int, iterations: int) -> np.ndarray:
    """Subpixel disparity by Gauss-Newton steps on the window's squared differences: each step
    moves d by -sum(r g) / sum(g^2) over the block, r = L(u) - R(u - d) and g = dR/du at u - d
    (R sampled linearly). SGBM's parabola through three aggregated costs snaps d to whole pixels
    (measured: up to 0.35 px off on a flat wall); the D4 ASIC's subpixel has no such lock. Steps
    are clipped to half a pixel: SGBM's whole-pixel answer stays the match."""
    if iterations == 0:
        return disparity_px
    h, w = left.shape
    # both images smoothed a little: the linear interpolation of sharp dots would pull d to whole pixels
    lf, rf = (cv2.GaussianBlur(im.astype(np.float64), (0, 0), REFINE_BLUR_PX) for im in (left, right))
    valid = np.isfinite(disparity_px)
    d0 = np.where(valid, disparity_px, 0.0)
    d = d0.copy()
    rows = np.arange(h)[:, None]
    sigma = block_px / 4.0  # Gaussian window of about the block's extent
    for _ in range(iterations):
        x = np.arange(w)[None, :] - d
        x0 = np.clip(np.floor(x).astype(np.int64), 0, w - 2)
        f = np.clip(x - x0, 0.0, 1.0)
        a, b = rf[rows, x0], rf[rows, x0 + 1]
        g = np.where(valid, b - a, 0.0)  # the derivative of the linear interpolant
        res = np.where(valid, lf - ((1 - f) * a + f * b), 0.0)
        num = cv2.GaussianBlur(res * g, (0, 0), sigma, borderType=cv2.BORDER_REPLICATE)
        den = cv2.GaussianBlur(g * g, (0, 0), sigma, borderType=cv2.BORDER_REPLICATE)
        with np.errstate(divide="ignore", invalid="ignore"):
            step = np.where(den > 0, num / den, 0.0)
        d = np.clip(d - step, d0 - 1.0, d0 + 1.0)
    return np.where(valid, d, np.nan)
