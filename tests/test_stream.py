"""Streaming detection: `spherebench detect` on RealSense recordings (.bag) and a live camera, and the
Python streaming API (spherebench.datasets.depth_frames, spherebench.method.stream), on recordings the
tests write themselves."""

from __future__ import annotations

import json
import time

import numpy as np
import pytest

rs = pytest.importorskip("pyrealsense2")

from spherebench.scripts import cli  # noqa: E402
from spherebench.camera import Intrinsics  # noqa: E402
from spherebench.cloud import cloud_from_depth, depth_to_metres  # noqa: E402
from spherebench.datasets import depth_frames, inout  # noqa: E402
from spherebench.datasets.bagwrite import write_realsense_bag  # noqa: E402
from spherebench.datasets.frame_sources import FrameSelection  # noqa: E402
from spherebench.method import config_for, stream  # noqa: E402
from test_prepare_bag import INTR, render_frames  # noqa: E402

N = 8
EMPTY = 3  # the frame with no depth at all
MISSING = (5,)  # frame numbers the camera lost


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    """8 frames of a ball moving before a wall (frame 3 without depth), numbered 0-8 without 5."""
    frames = render_frames(n=N + len(MISSING))
    numbers = [n for n in range(N + len(MISSING)) if n not in MISSING]
    frames = [frames[n] for n in numbers]
    frames[EMPTY] = np.zeros_like(frames[EMPTY])
    path = write_realsense_bag(tmp_path_factory.mktemp("rec") / "ball.bag", frames, INTR, fps=30,
                               frame_numbers=numbers)
    return path, frames, numbers


def _run(capsys, *argv):
    status = cli.main([str(a) for a in argv])
    cap = capsys.readouterr()
    return status, cap.out, cap.err


def _fails(capsys, *argv, words=()):
    status, out, err = _run(capsys, *argv)
    lines = err.strip().splitlines()
    assert status == 2 and out == "", (status, out, err)
    assert len(lines) == 1 and "error:" in lines[0] and "Traceback" not in err, err
    for w in words:
        assert w in lines[0], lines[0]
    return lines[0]


def test_detect_streams_a_recording_one_line_per_frame(recording, capsys):
    path, frames, numbers = recording
    status, out, err = _run(capsys, "detect", path, "--json")
    assert status == 0, err
    lines = [json.loads(x) for x in out.strip().splitlines()]
    assert [x["frame"] for x in lines] == numbers
    assert [x["timestamp_ms"] for x in lines] == pytest.approx([1000 + n * 1000 / 30 for n in numbers], abs=1e-3)
    for k, rec in enumerate(lines):
        assert rec["input"] == str(path) and rec["ms"] > 0 and rec["radius_m"] == 0.12
        if k == EMPTY:
            assert rec["detections"] == []
            continue
        best = rec["detections"][0]
        n = numbers[k]
        assert np.linalg.norm(np.array(best["center_m"]) - [-0.15 + 0.08 * n, 0.02 * n, 0.9 + 0.05 * n]) < 0.01
    # one note for the frame without depth, one for the lost frame, and the summary
    assert f"frame {numbers[EMPTY]} has no depth" in err
    assert "1 frame(s) before it are missing" in err
    assert f"{N} frame(s)" in err and "median" in err and "p95" in err and "1 missing" in err


def test_frame_selection_as_in_prepare(recording, capsys):
    path, _, numbers = recording
    for args, want in ((["--every", "3"], numbers[::3]), (["--frames", "2:5"], numbers[2:5]),
                       (["--time-range", "30:100"], [1, 2, 3])):
        status, out, err = _run(capsys, "detect", path, "--json", *args)
        assert status == 0, err
        assert [json.loads(x)["frame"] for x in out.strip().splitlines()] == want, args


def test_bad_streams_are_one_line_errors(recording, tmp_path, capsys):
    path, _, _ = recording
    _fails(capsys, "detect", path, "--time-range", "5000:6000", words=("past the end", "ms"))
    colour_only = write_realsense_bag(tmp_path / "colour.bag", [np.zeros((48, 64, 3), np.uint8)] * 2,
                                      INTR, stream="color")
    _fails(capsys, "detect", colour_only, words=("no depth stream",))
    cut = tmp_path / "cut.bag"
    data = path.read_bytes()
    cut.write_bytes(data[: len(data) * 2 // 3])  # ends in the middle of a frame
    _fails(capsys, "detect", cut, words=("cut short",))
    _fails(capsys, "detect", path, "--out-png", tmp_path / "x.png", words=("--labelme-out",))
    _fails(capsys, "detect", tmp_path / "missing.bag", words=("not found",))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["colour.bag", "cut.bag"]  # nothing written


def test_camera_without_a_camera_fails_at_once(capsys):
    if len(rs.context().query_devices()):
        pytest.skip("a RealSense camera is connected")
    t = time.perf_counter()
    _fails(capsys, "detect", "--camera", words=("no RealSense camera is connected",))
    _fails(capsys, "detect", "--camera", "012345678901", "--size", "424x240", "--fps", "90", "--json",
           words=("no RealSense camera",))
    assert time.perf_counter() - t < 30


def test_real_time_drops_frames_a_slow_detector_cannot_keep_up_with(recording, capsys, monkeypatch):
    def slow(cloud, config, seed=0, deadline=None):
        time.sleep(0.2)  # six frame periods at 30 fps
        return []
    monkeypatch.setattr(stream, "detect", slow)
    path, _, _ = recording
    stats = depth_frames.StreamStats()
    frames = depth_frames.recording_frames(path, real_time=True, stats=stats)
    got = [r.frame.number for r in stream.detect_stream(frames, config_for("improved"), stats=stats)]
    assert 1 <= len(got) < N and stats.dropped >= 1
    assert stats.frames == len(got)
    status, out, err = _run(capsys, "detect", path, "--real-time")
    assert status == 0 and "dropped (detection behind the frame rate)" in err


def test_python_api_and_rs_helpers(recording):
    path, frames, numbers = recording
    results = list(stream.detect_stream(depth_frames.recording_frames(path, FrameSelection(first=1, stop=3)),
                                        config_for("improved")))
    assert [r.frame.number for r in results] == numbers[1:3]
    frame, spheres, ms, cut_short = results[0]
    assert np.array_equal(frame.depth, frames[1]) and frame.intrinsics == INTR and ms > 0 and len(spheres) == 1
    assert cut_short is False  # no budget, nothing cut
    # the rs.depth_frame helper, on a frame played back by pyrealsense2's own pipeline
    pipe, cfg = rs.pipeline(), rs.config()
    cfg.enable_device_from_file(str(path), repeat_playback=False)
    profile = pipe.start(cfg)
    try:
        profile.get_device().as_playback().set_real_time(False)
        depth = pipe.wait_for_frames(5000).get_depth_frame()
        cloud = depth_frames.cloud_from_rs_depth(depth)
        intr = Intrinsics.from_rs(depth.get_profile().as_video_stream_profile().get_intrinsics(), depth.get_units())
        played = np.asanyarray(depth.get_data()).copy()
    finally:
        pipe.stop()
    assert intr == INTR  # float32 values read back as the decimals written
    # playback starts in real time, so on a busy machine it may skip the first frame before
    # set_real_time(False) takes hold: compare with whichever recorded frame it delivered
    delivered = [k for k, f in enumerate(frames) if np.array_equal(f, played)]
    assert len(delivered) == 1, "the played frame is none of the recorded ones"
    want = cloud_from_depth(depth_to_metres(frames[delivered[0]], INTR), INTR)
    assert cloud.intrinsics == INTR and np.allclose(cloud.points, want.points) and np.array_equal(cloud.rows, want.rows)


def test_labelme_out_pre_annotates_the_recording(recording, tmp_path, capsys):
    path, _, numbers = recording
    out = tmp_path / "labelme"
    status, stdout, err = _run(capsys, "detect", path, "--frames", "0:3", "--json", "--labelme-out", out)
    assert status == 0, err
    lines = [json.loads(x) for x in stdout.strip().splitlines()]
    files = sorted(p.name for p in out.glob("ball_*.json"))
    assert files == [f"ball_{k:06d}.json" for k in range(3)]
    # prepare reads them back as the scenes' ground truth: the circles detect printed
    status, _, err = _run(capsys, "prepare", path, "--frames", "0:3", "--labelme", out, "--out", tmp_path / "ds")
    assert status == 0, err
    for k, rec in enumerate(lines):
        gt = inout.read_json(tmp_path / "ds" / "scenes" / f"ball_{k:06d}" / "gt.json")
        c = rec["detections"][0]["circle_px"]
        assert gt["balls"][0]["circle"] == pytest.approx(c["center"] + [c["radius"]], abs=0.01)
    # a later run replaces its own folder; a folder of someone else's files is refused
    assert _run(capsys, "detect", path, "--frames", "0:1", "--labelme-out", out)[0] == 0
    assert sorted(p.name for p in out.glob("ball_*.json")) == ["ball_000000.json"]
    (tmp_path / "theirs").mkdir()
    (tmp_path / "theirs" / "notes.txt").write_text("mine")
    _fails(capsys, "detect", path, "--labelme-out", tmp_path / "theirs", words=("did not write",))


def test_rerun_save_writes_a_recording(recording, tmp_path, capsys):
    pytest.importorskip("rerun")
    path, _, _ = recording
    rrd = tmp_path / "ball.rrd"
    status, _, err = _run(capsys, "detect", path, "--frames", "0:3", "--rerun-save", rrd)
    assert status == 0, err
    assert rrd.stat().st_size > 1000
    _fails(capsys, "detect", path, "--rerun-save", rrd, words=("never overwritten",))


def test_intrinsics_from_an_rs_intrinsics():
    i = INTR.to_rs()
    assert isinstance(i, rs.intrinsics) and i.model == rs.distortion.inverse_brown_conrady
    assert Intrinsics.from_rs(i, 0.001) == INTR
    assert Intrinsics.from_dict(i) == INTR  # an rs.intrinsics where a dict is expected


def test_memory_stays_bounded_over_a_long_recording(tmp_path, monkeypatch):
    import tracemalloc

    monkeypatch.setattr(stream, "detect", lambda cloud, config, seed=0, deadline=None: [])  # the stream, not the detector
    intr = Intrinsics.d435(160, 120)
    frame = np.full((120, 160), 1500, np.uint16)  # 38 kB a frame: 300 of them held would be 11 MB
    path = write_realsense_bag(tmp_path / "long.bag", [frame] * 300, intr, fps=90)
    tracemalloc.start()
    try:
        held = []
        for r in stream.detect_stream(depth_frames.recording_frames(path), config_for("improved")):
            if r.frame.index in (50, 299):
                held.append(tracemalloc.get_traced_memory()[0])
    finally:
        tracemalloc.stop()
    assert len(held) == 2 and held[1] - held[0] < 2e6, held


def test_a_viewer_that_cannot_start_is_a_note(recording, tmp_path, capsys, monkeypatch):
    pytest.importorskip("rerun")
    path, _, _ = recording
    monkeypatch.setenv("PATH", str(tmp_path))  # no viewer to be found
    status, out, err = _run(capsys, "detect", path, "--frames", "0:2", "--rerun")
    assert status == 0 and len(out.strip().splitlines()) == 2
    assert "Rerun viewer cannot start" in err and "Traceback" not in err


class _FakeRealSense:
    """Just enough of pyrealsense2 for depth_frames.camera_frames: one D435 whose pipeline delivers the
    given depth frames with the given frame numbers (a gap: frames librealsense dropped)."""

    def __init__(self, frames, numbers, intr=INTR):
        from types import SimpleNamespace as NS

        self.camera_info = NS(serial_number="serial")
        self.stream, self.format = NS(depth="depth"), NS(z16="z16")
        rs_intr = NS(width=intr.width, height=intr.height, ppx=intr.ppx, ppy=intr.ppy, fx=intr.fx, fy=intr.fy,
                     model="distortion." + intr.model, coeffs=list(intr.coeffs))
        profile = NS(as_video_stream_profile=lambda: NS(get_intrinsics=lambda: rs_intr))
        self.stopped = False
        device = NS(get_info=lambda what: "012345678901")
        self.context = lambda: NS(query_devices=lambda: [device])
        self.config = lambda: NS(enable_device=lambda serial: None, enable_stream=lambda *a: None)
        queue = [NS(get_depth_frame=lambda d=d, n=n: NS(get_profile=lambda: profile, get_frame_number=lambda: n,
                                                         get_timestamp=lambda: 1000.0 + n * 100 / 9,
                                                         get_data=lambda: d))
                 for d, n in zip(frames, numbers)]
        sensor = NS(get_depth_scale=lambda: intr.depth_scale)
        started = NS(get_device=lambda: NS(first_depth_sensor=lambda: sensor))

        def stop():
            self.stopped = True
        self.pipeline = lambda: NS(start=lambda config: started, wait_for_frames=lambda timeout: queue.pop(0),
                                   stop=stop)


def test_camera_stream_with_a_fake_camera(monkeypatch, capsys):
    frames = render_frames(n=6)
    fake = _FakeRealSense(frames, [10, 11, 14, 15, 16, 17])
    monkeypatch.setattr(depth_frames, "_rs", lambda: fake)
    status, out, err = _run(capsys, "detect", "--camera", "--size", "64x48", "--fps", "90", "--frames", "0:4",
                            "--json")
    assert status == 0, err
    lines = [json.loads(x) for x in out.strip().splitlines()]
    assert [x["frame"] for x in lines] == [10, 11, 14, 15] and lines[0]["input"] == "camera"
    assert all(len(x["detections"]) == 1 for x in lines)
    assert "4 frame(s)" in err and "2 dropped" in err and fake.stopped
    _fails(capsys, "detect", "--camera", "999", words=("no RealSense camera with serial number 999",))


def test_detect_streams_an_sdk_recording(tmp_path, capsys):
    """A ROS2 .db3, as pyrealsense2 >= 2.56 records, with a lost frame."""
    from spherebench.datasets.bagwrite import record_with_sdk

    frames = render_frames(n=3)
    path = record_with_sdk(tmp_path / "d435.db3", frames, INTR, frame_numbers=[0, 1, 3])
    status, out, err = _run(capsys, "detect", path, "--json")
    assert status == 0, err
    lines = [json.loads(x) for x in out.strip().splitlines()]
    assert [x["frame"] for x in lines] == [0, 1, 3] and all(len(x["detections"]) == 1 for x in lines)
    assert "1 missing" in err


def test_a_recording_left_unfinished_lets_the_process_exit(recording):
    """A consumer that stops reading a recording part way (the playback still queueing frames) and ends
    its process: the playback is stopped before the interpreter's teardown, and the exit is clean."""
    import subprocess
    import sys

    path = recording[0]
    code = ("from spherebench.datasets import depth_frames\n"
            f"frames = depth_frames.recording_frames({str(path)!r})\n"
            "first = next(frames)\n"
            "print(first.index)\n")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0 and done.stdout == "0\n", (done.returncode, done.stderr[-500:])
