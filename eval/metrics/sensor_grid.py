"""Figures per sensor condition and range band (the `robust` preset's grid): pure functions.

A scene of a grid preset carries its cell in ``gt.json`` ``meta.sensor_cell``, e.g.
{"cell": 5, "subpixel": 0.08, "correlation": "none", "dropouts": "on"}; the runner copies it into
every scene record of a prediction set's meta file, so these figures are drawn from the stage
files alone. Groups are keyed by the levels of some grid axes (all three: one cell; "subpixel"
alone: pooled over the others) and a range band of the ball's true distance (camera to its
nearest surface, ||centre|| - R, the simulator's "distance"):

- the 3D detection rate: balls whose matched detection (``metrics3d.match_scene``, gate one
  radius) lies within 2 cm of the true centre, over the group's balls (a miss is a failure);
- the 2D mAP.50 (COCO protocol, circle IoU): over the group's images, with the balls of other
  bands as COCO's ignored ground truth (``coco_eval.evaluate_circles(keep_gt=...)``): a
  detection matched to one of those counts nowhere, and a detection matched to no ball is a
  false positive in every band (it has no distance of its own: 2D methods give none).

A row: {subpixel, correlation, dropouts (the axes grouped on), band, n_images, n_balls, found_2cm,
within_2cm, mAP50}; the 3D fields are None for a method without 3D centres, mAP50 None where no
ball of the band is in the group (and no detection could be scored).
"""

from __future__ import annotations

import math
from typing import Callable, Mapping, Sequence

import numpy as np

from spherebench.eval.metrics.coco_eval import evaluate_circles, load_ground_truth

#: The grid's axes, as a scene's sensor_cell names them.
GRID_AXES = ("subpixel", "correlation", "dropouts")
#: Range bands of the ball's true distance (m, to its nearest surface); [lo, hi), the last closed.
RANGE_BANDS_M = ((0.0, 1.0), (1.0, 2.0), (2.0, 3.0))
#: A ball is detected when its matched detection's centre is within this of the truth (m).
DETECTED_M = 0.02


def band_label(band: tuple[float, float]) -> str:
    """'0-1 m' for (0.0, 1.0)."""
    return f"{band[0]:g}-{band[1]:g} m"


def level_label(value) -> str:
    """A grid level as the tables print it: 0.20 for 0.2 (two decimals where they suffice), labels as they are."""
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        return f"{value:.2f}" if round(float(value), 2) == float(value) else f"{value:g}"
    return str(value)


def band_of(distance_m: float, bands: Sequence[tuple[float, float]] = RANGE_BANDS_M) -> str | None:
    """The label of the band holding a distance (m), or None (outside every band, or not finite)."""
    d = float(distance_m)
    for k, (lo, hi) in enumerate(bands):
        if lo <= d < hi or (k == len(bands) - 1 and d == hi):
            return band_label((lo, hi))
    return None


def surface_distance_m(centre_m, radius_m: float) -> float:
    """Distance from the camera to a ball's nearest surface: ||centre|| - R (m)."""
    return float(np.linalg.norm(np.asarray(centre_m, np.float64))) - float(radius_m)


def grid_key(cell: Mapping | None, axes: Sequence[str] = GRID_AXES) -> tuple | None:
    """The levels of ``axes`` in a scene's sensor cell, or None (no cell, or an axis missing)."""
    if not cell or any(a not in cell for a in axes):
        return None
    return tuple(cell[a] for a in axes)


def detection_rates(keys: Sequence[tuple | None], errors_m, threshold_m: float = DETECTED_M) -> dict[tuple, dict]:
    """{key: {n_balls, found, rate}} over the balls with a key (one key per ball, None = none);
    errors_m: each ball's centre error (m), NaN where missed."""
    err = np.nan_to_num(np.asarray(errors_m, np.float64).reshape(-1), nan=np.inf)
    if len(keys) != err.size:
        raise ValueError(f"{len(keys)} keys for {err.size} balls")
    out: dict[tuple, dict] = {}
    for key, e in zip(keys, err):
        if key is None:
            continue
        g = out.setdefault(key, {"n_balls": 0, "found": 0})
        g["n_balls"] += 1
        g["found"] += int(e <= threshold_m)
    for g in out.values():
        g["rate"] = g["found"] / g["n_balls"]
    return out


def map50_by_group(coco_gt, results: Sequence[dict], image_keys: Mapping[int, tuple | None],
                   ann_band: Callable[[dict], str | None],
                   bands: Sequence[tuple[float, float]] = RANGE_BANDS_M) -> dict[tuple, dict]:
    """{key + (band,): {n_images, n_gt, mAP50}}: COCO mAP.50 of each group of images (``image_keys``:
    image id -> group key, None = in no group) and band, the balls of other bands ignored.

    coco_gt: a COCO object (``coco_eval.load_ground_truth``) or dict; ann_band(annotation) gives
    an annotation's band label (``band_of``)."""
    gt = coco_gt if hasattr(coco_gt, "getImgIds") else load_ground_truth(coco_gt)
    groups: dict[tuple, list[int]] = {}
    for image_id, key in image_keys.items():
        if key is not None:
            groups.setdefault(key, []).append(image_id)
    out: dict[tuple, dict] = {}
    for key, ids in groups.items():
        members = set(ids)
        sub = [r for r in results if r["image_id"] in members]
        for band in bands:
            label = band_label(band)
            ev = evaluate_circles(gt, sub, image_ids=ids, keep_gt=lambda a, b=label: ann_band(a) == b)
            ap = ev["mAP50"]
            out[key + (label,)] = {"n_images": len(ids), "n_gt": ev["n_gt"],
                                   "mAP50": None if math.isnan(ap) else float(ap)}
    return out


def grid_rows(scene_keys: Sequence[tuple | None], rates: Mapping[tuple, dict] | None,
              maps: Mapping[tuple, dict] | None, axes: Sequence[str] = GRID_AXES,
              bands: Sequence[tuple[float, float]] = RANGE_BANDS_M) -> list[dict]:
    """The rows of ``detection_rates`` and ``map50_by_group`` merged, one per (group, band), groups
    in the order they first appear in ``scene_keys`` (scene order), bands in order."""
    order = list(dict.fromkeys(k for k in scene_keys if k is not None))
    rows = []
    for key in order:
        for band in bands:
            label = band_label(band)
            r = (rates or {}).get(key + (label,))
            m = (maps or {}).get(key + (label,))
            rows.append({**dict(zip(axes, key)), "band": label,
                         "n_images": sum(1 for k in scene_keys if k == key),
                         "n_balls": (r or {}).get("n_balls", 0) if rates is not None else (m or {}).get("n_gt"),
                         "found_2cm": None if rates is None else (r or {}).get("found", 0),
                         "within_2cm": None if rates is None or r is None else r["rate"],
                         "mAP50": None if m is None else m["mAP50"]})
    return rows


def ceiling_key(row: Mapping) -> tuple:
    """The key of a row in a ceiling dict: (subpixel, correlation, dropouts, band label)."""
    return (row["subpixel"], row["correlation"], row["dropouts"], row["band"])


def ceiling_by_cell(balls: Sequence[Mapping], axes: Sequence[str] = GRID_AXES) -> dict[tuple, float]:
    """A per-cell ceiling for the robustness figure from an oracle's per-ball rows ({cell (a sensor_cell),
    band, separable}, ``studies.oracle_balls``): {key + (band,): share of the group's balls that are
    separable} (``eval.bench.oracle``: verified from the true centre to within 2 cm at the right size,
    with a score above every clutter sphere of the frame). Balls without a cell or band are left out."""
    groups: dict[tuple, list[bool]] = {}
    for b in balls:
        key = grid_key(b.get("cell"), axes)
        if key is not None and b.get("band") is not None:
            groups.setdefault(key + (b["band"],), []).append(bool(b.get("separable")))
    return {k: sum(v) / len(v) for k, v in groups.items()}
