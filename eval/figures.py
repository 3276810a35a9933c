"""The benchmark's figures (matplotlib, Agg): precision-recall curves, centre error against
distance, latency per method, and a grid of example scenes with true and predicted circles.

Each function draws from scored prediction sets (``eval.report.ScoredSet``) and writes one PNG.
"""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from spherebench.eval.circle_iou import circle_iou_matrix  # noqa: E402

RECALL = np.linspace(0.0, 1.0, 101)
#: Methods drawn on the example scenes, with their colours (matplotlib names).
EXAMPLE_METHODS = (("improved", "red"), ("paper+paper-circle", "orange"), ("circlenet", "cyan"),
                   ("circlenet-full", "black"), ("hough", "magenta"))


def _colours(n: int):
    cmap = plt.get_cmap("tab10" if n <= 10 else "tab20")
    return [cmap(i % cmap.N) for i in range(n)]


def _save(fig, path: Path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)


def pr_curves(label: str, sets: Sequence, path: Path) -> None:
    """Precision against recall at IoU .50 and .75 (COCO's interpolated precision, area all, maxDets 1000)."""
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


def error_vs_distance(label: str, sets: Sequence, path: Path) -> None:
    """Centre error (mm, log scale) against the ball centre's distance from the camera; misses at the top."""
    sets = [s for s in sets if s.distance_m is not None and s.rule != "paper"]
    fig, ax = plt.subplots(figsize=(8, 4.8))
    cols = _colours(len(sets))
    finite = np.concatenate([s.centre_error_m[np.isfinite(s.centre_error_m)] for s in sets]) if sets else np.zeros(0)
    top = max(200.0, float(np.nanmax(finite)) * 1000 * 1.5) if finite.size else 200.0
    for c, s in zip(cols, sets):
        hit = np.isfinite(s.centre_error_m)
        ax.scatter(s.distance_m[hit], np.maximum(s.centre_error_m[hit] * 1000, 0.01), s=9, color=c, alpha=0.6,
                   label=f"{s.method} (found {hit.sum()}/{hit.size})")
        if (~hit).any():
            ax.scatter(s.distance_m[~hit], np.full((~hit).sum(), top), marker="x", s=18, color=c, alpha=0.8)
    ax.set_yscale("log")
    ax.axhline(20, color="grey", lw=0.8, ls=":")
    ax.set_xlabel("distance of the ball centre from the camera (m)")
    ax.set_ylabel("centre error (mm); x at the top: missed")
    ax.set_title(f"`{label}`: centre error against distance")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8)
    _save(fig, path)


def latency(per_dataset: dict, path: Path) -> None:
    """Time per frame (ms, log scale) per method, one box per dataset."""
    rows = []
    for label, sets in per_dataset.items():
        for s in sets:
            if s.rule != "paper" and s.ms.size:
                rows.append((f"{s.method} · {label}", s.ms))
    fig, ax = plt.subplots(figsize=(8, 0.45 * len(rows) + 1.5))
    if rows:
        ax.boxplot([r[1] for r in rows], vert=False, whis=(5, 95), showfliers=True, flierprops={"markersize": 2})
        ax.set_yticks(range(1, len(rows) + 1), [r[0] for r in rows], fontsize=8)
        for i, (_, ms) in enumerate(rows, start=1):
            ax.annotate(f"{np.median(ms):.1f}", (np.median(ms), i + 0.3), fontsize=7, ha="center")
    ax.set_xscale("log")
    ax.set_xlabel("ms per frame (one thread); box: quartiles, whiskers: 5th-95th percentile")
    ax.set_title("Latency per method")
    ax.grid(alpha=0.3, axis="x", which="both")
    _save(fig, path)


def _top_circles(s, scene_id: str, k: int) -> list[tuple[float, float, float, float]]:
    dets = [r for r in s.results if r.get("scene_id") == scene_id]
    dets.sort(key=lambda r: -r["score"])
    return [(*r["circle_center"], r["circle_radius"], r["score"]) for r in dets[:k]]


def examples(label: str, data_dir: Path, sets: Sequence, coco_gt: dict, path: Path, n_each: int = 4) -> None:
    """A grid of scenes: the top row where the primary method (``improved``, else the first set)
    matches the truth best, the bottom row its failures (a miss, or a detection on a negative
    scene). Green: ground truth; each method's k best circles (k = the number of true balls, at
    least 1) in its colour."""
    import cv2
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
            im = cv2.imread(str(Path(data_dir) / img["file_name"]), cv2.IMREAD_COLOR)
            ax.imshow(cv2.cvtColor(im, cv2.COLOR_BGR2RGB))
            g = gts[ids[c]]
            for cx, cy, rr in g:
                ax.add_patch(plt.Circle((cx, cy), rr, fill=False, color="lime", lw=2.0))
            for name, colour in EXAMPLE_METHODS:
                s = by_name.get(name)
                if s is None:
                    continue
                for cx, cy, rr, _ in _top_circles(s, img["scene_id"], max(1, len(g))):
                    ax.add_patch(plt.Circle((cx, cy), rr, fill=False, color=colour, lw=1.2, ls="--"))
            ax.set_title(f"{kind}: {img['scene_id']} ({img['width']}x{img['height']})", fontsize=8)
    handles = [plt.Line2D([], [], color="lime", lw=2, label="ground truth")] + [
        plt.Line2D([], [], color=col, ls="--", label=name) for name, col in EXAMPLE_METHODS if name in by_name]
    fig.legend(handles=handles, loc="lower center", ncol=len(handles), fontsize=8)
    fig.suptitle(f"`{label}`: examples for {primary.output} (top: best matches; bottom: failures)", fontsize=10)
    _save(fig, path)
