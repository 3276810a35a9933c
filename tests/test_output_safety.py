"""Nothing lost, nothing half-written: output folders, signals, file modes, closed pipes.

Every command replaces only what it wrote; each case asserts the exit status, the one-line
message, that the user's files are untouched and that no temporary output is left.
"""

from __future__ import annotations

import errno
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from spherebench.scripts import cli
from spherebench.datasets import inout
from spherebench.errors import SphereBenchError
from spherebench.eval.bench import report

SB = [sys.executable, "-m", "spherebench.scripts.cli"]


def _gen(out, *extra) -> int:
    return cli.main(["generate", "--preset", "default", "--n", "1", "--workers", "1", "--quiet", "--out", str(out),
                     *extra])


def _one_line_error(capsys, *words) -> str:
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err, err
    for w in words:
        assert w in err, err
    return err


def _snapshot(folder: Path) -> dict:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.fixture
def user_dir(tmp_path, monkeypatch):
    """A working folder with a user's file in it, as the current folder."""
    (tmp_path / "notes.txt").write_text("keep")
    monkeypatch.chdir(tmp_path)
    return tmp_path


# --------------------------------------------------------------------------- --out never destroys data

@pytest.mark.parametrize("out", ["", ".", "./", "  "])
def test_out_empty_or_current_folder_is_refused(user_dir, capsys, out):
    assert _gen(out) == 2
    _one_line_error(capsys, "--out")
    assert sorted(p.name for p in user_dir.iterdir()) == ["notes.txt"]


def test_out_above_the_current_folder_is_refused(user_dir, capsys):
    inner = user_dir / "work"
    inner.mkdir()
    os.chdir(inner)
    assert _gen("..") == 2
    _one_line_error(capsys, "one above it")
    assert (user_dir / "notes.txt").read_text() == "keep"


def test_out_folder_of_user_files_is_refused(user_dir, capsys):
    mine = user_dir / "photos"
    mine.mkdir()
    (mine / "a.jpg").write_bytes(b"jpeg")
    assert _gen(mine) == 2
    _one_line_error(capsys, "did not write", "never")
    assert _snapshot(mine) == {"a.jpg": b"jpeg"}
    assert sorted(p.name for p in user_dir.iterdir()) == ["notes.txt", "photos"]


def test_out_file_and_symlink_are_refused(user_dir, capsys):
    assert _gen("notes.txt") == 2
    _one_line_error(capsys, "is a file")
    target = user_dir / "real"
    target.mkdir()
    (target / "x").write_text("x")
    (user_dir / "link").symlink_to(target)
    assert _gen("link") == 2
    _one_line_error(capsys, "symbolic link")
    assert (target / "x").read_text() == "x" and (user_dir / "link").is_symlink()


def test_previous_dataset_is_replaced_but_not_a_file_added_to_it(user_dir, capsys):
    assert _gen("ds") == 0
    assert _gen("ds", "--seed", "1") == 0  # ours: replaced
    assert inout.read_dataset_meta(user_dir / "ds")["seed"] == 1
    (user_dir / "ds" / "README.txt").write_text("my notes")
    capsys.readouterr()
    assert _gen("ds") == 2
    _one_line_error(capsys, "README.txt", "not written by SphereBench")
    assert (user_dir / "ds" / "README.txt").read_text() == "my notes"
    assert not [p for p in user_dir.iterdir() if p.name.startswith(".tmp-")]


def test_labelme_annotations_in_a_dataset_are_never_dropped(user_dir, capsys):
    assert _gen("ds") == 0
    scene = next((user_dir / "ds" / "scenes").iterdir())
    (scene / "image.json").write_text("{}")  # what LabelMe saves beside image.png
    capsys.readouterr()
    assert _gen("ds") == 2
    _one_line_error(capsys, "LabelMe", "--labelme")
    assert (scene / "image.json").read_text() == "{}"


def _depth_pngs(folder: Path) -> tuple[Path, Path]:
    """Two depth PNGs and their intrinsics: a small recorded set."""
    import numpy as np
    from spherebench.camera import Intrinsics
    folder.mkdir()
    for k in range(2):
        inout.write_depth_png(folder / f"f{k}.png", np.full((24, 32), 1500, np.uint16))
    cam = folder.parent / "cam.json"
    inout.write_intrinsics(cam, Intrinsics(32, 24, 16.0, 12.0, 30.0, 30.0))
    return folder, cam


@pytest.mark.parametrize("where", ["input", "parent", "inside"])
def test_prepare_out_related_to_its_input_is_refused(user_dir, capsys, where):
    src, cam = _depth_pngs(user_dir / "rec")
    out = {"input": src, "parent": user_dir, "inside": src / "out"}[where]
    before = _snapshot(user_dir)
    assert cli.main(["prepare", str(src), "--intrinsics", str(cam), "--out", str(out)]) == 2
    _one_line_error(capsys)
    assert _snapshot(user_dir) == before
    assert sorted(p.name for p in user_dir.iterdir()) == ["cam.json", "notes.txt", "rec"]


def test_results_folder_of_user_files_is_refused(tmp_path, capsys):
    (tmp_path / "table.csv").write_text("mine")
    with pytest.raises(SphereBenchError, match="did not write"):
        report.claim_results_dir(tmp_path)
    fresh = report.claim_results_dir(tmp_path / "results")  # new: claimed and marked
    assert report.is_results_dir(fresh) and report.claim_results_dir(fresh) == fresh


# --------------------------------------------------------------------------- temporaries and signals

def test_stale_temporary_of_a_dead_run_is_removed_and_others_are_kept(user_dir):
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    stale = user_dir / ".tmp-ds.abc123"
    (stale / "scenes").mkdir(parents=True)
    (stale / ".spherebench-tmp.json").write_text(json.dumps({"pid": dead.pid, "host": os.uname().nodename}))
    foreign = user_dir / ".tmp-ds.userthing"  # looks like ours, but has no owner record
    foreign.mkdir()
    assert _gen("ds") == 0
    assert not stale.exists() and foreign.is_dir()


def _start(args, cwd, **kw):
    return subprocess.Popen(SB + args, cwd=cwd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True, **kw)


def _wait_for_temporary(cwd: Path, proc, timeout_s=60.0) -> None:
    t0 = time.monotonic()
    while not any(p.name.startswith(".tmp-ds.") for p in cwd.iterdir()):
        assert proc.poll() is None, proc.communicate()
        assert time.monotonic() - t0 < timeout_s
        time.sleep(0.05)
    time.sleep(1.0)  # let the workers start writing scenes


@pytest.mark.parametrize("how", ["SIGTERM to the process", "SIGINT to the process group"])
def test_stopped_generate_leaves_nothing(tmp_path, how):
    proc = _start(["generate", "--preset", "default", "--n", "400", "--workers", "2", "--quiet", "--out", "ds"],
                  tmp_path)
    _wait_for_temporary(tmp_path, proc)
    if how.startswith("SIGTERM"):
        proc.send_signal(signal.SIGTERM)
        expected = 128 + signal.SIGTERM
    else:
        os.killpg(proc.pid, signal.SIGINT)  # what a terminal's Ctrl-C does
        expected = 128 + signal.SIGINT
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == expected, err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    assert list(tmp_path.iterdir()) == []


def test_closed_pipe_is_quiet(small_default):
    scenes = [str(p) for p in inout.list_scenes(small_default)]
    proc = subprocess.Popen(SB + ["detect", *scenes, "--json"], stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    proc.stdout.close()  # the reader has gone, as `| head` does
    err = proc.stderr.read().decode()
    proc.wait(timeout=120)
    assert proc.returncode == 128 + signal.SIGPIPE
    assert "Traceback" not in err and "BrokenPipe" not in err, err


# --------------------------------------------------------------------------- modes, seeds, OS errors

@pytest.mark.parametrize("umask, file_mode, dir_mode", [(0o022, 0o644, 0o755), (0o077, 0o600, 0o700)])
def test_written_files_follow_the_umask(tmp_path, umask, file_mode, dir_mode):
    old = os.umask(umask)
    try:
        assert _gen(tmp_path / "ds") == 0
    finally:
        os.umask(old)
    paths = [tmp_path / "ds", *(tmp_path / "ds").rglob("*")]
    assert {oct(p.stat().st_mode & 0o777) for p in paths if p.is_file()} == {oct(file_mode)}
    assert {oct(p.stat().st_mode & 0o777) for p in paths if p.is_dir()} == {oct(dir_mode)}


@pytest.mark.parametrize("command", [["generate", "--out", "x"], ["detect", "x.ply"], ["evaluate", "--data", "d",
                                                                                       "--out", "o"]])
def test_negative_seed_is_a_usage_error(tmp_path, monkeypatch, capsys, command):
    monkeypatch.chdir(tmp_path)
    assert cli.main([*command, "--seed", "-1"]) == 2
    _one_line_error(capsys, "--seed", "from 0")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("code, words", [(errno.ENOSPC, "disk is full"), (errno.EROFS, "read-only"),
                                         (errno.EISDIR, "is a folder")])
def test_os_errors_are_one_line(capsys, code, words):
    def work():
        raise OSError(code, os.strerror(code), "/some/out.json")
    assert cli.run_guarded("spherebench x", work) == 2
    _one_line_error(capsys, "/some/out.json", words)


def test_writing_onto_a_folder_is_one_line(small_default, tmp_path, capsys):
    scene = inout.list_scenes(small_default)[0]
    (tmp_path / "out.ply").mkdir()
    assert cli.main(["detect", str(scene), "--out-ply", str(tmp_path / "out.ply")]) == 2
    _one_line_error(capsys, "out.ply")
    assert [p.name for p in tmp_path.iterdir()] == ["out.ply"]


def test_train_never_writes_into_a_folder_of_user_files(small_default, tmp_path, capsys):
    mine = tmp_path / "models"
    mine.mkdir()
    (mine / "model.onnx").write_bytes(b"my own model")
    assert cli.main(["train", "--data", str(small_default), "--out", str(mine), "--epochs", "1", "--quiet"]) == 2
    _one_line_error(capsys, "did not write")
    assert _snapshot(mine) == {"model.onnx": b"my own model"}
