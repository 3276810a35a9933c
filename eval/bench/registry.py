"""The benchmark's methods: a registry of adapters, each joined with one ``register_method``.

A *method* turns a scene folder into detections. One detection run of a 3D method gives two
prediction sets, one per 2D rule of ``spherebench.circles``:

    <name>               the exact silhouette reduced to a circle (the ground truth's rule)
    <name>+paper-circle  the paper's rule (project the centre and a point R to its left)

An adapter (``MethodAdapter``) is a class with ``kind`` (what it needs: "3d" reads the cloud,
"2d" the image; ``NEEDS``), built from its configuration and model file as
``Adapter(config, resource)``, with ``load(scene_dir)`` (its input) and ``detect(inputs, seed)`` ->
[{score, circle, and for 3D center_m, radius_m, circle_paper}]. ``register_method`` enters a
method (name, adapter, how its ``MethodSpec`` is built, its role in the reading) in ``METHODS``;
the order of registration is the order of the tables, and ``config["engine"]`` names the adapter
that a worker builds (``ADAPTERS``). A new baseline is one decorated adapter class:

    @register_method("mine", description="`mine` (what it is)")
    class MineAdapter:
        kind = "2d"
        def __init__(self, config, resource=None): ...
        def load(self, scene_dir): return inout.read_image(scene_dir / "image.png")
        def detect(self, image, seed): return [{"score": 0.9, "circle": (cx, cy, r)}]

The registered methods, in order:
- ``improved``, ``paper``, ``paper-lstsq``: ``spherebench.method.detect`` with that preset;
- ``pyransac3d``: the generic peer, pyransac3d's free-radius sphere RANSAC (``Sphere().fit``) on
  a seeded subsample of each cloud; its circle is the projection of its centre with its own
  radius, its score its inlier fraction;
- ``hough``: OpenCV's Hough circle transform (``baselines.hough``) on image.png, with a
  configuration tuned on the training split (``baselines.hough_tuning``);
- ``circlenet``: the CircleNet-style ONNX model (``baselines.circlenet.infer``) on image.png
  scaled to its training focal length by the scene's intrinsics, when a model file exists;
  ``circlenet-analytic`` the same model trained on the analytic sensor model's ``train`` alone (the
  earlier weights, for comparison), ``circlenet-full`` (ResNet-18 at its own widths) and
  ``circlenet-hg`` (the stacked hourglass) the same with the GPU-trained models (``CIRCLENET_MODELS``).

Each worker process builds an adapter once per configuration and runs it once untimed on a first
scene (``warm_adapter``), so that numba compilation and model loading stay out of every timing; a
CircleNet adapter holds one single-threaded ONNX Runtime session.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Protocol, Sequence

from spherebench.baselines import circlenet as circlenet_package
from spherebench.baselines import pyransac3d_peer
from spherebench.baselines.hough import HoughConfig, detect_circles
from spherebench.datasets import inout
from spherebench.errors import SphereBenchError
from spherebench.eval.bench import oracle
from spherebench.method import DetectorConfig, config_for, detect
from spherebench.method.detector import sphere_circles
from spherebench.method.verdict import MODEL_PATH as VERDICT_MODEL
from spherebench.provenance import REPO_ROOT, dist_version, file_sha256

#: Suffix of the prediction set that uses the paper's projection rule.
PAPER_CIRCLE = "+paper-circle"
#: The one scoring protocol of every method: its ranked output down to this score (CenterNet keeps
#: its top 100, most of which score ~0) ...
SCORE_FLOOR = 0.01
#: ... and at most this many detections per frame (COCO's maxDets, CenterNet's K).
MAX_DETECTIONS = 100
#: pyransac3d: the peer's own cost (2-3 s per 1,000 iterations on 100k points) does not fit the
#: benchmark's budget; it runs on this many points, drawn at random (seeded) from each cloud.
PYRANSAC3D_POINTS = 2_000
#: pyransac3d: RANSAC iterations and inlier threshold (m), its own defaults being 1,000 and 0.2 m.
PYRANSAC3D_ITERATIONS = 1000
PYRANSAC3D_THRESH_M = 0.01
#: The shipped CircleNet models' folder: the circlenet package's own, in a clone and in an installed wheel.
CIRCLENET_DIR = Path(circlenet_package.__file__).resolve().parent

#: The CircleNet models: method name -> (ONNX file under baselines/circlenet/, how to make it).
#: ``circlenet``: the half-width ResNet-18 trained on the CPU; the others need a CUDA machine.
CIRCLENET_MODELS = {
    "circlenet": ("model.onnx", "make train"),
    # the earlier shipped circlenet, trained on `train` alone, kept beside the one trained on both models
    "circlenet-analytic": ("analytic/model.onnx", "make train-analytic"),
    "circlenet-full": ("full/model.onnx", "make train-full, on a CUDA machine"),
    "circlenet-hg": ("hg/model.onnx", "make train-hg, on a CUDA machine"),
}

#: Shipped models trained on an earlier `train` preset, by the sha256 of their ONNX file: their rows
#: say so (the full-size model needs a CUDA machine to retrain, and none has been at hand since
#: `train` began drawing each scene's sensor).
EARLIER_TRAIN = {
    "3b72295ef7ff02b8fd1f939613db8828eb10db18006e57b50997ff17d2236862":
        "trained on the earlier train preset (the nominal sensor in every scene), never on train-stereo; "
        "`make train-full` on a CUDA machine retrains it on train + train-stereo",
}

DETECTOR_PRESETS = ("improved", "paper", "paper-lstsq")
#: What a method of each kind reads from a scene folder.
NEEDS = {"3d": "cloud.ply", "2d": "image.png"}
#: The roles the reading (``eval.bench.prose``) looks methods up by, rather than by name.
ROLE_DETECTOR = "the 3D detector"        # the improved detector: its figures are read first
ROLE_PAPER = "the paper's method"        # the paper's pipeline, read against the paper's numbers
ROLE_LEARNED_2D = "a learned 2D baseline"  # read beside the paper's CircleNet-HG
ROLE_CEILING = "the ceiling"             # an oracle from the truth: beside the detector, never a winner

#: Modules whose source is every method's code version (scene reading, circles, the adapters).
_CORE_MODULES = ("spherebench.camera", "spherebench.cloud", "spherebench.circles", "spherebench.datasets.inout",
                 "spherebench.eval.bench.registry")


@dataclass(frozen=True)
class MethodSpec:
    """A method of the benchmark.

    name: its name; its prediction sets are ``outputs``.
    kind: "3d" (reads cloud.ply + intrinsics) or "2d" (reads image.png).
    config: JSON-able settings that fully define it (part of the resume key); config["engine"]
        names its adapter.
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


# --------------------------------------------------------------------------- the registry

class MethodAdapter(Protocol):
    """What the task loop asks of a method, in a worker: built once per configuration as
    ``Adapter(config, resource)`` (resource: its model file, or None)."""

    kind: str  # "3d": reads the cloud; "2d": reads the image (NEEDS)

    def load(self, scene_dir: Path):
        """The method's input from a scene folder (read outside the timing)."""

    def detect(self, inputs, seed: int) -> list[dict]:
        """Detections on one input: [{score, circle, and for 3D center_m, radius_m, circle_paper}]."""


@dataclass(frozen=True)
class BuildOptions:
    """What a run gives every method's spec: the dataset's ball radius (m), the tuned Hough
    configuration (None: untuned), the ONNX file of ``circlenet`` (None: the shipped one)."""

    radius_m: float = 0.12
    hough_config: HoughConfig | None = None
    circlenet_model: str | Path | None = None


@dataclass(frozen=True)
class Method:
    """A registered method: its adapter, how its ``MethodSpec`` is built (``spec(name, options)``,
    which raises SphereBenchError when the method cannot run, e.g. its model is missing), its role
    in the reading (a ROLE_* or "") and the words the reading names it by."""

    name: str
    adapter: type
    spec: Callable[[str, BuildOptions], MethodSpec]
    role: str = ""
    description: str = ""

    @property
    def kind(self) -> str:
        return self.adapter.kind

    @property
    def needs(self) -> str:
        """The file it reads from each scene."""
        return NEEDS[self.kind]


#: name -> Method, in registration order (the order of the tables).
METHODS: dict[str, Method] = {}
#: config["engine"] -> adapter class.
ADAPTERS: dict[str, type] = {}


def default_spec(engine: str, adapter: type) -> Callable[[str, BuildOptions], MethodSpec]:
    """The spec of a method with no settings: its engine, and its adapter's module as its code."""
    def spec(name: str, options: BuildOptions) -> MethodSpec:
        return MethodSpec(name=name, kind=adapter.kind, config={"engine": engine},
                          modules=_CORE_MODULES + (adapter.__module__,))
    return spec


def register_method(name: str, adapter: type | None = None, *, spec: Callable[[str, BuildOptions], MethodSpec] | None = None,
                    engine: str | None = None, role: str = "", description: str = ""):
    """Enter method ``name`` in METHODS and its adapter in ADAPTERS under ``engine`` (default: the
    name); spec: how its MethodSpec is built (default: ``default_spec``). Called with an adapter,
    or used as a decorator on the adapter class (which it returns)."""
    def enter(cls: type) -> type:
        key = engine or name
        if name in METHODS or ADAPTERS.get(key, cls) is not cls:
            raise ValueError(f"method {name} (engine {key}) is registered already")
        ADAPTERS[key] = cls
        METHODS[name] = Method(name, cls, spec or default_spec(key, cls), role, description)
        return cls
    return enter if adapter is None else enter(adapter)


def method_names() -> tuple[str, ...]:
    """Every registered method's name, in the tables' order."""
    return tuple(METHODS)


def methods_with_role(role: str) -> list[Method]:
    """The registered methods of a role, in order."""
    return [m for m in METHODS.values() if m.role == role]


def method_with_role(role: str) -> str | None:
    """The name of the first registered method of a role, or None."""
    found = methods_with_role(role)
    return found[0].name if found else None


# --------------------------------------------------------------------------- specs

def detector_spec(name: str, **overrides) -> MethodSpec:
    """``improved`` / ``paper`` / ``paper-lstsq``: the 3D detector with that preset (fields overridden,
    e.g. radius_m for a dataset of another ball)."""
    cfg = config_for(name, **overrides)
    # the fitted verdict's model is data the code loads: a refitted one invalidates the cached predictions
    verdict = file_sha256(VERDICT_MODEL) if cfg.pipeline == "improved" else ""
    return MethodSpec(name=name, kind="3d", config={"engine": "detector", "preset": name, **cfg.flat()},
                      modules=_CORE_MODULES + ("spherebench.method",), extra_fingerprint=verdict)


def pyransac3d_spec(points: int = PYRANSAC3D_POINTS, iterations: int = PYRANSAC3D_ITERATIONS,
                    thresh_m: float = PYRANSAC3D_THRESH_M, radius_m: float = 0.12) -> MethodSpec:
    """pyransac3d's sphere fit on a random subsample of ``points`` points of each cloud.

    radius_m (the dataset's R) is not given to it (it fits the radius freely); it is recorded so
    that the radius error is read against it."""
    return MethodSpec(name="pyransac3d", kind="3d",
                      config={"engine": "pyransac3d", "points": int(points), "iterations": int(iterations),
                              "thresh_m": float(thresh_m), "radius_m": float(radius_m),
                              "pyransac3d": dist_version("pyransac3d")},
                      modules=_CORE_MODULES + ("spherebench.baselines.pyransac3d_peer",),
                      note=f"pyransac3d Sphere().fit on {points:,} points drawn at random from each cloud, "
                           f"{iterations:,} iterations, threshold {100 * thresh_m:g} cm (at full resolution it "
                           "takes 2-3 s per frame, beyond the budget)")


def hough_spec(config: HoughConfig) -> MethodSpec:
    """The Hough baseline with a ``HoughConfig`` (tuned on the training split)."""
    return MethodSpec(name="hough", kind="2d", config={"engine": "hough", **dataclasses.asdict(config)},
                      modules=_CORE_MODULES + ("spherebench.baselines.hough",))


def card_presets(card: dict) -> str:
    """The presets a CircleNet model card says it was trained on: "`train` + `train-stereo`"."""
    data = card.get("data", {})
    return " + ".join(f"`{d.get('preset', '?')}`" for d in data["datasets"]) if data.get("datasets") else \
        f"`{data.get('preset', 'train')}`"


def card_budget(card: dict) -> str:
    """One line of a CircleNet model card: its training budget and validation score."""
    val = card.get("val_onnx") or card.get("val_torch") or {}
    data = card.get("data", {})
    half = "; weights stored as float16" if (card.get("onnx") or {}).get("weights") == "float16" else ""
    presets = card_presets(card)
    return (f"trained from scratch on {data.get('train_images', '?')} {presets} images, "
            f"{card.get('epochs', '?')} epochs, {card.get('train_seconds', 0) / 60:.0f} min on {card.get('device', '?')}; "
            f"validation mAP.50 {val.get('mAP50', float('nan')):.3f}{half}")


@functools.lru_cache(maxsize=16)
def training_presets(name: str, model_sha256: str) -> str | None:
    """The presets a shipped CircleNet model was trained on, from its model card ("`train` +
    `train-stereo`"), or None when ``name`` is no shipped model or its file is not that model."""
    if name not in CIRCLENET_MODELS:
        return None
    path = circlenet_model_path(name)
    card_path = path.with_name("model_card.json")
    if not (path.is_file() and card_path.is_file()) or file_sha256(path) != model_sha256:
        return None
    card = inout.read_json(card_path)
    return card_presets(card) if isinstance(card, dict) else None


def circlenet_model_path(name: str = "circlenet") -> Path:
    """The shipped ONNX file of a CircleNet method of ``CIRCLENET_MODELS`` (it may not exist)."""
    return CIRCLENET_DIR / CIRCLENET_MODELS[name][0]


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
        card = inout.read_json(card_path)
        budget = "; " + card_budget(card if isinstance(card, dict) else {})
    return MethodSpec(name=name, kind="2d",
                      config={"engine": "circlenet", "model": path.name, "min_score": SCORE_FLOOR,
                              "top_k": MAX_DETECTIONS, "scale": "focal_px",
                              "onnxruntime": dist_version("onnxruntime")},
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
    CircleNetAdapter({}, path)


def build_methods(names: Sequence[str] | None = None, hough_config: HoughConfig | None = None,
                  circlenet_model: str | Path | None = None,
                  table_note: Callable[[str, str], None] | None = None, radius_m: float = 0.12) -> list[MethodSpec]:
    """The benchmark's methods (every registered one, or ``names``), skipping the unavailable ones.

    radius_m: the dataset's ball radius (the 3D methods' R).
    hough_config: the tuned ``HoughConfig`` (None: OpenCV-tutorial defaults, said in the note).
    circlenet_model: the ONNX file of ``circlenet`` (None: the shipped one); the other CircleNet
    methods always use their shipped files (``CIRCLENET_MODELS``).
    table_note(name, reason) is called for every method skipped, with the reason.
    Unknown names raise SphereBenchError.
    """
    wanted = list(METHODS if names is None else names)
    unknown = [n for n in wanted if n not in METHODS]
    if unknown:
        raise SphereBenchError(f"unknown method(s) {', '.join(unknown)}: choose from {', '.join(METHODS)}")
    options = BuildOptions(radius_m=float(radius_m), hough_config=hough_config, circlenet_model=circlenet_model)
    specs = []
    for name in wanted:
        try:
            specs.append(METHODS[name].spec(name, options))
        except SphereBenchError as exc:
            if table_note is None:
                raise
            table_note(name, str(exc))
    return specs


# --------------------------------------------------------------------------- adapters (in workers), registered

def ranked(detections: list[dict]) -> list[dict]:
    """A method's detections as the benchmark scores them: best first, down to SCORE_FLOOR, at most
    MAX_DETECTIONS (the same protocol for every method, whatever its own operating point)."""
    kept = sorted((d for d in detections if d["score"] >= SCORE_FLOOR), key=lambda d: -d["score"])
    return kept[:MAX_DETECTIONS]


def operating_score(config: dict) -> float:
    """The least score of a method's detections at its user's operating point (the 3D figures: found,
    false detections): the improved detector's ``verification.min_score``; every other method's
    detections count as they come (0)."""
    if config.get("engine") == "detector" and config.get("pipeline") == "improved":
        return float(config.get("min_score", 0.0))
    return 0.0


def at_operating_point(detections: list[dict], config: dict) -> list[dict]:
    """The detections a method's user gets at its operating point (``operating_score``)."""
    least = operating_score(config)
    return [d for d in detections if d["score"] >= least]


class DetectorAdapter:
    """The 3D detector (``spherebench.method``): its ranked output down to SCORE_FLOOR, at most
    MAX_DETECTIONS (the configuration's ``min_score`` is its operating point, ``operating_score``)."""

    kind = "3d"

    def __init__(self, config: dict, resource: str | None = None):
        self.config = DetectorConfig.from_flat(config)
        self.estimates_radius = self.config.pipeline == "improved"

    def load(self, scene_dir: Path):
        return inout.load_cloud(scene_dir)

    def detect(self, cloud, seed: int) -> list[dict]:
        return [{"score": float(s.score), "center_m": [float(v) for v in s.centre_m],
                 "radius_m": float(s.free_radius_m) if self.estimates_radius else None,
                 "circle": s.circle_exact, "circle_paper": s.circle_paper}
                for s in detect(cloud, self.config, seed=seed, min_score=SCORE_FLOOR, max_spheres=MAX_DETECTIONS)]


def _detector(name: str, options: BuildOptions) -> MethodSpec:
    return detector_spec(name, radius_m=options.radius_m)


register_method("improved", DetectorAdapter, spec=_detector, engine="detector", role=ROLE_DETECTOR)
register_method("paper", DetectorAdapter, spec=_detector, engine="detector", role=ROLE_PAPER)
register_method("paper-lstsq", DetectorAdapter, spec=_detector, engine="detector")


@register_method("pyransac3d", spec=lambda name, options: pyransac3d_spec(radius_m=options.radius_m))
class PyRansac3dAdapter:
    """The generic peer: pyransac3d's free-radius sphere RANSAC (``Sphere().fit``), used as a user
    would: on the cloud's points (a seeded random subsample of ``points``), inlier threshold
    ``thresh_m``, ``iterations`` iterations. Its sphere is reported with its own radius; its score
    is its inlier fraction; its circles project its own centre and radius by both 2D rules."""

    kind = "3d"

    def __init__(self, config: dict, resource: str | None = None):
        self.config = config

    def load(self, scene_dir: Path):
        return inout.load_cloud(scene_dir)

    def detect(self, cloud, seed: int) -> list[dict]:
        if len(cloud.points) < 4:
            return []
        found = pyransac3d_peer.detect(cloud, points=self.config["points"], iterations=self.config["iterations"],
                                       thresh_m=self.config["thresh_m"], seed=seed)
        return [{"score": d["score"], "center_m": [float(v) for v in d["center_m"]], "radius_m": float(d["radius_m"]),
                 "circle": d["circle_exact"], "circle_paper": d["circle_paper"]} for d in found]


def _own_pixel_fit(name: str, options: BuildOptions) -> MethodSpec:
    return MethodSpec(name=name, kind="3d",
                      config={"engine": "own-pixel-fit", "radius_m": float(options.radius_m),
                              "min_pixels": oracle.OWN_PIXELS_MIN, "rounds": oracle.OWN_FIT_ROUNDS,
                              "trim_sigmas": oracle.OWN_FIT_TRIM_SIGMAS},
                      modules=_CORE_MODULES + ("spherebench.eval.bench.oracle", "spherebench.method.detector"),
                      note="the ceiling, not a detector: a sphere of radius R fitted from each ball's true centre on "
                           "its own pixels (its mask, where the frame has depth)")


@register_method("own-pixel-fit", spec=_own_pixel_fit, role=ROLE_CEILING,
                 description="`own-pixel-fit` (the ceiling: each ball's R-fixed fit from the truth on its own pixels)")
class OwnPixelFitAdapter:
    """The ceiling of the data (``oracle.own_pixel_fit``): per true ball with a centre and a mask, the
    sphere fitted from its true centre on its mask's pixels with depth, score 1, its circles by the
    detector's rules (``method.detector.sphere_circles``: the visible pixels' circle for a ball seen
    over less than 0.9 of its silhouette, as the ground truth draws it)."""

    kind = "3d"

    def __init__(self, config: dict, resource: str | None = None):
        self.radius_m = float(config["radius_m"])

    def load(self, scene_dir: Path):
        cloud = inout.load_cloud(scene_dir)
        gt = inout.read_scene_gt(scene_dir)
        shape = cloud.intrinsics.shape if cloud.intrinsics is not None else None
        balls = [(b, inout.read_mask_png(scene_dir / b["mask"], shape)) for b in gt.get("balls", [])
                 if b.get("center_m") is not None and b.get("mask") and (scene_dir / b["mask"]).is_file()]
        return cloud, balls

    def detect(self, inputs, seed: int) -> list[dict]:
        cloud, balls = inputs
        if cloud.rows is None:
            return []
        out = []
        for ball, mask in balls:
            own = mask[cloud.rows, cloud.cols] > 0
            c = oracle.own_pixel_fit(cloud.points[own], ball["center_m"], self.radius_m)
            if c is None:
                continue
            seen = ball.get("visible_fraction")  # null on a recording whose silhouette nobody drew
            paper, exact = sphere_circles(cloud, c, self.radius_m, {"visible_fraction": 1.0 if seen is None else seen})
            out.append({"score": 1.0, "center_m": [float(v) for v in c], "radius_m": None, "circle": exact,
                        "circle_paper": paper})
        return out


def _hough(name: str, options: BuildOptions) -> MethodSpec:
    spec = hough_spec(options.hough_config or HoughConfig())
    if options.hough_config is None:
        spec = dataclasses.replace(spec, note="untuned defaults (no tuned configuration given)")
    return spec


@register_method("hough", spec=_hough)
class HoughAdapter:
    """OpenCV's Hough circle transform on a scene's image.png."""

    kind = "2d"

    def __init__(self, config: dict, resource: str | None = None):
        fields = {f.name for f in dataclasses.fields(HoughConfig)}
        self.config = HoughConfig(**{k: v for k, v in config.items() if k in fields})

    def load(self, scene_dir: Path):
        return inout.read_image(scene_dir / "image.png")

    def detect(self, image, seed: int) -> list[dict]:
        return [{"score": s, "circle": (cx, cy, r)} for cx, cy, r, s in detect_circles(image, self.config)]


class CircleNetAdapter:
    """CircleNet on a scene's image.png, scaled by the detector to its training focal length from the
    scene's own intrinsics (``scene_focal_px``; a scene without intrinsics.json: to the model's
    width, exact for every D435 mode). One ONNX Runtime session of one thread."""

    kind = "2d"

    def __init__(self, config: dict, resource: str | None = None):
        # here, not at the top: infer loads onnx and torch (about 2 s), needed only where CircleNet runs
        from spherebench.baselines.circlenet import infer
        self.infer = infer
        self.config = config
        self.detector = infer.CircleNetDetector(Path(resource), threads=1)

    def load(self, scene_dir: Path):
        return self.infer.load_image(scene_dir / "image.png"), self.infer.scene_focal_px(scene_dir)  # RGB, as trained

    def detect(self, inputs, seed: int) -> list[dict]:
        image, focal_px = inputs
        if self.config.get("scale") != "focal_px":  # a configuration of before the rule: the model's width
            focal_px = None
        circles = self.detector.detect(image, min_score=self.config["min_score"], top_k=self.config["top_k"],
                                       focal_px=focal_px)
        return [{"score": float(sc), "circle": (float(cx), float(cy), float(r))} for cx, cy, r, sc in circles]


def _circlenet(name: str, options: BuildOptions) -> MethodSpec:
    given = options.circlenet_model if name == "circlenet" else None
    return circlenet_spec(given if given is not None else circlenet_model_path(name), name=name)


#: How the reading names each CircleNet method.
CIRCLENET_DESCRIPTIONS = {"circlenet": "`circlenet` (half-width ResNet-18, CPU-trained)",
                          "circlenet-analytic": "`circlenet-analytic` (the same, trained on the analytic `train` alone)",
                          "circlenet-full": "`circlenet-full` (ResNet-18 at its own widths, GPU-trained)",
                          "circlenet-hg": "`circlenet-hg` (2-stack hourglass, GPU-trained)"}
for _name in CIRCLENET_MODELS:
    register_method(_name, CircleNetAdapter, spec=_circlenet, engine="circlenet", role=ROLE_LEARNED_2D,
                    description=CIRCLENET_DESCRIPTIONS[_name])


_BUILT: dict[tuple[str, str], object] = {}


def warm_adapter(config_json: str, resource: str | None, warm_scene: str | None = None):
    """The adapter of a configuration in this process, built once; a new one first runs ``warm_scene``
    untimed, so that compilation and model loading stay out of every timing."""
    key = (config_json, resource or "")
    if key not in _BUILT:
        config = json.loads(config_json)
        cls = ADAPTERS.get(config.get("engine"))  # a MethodAdapter
        if cls is None:
            raise SphereBenchError(f"unknown engine {config.get('engine')}")
        adapter = cls(config, resource)
        if warm_scene is not None:
            with contextlib.suppress(SphereBenchError):  # the scene itself reports its own error later
                adapter.detect(adapter.load(Path(warm_scene)), 0)
        _BUILT[key] = adapter
    return _BUILT[key]
