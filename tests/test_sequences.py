"""Recordings of moving balls (``datasets.sequences``): every family renders the same frames from the
same seed, its balls in view and truthful frame by frame, and a written sequence plays back as a
RealSense recording of the same depth."""

from __future__ import annotations

import json

import numpy as np
import pytest

from spherebench.camera import project
from spherebench.datasets import sequences
from spherebench.errors import SphereBenchError


@pytest.mark.parametrize("family", list(sequences.SEQUENCE_FAMILIES))
def test_each_family_is_its_seed_and_its_truth_follows_the_ball(family):
    a = sequences.build_sequence(family, 7, fps=10, duration_s=0.6)
    b = sequences.build_sequence(family, 7, fps=10, duration_s=0.6)
    assert np.array_equal(a.depth, b.depth) and a.truth == b.truth
    assert a.depth.shape == (6, 240, 424) and a.depth.dtype == np.uint16 and len(a.truth) == 6
    targets = [m for m in a.balls if m.kind == "target"]
    assert all(len(frame) == len(targets) for frame in a.truth)
    for k, frame in enumerate(a.truth):
        for ball in frame:
            centre = np.asarray(ball["center_m"])
            track = next(m.track for m in targets if m.track.track_id == ball["track_id"])
            assert np.allclose(centre, track.centres_m[k], atol=1e-6)
            if ball["circle_px"] is not None:  # the visible circle lies about the centre's image
                u, v = project(a.intrinsics, centre[None])[0]
                assert np.hypot(ball["circle_px"][0] - u, ball["circle_px"][1] - v) < ball["circle_px"][2]
    seen = [ball["visible_fraction"] for frame in a.truth for ball in frame]
    assert np.median(seen) > 0.8  # the balls are in view (the box of "behind" may hide one for a while)


def test_balls_on_the_floor_rest_on_it_and_the_soccer_ball_is_no_target():
    seq = sequences.build_sequence("soccer", 3, fps=10, duration_s=0.5)
    kinds = {m.kind: m.track for m in seq.balls}
    assert set(kinds) == {"target", "distractor"} and kinds["distractor"].radius_m == sequences.SOCCER_RADIUS_M
    assert all(len(frame) == 1 and frame[0]["track_id"] == kinds["target"].track_id for frame in seq.truth)
    # the soccer ball's own truth: its centre frame by frame, apart from the targets'
    assert all(len(o) == 1 and o[0]["radius_m"] == sequences.SOCCER_RADIUS_M for o in seq.distractors)
    assert np.allclose([o[0]["center_m"] for o in seq.distractors], kinds["distractor"].centres_m, atol=1e-6)
    heights = kinds["target"].centres_m[:, 1] + kinds["target"].radius_m
    assert np.allclose(heights, heights[0])  # rolling: its lowest point on the floor in every frame


def test_a_written_sequence_plays_back_as_a_recording_of_its_frames(tmp_path):
    pytest.importorskip("rosbags")
    pytest.importorskip("pyrealsense2")
    from spherebench.datasets.depth_frames import recording_frames

    seq = sequences.build_sequence("thrown", 2, fps=30, duration_s=0.2)
    folder = sequences.write_sequence(tmp_path / "thrown_0002", seq)
    assert sorted(p.name for p in folder.iterdir()) == ["recording.bag", "truth.json"]
    truth = json.loads((folder / "truth.json").read_text())
    assert truth["fps"] == 30 and len(truth["frames"]) == len(seq.times_s) == 6
    assert truth["balls"] == [{"track_id": 0, "kind": "target", "motion": "thrown", "radius_m": 0.12}]
    played = [np.asarray(f.depth) for f in recording_frames(folder / "recording.bag")]
    assert len(played) == 6 and all(np.array_equal(p, d) for p, d in zip(played, seq.depth))
    (folder / "notes.txt").write_text("mine")  # a folder holding a file of someone else's is not replaced
    with pytest.raises(SphereBenchError):
        sequences.write_sequence(folder, seq)
    assert (folder / "notes.txt").read_text() == "mine"


def test_the_motion_preset_writes_its_recordings_the_same_for_any_number_of_workers(tmp_path, monkeypatch):
    pytest.importorskip("rosbags")
    from spherebench.datasets import simulate

    monkeypatch.setattr(sequences, "SEQUENCE_DURATION_S", (0.05, 0.1))  # a few frames a sequence
    plan = sequences.plan_sequences("motion", 6)
    assert sorted(f for _i, f, _r in plan) == sorted(sequences.SEQUENCE_FAMILIES)  # one of each family
    one = simulate.generate_dataset("motion", tmp_path / "one", n=3, progress=False)
    two = simulate.generate_dataset("motion", tmp_path / "two", n=3, workers=2, progress=False)
    names = sorted(p.name for p in (one / "sequences").iterdir())
    assert names == sorted(p.name for p in (two / "sequences").iterdir()) and len(names) == 3
    for name in names:
        assert (one / "sequences" / name / "truth.json").read_bytes() == (two / "sequences" / name / "truth.json").read_bytes()
    meta = json.loads((one / "dataset.json").read_text())
    assert meta["kind"] == "sequences" and meta["preset"] == "motion" and meta["n"] == 3
    with pytest.raises(SphereBenchError, match="--sensor, --clouds and --sensor-model do not apply"):
        simulate.generate_dataset("motion", tmp_path / "three", n=1, clouds=True, progress=False)
    assert not (tmp_path / "three").exists()


def test_detect_track_follows_the_ball_of_a_recording_with_one_id(tmp_path, capsys):
    pytest.importorskip("rosbags")
    pytest.importorskip("pyrealsense2")
    from spherebench.method.tracking import SIZE_MIN_FRAMES
    from spherebench.scripts import cli

    seq = sequences.build_sequence("rolling", 4, fps=30, duration_s=0.4)
    folder = sequences.write_sequence(tmp_path / "rolling", seq)
    assert cli.main(["detect", str(folder / "recording.bag"), "--track", "--json"]) == 0
    lines = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert len(lines) == len(seq.times_s) == 12 and all("tracks" in line for line in lines)
    assert {line["search"] for line in lines} == {"full", "local"} and "cut_short" not in lines[0]  # no budget
    confirmed = [[t for t in line["tracks"] if t["confirmed"]] for line in lines]
    first = SIZE_MIN_FRAMES - 1  # confirmed once its radius is measured
    assert all(len(c) == 1 and c[0]["track_id"] == 0 for c in confirmed[first:])
    truth = [frame[0]["center_m"] for frame in seq.truth]
    errors = [np.linalg.norm(np.subtract(c[0]["center_m"], t)) for c, t in zip(confirmed[first:], truth[first:])]
    assert max(errors) < 0.05
    assert cli.main(["detect", str(folder / "truth.json"), "--track"]) == 2  # tracks are a recording's
    assert "--track follows balls over a recording" in capsys.readouterr().err


def test_a_clock_that_jumps_back_is_one_line_under_track():
    from types import SimpleNamespace

    from spherebench.scripts import detect

    frames = [SimpleNamespace(number=n, timestamp_ms=t) for n, t in ((7, 1000.0), (8, 1011.0), (9, 990.0))]
    ordered = detect._in_time_order(iter(frames), "r.bag")
    assert [f.number for f in (next(ordered), next(ordered))] == [7, 8]  # what came before is kept
    with pytest.raises(SphereBenchError, match="frame 9's timestamp .* comes before the previous frame's"):
        next(ordered)
