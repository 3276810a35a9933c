"""Retired: it reads the hand-set verdict (its factors and raw score), which the fitted verdict replaced
(issue 45); it runs at commit 7347584 (`git worktree add ../sb-7347584 7347584`).

The evidence tests' null distributions: each test's statistic on true balls, verified from their
true centre, against the threshold or allowance the detector compares it with.

``collect`` verifies every true ball (``truth_support.balls_with_circle``) of every scene with a depth
frame once from its true centre (``improved.verify_organised`` without the early stop, on the prepared
frame with its measured noise: the null hypothesis "a ball of radius R is here", as
``oracle_ceiling.py --factors`` verifies it) and writes one JSON line per scene (resumable): the
frame's noise (the A the kernels use, the measured and the model's, the correlation length; the true
A and correlation where known: the analytic sensor's subpixel / (fx baseline) from gt.json, on the
stereo model with ``--truth-noise`` the rebuilt truth's plane noise, ``noise_structure.noise_map``,
where the scene rebuilds, or a ``--noise-map`` file), and per ball its depth, band, one pixel's noise
over R, the verification's stats, factors (``improved.confidence_factors``) and per test the statistic
standardised as the detector standardises it (``tests``):

- relief: per side (h, v) t0 = (inner mean - outer mean) / (sigma sqrt(pixels_per_sample (1/n_in +
  1/n))), the one-sided t-test's statistic without the floor (N(0, 1) under the null), t with the
  floor (``relief_floor_fraction`` R) as the detector takes it; nominal, P(max(t_h, t_v) >
  ``relief_free_sigmas``) for normal t's with the floor's shift and the two sides' correlation (they
  share the inner zone); t0 also at the true noise (t0 A_used / A_true);
- size: z = (free radius - R) / its standard error, d = (free radius - R) / (tolerance + standard
  error) (the factor's), the verdict; nominal, P(|Z| > min(tolerance + size_sigmas se, limit) / se);
- see_through, behind, hug, coverage: the share, its expected value under the normal noise at the
  band the verification used (q = P(residual > band) behind, the same in front, erf(band / (sigma
  sqrt 2)) within), z = (share - expected) / sqrt(expected (1 - expected) pixels_per_sample / n), and
  at the true noise; nominal, the binomial probability (n / pixels_per_sample effective samples) that
  the factor falls below 1;
- edge_behind: the share, z = (share - edge_behind_free) / the detector's binomial error (an allowance,
  not a null);
- ring_continued, ring_front, ring_spread: the share against its free allowance.

``report`` tabulates collected lines per set, resolution and range band (the surface distance |c| - R,
``truth_support.BANDS``): per test the share of true balls it rejects (its factor below 1; for the size
test, the verdict), the nominal rate, the share it alone rejects (accepted with the test's factor 1 and
its verdict passed, rejected with it), the median factor, and the 10/50/90 % quantiles of the
standardised statistic against N(0, 1)'s -1.28 / 0 / 1.28; ``--figures DIR`` draws a QQ plot per
standardised test.

    python docs/experiments/scripts/null_checks.py collect data/train out/null_train.jsonl --workers 2
    python docs/experiments/scripts/null_checks.py collect data/train-stereo out/null_ts.jsonl --truth-noise
    python docs/experiments/scripts/null_checks.py report train=out/null_train.jsonl \\
        train-stereo=out/null_ts.jsonl --figures docs/experiments/figures
"""

from __future__ import annotations

import argparse
import functools
import json
import math
import sys
from pathlib import Path

import numpy as np
from scipy import stats as sps

import script_support as support
import truth_support as ts
from spherebench import options
from spherebench.datasets import inout
from spherebench.method import _kernels as K
from spherebench.method import improved
from spherebench.method.detector import prepare_frame
from spherebench.parallel import executor

#: The tests in table order: name -> the key of its statistic in a ball's tests (the standardised one; the
#: ring tests': their share, which the detector takes against a free allowance without standardising).
TESTS = {"relief": "t0", "size": "z", "see_through": "z", "edge_behind": "z", "coverage": "z",
         "behind": "z", "hug": "z", "ring_continued": "share", "ring_front": "share", "ring_spread": "share"}
#: The tests whose statistic is standardised (read against N(0, 1)); the QQ figures' tests.
STANDARDISED = ("relief", "size", "see_through", "edge_behind", "coverage", "behind", "hug")
QQ_TESTS = ("relief", "size", "see_through", "coverage", "behind")
RESOLUTIONS = ("424x240", "848x480", "1280x720")
NORMAL_Q = (-1.2816, 0.0, 1.2816)


# ---------------------------------------------------------------- the tests' statistics

def _normal_tail(x: float) -> float:
    return 0.5 * math.erfc(x / math.sqrt(2.0))


def relief_test(st: dict, config, a_ratio: float | None) -> dict:
    """The relief t-test's statistics (module docstring); a_ratio: A_used / A_true, or None."""
    n_in, sigma, per = st.get("inner_n", 0.0), st.get("sigma_m", 0.0), st.get("pixels_per_sample", 1.0)
    ev = config.evidence
    floor = ev.relief_floor_fraction * config.radius_m
    out = {"t": 0.0, "nominal": 0.0}
    if n_in < 3 or not sigma > 0:
        return out
    m_in = st["inner_sum"] / n_in
    shifts, ses = [], []
    for side in ("h", "v"):
        n = st[f"outer_{side}_n"]
        if n < 3:
            continue
        se = sigma * math.sqrt(per * (1.0 / n_in + 1.0 / n))
        flatter = m_in - st[f"outer_{side}_sum"] / n
        out[f"t0_{side}"] = flatter / se
        out[f"t_{side}"] = (flatter - floor) / se
        if a_ratio:
            out[f"t0_true_{side}"] = out[f"t0_{side}"] * a_ratio
        shifts.append(-floor / se)
        ses.append(1.0 / n_in + 1.0 / n)
    out["t"] = max([0.0] + [out[f"t_{s}"] for s in ("h", "v") if f"t_{s}" in out])
    c = ev.relief_free_sigmas
    if len(shifts) == 1:
        out["nominal"] = _normal_tail(c - shifts[0])
    elif shifts:
        rho = (1.0 / n_in) / math.sqrt(ses[0] * ses[1])  # the sides share the inner zone's mean
        below = sps.multivariate_normal(shifts, [[1.0, rho], [rho, 1.0]]).cdf([c, c])
        out["nominal"] = float(1.0 - below)
    return out


def size_test(free_r: float, free_se: float, config) -> dict:
    """The size test's standardised deviation, the factor's deviation and the verdict's nominal rate."""
    R, fit = config.radius_m, config.refinement
    tol = improved.size_tolerance(config)
    if not (math.isfinite(free_r) and math.isfinite(free_se) and free_se > 0):
        return {"z": None, "d": None, "nominal": None}
    allowed = min(tol + fit.size_sigmas * free_se, fit.size_limit_fraction * R)
    return {"z": (free_r - R) / free_se, "d": (free_r - R) / (tol + free_se),
            "nominal": 2.0 * _normal_tail(allowed / free_se)}


def share_test(count: float, n: float, expected: float, per: float, worse: str, allowed: float,
               expected_true: float | None = None) -> dict:
    """A share count / n against its expected value under the null, with the binomial error over n / per
    effective samples: z, the nominal probability that the share passes ``allowed`` on the ``worse``
    side ("above" or "below"), and z at the true noise's expected value where given."""
    if n < 1:
        return {"share": None, "z": None, "nominal": None}
    share, n_eff = count / n, max(1, round(n / per))
    out = {"share": share, "expected": expected, "n_eff": n_eff}

    def z(p):
        se = math.sqrt(p * (1.0 - p) * per / n)
        return (share - p) / se if se > 0 else None

    out["z"] = z(expected)
    if expected_true is not None:
        out["z_true"] = z(expected_true)
    k = math.floor(allowed * n_eff + 1e-9)
    p = min(max(expected, 0.0), 1.0)
    out["nominal"] = (float(sps.binom.sf(k, n_eff, p)) if worse == "above"
                      else float(sps.binom.cdf(math.ceil(allowed * n_eff - 1e-9) - 1, n_eff, p)))
    return out


def band_shares(eps: float, sigma: float) -> tuple[float, float]:
    """(within the band, beyond it on one side) for a normal error of sigma (m) and a band of eps (m)."""
    if not sigma > 0:
        return 1.0, 0.0
    x = eps / (sigma * math.sqrt(2.0))
    return math.erf(x), 0.5 * math.erfc(x)


def tests(st: dict, free_r: float, free_se: float, config, a_ratio: float | None) -> dict:
    """Every test's statistic of one verification (module docstring)."""
    ev = config.evidence
    sigma, eps, per = st.get("sigma_m", 0.0), st["eps_m"], st.get("pixels_per_sample", 1.0)
    p_band, q_tail = band_shares(eps, sigma)
    pt_band, qt_tail = band_shares(eps, sigma / a_ratio) if a_ratio else (None, None)
    vd = max(st["valid_disc"], 1.0)
    p_in, q_behind = improved.noise_shares(st, config)
    visible = improved.coverage_visible_share(st, improved.size_deviation(free_r, free_se, config), config)
    see_allowed = improved.see_through_allowance(st, ev.see_through_free, ev.see_through_sigmas)
    edge_n = st.get("edge_n", 0.0)
    edge = {"share": st["edge_behind"] / edge_n if edge_n >= 1 else None, "allowed": ev.edge_behind_free}
    if edge_n >= 1:
        se = math.sqrt(ev.edge_behind_free * (1.0 - ev.edge_behind_free) * per / edge_n)
        edge["z"] = (edge["share"] - ev.edge_behind_free) / se
        edge["allowed"] = improved.edge_behind_allowance(st, ev.edge_behind_free, ev.edge_behind_sigmas)
    ring = max(st["ring"], 1.0)
    return {
        "relief": relief_test(st, config, a_ratio),
        "size": size_test(free_r, free_se, config),
        "see_through": {**share_test(st["behind_inner"], st.get("valid_inner", 0.0), q_tail, per, "above",
                                     see_allowed, qt_tail), "allowed": see_allowed},
        "edge_behind": edge,
        # coverage: inliers over the (visible) valid pixels, the factor below 1 under p_in
        "coverage": share_test(st["inlier"] / max(visible, 1e-6), vd, p_band, per, "below", p_in, pt_band),
        "behind": share_test(st["behind"], vd, q_tail, per, "above", q_behind, qt_tail),
        "hug": share_test(st["front_near"], vd, q_tail, per, "above", 0.0, qt_tail),
        "ring_continued": {"share": st["ring_continued"] / ring, "allowed": 0.0},
        "ring_front": {"share": st["ring_front"] / ring, "allowed": ev.ring_front_free},
        "ring_spread": {"share": st.get("ring_spread", 0.0), "allowed": ev.ring_spread_free},
    }


# ---------------------------------------------------------------- collect

def true_noise(sd: Path, gt: dict, fx: float, width: int, truth: bool, noise_map: dict) -> tuple:
    """(A_true 1/m, correlation length px of the stream, source) of a scene, None where unknown: the
    analytic sensor's from gt.json; the stereo model's from the rebuilt truth (``--truth-noise``) or
    the noise map."""
    sensor = (gt.get("meta") or {}).get("sensor") or {}
    if "subpixel" in sensor and gt["meta"].get("sensor_model") != "stereo":
        return (sensor["subpixel"] / (fx * sensor["baseline_m"]), sensor.get("correlation_px", 0.0) * width / 424,
                "sensor")
    if sd.name in noise_map:
        return float(noise_map[sd.name]), None, "noise map"
    if truth:
        import noise_structure  # the rebuilt truth's plane noise (imports the simulator's stereo matcher)
        try:
            a = noise_structure.noise_map([noise_structure.scene_record(sd)]).get(sd.name)
        except ValueError:  # the scene does not rebuild (a holed ball: another random stream)
            a = None
        return a, None, "rebuilt truth" if a else None
    return None, None, None


def ball_record(frame, ball: dict, config, buf, a_true: float | None) -> dict:
    """One true ball verified once from its true centre: where it ends, score, factors, stats, tests."""
    c = np.asarray(ball["center_m"], np.float64)
    z = float(c[2])
    a_used = float(frame.noise_a)
    rec = {"z_m": z, "dist_surface": float(np.linalg.norm(c) - ball["radius_m"]),
           "band": ts.band_of(float(np.linalg.norm(c) - ball["radius_m"])),
           "visible_fraction_gt": ball.get("visible_fraction"),
           "noise_r": support.noise_over_r(a_used, c, config),
           "noise_r_true": support.noise_over_r(a_true, c, config) if a_true else None}
    v = improved.verify_organised(frame, c, config, buf, frame.no_gate)
    rec["verified"] = v is not None
    if v is None:
        return rec
    f = improved.confidence_factors(v.stats, 0, v.free_radius_m, v.free_radius_se_m, config, organised=True)
    rest = math.prod(x for k, x in f.items() if k != "support")
    f["support"] = float(v.score) / rest if rest > 0 else 0.0  # a Candidate keeps no inlier count
    cz = float(v.centre_m[2])
    stride = K.window_stride(float(v.centre_m[0]), float(v.centre_m[1]), cz,
                             config.radius_m * config.evidence.ring_factor,
                             max(frame.prm[K.P_FX], frame.prm[K.P_FY]), 4.0 * config.refinement.fit_max_points)
    rec.update(score=float(v.score), size_ok=bool(v.size_ok),
               accepted=bool(v.size_ok and v.score >= config.verification.min_score),
               error_m=float(np.linalg.norm(v.centre_m - c)), free_radius_m=float(v.free_radius_m),
               free_radius_se_m=float(v.free_radius_se_m), stride=int(stride),
               factors={k: float(x) for k, x in f.items()}, stats={k: float(x) for k, x in v.stats.items()},
               tests=tests(v.stats, v.free_radius_m, v.free_radius_se_m, config,
                           a_used / a_true if a_true else None))
    return rec


def scene_line(item: tuple[int, str], overrides: dict, dataset: str, truth: bool, noise_map: dict) -> dict:
    """One scene's JSON line (module docstring)."""
    k, path = item
    sd = Path(path)
    config = support.detector_config(dataset, overrides)
    gt = ts.read_gt(sd)
    cloud = inout.load_cloud(sd)
    frame = prepare_frame(cloud, config)
    intr = cloud.intrinsics
    a_true, corr_true, source = true_noise(sd, gt, float(intr.fx), int(intr.width), truth, noise_map)
    buf = improved.workspace("inliers", (frame.index_image.size + 1,), np.int64)
    holes = (gt.get("meta") or {}).get("hole_fraction") or []
    balls = []
    for j, b in enumerate(ts.balls_with_circle(gt)):
        r = ball_record(frame, b, config, buf, a_true)
        r["holed"] = j < len(holes) and holes[j] is not None
        balls.append(r)
    return {"scene": sd.name, "index": k, "family": gt.get("family"), "resolution": gt["meta"]["resolution"],
            "noise_a": float(frame.noise_a), "noise_a_measured": frame.noise_a_measured,
            "noise_a_model": improved.noise_a(config, float(intr.fx)), "noise_corr_px": float(frame.noise_corr_px),
            "noise_a_true": a_true, "noise_corr_true_px": corr_true, "true_noise_source": source, "balls": balls}


def collect(args) -> int:
    overrides = support.settings(args.set, "null_checks.py")
    noise_map = json.loads(Path(args.noise_map).read_text()) if args.noise_map else {}
    scenes = support.frame_scenes(args.dataset, args.limit, args.family)[::args.every]
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    done = {r["scene"] for r in ts.read_jsonl(out)}
    todo = [(s.index, str(s.path)) for s in scenes if s.scene_id not in done]
    fn = functools.partial(scene_line, overrides=overrides, dataset=str(args.dataset), truth=args.truth_noise,
                           noise_map=noise_map)
    with executor(args.workers) as ex, out.open("a") as fh:
        for n, rec in enumerate(ex.map(fn, todo), 1):
            fh.write(json.dumps(rec) + "\n")
            fh.flush()
            if n % 100 == 0:
                print(f"{n}/{len(todo)}", flush=True)
    print(f"done: {len(todo)} scenes written, {len(done)} there before")
    return 0


# ---------------------------------------------------------------- report

def rejected(ball: dict, test: str) -> bool:
    """Whether the test alone rejects the ball: its factor below 1 (the size test: its verdict)."""
    return not ball["size_ok"] if test == "size" else ball["factors"][test] < 1.0


def alone_rejects(ball: dict, test: str, min_score: float) -> bool:
    """Rejected from the truth, and accepted with this test's factor 1 (and, for the size test, its
    verdict passed)."""
    f = ball["factors"][test]
    without = ball["score"] / f >= min_score if f > 0 else True
    return not ball["accepted"] and without and (ball["size_ok"] or test == "size")


def standardised(ball: dict, test: str, key: str) -> list[float]:
    """The test's standardised statistic(s) of a ball (the relief: both sides)."""
    t = ball["tests"][test]
    keys = [f"{key}_h", f"{key}_v"] if test == "relief" else [key]
    return [float(t[k]) for k in keys if t.get(k) is not None and math.isfinite(t[k])]


def z_key_true(key: str) -> str:
    """The key of the statistic standardised at the true noise."""
    return "t0_true" if key == "t0" else "z_true"


def _quantiles(x: list[float]) -> str:
    return " / ".join(f"{v:.2f}" for v in np.quantile(x, (0.1, 0.5, 0.9))) if len(x) >= 5 else "-"


def _pct(x: float | None) -> str:
    return "-" if x is None else f"{100 * x:.1f}"


def group_row(balls: list[dict], test: str, min_score: float) -> list:
    """n, rejected %, nominal %, alone %, median factor, z q10/q50/q90, z at the true noise."""
    key = TESTS[test]
    nominal = [b["tests"][test].get("nominal") for b in balls]
    nominal = None if any(x is None for x in nominal) or not nominal else float(np.mean(nominal))
    zs = [z for b in balls for z in standardised(b, test, key)]
    zt = [z for b in balls for z in standardised(b, test, z_key_true(key))] if test in STANDARDISED else []
    return [len(balls), _pct(np.mean([rejected(b, test) for b in balls])), _pct(nominal),
            _pct(np.mean([alone_rejects(b, test, min_score) for b in balls])),
            f"{np.median([b['factors'][test] for b in balls]):.3f}", _quantiles(zs), _quantiles(zt)]


def verified_balls(recs: list[dict]) -> list[dict]:
    """The verified balls of scene lines, each with its scene's resolution."""
    return [{**b, "resolution": r["resolution"]} for r in recs for b in r["balls"] if b["verified"]]


def summary_table(data: dict[str, list[dict]], resolution: str, min_score: float) -> str:
    names = list(data)
    header = ["test"] + [f"{n}: {c}" for n in names for c in ("rejected %", "nominal %", "alone %", "z q10/q50/q90",
                                                                "z at true noise")]
    rows = []
    per = {n: [b for b in verified_balls(recs) if b["resolution"] == resolution] for n, recs in data.items()}
    for test in TESTS:
        cells = [test]
        for n in names:
            g = group_row(per[n], test, min_score) if per[n] else ["-"] * 7
            cells += [g[1], g[2], g[3], g[5], g[6]]
        rows.append(cells)
    acc = ["accepted from the truth (score and size)"]
    for n in names:
        acc += [_pct(np.mean([b["accepted"] for b in per[n]])) if per[n] else "-", "-", "-", "-", "-"]
    rows.append(acc)
    counts = ", ".join(f"{n} {len(per[n])} of {sum(len(r['balls']) for r in data[n] if r['resolution'] == resolution)}"
                       for n in names)
    return (f"Balls verified from the truth at {resolution}: {counts}. The ring tests' statistic is their share, "
            "not standardised.\n\n" + ts.table(header, rows))


def test_table(data: dict[str, list[dict]], test: str, min_score: float) -> str:
    rows = []
    for name, recs in data.items():
        balls = verified_balls(recs)
        for res in RESOLUTIONS + ("all",):
            for band in ts.BAND_NAMES + ("all",):
                g = [b for b in balls if res in ("all", b["resolution"]) and band in ("all", b["band"])]
                if len(g) >= 3 and (res == "all" or band == "all" or res == "424x240"):
                    rows.append([name, res, band, *group_row(g, test, min_score)])
    return ts.table(["set", "resolution", "band", "n", "rejected %", "nominal %", "alone %", "median factor",
                     "z q10 / q50 / q90" if test in STANDARDISED else "share q10 / q50 / q90", "z at true noise"], rows)


def stride_table(data: dict[str, list[dict]]) -> str:
    """The binomial tests' z by the window's stride: the counts are scaled by stride^2 (``_kernels.window_stats``)
    and their binomial errors taken over those scaled counts."""
    rows = []
    for name, recs in data.items():
        balls = verified_balls(recs)
        for lo, hi in ((1, 1), (2, 3), (4, 99)):
            g = [b for b in balls if lo <= b["stride"] <= hi]
            if len(g) >= 5:
                rows.append([name, f"{lo}" if lo == hi else f"{lo}-{hi}" if hi < 99 else f"{lo}+", len(g),
                             *(_quantiles([z for b in g for z in standardised(b, t, "z")])
                               for t in ("see_through", "edge_behind", "coverage", "behind"))])
    return ts.table(["set", "stride", "n", "see_through z", "edge_behind z", "coverage z", "behind z"], rows)


def noise_table(data: dict[str, list[dict]]) -> str:
    rows = []
    for name, recs in data.items():
        for res in RESOLUTIONS:
            rr = [r for r in recs if r["resolution"] == res and r["balls"]]
            known = [r for r in rr if r["noise_a_true"]]
            if not rr:
                continue
            used = [r["noise_a"] / r["noise_a_true"] for r in known]
            meas = [r["noise_a_measured"] / r["noise_a_true"] for r in known if r["noise_a_measured"]]
            nr = [b["noise_r"] for r in rr for b in r["balls"]]
            rows.append([name, res, len(rr), len(known), _quantiles(used), _quantiles(meas),
                         f"{np.median([r['noise_corr_px'] for r in rr]):.2f}", _quantiles(nr)])
    md = ts.table(["set", "resolution", "scenes", "with true A", "A used / true q10/q50/q90",
                   "A measured / true", "frame corr. px (median)", "sigma_z / R at the ball"], rows)
    rows = []
    for name, recs in data.items():
        for family in sorted({r["family"] for r in recs}):
            meas = [r["noise_a_measured"] / r["noise_a_true"] for r in recs
                    if r["family"] == family and r["noise_a_true"] and r["noise_a_measured"]]
            if meas:
                rows.append([name, family, len(meas), _quantiles(meas)])
    return md + "\nPer family (every scene with a measured and a true A, all resolutions):\n\n" + ts.table(
        ["set", "family", "scenes", "A measured / true q10/q50/q90"], rows)


def qq_figures(data: dict[str, list[dict]], folder: Path) -> list[str]:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    folder.mkdir(parents=True, exist_ok=True)
    written = []
    for test in QQ_TESTS:
        key = TESTS[test]
        lim = 5.0 if test in ("relief", "size") else 20.0
        fig, ax = plt.subplots(figsize=(4.2, 4.0), dpi=80)
        for j, (name, recs) in enumerate(data.items()):
            balls = [b for b in verified_balls(recs) if b["resolution"] == "424x240"]
            for k, style in ((key, "-"), (z_key_true(key), ":")):
                z = np.sort([x for b in balls for x in standardised(b, test, k)])
                if len(z) < 5:
                    continue
                theo = sps.norm.ppf((np.arange(1, len(z) + 1) - 0.5) / len(z))
                label = name + (" (true noise)" if k != key else "")
                ax.plot(theo, np.clip(z, -lim, lim), style, color=f"C{j}", lw=1.5, label=label)
        ax.plot([-3, 3], [-3, 3], "k--", lw=0.8)
        ax.set(xlim=(-3.2, 3.2), ylim=(-lim, lim), xlabel="N(0, 1) quantile", ylabel=f"{test} {key} (clipped at {lim:g})",
               title=f"{test}: true balls at 424x240")
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=7)
        fig.tight_layout()
        path = folder / f"null_qq_{test}.png"
        fig.savefig(path)
        plt.close(fig)
        written.append(str(path))
    return written


def report(args) -> int:
    config = ts.study_config()
    min_score = config.verification.min_score
    data = {name: ts.read_jsonl(path) for name, path in ts.named_paths(args.sets)}
    md = ["### The frame's noise against the truth\n", noise_table(data),
          "\n### Per test at 424x240, all bands\n", summary_table(data, "424x240", min_score)]
    for test in TESTS:
        md += [f"\n### {test}\n", test_table(data, test, min_score)]
    md += ["\n### The binomial tests' z (q10 / q50 / q90) by the window's stride, all resolutions\n", stride_table(data)]
    print("\n".join(md))
    result = {"sets": {n: len(r) for n, r in data.items()}}
    if args.figures:
        result["figures"] = qq_figures(data, Path(args.figures))
        print("\n".join(result["figures"]))
    support.write_json(args.json, result)
    return 0


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="command", required=True)
    c = sub.add_parser("collect", help="one JSON line per scene: each true ball verified from its true centre")
    c.add_argument("dataset")
    c.add_argument("out", help="the JSON-lines file (appended to; scenes already in it are skipped)")
    c.add_argument("--limit", type=options.count, default=None, help="the first N scenes only")
    c.add_argument("--every", type=options.count, default=1, help="every Nth scene of those (default 1)")
    c.add_argument("--family", action="append", default=[], metavar="NAME", help="only this family (repeatable)")
    c.add_argument("--workers", type=options.workers, default=2, help="worker processes (1: this process)")
    c.add_argument("--truth-noise", action="store_true",
                   help="stereo scenes: the true A from the rebuilt truth (noise_structure.noise_map; slower)")
    c.add_argument("--noise-map", default=None, metavar="JSON", help="{scene: true A (1/m)} (noise_structure.py)")
    c.add_argument("--set", action="append", default=[], metavar="PATH=VALUE",
                   help="a detector setting overridden, by its path (repeatable)")
    rp = sub.add_parser("report", help="coverage tables and QQ figures from collected lines")
    rp.add_argument("sets", nargs="+", metavar="NAME=JSONL")
    rp.add_argument("--figures", default=None, metavar="DIR", help="write null_qq_<test>.png there")
    support.add_json_argument(rp)
    args = p.parse_args(argv)
    return {"collect": collect, "report": report}[args.command](args)


if __name__ == "__main__":
    sys.exit(main())
