"""The stereo sensor model against Intel's published D435 behaviour: flat walls and an edge.

``python -m spherebench.eval.bench.stereo_calibration [--figure results/stereo/calibration.png]``
prints, for the analytic model (``sensor.D435Sensor``), the stereo model (``stereo.StereoSensor``)
and Intel's figures, at 848x480 and 424x240:

- walls facing the camera at 0.5-4 m: the depth error's RMS about the wall's best plane (mm),
  as a subpixel figure (RMS_z f B / z^2, px; Intel: 0.08, 0.05-0.1 typical), the mean error
  (the absolute accuracy, % of z; Intel: < 2 % at 2 m) and the fill rate of the central 80 %;
- walls turned 30 and 60 degrees about the vertical: the same figures, over the pixels whose
  wall is at most 4.5 m away;
- the noise's correlation length: the lag (px) where the error's autocorrelation falls to 1/e,
  along rows and columns, at 2 m;
- a box 1 m away before a wall at 2 and 3 m: the invalid band beside its left edge (px, the
  median over its rows) against the occlusion band f B (1/z_fg - 1/z_bg), the foreground's
  spill past its true edge (edge fattening, px) and the flying pixels per edge row;
- the stereo model's time per 848x480 scene of the cluttered family.
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

import numpy as np

from spherebench.camera import Intrinsics, image_rays
from spherebench.datasets import families, presets
from spherebench.datasets.primitives import Box, Plane, raycast
from spherebench.datasets.sensor import D435Sensor, apply_sensor
from spherebench.datasets.stereo import StereoSensor, stereo_depth
from spherebench.plotting import pyplot

DISTANCES_M = (0.5, 1.0, 1.5, 2.0, 3.0, 4.0)
INTEL_SUBPIXEL_PX = 0.08
BASELINE_M = 0.050
#: Wall pixels farther than this (a turned wall's far side) are left out of the wall figures.
MAX_CALIBRATED_M = 4.5
RESOLUTIONS = ((848, 480), (424, 240))
#: Each wall figure pools these seeds and these small changes of the distance (the stereo
#: matcher's error depends on the disparity's fractional part).
SEEDS = (1, 2)
JITTERS = (1.0, 1.013, 1.029)


def _wall(z_m: float, yaw_deg: float = 0.0) -> list:
    a = math.radians(yaw_deg)
    return [Plane(np.array([0.0, 0.0, z_m]), np.array([math.sin(a), 0.0, -math.cos(a)]))]


def _depth(model: str, objects: list, intr: Intrinsics, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """(depth m with NaN = invalid, true z m) of one model on a scene."""
    rng = np.random.default_rng(seed)
    z_true, _label = raycast(objects, image_rays(intr), intr)
    if model == "analytic":
        counts = apply_sensor(z_true, intr, D435Sensor(), rng)
    else:
        counts = stereo_depth(objects, intr, StereoSensor(), rng)
    return np.where(counts > 0, counts * 0.001, np.nan), z_true


def _roi(shape: tuple[int, int]) -> np.ndarray:
    h, w = shape
    roi = np.zeros(shape, bool)
    roi[h // 10: h - h // 10, w // 10: w - w // 10] = True
    return roi


def _plane_residual(depth_m: np.ndarray, intr: Intrinsics, mask: np.ndarray) -> np.ndarray:
    """Disparity (px) minus the best plane through the valid pixels of ``mask``: a plane's
    disparity f B / z is linear in (u, v), and Intel's subpixel RMS is this residual's."""
    v, u = np.nonzero(mask)
    a = np.stack([np.ones_like(u), u, v], axis=1).astype(np.float64)
    d = intr.fx * BASELINE_M / depth_m[v, u]
    coef, *_ = np.linalg.lstsq(a, d, rcond=None)
    return d - a @ coef


def wall_rows(model: str, intr: Intrinsics, yaw_deg: float = 0.0) -> list[dict]:
    """Per distance: the subpixel RMS (px), the RMS in mm at the distance (subpixel z^2 / f B),
    the mean |error| (% of z) and the fill rate, pooled over SEEDS and JITTERS."""
    rows = []
    fb = intr.fx * BASELINE_M
    for z in DISTANCES_M:
        sub, bias, fill = [], [], []
        for seed in SEEDS:
            for j in JITTERS:
                depth, z_true = _depth(model, _wall(z * j, yaw_deg), intr, seed)
                # a turned wall leaves the ROI's side open or beyond the calibrated range: not the sensor's
                roi = _roi(depth.shape) & (z_true <= MAX_CALIBRATED_M)
                ok = roi & np.isfinite(depth)
                fill.append(ok.sum() / roi.sum())
                if ok.sum() > 100:
                    sub.append(float(np.sqrt(np.mean(_plane_residual(depth, intr, ok) ** 2))))
                    bias.append(float(np.mean(depth[ok] - z_true[ok]) / np.mean(z_true[ok])))
        s = float(np.sqrt(np.mean(np.square(sub)))) if sub else math.nan
        rows.append({"z_m": z, "rms_mm": 1000 * s * z * z / fb, "subpixel_px": s,
                     "bias_pct": 100 * float(np.mean(np.abs(bias))) if bias else math.nan,
                     "fill": float(np.mean(fill))})
    return rows


def correlation_length(model: str, intr: Intrinsics, z_m: float = 2.0) -> tuple[float, float]:
    """(along rows, along columns): the lag (px) where the depth error's autocorrelation falls to 1/e."""
    depth, _ = _depth(model, _wall(z_m), intr, SEEDS[0])
    ok = _roi(depth.shape) & np.isfinite(depth)
    err = np.zeros(depth.shape)
    err[ok] = _plane_residual(depth, intr, ok)  # disparity px: the same correlation as depth's at one distance
    v0, v1 = np.nonzero(ok.any(axis=1))[0][[0, -1]]
    u0, u1 = np.nonzero(ok.any(axis=0))[0][[0, -1]]
    e, m = err[v0:v1 + 1, u0:u1 + 1], ok[v0:v1 + 1, u0:u1 + 1].astype(np.float64)
    shape = [2 * n for n in e.shape]
    power = np.fft.irfft2(np.abs(np.fft.rfft2(e, shape)) ** 2, shape)
    count = np.fft.irfft2(np.abs(np.fft.rfft2(m, shape)) ** 2, shape)
    acf = power / np.maximum(count, 1.0)
    acf /= acf[0, 0]
    return _one_over_e(acf[0, :e.shape[1] // 2]), _one_over_e(acf[:e.shape[0] // 2, 0])


def _one_over_e(acf: np.ndarray) -> float:
    below = np.nonzero(acf < 1 / math.e)[0]
    if not below.size:
        return math.nan
    k = below[0]
    return float(k - 1 + (acf[k - 1] - 1 / math.e) / (acf[k - 1] - acf[k]))


def edge_row(model: str, intr: Intrinsics, z_bg_m: float, z_fg_m: float = 1.0) -> dict:
    """The invalid band, fattening and flying pixels beside a box's left edge."""
    half_w = 0.25 * z_fg_m
    objects = [_wall(z_bg_m)[0], Box(np.array([half_w, 0.0, z_fg_m + 0.1]), np.array([half_w, 0.2 * z_fg_m, 0.1]))]
    depth, _ = _depth(model, objects, intr, SEEDS[0])
    edge_u = intr.ppx  # the box's left face edge lies on the optical axis: x = 0
    predicted = intr.fx * BASELINE_M * (1 / z_fg_m - 1 / z_bg_m)
    h = depth.shape[0]
    v_box = int(round(intr.fy * 0.2 * z_fg_m / z_fg_m))
    bands, invalid, fat, flying = [], [], [], []
    lo = max(0, int(edge_u - 3 * predicted) - 5)
    for v in range(int(intr.ppy) - v_box // 2, int(intr.ppy) + v_box // 2):
        if not 0 <= v < h:
            continue
        row = depth[v]
        left = row[lo:int(math.floor(edge_u)) + 1]     # pixels whose true surface is the wall
        right = row[int(math.floor(edge_u)) + 1:int(edge_u) + 20]
        fg = np.abs(left - z_fg_m) < 0.05 * z_fg_m
        bg = np.abs(left - z_bg_m) < 0.05 * z_bg_m
        between = np.isfinite(left) & ~fg & ~bg
        # band: invalid or mismeasured run next to the edge, counted back to the first background pixel
        k = len(left) - 1
        while k >= 0 and not bg[k]:
            k -= 1
        bands.append(len(left) - 1 - k)
        invalid.append(int(np.sum(~np.isfinite(left[k + 1:]))))
        fat.append(int(np.sum(fg)))
        flying.append(int(np.sum(between)) + int(np.sum(np.isfinite(right) & (np.abs(right - z_fg_m) >= 0.05 * z_fg_m))))
    return {"z_bg_m": z_bg_m, "predicted_px": predicted, "band_px": float(np.median(bands)),
            "invalid_px": float(np.median(invalid)),
            "fattening_px": float(np.median(fat)), "flying_per_row": float(np.mean(flying))}


def timing(n: int = 5) -> float:
    """Seconds per 848x480 cluttered scene through the stereo model (median of n)."""
    intr = Intrinsics.d435(848, 480)
    times = []
    for k in range(n):
        layout = families.family_cluttered(np.random.default_rng(100 + k), intr, presets.BASKETBALL_RADIUS_M)
        t0 = time.perf_counter()
        stereo_depth(layout, intr, StereoSensor(), np.random.default_rng(k))
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def _table(header: list[str], rows: list[list]) -> str:
    cells = [header] + [[f"{x:.3g}" if isinstance(x, float) else str(x) for x in r] for r in rows]
    widths = [max(len(r[i]) for r in cells) for i in range(len(header))]
    lines = ["| " + " | ".join(c.ljust(w) for c, w in zip(r, widths)) + " |" for r in cells]
    lines.insert(1, "|" + "|".join("-" * (w + 2) for w in widths) + "|")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--figure", type=Path, help="write the RMS and fill figure here (PNG)")
    args = ap.parse_args(argv)
    walls = {}
    for w, h in RESOLUTIONS:
        intr = Intrinsics.d435(w, h)
        fb = intr.fx * BASELINE_M
        for yaw in (0.0, 30.0, 60.0):
            a, s = wall_rows("analytic", intr, yaw), wall_rows("stereo", intr, yaw)
            walls[(w, yaw)] = (a, s)
            print(f"\nwall at {yaw:g} deg, {w}x{h} (f = {intr.fx:.0f} px): RMS about the plane, mm at z "
                  "(subpixel px), |mean error| %, fill")
            print(_table(["z m", "Intel RMS mm (0.08 px)", "analytic", "stereo", "analytic |bias| %",
                          "stereo |bias| %", "analytic fill", "stereo fill"],
                         [[ra["z_m"], 1000 * ra["z_m"] ** 2 * INTEL_SUBPIXEL_PX / fb,
                           f"{ra['rms_mm']:.2f} ({ra['subpixel_px']:.3f})", f"{rs['rms_mm']:.2f} ({rs['subpixel_px']:.3f})",
                           ra["bias_pct"], rs["bias_pct"], ra["fill"], rs["fill"]] for ra, rs in zip(a, s)]))
        corr = {m: correlation_length(m, intr) for m in ("analytic", "stereo")}
        print(f"\nnoise correlation length at 2 m, {w}x{h}: 1/e lag along rows, columns (px): "
              + "; ".join(f"{m} {r:.2f}, {c:.2f}" for m, (r, c) in corr.items()))
        edges = [(m, edge_row(m, intr, zb)) for zb in (2.0, 3.0) for m in ("analytic", "stereo")]
        print(f"\nbox 1 m away before a wall, {w}x{h}: beside its left edge (px; predicted f B (1/z_fg - 1/z_bg))")
        print(_table(["wall m", "model", "predicted band", "not wall", "of which invalid", "fattening", "flying / row"],
                     [[e["z_bg_m"], m, e["predicted_px"], e["band_px"], e["invalid_px"], e["fattening_px"],
                       e["flying_per_row"]]
                      for m, e in edges]))
    print(f"\nstereo model: {timing():.2f} s per 848x480 cluttered scene (median of 5)")
    if args.figure:
        _figure(walls, args.figure)
        print(f"figure: {args.figure}")
    return 0


def _figure(walls: dict, path: Path) -> None:
    plt = pyplot()
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(9, 3.4), dpi=90)
    for (w, h), colour in zip(RESOLUTIONS, ("C0", "C1")):
        intr = Intrinsics.d435(w, h)
        z = np.linspace(0.4, 4.2, 50)
        ax.plot(z, 1000 * z * z * INTEL_SUBPIXEL_PX / (intr.fx * BASELINE_M), "k--" if w == 848 else "k:",
                label=f"Intel 0.08 px, {w}")
        a, s = walls[(w, 0.0)]
        ax.plot([r["z_m"] for r in a], [r["rms_mm"] for r in a], "s-", color=colour, alpha=0.5, label=f"analytic {w}")
        ax.plot([r["z_m"] for r in s], [r["rms_mm"] for r in s], "o-", color=colour, label=f"stereo {w}")
        for yaw, mark in ((0.0, "o-"), (60.0, "^--")):
            s = walls[(w, yaw)][1]
            bx.plot([r["z_m"] for r in s], [r["fill"] for r in s], mark, color=colour, label=f"stereo {w}, {yaw:g} deg")
    ax.set(xlabel="wall distance (m)", ylabel="depth RMS about the plane (mm)", yscale="log")
    bx.set(xlabel="wall distance (m)", ylabel="fill rate (central 80 %)", ylim=(0.8, 1.005))
    ax.legend(fontsize=6)
    bx.legend(fontsize=6)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".part")
    fig.savefig(tmp, format="png")
    plt.close(fig)
    tmp.replace(path)


if __name__ == "__main__":
    raise SystemExit(main())
