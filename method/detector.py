"""``detect``: spheres of known radius in a point cloud. Arrays in, results out; no files.

Input handling (one rule each, documented here):
- Points with a NaN or infinite coordinate are dropped; the returned indices still refer to
  ``cloud.points``. A cloud with fewer than 3 finite points is refused.
- A cloud whose median |z| exceeds ``frame.MM_LIMIT_M`` (50 m) is refused as millimetres.
- A cloud larger than ``config.input.max_points`` is searched on a random subsample of that size
  (deterministic from the seed) as an unorganised cloud; the final inliers come from all points.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field, replace

import numpy as np

from spherebench.circles import sphere_circle_exact, sphere_circle_paper, sphere_circle_visible
from spherebench.cloud import Cloud, cloud_from_depth
from spherebench import sphere_distance
from spherebench.errors import SphereBenchError
from spherebench.method.config import IMPROVED, DetectorConfig
from spherebench.method.deadline import Deadline
from spherebench.method.frame import MM_LIMIT_M, FrameNoise, PreparedFrame
from spherebench.method.frame_kernels import finite_rows
from spherebench.method.improved import run_improved
from spherebench.method.outline import outline_centre, outline_size
from spherebench.method.unorganised import shell_counts, shell_indices
from spherebench.method.paper import PaperTrace, run_paper

Circle = tuple[float, float, float]


@dataclass
class Sphere:
    """One detected ball.

    centre_m (3,): centre, metres, camera frame. radius_m: the known radius R used.
    free_radius_m: the radius of a free (centre + radius) fit to the inliers, with its standard
        error free_radius_se_m (the size check). inlier_indices (K,): indices into cloud.points.
    score: in [0, 1], comparable across frames (ranks detections for mAP): for the improved pipeline
        the estimated probability that a ball of radius R lies within 2 cm (3 cm beyond 3 m deep) of
        centre_m (the fitted verdict's, ``verdict``; an unorganised cloud's, ``unorganised.unorganised_score``);
        for the paper's, its support ratio.
    raw_score: the score before its calibration map (the verdict model's output; for an unorganised cloud
        the evidence product).
    rmse_m: RMS of ||p - c|| - R over the inliers (the RMSE of Table 2, as this project defines it).
    circle_paper, circle_exact: (cx, cy, r) pixels by the paper's rule and by the exact silhouette,
        clipped to the image and, for a partly hidden sphere, to its visible pixels
        (``spherebench.circles``); None without intrinsics.
    evidence: the verification counts (silhouette pixels, coverage...) of the improved pipeline.
    trace: the paper pipeline's intermediate values (``PaperTrace``), else None.
    """

    centre_m: np.ndarray
    radius_m: float
    free_radius_m: float
    inlier_indices: np.ndarray
    score: float
    rmse_m: float
    free_radius_se_m: float = float("nan")
    raw_score: float = float("nan")
    circle_paper: Circle | None = None
    circle_exact: Circle | None = None
    evidence: dict = field(default_factory=dict, repr=False)
    trace: PaperTrace | None = field(default=None, repr=False)

    @property
    def center_m(self) -> np.ndarray:
        """Deprecated spelling of ``centre_m``, kept for one release."""
        warnings.warn("Sphere.center_m is deprecated: use Sphere.centre_m", DeprecationWarning, stacklevel=2)
        return self.centre_m

    def to_dict(self) -> dict:
        """The JSON record of the command line (circle: the exact rule)."""
        return {"center": [round(float(v), 6) for v in self.centre_m], "radius": float(self.radius_m),
                "free_radius": None if not np.isfinite(self.free_radius_m) else round(float(self.free_radius_m), 6),
                "score": round(float(self.score), 6), "raw_score": round(float(self.raw_score), 6), "inliers": int(len(self.inlier_indices)),
                "circle": None if self.circle_exact is None else [round(float(v), 3) for v in self.circle_exact],
                "circle_paper": None if self.circle_paper is None else [round(float(v), 3) for v in self.circle_paper]}


def _check_cloud(cloud: Cloud) -> None:
    if not isinstance(cloud, Cloud):
        raise SphereBenchError(f"detect() needs a spherebench.cloud.Cloud, got {type(cloud).__name__}")
    if len(cloud.points) == 0:
        raise SphereBenchError("the point cloud is empty: nothing to detect (check the file or the depth range)")


def _check_counts(points: np.ndarray, n_ok: int, n_big: int, config: DetectorConfig) -> None:
    n = len(points)
    if n_ok < 3:
        raise SphereBenchError(f"the cloud has {n_ok} finite points (of {n}): at least 3 are needed")
    # the median |z| exceeds the limit iff more than half of the points are beyond it
    if config.input.mm_check and n_big > n_ok // 2:
        z = np.abs(points[:: max(1, n // 4096), 2].astype(np.float64))
        med = float(np.median(z[np.isfinite(z)]))
        units = [(name, f) for name, f in (("centimetres", 100.0), ("millimetres", 1000.0))
                 if 0.1 <= med / f <= 2 * MM_LIMIT_M]  # what a depth camera could see
        told = " or ".join(f"{name} ({med / f:.3g} m: divide by {f:g})" for name, f in units) or "not metres"
        raise SphereBenchError(f"median |z| is {med:.4g}, beyond {MM_LIMIT_M:g} m: the cloud "
                               f"looks like {told}; metres are expected")


def prepare_cloud(cloud: Cloud, config: DetectorConfig, rng: np.random.Generator) -> tuple[Cloud, np.ndarray, bool]:
    """Validate an unorganised cloud (or one searched as such) and choose the points to search.

    Returns (searched cloud, their indices (M,) in cloud.points, whether it is a subsample).
    """
    _check_cloud(cloud)
    n = len(cloud.points)
    ok, n_ok = finite_rows(cloud.points)
    n_ok = int(n_ok)
    index = np.flatnonzero(ok) if n_ok < n else None
    n_big = 0
    if n_ok >= 3 and config.input.mm_check:
        probe = cloud.points[(index if index is not None else np.arange(n))[:: max(1, n_ok // 4096)], 2]
        n_big = int(np.count_nonzero(np.abs(probe) > MM_LIMIT_M)) * n_ok // max(len(probe), 1)
    _check_counts(cloud.points, n_ok, n_big, config)
    if n_ok > config.input.max_points:
        index = np.sort(rng.choice(index if index is not None else n, size=config.input.max_points, replace=False))
        return Cloud(cloud.points[index]), index, True
    if index is None:
        return cloud, np.arange(n), False
    return cloud.subset(index), index, False


def prepare_frame(cloud: Cloud, config: DetectorConfig, noise: FrameNoise | None = None) -> PreparedFrame:
    """Validate an organised cloud and build what its kernels need (one pass over the points);
    noise: the whole frame's, where the cloud is a window of it (``PreparedFrame``)."""
    _check_cloud(cloud)
    frame = PreparedFrame(cloud, config, noise)
    _check_counts(cloud.points, frame.n_ok, frame.n_big, config)
    return frame


#: A sphere seen over less than this share of its silhouette (``visible_fraction``) gets the circle of its
#: visible pixels (``circles.sphere_circle_visible``), as its ground truth is drawn; one seen whole keeps the
#: exact silhouette's, computed without the depth image.
VISIBLE_CIRCLE_BELOW = 0.9


class FrameDepth:
    """The depth (m) at pixels (v, u) of a prepared frame, NaN where it has no point, read through its
    index image: what a visible circle looks up, without drawing the whole depth image (5 ms at
    1280x720, for each of a ranked output's partly hidden spheres)."""

    def __init__(self, frame: PreparedFrame):
        self.z_m, self.index = frame.points[:, 2], frame.index_image

    def __getitem__(self, pixels) -> np.ndarray:
        idx = self.index[pixels]
        return np.where(idx >= 0, self.z_m[np.maximum(idx, 0)], np.nan)


def sphere_circles(cloud: Cloud, c: np.ndarray, R: float, evidence: dict | None = None,
                   depth: FrameDepth | None = None) -> tuple[Circle | None, Circle | None]:
    """(paper's circle, exact circle) px of a sphere; the exact one is of the visible silhouette where an
    occluder hides part of it (evidence: the improved pipeline's, with visible_fraction and sigma_m).
    depth: the frame's depth lookup, where the caller has the prepared frame."""
    if cloud.intrinsics is None or not c[2] > 0:
        return None, None
    intr = cloud.intrinsics
    exact = sphere_circle_exact(intr, c, R)
    if evidence and cloud.rows is not None and evidence.get("visible_fraction", 1.0) < VISIBLE_CIRCLE_BELOW:
        if depth is None:
            depth = np.full(intr.shape, np.nan, np.float32)
            depth[cloud.rows, cloud.cols] = cloud.points[:, 2]
        # an occluder is what visible_fraction counts: more than R / 2 in front, and beyond the noise
        seen = sphere_circle_visible(intr, c, R, depth, max(0.5 * R, 3.0 * evidence.get("sigma_m", 0.0)))
        exact = seen if seen is not None else exact
    return sphere_circle_paper(intr, c, R), exact


def _all_inliers(cloud: Cloud, c: np.ndarray, R: float, band: float) -> np.ndarray:
    """Shell indices over the whole original cloud (used after a subsampled search)."""
    pts = cloud.points
    out = []
    for start in range(0, len(pts), 1_000_000):  # chunks bound the temporary memory
        chunk = pts[start:start + 1_000_000]
        buf = np.empty(len(chunk), np.int64)
        m = shell_indices(np.ascontiguousarray(chunk), c[0], c[1], c[2], R, band, buf)
        out.append(buf[:m] + start)
    return np.concatenate(out) if out else np.empty(0, np.int64)


_SEEDS: dict = {}


def search_seed(seed: int | None) -> int:
    """The organised search's 63-bit seed from the caller's: the first draw of numpy's default_rng(seed)
    (cached: a Generator costs 20 us, a sizeable part of a small frame's detection); fresh for None."""
    if not isinstance(seed, (int, np.integer)):  # None (fresh), or a sequence or SeedSequence: no cache
        return int(np.random.default_rng(seed).integers(0, 2 ** 63))
    seed = int(seed)
    if seed not in _SEEDS:
        if len(_SEEDS) > 4096:
            _SEEDS.clear()
        _SEEDS[seed] = int(np.random.default_rng(seed).integers(0, 2 ** 63))
    return _SEEDS[seed]


def warm_up(config: DetectorConfig = IMPROVED) -> None:
    """Load (or compile) the compiled kernels that ``detect`` uses with ``config``, on a small synthetic
    frame with a ball, organised and unorganised: the first call in a process otherwise pays this
    (0.3-0.5 s from numba's cache, tens of seconds on a fresh install), which a stream's first frame
    or a command line's first timing would show as detection time."""
    from spherebench.camera import Intrinsics, image_rays  # the method reads no files: synthesised here

    intr = Intrinsics.d435(96, 72)
    rays = image_rays(intr)
    centre = np.array([0.0, 0.0, 0.8 / 0.12 * config.radius_m])  # a basketball's size at 0.8 m
    u = rays / np.linalg.norm(rays, axis=-1, keepdims=True)
    tc = u @ centre
    m2 = centre @ centre - tc * tc
    t_ball = tc - np.sqrt(np.maximum(config.radius_m ** 2 - m2, 0.0))
    depth_m = np.where(m2 < config.radius_m ** 2, t_ball * u[..., 2], 1.5 * centre[2])
    organised = cloud_from_depth(depth_m, intr)
    # the paths of a frame with a ball, of one without (every retry of the search) and of one whose
    # noise nears R (the multistart, the outline); a kernel's first call in a process loads it, which
    # a stream's first such frame would otherwise pay (tens of ms each)
    plane = cloud_from_depth(np.full(intr.shape, 1.5 * centre[2]), intr)
    noisy = replace(config, noise=replace(config.noise, noise_z2_per_m=config.radius_m / centre[2] ** 2))
    for cloud, cfg in ((organised, config), (Cloud(organised.points), config), (plane, config), (organised, noisy)):
        try:
            detect(cloud, cfg, seed=0)
        except SphereBenchError:  # a configuration this frame does not suit (a 5 m ball): best effort
            pass
    # outline centring and sizing run only where the depth noise nears R, which this frame's ball does
    # not reach
    prepared = prepare_frame(organised, config)
    outline_centre(prepared, centre, config)
    outline_size(prepared, centre, config)
    # a window of the frame, searched from a hint with the frame's noise (a tracker's local search)
    v0, v1, u0, u1 = intr.height // 4, intr.height - intr.height // 4, intr.width // 4, intr.width - intr.width // 4
    window = cloud_from_depth(depth_m[v0:v1, u0:u1], intr.window(v0, v1, u0, u1), rays[v0:v1, u0:u1])
    try:
        detect(window, config, seed=0, noise=prepared.noise, hints_m=centre.reshape(1, 3), search_all=False)
    except SphereBenchError:
        pass
    # the paper pipeline's candidate counting runs only where its global draws found a candidate, which
    # on this small frame they may not
    shell_counts(organised.points, centre.reshape(1, 3), config.radius_m, config.eps_m)


def detect(cloud: Cloud, config: DetectorConfig = IMPROVED, seed: int | None = 0, *,
           min_score: float | None = None, max_spheres: int | None = None,
           deadline: Deadline | None = None, noise: FrameNoise | None = None, hints_m=None,
           search_all: bool = True) -> list[Sphere]:
    """Find balls of radius ``config.radius_m`` in ``cloud``; best first.

    cloud: points (N, 3) metres in the camera frame (camera at the origin, z forward), organised
        (pixel rows/cols + intrinsics: image-window sampling and silhouette checks) or not.
    seed: the random seed (same seed, same output); None for a fresh one.
    min_score, max_spheres: report the distinct spheres whose score is at least min_score (default
        ``config.verification.min_score``; the improved pipeline ranks none below its ``rank_floor``),
        at most max_spheres (default ``config.verification.max_spheres``). The search is the same
        whatever they are: a lower min_score adds spheres below the others, it changes none.
    deadline: a latency bound (``deadline.Deadline``): the improved pipeline reports what it has
        verified when the time is up, and ``deadline.cut_short`` says whether it was; the paper's
        pipeline runs to its end.
    noise: for an organised cloud that is a window of a frame, the frame's measured depth noise
        (``frame.FrameNoise``; a detection's ``evidence["frame_noise"]``), in place of the window's own.
    hints_m: (K, 3) centres, m, where balls are expected (a tracker's predictions): an organised
        cloud's improved pipeline verifies each first, from that start alone; search_all False: where
        every hint is verified (accepted, or ranked below that), no other ball is searched for (a
        window about one ball).
    Raises SphereBenchError on bad input (see the module docstring).
    """
    if not isinstance(config, DetectorConfig):
        raise SphereBenchError("config must be a DetectorConfig (use spherebench.method.config_for)")
    if min_score is not None and not 0.0 <= float(min_score) <= 1.0:
        raise SphereBenchError(f"min_score={min_score!r} must be a probability in [0, 1]")
    if max_spheres is not None and (isinstance(max_spheres, bool) or not isinstance(max_spheres, (int, np.integer))
                                    or max_spheres < 1):
        raise SphereBenchError(f"max_spheres={max_spheres!r} must be a whole number of at least 1")
    R = config.radius_m
    if config.pipeline == "paper":
        rng = np.random.default_rng(seed)
        work, index, _ = prepare_cloud(cloud, config, rng)
        got = run_paper(work.points, config, rng)
        if got is None:
            return []
        centre, inl, trace = got
        trace.ransac_indices = index[trace.ransac_indices]
        trace.kept_indices = index[trace.kept_indices]
        inl_orig = index[inl]
        rmse = sphere_distance.rmse(cloud.points[inl_orig], centre, R)
        # the paper has no confidence: a saturating function of the support stands in for it
        score = len(inl_orig) / (len(inl_orig) + 100.0)
        cp, ce = sphere_circles(cloud, centre, R)
        return [Sphere(centre_m=centre, radius_m=R, free_radius_m=float("nan"), inlier_indices=inl_orig, score=score,
                       raw_score=score, rmse_m=rmse, circle_paper=cp, circle_exact=ce, trace=trace)]
    least = None if min_score is None else float(min_score)
    if cloud.organised and len(cloud.points) <= config.input.max_points:
        # organised: NaN points get no pixel, so the searched points are the cloud's own
        frame = prepare_frame(cloud, config, noise)
        work, index, subsampled = cloud, None, False
        found = run_improved(cloud.points, frame, config, search_seed(seed), least, max_spheres, deadline,
                             hints_m, search_all)
        depth = FrameDepth(frame)
    else:
        depth = None
        rng = np.random.default_rng(seed)
        work, index, subsampled = prepare_cloud(cloud, config, rng)
        found = run_improved(work.points, None, config, int(rng.integers(0, 2 ** 63)), least, max_spheres, deadline)
    spheres = []
    for v in found:
        if subsampled:
            inl = _all_inliers(cloud, v.centre_m, R, v.eps_m)
        else:
            inl = v.inliers if index is None else index[v.inliers]
        cp, ce = sphere_circles(cloud, v.centre_m, R, v.stats, depth)
        spheres.append(Sphere(centre_m=v.centre_m, radius_m=R, free_radius_m=v.free_radius_m, inlier_indices=inl,
                              score=v.score, raw_score=v.raw_score, rmse_m=v.rmse_m, free_radius_se_m=v.free_radius_se_m, circle_paper=cp,
                              circle_exact=ce, evidence={**v.stats, "eps_m": v.eps_m,
                                                          **({"frame_noise": frame.noise} if depth is not None else {})}))
    return spheres
