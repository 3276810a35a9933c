"""Recordings of moving balls for streams: a room seen by a still camera, balls moving in it by
``motion``'s physics, rendered frame by frame (``rendering.render``) through a sensor model, with
each frame's ground truth: per ball, its track id, centre, visible fraction and circles.

A sequence family is a function ``(rng, intr, floor_y_m, times_s, radius_m) -> (static items,
moving balls)`` registered in ``SEQUENCE_FAMILIES``; a sequence is drawn from its seed alone (the
room, the motion, then the sensor's noise frame by frame), so that the same seed gives the same
frames. ``write_sequence`` writes one as a RealSense recording (``bagwrite``: a ROS1 ``.bag``)
with its ground truth beside it (``truth.json``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from spherebench import __version__
from spherebench.camera import Intrinsics, image_rays
from spherebench.circles import sphere_circle_amodal
from spherebench.datasets import motion
from spherebench.datasets.inout import write_json
from spherebench.datasets.layouts import Item, Layout, floor_box, room
from spherebench.datasets.outputs import atomic_directory, replaceable_dataset
from spherebench.datasets.presets import BASKETBALL_RADIUS_M, PRESETS, RESOLUTIONS, assign_shares, generation_seed
from spherebench.datasets.primitives import Box, SolidSphere
from spherebench.datasets.rendering import render
from spherebench.datasets.sensor import D435Sensor
from spherebench.datasets.stereo import StereoSensor
from spherebench.errors import SphereBenchError, require
from spherebench.parallel import each_with_progress
from spherebench.reading import read_json

#: A size 5 soccer ball's radius, m (68-70 cm round): the ball a basketball tracker must not take.
SOCCER_RADIUS_M = 0.11
#: The camera's height above the floor, m: a mobile robot's to a tripod's.
CAMERA_HEIGHT_M = (0.5, 1.1)
#: How far from the camera the balls move, m (nearer where the floor is out of view there).
PATH_DEPTH_M = (1.5, 3.5)


@dataclass(frozen=True)
class MovingBall:
    """A ball of a sequence: its track (``motion.Track``) and what it is (``target``: a ball of the
    dataset's radius; ``distractor``: another ball)."""

    track: motion.Track
    kind: str = "target"


@dataclass(frozen=True)
class Sequence:
    """A rendered sequence: depth frames (T, H, W) uint16 in counts of ``intrinsics.depth_scale``,
    their times (T,) s, the balls that move in it, per frame a list of the targets' truth (track id,
    centre m, radius m, visible fraction, circle px of the visible mask, amodal circle px) and a list
    of the other balls' (track id, centre m, radius m: what a tracker of the targets must not take)."""

    family: str
    seed: int
    fps: float
    intrinsics: Intrinsics
    times_s: np.ndarray
    depth: np.ndarray
    balls: list[MovingBall]
    truth: list[list[dict]]
    distractors: list[list[dict]]


#: family name -> builder (rng, intr, floor_y_m, times_s, radius_m) -> (static items, moving balls).
SEQUENCE_FAMILIES: dict[str, Callable] = {}


def register_sequence_family(name: str):
    """A decorator: enter the builder it wraps as sequence family ``name``."""
    def enter(build: Callable) -> Callable:
        if name in SEQUENCE_FAMILIES:
            raise ValueError(f"sequence family {name} is registered already")
        SEQUENCE_FAMILIES[name] = build
        return build
    return enter


def _edge_x(intr: Intrinsics, z_m: float, inset: float) -> float:
    """The x (m) at depth ``z_m`` of the image's left edge, moved in by ``inset`` of the half-width."""
    return -(intr.ppx / intr.fx) * z_m * (1.0 - inset)


def _nearest_floor_m(intr: Intrinsics, floor_y_m: float) -> float:
    """The nearest depth (m) at which a ball on the floor is wholly in view: where the floor meets
    the image's bottom row (a level camera), a tenth farther; at least ``PATH_DEPTH_M[0]``."""
    return max(PATH_DEPTH_M[0], 1.1 * intr.fy * floor_y_m / (intr.height - 1 - intr.ppy))


def _floor_depth(rng, intr: Intrinsics, floor_y_m: float, far_m: float = PATH_DEPTH_M[1]) -> float:
    near = _nearest_floor_m(intr, floor_y_m)
    return float(rng.uniform(near, max(near, far_m)))


def _across(rng, intr: Intrinsics, floor_y_m: float, times_s, radius_m: float, track_id: int,
            z_m: float | None = None, leftward: bool | None = None) -> motion.Track:
    """A ball rolling across the view at one depth, from near one side toward the other, at the speed
    that crosses it in about the sequence's length (rolling resistance slows it)."""
    z = _floor_depth(rng, intr, floor_y_m) if z_m is None else z_m
    left = bool(rng.random() < 0.5) if leftward is None else leftward
    x0 = _edge_x(intr, z, 0.2)
    start, end = (x0, -x0) if not left else (-x0, x0)
    resistance = float(rng.uniform(*motion.ROLLING_RESISTANCE))
    duration = max(float(times_s[-1]), 1e-3)
    distance = abs(end - start)
    speed = distance / duration + 0.5 * resistance * motion.GRAVITY_M_S2 * duration  # reaches ``end`` as time runs out
    velocity = np.array([math.copysign(speed, end - start), 0.0, 0.0])
    centres = motion.rolling([start, 0.0, z], velocity, floor_y_m, radius_m, resistance, times_s)
    return motion.Track(times_s, centres, radius_m, track_id, "rolling")


@register_sequence_family("rolling")
def rolling_across(rng, intr, floor_y_m, times_s, radius_m):
    """A ball rolling across the floor in front of a wall."""
    return [], [MovingBall(_across(rng, intr, floor_y_m, times_s, radius_m, 0))]


@register_sequence_family("thrown")
def thrown_across(rng, intr, floor_y_m, times_s, radius_m):
    """A ball thrown from hand height across the view, bouncing on the floor, then rolling."""
    z = _floor_depth(rng, intr, floor_y_m)
    x0 = _edge_x(intr, z, 0.25) * (1 if rng.random() < 0.5 else -1)
    start = np.array([x0, floor_y_m - rng.uniform(0.8, 1.2) * floor_y_m, z])  # from about the camera's height
    velocity = np.array([-math.copysign(rng.uniform(0.8, 1.6), x0), -rng.uniform(1.5, 3.5), rng.uniform(-0.2, 0.2)])
    centres = motion.thrown(start, velocity, floor_y_m, radius_m, float(rng.uniform(*motion.RESTITUTION)),
                            float(rng.uniform(*motion.ROLLING_RESISTANCE)), times_s)
    return [], [MovingBall(motion.Track(times_s, centres, radius_m, 0, "thrown"))]


@register_sequence_family("crossing")
def two_crossing(rng, intr, floor_y_m, times_s, radius_m):
    """Two balls of the dataset's size rolling across the view in opposite directions, one behind
    the other, so that the nearer hides the farther as they cross."""
    near = _floor_depth(rng, intr, floor_y_m, 2.4)
    far = near + float(rng.uniform(0.6, 1.2))
    leftward = bool(rng.random() < 0.5)
    return [], [MovingBall(_across(rng, intr, floor_y_m, times_s, radius_m, 0, near, leftward)),
                MovingBall(_across(rng, intr, floor_y_m, times_s, radius_m, 1, far, not leftward))]


@register_sequence_family("behind")
def behind_furniture(rng, intr, floor_y_m, times_s, radius_m):
    """A ball rolling across the view behind a box on the floor that hides it for part of the way."""
    ball = _across(rng, intr, floor_y_m, times_s, radius_m, 0)
    z = float(ball.centres_m[0, 2])
    layout = Layout(floor_y_m=floor_y_m)
    floor_box(rng, layout, float(rng.uniform(-0.3, 0.3)) * z, z - float(rng.uniform(0.5, 0.9)), size_m=(0.4, 0.6))
    return layout.items, [MovingBall(ball)]


@register_sequence_family("soccer")
def soccer_beside(rng, intr, floor_y_m, times_s, radius_m):
    """The ball rolling across the view and a soccer ball (``SOCCER_RADIUS_M``) rolling the other
    way at another depth: the ball that a tracker of the dataset's ball must not confirm."""
    near = _floor_depth(rng, intr, floor_y_m, 2.6)
    leftward = bool(rng.random() < 0.5)
    target = _across(rng, intr, floor_y_m, times_s, radius_m, 0, near, leftward)
    other = _across(rng, intr, floor_y_m, times_s, SOCCER_RADIUS_M, 1, near + float(rng.uniform(0.4, 1.0)),
                    not leftward)
    return [], [MovingBall(target), MovingBall(other, "distractor")]


@register_sequence_family("carried")
def carried_by_hand(rng, intr, floor_y_m, times_s, radius_m):
    """A ball carried across the view at hand height, a hand and forearm (a box) holding it from
    below on the camera's side, hiding part of its lower face."""
    z0, z1 = (float(rng.uniform(*PATH_DEPTH_M)) for _ in range(2))
    height = floor_y_m + float(rng.uniform(-0.15, 0.15))  # about the camera's height: in view
    side = 1 if rng.random() < 0.5 else -1
    start = np.array([side * _edge_x(intr, z0, 0.25), floor_y_m - height, z0])
    end = np.array([-side * _edge_x(intr, z1, 0.25), floor_y_m - height, z1])
    centres = motion.carried(rng, start, end, times_s, speed_m_s=float(np.linalg.norm(end - start)) / max(
        float(times_s[-1]), 1e-3) * 1.3)
    return [], [MovingBall(motion.Track(times_s, centres, radius_m, 0, "carried"))]


def _hand(centre_m: np.ndarray, radius_m: float) -> Box:
    """The hand and forearm under a carried ball: a 9 x 6 x 30 cm box from the ball's lower front
    toward the camera."""
    half = np.array([0.045, 0.03, 0.15])
    return Box(centre_m + np.array([0.0, 0.75 * radius_m + half[1], -0.4 * radius_m - half[2] + 0.08]), half, np.eye(3))


def build_sequence(family: str, seed: int, resolution: str = "424x240", fps: float = 90.0, duration_s: float = 2.0,
                   sensor: D435Sensor | StereoSensor | None = None, radius_m: float = BASKETBALL_RADIUS_M) -> Sequence:
    """One sequence of ``family`` drawn from ``seed``, rendered at ``resolution`` through ``sensor``
    (default the nominal analytic one) at ``fps`` for ``duration_s``."""
    if family not in SEQUENCE_FAMILIES:
        raise ValueError(f"unknown sequence family {family}: one of {', '.join(SEQUENCE_FAMILIES)}")
    sensor = D435Sensor() if sensor is None else sensor
    rng = np.random.default_rng([int(seed), 0x5E0])
    w, h = RESOLUTIONS[resolution]
    intr = Intrinsics(**{**Intrinsics.d435(w, h).to_dict(), "depth_scale": sensor.depth_scale_m})
    rays = image_rays(intr)
    times = motion.frame_times(fps, duration_s)
    floor_y = float(rng.uniform(*CAMERA_HEIGHT_M))
    static = Layout(floor_y_m=floor_y)
    room(rng, static, float(rng.uniform(4.0, 6.0)))
    extra, balls = SEQUENCE_FAMILIES[family](rng, intr, floor_y, times, radius_m)
    static.items.extend(extra)
    frames, truth, others = [], [], []
    targets = [b for b in balls if b.kind == "target"]
    for k in range(len(times)):
        layout = Layout(items=list(static.items), floor_y_m=floor_y)
        for b in balls:  # targets first: rendering.render reports them in the layout's order
            c = b.track.centres_m[k]
            layout.items.append(Item(SolidSphere(c, b.track.radius_m), b.kind))
            if b.track.kind == "carried":
                layout.items.append(Item(_hand(c, b.track.radius_m), "clutter"))
        depth, _z, rendered = render(layout, intr, sensor, rng, rays)
        frames.append(depth)
        truth.append([{"track_id": b.track.track_id, "center_m": [round(float(x), 6) for x in b.track.centres_m[k]],
                       "radius_m": b.track.radius_m, "visible_fraction": round(r.visible_fraction, 4),
                       "circle_px": None if r.circle_px is None else [round(float(x), 3) for x in r.circle_px],
                       "amodal_circle_px": _rounded(sphere_circle_amodal(intr, b.track.centres_m[k], b.track.radius_m))}
                      for b, r in zip(targets, rendered)])
        others.append([{"track_id": b.track.track_id, "center_m": [round(float(x), 6) for x in b.track.centres_m[k]],
                        "radius_m": b.track.radius_m} for b in balls if b.kind != "target"])
    return Sequence(family, int(seed), float(fps), intr, times, np.stack(frames), balls, truth, others)


def _rounded(circle) -> list[float] | None:
    return None if circle is None else [round(float(x), 3) for x in circle]


def truth_document(seq: Sequence) -> dict:
    """The ground truth of a sequence as ``truth.json`` holds it."""
    return {"family": seq.family, "seed": seq.seed, "fps": seq.fps, "intrinsics": seq.intrinsics.to_dict(),
            "balls": [{"track_id": b.track.track_id, "kind": b.kind, "motion": b.track.kind,
                       "radius_m": b.track.radius_m} for b in seq.balls],
            "frames": [{"index": k, "time_s": round(float(t), 6), "balls": balls, "distractors": others}
                       for k, (t, balls, others) in enumerate(zip(seq.times_s, seq.truth, seq.distractors))]}


#: What ``write_sequence`` writes in a sequence's folder (a folder holding only these may be replaced).
SEQUENCE_FILES = ("recording.bag", "truth.json")


def _is_sequence(folder: Path) -> bool:
    return {p.name for p in Path(folder).iterdir()} <= set(SEQUENCE_FILES)


def write_sequence(folder: str | Path, seq: Sequence) -> Path:
    """Write a sequence as ``folder/recording.bag`` (a RealSense ROS1 recording, ``bagwrite``; needs
    rosbags, of the ``realsense`` and ``test`` extras) and ``folder/truth.json``, the folder replaced
    atomically."""
    from spherebench.datasets.bagwrite import write_realsense_bag  # here: rosbags is an extra

    if seq.fps != round(seq.fps):
        raise ValueError(f"a recording's frame rate is whole frames a second, not {seq.fps}")
    with atomic_directory(folder, _is_sequence) as tmp:
        write_realsense_bag(tmp / "recording.bag", list(seq.depth), seq.intrinsics, fps=int(seq.fps))
        write_json(tmp / "truth.json", truth_document(seq))
    return Path(folder)


def read_truth(folder: str | Path) -> dict:
    """A sequence's ``truth.json`` (``truth_document``), read through the JSON gate; its frames checked
    to be in order, one per recorded frame number."""
    path = Path(folder) / "truth.json"
    doc = read_json(path)
    frames = doc.get("frames") if isinstance(doc, dict) else None
    if not isinstance(frames, list) or [f.get("index") if isinstance(f, dict) else None for f in frames] \
            != list(range(len(frames))):
        raise SphereBenchError(f"{path}: not a sequence's truth (frames indexed 0, 1, ...): write it with "
                               "spherebench generate --preset motion")
    return doc


def sequence_folders(dataset: str | Path) -> list[Path]:
    """The sequences of a dataset of the motion grammar (``DIR/sequences/<name>/`` holding a recording
    and its truth), by name; a folder beside them that is not one is passed over."""
    root = Path(dataset) / "sequences"
    if not root.is_dir():
        raise SphereBenchError(f"{dataset}: no sequences/ folder: give a dataset of moving balls "
                               "(spherebench generate --preset motion)")
    return sorted(p for p in root.iterdir() if p.is_dir() and all((p / f).is_file() for f in SEQUENCE_FILES))


# --------------------------------------------------------------------------- a preset's recordings

#: The depth stream's frame rate at each resolution, frames a second (the D435 streams 1280x720 at 30).
SEQUENCE_FPS = {"424x240": 90, "848x480": 90, "1280x720": 30}
#: A sequence's length, s.
SEQUENCE_DURATION_S = (2.0, 6.0)


def plan_sequences(preset_name: str, n: int | None = None, seed: int = 0) -> list[tuple[int, str, str]]:
    """(index, family, resolution) of every sequence of a preset of the motion grammar."""
    preset = PRESETS[preset_name]
    n = preset.n_default if n is None else int(n)
    if not 1 <= n <= 100_000:
        raise SphereBenchError(f"--n {n}: the number of sequences must be between 1 and 100,000")
    unknown = [f for f, _share in preset.families if f not in SEQUENCE_FAMILIES]
    if unknown:
        raise SphereBenchError(f"the {preset_name} preset names sequence families that do not exist: "
                               f"{', '.join(unknown)} (register_sequence_family)")
    families = assign_shares(preset.families, n)
    names, shares = zip(*preset.resolutions)
    resolutions = np.random.default_rng([preset.code, int(seed), 7]).choice(names, size=n, p=np.asarray(shares) / sum(shares))
    return [(i, f, str(r)) for i, (f, r) in enumerate(zip(families, resolutions))]


def _build_one(args) -> str:
    preset_name, index, family, seed, resolution, radius_m, sequences_dir = args
    preset = PRESETS[preset_name]
    scene_seed = generation_seed(preset, seed, index)
    duration = float(np.random.default_rng([scene_seed, 0xD0]).uniform(*SEQUENCE_DURATION_S))
    sensor = StereoSensor() if preset.sensor_model == "stereo" else D435Sensor()
    seq = build_sequence(family, scene_seed, resolution, SEQUENCE_FPS[resolution], duration, sensor, radius_m)
    name = f"{family}_{index:04d}"
    write_sequence(sequences_dir / name, seq)
    return name


def generate_sequences(preset_name: str, out_dir: str | Path, n: int | None = None, seed: int = 0,
                       radius_m: float = BASKETBALL_RADIUS_M, workers: int = 1, progress: bool = True,
                       before_commit: Callable[[Path], None] | None = None) -> Path:
    """Build a preset of the motion grammar into ``out_dir`` (replaced atomically when complete):
    ``out_dir/sequences/<family>_<index>/`` (``write_sequence``) and ``dataset.json``. Each sequence is
    drawn from its generation seed (``presets.generation_seed``), its length from a stream of it;
    the output is the same for any number of ``workers``. before_commit: as ``simulate.generate_dataset``'s."""
    require("rosbags", "realsense", "writing recordings (the motion presets)")
    preset = PRESETS[preset_name]
    jobs = plan_sequences(preset_name, n, seed)
    out_dir = Path(out_dir)
    with atomic_directory(out_dir, replaceable_dataset) as tmp:
        sequences_dir = tmp / "sequences"
        sequences_dir.mkdir()
        tasks = [(preset_name, i, f, seed, r, radius_m, sequences_dir) for i, f, r in jobs]
        each_with_progress(_build_one, tasks, workers, f"generate {preset_name}", "sequence", progress)
        meta = {"name": out_dir.name, "preset": preset_name, "n": len(jobs), "seed": int(seed),
                "ball_radius_m": radius_m, "category": "basketball", "source": "simulated", "kind": "sequences",
                "grammar": preset.grammar, "sensor_model": preset.sensor_model,
                "fps": SEQUENCE_FPS, "duration_s": list(SEQUENCE_DURATION_S),
                "spherebench_version": __version__, "numpy_version": np.__version__}
        write_json(tmp / "dataset.json", meta)
        if before_commit is not None:
            before_commit(out_dir)
    return out_dir
