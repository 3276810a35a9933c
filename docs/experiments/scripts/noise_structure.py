"""The depth noise of a sensor model against the simulator's own truth: its level against range, its
spatial correlation, the invalid-pixel share, the depth bias on the ball's face and on the planes, and
how the detector's own per-frame estimate reads it.

``collect`` rebuilds each scene's truth (``truth_support.rebuild``: the true z and which layout item
each pixel shows) and writes one JSON line per scene (resumable):

- planes: floor and wall pixels whose 15x15 window shows the same plane, per 0.25 m bin of true z: n,
  the bias (median of e = z_measured - z_true), robust sigma (1.4826 MAD), RMS clipped at 5 sigmas and
  the share beyond (gross errors); planes_by_kind: floor and wall apart, with the robust sigma after a
  quadratic in (u, v) per plane is removed ("detrended": the part a ball-sized patch sees as noise);
- invalid: per z bin, the pixels that see something and the invalid ones among them (planes, all, ball);
- acf: sums for the autocorrelation of the detrended plane residuals standardised per z bin, at lags
  1-12 px along rows (h) and columns (v), pairs on one plane, per band of true z;
- spheres: per target ball and distractor, the median e over its valid pixels (all, the inner disc
  within 0.7 of the silhouette radius, the limb), the planes' bias within 0.25 m of its centre's z, and
  a trimmed least-squares free-radius fit on the ray residuals from the true centre
  (``truth_support.fit_sphere``) on all its valid pixels (lsq_all) and on those 2 px inside its mask
  (lsq_inner; ``size_separation.py`` reads both).

``report`` tabulates them per set, beside ``stereo_losses.py collect``'s lines of the same scenes (the
detector's frame estimates ``noise_a`` and ``noise_corr_px``). ``noise-map`` writes each scene's true
A = sigma / z^2 (floor and wall, detrended, bins of 200 pixels or more beyond 0.5 m, those within
0.5 m of the ball's z where there are some; the pixel-weighted median) for ``stereo_losses.py collect
--noise-map``.

    python docs/experiments/scripts/noise_structure.py collect data/train-stereo out/train-stereo_q23.jsonl
    python docs/experiments/scripts/noise_structure.py report \\
        train=out/train_q23.jsonl:out/train_q1.jsonl train-stereo=out/train-stereo_q23.jsonl:out/train-stereo_q1.jsonl
    python docs/experiments/scripts/noise_structure.py noise-map out/train-stereo_q23.jsonl \\
        out/train-stereo_noise_map.json
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np
from scipy import ndimage

import script_support as support
import truth_support as ts
from spherebench import options
from spherebench.camera import Intrinsics, image_rays

ZBINS = np.arange(0.25, 6.01, 0.25)
LAGS = tuple(range(1, 13))
BASELINE_M = 0.05  # the D435's stereo baseline: subpixel = a * fx * baseline
RESOLUTIONS = ("424x240", "848x480", "1280x720")


# ---------------------------------------------------------------- collect

def _zbin(z):
    return np.digitize(z, ZBINS) - 1  # -1 below 0.25 m, len(ZBINS) - 1 beyond 6 m


def _plane_rows(e, sel_all, b, dres=None) -> list[dict]:
    rows = []
    for k in range(len(ZBINS) - 1):
        sel = sel_all & (b == k)
        n = int(sel.sum())
        if n < 50:
            continue
        x = e[sel]
        med, rs = float(np.median(x)), ts.robust_sigma(x)
        if dres is None:
            keep = np.abs(x - med) <= 5 * rs
            rows.append({"z": float(ZBINS[k] + 0.125), "n": n, "median_e": med, "rsigma": rs,
                         "rms_clip": float(np.sqrt(np.mean((x[keep] - med) ** 2))), "gross": float(np.mean(~keep))})
        else:
            dx = dres[sel & np.isfinite(dres)]
            rows.append({"z": float(ZBINS[k] + 0.125), "n": n, "median_e": med, "rsigma": rs,
                         "rsigma_detr": ts.robust_sigma(dx) if len(dx) >= 50 else None})
    return rows


def scene_record(sd: Path) -> dict:
    """One scene's line (fields in the module docstring)."""
    g = ts.rebuild(sd)
    depth, z_true, label, kinds, shapes, intr = g["depth"], g["z_true"], g["label"], g["kinds"], g["shapes"], g["intr"]
    z = depth.astype(np.float64) * intr.depth_scale
    valid = depth > 0
    seen = np.isfinite(z_true) & (label > 0)
    e = np.where(valid & seen, z - np.where(np.isfinite(z_true), z_true, 0.0), np.nan)
    H, W = depth.shape
    vv, uu = np.mgrid[0:H, 0:W]
    plane_ids = [k + 1 for k, kd in enumerate(kinds) if kd in ("floor", "wall")]
    interior = np.zeros((H, W), bool)
    for lab in plane_ids:
        interior |= ndimage.binary_erosion(label == lab, structure=np.ones((15, 15), bool), border_value=0)
    b = _zbin(np.where(seen, z_true, 0.0))
    pm = interior & valid
    rec = {"scene": sd.name, "resolution": f"{W}x{H}", "family": g["gt"].get("family"),
           "planes": _plane_rows(e, pm, b)}

    inv = []
    ball_px = np.isin(label, [k + 1 for k, kd in enumerate(kinds) if kd == "target"])
    for k in range(len(ZBINS) - 1):
        inb = seen & (b == k)
        if inb.any():
            inv.append({"z": float(ZBINS[k] + 0.125),
                        **{name: [int(m.sum()), int((m & ~valid).sum())]
                           for name, m in (("plane", inb & interior), ("all", inb), ("ball", inb & ball_px))}})
    rec["invalid"] = inv

    # the plane residuals less a quadratic in (u, v) per plane, standardised by their z bin's robust sigma
    dres = np.full((H, W), np.nan)
    for lab in plane_ids:
        m = interior & valid & (label == lab)
        if m.sum() < 200:
            continue
        u, v, x = uu[m] / W, vv[m] / H, e[m]
        A = np.stack([np.ones_like(u), u, v, u * u, u * v, v * v], 1)
        keep = np.ones(len(x), bool)
        for _ in range(2):
            coef, *_ = np.linalg.lstsq(A[keep], x[keep], rcond=None)
            r = x - A @ coef
            keep = np.abs(r) <= 4 * ts.robust_sigma(r[keep])
        dres[m] = r
    std = np.full((H, W), np.nan)
    ok = np.isfinite(dres)
    for k in np.unique(b[ok]):
        sel = ok & (b == k)
        if sel.sum() >= 50:
            s = ts.robust_sigma(dres[sel])
            if s > 0:
                std[sel] = np.clip(dres[sel] / s, -5, 5)
    acf = {}
    for band, (lo, hi) in zip(ts.BAND_NAMES, ts.BANDS):
        inband = (z_true >= lo) & (z_true < hi)
        acf[band] = {}
        for axis in ("h", "v"):
            rows = []
            for L in LAGS:
                if axis == "h":
                    x1, x2, l1, l2, m1 = std[:, :-L], std[:, L:], label[:, :-L], label[:, L:], inband[:, :-L]
                else:
                    x1, x2, l1, l2, m1 = std[:-L], std[L:], label[:-L], label[L:], inband[:-L]
                m = np.isfinite(x1) & np.isfinite(x2) & (l1 == l2) & m1
                a, c = x1[m], x2[m]
                rows.append([float(np.sum(a * c)), float(np.sum(a * a)), float(np.sum(c * c)), int(m.sum())])
            acf[band][axis] = rows
    rec["acf"] = acf
    rec["planes_by_kind"] = {kd: _plane_rows(e, pm & np.isin(label, [k + 1 for k, x in enumerate(kinds) if x == kd]),
                                             b, dres) for kd in ("floor", "wall")}

    rays = image_rays(intr)
    spheres = []
    for k, kd in enumerate(kinds):
        if kd not in ("target", "distractor"):
            continue
        c, R = np.asarray(shapes[k].centre_m, float), float(shapes[k].radius_m)
        if c[2] <= R:
            continue
        m_all = label == k + 1
        m = m_all & valid
        n = int(m.sum())
        row = {"kind": kd, "center": c.tolist(), "radius": R, "dist_surface": float(np.linalg.norm(c) - R),
               "n_seen": int(m_all.sum()), "n_valid": n}
        if n >= 10:
            cu = intr.fx * c[0] / c[2] + intr.ppx
            cv = intr.fy * c[1] / c[2] + intr.ppy
            r_px = intr.fx * math.tan(math.asin(R / np.linalg.norm(c)))
            rr = np.hypot(uu - cu, vv - cv) / max(r_px, 1e-9)
            mm_median = lambda sel, least: 1000 * float(np.median(e[sel])) if sel.sum() >= least else None  # noqa: E731
            row["median_e_mm"] = 1000 * float(np.median(e[m]))
            row["median_e_inner_mm"] = mm_median(m & (rr <= 0.7), 5)
            row["median_e_limb_mm"] = mm_median(m & (rr > 0.7), 5)
            near = pm & (np.abs(z_true - c[2]) <= 0.25)
            row["plane_e_mm"] = mm_median(near, 50)
            for kind in ("floor", "wall"):
                ids = [j + 1 for j, x in enumerate(kinds) if x == kind]
                row[f"{kind}_e_mm"] = mm_median(near & np.isin(label, ids), 50)
            m2 = ndimage.binary_erosion(m_all, structure=np.ones((5, 5), bool)) & valid
            for name, sel in (("lsq_all", m), ("lsq_inner", m2)):
                if sel.sum() < 10:
                    continue
                f = ts.fit_sphere(z[sel][:, None] * rays[sel], c, R)
                row[name] = None if f is None else {"r": f[1], "se": f[2], "n": int(sel.sum()), "kept": f[3],
                                                    "centre_err": float(np.linalg.norm(f[0] - c))}
        spheres.append(row)
    rec["spheres"] = spheres
    return rec


def collect(args) -> int:
    ts.collect_jsonl(args.dataset, args.out, lambda _k, sd: scene_record(sd), args.limit, every=10)
    return 0


# ---------------------------------------------------------------- report

def fx_of(resolution: str) -> float:
    w, h = (int(x) for x in resolution.split("x"))
    return Intrinsics.d435(w, h).fx


def lag_below(rho, level: float = 0.5) -> float:
    """The lag (px) where rho (lags 1, 2, ...) first falls below ``level``, interpolated; rho(0) = 1."""
    prev_l, prev = 0, 1.0
    for L, r in enumerate(rho, start=1):
        if r < level:
            return prev_l + (prev - level) / (prev - r) * (L - prev_l) if prev != r else L
        prev_l, prev = L, r
    return float("nan")


def _fit_bins(r: dict, detrended: bool) -> list[dict]:
    """The plane bins a per-scene A is taken from: 200 pixels or more, beyond 0.5 m."""
    if detrended:
        return [p for kd in ("floor", "wall") for p in r.get("planes_by_kind", {}).get(kd, [])
                if p["n"] >= 200 and p["z"] >= 0.5 and p.get("rsigma_detr")]
    return [p for p in r["planes"] if p["n"] >= 200 and p["z"] >= 0.5]


def _acf_sums(q23: list[dict], res: str, bands, axis: str) -> np.ndarray:
    S = np.zeros((len(LAGS), 4))
    for r in q23:
        if r["resolution"] == res:
            for band in bands:
                S += np.asarray(r["acf"][band][axis], float)
    return S


def report_tables(data: dict) -> tuple[str, dict]:
    """The Markdown tables of ``report`` and, per set, the frame's A over the truth's per resolution."""
    md, summary = [], {}
    f3 = lambda x: ts.median_range(x, ".3g")  # noqa: E731
    md.append("### Depth noise on planes against range\n")
    md.append("sigma (mm): median over scenes of the per-scene robust sigma in that band of true z; a = sigma / z^2 "
              "(per scene, median); subpixel = a * fx * 0.05 m (px, resolution-free). Gross: share of plane "
              "pixels beyond 5 robust sigmas.\n")
    rows = []
    for name, (q23, _q1) in data.items():
        for band in ts.BAND_NAMES:
            sig, sub, gross = [], [], []
            a_res = defaultdict(list)
            for r in q23:
                bins = [p for p in r["planes"] if ts.band_of(p["z"]) == band]
                if not bins:
                    continue
                n = np.array([p["n"] for p in bins], float)
                s = np.array([p["rsigma"] for p in bins])
                z = np.array([p["z"] for p in bins])
                a = float(np.average(s / z ** 2, weights=n))
                sig.append(1000 * float(np.average(s, weights=n)))
                a_res[r["resolution"]].append(a)
                sub.append(a * fx_of(r["resolution"]) * BASELINE_M)
                gross.append(float(np.average([p["gross"] for p in bins], weights=n)))
            if sig:
                rows.append([name, band, len(sig), f3(sig)]
                            + [f"{np.median(a_res[res]):.4f} (n {len(a_res[res])})" if a_res[res] else "-"
                               for res in RESOLUTIONS] + [f3(sub), f"{np.mean(gross):.4f}"])
    md.append(ts.table(["set", "z band", "scenes", "sigma mm q50 [q10, q90]", "a (1/m) @424", "a @848", "a @1280",
                        "subpixel px q50 [q10, q90]", "gross errors"], rows))

    md.append("\nPer scene: the truth's subpixel figure over all plane bins, its growth with range (the slope "
              "of log sigma against log z; 2 = the a z^2 form), and the detector's own frame estimate "
              "(`PreparedFrame.noise_a`) over the truth's:\n")
    rows = []
    for name, (q23, q1) in data.items():
        sub, slope, ratio = [], [], []
        for r in q23:
            bins = _fit_bins(r, False)
            if len(bins) < 2:
                continue
            n = np.array([p["n"] for p in bins], float)
            s = np.array([p["rsigma"] for p in bins])
            z = np.array([p["z"] for p in bins])
            a = float(np.average(s / z ** 2, weights=n))
            sub.append(a * fx_of(r["resolution"]) * BASELINE_M)
            if z.max() / z.min() > 1.5:
                slope.append(float(np.polyfit(np.log(z), np.log(s), 1, w=np.sqrt(n))[0]))
            if r["scene"] in q1:
                ratio.append(q1[r["scene"]]["noise_a"] / a)
        if sub:
            rows.append([name, len(sub), f3(sub), f3(slope) if slope else "-", f3(ratio) if ratio else "-"])
    md.append(ts.table(["set", "scenes", "truth subpixel q50 [q10, q90]", "log-log slope q50 [q10, q90]",
                        "frame estimate / truth q50 [q10, q90]"], rows))

    md.append("\nFloor and wall apart: per band of true z, median over scenes of the bias (median e, mm), the "
              "robust sigma (mm) and the robust sigma after a quadratic per plane is removed, and the subpixel "
              "figure of the detrended sigma:\n")
    rows = []
    for name, (q23, _q1) in data.items():
        for kd in ("floor", "wall"):
            for band in ts.BAND_NAMES:
                bias, sig, sigd, sub = [], [], [], []
                for r in q23:
                    bins = [p for p in r.get("planes_by_kind", {}).get(kd, [])
                            if ts.band_of(p["z"]) == band and p.get("rsigma_detr")]
                    if not bins:
                        continue
                    n = np.array([p["n"] for p in bins], float)
                    z = np.array([p["z"] for p in bins])
                    sd = np.array([p["rsigma_detr"] for p in bins])
                    bias.append(1000 * float(np.average([p["median_e"] for p in bins], weights=n)))
                    sig.append(1000 * float(np.average([p["rsigma"] for p in bins], weights=n)))
                    sigd.append(1000 * float(np.average(sd, weights=n)))
                    sub.append(float(np.average(sd / z ** 2, weights=n)) * fx_of(r["resolution"]) * BASELINE_M)
                if bias:
                    rows.append([name, kd, band, len(bias), f3(bias), f"{np.median(sig):.3g}", f"{np.median(sigd):.3g}",
                                 f3(sub)])
    md.append(ts.table(["set", "plane", "z band", "scenes", "bias mm q50 [q10, q90]", "sigma mm",
                        "sigma detrended mm", "subpixel (detrended) q50 [q10, q90]"], rows))

    md.append("\nThe detector's frame estimate of A against the truth's detrended A (all plane bins beyond 0.5 m, "
              "per scene):\n")
    rows = []
    for name, (q23, q1) in data.items():
        summary[name] = {}
        for res in RESOLUTIONS + ("all",):
            ratio = []
            for r in q23:
                bins = _fit_bins(r, True)
                if (res != "all" and r["resolution"] != res) or not bins or r["scene"] not in q1:
                    continue
                n = np.array([p["n"] for p in bins], float)
                a = float(np.average([p["rsigma_detr"] / p["z"] ** 2 for p in bins], weights=n))
                ratio.append(q1[r["scene"]]["noise_a"] / a)
            if ratio:
                rows.append([name, res, len(ratio), f3(ratio)])
                summary[name][res] = float(np.median(ratio))
    md.append(ts.table(["set", "resolution", "scenes", "frame A / truth A (detrended) q50 [q10, q90]"], rows))

    md.append("\n### Spatial autocorrelation of the plane residuals\n")
    md.append("Residual less a quadratic in (u, v) per plane, standardised per z bin; pairs on one plane. "
              "rho at lags 1, 2, 3, 4, 6, 8 px and the lag where rho < 0.5, per resolution (all bands pooled), "
              "then per band of true z (lag in 424-px units: lag x 424 / width).\n")
    rows = []
    for name, (q23, _q1) in data.items():
        for res in RESOLUTIONS:
            for axis in ("h", "v"):
                S = _acf_sums(q23, res, ts.BAND_NAMES, axis)
                if S[0, 3] == 0:
                    continue
                rho = S[:, 0] / np.sqrt(S[:, 1] * S[:, 2])
                lag = lag_below(rho)
                w = int(res.split("x")[0])
                rows.append([name, res, axis, int(S[0, 3])] + [f"{rho[L - 1]:.2f}" for L in (1, 2, 3, 4, 6, 8)]
                            + [f"{lag:.2f}" if lag >= 1 else f"<1 ({lag:.2f})", f"{lag * 424 / w:.2f}"])
    md.append(ts.table(["set", "resolution", "axis", "pairs (lag 1)", "rho(1)", "rho(2)", "rho(3)", "rho(4)", "rho(6)",
                        "rho(8)", "lag rho < 0.5 (px)", "in 424-px units"], rows))
    md.append("\nThe detector's own correlation length (`PreparedFrame.noise_corr_px`, l of exp(-(d/l)^2), for "
              "which rho = 0.5 at 0.83 l) per resolution, median [q10, q90] over scenes:\n")
    rows = []
    for name, (_q23, q1) in data.items():
        for res in RESOLUTIONS:
            ls = [r["noise_corr_px"] for r in q1.values() if r["resolution"] == res]
            if ls:
                rows.append([name, res, len(ls), ts.median_range(ls, ".2f"), f"{0.83 * np.median(ls):.2f}"])
    md.append(ts.table(["set", "resolution", "scenes", "frame l px", "frame l as lag(rho=0.5) px"], rows))
    rows = []
    for name, (q23, _q1) in data.items():
        for band in ts.BAND_NAMES:
            for axis in ("h", "v"):
                cells = []
                for res in RESOLUTIONS:
                    S = _acf_sums(q23, res, (band,), axis)
                    if S[0, 3] < 1000:
                        cells.append("-")
                        continue
                    rho = S[:, 0] / np.sqrt(S[:, 1] * S[:, 2])
                    cells.append(f"{lag_below(rho) * 424 / int(res.split('x')[0]):.2f}")
                rows.append([name, band, axis, " / ".join(cells)])
    md.append(ts.table(["set", "z band", "axis", "lag rho < 0.5 (424-px units), per resolution 424 / 848 / 1280"],
                       rows))

    md.append("\n### Invalid pixels against range (band of true z)\n")
    rows = []
    for name, (q23, _q1) in data.items():
        for band in ts.BAND_NAMES:
            acc = defaultdict(lambda: [0, 0])
            for r in q23:
                for row in r["invalid"]:
                    if ts.band_of(row["z"]) == band:
                        for k in ("plane", "all", "ball"):
                            acc[k][0] += row[k][0]
                            acc[k][1] += row[k][1]
            sh = lambda k: f"{acc[k][1] / acc[k][0]:.3f}" if acc[k][0] else "-"  # noqa: E731
            rows.append([name, band] + [x for k in ("plane", "all", "ball") for x in (acc[k][0], sh(k))])
    md.append(ts.table(["set", "z band", "plane px", "invalid share (planes)", "all px", "invalid share (all)",
                        "ball px", "invalid share (ball)"], rows))

    md.append("\n### Depth bias on the ball's face against the planes' (mm, + = measured behind the truth)\n")
    md.append("Per ball: median of z_measured - z_true over its valid pixels (all; inner disc within 0.7 of the "
              "silhouette radius; limb beyond); the planes' bias: the same scene's plane pixels within 0.25 m of "
              "the ball's centre z. Median over balls [q10, q90]; band: the ball's surface distance.\n")
    rows = []
    f1 = lambda x: ts.median_range(x) if len(x) else "-"  # noqa: E731
    for name, (q23, _q1) in data.items():
        for band in ts.BAND_NAMES:
            bb = [s for r in q23 for s in r["spheres"]
                  if s["kind"] == "target" and "median_e_mm" in s and ts.band_of(s["dist_surface"]) == band]
            if not bb:
                continue
            got = lambda k: [s[k] for s in bb if s.get(k) is not None]  # noqa: E731
            pl = got("plane_e_mm")
            diff = [s["median_e_mm"] - s["plane_e_mm"] for s in bb if s.get("plane_e_mm") is not None]
            rows.append([name, band, len(bb), f1(got("median_e_mm")), f1(got("median_e_inner_mm")),
                         f1(got("median_e_limb_mm")), f"{f1(pl)} ({len(pl)})", f1(diff)])
    md.append(ts.table(["set", "band", "balls", "ball face", "inner disc", "limb", "planes near it (n)",
                        "ball - planes"], rows))
    return "\n".join(md), summary


def report(args) -> int:
    data = {}
    for name, paths in ts.named_paths(args.sets):
        p23, _, p1 = paths.partition(":")
        data[name] = (ts.read_jsonl(p23), {r["scene"]: r for r in ts.read_jsonl(p1)} if p1 else {})
    text, summary = report_tables(data)
    print(text)
    support.write_json(args.json, {"frame_over_truth_a": summary})
    return 0


def noise_map(q23: list[dict]) -> dict[str, float]:
    """{scene: the truth's A (1/m)} (see the module docstring)."""
    out = {}
    for r in q23:
        bins = _fit_bins(r, True)
        if not bins:
            continue
        balls = [s for s in r["spheres"] if s["kind"] == "target"]
        near = [p for p in bins if balls and abs(p["z"] - balls[0]["center"][2]) <= 0.5] or bins
        a = np.array([p["rsigma_detr"] / p["z"] ** 2 for p in near])
        n = np.array([p["n"] for p in near], float)
        o = np.argsort(a)
        c = np.cumsum(n[o])
        out[r["scene"]] = float(a[o][np.searchsorted(c, 0.5 * c[-1])])
    return out


def write_noise_map(args) -> int:
    out = noise_map(ts.read_jsonl(args.q23))
    Path(args.out).write_text(json.dumps(out, indent=1))
    print(f"{len(out)} scenes; A median {np.median(list(out.values())):.4f}" if out else "no scene with plane bins")
    return 0


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="command", required=True)
    c = sub.add_parser("collect", help="one JSON line per scene, measured against the rebuilt truth")
    c.add_argument("dataset")
    c.add_argument("out", help="the JSON-lines file (appended to; scenes already in it are skipped)")
    c.add_argument("--limit", type=options.count, default=None, help="the first N scenes only")
    rp = sub.add_parser("report", help="tables from collected lines")
    rp.add_argument("sets", nargs="+", metavar="NAME=Q23.jsonl[:Q1.jsonl]",
                    help="this script's lines, and stereo_losses.py collect's of the same scenes")
    support.add_json_argument(rp)
    nm = sub.add_parser("noise-map", help="{scene: true A} for stereo_losses.py collect --noise-map")
    nm.add_argument("q23")
    nm.add_argument("out")
    args = p.parse_args(argv)
    return {"collect": collect, "report": report, "noise-map": write_noise_map}[args.command](args)


if __name__ == "__main__":
    sys.exit(main())
