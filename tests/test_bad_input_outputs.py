"""Outputs: nothing of the user's or of a dataset overwritten, nothing half-written, and a failed or
stopped run leaves only what it says it leaves.

Each case asserts the exit status, the one line on stderr, that a sentinel folder and the input
dataset are unchanged (by hash) and what remains after the failure.
"""

from __future__ import annotations

import errno
import hashlib
import json
import os
import shutil
from pathlib import Path

import pytest

from spherebench.scripts import cli
from spherebench.datasets import inout, outputs


def _tree(root: Path) -> dict:
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(Path(root).rglob("*")) if p.is_file()}


def _fails(capsys, argv, *words) -> str:
    assert cli.main([str(a) for a in argv]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err and ".tmp-" not in err, err
    for w in words:
        assert w in err, err
    return err


def _no_temporaries(*roots: Path) -> None:
    for root in roots:
        assert not [p for p in Path(root).rglob(".tmp-*")], list(Path(root).rglob(".tmp-*"))


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("data") / "ds"
    argv = ["generate", "--preset", "default", "--n", "2", "--workers", "1", "--quiet", "--out", str(out)]
    assert cli.main(argv) == 0
    return out


@pytest.fixture
def ds(dataset, tmp_path) -> Path:
    """A copy of the dataset, for a test that might change it."""
    return Path(shutil.copytree(dataset, tmp_path / "ds"))


@pytest.fixture
def user(tmp_path, monkeypatch) -> Path:
    """The current folder, with a user's files in it."""
    home = tmp_path / "home"
    home.mkdir()
    (home / "my_scan.ply").write_text("ply\nformat ascii 1.0\nelement vertex 0\nend_header\n")
    (home / "photo.png").write_bytes(b"\x89PNG\r\n\x1a\n my photo")
    monkeypatch.chdir(home)
    return home


def _fail_on(monkeypatch, nth: int, name: str | None = None, err: int = errno.ENOSPC):
    """os.replace in outputs fails (``err``) on its ``nth`` call onto a file called ``name`` (any name)."""
    real, calls = os.replace, []

    def replace(src, dst):
        if name is None or Path(dst).name == name:
            calls.append(dst)
            if len(calls) == nth:
                raise OSError(err, os.strerror(err), str(src))
        return real(src, dst)
    monkeypatch.setattr(outputs.os, "replace", replace)


# --------------------------------------------------------------------------- data lost

def test_annotate_overwrite_failing_puts_back_every_replaced_file(tmp_path, monkeypatch, capsys):
    from test_annotate_colour import make_dataset
    data = make_dataset(tmp_path / "rec", n=3)
    assert cli.main(["annotate", str(data), "--from-colour"]) == 0
    corrected = data / "scenes/frame_0/colour.json"
    corrected.write_text(corrected.read_text().replace("not reviewed", "corrected by hand"))
    capsys.readouterr()
    before = _tree(data)
    _fail_on(monkeypatch, 2, "colour.json")
    _fails(capsys, ["annotate", data, "--from-colour", "--overwrite"], "frame_1/colour.json", "disk is full")
    assert _tree(data) == before  # the corrected file is back, the others as they were
    _no_temporaries(data)


def test_evaluate_rerun_keeps_the_users_files_in_tables_and_figures(ds, tmp_path, capsys):
    out = tmp_path / "ev"
    argv = ["evaluate", "--data", ds, "--out", out, "--methods", "improved", "--quiet", "--workers", "1"]
    assert cli.main([str(a) for a in argv]) == 0
    (out / "tables/my_table.md").write_text("mine")
    (out / "figures/my_plot.png").write_bytes(b"mine")
    assert cli.main([str(a) for a in argv]) == 0
    assert (out / "tables/my_table.md").read_text() == "mine"
    assert (out / "figures/my_plot.png").read_bytes() == b"mine"
    assert (out / "tables/table3_ds.md").is_file()
    # a file of the user's named as one the report writes is refused, not replaced
    (out / "tables/hand.md").write_text("mine")
    listed = json.loads((out / "tables" / ".spherebench-files.json").read_text())
    (out / "tables" / ".spherebench-files.json").write_text(json.dumps([n for n in listed if n != "timings.md"]))
    capsys.readouterr()
    _fails(capsys, argv, "timings.md", "not written by evaluate")
    assert (out / "tables/hand.md").read_text() == "mine"


@pytest.mark.parametrize("target", ["scene/image.png", "scene/cloud.ply", "other/mask_0.png", "dataset.json",
                                    "my_scan.ply", "photo.png"])
@pytest.mark.parametrize("command", ["show", "detect"])
def test_single_file_outputs_never_replace_a_dataset_or_user_file(dataset, user, capsys, command, target):
    scenes = inout.list_scenes(dataset)
    path = {"scene": scenes[0], "other": scenes[1]}.get(target.split("/")[0], None)
    path = path / target.split("/")[1] if path is not None else (dataset / target if target == "dataset.json"
                                                                 else user / target)
    option = "--out-png" if target.endswith(".png") else "--out-ply"
    before, mine = _tree(dataset), _tree(user)
    words = ("exists", "--force") if path.parent == user else ("inside",)
    _fails(capsys, [command, scenes[0], option, path], option, *words)
    assert _tree(dataset) == before and _tree(user) == mine


def test_single_file_outputs_replace_their_own_and_force_replaces_a_users(dataset, user, capsys):
    scene = inout.list_scenes(dataset)[0]
    for _ in range(2):  # the second run replaces what the first wrote: it carries the mark
        assert cli.main(["show", str(scene), "--out-png", "s.png", "--out-ply", "s.ply"]) == 0
        assert cli.main(["detect", str(scene), "--out-png", "d.png", "--out-ply", "d.ply"]) == 0
    assert all(outputs.is_marked(user / n) for n in ("s.png", "s.ply", "d.png", "d.ply"))
    assert cli.main(["show", str(scene), "--out-png", "photo.png", "--out-ply", "my_scan.ply", "--force"]) == 0
    assert outputs.is_marked(user / "photo.png")


@pytest.mark.parametrize("command", ["show", "detect"])
def test_two_file_output_is_all_or_nothing(dataset, user, monkeypatch, capsys, command):
    scene = inout.list_scenes(dataset)[0]
    assert cli.main([command, str(scene), "--out-png", "a.png", "--out-ply", "a.ply"]) == 0
    before = _tree(user)
    second = "a.ply" if command == "show" else "a.png"  # the order each writes them
    _fail_on(monkeypatch, 2)
    capsys.readouterr()
    _fails(capsys, [command, scene, "--out-png", "a.png", "--out-ply", "a.ply"], second, "disk is full")
    assert _tree(user) == before  # the first file put back as it was
    (user / "a.png").unlink()
    (user / "a.ply").unlink()
    _fail_on(monkeypatch, 2)  # both new: neither is left
    _fails(capsys, [command, scene, "--out-png", "a.png", "--out-ply", "a.ply"], "disk is full")
    assert _tree(user) == {k: v for k, v in before.items() if k not in ("a.png", "a.ply")}
    _no_temporaries(user)


@pytest.mark.parametrize("command", ["sweep", "bench"])
def test_a_users_json_with_a_seed_is_not_taken_for_a_report(dataset, user, capsys, command):
    (user / "run.json").write_text('{"seed": 1, "mine": true}')
    (user / "run.md").write_text("my notes")
    mine = _tree(user)
    _fails(capsys, [command, dataset, "--out", "run"], "not written by this report")
    (user / "run.json").unlink()  # a run.md alone is the user's too
    _fails(capsys, [command, dataset, "--out", "run"], "not written by this report")
    assert _tree(user) == {k: v for k, v in mine.items() if k != "run.json"}


def test_robustness_checks_its_report_the_same_way(dataset, user, capsys):
    (user / "run.json").write_text('{"seeds": [0]}')
    _fails(capsys, ["robustness", dataset, "--out", "run"], "not written by this report")
    assert (user / "run.json").read_text() == '{"seeds": [0]}'


@pytest.mark.parametrize("argv, words", [
    (["generate", "--n", "1", "--workers", "1", "--quiet", "--out", "{ds}/scenes/new"], ("inside the dataset",)),
    (["prepare", "{ds}/scenes/{scene}/depth.png", "--out", "{ds}/scenes/new"], ("inside the dataset",)),
    (["evaluate", "--data", "{ds}", "--out", "{ds}/scenes/ev", "--methods", "improved"], ("inside the dataset",)),
])
def test_no_output_folder_inside_a_dataset(dataset, user, capsys, argv, words):
    before = _tree(dataset)
    scene = inout.list_scenes(dataset)[0].name
    _fails(capsys, [a.format(ds=dataset, scene=scene) for a in argv], *words)
    assert _tree(dataset) == before and not (dataset / "scenes/new").exists() and not (dataset / "scenes/ev").exists()


# --------------------------------------------------------------------------- --out edge cases

@pytest.mark.parametrize("out", [".", "/", "..", ""])
@pytest.mark.parametrize("command", ["sweep", "bench", "robustness"])
def test_report_out_that_names_no_file_is_refused(dataset, user, capsys, command, out):
    before = _tree(user.parent)
    argv = [command, dataset]
    _fails(capsys, [*argv, "--out", out], "--out", "is empty" if out == "" else "is a folder")
    assert _tree(user.parent) == before


@pytest.mark.parametrize("argv, words", [
    (["show", "{scene}", "--out-png", ""], ("--out-png is empty",)),
    (["show", "{scene}", "--out-ply", ""], ("--out-ply is empty",)),
    (["show", "{scene}", "--out-png", "x", "--out-ply", "x"], ("same file",)),
    (["detect", "{scene}", "--out-ply", ""], ("--out-ply is empty",)),
    (["detect", "{scene}", "--out-png", ""], ("--out-png is empty",)),
    (["detect", "{scene}", "--labelme-out", ""], ("--labelme-out is empty",)),
])
def test_empty_or_doubled_file_outputs_are_refused(dataset, user, capsys, argv, words):
    before = _tree(user)
    scene = str(inout.list_scenes(dataset)[0])
    _fails(capsys, [a.format(scene=scene) for a in argv], *words)
    assert _tree(user) == before


# --------------------------------------------------------------------------- what a failure leaves

def _evaluate(ds, out, *extra) -> list:
    return ["evaluate", "--data", ds, "--out", out, "--methods", "improved", "--quiet", "--workers", "1", *extra]


def test_failed_evaluate_removes_the_folder_it_made(dataset, user, capsys, monkeypatch):
    (user / "bad.json").write_text("{")
    _fails(capsys, [*_evaluate(dataset, "ev"), "--methods", "hough", "--hough-config", "bad.json"], "bad.json")
    assert not (user / "ev").exists()
    real, calls = os.fchmod, []

    def fchmod(fd, mode):  # the owner marker goes through; the first prediction set meets a full disk
        calls.append(fd)
        if len(calls) == 2:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))  # as a write's error: naming no file
        return real(fd, mode)
    monkeypatch.setattr(outputs.os, "fchmod", fchmod)
    _fails(capsys, _evaluate(dataset, "ev"), "ev/predictions/ds/improved.json", "disk is full")
    assert not (user / "ev").exists()


def test_stopped_evaluate_says_what_it_kept(dataset, ds, user, capsys, monkeypatch):
    from spherebench.eval.bench import evaluate
    real, calls = evaluate.run_methods, []

    def run_methods(*args, **kwargs):  # the second dataset is stopped: the first's predictions are done
        calls.append(1)
        if len(calls) == 2:
            raise KeyboardInterrupt
        return real(*args, **kwargs)
    monkeypatch.setattr(evaluate, "run_methods", run_methods)
    assert cli.main([str(a) for a in _evaluate(dataset, "ev", "--data", ds)]) == 130
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "no partial output" not in err, err
    assert "interrupted" in err and "ev/predictions" in err and "rerun" in err, err
    assert any((user / "ev/predictions").rglob("*.json"))
    calls[:] = [1]  # a new folder stopped before any set is done: nothing is left, and it says so
    assert cli.main([str(a) for a in _evaluate(dataset, "ev2")]) == 130
    assert "no partial output is left" in capsys.readouterr().err and not (user / "ev2").exists()


def test_failed_training_keeps_only_a_checkpoint(dataset, user, capsys, monkeypatch):
    from spherebench.baselines.circlenet import train

    def fails(*args, **kwargs):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(user / "run/curve.png"))
    monkeypatch.setattr(train, "_train", fails)
    _fails(capsys, ["train", "--data", dataset, "--out", "run", "--device", "cpu"], "run/curve.png", "disk is full")
    assert not (user / "run").exists()

    def stopped(config, device, seed, out, *rest):
        (out / "checkpoint.pt").write_bytes(b"state")
        raise KeyboardInterrupt
    monkeypatch.setattr(train, "_train", stopped)
    assert cli.main(["train", "--data", str(dataset), "--out", "run", "--device", "cpu"]) == 130
    err = capsys.readouterr().err
    assert "run/checkpoint.pt" in err and "--resume" in err and (user / "run/checkpoint.pt").is_file()


def test_write_errors_name_the_destination_not_a_temporary(dataset, user, capsys, monkeypatch):
    (user / "userfile.txt").write_text("mine")
    scene = inout.list_scenes(dataset)[0]
    _fails(capsys, ["show", scene, "--out-png", "userfile.txt/a.png", "--out-ply", "a.ply"],
           "userfile.txt is a file, not a folder")
    _fails(capsys, ["evaluate", "--data", dataset, "--out", "userfile.txt/ev"], "userfile.txt is a file, not a folder")
    _fail_on(monkeypatch, 1, err=errno.EACCES)  # os.replace's error names the temporary and the destination
    _fails(capsys, ["show", scene, "--out-png", "a.png", "--out-ply", "a.ply"], "a.png", "permission denied")
    assert sorted(p.name for p in user.iterdir()) == ["my_scan.ply", "photo.png", "userfile.txt"]


def test_os_error_message_names_the_file_in_the_way_and_no_temporary(tmp_path):
    (tmp_path / "userfile.txt").write_text("x")
    msg = cli.os_error_message(FileExistsError(errno.EEXIST, "File exists", str(tmp_path / "userfile.txt")))
    assert "userfile.txt is a file, not a folder" in msg
    msg = cli.os_error_message(OSError(errno.ENOSPC, "No space", str(tmp_path / ".tmp-ds.abc123" / "cloud.ply")))
    assert ".tmp-" not in msg and str(tmp_path / "ds" / "cloud.ply") in msg


def test_stopped_detect_says_its_recording_is_kept(dataset, user, capsys, monkeypatch):
    pytest.importorskip("rerun")
    from spherebench.scripts import detect as detect_script

    def stopped(*args, **kwargs):
        raise KeyboardInterrupt
    monkeypatch.setattr(detect_script, "detect", stopped)
    scene = inout.list_scenes(dataset)[0]
    assert cli.main(["detect", str(scene), "--rerun-save", "run.rrd"]) == 130
    err = capsys.readouterr().err
    assert "run.rrd holds what was logged" in err and "no partial output" not in err, err


@pytest.mark.parametrize("target, words", [("", ("--rerun-save is empty",)), ("{ds}/x.rrd", ("inside the dataset",))])
def test_rerun_save_refuses_an_empty_path_or_one_inside_a_dataset(dataset, user, capsys, target, words):
    before = _tree(dataset)
    _fails(capsys, ["detect", inout.list_scenes(dataset)[0], "--rerun-save", target.format(ds=dataset)], *words)
    assert _tree(dataset) == before


def test_a_full_disk_in_the_report_names_the_folder_and_what_was_kept(dataset, user, capsys, monkeypatch):
    real = Path.write_text

    def write_text(self, *args, **kwargs):
        if self.suffix == ".csv":
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))  # as a write's error: naming no file
        return real(self, *args, **kwargs)
    monkeypatch.setattr(Path, "write_text", write_text)
    _fails(capsys, _evaluate(dataset, "ev", "--no-figures"), "ev/tables: the disk is full",
           "completed work is kept in ev/predictions")
    assert not (user / "ev/tables").exists() and any((user / "ev/predictions").rglob("*.json"))


def test_training_refuses_an_output_inside_a_dataset(dataset, user, capsys):
    before = _tree(dataset)
    _fails(capsys, ["train", "--data", dataset, "--out", dataset / "scenes/run", "--device", "cpu"],
           "inside the dataset")
    assert _tree(dataset) == before


def test_report_and_detect_outputs_respect_datasets_and_every_input(dataset, user, capsys):
    before = _tree(dataset)
    _fails(capsys, ["sweep", dataset, "--out", dataset / "run"], "inside the dataset")
    scene = inout.list_scenes(dataset)[0]
    shutil.copy(scene / "intrinsics.json", user / "intr.json")
    shutil.copy(scene / "cloud.ply", user / "c.ply")
    _fails(capsys, ["detect", "c.ply", "--intrinsics", "intr.json", "--out-ply", "intr.json", "--force"],
           "is the input")
    assert _tree(dataset) == before and (user / "intr.json").read_bytes() == (scene / "intrinsics.json").read_bytes()


def test_evaluate_summary_files_are_written_together(dataset, user, capsys, monkeypatch):
    argv = [str(a) for a in _evaluate(dataset, "ev", "--no-figures")]
    assert cli.main(argv) == 0
    before = {n: (user / "ev" / n).read_bytes() for n in ("metrics.json", "README.md", "provenance.json")}
    for name in ("metrics.json", "provenance.json"):  # to tell the earlier set from a new one
        (user / "ev" / name).write_bytes(b'{"edited": 1}\n')
        before[name] = b'{"edited": 1}\n'
    _fail_on(monkeypatch, 1, "README.md", errno.EIO)
    capsys.readouterr()
    assert cli.main(argv) == 2
    assert "ev/README.md" in capsys.readouterr().err
    assert {n: (user / "ev" / n).read_bytes() for n in before} == before
    _no_temporaries(user)
