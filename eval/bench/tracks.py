"""The tracking benchmark (`make track-bench`): `detect --track` and the per-frame detector on the
recordings of the motion presets, scored against each sequence's truth (``eval.metrics.tracking``),
with each frame's latency under the budget of the stream's frame period.

Each sequence is played twice per method through ``method.stream``: frame by frame (every frame
read: the answers scored, each frame's time measured) and in real time (the recording at its own
rate, frames arriving while the detector is busy dropped, as by a camera's frame queue: the frames
dropped). The methods are ``track`` (``stream.track_stream``: the tracks it reports answer, confirmed
and new: ``tracking.Track.reported``) and
``detect`` (``stream.detect_stream``: every sphere reported answers), each frame under a budget of
the frame period (``deadline``). Before either method, the sequence's first ``WARM_FRAMES`` frames
are played once through the detector, untimed: a stream's first frames at a new frame size pay for
the detector's buffers and cold caches (a tracker played first would pay them for the detector
played after it), which is set-up, not a frame's time.
"""

from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np

from spherebench.datasets import depth_frames, sequences
from spherebench.eval.metrics import tracking as T
from spherebench.method import stream

#: The methods compared: the tracker (local search, fused tracks) and the detector frame by frame.
METHODS = ("track", "detect")
#: Frames of a sequence played untimed before its methods: the first 848x480 frames of a stream
#: otherwise take 10-15 ms against 5-6 (docs/experiments/2026-12-06-stream-start.md).
WARM_FRAMES = 5


def truth_frames(doc: dict) -> list[T.FrameTruth]:
    """A sequence's truth (``sequences.read_truth``) as the scorer's frames."""
    out = []
    for f in doc["frames"]:
        balls = f["balls"]
        out.append(T.FrameTruth(np.array([b["track_id"] for b in balls], np.int64),
                                np.array([b["center_m"] for b in balls], np.float64).reshape(-1, 3),
                                np.array([b["visible_fraction"] for b in balls], np.float64),
                                np.array([b["center_m"] for b in f.get("distractors", [])], np.float64).reshape(-1, 3)))
    return out


def _empty() -> T.Answers:
    return T.Answers(np.zeros(0, np.int64), np.zeros((0, 3)))


def play(recording: Path, n_frames: int, config, method: str, budget_ms: float | None, real_time: bool,
         seed: int = 0) -> dict:
    """One playback of a recording: answers (n_frames,) ``Answers`` (none for a frame not
    delivered), ms (frames delivered,) per frame, frames searched locally, frames cut short, frames
    dropped by the reader."""
    stats = depth_frames.StreamStats()
    frames = depth_frames.recording_frames(recording, real_time=real_time, stats=stats)
    answers = [_empty() for _ in range(n_frames)]
    ms, local, cut = [], 0, 0
    if method == "track":
        for r in stream.track_stream(frames, config, seed, budget_ms=budget_ms):
            said = [t for t in r.tracks if t.reported]
            answers[r.frame.number] = T.Answers(np.array([t.track_id for t in said], np.int64),
                                                np.array([t.centre_m for t in said], np.float64).reshape(-1, 3),
                                                np.array([t.confirmed for t in said], bool))
            ms.append(r.ms)
            local += r.search == "local"
            cut += r.cut_short
    else:
        for r in stream.detect_stream(frames, config, seed, budget_ms=budget_ms):
            answers[r.frame.number] = T.Answers(np.full(len(r.spheres), -1, np.int64),
                                                np.array([s.centre_m for s in r.spheres], np.float64).reshape(-1, 3))
            ms.append(r.ms)
            cut += r.cut_short
    return {"answers": answers, "ms": np.asarray(ms, np.float64), "local": local, "cut": cut,
            "dropped": stats.dropped}


def bench_sequence(folder: Path, config, radius_m: float, real_time: bool = True, seed: int = 0,
                   budget_ms: float | None = None) -> list[dict]:
    """Both methods on one sequence: a row each (counts, latencies, the real-time playback's drops).
    budget_ms: each frame's latency bound (default the frame period; inf: none)."""
    doc = sequences.read_truth(folder)
    truth = truth_frames(doc)
    fps = float(doc["fps"])
    resolution = f"{doc['intrinsics']['width']}x{doc['intrinsics']['height']}"
    budget = 1000.0 / fps if budget_ms is None else None if math.isinf(budget_ms) else budget_ms
    warm = depth_frames.recording_frames(folder / "recording.bag")
    for _ in zip(range(WARM_FRAMES), stream.detect_stream(warm, config, seed)):
        pass
    warm.close()
    rows = []
    for method in METHODS:
        t0 = time.perf_counter()
        offline = play(folder / "recording.bag", len(truth), config, method, budget, False, seed)
        live = play(folder / "recording.bag", len(truth), config, method, budget, True, seed) if real_time else None
        rows.append({"sequence": folder.name, "family": doc["family"], "resolution": resolution, "fps": fps,
                     "method": method, "frames": len(truth), "ms": offline["ms"].tolist(),
                     "local": offline["local"], "cut": offline["cut"],
                     "dropped": None if live is None else live["dropped"],
                     "counts": T.sequence_counts(truth, offline["answers"], radius_m),
                     "wall_s": time.perf_counter() - t0})
    return rows


def _percentile(ms: np.ndarray, q: float) -> float:
    return float(np.percentile(ms, q)) if ms.size else math.nan


def aggregate(rows: list[dict]) -> dict:
    """Rows of one group summed: the scorer's rates, the latency's median / p95 / p99 / max (ms), the
    shares searched locally and cut short, and the frames dropped in real time (None: not played)."""
    counts = T.add_counts([r["counts"] for r in rows])
    ms = np.concatenate([np.asarray(r["ms"], np.float64) for r in rows]) if rows else np.zeros(0)
    frames = sum(r["frames"] for r in rows)
    dropped = [r["dropped"] for r in rows]
    return {"sequences": len(rows), "frames": frames, **counts, **T.summary(counts),
            "median_ms": _percentile(ms, 50), "p95_ms": _percentile(ms, 95), "p99_ms": _percentile(ms, 99),
            "max_ms": float(ms.max()) if ms.size else math.nan,
            "period_ms": 1000.0 / rows[0]["fps"] if rows else math.nan,
            "local_share": sum(r["local"] for r in rows) / max(len(ms), 1),
            "cut_share": sum(r["cut"] for r in rows) / max(len(ms), 1),
            "dropped": None if any(d is None for d in dropped) else int(sum(dropped))}


def groups(rows: list[dict]) -> dict[tuple[str, str, str], dict]:
    """(family, resolution, method) -> the aggregate of its rows, and ("all", resolution, method)."""
    keys: dict[tuple[str, str, str], list[dict]] = {}
    for r in rows:
        keys.setdefault((r["family"], r["resolution"], r["method"]), []).append(r)
        keys.setdefault(("all", r["resolution"], r["method"]), []).append(r)
    return {k: aggregate(v) for k, v in sorted(keys.items(), key=lambda kv: (kv[0][0] == "all", kv[0]))}


def targets(by_dataset: dict[str, dict], stereo: set[str]) -> list[tuple[str, str, bool]]:
    """The issue's targets as (target, measured, met) from each dataset's groups; ``stereo`` names the
    datasets of the stereo model."""
    out = []
    for name, g in by_dataset.items():
        for (family, res, method), a in g.items():
            if family != "all" or method != "track":
                continue
            if res == "848x480" and a["dropped"] is not None:
                out.append((f"{name} 848x480 --track in real time: 0 frames dropped", f"{a['dropped']} of {a['frames']}",
                            a["dropped"] == 0))
            if res == "848x480":
                out.append((f"{name} 848x480 --track p99 within the {a['period_ms']:.1f} ms period",
                            f"{a['p99_ms']:.2f} ms", a["p99_ms"] <= a["period_ms"]))
            if res == "424x240":
                out.append((f"{name} 424x240 --track p99 <= 5 ms", f"{a['p99_ms']:.2f} ms", a["p99_ms"] <= 5.0))
            out.append((f"{name} {res}: identity switches <= 1 per 100 track frames",
                        f"{a['switches_per_100']:.2f}", a["switches_per_100"] <= 1.0))
            if name in stereo:
                out.append((f"{name} {res}: tracked centre within 2 cm on >= 90 % of frames within 2.5 m",
                            f"{100 * a['found_near_share']:.1f} %", a["found_near_share"] >= 0.9))
        if name in stereo:  # and over every depth mode
            pooled = [a for (family, res, method), a in g.items() if family == "all" and method == "track"]
            near = sum(a["near"] for a in pooled)
            share = sum(a["found_near"] for a in pooled) / near if near else math.nan
            out.append((f"{name} every depth mode: tracked centre within 2 cm on >= 90 % of frames within 2.5 m",
                        f"{100 * share:.1f} %", share >= 0.9))
        for (family, res, method), a in g.items():
            if method != "track" or family == "all":
                continue
            d = g.get((family, res, "detect"))
            if d is not None:
                out.append((f"{name} {family} {res}: tracked frames found >= the per-frame detector's",
                            f"{100 * a['found_share']:.1f} % vs {100 * d['found_share']:.1f} %",
                            a["found"] >= d["found"]))
            if family == "soccer":
                out.append((f"{name} {family} {res}: soccer ball never confirmed within 3 m",
                            f"{a['distractor_frames']} frames", a["distractor_frames"] == 0))
    return out


def _f(v, fmt: str) -> str:
    return "-" if v is None or (isinstance(v, float) and math.isnan(v)) else format(v, fmt)


def table(g: dict) -> list[str]:
    """A dataset's groups as markdown rows."""
    md = ["| family | depth mode | method | seq. | ball-frames | found (2 cm) | found within 2.5 m | RMSE cm | "
          "ID sw. / 100 | breaks | MOTA | false | distractor taken | median ms | p95 ms | p99 ms | max ms | "
          "local % | cut % | dropped (real time) |", "|" + "---|" * 20]
    for (family, res, method), a in g.items():
        dropped = "-" if a["dropped"] is None else f"{a['dropped']} / {a['frames']}"
        switches = _f(a["switches_per_100"], ".2f") if method == "track" else "-"
        md.append(f"| {family} | {res} | {method} | {a['sequences']} | {a['balls']} | {_f(100 * a['found_share'], '.1f')} | "
                  f"{_f(100 * a['found_near_share'], '.1f')} | {_f(100 * a['rmse_m'], '.2f')} | {switches} | "
                  f"{a['fragments']} | {_f(a['mota'], '.3f')} | {a['false']} | {a['distractor_frames']} | "
                  f"{_f(a['median_ms'], '.2f')} | {_f(a['p95_ms'], '.2f')} | {_f(a['p99_ms'], '.2f')} | "
                  f"{_f(a['max_ms'], '.1f')} | {_f(100 * a['local_share'], '.0f')} | {_f(100 * a['cut_share'], '.1f')} | "
                  f"{dropped} |")
    return md
