"""Which depth mode for which range: the resolution study of `make eval`.

`default-stereo`'s scenes are rendered through the stereo sensor model at the D435's three depth
modes of the benchmark (the presets `default-stereo` at 424x240, `default-stereo-848` at 848x480 and
`default-stereo-1280` at 1280x720: one seed stream, so the same layouts, within the few mm that the
image's border moves a ball drawn in view). ``resolution_study`` runs the improved detector and its
ceiling (``own-pixel-fit``: a sphere of radius R fitted from each ball's true centre on its own
pixels) on each, and ``resolution_table`` sets the share of balls found per range band side by side:
a detection at the operating point within 2 cm of the ball's centre (3 cm beyond 3 m,
``metrics3d.found_by_band``), with the detector's median time per frame.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from pathlib import Path

from spherebench.datasets import inout
from spherebench.errors import SphereBenchError
from spherebench.eval.bench.registry import build_methods
from spherebench.eval.bench.scoring import ScoredSet, score_set
from spherebench.eval.bench.tables import Table, fmt
from spherebench.eval.bench.tasks import dataset_scenes, run_methods
from spherebench.eval.metrics.metrics3d import DISTANCE_BANDS_M, band_name

#: The study's datasets (presets under the benchmark's data folder), by depth mode.
RESOLUTION_PRESETS = {"424x240": "default-stereo", "848x480": "default-stereo-848", "1280x720": "default-stereo-1280"}
#: The detector and its ceiling.
METHODS = ("improved", "own-pixel-fit")


def missing_presets(data: Path) -> list[str]:
    """The study's presets not built under ``data``."""
    return [name for name in RESOLUTION_PRESETS.values() if not (Path(data) / name / "coco_gt.json").is_file()]


def resolution_study(data: Path, out: Path, seed: int = 0, workers: int = 2, force: bool = False,
                     log: Callable[[str], None] = print, engine: str = "local",
                     address: str | None = None) -> dict[str, list[ScoredSet]]:
    """The improved detector and its ceiling on each depth mode's dataset: {resolution: [scored
    set of each method's exact-silhouette output]}. Predictions go to OUT/predictions/<preset> (a
    finished set with the same inputs is reused, `default-stereo`'s from the benchmark itself)."""
    data, out = Path(data), Path(out)
    missing = missing_presets(data)
    if missing:
        raise SphereBenchError(f"the resolution study's datasets are missing: {', '.join(missing)}; build them "
                               "with `make data-resolution`")
    sets: dict[str, list[ScoredSet]] = {}
    for resolution, preset in RESOLUTION_PRESETS.items():
        data_dir = data / preset
        radius_m = float(inout.read_dataset_meta(data_dir).get("ball_radius_m", 0.12))
        specs = build_methods(METHODS, radius_m=radius_m)
        log(f"resolution study: {', '.join(METHODS)} on {data_dir} ({resolution})")
        paths = run_methods(data_dir, out / "predictions" / preset, specs, seed=seed, workers=workers,
                            progress=False, force=force, log=log, engine=engine, address=address)
        coco, scenes = inout.read_coco_gt(data_dir), dataset_scenes(data_dir)
        sets[resolution] = [score_set(paths[spec.name], coco, scenes) for spec in specs]
    return sets


def resolution_table(sets: Mapping[str, Sequence[ScoredSet]]) -> Table:
    """One row per depth mode and method: the balls, and per band of surface distance the share found
    with its ball count, and the median time per frame."""
    bands = [band_name(b) for b in DISTANCE_BANDS_M]
    rows = []
    for resolution, scored in sets.items():
        for s in scored:
            by_band = (s.metrics.get("3d") or {}).get("found_by_band") or {}
            cells = []
            for band in bands:
                b = by_band.get(band) or {}
                cells.append(f"{fmt(b.get('found'))} ({b.get('balls', 0)})" if b.get("balls") else "–")
            ms = s.metrics.get("ms_median")
            rows.append([resolution, s.output, str((s.metrics.get("3d") or {}).get("n_gt", "–"))] + cells
                        + [fmt(ms, 1) if s.output == "improved" else "–"])
    return Table(name="resolution", title="Which depth mode for which range (`default-stereo`'s scenes at each mode)",
                 columns=["depth mode", "method", "balls"] + [f"found {b}" for b in bands] + ["median ms"],
                 rows=rows,
                 notes=["The same 200 layouts (`default-stereo`'s seed stream) rendered through the stereo sensor "
                        "model at each depth mode (presets `default-stereo`, `default-stereo-848`, `default-stereo-1280`).",
                        "Found: a detection at the operating point (score >= 0.67) within 2 cm of the ball's centre, "
                        "3 cm beyond 3 m, per band of surface distance |c| - R (balls in brackets). `own-pixel-fit` is "
                        "the ceiling of the data, not a detector: a sphere of radius R fitted from each ball's true "
                        "centre on its own pixels.",
                        "Median ms: the improved detector's time per frame on this machine (`timings` for the "
                        "benchmark's own)."])
