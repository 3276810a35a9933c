"""What the ground-truth scripts share (``stereo_losses.py``, ``noise_structure.py``,
``size_separation.py``): the range bands, the basketball detector's configuration, a scene's simulator
truth rebuilt, a log of every candidate the detector verifies, ray-residual sphere fits, Markdown tables
and resumable JSON-lines output.

Not a command. The scripts beside it import it (``python docs/experiments/scripts/NAME.py`` puts this
folder on ``sys.path``).

``rebuild(scene_dir)`` re-runs ``simulate_scene``'s own loop (the same seed, the same draws) and keeps
what ``render`` computes and the saved Scene drops: the true z image and the label image (which layout
item each pixel shows), so that floor, wall, the ball and distractor spheres can be told apart. The
rebuilt depth must equal the scene's depth.png byte for byte (``rebuild`` says where it does not).

``CandidateLog`` wraps ``verification.verify_organised``, ``verify_noisy`` and ``verify_pushed`` while it
is open (library functions replaced at run time, restored on exit; no library code changes) and records
every top-level verification the detector's ``_verify_candidates`` makes, accepted or not.
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path
from typing import Callable, Iterable

import numpy as np

from spherebench.camera import Intrinsics, image_rays
from spherebench.datasets import families, inout, presets, rendering
from spherebench.datasets.primitives import raycast
from spherebench.datasets.sensor import D435Sensor
from spherebench.datasets.stereo import StereoSensor
from spherebench.eval.metrics.metrics3d import FOUND_M  # noqa: F401  (a detection this near a ball finds it, m)
from spherebench.method import config_for, verification
from spherebench.method.config import DetectorConfig

#: Range bands of a ball's surface distance |c| - R (m), as ``spherebench robustness`` bands it.
BANDS = ((0.0, 1.5), (1.5, 2.5), (2.5, 3.5), (3.5, 5.0))
BAND_NAMES = tuple(f"{lo:g}-{hi:g}" for lo, hi in BANDS)
#: A verified candidate this near a ball was started at it (m): the detector's match gate, about R.
GATE_M = 0.12
#: The basketball detector's radius: every dataset is detected as a basketball detector would (m).
BASKETBALL_M = 0.12


def band_of(distance_m: float) -> str | None:
    """The band name of a surface distance (m); None beyond 5 m."""
    for (lo, hi), name in zip(BANDS, BAND_NAMES):
        if lo <= distance_m < hi:
            return name
    return None


def study_config(overrides: dict | None = None, radius_m: float = BASKETBALL_M) -> DetectorConfig:
    """The improved detector as the benchmark's adapter builds it, at ``radius_m``, with ``overrides``
    ({path: value}, e.g. {"noise.noise_z2_per_m": 0.02})."""
    return config_for("improved", dict(overrides or {}), radius_m=radius_m)


def dist(a, b) -> float:
    return math.dist(a, b)


def range_lateral(estimate_m, truth_m) -> tuple[float, float]:
    """An estimated centre's error split along the true centre's ray (range, + = behind) and across it
    (lateral), in metres."""
    ct = np.asarray(truth_m, float)
    u = ct / np.linalg.norm(ct)
    d = np.asarray(estimate_m, float) - ct
    r = float(d @ u)
    return r, float(np.linalg.norm(d - r * u))


def robust_sigma(x) -> float:
    """1.4826 MAD (NaN when empty)."""
    x = np.asarray(x, float)
    return 1.4826 * float(np.median(np.abs(x - np.median(x)))) if len(x) else float("nan")


def median_range(x, fmt: str = ".1f") -> str:
    """"median [q10, q90]" of x."""
    return f"{np.median(x):{fmt}} [{np.quantile(x, 0.1):{fmt}}, {np.quantile(x, 0.9):{fmt}}]"


def table(header: list, rows: Iterable) -> str:
    """A Markdown table."""
    s = "| " + " | ".join(str(h) for h in header) + " |\n|" + "---|" * len(header) + "\n"
    for r in rows:
        s += "| " + " | ".join(str(c) for c in r) + " |\n"
    return s


def read_jsonl(path: str | Path) -> list[dict]:
    """The records of a JSON-lines file (none when it does not exist)."""
    p = Path(path)
    return [json.loads(x) for x in p.read_text().splitlines() if x.strip()] if p.exists() else []


def named_paths(items: list[str]) -> list[tuple[str, str]]:
    """NAME=PATH arguments as (name, path) pairs."""
    out = []
    for item in items:
        if "=" not in item:
            raise SystemExit(f"{item!r}: give NAME=PATH")
        out.append(tuple(item.split("=", 1)))
    return out


def collect_jsonl(dataset: str | Path, out_path: str | Path, record: Callable[[int, Path], dict],
                  limit: int | None = None, every: int = 20) -> int:
    """``record(k, scene_dir)`` for every scene of the dataset (k its index in scene-id order) into
    one JSON line each, appended to ``out_path``; scenes already there are skipped (resumable).
    Returns the number of scenes written."""
    out = Path(out_path)
    out.parent.mkdir(parents=True, exist_ok=True)
    done = {r["scene"] for r in read_jsonl(out)}
    scenes = inout.list_scenes(dataset)[:limit]
    t0, n = time.time(), 0
    with out.open("a") as fh:
        for k, sd in enumerate(scenes):
            if sd.name in done:
                continue
            fh.write(json.dumps(record(k, sd)) + "\n")
            fh.flush()
            n += 1
            if k % every == 0:
                print(f"{k + 1}/{len(scenes)} {time.time() - t0:.0f} s", flush=True)
    print(f"done: {n} scenes in {time.time() - t0:.0f} s")
    return n


def read_gt(scene_dir: str | Path) -> dict:
    return json.loads((Path(scene_dir) / "gt.json").read_text())


def balls_with_circle(gt: dict) -> list[dict]:
    """The scene's balls that count (a centre and a 2D circle, as ``dataset_scenes`` counts them)."""
    return [b for b in gt.get("balls", []) if b.get("center_m") is not None and b.get("circle") is not None]


def rebuild(scene_dir: str | Path) -> dict:
    """The scene's simulator truth: {depth (H, W) uint16 as rendered, z_true (H, W) m, label (H, W) int
    (0 nothing, k + 1 layout item k), kinds (each item's kind: floor, wall, target, distractor...),
    shapes, intr, gt}. Raises ValueError where the rebuilt depth is not the saved depth.png."""
    scene_dir = Path(scene_dir)
    gt = read_gt(scene_dir)
    meta = gt["meta"]
    preset_name, index, resolution = meta["preset"], int(meta["index"]), meta["resolution"]
    ds = json.loads((scene_dir.parent.parent / "dataset.json").read_text())
    seed = int(ds["seed"])
    preset = presets.PRESETS[preset_name]
    stereo = meta.get("sensor_model") == "stereo"
    rng = np.random.default_rng(presets.generation_seed(preset, seed, index))
    if stereo:
        sensor = rendering.scene_stereo(preset_name, seed, index, StereoSensor())
    else:
        sensor, _cell = rendering.scene_sensor(preset_name, seed, index, D435Sensor(), None)
    w, h = presets.RESOLUTIONS[resolution]
    intr = Intrinsics.d435(w, h)
    intr = Intrinsics(**{**intr.to_dict(), "depth_scale": sensor.depth_scale_m})
    rays = image_rays(intr)
    kind = families.FAMILIES[(preset.grammar, gt["family"])]
    for _attempt in range(40):
        layout = kind.build(rng, intr, float(ds.get("ball_radius_m", 0.12)))
        depth, z_true, balls = rendering.render(layout, intr, sensor, rng, rays)
        if kind.fixed or kind.accept([b.visible_fraction for b in balls]):
            break
    shapes = [it.shape for it in layout.items]
    _z, label = raycast(shapes, rays, intr)
    if not np.array_equal(depth, inout.read_depth_png(scene_dir / "depth.png")):
        raise ValueError(f"{scene_dir}: the rebuilt depth differs from depth.png (another generator?)")
    return {"depth": depth, "z_true": z_true, "label": label, "kinds": [it.kind for it in layout.items],
            "shapes": shapes, "intr": intr, "gt": gt}


class CandidateLog:
    """Context manager: records every candidate the detector verifies at top level (``verify_organised``,
    ``verify_noisy``, ``verify_pushed`` called from ``_verify_candidates``; their inner calls and
    ``rescore``'s are not logged). ``rescore`` updates the logged Candidate, so a logged score is the
    final one. ``verify_noisy`` verifies several hypotheses ahead of their turn: each is logged, also
    those after an accepted one that the detector then leaves unused. ``records``: the Candidates
    (centre_m, score, size_ok, free_radius_m, ...)."""

    NAMES = ("verify_organised", "verify_noisy", "verify_pushed")

    def __init__(self):
        self.records: list = []
        self._depth = 0
        self._orig: dict = {}

    def _wrap(self, orig, log: bool):
        def wrapped(*a, **k):
            top = self._depth == 0
            self._depth += 1
            try:
                v = orig(*a, **k)
            finally:
                self._depth -= 1
            if log and top:
                self.records.extend(x for x in (v if isinstance(v, list) else [v]) if x is not None)
            return v
        return wrapped

    def __enter__(self):
        for n in self.NAMES + ("rescore",):
            self._orig[n] = getattr(verification, n)
            setattr(verification, n, self._wrap(self._orig[n], n != "rescore"))
        return self

    def __exit__(self, *exc):
        for n, f in self._orig.items():
            setattr(verification, n, f)
        return False


def fit_sphere(p: np.ndarray, c0, r0: float, rounds: int = 4):
    """Trimmed least-squares sphere on points p (N, 3) m, from centre c0 and radius r0: each round a
    Gauss-Newton fit on the ray residuals of the kept points, then points beyond 3 robust sigmas of the
    residual (flying pixels, mixed edge depths) dropped. (centre, radius, radius s.e., points kept), or
    None where the fit runs away (radius outside 0.3-3 r0, fewer than 10 points)."""
    c = np.asarray(c0, float).copy()
    r = float(r0)
    keep = np.ones(len(p), bool)
    for _ in range(rounds):
        c, r, se = _gauss_newton_sphere(p[keep], c, r)
        if not (0.3 * r0 < r < 3 * r0) or keep.sum() < 10:
            return None
        res = _ray_residuals(p, c, r)
        s = robust_sigma(res[keep])
        keep = np.abs(res - np.median(res[keep])) <= 3 * s
    return c, r, se, int(keep.sum())


def _ray_residuals(p: np.ndarray, c: np.ndarray, r: float) -> np.ndarray:
    """|p| less the range at which p's ray enters the sphere (c, r); a ray that misses, at its nearest."""
    tm = np.linalg.norm(p, axis=1)
    b = (p / tm[:, None]) @ c
    return tm - (b - np.sqrt(np.maximum(r * r - c @ c + b * b, 0.0)))


def _gauss_newton_sphere(p: np.ndarray, c0, r0: float, iters: int = 20, fixed_r: bool = False):
    """Gauss-Newton on the ray residuals |p| - t(c, r), t the range at which p's ray enters the sphere
    (the depth noise lies along the ray; 3D residuals bias a cap's radius low). Rays that miss the
    current sphere are left out of that step. (c, r, s.e. of r; NaN with ``fixed_r``), or None where
    fewer than 10 rays hit."""
    c = np.asarray(c0, float).copy()
    r = float(r0)
    tm = np.linalg.norm(p, axis=1)
    d = p / tm[:, None]
    J = res = None
    for _ in range(iters):
        b = d @ c
        q = r * r - c @ c + b * b
        ok = q > 1e-10
        if ok.sum() < 10:
            if fixed_r:
                return None
            break
        s = np.sqrt(q[ok])
        res = tm[ok] - (b[ok] - s)
        J = d[ok] + (c - b[ok, None] * d[ok]) / s[:, None]
        if not fixed_r:
            J = np.hstack([J, (-r / s)[:, None]])
        step, *_ = np.linalg.lstsq(J, res, rcond=None)
        c += step[:3]
        if not fixed_r:
            r += float(step[3])
        if np.linalg.norm(step) < 1e-7:
            break
    se = float("nan")
    if not fixed_r and J is not None:
        try:
            cov = np.linalg.inv(J.T @ J) * float(np.sum(res ** 2) / max(len(res) - 4, 1))
            se = float(math.sqrt(max(cov[3, 3], 0.0)))
        except np.linalg.LinAlgError:
            pass
    return c, r, se


def fit_centre(p: np.ndarray, c0, radius_m: float, rounds: int = 4):
    """The centre of a sphere of known radius on points p (N, 3) m: trimmed Gauss-Newton on the ray
    residuals from c0 (3 robust sigmas kept each round); None where it runs away (more than R from c0)."""
    c0 = np.asarray(c0, float)
    c = c0.copy()
    keep = np.ones(len(p), bool)
    for _ in range(rounds):
        fit = _gauss_newton_sphere(p[keep], c, radius_m, iters=15, fixed_r=True)
        if fit is None:
            return None
        c = fit[0]
        if np.linalg.norm(c - c0) > radius_m:
            return None
        res = _ray_residuals(p, c, radius_m)
        keep = np.abs(res - np.median(res[keep])) <= 3 * robust_sigma(res[keep])
    return c
