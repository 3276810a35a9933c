"""The experiment scripts of docs/experiments/scripts/ on a few generated `train` scenes: each runs, writes
its fields, and agrees with the library where the two measure the same thing."""

from __future__ import annotations

import importlib
import json
import math
import sys
from pathlib import Path

import pytest

from spherebench.datasets import simulate
from spherebench.eval.bench.sweep import sweep
from spherebench.method import config_for

SCRIPTS = Path(__file__).resolve().parents[1] / "docs" / "experiments" / "scripts"


@pytest.fixture(scope="module")
def train4(tmp_path_factory):
    """Four `train` scenes (clean, cluttered, distractor: organised depth frames, no clouds)."""
    return simulate.generate_dataset("train", tmp_path_factory.mktemp("data") / "train4", n=4, progress=False)


def _script(name: str):
    if str(SCRIPTS) not in sys.path:
        sys.path.insert(0, str(SCRIPTS))
    return importlib.import_module(name)


def _run(name: str, args: list[str], tmp_path: Path, capsys) -> tuple[dict, str]:
    out = tmp_path / f"{name}.json"
    assert _script(name).main([*args, "--json", str(out)]) == 0
    return json.loads(out.read_text()), capsys.readouterr().out


def test_every_script_says_what_it_measures_and_how_to_run_it():
    for path in SCRIPTS.glob("*.py"):
        doc = _script(path.stem).__doc__
        assert doc and len(doc.split()) > 20, path.name
        if path.stem != "script_support":
            assert f"python docs/experiments/scripts/{path.name}" in doc, path.name


def test_per_ball_totals_are_the_sweeps_and_the_ab_is_consistent(train4, tmp_path, capsys):
    res, text = _run("per_ball", [str(train4), "--seeds", "0", "--workers", "1", "--set-b", "verification.min_score=0.9",
                                  "--frame-noise", "--by-noise", "--list"], tmp_path, capsys)
    a, b = res["a"], res["b"]
    assert len(a["balls"]) == len(b["balls"]) == 4  # one ball per scene, one seed
    for r in a["balls"] + b["balls"]:
        assert set(r) >= {"scene", "ball", "seed", "z_m", "noise_r", "error_mm", "found", "found_far_rule", "score"}
        assert r["found"] == (r["error_mm"] is not None and r["error_mm"] <= 20.0)
        assert r["found_far_rule"] >= r["found"] and 0.5 < r["z_m"] < 6.0 and r["noise_r"] > 0
        assert r["score"] is None or 0.0 <= r["score"] <= 1.0
    # the per-ball count is `spherebench sweep`'s on the same scenes and seed
    swept = sweep([str(train4)], [0], workers=1)["datasets"][train4.name]["per_seed"][0]["total"]
    mine = a["totals"]["0"]
    assert (mine["balls"], mine["found"], mine["false_detections"]) == (
        swept["balls"], swept["found"], swept["false_detections"])
    assert mine["found"] >= 2  # the detector finds most of these balls
    # the differing balls are exactly the difference between the two counts
    only_a = sum(r["found_by"] == "A" for r in res["differ"])
    only_b = sum(r["found_by"] == "B" for r in res["differ"])
    assert only_a - only_b == mine["found"] - b["totals"]["0"]["found"]
    assert sum(g["balls"] for g in res["by_noise"]["a"]) == 4
    assert "Balls found by A only" in text and "| sigma_z / R |" in text
    assert sum(line.startswith("| A | ") for line in text.splitlines()) == 4  # --list: A's four balls


def test_oracle_ceiling_rows_follow_the_acceptance_rule(train4, tmp_path, capsys):
    res, text = _run("oracle_ceiling", [str(train4), "--factors", "--by-noise", "0,0.2,1"], tmp_path, capsys)
    min_score = config_for("improved").verification.min_score
    assert len(res["balls"]) == 4 and sum(g["balls"] for g in res["by_family"]) == 4
    for r in res["balls"]:
        if r["accepted"]:
            assert r["size_ok"] and r["score"] >= min_score and r["error_mm"] <= 20.0
        assert isinstance(r["separable"], bool)
        t = r["truth"]
        assert t["verified"] and {"coverage", "behind", "ring_continued", "size"} <= set(t["factors"])
        assert all(0.0 <= v <= 1.0 for v in t["factors"].values())  # support too: the others' product >= score
        assert 0.5 < t["factors"]["support"] and math.prod(t["factors"].values()) == pytest.approx(t["score"])
        assert 0.0 <= t["visible_fraction"] <= 1.0 and abs(t["free_radius_mm"] - 120.0) < 60.0
        assert r["accepted_far_rule"] >= r["accepted"]
    assert sum(r["accepted"] for r in res["balls"]) >= 3  # from the truth, these near balls verify
    for table in (res["by_family"], res["by_noise"]):
        assert sum(g["balls"] for g in table) == 4
        assert all(g["truth_accepted"] <= g["balls"] and g["accepted"] <= g["within_2cm"] for g in table)
    assert "| family | balls |" in text


def test_ab_timing_of_one_configuration_against_itself(train4, tmp_path, capsys):
    res, text = _run("ab_timing", [str(train4), "--passes", "2", "--control", "paper-lstsq"], tmp_path, capsys)
    assert len(res["frames"]) == 4 and res["configs"][2] == "paper-lstsq"
    for r in res["frames"]:
        assert r["same_detections"]  # A and B are one configuration: bit-identical output
        assert len(r["ms"]) == 3 and all(0.0 < t < 5000.0 for t in r["ms"])
    assert sum(s["frames"] for s in res["summary"]) == 4
    for s in res["summary"]:
        assert s["same_detections"] == s["frames"]
        assert 0.0 < s["ratio_b_a"] < 10.0 and s["ratio_a_control"] > 0.0
    assert "B/A (median of ratios)" in text
