"""The ceiling of the data: each ball's R-fixed fit from the truth on its own pixels (``oracle.own_pixel_fit``),
scored as a method (``own-pixel-fit``), and the per-band found shares it is read by."""

from __future__ import annotations

import json
import math

import numpy as np

from spherebench.datasets import simulate
from spherebench.eval.bench import oracle, registry, tasks
from spherebench.eval.metrics.metrics3d import DISTANCE_BANDS_M, band_name, found_by_band
from test_method_detector import R, scene


def _ball_points(centre, noise_m=0.0, seed=0):
    cloud = scene(ball_c=tuple(centre), noise=noise_m, seed=seed, width=424, height=240)
    near = np.abs(np.linalg.norm(cloud.points - np.asarray(centre), axis=1) - R) < 0.03
    return cloud.points[near & (cloud.points[:, 2] < centre[2])]


def test_the_fit_on_a_balls_own_pixels_finds_its_centre():
    c = np.array([0.1, -0.05, 1.3])
    pts = _ball_points(c)
    # from a start 3 cm off (the fit does not just return its start)
    assert np.linalg.norm(oracle.own_pixel_fit(pts, c + [0.03, 0.0, 0.0], R) - c) < 1e-3
    noisy = _ball_points(c, noise_m=0.004, seed=1)
    assert np.linalg.norm(oracle.own_pixel_fit(noisy, c, R) - c) < 0.01


def test_the_fit_refuses_too_few_pixels_and_a_wall():
    c = np.array([0.0, 0.0, 1.2])
    assert oracle.own_pixel_fit(_ball_points(c)[: oracle.OWN_PIXELS_MIN - 1], c, R) is None
    wall = scene(ball_c=None, wall_z=1.2).points  # no sphere: it runs off the truth or finds none
    got = oracle.own_pixel_fit(wall[:2000], c + [0.0, 0.0, 0.12], R)
    assert got is None or np.linalg.norm(got - c) > 0.02


def test_found_by_band_takes_the_far_rule_per_band():
    errors = [0.01, np.nan, 0.025, 0.025, 0.001]
    depths = [1.0, 1.2, 2.0, 3.3, 4.0]
    distances = [0.9, 1.1, 1.9, 3.2, 3.9]
    got = found_by_band(errors, depths, distances)
    assert list(got) == [band_name(b) for b in DISTANCE_BANDS_M] == ["0-1.5 m", "1.5-2.5 m", "2.5-3.5 m", "3.5+ m"]
    assert got["0-1.5 m"] == {"balls": 2, "found": 0.5}
    assert got["1.5-2.5 m"] == {"balls": 1, "found": 0.0}  # 2.5 cm at 2 m: beyond the 2 cm rule
    assert got["2.5-3.5 m"] == {"balls": 1, "found": 1.0}  # 2.5 cm at 3.3 m deep: the 3 cm rule
    assert got["3.5+ m"]["found"] == 1.0
    assert math.isnan(found_by_band([], [], [])["0-1.5 m"]["found"])


def test_the_ceiling_is_a_method_beside_the_detector(tmp_path):
    assert registry.METHODS["own-pixel-fit"].role == registry.ROLE_CEILING
    data = simulate.generate_dataset("default", tmp_path / "d", n=3, progress=False)
    specs = registry.build_methods(["improved", "own-pixel-fit"])
    paths = tasks.run_methods(data, tmp_path / "p", specs, workers=1, progress=False, log=lambda m: None)
    fits = json.loads(paths["own-pixel-fit"].read_text())
    assert len(fits) == 3 and all(r["score"] == 1.0 for r in fits)  # one per ball of the analytic model
    from spherebench.scripts.cli import main
    out = tmp_path / "out"
    assert main(["evaluate", "--data", str(data), "--out", str(out), "--methods", "improved", "own-pixel-fit",
                 "--workers", "1", "--quiet", "--no-figures"]) == 0
    metrics = json.loads((out / "metrics.json").read_text())
    ceiling = metrics["own-pixel-fit"]["d"]
    assert ceiling["3d"]["within_2cm"] == 1.0 and ceiling["mAP50"] > 0.9
    assert sum(b["balls"] for b in ceiling["3d"]["found_by_band"].values()) == 3
    table = (out / "tables" / "metrics3d_d.md").read_text()
    assert "own-pixel-fit" in table and "found 0-1.5 m" in table
    # never read as the method that wins
    assert "own-pixel-fit" not in (out / "README.md").read_text().split("## Tables")[0]
    assert "own-pixel-fit" not in (out / "tables" / "calibration.md").read_text()


def test_a_ball_of_unknown_visibility_is_fitted_whole(tmp_path):
    """A recorded set's gt.json gives a reference centre and a mask, and null for what it does not know."""
    data = simulate.generate_dataset("default", tmp_path / "d", n=1, progress=False)
    scene_dir = sorted((data / "scenes").iterdir())[0]
    gt = json.loads((scene_dir / "gt.json").read_text())
    gt["balls"][0]["visible_fraction"] = None
    (scene_dir / "gt.json").write_text(json.dumps(gt))
    adapter = registry.OwnPixelFitAdapter({"radius_m": R})
    (fit,) = adapter.detect(adapter.load(scene_dir), 0)
    assert np.linalg.norm(np.subtract(fit["center_m"], gt["balls"][0]["center_m"])) < 0.02 and fit["circle"]
