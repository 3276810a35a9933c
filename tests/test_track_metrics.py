"""The tracking scores (``eval.metrics.tracking``) on hand-made frames: a perfect answer, an identity
switch, a break, a false answer, a ball barely seen, a distractor taken, and the rates."""

from __future__ import annotations

import numpy as np
import pytest

from spherebench.eval.metrics import tracking as T

R = 0.12


def _truth(centre, visible=1.0, distractor=None):
    return T.FrameTruth(np.array([0]), np.array([centre], float), np.array([visible]),
                        np.zeros((0, 3)) if distractor is None else np.array([distractor], float))


def _answer(*pairs, confirmed=None):
    ids = np.array([i for i, _ in pairs], np.int64)
    centres = np.array([c for _, c in pairs], float).reshape(-1, 3)
    return T.Answers(ids, centres, None if confirmed is None else np.array(confirmed, bool))


def test_a_track_on_the_ball_every_frame_is_found_with_no_switch():
    truth = [_truth([0.1 * k, 0.0, 2.0]) for k in range(5)]
    answers = [_answer((3, [0.1 * k + 0.005, 0.0, 2.0])) for k in range(5)]
    c = T.sequence_counts(truth, answers, R)
    assert (c["balls"], c["found"], c["matched"], c["switches"], c["fragments"], c["false"]) == (5, 5, 5, 0, 0, 0)
    s = T.summary(c)
    assert s["found_share"] == 1.0 and s["rmse_m"] == pytest.approx(0.005) and s["mota"] == 1.0
    assert c["near"] == 5 and s["found_near_share"] == 1.0  # 2 m: within the near range


def test_an_id_change_is_a_switch_a_gap_a_break_and_a_far_answer_false():
    truth = [_truth([0.0, 0.0, 3.0]) for _ in range(6)]
    answers = [_answer((1, [0, 0, 3.0])), _answer((1, [0, 0, 3.03])), _answer(), _answer((2, [0, 0, 3.0])),
               _answer((2, [0, 0, 3.0]), (7, [1.0, 0, 3.0])), _answer((2, [0, 0, 3.0]))]
    c = T.sequence_counts(truth, answers, R)
    assert c["switches"] == 1 and c["fragments"] == 1 and c["misses"] == 1 and c["false"] == 1
    assert c["found"] == 4 and c["matched"] == 5  # 3 cm off: on the ball, not found
    assert c["near"] == 0  # 3 m: beyond the near range
    assert T.summary(c)["mota"] == pytest.approx(1 - (1 + 1 + 1) / 6)
    assert T.summary(c)["switches_per_100"] == pytest.approx(20.0)


def test_a_ball_barely_seen_counts_for_nothing_either_way():
    truth = [_truth([0, 0, 2.0], visible=0.1), _truth([0, 0, 2.0], visible=0.1)]
    c = T.sequence_counts(truth, [_answer((0, [0, 0, 2.0])), _answer()], R)
    assert c["balls"] == 0 and c["false"] == 0 and c["misses"] == 0


def test_a_distractor_counts_when_a_confirmed_answer_is_on_it_within_range():
    near = _truth([0, 0, 2.0], distractor=[1.0, 0, 2.0])
    far = _truth([0, 0, 2.0], distractor=[1.0, 0, 3.5])
    on = (5, [1.0, 0, 2.0])
    c = T.sequence_counts([near, near, far], [_answer(on, confirmed=[True]), _answer(on, confirmed=[False]),
                                              _answer((5, [1.0, 0, 3.5]), confirmed=[True])], R)
    assert c["distractor_frames"] == 1 and c["false"] == 3  # every answer off the target is false
    with pytest.raises(ValueError, match="frames"):
        T.sequence_counts([near], [], R)


def test_counts_add_over_sequences():
    a = T.sequence_counts([_truth([0, 0, 2.0])], [_answer((0, [0, 0, 2.0]))], R)
    b = T.sequence_counts([_truth([0, 0, 2.0])], [_answer()], R)
    total = T.add_counts([a, b])
    assert total["balls"] == 2 and total["found"] == 1 and T.summary(total)["found_share"] == 0.5


def test_track_bench_scores_a_small_motion_dataset_and_refuses_others(tmp_path, capsys):
    pytest.importorskip("rosbags")
    pytest.importorskip("pyrealsense2")
    import json

    from spherebench.datasets import sequences
    from spherebench.scripts import cli, track_bench

    data = tmp_path / "tiny"
    seq = sequences.build_sequence("soccer", 5, fps=30, duration_s=0.4)
    sequences.write_sequence(data / "sequences" / "soccer_0000", seq)
    (data / "dataset.json").write_text(json.dumps({"kind": "sequences", "ball_radius_m": 0.12,
                                                   "sensor_model": "analytic"}))
    (data / "sequences" / "notes.txt").write_text("not ours")  # passed over
    out = tmp_path / "report" / "track_bench"
    out.parent.mkdir()
    argv = [str(data), "--out", str(out), "--figure", str(tmp_path / "lat.png"), "--no-real-time",
            "--budget-ms", "none"]
    assert cli.run_module("track_bench", track_bench, argv) == 0
    report = json.loads(out.with_suffix(".json").read_text())
    rows = {(g["family"], g["method"]): g for g in report["groups"]["tiny"]}
    assert rows["soccer", "track"]["balls"] == len(seq.times_s) == 12 and rows["soccer", "track"]["dropped"] is None
    assert rows["soccer", "track"]["found"] >= rows["soccer", "detect"]["found"] > 6  # of 12 ball-frames
    assert (tmp_path / "lat.png").stat().st_size > 0 and "## Targets" in out.with_suffix(".md").read_text()
    capsys.readouterr()
    assert cli.run_module("track_bench", track_bench, [str(tmp_path / "report")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "not a dataset of moving-ball recordings" in err[0]
    theirs = tmp_path / "theirs.png"  # a picture the user made: never overwritten
    theirs.write_bytes(b"not ours")
    assert cli.run_module("track_bench", track_bench, [str(data), "--figure", str(theirs), "--no-real-time"]) == 2
    assert "was not written by SphereBench" in capsys.readouterr().err and theirs.read_bytes() == b"not ours"


def test_each_sequence_warms_the_detector_before_either_method_is_timed(tmp_path, monkeypatch):
    """A stream's first frames at a new size pay for cold buffers and caches: each sequence's first
    ``WARM_FRAMES`` are played untimed through the detector first, so that neither method pays them
    for the other."""
    pytest.importorskip("rosbags")
    pytest.importorskip("pyrealsense2")
    from spherebench.datasets import sequences
    from spherebench.eval.bench import tracks
    from spherebench.method import config_for

    folder = sequences.write_sequence(tmp_path / "rolling_0000", sequences.build_sequence("rolling", 1, fps=30,
                                                                                          duration_s=0.3))
    played = []  # (method, frames it yielded)

    def counted(name, fn):
        def run(*args, **kwargs):
            played.append([name, 0])
            for r in fn(*args, **kwargs):
                played[-1][1] += 1
                yield r
        return run

    monkeypatch.setattr(tracks.stream, "detect_stream", counted("detect", tracks.stream.detect_stream))
    monkeypatch.setattr(tracks.stream, "track_stream", counted("track", tracks.stream.track_stream))
    config = config_for("improved")
    rows = tracks.bench_sequence(folder, config, config.radius_m, real_time=False)
    assert [r["method"] for r in rows] == list(tracks.METHODS)
    assert played == [["detect", tracks.WARM_FRAMES], ["track", 9], ["detect", 9]]
