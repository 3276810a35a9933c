"""The experiment scripts of docs/experiments/scripts/ on a few generated `train` scenes: each runs, writes
its fields, and agrees with the library where the two measure the same thing."""

from __future__ import annotations

import ast
import importlib
import json
import sys
from pathlib import Path

import numpy as np
import pytest

from spherebench.datasets import inout, simulate
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
        doc = ast.get_docstring(ast.parse(path.read_text()))  # a retired script may not import at this commit
        assert doc and len(doc.split()) > 20, path.name
        if not path.stem.endswith("_support"):
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




def test_frame_cost_splits_the_time_and_both_thread_counts_agree(train4, tmp_path, capsys):
    import numba

    threads = min(2, numba.config.NUMBA_NUM_THREADS)
    res, text = _run("frame_cost", [str(train4), "--passes", "2", "--threads", str(threads)], tmp_path, capsys)
    assert len(res["frames"]) == 4
    for r in res["frames"]:
        assert r["same_detections"]  # the detections do not depend on the thread count
        assert 0.0 < r["kernel_ms"] < r["one_thread_ms"] < 5000.0 and 0.0 < r["threads_ms"] < 5000.0
    for s in res["summary"]:
        assert 0.0 < s["kernel_share"] < 1.0 and s["bound_median_ms"] < s["one_median_ms"]
        frames = [r for r in res["frames"] if r["resolution"] == s["resolution"]]
        assert s["threads_slowest"] == max(frames, key=lambda r: r["threads_ms"])["scene"]
        assert s["threads_max_over_median"] >= 1.0
        assert s["one_max_over_median"] == pytest.approx(max(r["one_thread_ms"] for r in frames) / s["one_median_ms"])
    assert "kernels halved" in text and "slowest / median" in text


def test_code_sizes_counts_a_checkouts_modules_and_long_functions(tmp_path, capsys):
    import subprocess

    def git(*args):
        subprocess.run(["git", *args], cwd=tmp_path, check=True, capture_output=True)

    git("init", "-q")
    (tmp_path / "pkg").mkdir()
    (tmp_path / "tests").mkdir()
    body = "\n".join(f"    x{i} = {i}" for i in range(90))
    (tmp_path / "pkg" / "long.py").write_text(f"def long():\n{body}\n\n\ndef short():\n    return 1\n")
    (tmp_path / "tests" / "test_x.py").write_text("def test_left_out():\n    pass\n")
    git("add", ".")
    sizes, out = _run("code_sizes", [str(tmp_path), "--over", "80"], tmp_path, capsys)
    assert sizes["functions"] == 2 and sizes["long_functions"] == [[91, "pkg/long.py:long"]]
    assert sizes["modules"] == [[95, "pkg/long.py"]] and "over 80 lines: 1" in out


def test_holes_only_and_none_split_a_dataset_by_its_gt_hole_fraction(train4, tmp_path):
    support = _script("script_support")
    holes2 = simulate.generate_dataset("holes", tmp_path / "holes2", n=2, progress=False)
    for data in (train4, holes2):
        every = support.frame_scenes(data)
        only, none = support.frame_scenes(data, holes="only"), support.frame_scenes(data, holes="none")
        assert sorted(s.scene_id for s in only + none) == sorted(s.scene_id for s in every)
        for s in every:
            fractions = inout.read_scene_gt(s.path)["meta"].get("hole_fraction", [])
            assert (s in only) == any(f is not None for f in fractions)
    assert len(support.frame_scenes(holes2, holes="only")) == 2


def test_per_ball_by_range_counts_the_ranked_candidates(train4, tmp_path, capsys):
    res, text = _run("per_ball", [str(train4), "--seeds", "0", "--workers", "1", "--by-range"], tmp_path, capsys)
    rows = res["by_range"]["a"]
    assert sum(r["balls"] for r in rows) == 4 and "ranked within 2 cm" in text
    for r in rows:
        assert r["found_far_rule"] <= r["ranked_2cm"] <= r["ranked_6cm"] <= r["balls"]


def test_size_resolution_reads_the_free_radius_of_both_balls(train4, tmp_path, capsys):
    sizes = _script("size_resolution")
    small = simulate.generate_dataset("train", tmp_path / "train4-r011", n=4, radius_m=0.11, progress=False)
    big_lines, small_lines = tmp_path / "big.jsonl", tmp_path / "small.jsonl"
    assert sizes.main(["collect", str(train4), str(big_lines), "--workers", "1"]) == 0
    assert sizes.main(["collect", str(small), str(small_lines), "--workers", "1"]) == 0
    big = [json.loads(t) for t in big_lines.read_text().splitlines()]
    little = [json.loads(t) for t in small_lines.read_text().splitlines()]
    assert len(big) == len(little) == 4
    assert {x["true_radius_m"] for x in big} == {0.12} and {x["true_radius_m"] for x in little} == {0.11}
    # each ball verified from its truth: a free radius near a ball's size, with a standard error
    fits = [x for x in big + little if "free_radius_m" in x and x["error_m"] <= 0.02]
    assert len(fits) >= 6 and all(0.08 < x["free_radius_m"] < 0.16 and x["free_radius_se_m"] > 0 for x in fits)
    capsys.readouterr()
    assert sizes.main(["report", f"analytic={big_lines}:{small_lines}"]) == 0
    assert "| sensor | band (m) |" in capsys.readouterr().out


@pytest.fixture(scope="module")
def soccer_recording(tmp_path_factory):
    """A dataset of one short `soccer` recording (424x240, 30 fps, 12 frames): the basketball 2.1-2.7 m
    away and a 0.11 m ball beside it."""
    pytest.importorskip("rosbags")
    pytest.importorskip("pyrealsense2")
    from spherebench.datasets import sequences

    root = tmp_path_factory.mktemp("motion")
    seq = sequences.build_sequence("soccer", 3, fps=30, duration_s=0.4)
    return root, sequences.write_sequence(root / "sequences" / "soccer_0003", seq)


def test_track_ceiling_feeds_the_tracker_the_verifications_from_the_truth(soccer_recording, capsys):
    root, folder = soccer_recording
    r = _script("track_ceiling").sequence_ceiling(folder, config_for("improved"), 1, True)
    c = r["counts"]
    # a clean analytic ball 2-3 m away: every verification from its centre accepted within 2 cm
    assert r["mode"] == "424x240" and c["balls"] == 12 and r["n"] == c["near"] > 0 and r["hit"] == r["n"]
    assert c["found"] == c["balls"] and c["found_near"] == c["near"] and c["switches"] == 0
    assert _script("track_ceiling").main([str(root), "--tracked", "--every", "3"]) == 0
    out = capsys.readouterr().out
    assert f"the tracker fed from the truth: within 2 cm on {c['near']} of {c['near']}" in out


def test_track_radius_reads_the_basketball_and_the_smaller_ball_apart(soccer_recording):
    _, folder = soccer_recording
    radii = _script("track_radius").sequence_radii(folder, config_for("improved"))
    ball = np.array([r for r, _, _ in radii["ball"]])
    other = np.array([r for r, _, _ in radii["other"]])
    assert len(ball) == 12 and all(a for _, _, a in radii["ball"])
    assert abs(np.median(ball) - 0.12) < 0.002 and len(other) and np.median(other) < np.median(ball) - 0.003


def test_track_cost_classes_each_frame_of_a_tracked_stream(soccer_recording):
    root, _ = soccer_recording
    rows = _script("track_cost").frame_costs(str(root), "424x240", config_for("improved"))
    assert len(rows) == 12 and all(r["ms"] > 0 and r["ball_seen"] for r in rows)
    assert rows[0]["search"] == "full" and not rows[0]["had_track"] and rows[0]["reported"]
    # once its track is confirmed, the ball is looked for about its prediction
    assert any(r["search"] == "local" and r["had_track"] for r in rows)
    assert _script("track_cost").frame_costs(str(root), "848x480", config_for("improved")) == []
