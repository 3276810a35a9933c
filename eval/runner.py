"""Running the benchmark's methods over a dataset: per-scene predictions, seeded, resumable.

A *method* (``MethodSpec``) turns a scene folder into detections. One detection run of a 3D
method gives two prediction sets, one per 2D rule of ``spherebench.circles``:

    <name>               the exact silhouette reduced to a circle (the ground truth's rule)
    <name>+paper-circle  the paper's rule (project the centre and a point R to its left)

Methods (``build_methods``):
- ``improved``, ``paper``, ``paper-lstsq``: ``spherebench.method.detect`` with that preset;
- ``pyransac3d``: the generic peer, pyransac3d's free-radius sphere RANSAC (``Sphere().fit``) on
  a seeded subsample of each cloud; its circle is the projection of its centre with its own
  radius, its score its inlier fraction;
- ``hough``: OpenCV's Hough circle transform (``spherebench.baselines.hough``) on image.png,
  with a configuration tuned on the training split (``tuned_hough_config``);
- ``circlenet``: the CircleNet-style ONNX model (``spherebench.baselines.circlenet.infer``)
  on image.png scaled to its training focal length by the scene's intrinsics, when a model file
  exists; ``circlenet-full`` (ResNet-18 at its own widths) and
  ``circlenet-hg`` (the stacked hourglass) the same with the GPU-trained models
  (``CIRCLENET_MODELS``).

Output, per prediction set, in ``<out>/<name>.json``: a COCO results list with CircleNet's
fields (image_id, category_id, circle_center [x, y], circle_radius (px), score) plus scene_id
and, for 3D methods, center_m (m) and radius_m (m, only where the method estimates a radius:
the free-fit radius of ``improved``, pyransac3d's own radius). Beside it ``<name>.meta.json``:
the provenance (dataset fingerprint, configuration, seed, code version: the resume key), the
per-scene records (time per frame, detections in 3D, resolution) and what the scoring needs.
Both are written atomically, the meta file last: a set whose meta file is present, readable and
carries the same key and the same predictions hash is finished and is reused, so an interrupted
run redoes no finished work.

Seeding: scene k of a dataset (scene folders sorted by id) is run with the seed
``scene_seed(seed, k)`` (numpy SeedSequence of (seed, k)). Scenes are spread over worker
processes (``spawn``), but every scene's output depends on its seed only, so the files are
identical for any number of workers. Time per frame is measured around the detection call
alone (no file reading), one thread per worker (numba, OpenMP/BLAS, OpenCV, ONNX Runtime).
"""

from __future__ import annotations

import contextlib
import ctypes
import dataclasses
import datetime as _dt
import functools
import hashlib
import json
import math
import os
import sys
import platform
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterable, Sequence

import numpy as np

from spherebench.errors import SphereBenchError
from spherebench.parallel import process_pool

#: Format version of the predictions' meta files (part of the resume key).
FORMAT_VERSION = 1
#: Repository root (the folder that holds method/, baselines/, ...).
REPO_ROOT = Path(__file__).resolve().parents[1]
#: Suffix of the prediction set that uses the paper's projection rule.
PAPER_CIRCLE = "+paper-circle"
#: Environment variables that pin a worker to one thread (set before the worker starts).
SINGLE_THREAD_ENV = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1",
                     "NUMBA_NUM_THREADS": "1", "VECLIB_MAXIMUM_THREADS": "1"}
#: CircleNet: detections below this score are not written (keeps files small; CenterNet keeps
#: its top 100, most of which score ~0).
CIRCLENET_MIN_SCORE = 0.01
#: CircleNet: at most this many circles per image (CenterNet's K).
CIRCLENET_TOP_K = 100
#: pyransac3d: the peer's own cost (2-3 s per 1,000 iterations on 100k points) does not fit the
#: benchmark's budget; it runs on this many points, drawn at random (seeded) from each cloud.
PYRANSAC3D_POINTS = 2_000
#: pyransac3d: RANSAC iterations and inlier threshold (m), its own defaults being 1,000 and 0.2 m.
PYRANSAC3D_ITERATIONS = 1000
PYRANSAC3D_THRESH_M = 0.01

#: The CircleNet models: method name -> (ONNX file under baselines/circlenet/, how to make it).
#: ``circlenet``: the half-width ResNet-18 trained on the CPU; the others need a CUDA machine.
CIRCLENET_MODELS = {
    "circlenet": ("model.onnx", "make train"),
    "circlenet-full": ("full/model.onnx", "make train-full, on a CUDA machine"),
    "circlenet-hg": ("hg/model.onnx", "make train-hg, on a CUDA machine"),
}

#: Shipped models trained on an earlier `train` preset, by the sha256 of their ONNX file: their rows
#: say so (the full-size model needs a CUDA machine to retrain, and none was at hand when `train`
#: began drawing each scene's sensor, bf6a801).
EARLIER_TRAIN = {
    "3b72295ef7ff02b8fd1f939613db8828eb10db18006e57b50997ff17d2236862":
        "trained on the earlier train preset (nominal sensor, before bf6a801); `make train-full` on a CUDA "
        "machine retrains it on the current one",
}

METHOD_ORDER = ("improved", "paper", "paper-lstsq", "pyransac3d", "hough", *CIRCLENET_MODELS)


def scene_seed(seed: int, index: int) -> int:
    """The seed of scene ``index`` (0-based, scene-id order) for a run seed: SeedSequence((seed, index))."""
    return int(np.random.SeedSequence([int(seed), int(index)]).generate_state(1, np.uint64)[0] >> 1)


# --------------------------------------------------------------------------- provenance helpers

def _hash_files(paths: Iterable[Path], root: Path) -> str:
    h = hashlib.blake2b(digest_size=16)
    for p in paths:
        h.update(str(p.relative_to(root)).encode())
        h.update(b"\0")
        with open(p, "rb") as f:
            for block in iter(lambda: f.read(1 << 20), b""):
                h.update(block)
        h.update(b"\1")
    return h.hexdigest()


def dataset_fingerprint(data_dir: str | Path) -> str:
    """Content hash of a dataset: every file under scenes/ and the ground truth (not its folder name)."""
    root = Path(data_dir)
    scenes = root / "scenes"
    if not scenes.is_dir():
        raise SphereBenchError(f"{root}: not a dataset (no scenes/ folder); build one with 'spherebench generate' "
                               "or 'spherebench prepare'")
    files = sorted(p for p in scenes.rglob("*") if p.is_file() and not any(s.startswith(".") for s in p.parts[-2:]))
    h = hashlib.blake2b(digest_size=16)
    h.update(_hash_files(files, root).encode())
    gt = root / "coco_gt.json"
    if gt.is_file():
        from spherebench.datasets import inout  # deferred, as everywhere here: `evaluate --help` stays fast
        coco = inout.read_json(gt)  # a truncated file: one line, not a traceback
        h.update(json.dumps({k: coco.get(k) for k in ("images", "annotations", "categories")},
                            sort_keys=True).encode())
    return h.hexdigest()


def code_version(modules: Sequence[str]) -> str:
    """Content hash of the source files of the given modules (dotted names; a package: all its .py)."""
    import importlib.util
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


def file_sha256(path: str | Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


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


# --------------------------------------------------------------------------- methods

#: Modules whose source is every method's code version (scene reading, circles, the runner).
_CORE_MODULES = ("spherebench.camera", "spherebench.cloud", "spherebench.circles", "spherebench.datasets.inout",
                 "spherebench.eval.runner")


@dataclass(frozen=True)
class MethodSpec:
    """A method of the benchmark.

    name: its name; its prediction sets are ``outputs``.
    kind: "3d" (reads cloud.ply + intrinsics) or "2d" (reads image.png).
    config: JSON-able settings that fully define it (part of the resume key).
    modules: the modules whose source defines it (their hash is the code version).
    note: a sentence for the tables (subsampling, model card), or "".
    extra_fingerprint: anything else it depends on (the CircleNet model file's hash).
    resource: a file the method loads (the model), not part of the key (its hash is).
    """

    name: str
    kind: str
    config: dict
    modules: tuple[str, ...]
    note: str = ""
    extra_fingerprint: str = ""
    resource: str | None = None
    outputs: tuple[str, ...] = field(default=())

    def __post_init__(self) -> None:
        if not self.outputs:
            outs = (self.name, self.name + PAPER_CIRCLE) if self.kind == "3d" else (self.name,)
            object.__setattr__(self, "outputs", outs)

    def config_json(self) -> str:
        return json.dumps(self.config, sort_keys=True)


def detector_spec(name: str, **overrides) -> MethodSpec:
    """``improved`` / ``paper`` / ``paper-lstsq``: the 3D detector with that preset (fields overridden,
    e.g. radius_m for a dataset of another ball)."""
    from spherebench.method import config_for
    cfg = config_for(name, **overrides)
    return MethodSpec(name=name, kind="3d", config={"engine": "detector", "preset": name, **dataclasses.asdict(cfg)},
                      modules=_CORE_MODULES + ("spherebench.method",))


def pyransac3d_spec(points: int = PYRANSAC3D_POINTS, iterations: int = PYRANSAC3D_ITERATIONS,
                    thresh_m: float = PYRANSAC3D_THRESH_M, radius_m: float = 0.12) -> MethodSpec:
    """pyransac3d's sphere fit on a random subsample of ``points`` points of each cloud.

    radius_m (the dataset's R) is not given to it (it fits the radius freely); it is recorded so
    that the radius error is read against it."""
    return MethodSpec(name="pyransac3d", kind="3d",
                      config={"engine": "pyransac3d", "points": int(points), "iterations": int(iterations),
                              "thresh_m": float(thresh_m), "radius_m": float(radius_m),
                              "pyransac3d": _dist_version("pyransac3d")},
                      modules=_CORE_MODULES + ("spherebench.baselines.pyransac3d_peer",),
                      note=f"pyransac3d Sphere().fit on {points:,} points drawn at random from each cloud, "
                           f"{iterations:,} iterations, threshold {100 * thresh_m:g} cm (at full resolution it "
                           "takes 2-3 s per frame, beyond the budget)")


def hough_spec(config) -> MethodSpec:
    """The Hough baseline with a ``HoughConfig`` (tuned on the training split)."""
    return MethodSpec(name="hough", kind="2d", config={"engine": "hough", **dataclasses.asdict(config)},
                      modules=_CORE_MODULES + ("spherebench.baselines.hough",))


def card_budget(card: dict) -> str:
    """One line of a CircleNet model card: its training budget and validation score."""
    val = card.get("val_onnx") or card.get("val_torch") or {}
    data = card.get("data", {})
    half = "; weights stored as float16" if (card.get("onnx") or {}).get("weights") == "float16" else ""
    return (f"trained from scratch on {data.get('train_images', '?')} `{data.get('preset', 'train')}` images, "
            f"{card.get('epochs', '?')} epochs, {card.get('train_seconds', 0) / 60:.0f} min on {card.get('device', '?')}; "
            f"validation mAP.50 {val.get('mAP50', float('nan')):.3f}{half}")


def circlenet_model_path(name: str = "circlenet") -> Path:
    """The shipped ONNX file of a CircleNet method of ``CIRCLENET_MODELS`` (it may not exist)."""
    from spherebench.baselines.circlenet.infer import DEFAULT_MODEL
    return DEFAULT_MODEL.parent / CIRCLENET_MODELS[name][0]


def circlenet_spec(model_path: str | Path, name: str = "circlenet") -> MethodSpec:
    """CircleNet from an ONNX file, as method ``name``; raises SphereBenchError if the file is missing or
    is not a loadable SphereBench CircleNet model."""
    path = Path(model_path)
    if not path.is_file():
        shown = path.resolve().relative_to(REPO_ROOT) if path.resolve().is_relative_to(REPO_ROOT) else path
        how = CIRCLENET_MODELS.get(name, CIRCLENET_MODELS["circlenet"])[1]
        raise SphereBenchError(f"CircleNet model {shown} not found (train it with `{how}`)")
    sha = file_sha256(path)
    _check_model(str(path.resolve()), sha)
    card_path = path.with_name("model_card.json")
    budget = ""
    if card_path.is_file():  # the training budget belongs next to the numbers (fairness)
        from spherebench.datasets import inout
        card = inout.read_json(card_path)
        budget = "; " + card_budget(card if isinstance(card, dict) else {})
    return MethodSpec(name=name, kind="2d",
                      config={"engine": "circlenet", "model": path.name, "min_score": CIRCLENET_MIN_SCORE,
                              "top_k": CIRCLENET_TOP_K, "scale": "focal_px",
                              "onnxruntime": _dist_version("onnxruntime")},
                      modules=_CORE_MODULES + ("spherebench.baselines.circlenet",),
                      extra_fingerprint=sha, resource=str(path.resolve()),
                      note="ONNX Runtime, CPU, 1 thread; each image is scaled uniformly to the training focal "
                           "length (the scene's sqrt(fx fy) from intrinsics.json; nearest neighbour, padded to the "
                           "stride, as in training) and the circles scaled back" + budget
                           + (f"; {EARLIER_TRAIN[sha]}" if sha in EARLIER_TRAIN else ""))


@functools.lru_cache(maxsize=8)
def _check_model(path: str, sha256: str) -> None:
    """Load the ONNX model once (per content) before any method runs: a corrupt or foreign file is
    refused here, not in a worker after the other methods have run."""
    from spherebench.baselines.circlenet.infer import CircleNetDetector
    CircleNetDetector(path, threads=1)


def _dist_version(name: str) -> str | None:
    from importlib.metadata import PackageNotFoundError, version
    try:
        return version(name)
    except PackageNotFoundError:
        return None


def build_methods(names: Sequence[str] | None = None, hough_config=None, circlenet_model: str | Path | None = None,
                  table_note: Callable[[str, str], None] | None = None, radius_m: float = 0.12) -> list[MethodSpec]:
    """The benchmark's methods (``METHOD_ORDER`` or ``names``), skipping the unavailable ones.

    radius_m: the dataset's ball radius (the 3D methods' R).
    hough_config: the tuned ``HoughConfig`` (None: OpenCV-tutorial defaults, said in the note).
    circlenet_model: the ONNX file of ``circlenet`` (None: the shipped one); the other CircleNet
    methods always use their shipped files (``CIRCLENET_MODELS``).
    table_note(name, reason) is called for every method skipped, with the reason.
    Unknown names raise SphereBenchError.
    """
    wanted = list(METHOD_ORDER if names is None else names)
    unknown = [n for n in wanted if n not in METHOD_ORDER]
    if unknown:
        raise SphereBenchError(f"unknown method(s) {', '.join(unknown)}: choose from {', '.join(METHOD_ORDER)}")
    specs = []
    for name in wanted:
        try:
            if name in ("improved", "paper", "paper-lstsq"):
                specs.append(detector_spec(name, radius_m=float(radius_m)))
            elif name == "pyransac3d":
                specs.append(pyransac3d_spec(radius_m=float(radius_m)))
            elif name == "hough":
                from spherebench.baselines.hough import HoughConfig
                spec = hough_spec(hough_config or HoughConfig())
                if hough_config is None:
                    spec = dataclasses.replace(spec, note="untuned defaults (no tuned configuration given)")
                specs.append(spec)
            elif name in CIRCLENET_MODELS:
                given = circlenet_model if name == "circlenet" else None
                specs.append(circlenet_spec(given if given is not None else circlenet_model_path(name), name=name))
        except SphereBenchError as exc:
            if table_note is None:
                raise
            table_note(name, str(exc))
    return specs


# --------------------------------------------------------------------------- engines (in workers)

def _r(x, nd: int):
    return None if x is None or not math.isfinite(float(x)) else round(float(x), nd)


def _circle(c) -> list[float] | None:
    return None if c is None else [round(float(v), 3) for v in c]


def _coco_bbox(circle) -> list[float]:
    """A result's COCO bbox [x, y, w, h] px round its circle: pycocotools' loadRes needs one."""
    from spherebench.circles import circle_bbox
    return [round(v, 3) for v in circle_bbox(*circle)]


class _DetectorEngine:
    """The 3D detector (``spherebench.method``)."""

    kind = "3d"

    def __init__(self, config: dict):
        from spherebench.method import DetectorConfig
        fields = {f.name for f in dataclasses.fields(DetectorConfig)}
        self.config = DetectorConfig(**{k: v for k, v in config.items() if k in fields})
        self.estimates_radius = self.config.pipeline == "improved"

    def load(self, scene_dir: Path):
        from spherebench.datasets import inout
        return inout.load_cloud(scene_dir)

    def detect(self, cloud, seed: int) -> list[dict]:
        from spherebench.method import detect
        return [{"score": float(s.score), "center_m": [float(v) for v in s.center_m],
                 "radius_m": float(s.free_radius_m) if self.estimates_radius else None,
                 "circle": s.circle_exact, "circle_paper": s.circle_paper}
                for s in detect(cloud, self.config, seed=seed)]


class _PyRansac3dEngine:
    """The generic peer: pyransac3d's free-radius sphere RANSAC (``Sphere().fit``), used as a user
    would: on the cloud's points (a seeded random subsample of ``points``), inlier threshold
    ``thresh_m``, ``iterations`` iterations. Its sphere is reported with its own radius; its score
    is its inlier fraction; its circles project its own centre and radius by both 2D rules."""

    kind = "3d"

    def __init__(self, config: dict):
        self.config = config

    def load(self, scene_dir: Path):
        from spherebench.datasets import inout
        return inout.load_cloud(scene_dir)

    def detect(self, cloud, seed: int) -> list[dict]:
        from spherebench.baselines import pyransac3d_peer
        if len(cloud.points) < 4:
            return []
        found = pyransac3d_peer.detect(cloud, points=self.config["points"], iterations=self.config["iterations"],
                                       thresh_m=self.config["thresh_m"], seed=seed)
        return [{"score": d["score"], "center_m": [float(v) for v in d["center_m"]], "radius_m": float(d["radius_m"]),
                 "circle": d["circle_exact"], "circle_paper": d["circle_paper"]} for d in found]


class _HoughEngine:
    kind = "2d"

    def __init__(self, config: dict):
        from spherebench.baselines.hough import HoughConfig
        fields = {f.name for f in dataclasses.fields(HoughConfig)}
        self.config = HoughConfig(**{k: v for k, v in config.items() if k in fields})

    def load(self, scene_dir: Path):
        from spherebench.datasets import inout
        return inout.read_image(scene_dir / "image.png")

    def detect(self, image, seed: int) -> list[dict]:
        from spherebench.baselines.hough import detect_circles
        return [{"score": s, "circle": (cx, cy, r)} for cx, cy, r, s in detect_circles(image, self.config)]


class _CircleNetEngine:
    """CircleNet on a scene's image.png, scaled by the detector to its training focal length from the
    scene's own intrinsics (``scene_focal_px``; a scene without intrinsics.json: to the model's
    width, exact for every D435 mode)."""

    kind = "2d"

    def __init__(self, config: dict, model_path: Path):
        from spherebench.baselines.circlenet.infer import CircleNetDetector
        self.config = config
        self.detector = CircleNetDetector(model_path, threads=1)

    def load(self, scene_dir: Path):
        from spherebench.baselines.circlenet.imaging import load_image
        from spherebench.baselines.circlenet.infer import scene_focal_px
        return load_image(scene_dir / "image.png"), scene_focal_px(scene_dir)  # RGB, as in training

    def detect(self, inputs, seed: int) -> list[dict]:
        image, focal_px = inputs
        if self.config.get("scale") != "focal_px":  # a configuration of before the rule: the model's width
            focal_px = None
        circles = self.detector.detect(image, min_score=self.config["min_score"], top_k=self.config["top_k"],
                                       focal_px=focal_px)
        return [{"score": float(sc), "circle": (float(cx), float(cy), float(r))} for cx, cy, r, sc in circles]


_ENGINES: dict[tuple[str, str], object] = {}


def _engine(spec_name: str, config_json: str, model_path: str | None, warm_scene: str | None = None):
    """The engine of a method in this process, built once; a new one first runs ``warm_scene``
    untimed, so that compilation and model loading stay out of every timing."""
    key = (spec_name, config_json)
    if key not in _ENGINES:
        config = json.loads(config_json)
        kind = config["engine"]
        if kind == "detector":
            _ENGINES[key] = _DetectorEngine(config)
        elif kind == "pyransac3d":
            _ENGINES[key] = _PyRansac3dEngine(config)
        elif kind == "hough":
            _ENGINES[key] = _HoughEngine(config)
        elif kind == "circlenet":
            _ENGINES[key] = _CircleNetEngine(config, Path(model_path))
        else:
            raise SphereBenchError(f"unknown engine {kind}")
        if warm_scene is not None:
            engine = _ENGINES[key]
            with contextlib.suppress(SphereBenchError):  # the scene itself reports its own error later
                engine.detect(engine.load(Path(warm_scene)), 0)
    return _ENGINES[key]


def _single_thread() -> None:
    """Pin this process's libraries to one thread (the timings are single-threaded)."""
    for k, v in SINGLE_THREAD_ENV.items():
        if k != "NUMBA_NUM_THREADS" or "numba" not in sys.modules:  # numba: only before it loads
            os.environ[k] = v
    try:
        import cv2
        cv2.setNumThreads(1)
    except ImportError:
        pass
    try:
        import numba
        numba.set_num_threads(1)
    except (ImportError, ValueError):
        pass


def _run_task(task: tuple) -> dict:
    """One scene through one method (in a worker). Returns the scene's record.

    A scene the method refuses (SphereBenchError: say, a cloud with too few valid points) gives
    no detection, and the reason is kept in the record's "error"."""
    spec_name, config_json, model_path, warm_scene, scene_dir, index, seed = task
    engine = _engine(spec_name, config_json, model_path, warm_scene)
    inputs = engine.load(Path(scene_dir))
    error = None
    t0 = time.perf_counter()
    try:
        dets = engine.detect(inputs, seed)
    except SphereBenchError as exc:
        dets, error = [], str(exc)
    ms = 1000.0 * (time.perf_counter() - t0)
    return {"index": index, "seed": seed, "ms": ms, "detections": dets, "error": error}


# --------------------------------------------------------------------------- running

@dataclass
class SceneInfo:
    """A scene of the dataset as the runner and the scoring see it."""

    index: int
    scene_id: str
    path: Path
    image_id: int | None          # in coco_gt.json, or None (not scored in 2D)
    family: str
    resolution: str | None        # "WxH" or None (no intrinsics)
    annotated: bool
    has_cloud: bool
    has_image: bool
    gt_centres_m: list            # visible balls of the dataset's radius with a known centre, metres
    gt_radii_m: list
    n_balls: int                  # visible balls (in 2D: with a circle), whether or not their centre is known
    reference_centre_m: list | None = None  # a recording's reference fit (not ground truth), if any
    sensor_cell: dict | None = None         # a grid preset's sensor condition (gt.json meta.sensor_cell)


def dataset_scenes(data_dir: str | Path) -> list[SceneInfo]:
    """Every scene of a dataset, in scene-id order, with its image id and 3D ground truth."""
    from spherebench.datasets import inout
    root = Path(data_dir)
    coco = inout.read_coco_gt(root)
    image_ids = {img.get("scene_id"): img["id"] for img in coco["images"]}
    out = []
    for k, scene in enumerate(inout.list_scenes(root)):
        gt = inout.read_json(scene / "gt.json")
        res = None
        if (scene / "intrinsics.json").is_file():
            intr = inout.read_json(scene / "intrinsics.json")
            res = f"{intr.get('width')}x{intr.get('height')}"
        visible = [b for b in gt.get("balls", []) if b.get("circle") is not None or not (scene / "image.png").is_file()]
        balls = [b for b in visible if b.get("center_m") is not None]
        out.append(SceneInfo(index=k, scene_id=str(gt.get("scene_id", scene.name)), path=scene,
                             image_id=image_ids.get(gt.get("scene_id", scene.name)), family=str(gt.get("family")),
                             resolution=res, annotated=bool(gt.get("annotated", True)),
                             has_cloud=(scene / "cloud.ply").is_file(), has_image=(scene / "image.png").is_file(),
                             gt_centres_m=[b["center_m"] for b in balls], gt_radii_m=[b["radius_m"] for b in balls],
                             n_balls=len(visible),
                             reference_centre_m=(gt.get("meta") or {}).get("reference_center_m"),
                             sensor_cell=(gt.get("meta") or {}).get("sensor_cell")))
    if not out:
        raise SphereBenchError(f"{root}: the dataset has no scenes")
    return out


def _key(spec: MethodSpec, output: str, fingerprint: str, seed: int, version: str, scene_ids: list[str]) -> str:
    blob = json.dumps({"format": FORMAT_VERSION, "output": output, "config": spec.config, "seed": int(seed),
                       "dataset": fingerprint, "code": version, "extra": spec.extra_fingerprint,
                       "scenes": scene_ids}, sort_keys=True)
    return hashlib.sha256(blob.encode()).hexdigest()


def meta_path(pred_path: Path) -> Path:
    return pred_path.with_name(pred_path.name[:-len(".json")] + ".meta.json")


def is_finished(pred_path: Path, key: str) -> bool:
    """A prediction set is finished when its meta file carries ``key`` and the predictions' hash."""
    meta_file = meta_path(pred_path)
    if not pred_path.is_file() or not meta_file.is_file():
        return False
    try:
        meta = json.loads(meta_file.read_text())
    except (OSError, json.JSONDecodeError, UnicodeDecodeError):
        return False
    return meta.get("key") == key and meta.get("predictions_sha256") == file_sha256(pred_path)


def read_predictions(pred_path: str | Path) -> tuple[list[dict], dict]:
    """(COCO results list, meta dict) of a prediction set."""
    from spherebench.datasets import inout
    pred_path = Path(pred_path)
    return inout.read_json(pred_path), inout.read_json(meta_path(pred_path))


def _results_and_records(spec: MethodSpec, output: str, scenes: list[SceneInfo], records: list[dict],
                         category_id: int) -> tuple[list[dict], list[dict]]:
    """The COCO results list and the per-scene records of one prediction set."""
    circle_key = "circle_paper" if output.endswith(PAPER_CIRCLE) else "circle"
    results, scene_records = [], []
    for scene, rec in zip(scenes, records):
        dets3d = []
        for d in rec["detections"]:
            circle = d.get(circle_key)
            entry = {"score": round(float(d["score"]), 6), "circle": _circle(circle)}
            if spec.kind == "3d":
                entry["center_m"] = [round(float(v), 6) for v in d["center_m"]]
                entry["radius_m"] = _r(d.get("radius_m"), 6)
            dets3d.append(entry)
            if scene.image_id is not None and circle is not None and circle[2] > 0:
                r = {"image_id": scene.image_id, "category_id": category_id,
                     "circle_center": entry["circle"][:2], "circle_radius": entry["circle"][2],
                     "bbox": _coco_bbox(entry["circle"]), "score": entry["score"], "scene_id": scene.scene_id}
                if spec.kind == "3d":
                    r["center_m"] = entry["center_m"]
                    if entry["radius_m"] is not None:
                        r["radius_m"] = entry["radius_m"]
                results.append(r)
        scene_records.append({"scene_id": scene.scene_id, "image_id": scene.image_id, "index": scene.index,
                              "seed": rec["seed"], "resolution": scene.resolution, "ms": round(rec["ms"], 4),
                              "detections": dets3d, **({"error": rec["error"]} if rec.get("error") else {}),
                              **({"sensor_cell": scene.sensor_cell} if scene.sensor_cell else {})})
    return results, scene_records


@contextlib.contextmanager
def _pool(workers: int):
    """A pool of ``workers`` spawned processes, each pinned to one thread; None for workers <= 1."""
    if workers <= 1:
        with _SingleThreadHere():
            yield None
        return
    # inherited by the workers before they import anything; NUMBA_NUM_THREADS is left to the
    # workers' initializer: numba rereads it in this process at its next compilation, and refuses
    # a value other than its running thread pool's
    child_env = {k: v for k, v in SINGLE_THREAD_ENV.items() if k != "NUMBA_NUM_THREADS"}
    saved = {k: os.environ.get(k) for k in child_env}
    os.environ.update(child_env)
    try:
        # workers ignore Ctrl-C and are terminated when this run stops (spherebench.parallel)
        with process_pool(workers, initializer=_single_thread, start_method="spawn") as pool:
            yield pool
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def run_methods(data_dir: str | Path, out_dir: str | Path, specs: Sequence[MethodSpec], seed: int = 0,
                workers: int = 2, progress: bool = True, force: bool = False,
                scene_filter: Callable[[SceneInfo], bool] | None = None,
                fingerprint: str | None = None, log: Callable[[str], None] = print) -> dict[str, Path]:
    """Run ``specs`` on every scene of ``data_dir``; write one prediction set per output into ``out_dir``.

    seed: the run seed (scene k gets ``scene_seed(seed, k)``). workers: processes (<= 1: in this
    process). force: recompute even finished sets. scene_filter: run only the scenes it accepts
    (others are absent from the files; the scoring restricts itself to the scenes run).
    Returns {output name: predictions path}. Finished sets with the same inputs are reused.
    """
    from tqdm import tqdm
    from spherebench.datasets import inout

    data_dir, out_dir = Path(data_dir), Path(out_dir)
    scenes = dataset_scenes(data_dir)
    fingerprint = fingerprint or dataset_fingerprint(data_dir)
    coco = inout.read_coco_gt(data_dir)
    category_id = int(coco["categories"][0]["id"]) if coco.get("categories") else 1
    meta_ds = inout.read_dataset_meta(data_dir) if (data_dir / "dataset.json").is_file() else {}
    paths: dict[str, Path] = {}
    pending: list[tuple[MethodSpec, list[SceneInfo], dict[str, str], str]] = []
    for spec in specs:
        chosen = [s for s in scenes if (s.has_cloud if spec.kind == "3d" else s.has_image)]
        if scene_filter is not None:
            chosen = [s for s in chosen if scene_filter(s)]
        if not chosen:
            log(f"{spec.name}: no scene of {data_dir} has its input ({'cloud.ply' if spec.kind == '3d' else 'image.png'})")
            continue
        version = code_version(spec.modules)
        keys = {o: _key(spec, o, fingerprint, seed, version, [s.scene_id for s in chosen]) for o in spec.outputs}
        for o in spec.outputs:
            paths[o] = out_dir / f"{o}.json"
        if not force and all(is_finished(paths[o], keys[o]) for o in spec.outputs):
            log(f"{spec.name}: predictions on {data_dir.name} up to date, reused")
            continue
        pending.append((spec, chosen, keys, version))
    if not pending:
        return paths
    tasks = [(spec.name, spec.config_json(), spec.resource, str(chosen[0].path), str(s.path), s.index,
              scene_seed(seed, s.index)) for spec, chosen, _, _ in pending for s in chosen]
    counts = [len(chosen) for _, chosen, _, _ in pending]
    bar = tqdm(total=len(tasks), desc=f"run {data_dir.name}", unit="frame", disable=not progress)
    try:
        with _pool(workers) as pool:
            it = iter(pool.map(_run_task, tasks, chunksize=1) if pool is not None else map(_run_task, tasks))
            for (spec, chosen, keys, version), n in zip(pending, counts):
                bar.set_postfix_str(spec.name)
                records = []
                for _ in range(n):
                    records.append(next(it))
                    bar.update()
                for output in spec.outputs:
                    _write_set(out_dir / f"{output}.json", spec, output, chosen, records, category_id, keys[output],
                               version, seed, fingerprint, data_dir, meta_ds, len(scenes), workers)
    finally:
        bar.close()
    return paths


def _write_set(pred: Path, spec: MethodSpec, output: str, chosen: list[SceneInfo], records: list[dict],
               category_id: int, key: str, version: str, seed: int, fingerprint: str, data_dir: Path,
               meta_ds: dict, n_scenes: int, workers: int) -> None:
    """Write one prediction set and then its meta file (the mark of a finished set)."""
    from spherebench.datasets import inout
    res, scene_records = _results_and_records(spec, output, chosen, records, category_id)
    inout.write_json(pred, res, indent=None)
    meta = {"format": FORMAT_VERSION, "output": output, "method": spec.name, "kind": spec.kind,
            "rule": ("paper" if output.endswith(PAPER_CIRCLE) else "exact") if spec.kind == "3d" else None,
            "key": key, "predictions_sha256": file_sha256(pred), "config": spec.config,
            "note": spec.note, "seed": int(seed), "seeding": "scene k: SeedSequence((seed, k))",
            "dataset": {"path": str(data_dir), "fingerprint": fingerprint, "preset": meta_ds.get("preset"),
                        "name": meta_ds.get("name"), "n_scenes": n_scenes, "n_run": len(chosen)},
            "code_version": version, "modules": list(spec.modules), "extra_fingerprint": spec.extra_fingerprint,
            "workers": int(max(1, workers)),
            "timing": "ms around the detection call only (no file reading), 1 thread per worker process",
            "machine": machine_info(), "created": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
            "scenes": scene_records}
    inout.write_json(meta_path(pred), meta, indent=None)


class _SingleThreadHere:
    """Numba and OpenCV at one thread in this process for a while (in-process runs), then restored."""

    def __enter__(self):
        self.saved = {}
        try:
            import cv2
            self.saved["cv2"] = cv2.getNumThreads()
            cv2.setNumThreads(1)
        except ImportError:
            pass
        try:
            import numba
            self.saved["numba"] = numba.get_num_threads()
            numba.set_num_threads(1)
        except ImportError:
            pass
        return self

    def __exit__(self, *exc):
        if "cv2" in self.saved:
            import cv2
            cv2.setNumThreads(self.saved["cv2"])
        if "numba" in self.saved:
            import numba
            numba.set_num_threads(self.saved["numba"])
        return False


# --------------------------------------------------------------------------- Hough: tuned on the training split

#: The training subset the Hough parameters are chosen on: `spherebench generate --preset train --n 200`.
HOUGH_TRAIN_SCENES = 200


def _hough_key(n: int, seed: int) -> str:
    from spherebench.baselines.hough import DEFAULT_GRID, HoughConfig
    blob = json.dumps({"train": {"preset": "train", "n": int(n), "seed": int(seed)}, "grid": DEFAULT_GRID,
                       "base": dataclasses.asdict(HoughConfig()),
                       "code": code_version(("spherebench.baselines.hough", "spherebench.eval.coco_eval",
                                             "spherebench.datasets"))}, sort_keys=True)
    return hashlib.sha256(blob.encode()).hexdigest()


def tuned_hough_config(cache_path: str | Path, train_dir: str | Path, n: int = HOUGH_TRAIN_SCENES, seed: int = 0,
                       workers: int = 2, progress: bool = True, log: Callable[[str], None] = print):
    """The Hough configuration with the best mAP.50 on the training split (``hough.tune``), cached.

    The cache (JSON at ``cache_path``) is reused while its key (training subset: preset train,
    ``n`` scenes, ``seed``; the search grid; the code of the Hough baseline, the scoring and the
    simulator) is unchanged. Otherwise the subset is built in ``train_dir`` if absent
    (`spherebench generate --preset train --n N`) and the grid searched. The benchmark's scenes
    are never seen: the training preset's seeds are disjoint from theirs.
    """
    from spherebench.baselines import hough
    from spherebench.datasets import inout, simulate

    cache_path, train_dir = Path(cache_path), Path(train_dir)
    key = _hough_key(n, seed)
    if cache_path.is_file():
        try:
            cached = json.loads(cache_path.read_text())
            if cached.get("key") == key:
                log(f"hough: tuned configuration reused from {cache_path}")
                return hough.HoughConfig(**cached["config"])
        except (OSError, json.JSONDecodeError, TypeError):
            pass
    meta = inout.read_dataset_meta(train_dir) if (train_dir / "dataset.json").is_file() else None
    if meta is None or meta.get("preset") != "train" or meta.get("n") != n or meta.get("seed") != seed:
        if meta is not None and meta.get("preset") != "train":
            raise SphereBenchError(f"{train_dir} holds the '{meta.get('preset')}' preset: the Hough baseline is tuned "
                                   "on the training split only")
        log(f"hough: building the training subset ({n} scenes of the train preset) in {train_dir}")
        simulate.generate_dataset("train", train_dir, n=n, seed=seed, workers=workers, progress=progress)
    t0 = time.perf_counter()
    grid = hough.DEFAULT_GRID
    log(f"hough: searching {len(grid)} settings on the {n} training images")
    parts = [grid[i::max(1, workers)] for i in range(max(1, workers))]
    with _pool(workers) as pool:
        scored_parts = list(pool.map(_hough_grid_part, [str(train_dir)] * len(parts), parts)
                            if pool is not None else map(_hough_grid_part, [str(train_dir)], parts))
    # back to grid order: part i holds entries i, i + workers, ...
    scored = [None] * len(grid)
    for i, part in enumerate(scored_parts):
        for j, item in enumerate(part):
            scored[i + j * len(parts)] = item
    # hough.tune's rule: best mAP.50, ties to mAP, then to the earlier grid entry
    best, best_metrics = scored[0]
    for cfg, m in scored[1:]:
        if (np.nan_to_num(m["mAP50"], nan=-1.0), np.nan_to_num(m["mAP"], nan=-1.0)) > \
                (np.nan_to_num(best_metrics["mAP50"], nan=-1.0), np.nan_to_num(best_metrics["mAP"], nan=-1.0)):
            best, best_metrics = cfg, m
    record = {"key": key, "config": dataclasses.asdict(best),
              "chosen_by": "mAP.50 (circle IoU, COCO protocol) on the training subset, ties to mAP",
              "train": {"path": str(train_dir), "preset": "train", "n": n, "seed": seed,
                        "fingerprint": dataset_fingerprint(train_dir)},
              "train_metrics": {k: best_metrics.get(k) for k in ("mAP", "mAP50", "mAP75", "mAR")},
              "grid": [{"overrides": {k: v for k, v in dataclasses.asdict(c).items()
                                      if v != getattr(hough.HoughConfig(), k)},
                        "mAP": m.get("mAP"), "mAP50": m.get("mAP50")} for c, m in scored],
              "seconds": round(time.perf_counter() - t0, 1)}
    inout.write_json(cache_path, _json_safe(record))
    return best


def _hough_grid_part(train_dir: str, grid: list[dict]) -> list:
    """``hough.grid_scores`` of part of the grid on a training dataset's images (in a worker)."""
    from spherebench.baselines import hough
    from spherebench.datasets import inout
    root = Path(train_dir)
    coco = inout.read_coco_gt(root)
    circles: dict[int, list] = {img["id"]: [] for img in coco["images"]}
    for a in coco["annotations"]:
        circles[a["image_id"]].append([*a["circle_center"], a["circle_radius"]])
    images = [inout.read_image(root / img["file_name"]) for img in coco["images"]]
    gts = [np.asarray(circles[img["id"]], np.float64).reshape(-1, 3) for img in coco["images"]]
    return hough.grid_scores(images, gts, grid)


def _json_safe(obj):
    """NaN and infinities -> None, numpy scalars -> Python (strict JSON)."""
    if isinstance(obj, dict):
        return {str(k): _json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_json_safe(v) for v in obj]
    if isinstance(obj, (np.floating, float)):
        return float(obj) if math.isfinite(float(obj)) else None
    if isinstance(obj, (np.integer,)):
        return int(obj)
    if isinstance(obj, np.ndarray):
        return _json_safe(obj.tolist())
    return obj


# --------------------------------------------------------------------------- the oracle's ceiling (grid presets)

#: The modules whose source defines the oracle's rows (with the detector's configuration and the data).
ORACLE_MODULES = ("spherebench.eval.oracle", "spherebench.method", "spherebench.eval.sensor_grid",
                  "spherebench.datasets.inout", "spherebench.cloud")


def oracle_balls(data_dir: str | Path, cache_path: str | Path, seed: int = 0, workers: int = 2,
                 log: Callable[[str], None] = print) -> list[dict] | None:
    """Per true ball of a dataset with known centres: the improved detector's ceiling there
    (``eval.oracle.ceiling``: its verification started from the true centre), cached.

    Rows {scene_id, ball (index in gt.json), cell (the scene's sensor_cell or None), band
    (``sensor_grid.band_of``), within, separable, score}; scene k's clutter search uses the seed
    ``scene_seed(seed, k)``. The cache (JSON at ``cache_path``) is reused while its key (the
    dataset's fingerprint, the configuration, the seed and ``ORACLE_MODULES``' code) is unchanged.
    None when this installation has no ``spherebench.eval.oracle``.
    """
    import importlib.util
    from spherebench.datasets import inout
    from spherebench.method import config_for
    if importlib.util.find_spec("spherebench.eval.oracle") is None:
        log("oracle: spherebench.eval.oracle is not installed; no ceiling drawn")
        return None
    data_dir, cache_path = Path(data_dir), Path(cache_path)
    radius = float((inout.read_dataset_meta(data_dir) or {}).get("ball_radius_m", 0.12))
    config = dataclasses.asdict(config_for("improved", radius_m=radius))
    key = hashlib.sha256(json.dumps({"dataset": dataset_fingerprint(data_dir), "config": config, "seed": int(seed),
                                     "code": code_version(ORACLE_MODULES)}, sort_keys=True).encode()).hexdigest()
    if cache_path.is_file():
        try:
            cached = json.loads(cache_path.read_text())
            if cached.get("key") == key:
                log(f"oracle: ceiling rows reused from {cache_path}")
                return cached["balls"]
        except (OSError, json.JSONDecodeError, TypeError, KeyError):
            pass
    t0 = time.perf_counter()
    scenes = dataset_scenes(data_dir)
    log(f"oracle: the improved detector's verification from the true centres of {len(scenes)} scenes")
    tasks = [(json.dumps(config), str(s.path), scene_seed(seed, s.index)) for s in scenes if s.has_cloud]
    with _pool(workers) as pool:
        parts = list(pool.map(_oracle_scene, tasks, chunksize=4) if pool is not None else map(_oracle_scene, tasks))
    balls = [b for part in parts for b in part]
    inout.write_json(cache_path, _json_safe({"key": key, "dataset": str(data_dir), "seed": int(seed), "balls": balls,
                                          "seconds": round(time.perf_counter() - t0, 1)}))
    return balls


def _oracle_scene(task: tuple) -> list[dict]:
    """``oracle_balls``' rows of one scene (in a worker)."""
    from spherebench.datasets import inout
    from spherebench.eval.oracle import ceiling
    from spherebench.eval.sensor_grid import band_of, surface_distance_m
    from spherebench.method import DetectorConfig
    config_json, scene_dir, seed = task
    config = DetectorConfig(**json.loads(config_json))
    gt = inout.read_json(Path(scene_dir) / "gt.json")
    balls = [(k, b) for k, b in enumerate(gt.get("balls", [])) if b.get("center_m") is not None]
    if not balls:
        return []
    found = ceiling(inout.load_cloud(scene_dir), [b["center_m"] for _, b in balls], config, seed=seed)
    cell = (gt.get("meta") or {}).get("sensor_cell")
    return [{"scene_id": str(gt.get("scene_id", Path(scene_dir).name)), "ball": k, "cell": cell,
             "band": band_of(surface_distance_m(b["center_m"], b.get("radius_m", config.radius_m))),
             "within": bool(o["within"]), "separable": o.get("separable"), "score": o.get("score")}
            for (k, b), o in zip(balls, found)]


# --------------------------------------------------------------------------- Table 2 (paper preset)

#: The paper's Table 2 (metres): (scene, z threshold) -> (RMSE RANSAC, RMSE RANSAC centre with the
#: z-filtered points, RMSE barycentre with the z-filtered points).
PAPER_TABLE2 = {("E1", 3.0): (0.007343368, 0.007343368, 0.032156230),
                ("E1", 2.0): (0.007343368, 0.007343368, 0.020370757),
                ("E1", 1.5): (0.007343368, 0.007343368, 0.004612417),
                ("E2", 1.5): (0.366534813, 0.357131966, 0.041731429),
                ("E3", 1.5): (0.033177435, 0.033539393, 0.027763554)}
#: The paper's iteration counts: 1,000, and 10,000 for the cluttered scene E2.
PAPER_ITERATIONS = {"E2": 10_000}
TABLE2_THRESHOLDS = (3.0, 2.0, 1.5)


def table2_rows(paper_dir: str | Path, seed: int = 0, thresholds: Sequence[float] = TABLE2_THRESHOLDS,
                iterations: int | None = None) -> list[dict]:
    """Table 2 on the paper preset (E1, E2, E3): one row per scene and z threshold.

    The paper configuration (``PAPER``; 1,000 iterations, 10,000 for E2, or ``iterations`` for
    all) runs once per threshold with the scene's seed, so every threshold filters the same
    RANSAC draw (the draw does not depend on the threshold; checked). Each row holds
    ``eval.table2.table2_row`` (RMSEs in metres, true centre errors), the centre error of the
    least-squares refinement of the same kept points (R fixed), that of the whole improved
    detector, and the paper's values where it reports the row.
    """
    from spherebench.datasets import inout
    from spherebench.eval.table2 import table2_row
    from spherebench.method import IMPROVED, config_for, detect

    scenes = dataset_scenes(paper_dir)
    rows = []
    with _SingleThreadHere():
        for scene in scenes:
            cloud = inout.load_cloud(scene.path)
            s_seed = scene_seed(seed, scene.index)
            truth = scene.gt_centres_m[0] if scene.gt_centres_m else None
            its = iterations or PAPER_ITERATIONS.get(scene.scene_id, 1000)
            radius = IMPROVED.radius_m
            improved = detect(cloud, IMPROVED, seed=s_seed)
            err_improved = (min(float(np.linalg.norm(np.asarray(s.center_m) - truth)) for s in improved)
                            if improved and truth is not None else None)
            ransac_centre = None
            for z in thresholds:
                cfg = config_for("paper", zscore_threshold=float(z), iterations=int(its))
                t0 = time.perf_counter()
                found = detect(cloud, cfg, seed=s_seed)
                ms = 1000.0 * (time.perf_counter() - t0)
                refined = detect(cloud, dataclasses.replace(cfg, refine="least_squares"), seed=s_seed)
                row = {"scene": scene.scene_id, "z": float(z), "iterations": int(its), "seed": s_seed, "ms": ms}
                if found and refined:
                    tr = found[0].trace
                    if ransac_centre is not None and not np.allclose(tr.ransac_center_m, ransac_centre):
                        raise SphereBenchError("the paper pipeline's RANSAC draw changed with the z threshold")
                    ransac_centre = tr.ransac_center_m
                    pts = cloud.points.astype(np.float64)
                    row.update(table2_row(pts[tr.ransac_indices], pts[tr.kept_indices], tr.ransac_center_m, radius,
                                          barycentre_m=tr.barycentre_m, refined_centre_m=refined[0].center_m,
                                          true_centre_m=truth))
                row["error_improved_m"] = err_improved
                paper = PAPER_TABLE2.get((scene.scene_id, float(z)))
                row["paper"] = None if paper is None else dict(zip(
                    ("rmse_ransac", "rmse_ransac_filtered", "rmse_barycentre"), paper))
                rows.append(row)
    return rows
