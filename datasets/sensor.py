"""The D435 depth sensor model: what the camera makes of the true depth of a scene.

All parameters live in ``D435Sensor``, with the D435's values as defaults (METHOD_NOTES.md):
- depth noise, Intel's stereo RMS model: sigma_z = z^2 * subpixel / (f_px * baseline), with
  f_px the focal length at the stream's resolution (so 424x240 is noisier than 1280x720);
  optionally spatially correlated (the stereo matcher's window), the per-pixel RMS unchanged;
- the invalid "shadow" band left of foreground objects: background the right imager cannot see
  (the depth is in the left imager's frame, the right imager is ``baseline_m`` to its right);
- flying pixels at depth edges: depths between the foreground and the background;
- holes: isolated invalid pixels and small invalid blobs;
- optionally low-texture dropouts: smooth invalid blobs over a share of some planar surfaces;
- optionally a depth scale error and bias (an uncalibrated unit);
- valid range limits, and 1 mm quantisation (z16 counts of depth_scale), invalid = 0.

The newer parameters' defaults are off, and off draws nothing from the generator: the nominal
sensor makes the same frames, bit for bit, as the model had before them. ``SensorRanges`` says
how a preset draws each scene's sensor (fixed values, per-scene ranges, a grid of conditions).

Pixel lengths of the newer parameters (correlation, blob scale) are given at 424 pixels wide and
scale with the stream's width: the matcher's window covers the same part of the scene.
"""

from __future__ import annotations

import difflib
import itertools
import math
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field, fields, replace

import cv2
import numpy as np

from spherebench.camera import Intrinsics
from spherebench.errors import SphereBenchError

#: Width (px) at which the newer pixel-length parameters are given.
REFERENCE_WIDTH_PX = 424


def _param(default, lo: float, hi: float, doc: str, kind: str = "scalar", new: bool = False):
    """A sensor parameter: default, valid range [lo, hi], meaning; kind scalar (a range may be
    drawn per scene), pair (its value is itself a (lo, hi) range) or bool."""
    return field(default=default, metadata={"range": (lo, hi), "doc": doc, "kind": kind, "new": new})


@dataclass(frozen=True)
class D435Sensor:
    """Sensor parameters (metres, pixels, probabilities); defaults are the D435's, newer features off.

    correlation_px: the depth noise's correlation length: the lag (pixels, any direction) at which
        the autocorrelation of the noise falls to 1/e; the noise's autocorrelation at lag d is
        exp(-(d / length)^2). Given at 424 px wide, scaled by width / 424. 0 = independent pixels.
    dropout_probability, dropout_fraction, dropout_blob_px: each planar surface (a wall, the floor,
        a face of a box, a cylinder's cap) is low-texture with this probability; the stereo matcher
        then fails on this fraction of its visible pixels, in smooth blobs: the upper tail of a
        smooth Gaussian field whose correlation length is dropout_blob_px (at 424 px wide).
        Curved surfaces never drop out; the ball (target spheres) only with dropout_ball.
    depth_scale_error, depth_bias_m: the depth reads z (1 + depth_scale_error) + depth_bias_m
        (0.003 = 3 mm per metre too far).
    """

    baseline_m: float = _param(0.050, 0.01, 0.5, "stereo baseline, m")
    subpixel: float = _param(0.08, 0.0, 1.0, "disparity RMS error, px; 0.05-0.1 typical")
    depth_scale_m: float = _param(0.001, 1e-4, 0.01, "metres per z16 count")
    min_depth_m: float = _param(0.11, 0.0, 5.0, "nearest valid depth, m")
    max_depth_m: float = _param(10.0, 0.2, 65.0, "farthest valid depth, m")
    shadow: bool = _param(True, 0, 1, "invalidate the occlusion band left of foreground edges", "bool")
    flying_edge_jump: float = _param(0.05, 1e-3, 1.0, "relative depth jump that makes an edge")
    flying_probability: float = _param(0.3, 0.0, 1.0, "chance that an edge pixel becomes a flying pixel")
    hole_probability: float = _param(0.003, 0.0, 0.5, "share of isolated invalid pixels")
    hole_blobs_per_mpx: float = _param(40.0, 0.0, 10000.0, "small invalid blobs per million pixels")
    hole_blob_radius_px: tuple[float, float] = _param((1.0, 4.0), 0.0, 50.0, "hole blob radii, px", "pair")
    flying_mix: tuple[float, float] = _param(
        (0.1, 0.9), 0.0, 1.0, "a flying pixel's depth lies this share of the way to the background, "
        "uniform in the range", "pair", new=True)
    correlation_px: float = _param(0.0, 0.0, 20.0, "noise correlation length, px at 424 wide: the lag where the autocorrelation is 1/e", new=True)
    dropout_probability: float = _param(0.0, 0.0, 1.0, "chance that a planar surface is low-texture", new=True)
    dropout_fraction: float = _param(0.3, 0.0, 1.0, "share of a low-texture surface that drops out", new=True)
    dropout_blob_px: float = _param(8.0, 1.0, 60.0, "dropout blob scale, px at 424 wide", new=True)
    dropout_ball: bool = _param(False, 0, 1, "the ball may be low-texture too", "bool", new=True)
    depth_scale_error: float = _param(0.0, -0.05, 0.05, "relative depth scale error", new=True)
    depth_bias_m: float = _param(0.0, -0.1, 0.1, "depth bias, m", new=True)

    def __post_init__(self) -> None:
        for f in fields(self):
            check_setting(f.name, getattr(self, f.name), "sensor", ranged=False)
        if self.min_depth_m >= self.max_depth_m:
            raise SphereBenchError(f"sensor min_depth_m={self.min_depth_m} must be below "
                                   f"max_depth_m={self.max_depth_m} (the valid depth range would be empty)")

    @property
    def dropouts(self) -> bool:
        """Whether low-texture dropouts can happen (they need the frame's surface map)."""
        return self.dropout_probability > 0 and self.dropout_fraction > 0

    def sigma_z_m(self, z_m: np.ndarray, fx_px: float) -> np.ndarray:
        """Depth noise RMS (metres) at depth z (metres) for focal length fx (pixels)."""
        return np.asarray(z_m) ** 2 * self.subpixel / (fx_px * self.baseline_m)

    def to_dict(self, compact: bool = False) -> dict:
        """The parameters as JSON-ready values. compact: the newer parameters only where they are
        not at their defaults (a nominal sensor's record reads as it did before they existed)."""
        d = asdict(self)
        if compact:
            d = {f.name: d[f.name] for f in fields(self)
                 if not f.metadata["new"] or getattr(self, f.name) != f.default}
        return d

    @classmethod
    def from_dict(cls, d: Mapping) -> "D435Sensor":
        """A sensor from ``to_dict``'s record (either form; missing parameters take their defaults)."""
        unknown = sorted(set(d) - set(PARAMETERS))
        if unknown:
            raise _unknown(unknown[0], "sensor record:")
        return cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in d.items()})


PARAMETERS = {f.name: f for f in fields(D435Sensor)}


# --------------------------------------------------------------------------- settings and ranges

def _valid(name: str) -> str:
    meta = PARAMETERS[name].metadata
    lo, hi = meta["range"]
    if meta["kind"] == "bool":
        return f"{name} must be 0 or 1 ({meta['doc']})"
    if meta["kind"] == "pair":
        return f"{name} must be a range LO:HI with {lo:g} <= LO <= HI <= {hi:g} ({meta['doc']})"
    return f"{name} must be a value or a range LO:HI from {lo:g} to {hi:g} ({meta['doc']})"


def _unknown(name: str, where: str) -> SphereBenchError:
    close = difflib.get_close_matches(name, PARAMETERS, n=1)
    hint = f"did you mean {close[0]}? " if close else ""
    return SphereBenchError(f"{where} {name}: unknown sensor parameter; {hint}use one of {', '.join(PARAMETERS)}")


def check_setting(name: str, value, where: str = "--sensor", ranged: bool = True) -> None:
    """Raise a one-line SphereBenchError unless ``value`` is valid for parameter ``name``.

    A scalar parameter takes a number or, where ``ranged``, a (lo, hi) range with lo <= hi; a pair
    parameter a (lo, hi) pair; a bool parameter a bool. Every number is finite and within range."""
    if name not in PARAMETERS:
        raise _unknown(name, where)
    meta = PARAMETERS[name].metadata
    kind, (lo, hi) = meta["kind"], meta["range"]
    shown = ":".join(f"{x:g}" for x in value) if isinstance(value, tuple) else value
    bad = SphereBenchError(f"{where} {name}={shown}: {_valid(name)}")
    if kind == "bool":
        if not isinstance(value, (bool, np.bool_)):
            raise bad
        return
    if isinstance(value, tuple):
        if (kind == "scalar" and not ranged) or len(value) != 2:
            raise bad
        values = value
    elif kind == "pair":
        raise bad
    else:
        values = (value,)
    for x in values:
        if isinstance(x, (bool, np.bool_)) or not isinstance(x, (int, float, np.floating, np.integer)) \
                or not math.isfinite(x) or not lo <= x <= hi:
            raise bad
    if len(values) == 2 and values[0] > values[1]:
        raise SphereBenchError(f"{where} {name}={shown}: LO > HI; {_valid(name)}")


def parse_settings(items: list[str], where: str = "--sensor") -> dict:
    """``NAME=VALUE`` strings (VALUE a number, a range LO:HI, or 0/1 for a switch) -> {name: value},
    each checked by ``check_setting``. A name given twice is an error."""
    out: dict = {}
    for item in items:
        name, eq, text = item.partition("=")
        name, text = name.strip(), text.strip()
        if not eq or not name or not text:
            raise SphereBenchError(f"{where} {item!r}: expected NAME=VALUE (a number or a range LO:HI), "
                                   f"e.g. {where} subpixel=0.05:0.2")
        if name not in PARAMETERS:
            raise _unknown(name, where)
        if name in out:
            raise SphereBenchError(f"{where} {name}: given twice; give each sensor parameter once")
        kind = PARAMETERS[name].metadata["kind"]
        if kind == "bool":
            flag = {"1": True, "true": True, "on": True, "yes": True,
                    "0": False, "false": False, "off": False, "no": False}.get(text.lower())
            if flag is None:
                raise SphereBenchError(f"{where} {name}={text}: {_valid(name)}")
            out[name] = flag
            continue
        try:
            parts = tuple(float(p) for p in text.split(":"))
        except ValueError:
            raise SphereBenchError(f"{where} {name}={text}: not a number; {_valid(name)}") from None
        if len(parts) > 2:
            raise SphereBenchError(f"{where} {name}={text}: {_valid(name)}")
        if len(parts) == 1:
            parts = parts * 2 if kind == "pair" else parts[0]
        check_setting(name, parts, where)
        out[name] = parts
    return out


def draw_sensor(base: D435Sensor, settings: Mapping, rng: np.random.Generator) -> D435Sensor:
    """``base`` with ``settings`` applied; a scalar given as (lo, hi) is drawn uniformly from
    ``rng``, in the parameters' order, so the draws depend only on the settings and the rng."""
    changes = {}
    for name, f in PARAMETERS.items():
        if name not in settings:
            continue
        value = settings[name]
        if f.metadata["kind"] == "scalar" and isinstance(value, tuple):
            lo, hi = value
            value = lo if lo == hi else float(rng.uniform(lo, hi))
        changes[name] = value
    return replace(base, **changes)


def _json_value(value):
    return list(value) if isinstance(value, tuple) else value


@dataclass(frozen=True)
class SensorRanges:
    """How a preset draws each scene's sensor.

    values: parameter -> value, or (lo, hi) drawn uniformly per scene (scalar parameters; a pair
        parameter's value is its pair, the same for every scene).
    grid: axes of a grid of sensor conditions, each (axis name, ((level label, {parameter: value}),
        ...)); the cells are the axes' product in ``itertools.product`` order, and scene k of a
        preset run is in cell k mod (number of cells). A cell's values override ``values``.
    """

    values: Mapping = field(default_factory=dict)
    grid: tuple = ()

    def __post_init__(self) -> None:
        for name, value in self.values.items():
            check_setting(name, value, "preset sensor")
        for _axis, levels in self.grid:
            for _label, values in levels:
                for name, value in values.items():
                    check_setting(name, value, "preset sensor")

    @property
    def grid_parameters(self) -> set[str]:
        """The parameters some grid cell sets."""
        return {name for _axis, levels in self.grid for _label, values in levels for name in values}

    @property
    def n_cells(self) -> int:
        return math.prod(len(levels) for _axis, levels in self.grid) if self.grid else 0

    def cell(self, index: int) -> tuple[int, dict, dict] | None:
        """(cell number, {axis: level label}, {parameter: value}) of scene ``index``; None without a grid."""
        if not self.grid:
            return None
        k = index % self.n_cells
        levels = list(itertools.product(*(levels for _axis, levels in self.grid)))[k]
        values: dict = {}
        for _label, v in levels:
            values.update(v)
        return k, {axis: label for (axis, _), (label, _v) in zip(self.grid, levels)}, values

    def to_dict(self) -> dict:
        out: dict = {"values": {k: _json_value(v) for k, v in self.values.items()}}
        if self.grid:
            out["grid"] = [{"axis": axis, "levels": [{"label": label, "values": {k: _json_value(v) for k, v in vals.items()}}
                                                     for label, vals in levels]} for axis, levels in self.grid]
            out["cells"] = self.n_cells
            out["cell_of_scene"] = f"index mod {self.n_cells}, cells in the axes' product order"
        return out


# --------------------------------------------------------------------------- the sensor

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


def _axis_filter(n: int, length_px: float) -> np.ndarray:
    """rfft of the circular length-n kernel whose output autocorrelation is exp(-(lag / length)^2),
    normalised to unit energy (unit-variance output from unit white noise)."""
    k = np.arange(n)
    acf = np.exp(-(np.minimum(k, n - k) / length_px) ** 2)
    power = np.clip(np.fft.rfft(acf).real, 0.0, None)  # >= 0 up to rounding for lengths << n
    kernel = np.fft.irfft(np.sqrt(power), n)
    return np.fft.rfft(kernel / np.sqrt(np.sum(kernel ** 2)))


def correlated_noise(white: np.ndarray, length_px: float) -> np.ndarray:
    """Unit-variance noise whose autocorrelation at a lag of d pixels (any direction) is
    exp(-(d / length_px)^2), i.e. it falls to 1/e at length_px: unit white noise (H, W) filtered
    along each axis by a circular filter, so every pixel keeps variance exactly 1 (the field
    wraps around the image edges, which matters only for lengths near the image size)."""
    out = np.asarray(white, np.float64)
    if length_px <= 0:
        return out
    h, w = out.shape
    out = np.fft.irfft(np.fft.rfft(out, axis=1) * _axis_filter(w, length_px)[None, :], w, axis=1)
    return np.fft.irfft(np.fft.rfft(out, axis=0) * _axis_filter(h, length_px)[:, None], h, axis=0)


def dropout_mask(surfaces: np.ndarray, sensor: D435Sensor, scale: float, rng: np.random.Generator) -> np.ndarray:
    """(H, W) bool: the low-texture dropouts. Each surface id (> 0 in ``surfaces``) present is
    low-texture with dropout_probability; of each such surface, the round(fraction x pixels)
    pixels where one smooth field (correlation length dropout_blob_px x scale) is highest drop out."""
    mask = np.zeros(surfaces.shape, bool)
    ids = surfaces.ravel()
    present = np.unique(ids[ids > 0])
    low = present[rng.random(present.size) < sensor.dropout_probability]
    if not low.size:
        return mask
    smooth = correlated_noise(rng.standard_normal(surfaces.shape), sensor.dropout_blob_px * scale).ravel()
    pix = np.flatnonzero(np.isin(ids, low))
    pix = pix[np.lexsort((smooth[pix], ids[pix]))]  # by surface, then by field value
    start = np.searchsorted(ids[pix], low, "left")
    size = np.searchsorted(ids[pix], low, "right") - start
    rank = np.arange(pix.size) - np.repeat(start, size)
    keep = np.repeat(size - np.round(sensor.dropout_fraction * size), size)
    mask.ravel()[pix[rank >= keep]] = True
    return mask


def apply_sensor(z_true_m: np.ndarray, intr: Intrinsics, sensor: D435Sensor, rng: np.random.Generator,
                 surfaces: np.ndarray | None = None) -> np.ndarray:
    """True depth (H, W) metres (inf = no surface) -> D435 depth (H, W) uint16 counts, 0 = invalid.

    surfaces: (H, W) int, the id (> 0) of the surface each pixel sees where it may be low-texture
    (``primitives.surface_map``), 0 where it may not; needed when ``sensor.dropouts``. The
    dropouts draw from a generator spawned from ``rng`` (``rng``'s own stream is untouched)."""
    z = np.array(z_true_m, dtype=np.float64)
    h, w = z.shape
    scale = w / REFERENCE_WIDTH_PX
    if sensor.dropouts and (surfaces is None or surfaces.shape != z.shape):
        raise ValueError("apply_sensor: dropouts need the frame's (H, W) surface map")
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
    mix = rng.uniform(*sensor.flying_mix, size=(h, w))
    z = np.where(fly, zf + mix * (far - zf), z)

    unit = correlated_noise(rng.standard_normal((h, w)), sensor.correlation_px * scale)
    noisy = z + unit * sensor.sigma_z_m(np.where(finite, z, 0.0), intr.fx)
    if sensor.depth_scale_error or sensor.depth_bias_m:
        noisy = noisy * (1.0 + sensor.depth_scale_error) + sensor.depth_bias_m

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
    if sensor.dropouts:
        invalid |= dropout_mask(surfaces, sensor, scale, rng.spawn(1)[0])

    invalid |= ~np.isfinite(noisy) | (noisy < sensor.min_depth_m) | (noisy > sensor.max_depth_m)
    counts = np.round(np.where(invalid, 0.0, noisy) / sensor.depth_scale_m)
    return np.clip(counts, 0, np.iinfo(np.uint16).max).astype(np.uint16)
