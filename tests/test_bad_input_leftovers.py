"""Bad input that a hostile re-test still got through: outputs that are no regular file, other
libraries' log lines before ours, a batch stopped at its first bad input, messages that named the
wrong thing or contradicted themselves, and damaged files of ours read late or not at all.

Each test asserts the exit status, exactly one error line on stderr (no traceback), and that
nothing was printed or written before the error.
"""

from __future__ import annotations

import errno
import io
import json
import os
import shutil
import socket
import stat
import subprocess
import sys
from pathlib import Path

import pytest

from spherebench.scripts import cli
from spherebench.datasets import inout, outputs, simulate
from test_bad_input_commands import _fails, _listing, big_ball  # noqa: E402, F401  (tests/ is on sys.path)


@pytest.fixture
def data(big_ball, tmp_path):
    """A copy of a one-scene prepared dataset (160x120, a 0.2 m ball) to damage."""
    return shutil.copytree(big_ball, tmp_path / "data")


def _scene(ds):
    return inout.list_scenes(ds)[0]


# ---------------------------------------------------------------- outputs that are no regular file

def _specials(folder):
    """A FIFO, and a character device (the null device's numbers) where this user may make one."""
    made = {"fifo": folder / "fifo"}
    os.mkfifo(made["fifo"])
    try:
        os.mknod(folder / "mynull", stat.S_IFCHR | 0o644, os.makedev(1, 3))
        made["device"] = folder / "mynull"
    except PermissionError:  # not root: the FIFO alone
        pass
    return made


def _unchanged(specials):
    return all(stat.S_ISFIFO(p.lstat().st_mode) if k == "fifo" else stat.S_ISCHR(p.lstat().st_mode)
               for k, p in specials.items())


def test_force_never_replaces_a_device_or_fifo(data, tmp_path, capsys):
    out = tmp_path / "out"
    out.mkdir()
    specials = _specials(out)
    scene = _scene(data)
    for kind, special in specials.items():
        what = "FIFO" if kind == "fifo" else "device"
        _fails(capsys, ["detect", scene, "--out-ply", special, "--force"], "--out-ply", what, "not a regular file")
        _fails(capsys, ["show", scene, "--out-png", special, "--out-ply", out / "s.ply", "--force"],
               "--out-png", what, "not a regular file")
    assert _unchanged(specials)
    assert sorted(p.name for p in out.iterdir()) == sorted(p.name for p in specials.values())


def test_a_report_never_replaces_a_fifo(data, tmp_path, capsys):
    os.mkfifo(tmp_path / "sweep.md")
    _fails(capsys, ["sweep", data, "--seeds", "0", "--workers", "1", "--out", tmp_path / "sweep"],
           "sweep.md", "FIFO", "not a regular file")
    assert stat.S_ISFIFO((tmp_path / "sweep.md").lstat().st_mode)
    assert not (tmp_path / "sweep.json").exists()


def test_a_write_through_inout_never_replaces_a_fifo(tmp_path):
    os.mkfifo(tmp_path / "p.json")
    with pytest.raises(inout.SphereBenchError, match="FIFO"):
        inout.write_json(tmp_path / "p.json", {"a": 1})
    with pytest.raises(inout.SphereBenchError, match="FIFO"):
        outputs.replace_files({tmp_path / "a.txt": b"a", tmp_path / "p.json": b"b"})
    assert stat.S_ISFIFO((tmp_path / "p.json").lstat().st_mode)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["p.json"]  # nor the other file, nor a temporary


# ---------------------------------------------------------------- a damaged PNG: our line only

def test_a_png_with_a_truncated_header_gets_one_line(data, tmp_path, capfd):
    """OpenCV's decoder logs WARN and ERROR lines of its own (on the file descriptor: capfd)."""
    scene = _scene(data)
    (scene / "image.png").write_bytes((scene / "image.png").read_bytes()[:20])
    pngs = tmp_path / "pngs"
    pngs.mkdir()
    (pngs / "f.png").write_bytes((scene / "depth.png").read_bytes()[:20])
    runs = [["show", scene, "--out-png", tmp_path / "s.png", "--out-ply", tmp_path / "s.ply"],
            ["detect", scene, "--out-png", tmp_path / "d.png"],
            ["evaluate", "--data", data, "--out", tmp_path / "ev", "--methods", "hough", "--workers", "1", "--quiet",
             "--no-figures"],
            ["prepare", pngs, "--intrinsics", scene / "intrinsics.json", "--out", tmp_path / "p"]]
    for argv in runs:
        assert cli.main([str(a) for a in argv]) == 2, argv
        err = capfd.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "not a readable image" in err[0], (argv, err)
    pytest.importorskip("onnxruntime")
    assert cli.main(["detect-2d", str(scene)]) == 2
    err = capfd.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "not a readable image" in err[0], err


def test_a_png_cut_in_its_data_or_altered_gets_one_line(data, tmp_path, capfd):
    """libpng prints a line of its own ("libpng error: ...") of a PNG that ends inside its image data
    or whose checksum fails, whatever OpenCV's log level: such a file is refused before it is decoded."""
    scene = Path(shutil.copytree(_scene(data), tmp_path / "scene"))
    whole = (scene / "depth.png").read_bytes()
    altered = bytearray(whole)
    altered[len(whole) // 2] ^= 0xFF
    for damaged, why in ((whole[:len(whole) // 2], "truncated"), (whole[:-5], "truncated"), (bytes(altered), "checksum")):
        (scene / "depth.png").write_bytes(damaged)
        (scene / "cloud.ply").unlink(missing_ok=True)  # the depth image is the scene's cloud
        assert cli.main(["detect", str(scene)]) == 2
        err = capfd.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "not a readable image" in err[0] and why in err[0], err


# ---------------------------------------------------------------- messages that named the wrong thing

def test_a_reversed_seed_range_says_so(data, capsys):
    _fails(capsys, ["sweep", data, "--seeds", "5-2", "--workers", "1"], "5-2", "reversed", "2-5")


def test_a_report_out_ending_in_a_slash_is_refused_as_a_folder(data, tmp_path, capsys):
    _fails(capsys, ["sweep", data, "--seeds", "0", "--workers", "1", "--out", f"{tmp_path}/newdir/"],
           "newdir/", "folder", "newdir/sweep", "sweep.md")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["data"]


# ---------------------------------------------------------------- a Ray address that never answers

def test_a_ray_address_that_never_answers_gets_our_line_only(data, tmp_path):
    """A port that takes the connection and says nothing: Ray logs its attempts (Python INFO lines,
    its core's warnings on the file descriptor) before the command gives up. In a process of its
    own: Ray's connecting thread outlives the error."""
    pytest.importorskip("ray")
    with socket.socket() as server:
        server.bind(("127.0.0.1", 0))
        server.listen(4)
        code = ("import sys; from spherebench import parallel; from spherebench.scripts import cli; parallel.RAY_CONNECT_TIMEOUT_S = 2.0; "
                "sys.exit(cli.main(sys.argv[1:]))")
        argv = ["sweep", str(data), "--seeds", "0", "--engine", "ray", "--address",
                f"127.0.0.1:{server.getsockname()[1]}"]
        run = subprocess.run([sys.executable, "-c", code, *argv], capture_output=True, text=True, timeout=120,
                             cwd=tmp_path)
    lines = run.stderr.strip().splitlines()
    assert run.returncode == 2 and run.stdout == ""
    assert len(lines) == 1 and "no answer from a Ray cluster within 2 s" in lines[0], run.stderr


# ---------------------------------------------------------------- detect-2d: a batch goes on past a bad input

def test_detect_2d_reports_and_skips_each_bad_input_and_detects_the_others(data, tmp_path, capsys):
    pytest.importorskip("onnxruntime")
    scene = _scene(data)
    good = tmp_path / "good.png"
    shutil.copy(scene / "image.png", good)
    broken = tmp_path / "broken.png"
    broken.write_bytes(good.read_bytes()[:20])
    status = cli.main(["detect-2d", str(scene), str(tmp_path / "missing.png"), str(broken), str(good), "--json"])
    cap = capsys.readouterr()
    assert status == 2
    assert [json.loads(x)["input"] for x in cap.out.splitlines()] == [str(scene), str(good)]
    errors = [x for x in cap.err.splitlines() if "error:" in x]
    assert len(errors) == 2 and "missing.png" in errors[0] and "broken.png" in errors[1], cap.err
    assert "Traceback" not in cap.err


# ---------------------------------------------------------------- messages that name the right thing

class _FullDisk(io.StringIO):
    """Standard output on a full disk (`> /dev/full`): every write and flush fails."""

    def write(self, text):
        raise OSError(errno.ENOSPC, "No space left on device")

    def flush(self):
        raise OSError(errno.ENOSPC, "No space left on device")


def test_a_failed_write_to_stdout_names_stdout_and_stops_the_batch(data, monkeypatch, capsys):
    scene = _scene(data)
    monkeypatch.setattr(sys, "stdout", _FullDisk())
    assert cli.main(["detect", str(scene), str(scene)]) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and "cannot write to standard output: the disk is full" in lines[0], lines


def test_a_full_stdout_fails_the_run_before_its_output_is_in_place(data, tmp_path, monkeypatch, capsys):
    """generate says "wrote" before its dataset replaces --out, sweep prints its report before it writes
    the report's files: stdout on a full disk leaves neither (status 2, one line naming stdout)."""
    out = tmp_path / "out"
    out.mkdir()
    monkeypatch.setattr(sys, "stdout", _FullDisk())
    for argv in (["generate", "--preset", "default", "--n", "1", "--out", out / "g", "--quiet"],
                 ["sweep", data, "--seeds", "0", "--limit", "1", "--out", out / "sw"]):
        assert cli.main([str(a) for a in argv]) == 2
        lines = capsys.readouterr().err.strip().splitlines()
        assert len(lines) == 1 and "cannot write to standard output: the disk is full" in lines[0], lines
    assert list(out.iterdir()) == []


@pytest.fixture(scope="module")
def annotated(tmp_path_factory):
    """One simulated scene with a ball (424x240)."""
    return simulate.generate_dataset("default", tmp_path_factory.mktemp("sim") / "sim", n=1, progress=False)


@pytest.mark.parametrize("damage, words", [
    (lambda coco: coco["annotations"][0].update(image_id=99), ("annotations[0].image_id is 99", "no image has")),
    (lambda coco: coco.update(categories=[]), ("categories is empty",)),
])
def test_evaluate_refuses_a_coco_gt_that_scoring_would_meet_late_before_anything_is_printed(
        annotated, tmp_path, capsys, damage, words):
    data = shutil.copytree(annotated, tmp_path / "data")
    coco = json.loads((data / "coco_gt.json").read_text())
    damage(coco)
    (data / "coco_gt.json").write_text(json.dumps(coco))
    for _ in range(2):  # a rerun says the same, nothing printed or kept before it ("reused", "rerun to resume")
        line = _fails(capsys, ["evaluate", "--data", data, "--out", tmp_path / "out", "--methods", "hough", "--workers",
                               "1", "--quiet", "--no-figures"], "coco_gt.json", *words, "rebuild the dataset")
        assert "resume" not in line
        assert not (tmp_path / "out").exists()


def test_an_intrinsics_number_given_as_text_says_what_it_got(data, capsys):
    path = _scene(data) / "intrinsics.json"
    intr = json.loads(path.read_text())
    path.write_text(json.dumps({**intr, "fx": "nan"}))
    line = _fails(capsys, ["detect", _scene(data)], "intrinsics.json", "fx must be a finite number", '"nan"')
    assert "not a finite number;" not in line  # the old message: "fx is not a finite number ... fx=nan must be > 0"


@pytest.mark.parametrize("argv", [[], ["--radius", "0.2"]])
def test_detect_refuses_a_damaged_gt_json_of_the_scene_it_reads(data, capsys, argv):
    """A scene folder is read strictly; a cloud given by its path is read as that file, the damaged
    gt.json beside it ignored with one note (a sidecar counts only in the project's schema)."""
    (_scene(data) / "gt.json").write_text('{"scene_id": 5')
    _fails(capsys, ["detect", _scene(data), *argv], "gt.json", "not valid JSON")
    assert cli.main(["detect", str(_scene(data) / "cloud.ply"), *argv]) == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("note:") and "gt.json" in err[0] and "ignored" in err[0]


def test_show_refuses_a_damaged_dataset_json(data, tmp_path, capsys):
    for text, words in (("[1", ("not valid JSON",)), ('{"ball_radius_m": "x"}', ("ball_radius_m", '"x"'))):
        (data / "dataset.json").write_text(text)
        _fails(capsys, ["show", _scene(data), "--out-png", tmp_path / "s.png", "--out-ply", tmp_path / "s.ply"],
               "dataset.json", *words)
    assert not (tmp_path / "s.png").exists() and not (tmp_path / "s.ply").exists()
