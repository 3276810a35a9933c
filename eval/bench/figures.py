"""The benchmark's figures (matplotlib, Agg): precision-recall curves, centre error against
distance, latency per method (and per stream of the tracking benchmark), a grid of example scenes
with true and predicted circles, the robustness figure of a grid preset (rates per sensor condition
and range band), and the reliability diagram of the 3D methods' scores.

Each function draws from scored prediction sets (``eval.bench.scoring.ScoredSet``), ``robustness`` from
the per-cell rows that metrics.json holds, ``reliability_diagram`` from ``eval.bench.calibration``'s
frame, and writes one PNG.
"""

from __future__ import annotations

import io
from pathlib import Path
from typing import Sequence

import cv2
import numpy as np

from spherebench.eval.metrics.circle_iou import circle_iou_matrix
from spherebench.eval.metrics.sensor_grid import ceiling_key, level_label
from spherebench.plotting import pyplot

RECALL = np.linspace(0.0, 1.0, 101)
#: Methods drawn on the example scenes, with their colours (matplotlib names).
EXAMPLE_METHODS = (("improved", "red"), ("paper+paper-circle", "orange"), ("circlenet", "cyan"),
                   ("circlenet-full", "black"), ("hough", "magenta"))


def _colours(n: int):
    cmap = pyplot().get_cmap("tab10" if n <= 10 else "tab20")
    return [cmap(i % cmap.N) for i in range(n)]


def _save(fig, path: Path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110, bbox_inches="tight")
    pyplot().close(fig)


def pr_curves(label: str, sets: Sequence, path: Path) -> None:
    """Precision against recall at IoU .50 and .75 (COCO's interpolated precision, area all, maxDets 1000)."""
    plt = pyplot()
    sets = [s for s in sets if s.pr50 is not None]
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.8), sharey=True)
    colours = {}
    for s in sets:
        colours.setdefault(s.method, _colours(10)[len(colours) % 10])
    for ax, which, iou in ((axes[0], "pr50", "0.50"), (axes[1], "pr75", "0.75")):
        for s in sets:
            p = getattr(s, which)
            style = "--" if s.rule == "paper" else "-"
            key = "mAP50" if which == "pr50" else "mAP75"
            ax.plot(RECALL, np.where(np.isnan(p), np.nan, p), style, color=colours[s.method], lw=1.6,
                    label=f"{s.output} (AP {s.metrics.get(key) or 0:.3f})")
        ax.set_title(f"`{label}`: precision-recall at circle IoU {iou}")
        ax.set_xlabel("recall")
        ax.set_xlim(0, 1)
        ax.set_ylim(0, 1.02)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc="lower left")
    axes[0].set_ylabel("precision (interpolated)")
    _save(fig, path)


def plot_error_vs_distance(label: str, sets: Sequence, path: Path, reference: bool = False) -> None:
    """Centre error (mm, log scale) against the ball centre's distance from the camera; misses at the top.
    reference: the centres are a recording's reference fits, not true centres (said on the axis)."""
    plt = pyplot()
    sets = [s for s in sets if s.distance_m is not None and s.rule != "paper"]
    fig, ax = plt.subplots(figsize=(8, 4.8))
    cols = _colours(len(sets))
    finite = np.concatenate([s.centre_error_m[np.isfinite(s.centre_error_m)] for s in sets]) if sets else np.zeros(0)
    top = max(200.0, float(np.nanmax(finite)) * 1000 * 1.5) if finite.size else 200.0
    for c, s in zip(cols, sets):
        hit = np.isfinite(s.centre_error_m)
        ax.scatter(s.distance_m[hit], np.maximum(s.centre_error_m[hit] * 1000, 0.01), s=9, color=c, alpha=0.6,
                   label=f"{s.method} (matched {hit.sum()}/{hit.size})")
        if (~hit).any():
            ax.scatter(s.distance_m[~hit], np.full((~hit).sum(), top), marker="x", s=18, color=c, alpha=0.8)
    ax.set_yscale("log")
    ax.axhline(20, color="grey", lw=0.8, ls=":")
    ax.set_xlabel("distance of the ball centre from the camera (m)")
    ax.set_ylabel(("distance to the reference centre" if reference else "centre error") + " (mm); x at the top: missed")
    ax.set_title(f"`{label}`: centre error against distance" + (" (reference: mask fit, not ground truth)"
                                                                 if reference else ""))
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8)
    _save(fig, path)


def latency(per_dataset: dict, path: Path) -> None:
    """Time per frame (ms, log scale) per method, one box per dataset."""
    plt = pyplot()
    rows = []
    for label, sets in per_dataset.items():
        for s in sets:
            if s.rule != "paper" and s.ms.size:
                rows.append((f"{s.method} · {label}", s.ms))
    fig, ax = plt.subplots(figsize=(8, 0.45 * len(rows) + 1.5))
    if rows:
        ax.boxplot([r[1] for r in rows], orientation="horizontal", whis=(5, 95), showfliers=True, flierprops={"markersize": 2})
        ax.set_yticks(range(1, len(rows) + 1), [r[0] for r in rows], fontsize=8)
        for i, (_, ms) in enumerate(rows, start=1):
            ax.annotate(f"{np.median(ms):.1f}", (np.median(ms), i + 0.3), fontsize=7, ha="center")
    ax.set_xscale("log")
    ax.set_xlabel("ms per frame (one thread); box: quartiles, whiskers: 5th-95th percentile")
    ax.set_title("Latency per method")
    ax.grid(alpha=0.3, axis="x", which="both")
    _save(fig, path)


def track_latency(series: dict[str, tuple[np.ndarray, float]]) -> bytes:
    """Histograms of time per frame (ms, log scale) of the streams of the tracking benchmark, one
    panel per label (dataset and depth mode), a line per method, the frame period marked; the PNG's
    bytes. series: "label / method" -> (ms per frame, the period in ms)."""
    plt = pyplot()
    labels = sorted({k.split(" / ")[0] for k in series})
    methods = sorted({k.split(" / ")[1] for k in series})
    fig, axes = plt.subplots(len(labels), 1, figsize=(8, 2.4 * len(labels) + 0.6), squeeze=False)
    for ax, label in zip(axes[:, 0], labels):
        mine = {k.split(" / ")[1]: v for k, v in series.items() if k.split(" / ")[0] == label}
        every = np.concatenate([ms for ms, _ in mine.values()])
        if not every.size:
            continue
        edges = np.geomspace(max(every.min(), 0.05), every.max() * 1.05, 60)
        for method, (ms, period) in sorted(mine.items()):
            colour = _colours(10)[methods.index(method)]  # a method's colour the same in every panel
            ax.hist(ms, bins=edges, histtype="step", lw=1.6, color=colour,
                    label=f"{method} (median {np.median(ms):.2f}, p99 {np.percentile(ms, 99):.2f} ms)")
            ax.axvline(period, color="grey", ls="--", lw=1)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.xaxis.set_minor_formatter(plt.NullFormatter())  # decades only: no crowded labels
        ax.set_ylabel("frames", fontsize=8)
        ax.set_title(f"{label} (dashed: the frame period)", fontsize=9)
        ax.legend(fontsize=7)
        ax.grid(alpha=0.3, which="both")
    axes[-1, 0].set_xlabel("ms per frame (deprojection, detection, tracking; one thread)")
    fig.subplots_adjust(hspace=0.45)
    out = io.BytesIO()
    fig.savefig(out, format="png", dpi=110, bbox_inches="tight")
    plt.close(fig)
    return out.getvalue()


def _top_circles(s, scene_id: str, k: int) -> list[tuple[float, float, float, float]]:
    dets = [r for r in s.results if r.get("scene_id") == scene_id]
    dets.sort(key=lambda r: -r["score"])
    return [(*r["circle_center"], r["circle_radius"], r["score"]) for r in dets[:k]]


def _background(data_dir: Path, img: dict) -> np.ndarray:
    """An example's picture (RGB): the scene's colour frame where it has one (a recording registered
    to depth), else the image the 2D methods are given."""
    path = Path(data_dir) / img["file_name"]
    for name in ("colour.jpg", "colour.png"):
        if (path.parent / name).is_file():
            path = path.parent / name
            break
    return cv2.cvtColor(cv2.imread(str(path), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)


def examples(label: str, data_dir: Path, sets: Sequence, coco_gt: dict, path: Path, n_each: int = 4) -> None:
    """A grid of scenes: the top row where the primary method (``improved``, else the first set)
    matches the truth best, the bottom row its failures (a miss, or a detection on a negative
    scene). Green: ground truth; each method's k best circles (k = the number of true balls, at
    least 1) in its colour, their scores listed in the corner. A scene with a colour frame is shown
    in colour (the masks were drawn there), others as the image the 2D methods see."""
    plt = pyplot()
    by_name = {s.output: s for s in sets}
    primary = by_name.get("improved") or (sets[0] if sets else None)
    if primary is None:
        return
    gts: dict[int, list] = {img["id"]: [] for img in coco_gt["images"]}
    for a in coco_gt["annotations"]:
        gts[a["image_id"]].append([*a["circle_center"], a["circle_radius"]])
    images = {img["id"]: img for img in coco_gt["images"]}
    quality = []
    for image_id, img in images.items():
        g = np.asarray(gts[image_id], np.float64).reshape(-1, 3)
        top = _top_circles(primary, img["scene_id"], max(1, len(g)))
        if len(g) == 0:
            q = 0.0 if top else 1.0  # a detection on a negative scene is a failure
        elif not top:
            q = 0.0
        else:
            q = float(circle_iou_matrix(np.asarray(top)[:, :3], g).max(axis=0).min())
        quality.append((q, image_id))
    def varied(candidates: list[int]) -> list[int]:
        """Up to n_each ids, one per scene family first (in the given order), then the rest."""
        picked, families = [], set()
        for i in candidates:
            if images[i].get("family") not in families:
                picked.append(i)
                families.add(images[i].get("family"))
        return (picked + [i for i in candidates if i not in picked])[:n_each]

    positives = {i for i, g in gts.items() if g}
    failures = varied([i for q, i in sorted(quality, key=lambda t: (t[0], t[1])) if q < 0.5])
    # successes: scenes with a ball first (a negative scene left empty is a success too, but shows little)
    good = sorted((t for t in quality if t[0] >= 0.5), key=lambda t: (t[1] not in positives, -t[0], t[1]))
    successes = varied([i for _, i in good])
    rows = [("success", successes), ("failure", failures)]
    fig, axes = plt.subplots(2, n_each, figsize=(3.6 * n_each, 5.4))
    for r, (kind, ids) in enumerate(rows):
        for c in range(n_each):
            ax = axes[r, c]
            ax.axis("off")
            if c >= len(ids):
                continue
            img = images[ids[c]]
            ax.imshow(_background(data_dir, img))
            g = gts[ids[c]]
            for cx, cy, rr in g:
                ax.add_patch(plt.Circle((cx, cy), rr, fill=False, color="lime", lw=2.0))
            scores = []
            for name, colour in EXAMPLE_METHODS:
                s = by_name.get(name)
                if s is None:
                    continue
                top = _top_circles(s, img["scene_id"], max(1, len(g)))
                for cx, cy, rr, _ in top:
                    ax.add_patch(plt.Circle((cx, cy), rr, fill=False, color=colour, lw=1.2, ls="--"))
                scores.append((f"{name} " + (" ".join(f"{sc:.2f}" for *_, sc in top) if top else "none"), colour))
            for k, (text, colour) in enumerate(scores):  # each method's best scores, in its colour
                ax.text(0.01, 0.99 - 0.09 * k, text, transform=ax.transAxes, ha="left", va="top", fontsize=6.5,
                        color="white" if colour == "black" else colour,
                        bbox={"facecolor": "black", "alpha": 0.55, "pad": 0.6, "lw": 0})
            ax.set_title(f"{kind}: {img['scene_id']} ({img['width']}x{img['height']})", fontsize=8)
    handles = [plt.Line2D([], [], color="lime", lw=2, label="ground truth")] + [
        plt.Line2D([], [], color=col, ls="--", label=name) for name, col in EXAMPLE_METHODS if name in by_name]
    fig.legend(handles=handles, loc="lower center", ncol=len(handles), fontsize=8)
    fig.suptitle(f"`{label}`: examples for {primary.output} (top: best matches; bottom: failures)", fontsize=10)
    _save(fig, path)


#: The robustness figure's lines: (correlation, dropouts) -> (line style, marker), in the grid's order.
ROBUST_LINES = {("none", "off"): ("-", "o"), ("none", "on"): ("--", "o"),
                ("1px", "off"): ("-", "^"), ("1px", "on"): ("--", "^")}


def robustness(label: str, rows_by_method: dict, path: Path, ceiling: dict | None = None,
               ceiling_method: str = "improved") -> None:
    """The 3D detection rate (within 2 cm) and the 2D mAP.50 against subpixel, per range band: one
    row of panels per method (its colour), three bands of each metric side by side; correlation
    and dropouts as line styles (``ROBUST_LINES``: solid dropouts off, dashed on; circles
    correlation none, triangles 1 px), the four lines nudged apart in x.

    rows_by_method: {method: its ``sensor_cells`` rows (``eval.metrics.sensor_grid.grid_rows``, as in
    metrics.json)}, in drawing order. A method without 3D centres leaves its 3D panels blank.
    ceiling: the hook for an oracle's per-cell ceiling of the detection rate, {(subpixel,
    correlation, dropouts, band label e.g. "0-1 m"): rate in 0-1} (``sensor_grid.ceiling_key``),
    drawn as a grey marker beside ``ceiling_method``'s rate in its 3D panels; None: none drawn.
    """
    plt = pyplot()
    methods = [m for m, rows in rows_by_method.items() if rows]
    bands = list(dict.fromkeys(r["band"] for m in methods for r in rows_by_method[m]))
    levels = sorted({r["subpixel"] for m in methods for r in rows_by_method[m]})
    n_rows, n_cols = max(1, len(methods)), 2 * max(1, len(bands))
    fig, axes = plt.subplots(n_rows, n_cols, figsize=(2.55 * n_cols, 1.9 * n_rows + 1.2), sharex=True, sharey=True,
                             squeeze=False, layout="constrained")
    span = (levels[-1] - levels[0]) if len(levels) > 1 else 0.1
    nudge = {k: (i - 1.5) * 0.02 * span for i, k in enumerate(ROBUST_LINES)}
    colours = _colours(max(len(methods), 1))
    for j, name in enumerate(("3D matched within 2 cm", "2D mAP.50")):
        for b, band in enumerate(bands):
            n = [r["n_balls"] for r in rows_by_method[methods[0]] if r["band"] == band
                 and r.get("n_balls") is not None] if methods else []
            count = "" if not n else f"\n{min(n)}-{max(n)} balls per cell" if min(n) != max(n) else \
                f"\n{n[0]} balls per cell"
            axes[0, j * len(bands) + b].set_title(f"{name}, {band}{count}", fontsize=9)
    for i, method in enumerate(methods):
        rows = rows_by_method[method]
        axes[i, 0].set_ylabel(method, fontsize=9)
        for j, metric in enumerate(("within_2cm", "mAP50")):
            for b, band in enumerate(bands):
                ax = axes[i, j * len(bands) + b]
                ax.grid(alpha=0.3)
                in_band = [r for r in rows if r["band"] == band]
                if all(r.get(metric) is None for r in in_band):
                    ax.text(0.5, 0.5, "no 3D centre" if metric == "within_2cm" else "no 2D score",
                            transform=ax.transAxes, ha="center", va="center", fontsize=8, color="grey")
                    continue
                for line, (ls, marker) in ROBUST_LINES.items():
                    pts = sorted((r["subpixel"], r[metric]) for r in in_band
                                 if (r["correlation"], r["dropouts"]) == line and r.get(metric) is not None)
                    if pts:
                        x, y = np.asarray(pts, np.float64).T
                        ax.plot(x + nudge[line], y, ls=ls, marker=marker, color=colours[i], lw=1.2, ms=4,
                                mfc="white" if line[1] == "on" else colours[i])
                    if ceiling and method == ceiling_method and metric == "within_2cm":
                        keys = [ceiling_key(r) for r in in_band if (r["correlation"], r["dropouts"]) == line]
                        cx = [(k[0], ceiling[k]) for k in keys if ceiling.get(k) is not None]
                        if cx:
                            x, y = np.asarray(cx, np.float64).T
                            ax.scatter(x + nudge[line] + 0.01 * span, y, marker=marker, s=22, color="grey", zorder=1.5)
    for ax in axes[-1]:
        ax.set_xlabel("subpixel (px)", fontsize=8)
        ax.set_xticks(levels, [level_label(v) for v in levels], fontsize=7)
    axes[0, 0].set_ylim(-0.03, 1.05)
    handles = [plt.Line2D([], [], color="black", ls=ls, marker=mk, mfc="white" if line[1] == "on" else "black",
                          label=f"correlation {line[0]}, dropouts {line[1]}") for line, (ls, mk) in ROBUST_LINES.items()]
    if ceiling:
        handles.append(plt.Line2D([], [], color="grey", ls="", marker="o", label=f"ceiling of {ceiling_method}"))
    fig.legend(handles=handles, loc="outside lower center", ncol=len(handles), fontsize=8)
    fig.suptitle(f"`{label}`: detection rate and mAP.50 against the sensor's subpixel noise, per range band "
                 "(true distance to the ball's surface)", fontsize=10)
    _save(fig, path)


def transfer(rows: Sequence[dict], path: Path) -> None:
    """The transfer table (``eval.bench.transfer.transfer_rows``) as bars: one column of panels per preset
    pair, circle mAP above and the 3D found rate below, each method's analytic bar (solid) beside
    its stereo bar (hatched), the drop written over the pair."""
    plt = pyplot()
    pairs = list(dict.fromkeys((r["analytic"], r["stereo"]) for r in rows))
    fig, axes = plt.subplots(2, len(pairs), figsize=(4.6 * len(pairs), 7.2), squeeze=False, sharey=True)
    for col, pair in enumerate(pairs):
        mine = [r for r in rows if (r["analytic"], r["stereo"]) == pair]
        colours = _colours(len(mine))
        for ax, key, what in ((axes[0, col], "mAP", "circle mAP (.50:.95)"), (axes[1, col], "found", "3D found rate")):
            for k, r in enumerate(mine):
                a, s, drop = r[key]
                if a is None or s is None:
                    continue
                ax.bar(k - 0.2, a, 0.4, color=colours[k])
                ax.bar(k + 0.2, s, 0.4, color=colours[k], alpha=0.45, hatch="//", edgecolor="black", lw=0.5)
                ax.text(k, max(a, s) + 0.02, f"{-drop:+.2f}", ha="center", fontsize=7)
            ax.set_xticks(range(len(mine)), [r["output"] for r in mine], rotation=45, ha="right", fontsize=7)
            ax.set_ylim(0, 1.12)
            ax.grid(axis="y", alpha=0.3)
            ax.set_title(f"`{pair[0]}` (solid) vs `{pair[1]}` (hatched)", fontsize=9)
            if col == 0:
                ax.set_ylabel(what)
    fig.tight_layout()
    _save(fig, path)


def reliability_diagram(frame, path: Path) -> None:
    """The reliability diagram of ``eval.bench.calibration``'s frame: one panel per preset, each method's
    non-empty bins as points (mean score, fraction correct), their area and the number beside them the
    bin's detections, over the diagonal of a calibrated score; the legend gives each method's ECE and detections."""
    plt = pyplot()
    presets = list(dict.fromkeys(frame["preset"]))
    methods = list(dict.fromkeys(frame["method"]))
    colours = dict(zip(methods, _colours(len(methods))))
    n_cols = min(4, max(1, len(presets)))
    n_rows = -(-max(1, len(presets)) // n_cols)
    fig, axes = plt.subplots(n_rows, n_cols, figsize=(3.6 * n_cols, 3.6 * n_rows + 0.4), sharex=True, sharey=True,
                             squeeze=False, layout="constrained")
    for ax in axes.flat[len(presets):]:
        ax.set_visible(False)
    for ax, preset in zip(axes.flat, presets):
        ax.plot([0, 1], [0, 1], color="grey", lw=0.8, ls=":")
        mine = frame[frame["preset"] == preset]
        for method, g in mine.groupby("method", sort=False):
            g = g[g["count"] > 0]
            n = int(g["count"].sum())
            ece = g["ece"].iloc[0] if n else float("nan")
            ax.plot(g["mean_score"], g["fraction_correct"], "-", color=colours[method], lw=0.8, alpha=0.6)
            ax.scatter(g["mean_score"], g["fraction_correct"], s=12 + 180 * np.sqrt(g["count"] / max(n, 1)),
                       color=colours[method], alpha=0.7, label=f"{method}: ECE {ece:.3f}, {n} det.")
            for x, y, k in zip(g["mean_score"], g["fraction_correct"], g["count"]):
                ax.annotate(str(k), (x, y), xytext=(4, 4), textcoords="offset points", fontsize=6,
                            color=colours[method])
        ax.set_title(f"`{preset}`", fontsize=9)
        ax.set_xlim(-0.02, 1.05)
        ax.set_ylim(-0.04, 1.08)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=6, loc="best")
    for col in range(n_cols):  # the lowest panel drawn in each column
        ax = axes[(len(presets) - 1 - col) // n_cols, col]
        ax.xaxis.set_tick_params(labelbottom=True)
        ax.set_xlabel("mean score of the bin", fontsize=8)
    for ax in axes[:, 0]:
        ax.set_ylabel("fraction correct", fontsize=8)
    fig.suptitle("Reliability of the 3D methods' scores: correct = within 2 cm of a ball (3 cm beyond 3 m), one "
                 "per ball; point area and number = the bin's detections", fontsize=9)
    _save(fig, path)
