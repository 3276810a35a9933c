"""Processes, Ray, stdout, progress output and $HOME: --workers below 1 refused in one line and the
processes started capped; workers that die with their parent; a Ray cluster that is not there, or a
Ray that does not load, in one line; stdout closed; progress in a log file a few lines, not one per
update; commands that leave nothing in the user's home folder."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import threading
import time
import types
from pathlib import Path

import cv2
import numpy as np
import pytest

from spherebench import parallel, progress
from spherebench.scripts import cli
from spherebench.datasets import simulate
from spherebench.errors import SphereBenchError

ROOT = Path(__file__).resolve().parents[1]


def _one_line(capsys, argv, *words):
    status = cli.main([str(a) for a in argv])
    out, err = capsys.readouterr()
    assert status == 2, (argv, err)
    assert not out and len(err.strip().splitlines()) == 1, (argv, err)
    for w in words:
        assert w in err, (argv, err)
    assert "Traceback" not in err
    return err


# --------------------------------------------------------------------------- --workers


@pytest.mark.parametrize("command", ["generate", "evaluate", "eval", "sweep", "robustness"])
@pytest.mark.parametrize("value", ["0", "-3", "many"])
def test_workers_below_one_are_refused_everywhere(command, value, capsys, tmp_path):
    _one_line(capsys, [command, "--workers", value, "--out", tmp_path / "out"], "--workers")
    assert not list(tmp_path.iterdir())


def test_train_loader_workers_are_zero_or_more(capsys, tmp_path):
    _one_line(capsys, ["train", "--workers", "-3", "--data", tmp_path, "--out", tmp_path / "run"], "--workers")


def test_processes_started_are_capped_at_the_tasks_and_cpus(tmp_path, monkeypatch):
    assert parallel.pool_size(999999) == parallel.usable_cpus()
    assert parallel.pool_size(64, tasks=1) == 1 and parallel.pool_size(3, tasks=0) == 1

    def no_pool(*args, **kwargs):
        raise AssertionError("a process pool for a single scene")

    monkeypatch.setattr(parallel, "process_pool", no_pool)
    simulate.generate_dataset("default", tmp_path / "one", n=1, workers=999999, progress=False)
    assert (tmp_path / "one" / "dataset.json").is_file()


def _children(pid: int) -> set[int]:
    found = set()
    for task in Path(f"/proc/{pid}/task").glob("*"):
        try:
            found |= {int(c) for c in (task / "children").read_text().split()}
        except OSError:
            pass
    return found


def _alive(pid: int) -> bool:
    """Running, not a zombie waiting to be reaped (the parent that would reap it is gone)."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (OSError, IndexError):
        return False
    return state not in ("Z", "X")


@pytest.mark.skipif(not Path("/proc/self/task").is_dir(), reason="needs Linux /proc")
@pytest.mark.skipif(parallel.usable_cpus() < 2, reason="one CPU: generate runs in one process")
def test_workers_die_when_their_parent_is_killed(tmp_path):
    proc = subprocess.Popen([sys.executable, "-m", "spherebench.scripts.cli", "generate", "--n", "400", "--workers", "2",
                             "--quiet", "--out", str(tmp_path / "ds")], cwd=tmp_path,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    workers: set[int] = set()
    try:
        for _ in range(600):  # up to a minute for the pool to start
            workers = _children(proc.pid)
            if len(workers) >= 2 or proc.poll() is not None:
                break
            time.sleep(0.1)
        assert len(workers) >= 2, "the pool did not start"
        proc.send_signal(signal.SIGKILL)  # as the OOM killer does: no cleanup of its own runs
        proc.wait()
        for _ in range(100):
            if not any(_alive(w) for w in workers):
                break
            time.sleep(0.1)
        assert not [w for w in workers if _alive(w)], "workers outlived their parent"
    finally:
        for w in workers:
            if _alive(w):
                os.kill(w, signal.SIGKILL)
        if proc.poll() is None:
            proc.kill()


# --------------------------------------------------------------------------- Ray


def test_a_ray_address_with_nothing_there_is_one_line_at_once(tmp_path, capsys):
    pytest.importorskip("ray", reason="the `distributed` extra (ray) is not installed")
    simulate.generate_dataset("default", tmp_path / "ds", n=1, progress=False)
    err = _one_line(capsys, ["sweep", tmp_path / "ds", "--seeds", "0", "--engine", "ray", "--address", "127.0.0.1:1"],
                    "--address 127.0.0.1:1", "no Ray cluster")
    assert "ray start" in err
    # before any stage runs (evaluate's Hough set-up said its note first)
    _one_line(capsys, ["evaluate", "--data", tmp_path / "ds", "--out", tmp_path / "ev", "--engine", "ray",
                       "--address", "ray://127.0.0.1:1"], "--address ray://127.0.0.1:1", "no Ray cluster")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ds"]


def test_the_address_is_checked_before_ray_is_asked():
    with pytest.raises(SphereBenchError, match="--address ray://127.0.0.1:1: no Ray cluster"):
        parallel.check_reachable("ray://127.0.0.1:1")
    with pytest.raises(SphereBenchError, match="HOST:PORT"):
        parallel.check_reachable("ray://127.0.0.1")
    parallel.check_reachable("auto")  # found by Ray itself
    with socket.socket() as server:
        server.bind(("127.0.0.1", 0))
        server.listen()
        parallel.check_reachable(f"ray://127.0.0.1:{server.getsockname()[1]}")


def test_ray_failing_to_start_is_one_line(monkeypatch):
    ray = pytest.importorskip("ray", reason="the `distributed` extra (ray) is not installed")

    def no_client(**kwargs):
        raise ValueError("Ray Client requires pip package `ray[client]`. If you installed the minimal Ray\n"
                         "(e.g. `pip install ray`), please reinstall")

    monkeypatch.setattr(ray, "is_initialized", lambda: False)
    monkeypatch.setattr(ray, "init", no_client)
    monkeypatch.setattr(parallel, "check_reachable", lambda address: None)
    with pytest.raises(SphereBenchError) as info:
        with parallel.executor(1, "ray", "ray://127.0.0.1:10001"):
            pass
    assert "ray://127.0.0.1:10001" in str(info.value) and "ray[client]" in str(info.value)
    assert "\n" not in str(info.value)


def test_a_local_ray_cluster_gets_no_more_cpus_than_there_are(monkeypatch):
    ray = pytest.importorskip("ray", reason="the `distributed` extra (ray) is not installed")
    asked = {}

    def init(**kwargs):
        asked.update(kwargs)
        raise RuntimeError("not started in this test")

    monkeypatch.setattr(ray, "is_initialized", lambda: False)
    monkeypatch.setattr(ray, "init", init)
    with pytest.raises(SphereBenchError, match="Ray did not start: not started in this test"):
        with parallel.executor(999999, "ray"):
            pass
    assert asked["num_cpus"] == parallel.usable_cpus()


def test_a_port_that_answers_but_is_no_ray_cluster_is_given_up_in_one_line():
    release = threading.Event()
    hangs = types.SimpleNamespace(init=lambda **kwargs: release.wait(60))  # Ray retries such a port for minutes
    try:
        with pytest.raises(SphereBenchError, match=r"^--address 127.0.0.1:6379: no answer from a Ray cluster "
                                                   r"within 0.2 s"):
            parallel._join_cluster(hangs, "127.0.0.1:6379", {}, timeout_s=0.2)
    finally:
        release.set()

    def refuses(**kwargs):
        raise ConnectionError("Failed to connect to Ray cluster at 127.0.0.1:6379")

    with pytest.raises(ConnectionError):  # a failure within the time is Ray's own, worded by _ray
        parallel._join_cluster(types.SimpleNamespace(init=refuses), "127.0.0.1:6379", {}, timeout_s=5)


def test_a_ray_that_does_not_load_is_one_line(tmp_path, monkeypatch):
    broken = tmp_path / "ray"
    broken.mkdir()
    (broken / "__init__.py").write_text("raise ImportError('libray.so: cannot open shared object file')\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.delitem(sys.modules, "ray", raising=False)
    with pytest.raises(SphereBenchError, match="Ray is installed but does not load .*libray.so"):
        with parallel.executor(1, "ray"):
            pass


# --------------------------------------------------------------------------- stdout closed


def test_stdout_closed_is_one_line_on_stderr(tmp_path):
    cloud = tmp_path / "c.xyz"
    cloud.write_text("0 0 1\n")
    done = subprocess.run([sys.executable, "-m", "spherebench.scripts.cli", "detect", str(cloud)], cwd=tmp_path,
                          preexec_fn=lambda: os.close(1), stderr=subprocess.PIPE, text=True, timeout=120)
    assert done.returncode == 2, done.stderr
    assert len(done.stderr.strip().splitlines()) == 1 and "stdout is closed" in done.stderr, done.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["c.xyz"]


@pytest.mark.parametrize("argv", [["--version"], ["--help"], ["detect", "--help"], ["detect", "--no-such-option"]])
def test_stdout_closed_before_argparse_writes_is_one_line(tmp_path, argv):
    done = subprocess.run([sys.executable, "-m", "spherebench.scripts.cli", *argv], cwd=tmp_path,
                          preexec_fn=lambda: os.close(1), stderr=subprocess.PIPE, text=True, timeout=120)
    assert done.returncode == 2, done.stderr
    assert len(done.stderr.strip().splitlines()) == 1 and "stdout is closed" in done.stderr, done.stderr


# --------------------------------------------------------------------------- progress in a log


def test_progress_to_a_file_is_a_few_lines(tmp_path, capsys):
    assert cli.main(["generate", "--n", "3", "--workers", "1", "--out", str(tmp_path / "ds")]) == 0
    err = capsys.readouterr().err  # captured: not a terminal
    assert "\r" not in err and "generate default" in err
    assert len(err.strip().splitlines()) <= 2, err


def test_a_long_stage_in_a_log_prints_at_most_a_line_per_interval(capsys):
    bar = progress.bar(total=10000, desc="run x", unit="frame")
    for _ in range(10000):
        bar.update()
    bar.set_postfix_str("improved")
    bar.close()
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) <= 2 and lines[-1].startswith("run x: frame 10000/10000"), lines
    assert list(progress.bar(range(5), desc="x", enabled=False)) == [0, 1, 2, 3, 4]
    stopped = progress.bar(total=10, desc="run y")
    stopped.update(5)
    stopped.close()  # the command's error line says why, alone
    assert not capsys.readouterr().err


# --------------------------------------------------------------------------- $HOME left alone

_HOME_SCRIPT = """
import sys
from spherebench.scripts import cli
w = sys.argv[1]
refused = [["detect-2d", w + "/missing.png"], ["evaluate", "--data", w + "/missing", "--out", w + "/ev"],
           ["prepare", w + "/bad.bag", "--out", w + "/p"], ["detect", w + "/bad.db3"],
           ["show", w + "/missing"], ["sweep", w + "/missing", "--workers", "0"]]
codes = [cli.main(a) for a in refused]
codes.append(cli.main(["detect-2d", w + "/image.png"]))
print(codes)
"""


def test_commands_leave_the_home_folder_empty(tmp_path):
    home, work = tmp_path / "home", tmp_path / "work"
    home.mkdir()
    work.mkdir()
    (work / "bad.bag").write_bytes(b"not a bag")
    (work / "bad.db3").write_bytes(b"not a db")
    cv2.imwrite(str(work / "image.png"), np.full((48, 64, 3), 80, np.uint8))
    env = {k: v for k, v in os.environ.items()
           if k not in ("XDG_CACHE_HOME", "XDG_CONFIG_HOME", "MPLCONFIGDIR", "ORT_DISABLE_TELEMETRY")}
    env["HOME"] = str(home)
    done = subprocess.run([sys.executable, "-c", _HOME_SCRIPT, str(work)], cwd=work, env=env,
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip().splitlines()[-1] == "[2, 2, 2, 2, 2, 2, 0]", done.stdout + done.stderr
    assert not [str(p.relative_to(home)) for p in home.rglob("*")]


def test_an_interrupt_that_a_library_turned_into_an_import_error_is_still_an_interrupt(monkeypatch):
    """numpy re-raises what stops its import as an ImportError (with the interrupt as its context,
    or, from C code, with none): a signal at that moment is the command's one line, not a traceback."""
    try:
        try:
            raise KeyboardInterrupt
        except KeyboardInterrupt:
            raise ImportError("numpy: the C extensions failed to import")
    except ImportError as exc:
        assert isinstance(cli._interrupt_behind(exc), KeyboardInterrupt)
    assert cli._interrupt_behind(ImportError("no such module")) is None
    monkeypatch.setattr(cli, "_received", [signal.SIGTERM])
    behind = cli._interrupt_behind(ImportError('PyCapsule_Import could not import module "datetime"'))
    assert isinstance(behind, cli.Terminated) and behind.signum == signal.SIGTERM
