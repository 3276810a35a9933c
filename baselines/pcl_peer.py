"""PCL's sphere segmentation as a timed peer: ``pcl_sphere.cpp`` (pcl::SACSegmentation, SACMODEL_SPHERE,
RANSAC with the radius bounded about R), built here against the system's PCL and run as one process
that segments the clouds it is sent, one at a time, and times each segmentation itself.

PCL is a C++ library with no wheel: ``build_peer`` compiles the program with the system's compiler
and pkg-config (Debian: ``apt-get install libpcl-dev``), and refuses in one line where they are missing.
"""

from __future__ import annotations

import math
import os
import shutil
import subprocess
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from spherebench.errors import SphereBenchError

SOURCE = Path(__file__).with_name("pcl_sphere.cpp")
#: the PCL libraries the program links against (pkg-config names)
PCL_PACKAGES = ("pcl_segmentation", "pcl_search", "pcl_kdtree", "pcl_sample_consensus", "pcl_common")
INSTALL_HINT = "install PCL's headers and libraries (Debian: apt-get install libpcl-dev)"


@dataclass(frozen=True)
class PclSettings:
    """The segmentation's settings (``pcl_sphere.cpp``'s arguments)."""

    radius_m: float = 0.12
    tolerance_m: float = 0.01          # the radius limits: R -/+ this
    threshold_m: float = 0.01          # an inlier's distance to the sphere
    max_iterations: int = 10000        # RANSAC stops earlier once a sample of inliers is 99 % likely drawn
    samples_max_dist_m: float = 0.24   # local sampling: a sample's points within 2 R of its first (0: anywhere)


@dataclass(frozen=True)
class PclSphere:
    """One cloud's segmentation: wall time (ms, the search tree's build included), centre (3,) m
    and radius m (nan where none was found), and the inliers' count."""

    ms: float
    centre_m: np.ndarray
    radius_m: float
    inliers: int

    @property
    def found(self) -> bool:
        return self.inliers > 0 and math.isfinite(self.radius_m)


def pcl_version() -> str | None:
    """The system's PCL version (pkg-config), or None without it."""
    if shutil.which("pkg-config") is None:
        return None
    got = subprocess.run(["pkg-config", "--modversion", PCL_PACKAGES[0]], capture_output=True, text=True)
    return got.stdout.strip() if got.returncode == 0 else None


def build_peer(build_dir: Path) -> Path:
    """The compiled program in build_dir (made there if missing or older than its source)."""
    binary = Path(build_dir) / "pcl_sphere"
    if binary.is_file() and binary.stat().st_mtime >= SOURCE.stat().st_mtime:
        return binary
    compiler = shutil.which(os.environ.get("CXX", "g++"))
    if compiler is None or pcl_version() is None:
        raise SphereBenchError(f"PCL or a C++ compiler is missing: {INSTALL_HINT}, and g++")
    flags = subprocess.run(["pkg-config", "--cflags", "--libs", *PCL_PACKAGES], capture_output=True, text=True)
    if flags.returncode != 0:
        raise SphereBenchError(f"pkg-config cannot find PCL's libraries ({flags.stderr.strip()}): {INSTALL_HINT}")
    binary.parent.mkdir(parents=True, exist_ok=True)
    partial = binary.with_name(f".{binary.name}.{os.getpid()}.tmp")
    try:
        made = subprocess.run([compiler, "-O2", "-std=c++17", str(SOURCE), "-o", str(partial), *flags.stdout.split()],
                              capture_output=True, text=True)
        if made.returncode != 0:
            last = (made.stderr.strip().splitlines() or ["no message"])[-1]
            raise SphereBenchError(f"{SOURCE.name} did not compile against PCL {pcl_version()}: {last}")
        os.replace(partial, binary)
    finally:
        partial.unlink(missing_ok=True)
    return binary


class PclPeer:
    """The program running as one process: ``segment`` sends it a cloud and reads its answer. A
    context manager; the process ends with it."""

    def __init__(self, binary: Path, settings: PclSettings = PclSettings()):
        s = settings
        self.settings = s
        self._proc = subprocess.Popen(
            [str(binary), repr(s.radius_m), repr(s.tolerance_m), repr(s.threshold_m), str(s.max_iterations),
             repr(s.samples_max_dist_m)], stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE)

    def segment(self, points: np.ndarray) -> PclSphere:
        """Segment points (N, 3) m."""
        pts = np.ascontiguousarray(points, "<f4").reshape(-1, 3)
        self._proc.stdin.write(np.uint32(len(pts)).astype("<u4").tobytes() + pts.tobytes())
        self._proc.stdin.flush()
        line = self._proc.stdout.readline().decode().split()
        if len(line) != 6:
            err = self._proc.stderr.read().decode().strip() if self._proc.poll() is not None else ""
            raise SphereBenchError(f"the PCL peer stopped answering ({err or 'no message'})")
        ms, cx, cy, cz, r, n = line
        return PclSphere(ms=float(ms), centre_m=np.array([float(cx), float(cy), float(cz)]), radius_m=float(r),
                         inliers=int(n))

    def close(self) -> None:
        if self._proc.poll() is None:
            self._proc.stdin.close()
            try:
                self._proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self._proc.kill()
                self._proc.wait()

    def __enter__(self) -> PclPeer:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
