"""Training the CircleNet-style baseline from scratch on a training dataset (never the benchmark).

``train(train_dir, out_dir, config, seed)`` writes to out_dir:
    checkpoint.pt        the run's state, rewritten atomically after every epoch and every
                         ``checkpoint_minutes``; ``resume=True`` continues from it, bit for bit
                         the same batches (the data order and augmentation derive from the seed)
    history.json         per-iteration loss, per-epoch validation mAP / mAP.50 / mAP.75 (at the end;
                         a stopped run leaves the checkpoint alone, which holds it)
    training_curve.png   both, as a figure
    model.onnx           the final model (not a best-of-epochs pick: no selection on validation)
    model_card.json/.md  data, seed, epochs, time, device, validation mAP of the ONNX model, command

The validation split is a seeded draw of the training dataset's scenes (``data.split_scenes``);
its mAP is the COCO protocol with circle IoU (``spherebench.eval.metrics.coco_eval``).
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import math
import os
import platform
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch

from spherebench.baselines.circlenet.data import AugmentConfig, CircleDataset, read_datasets, split_scenes
from spherebench.baselines.circlenet.imaging import scale_circles
from spherebench.baselines.circlenet.infer import CircleNetDetector
from spherebench.baselines.circlenet.loss import circlenet_loss
from spherebench.baselines.circlenet.model import CircleNet, CircleNetConfig, count_parameters, decode
from spherebench.baselines.circlenet.onnx_export import export_onnx
from spherebench.datasets import inout, outputs
from spherebench.errors import SphereBenchError
from spherebench.eval.metrics.coco_eval import coco_from_circles, evaluate_circles, results_from_circles
from spherebench.parallel import usable_cpus
from spherebench.plotting import pyplot
from spherebench.progress import bar as progress_bar, write as progress_write

#: The owner-marker kind of a training run's folder (``outputs.claim_output_dir``).
TRAINING_RUN_KIND = "training run"


@dataclass
class TrainConfig:
    """Every training default in one place (the model's are in ``CircleNetConfig``)."""

    model: CircleNetConfig = field(default_factory=CircleNetConfig)
    augment: AugmentConfig = field(default_factory=AugmentConfig)
    epochs: int = 20
    batch_size: int = 16
    lr: float = 1e-3  # AdamW; linear warm-up, then cosine decay to lr * final_lr_fraction
    final_lr_fraction: float = 0.01
    warmup_iters: int = 200
    weight_decay: float = 1e-4
    grad_clip: float = 10.0  # max gradient norm: the focal loss spikes early on from scratch
    offset_weight: float = 1.0  # CenterNet's weights
    radius_weight: float = 0.1
    val_fraction: float = 0.1  # of the training dataset's scenes
    max_objects: int = 32
    # -- how, not what: these do not change the result's definition and may differ on resume --
    device: str = "auto"  # "auto": CUDA if present, else CPU
    mixed_precision: str = "auto"  # "auto": bfloat16 where the hardware has it (AMX/AVX512-BF16, CUDA); "off"
    workers: int = 0  # DataLoader workers (0: in the main process; the model dominates the time)
    threads: int | None = None  # torch CPU threads (None: torch's default, one per core); 1 on a busy shared machine
    checkpoint_minutes: float = 5.0
    onnx_weights: str = "float32"  # how model.onnx stores its weights: "float32", or "float16" (half the file)

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "TrainConfig":
        d = dict(d)
        model = CircleNetConfig.from_dict(d.pop("model", {}))
        aug = AugmentConfig(**{k: tuple(v) if isinstance(v, list) else v for k, v in d.pop("augment", {}).items()})
        return cls(model=model, augment=aug, **{k: v for k, v in d.items() if k in cls.__dataclass_fields__})


#: Fields that may differ between a run and its resume.
_HOW_FIELDS = ("device", "mixed_precision", "workers", "threads", "checkpoint_minutes", "onnx_weights")


# ---------------------------------------------------------------- validation mAP

def coco_circle_map(gt: dict[int, np.ndarray], detections: dict[int, np.ndarray]) -> dict[str, float]:
    """COCO AP with circle IoU (CircleNet's protocol, ``spherebench.eval.metrics.coco_eval``): mAP over
    IoU 0.50:0.05:0.95, mAP.50, mAP.75 (101 recall points, maxDets 1000, area = pi r^2).

    gt: image id -> circles (N, 3) (cx, cy, r) px, every image of the set (empty for negatives).
    detections: image id -> (K, 4) (cx, cy, r, score); missing ids have none. NaN when there is
    no ground-truth circle at all.
    """

    ids = sorted(gt)
    none = np.zeros((0, 4))
    m = evaluate_circles(coco_from_circles([gt[i] for i in ids]),
                         results_from_circles([detections.get(i, none) for i in ids]))
    return {k: float(m[k]) for k in ("mAP", "mAP50", "mAP75")}


@torch.no_grad()
def predict(model: CircleNet, dataset: CircleDataset, batch_size: int = 16, device="cpu",
            top_k: int | None = None, amp: torch.dtype | None = None, workers: int = 0) -> dict[int, np.ndarray]:
    """Detections of the model on an un-augmented dataset: image id -> (K, 4) (cx, cy, r, score) px.

    amp: autocast dtype (the training's, for speed; the model card's figure is the float32 ONNX model's).
    workers: DataLoader processes reading the images (the result does not depend on them).
    """
    model.eval()
    device = torch.device(device)
    loader = torch.utils.data.DataLoader(dataset, batch_size=batch_size, shuffle=False,
                                         num_workers=min(workers, usable_cpus()))
    out, layout = {}, memory_format(model, device)
    for batch in loader:
        x = batch["image"].to(device).float().contiguous(memory_format=layout)
        with torch.autocast(device.type, dtype=amp or torch.float32, enabled=amp is not None):
            heat, offset, radius = model(x)
        heat, offset, radius = heat.float(), offset.float(), radius.float()
        circles = decode(heat, offset, radius, top_k or model.config.top_k, dataset.image_size).cpu().numpy()
        for i, c in zip(batch["index"].tolist(), circles):  # back to the image's own pixels
            rec = dataset.records[i]
            out[rec.image_id] = scale_circles(c[c[:, 3] > 0], 1.0 / dataset.scale_of(i))
    return out


# ---------------------------------------------------------------- training

def memory_format(model: torch.nn.Module, device: torch.device) -> torch.memory_format:
    """Channels-last (faster convolutions) unless the model has a strided 1x1 convolution of 2 to 15
    input channels on the CPU: torch 2.13's CPU backward of one on channels-last tensors corrupts
    the heap (the process aborts) on images of the model's size (a narrow ``--resnet-width``)."""
    narrow = any(isinstance(m, torch.nn.Conv2d) and m.kernel_size == (1, 1) and m.stride != (1, 1)
                 and 1 < m.in_channels < 16 for m in model.modules())
    return torch.contiguous_format if narrow and torch.device(device).type == "cpu" else torch.channels_last


def _atomic_write(path: Path, write) -> None:
    tmp = path.with_name(f".tmp-{path.name}")
    write(tmp)
    os.replace(tmp, path)


def _precision(config: TrainConfig, device: torch.device) -> torch.dtype | None:
    """bfloat16 autocast where the hardware runs it natively, else None (float32)."""
    if config.mixed_precision == "off":
        return None
    if config.mixed_precision not in ("auto", "bf16"):
        raise SphereBenchError(f"mixed_precision must be 'auto', 'bf16' or 'off', got {config.mixed_precision!r}")
    if device.type == "cuda":
        return torch.bfloat16 if torch.cuda.is_bf16_supported() else None
    native = getattr(torch.cpu, "_is_amx_tile_supported", lambda: False)() or \
        getattr(torch.cpu, "_is_avx512_bf16_supported", lambda: False)()
    return torch.bfloat16 if (native or config.mixed_precision == "bf16") else None


def _learning_rate(config: TrainConfig, iteration: int, total: int) -> float:
    if iteration < config.warmup_iters:
        return config.lr * (iteration + 1) / config.warmup_iters
    t = (iteration - config.warmup_iters) / max(1, total - config.warmup_iters)
    floor = config.lr * config.final_lr_fraction
    return floor + (config.lr - floor) * 0.5 * (1 + math.cos(math.pi * min(1.0, t)))


def _batches(n: int, batch_size: int, seed: int, epoch: int) -> list[list[int]]:
    """The epoch's batches: a seeded permutation cut into full batches (BatchNorm dislikes tiny ones)."""
    perm = np.random.default_rng([seed, epoch]).permutation(n).tolist()
    if n < batch_size:
        return [perm]
    return [perm[i:i + batch_size] for i in range(0, n - batch_size + 1, batch_size)]


def plot_training_curve(history: dict, path) -> None:
    """Training loss (per iteration, and its running mean) and validation mAP per epoch, as a PNG."""
    plt = pyplot()
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(10, 3.8))
    if history["loss"]:
        x, y = np.asarray(history["loss"], dtype=np.float64).T
        ax1.plot(x, y, lw=0.5, alpha=0.35, color="tab:blue", label="per iteration")
        k = max(1, len(y) // 50)
        if k > 1:
            ax1.plot(x[k - 1:], np.convolve(y, np.ones(k) / k, mode="valid"), color="tab:blue", label=f"mean of {k}")
        ax1.set_yscale("log")
        ax1.legend()
    ax1.set_xlabel("epoch")
    ax1.set_ylabel("training loss")
    if history["val"]:
        ep = [v["epoch"] for v in history["val"]]
        ax2.plot(ep, [v["mAP50"] for v in history["val"]], "o-", label="mAP.50")
        ax2.plot(ep, [v["mAP"] for v in history["val"]], "s-", label="mAP (.50:.95)")
        ax2.set_ylim(0, 1)
        ax2.legend()
    ax2.set_xlabel("epoch")
    ax2.set_ylabel("validation (circle IoU)")
    ax2.grid(alpha=0.3)
    fig.tight_layout()
    _atomic_write(Path(path), lambda tmp: fig.savefig(tmp, dpi=120, format="png"))
    plt.close(fig)


def _dataset_fingerprint(records) -> str:
    h = hashlib.sha256()
    for r in records:
        h.update(f"{r.image_id}:{r.scene_id}:{r.circles.round(3).tolist()};".encode())
    return h.hexdigest()[:16]


def _load_checkpoint(path: Path) -> dict:
    if not path.is_file():
        raise SphereBenchError(f"nothing to resume: {path} not found")
    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:
        raise SphereBenchError(f"cannot read checkpoint {path} ({type(exc).__name__}); "
                               "start a fresh run in another --out") from None


def run_config(out_dir) -> TrainConfig:
    """The settings of the run (its checkpoint) in out_dir, e.g. to resume it with a change of workers."""
    return TrainConfig.from_dict(_load_checkpoint(Path(out_dir) / "checkpoint.pt")["config"])


def train(train_dir, out_dir, config: TrainConfig | None = None, seed: int = 0, resume: bool = False,
          progress: bool = True, command: str | None = None) -> dict:
    """Train, validate each epoch, export model.onnx; returns the model card (a dict).

    train_dir: a dataset folder, or a list of them trained on as one (``data.read_datasets``).
    config: None = the defaults, or on resume the checkpoint's. resume: continue the run in
    out_dir (its config must then match in every field that defines the result).
    """
    out = Path(out_dir)
    ckpt_path = out / "checkpoint.pt"
    records = read_datasets(train_dir)
    state = None
    if resume:
        state = _load_checkpoint(ckpt_path)
        saved = TrainConfig.from_dict(state["config"])
        if config is not None:
            a, b = config.to_dict(), saved.to_dict()
            diff = [k for k in a if k not in _HOW_FIELDS and a[k] != b[k]]
            if diff:
                raise SphereBenchError(f"the checkpoint in {out} was made with other settings ({', '.join(diff)}); "
                                       "resume with the same settings or start a fresh run in another --out")
            saved = TrainConfig.from_dict({**b, **{k: a[k] for k in _HOW_FIELDS}})
        config = saved
        if state["seed"] != seed:
            raise SphereBenchError(f"the checkpoint in {out} has seed {state['seed']}, not {seed}")
        if state["data_fingerprint"] != _dataset_fingerprint(records):
            raise SphereBenchError(f"{train_dir} is not the dataset the checkpoint in {out} was trained on")
    elif ckpt_path.exists():
        raise SphereBenchError(f"{out} already holds a training run; pass --resume to continue it "
                               "or choose another --out")
    config = config or TrainConfig()
    device = check_config(config)  # before the output folder exists: a refused run leaves nothing
    train_recs, val_recs = split_scenes(records, config.val_fraction, seed)
    # a new, empty or earlier training folder only: a run never overwrites files it did not write; a
    # failed run removes the folder it made unless a checkpoint is there to resume from
    with outputs.output_run(out, TRAINING_RUN_KIND, resumable=("checkpoint.pt",),
                            resume="rerun with --resume to continue", legacy="checkpoint.pt"):
        return _train(config, device, seed, out, ckpt_path, train_dir, records, train_recs, val_recs, state,
                      progress, command)


def check_config(config: TrainConfig) -> torch.device:
    """The torch device of a run, once every setting has been checked (SphereBenchError otherwise)."""
    problems = [f"{name} must be at least 1 (got {getattr(config, name)})"
                for name in ("epochs", "batch_size") if not getattr(config, name) >= 1]
    if not config.workers >= 0:
        problems.append(f"workers must be 0 (load in the main process) or more data-loading processes "
                        f"(got {config.workers})")
    if config.threads is not None and not config.threads >= 1:
        problems.append(f"threads must be at least 1 (got {config.threads})")
    if config.onnx_weights not in ("float32", "float16"):
        problems.append(f"onnx_weights must be 'float32' or 'float16' (got {config.onnx_weights!r})")
    if config.mixed_precision not in ("auto", "bf16", "off"):
        problems.append(f"mixed_precision must be 'auto', 'bf16' or 'off' (got {config.mixed_precision!r})")
    if problems:
        raise SphereBenchError("; ".join(problems))
    if config.device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        device = torch.device(config.device)
    except (RuntimeError, TypeError):
        device = None
    if device is None or device.type not in ("cpu", "cuda"):
        raise SphereBenchError(f"device {config.device!r} is not one torch trains on here: use auto, cpu, cuda "
                               "or cuda:N")
    if device.type == "cuda" and not torch.cuda.is_available():
        raise SphereBenchError(f"device {config.device}: this machine has no CUDA device for torch {torch.__version__}; "
                               "train on a machine with a GPU (and a CUDA build of torch), or use --device cpu")
    if device.type == "cuda" and device.index is not None and device.index >= torch.cuda.device_count():
        raise SphereBenchError(f"device {config.device}: this machine has {torch.cuda.device_count()} CUDA device(s), "
                               f"cuda:0 to cuda:{torch.cuda.device_count() - 1}")
    return device


def _train(config: TrainConfig, device: torch.device, seed: int, out: Path, ckpt_path: Path, train_dir, records,
           train_recs, val_recs, state, progress: bool, command: str | None) -> dict:
    """The training loop of ``train``, in an output folder that exists."""
    size = config.model.image_size
    train_set = CircleDataset(train_recs, size, config.augment, seed, config.max_objects)
    val_set = CircleDataset(val_recs, size, None, seed, config.max_objects)
    val_gt = {r.image_id: r.circles for r in val_recs}
    amp = _precision(config, device)
    if config.threads:
        torch.set_num_threads(config.threads)  # OpenMP threads that wait on each other crawl on a busy machine
    torch.manual_seed(seed)
    model = CircleNet(config.model)
    layout = memory_format(model, device)
    model = model.to(device, memory_format=layout)
    optimizer = torch.optim.AdamW(model.parameters(), lr=config.lr, weight_decay=config.weight_decay)
    history = {"loss": [], "val": []}
    epoch, batch_pos, iteration, seconds = 0, 0, 0, 0.0
    if state is not None:
        model.load_state_dict(state["model"])
        optimizer.load_state_dict(state["optimizer"])
        history, epoch, batch_pos = state["history"], state["epoch"], state["batch_pos"]
        iteration, seconds = state["iteration"], state["seconds"]

    iters_per_epoch = len(_batches(len(train_set), config.batch_size, seed, 0))
    total_iters = iters_per_epoch * config.epochs
    fingerprint = _dataset_fingerprint(records)

    def save(epoch_: int, pos: int) -> None:
        blob = {"config": config.to_dict(), "seed": seed, "model": model.state_dict(),
                "optimizer": optimizer.state_dict(), "history": history, "epoch": epoch_, "batch_pos": pos,
                "iteration": iteration, "seconds": seconds + time.perf_counter() - t_start,
                "data_fingerprint": fingerprint}
        _atomic_write(ckpt_path, lambda tmp: torch.save(blob, tmp))

    t_start = time.perf_counter()
    last_save = time.monotonic()
    while epoch < config.epochs:
        model.train()
        train_set.set_epoch(epoch)
        batches = _batches(len(train_set), config.batch_size, seed, epoch)
        loader = torch.utils.data.DataLoader(train_set, batch_sampler=batches[batch_pos:],
                                             num_workers=min(config.workers, usable_cpus()))
        bar = progress_bar(loader, desc=f"epoch {epoch + 1}/{config.epochs}", initial=batch_pos, total=len(batches),
                           unit="batch", enabled=progress)
        running = None
        for pos, batch in enumerate(bar, start=batch_pos):
            lr = _learning_rate(config, iteration, total_iters)
            for group in optimizer.param_groups:
                group["lr"] = lr
            x = batch["image"].to(device).float().contiguous(memory_format=layout)
            targets = {k: batch[k].to(device) for k in ("heat", "cells", "mask", "offset", "radius")}
            with torch.autocast(device.type, dtype=amp or torch.float32, enabled=amp is not None):
                stages = model.forward_stages(x)
            loss, parts = circlenet_loss(stages, targets, config.offset_weight, config.radius_weight)
            if not torch.isfinite(loss):
                raise SphereBenchError(f"the loss became {float(loss)} at iteration {iteration}; "
                                       "lower the learning rate (TrainConfig.lr)")
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            torch.nn.utils.clip_grad_norm_(model.parameters(), config.grad_clip)
            optimizer.step()
            iteration += 1
            history["loss"].append([epoch + (pos + 1) / len(batches), parts["total"]])
            running = parts["total"] if running is None else 0.95 * running + 0.05 * parts["total"]
            bar.set_postfix(loss=f"{running:.3f}", heat=f"{parts['heat']:.3f}", lr=f"{lr:.1e}")
            if time.monotonic() - last_save > 60 * config.checkpoint_minutes:
                save(epoch, pos + 1)
                last_save = time.monotonic()
        bar.close()
        val = coco_circle_map(val_gt, predict(model, val_set, config.batch_size, device, amp=amp,
                                              workers=config.workers))
        history["val"].append({"epoch": epoch + 1, **val})
        epoch, batch_pos = epoch + 1, 0
        save(epoch, 0)  # the history travels in the checkpoint: a stopped run leaves only what --resume reads
        last_save = time.monotonic()
        if progress:
            progress_write(f"epoch {epoch}/{config.epochs}: loss {running if running is not None else float('nan'):.4f}, "
                           f"val mAP {val['mAP']:.3f}, mAP.50 {val['mAP50']:.3f}")
    seconds += time.perf_counter() - t_start
    return _finish(model, config, seed, out, train_dir, train_recs, val_recs, val_set, val_gt, history,
                   iteration, seconds, device, amp, command)


def _finish(model, config, seed, out, train_dir, train_recs, val_recs, val_set, val_gt, history,
            iteration, seconds, device, amp, command) -> dict:
    """Export the final model to ONNX, score the exported file on validation, write the history, its
    curve and the model card."""
    _atomic_write(out / "history.json", lambda tmp: tmp.write_text(json.dumps(history)))
    plot_training_curve(history, out / "training_curve.png")

    dirs = [train_dir] if isinstance(train_dir, (str, Path)) else list(train_dir)
    metas = []
    for d_path in dirs:
        meta, meta_path = {}, Path(d_path) / "dataset.json"
        if meta_path.is_file():
            with contextlib.suppress(SphereBenchError, TypeError):
                d = inout.read_json(meta_path)
                meta = {k: d[k] for k in ("name", "preset", "seed") if k in d}
        metas.append(meta)
    # one folder: its fields as before; several: each folder's in "datasets"
    dataset_meta = metas[0] if len(dirs) == 1 else {
        "datasets": [{"train_dir": str(p), **m} for p, m in zip(dirs, metas)]}
    last = history["val"][-1] if history["val"] else {}
    card = {
        "model": f"CircleNet-style ({config.model.backbone}), CenterNet circle heads at stride 4",
        "parameters": count_parameters(model),
        "data": {"train_dir": " + ".join(str(p) for p in dirs), **dataset_meta, "train_images": len(train_recs),
                 "val_images": len(val_recs), "val_split": f"{config.val_fraction:g} of the training scenes, seed {seed}"},
        "seed": seed, "epochs": config.epochs, "iterations": iteration, "batch_size": config.batch_size,
        "train_seconds": round(seconds, 1), "device": _device_name(device),
        "precision": "bfloat16 autocast" if amp is not None else "float32",
        "val_torch": last,
        "command": command or "train(...) from Python",
        "versions": {"python": platform.python_version(), "torch": torch.__version__},
        "config": config.to_dict(),
    }
    onnx_path = export_onnx(model, out / "model.onnx", metadata={
        "backbone": config.model.backbone, "seed": seed, "epochs": config.epochs, "train_data": dataset_meta},
        weights=config.onnx_weights)
    detector = CircleNetDetector(onnx_path)
    dets = {r.image_id: detector.detect_file(r.path) for r in val_recs}
    card["val_onnx"] = coco_circle_map(val_gt, dets)
    card["onnx"] = {"file": onnx_path.name, "bytes": onnx_path.stat().st_size,
                    "sha256": hashlib.sha256(onnx_path.read_bytes()).hexdigest(),
                    "input": f"1x3x{config.model.input_size[0]}x{config.model.input_size[1]} float32 RGB [0, 255]",
                    "weights": config.onnx_weights}
    _atomic_write(out / "model_card.json", lambda tmp: tmp.write_text(json.dumps(card, indent=2)))
    _atomic_write(out / "model_card.md", lambda tmp: tmp.write_text(_card_markdown(card)))
    return card


def _device_name(device: torch.device) -> str:
    if device.type == "cuda":
        return f"GPU: {torch.cuda.get_device_name(device)}"
    return f"CPU: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, torch threads {torch.get_num_threads()}"


def _data_line(d: dict) -> str:
    return f"`{d['train_dir']}`" + (f" (preset {d['preset']}, seed {d.get('seed')})" if "preset" in d else "")


def _card_markdown(card: dict) -> str:
    v, d = card["val_onnx"], card["data"]
    lines = [
        f"# Model card: {card['model']}",
        "",
        "- Data: " + (", ".join(_data_line(x) for x in d["datasets"]) if "datasets" in d else _data_line(d))
        + f": {d['train_images']} training images, {d['val_images']} validation images ({d['val_split']}).",
        f"- Trained from scratch: seed {card['seed']}, {card['epochs']} epochs, {card['iterations']} iterations "
        f"of batch {card['batch_size']}, {card['train_seconds'] / 60:.1f} min on {card['device']} "
        f"({card['precision']}).",
        f"- Validation (ONNX model, COCO circle IoU): mAP {v['mAP']:.3f}, mAP.50 {v['mAP50']:.3f}, "
        f"mAP.75 {v['mAP75']:.3f}.",
        f"- Parameters: {card['parameters']:,}; ONNX {card['onnx']['bytes'] / 1e6:.1f} MB"
        + (" (weights stored as float16, computed in float32)" if card["onnx"].get("weights") == "float16" else "")
        + f", input {card['onnx']['input']}, sha256 `{card['onnx']['sha256'][:16]}...`.",
        f"- Command: `{card['command']}`",
        f"- Versions: Python {card['versions']['python']}, torch {card['versions']['torch']}.",
        "",
    ]
    return "\n".join(lines)
