"""`--engine ray`: the benchmark's tasks on a local Ray cluster give the same prediction files as the
local engine (``spherebench.parallel.executor``)."""

from __future__ import annotations

import filecmp
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest

from spherebench.baselines.hough import HoughConfig
from spherebench.datasets import simulate
from spherebench.errors import SphereBenchError
from spherebench.eval.bench import registry, tasks
from spherebench.parallel import RAY_AUTH_VARIABLES, executor

ray = pytest.importorskip("ray", reason="the `distributed` extra (ray) is not installed")


@pytest.fixture(scope="module")
def three(tmp_path_factory):
    """Three scenes of the default preset."""
    return simulate.generate_dataset("default", tmp_path_factory.mktemp("raydata") / "three", n=3, progress=False)


def test_ray_and_local_engines_write_the_same_predictions(three, tmp_path, monkeypatch):
    # a local cluster's session folder and token go with it: nothing is left in TMPDIR or HOME
    temp = Path(tempfile.mkdtemp(dir="/tmp"))  # a Unix socket's path has 107 bytes at most: not under tmp_path
    (tmp_path / "home").mkdir()
    monkeypatch.setenv("TMPDIR", str(temp))
    monkeypatch.setattr(tempfile, "tempdir", str(temp))
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    for variable in RAY_AUTH_VARIABLES:
        monkeypatch.delenv(variable, raising=False)
    specs = [registry.detector_spec("improved"), registry.pyransac3d_spec(points=500, iterations=40),
             registry.hough_spec(HoughConfig())]
    local = tasks.run_methods(three, tmp_path / "local", specs, seed=1, workers=1, progress=False, log=lambda m: None)
    ray_paths = tasks.run_methods(three, tmp_path / "ray", specs, seed=1, workers=2, progress=False,
                                   log=lambda m: None, engine="ray")
    assert set(local) == set(ray_paths) and len(local) == 5
    for name, path in local.items():
        assert filecmp.cmp(path, ray_paths[name], shallow=False), name
    assert not ray.is_initialized()  # the local cluster it started is shut down
    assert list(temp.iterdir()) == [] and list((tmp_path / "home").iterdir()) == []
    temp.rmdir()
    assert all(variable not in os.environ for variable in RAY_AUTH_VARIABLES)


def test_engine_arguments_are_checked():
    with pytest.raises(SphereBenchError, match="--engine"):
        with executor(1, "spark"):
            pass
    with pytest.raises(SphereBenchError, match="--address"):
        with executor(1, "local", "ray://head:10001"):
            pass


@pytest.mark.parametrize("signum, delay_s", [(signal.SIGTERM, 1.5), (signal.SIGINT, 3.0)])
def test_a_signal_while_the_local_cluster_starts_is_one_line_and_leaves_no_process(three, tmp_path, signum, delay_s):
    """Ray's start sets a SIGTERM handler that exits mid-start (its processes left running): the
    signal is held until the start returns, then the command's own handler stops the run."""
    temp = Path(tempfile.mkdtemp(dir="/tmp"))  # a Unix socket's path has 107 bytes at most
    env = {**os.environ, "TMPDIR": str(temp)}
    run = subprocess.Popen([sys.executable, "-m", "spherebench.scripts.cli", "sweep", str(three), "--seeds", "0-3",
                            "--workers", "1", "--engine", "ray", "--out", str(tmp_path / "sw")],
                           env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    time.sleep(delay_s)
    run.send_signal(signum)
    err = run.communicate(timeout=120)[1]
    assert run.returncode == 128 + signum, err
    assert len(err.strip().splitlines()) == 1 and "no partial output is left" in err, err
    time.sleep(1.0)
    left = subprocess.run(["pgrep", "-f", str(temp)], capture_output=True, text=True).stdout.split()
    assert left == [] and list(temp.iterdir()) == [] and not list(tmp_path.glob("sw*"))
    temp.rmdir()
