"""The robustness targets on the `robust` preset: pure functions on per-ball and per-scene rows.

A ball row: {cell: (subpixel, correlation, dropouts), band (``sensor_grid.band_of`` label), seed,
found (a detection within 2 cm), within (accepted by the oracle, ``eval.bench.oracle``), separable}; the
ceiling holds for a ball that is separable or that the detector found (``ceiling_holds``). A
scene row: {seed, false (detections farther than 2 cm from every ball)}.

Targets per cell (every subpixel x correlation x dropouts cell, pooled over the seeds):
- balls within 2 m (bands 0-1 and 1-2 m): >= 99 % up to subpixel 0.16 px, >= 97 % at 0.20 px;
- balls at 2-3 m: >= 95 % up to 0.12 px, >= 80 % at 0.16-0.20 px;
- where a target is beyond the ceiling, it becomes 97 % of the ceiling (the data, as the
  detector's evidence sees them, allow no more; ``TARGET_OF_CEILING``).
Overall: the rate on `robust` within 3 points of the rate on `default`; false detections in at
most 0.5 % of the scene runs.
"""

from __future__ import annotations

from typing import Mapping, Sequence

#: The two range groups of the targets, by band label.
NEAR_BANDS = ("0-1 m", "1-2 m")
FAR_BANDS = ("2-3 m",)
#: A cell's target where the ceiling is lower: this share of the ceiling.
TARGET_OF_CEILING = 0.97
#: The overall rate on robust may fall this far below default's (a fraction).
OVERALL_GAP = 0.03
#: False detections: in at most this share of the scene runs.
FALSE_SCENE_SHARE = 0.005


def ceiling_holds(ball: Mapping) -> bool:
    """A ball is within the ceiling when it is separable (``eval.bench.oracle``: verified from about the
    truth to within 2 cm with the right size, its score above every clutter sphere of its frame: some
    score threshold takes it and no false detection there), or the detector found it at this seed:
    the ceiling is never below the rate. ``within`` (the oracle accepts it at the detector's own
    threshold) is reported beside it: where it is far below the ceiling, the evidence's score, not
    the search, loses the ball."""
    return bool(ball.get("separable") or ball["found"])


def nominal_target(subpixel: float, far: bool) -> float:
    """The issue's rate target for a cell's balls within 2 m (far=False) or at 2-3 m (far=True)."""
    if far:
        return 0.95 if subpixel <= 0.12 + 1e-9 else 0.80
    return 0.99 if subpixel <= 0.16 + 1e-9 else 0.97


def cell_table(balls: Sequence[Mapping]) -> list[dict]:
    """One row per (cell, range group): n, found, rate, ceiling, accepted, nominal target, target
    (``TARGET_OF_CEILING`` of the ceiling where the nominal one is beyond it) and ok."""
    groups: dict[tuple, list] = {}
    for b in balls:
        band = b["band"]
        group = "within 2 m" if band in NEAR_BANDS else "2-3 m" if band in FAR_BANDS else None
        if group is None:
            continue
        groups.setdefault((tuple(b["cell"]), group), []).append(b)
    rows = []
    for (cell, group), bs in sorted(groups.items(), key=lambda kv: (kv[0][0], kv[0][1] != "within 2 m")):
        n = len(bs)
        rate = sum(b["found"] for b in bs) / n
        ceil = sum(ceiling_holds(b) for b in bs) / n
        accepted = sum(bool(b["within"]) for b in bs) / n
        nominal = nominal_target(float(cell[0]), group == "2-3 m")
        target = nominal if nominal <= ceil else TARGET_OF_CEILING * ceil  # beyond the data: 97 % of what they allow
        rows.append({"subpixel": cell[0], "correlation": cell[1], "dropouts": cell[2], "range": group, "n": n,
                     "found": int(sum(b["found"] for b in bs)), "rate": rate, "ceiling": ceil, "accepted": accepted,
                     "nominal_target": nominal, "target": target, "ok": rate >= target - 1e-12})
    return rows


def overall(balls: Sequence[Mapping], scenes: Sequence[Mapping], default_rate: float | None) -> dict:
    """Overall figures: the rate on robust (all bands), default's, the gap and its verdict; false
    detections (all, and the share of scene runs with any) and its verdict."""
    n = len(balls)
    rate = sum(b["found"] for b in balls) / n if n else None
    runs = len(scenes)
    with_false = sum(1 for s in scenes if s["false"] > 0)
    out = {"balls": n, "found": int(sum(b["found"] for b in balls)), "rate": rate,
           "ceiling": sum(ceiling_holds(b) for b in balls) / n if n else None,
           "default_rate": default_rate, "scene_runs": runs, "false_detections": int(sum(s["false"] for s in scenes)),
           "scene_runs_with_false": with_false, "false_share": with_false / runs if runs else None}
    out["gap_ok"] = None if rate is None or default_rate is None else rate >= default_rate - OVERALL_GAP
    out["false_ok"] = None if not runs else out["false_share"] <= FALSE_SCENE_SHARE
    return out


def by_level(balls: Sequence[Mapping]) -> list[dict]:
    """Rate and ceiling per subpixel level and band (pooled over correlation and dropouts): the
    figures a closing note quotes."""
    groups: dict[tuple, list] = {}
    for b in balls:
        groups.setdefault((b["cell"][0], b["band"]), []).append(b)
    return [{"subpixel": s, "band": band, "n": len(bs), "found": int(sum(b["found"] for b in bs)),
             "rate": sum(b["found"] for b in bs) / len(bs),
             "ceiling": sum(ceiling_holds(b) for b in bs) / len(bs),
             "accepted": sum(bool(b["within"]) for b in bs) / len(bs)}
            for (s, band), bs in sorted(groups.items())]
