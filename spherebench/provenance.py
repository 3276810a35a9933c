"""Provenance: content hashes of files and code, the machine, package versions, git state.

These hashes (with a dataset's, ``datasets.fingerprint``) are the resume keys of the prediction
sets (``eval.bench.cache``) and of the cached tuning and oracle runs; the rest is recorded beside
the results (provenance.json).
"""

from __future__ import annotations

import ctypes
import datetime as _dt
import hashlib
import importlib.util
import math
import os
import platform
import subprocess
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np

from spherebench import __version__
from spherebench.errors import SphereBenchError

#: The folder that holds the layers (method/, baselines/, ...): a clone's root, or in an installed
#: wheel the spherebench package itself (where method/ and the rest sit inside it).
REPO_ROOT = Path(importlib.util.find_spec("spherebench.method").origin).resolve().parents[1]
#: Packages whose versions go into the provenance.
PACKAGES = ("numpy", "scipy", "opencv-python-headless", "numba", "pycocotools", "onnxruntime", "torch",
            "pyransac3d", "matplotlib", "tqdm", "plyfile", "open3d", "pandas", "ray")


def json_safe(obj):
    """NaN and infinities -> None, numpy scalars and arrays -> Python (strict JSON)."""
    if isinstance(obj, dict):
        return {str(k): json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_safe(v) for v in obj]
    if isinstance(obj, (np.floating, float)):
        return float(obj) if math.isfinite(float(obj)) else None
    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, np.ndarray):
        return json_safe(obj.tolist())
    return obj


def file_sha256(path: str | Path) -> str:
    """sha256 of a file's bytes (hex)."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def hash_files(paths: Iterable[Path], root: Path) -> str:
    """One hash (blake2b, hex) of the files' paths relative to ``root`` and their bytes, in order."""
    h = hashlib.blake2b(digest_size=16)
    for p in paths:
        h.update(str(p.relative_to(root)).encode())
        h.update(b"\0")
        with open(p, "rb") as f:
            for block in iter(lambda: f.read(1 << 20), b""):
                h.update(block)
        h.update(b"\1")
    return h.hexdigest()


def code_version(modules: Sequence[str]) -> str:
    """Content hash of the source files of the given modules (dotted names; a package: all its .py)."""
    files = []
    for name in modules:
        spec = importlib.util.find_spec(name)
        if spec is None or spec.origin is None:
            raise SphereBenchError(f"module {name} not found: reinstall the package (pip install -e .)")
        origin = Path(spec.origin)
        files += sorted(origin.parent.glob("*.py")) if origin.name == "__init__.py" else [origin]
    h = hashlib.blake2b(digest_size=16)
    for p in files:
        h.update(p.name.encode())
        h.update(p.read_bytes())
    return h.hexdigest()


def dist_version(name: str) -> str | None:
    """The installed version of a distribution, or None."""
    try:
        return version(name)
    except PackageNotFoundError:
        return None


def blas_info() -> str | None:
    """numpy's OpenBLAS and the kernel it chose for this CPU at start-up (its configuration line), or
    None when numpy does not bundle one. The last bits of numpy's linear algebra follow that kernel,
    and with them pyransac3d's near-degenerate sphere fits: another CPU can flip one of them."""
    for lib_path in sorted((Path(np.__file__).resolve().parent.parent / "numpy.libs").glob("*openblas*")):
        try:
            lib = ctypes.CDLL(str(lib_path))  # already loaded by numpy: the same library, not a second copy
        except OSError:
            continue
        for name in ("scipy_openblas_get_config64_", "scipy_openblas_get_config", "openblas_get_config64_",
                     "openblas_get_config"):
            get = getattr(lib, name, None)
            if get is not None:
                get.restype = ctypes.c_char_p
                return " ".join(get().decode(errors="replace").split())
    return None


def machine_info() -> dict:
    """CPU model, core count, OS, Python and numpy's BLAS kernel (``blas_info``) of this machine."""
    cpu = platform.processor() or ""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return {"cpu": cpu, "cores": os.cpu_count(), "system": platform.platform(), "python": platform.python_version(),
            "blas": blas_info()}


def git_state(repo: Path, outputs: tuple = ()) -> dict:
    """{commit, dirty} of the repository (None when git is unavailable); dirty: tracked files changed,
    leaving out ``outputs`` (the run's own output folders, which a run rewrites as it goes)."""
    def run(*args):
        try:
            return subprocess.run(["git", *args], cwd=repo, capture_output=True, text=True, timeout=20).stdout.strip()
        except (OSError, subprocess.SubprocessError):
            return None
    commit = run("rev-parse", "HEAD")
    excluded = []
    for out in outputs:
        try:
            excluded.append(f":(exclude){Path(out).resolve().relative_to(Path(repo).resolve()).as_posix()}")
        except ValueError:  # outside the repository: git does not see it anyway
            pass
    status = run("status", "--porcelain", "--untracked-files=no", "--", ".", *excluded)
    return {"commit": commit or None, "dirty": None if status is None else bool(status)}


def package_versions() -> dict:
    return {name: dist_version(name) for name in PACKAGES}


def now_utc() -> str:
    """The current UTC time, ISO 8601 to the second."""
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")


def provenance(repo: Path, seeds: dict, configs: dict, extra: dict | None = None, outputs: tuple = ()) -> dict:
    """provenance.json's content: versions, git state (``outputs``: the run's output folders, left out
    of its dirty check), machine, seeds, configurations, date."""
    return json_safe({"spherebench": __version__, "git": git_state(repo, outputs), "python": platform.python_version(),
                      "packages": package_versions(), "machine": machine_info(), "seeds": seeds,
                      "configurations": configs, "date": now_utc(), **(extra or {})})
