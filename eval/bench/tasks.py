"""The benchmark's one task loop: methods over the scenes of a dataset, seeded, resumable.

A task is one scene through one method configuration (``SceneTask``); ``run_tasks`` runs tasks on
an executor (``spherebench.parallel.executor``: this process, a pool of local worker processes,
or Ray) and returns each task's record in task order. ``run_methods`` builds the tasks of the
benchmark's methods (``eval.bench.registry``) on a dataset and writes one prediction set per output
(``eval.bench.cache``), reusing the finished ones; ``bench``, ``sweep`` and ``robustness`` run their
tasks through the same loop, Table 2 and the oracle's ceiling (``eval.bench.studies``) theirs on the same
executor with the same seeds.

Seeding: scene k of a dataset (scene folders sorted by id) is run with ``detection_seed(seed, k)``
(``eval.bench.seeds``). Every task's output depends on its arguments only, so the files are identical
for any number of workers and either engine. Time per frame is measured around the detection call
alone (no file reading), one thread per worker.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterator, Sequence

from spherebench.datasets import inout
from spherebench.datasets.fingerprint import dataset_fingerprint
from spherebench.errors import SphereBenchError
from spherebench.eval.bench.cache import is_finished, prediction_key, write_prediction_set
from spherebench.eval.bench.registry import NEEDS, MethodSpec, ranked, warm_adapter
from spherebench.eval.bench.seeds import detection_seed
from spherebench.parallel import executor
from spherebench.progress import bar as progress_bar
from spherebench.provenance import code_version


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

    @property
    def has_frame(self) -> bool:
        """A cloud can be loaded (``inout.load_cloud``): cloud.ply, or depth.png with intrinsics.json (the
        `train` preset ships no clouds)."""
        return self.has_cloud or ((self.path / "depth.png").is_file() and self.resolution is not None)


def dataset_scenes(data_dir: str | Path, limit: int | None = None) -> list[SceneInfo]:
    """Every scene of a dataset (the first ``limit``), in scene-id order, with its image id and 3D
    ground truth."""
    root = Path(data_dir)
    coco = inout.read_coco_gt(root)
    image_ids = {img.get("scene_id"): img["id"] for img in coco["images"]}
    out = []
    for k, scene in enumerate(inout.list_scenes(root)[:limit]):
        gt = inout.read_scene_gt(scene)
        res = None
        if (scene / "intrinsics.json").is_file():
            intr = inout.read_intrinsics(scene / "intrinsics.json")
            res = f"{intr.width}x{intr.height}"
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


@dataclass(frozen=True)
class SceneTask:
    """One scene through one method configuration.

    config_json: the method's configuration (``MethodSpec.config_json``); resource: its model file.
    warm_scene: a scene the worker runs once, untimed, before its first task of this configuration.
    seed: the detector's seed (``detection_seed(run seed, index)``)."""

    config_json: str
    resource: str | None
    warm_scene: str | None
    scene_dir: str
    index: int
    seed: int


def run_task(task: SceneTask) -> dict:
    """One scene through one method (in a worker): {index, seed, ms (wall), cpu_ms (this thread's CPU
    time), detections, error}.

    A scene the method refuses (SphereBenchError: say, a cloud with too few valid points) gives
    no detection, and the reason is kept in the record's "error"."""
    adapter = warm_adapter(task.config_json, task.resource, task.warm_scene)
    inputs = adapter.load(Path(task.scene_dir))
    error = None
    t0, c0 = time.perf_counter(), time.thread_time()
    try:
        dets = adapter.detect(inputs, task.seed)
    except SphereBenchError as exc:
        dets, error = [], str(exc)
    ms, cpu_ms = 1000.0 * (time.perf_counter() - t0), 1000.0 * (time.thread_time() - c0)
    return {"index": task.index, "seed": task.seed, "ms": ms, "cpu_ms": cpu_ms, "detections": ranked(dets),
            "error": error}


def tasks_for(spec: MethodSpec, scenes: Sequence[SceneInfo], seed: int) -> list[SceneTask]:
    """The tasks of one method on some scenes of a run with seed ``seed``; the first scene warms."""
    warm = str(scenes[0].path) if scenes else None
    return [SceneTask(spec.config_json(), spec.resource, warm, str(s.path), s.index, detection_seed(seed, s.index))
            for s in scenes]


def run_tasks(ex, tasks: Sequence[SceneTask], progress: Callable[[], None] | None = None) -> Iterator[dict]:
    """Each task's record (``run_task``), in task order, run on the executor ``ex``."""
    for record in ex.map(run_task, tasks):
        if progress is not None:
            progress()
        yield record


def run_methods(data_dir: str | Path, out_dir: str | Path, specs: Sequence[MethodSpec], seed: int = 0,
                workers: int = 2, progress: bool = True, force: bool = False,
                scene_filter: Callable[[SceneInfo], bool] | None = None,
                fingerprint: str | None = None, log: Callable[[str], None] = print,
                engine: str = "local", address: str | None = None) -> dict[str, Path]:
    """Run ``specs`` on every scene of ``data_dir``; write one prediction set per output into ``out_dir``.

    seed: the run seed (scene k gets ``detection_seed(seed, k)``). workers: processes (<= 1: in this
    process; with Ray, the CPUs of a local cluster). engine, address: the executor
    (``parallel.executor``). force: recompute even finished sets. scene_filter: run only the scenes
    it accepts (others are absent from the files; the scoring restricts itself to the scenes run).
    Returns {output name: predictions path}. Finished sets with the same inputs are reused.
    """
    data_dir, out_dir = Path(data_dir), Path(out_dir)
    scenes = dataset_scenes(data_dir)
    fingerprint = fingerprint or dataset_fingerprint(data_dir)
    coco = inout.read_coco_gt(data_dir)
    category_id = int(coco["categories"][0]["id"]) if coco.get("categories") else 1
    meta_ds = inout.read_dataset_meta(data_dir) if (data_dir / "dataset.json").is_file() else {}
    dataset = {"path": str(data_dir), "fingerprint": fingerprint, "preset": meta_ds.get("preset"),
               "name": meta_ds.get("name"), "n_scenes": len(scenes)}
    paths: dict[str, Path] = {}
    pending: list[tuple[MethodSpec, list[SceneInfo], dict[str, str], str]] = []
    for spec in specs:
        chosen = [s for s in scenes if (s.has_cloud if spec.kind == "3d" else s.has_image)]
        if scene_filter is not None:
            chosen = [s for s in chosen if scene_filter(s)]
        if not chosen:
            log(f"{spec.name}: no scene of {data_dir} has its input ({NEEDS[spec.kind]})")
            continue
        version = code_version(spec.modules)
        keys = {o: prediction_key(spec, o, fingerprint, seed, version, [s.scene_id for s in chosen])
                for o in spec.outputs}
        for o in spec.outputs:
            paths[o] = out_dir / f"{o}.json"
        if not force and all(is_finished(paths[o], keys[o]) for o in spec.outputs):
            log(f"{spec.name}: predictions on {data_dir.name} up to date, reused")
            continue
        pending.append((spec, chosen, keys, version))
    if not pending:
        return paths
    tasks = [t for spec, chosen, _, _ in pending for t in tasks_for(spec, chosen, seed)]
    bar = progress_bar(total=len(tasks), desc=f"run {data_dir.name}", unit="frame", enabled=progress)
    try:
        with executor(workers, engine, address) as ex:
            records = run_tasks(ex, tasks, progress=bar.update)
            for spec, chosen, keys, version in pending:
                bar.set_postfix_str(spec.name)
                mine = [next(records) for _ in chosen]
                for output in spec.outputs:
                    write_prediction_set(out_dir / f"{output}.json", spec, output, chosen, mine, category_id,
                                         keys[output], version, seed, dataset, ex.workers, engine)
    finally:
        bar.close()
    return paths
