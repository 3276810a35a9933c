"""Where the command's caches go (``spherebench.caches``): one folder the user can set, a
sub-folder per library, a user's own library setting kept."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

from spherebench import caches


def test_the_cache_folder_follows_the_users_settings(tmp_path, monkeypatch):
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert caches.cache_folder({}) == tmp_path / "home/.cache/spherebench"
    assert caches.cache_folder({"XDG_CACHE_HOME": str(tmp_path / "xdg")}) == tmp_path / "xdg/spherebench"
    # a relative XDG_CACHE_HOME is to be ignored (the XDG base directory specification)
    assert caches.cache_folder({"XDG_CACHE_HOME": "rel"}) == tmp_path / "home/.cache/spherebench"
    own = {"SPHEREBENCH_CACHE_DIR": str(tmp_path / "mine"), "XDG_CACHE_HOME": str(tmp_path / "xdg")}
    assert caches.cache_folder(own) == tmp_path / "mine"


def test_each_library_gets_a_sub_folder_unless_the_user_set_its_own(tmp_path):
    environ = {"SPHEREBENCH_CACHE_DIR": str(tmp_path / "c"), "MPLCONFIGDIR": "/users/own"}
    assert caches.use_cache_folder(environ) == tmp_path / "c"
    assert environ["NUMBA_CACHE_DIR"] == str(tmp_path / "c/numba")
    assert environ["TORCHINDUCTOR_CACHE_DIR"] == str(tmp_path / "c/torch")
    assert environ["MPLCONFIGDIR"] == "/users/own"
    assert not (tmp_path / "c").exists()  # made by a library when it first writes there
    (tmp_path / "home-file").write_text("not a folder")
    environ = {"HOME": str(tmp_path / "home-file")}
    fallback = Path(tempfile.gettempdir()).absolute() / f"spherebench-cache-{os.getuid()}"
    assert caches.use_cache_folder(environ) == fallback and environ["NUMBA_CACHE_DIR"] == str(fallback / "numba")


_PROBE = """
import json, sys
from spherebench.scripts import cli
before = sorted(m for m in ("numba", "matplotlib", "torch") if m in sys.modules)
code = cli.main(["generate", "--help"])
import numba, matplotlib
print(json.dumps({"before": before, "code": code, "numba": numba.config.CACHE_DIR,
                  "matplotlib": matplotlib.get_cachedir()}))
"""


def test_the_command_sets_them_before_the_libraries_load(tmp_path):
    home = tmp_path / "home"
    home.mkdir()
    env = {k: v for k, v in os.environ.items() if k not in (*caches.LIBRARY_FOLDERS, "XDG_CACHE_HOME",
                                                            caches.CACHE_VARIABLE)}
    env["HOME"] = str(home)
    done = subprocess.run([sys.executable, "-c", _PROBE], env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    seen = json.loads(done.stdout.strip().splitlines()[-1])
    folder = home / ".cache/spherebench"
    assert seen["before"] == [] and seen["code"] == 0
    assert Path(seen["numba"]) == folder / "numba" and Path(seen["matplotlib"]) == folder / "matplotlib"
    # matplotlib's configuration folder is the same one: no empty ~/.config/matplotlib
    assert not (home / ".config").exists()
