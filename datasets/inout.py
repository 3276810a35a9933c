"""Every file format of SphereBench, in one module (as the BOP toolkit's inout.py).

Dataset layout (simulated and recorded alike)::

    DIR/dataset.json              name, preset, ball radius (m), category, seed, versions
    DIR/coco_gt.json              COCO ground truth with CircleNet's circle fields
    DIR/scenes/<scene_id>/
        depth.png                 uint16, counts of depth_scale (0 = no depth)
        intrinsics.json           pyrealsense2's rs.intrinsics fields + depth_scale
        cloud.ply                 binary PLY: float32 x, y, z (m) [+ int32 row, col]
        image.png                 the depth colourised (datasets.reproject): 2D methods' input
        gt.json                   balls (3D centre, radius, circles, visibility), family, seed
        mask_<k>.png              visible mask of ball k (255 = ball)
        silhouette_<k>.png        full silhouette of ball k (simulated scenes)

Writes are atomic: a file is written to a temporary name and renamed; a scene folder and a whole
dataset are built under a temporary name and renamed when complete, so an interrupted or failed
run leaves nothing half-written behind.
"""

from __future__ import annotations

import collections
import contextlib
import functools
import glob
import io
import json
import math
import os
import queue
import shutil
import socket
import stat
import tempfile
import threading
import warnings
import zlib
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from plyfile import PlyData, PlyElement

from spherebench.camera import MAX_IMAGE_SIDE_PX, Intrinsics, float32_decimal
from spherebench.circles import circle_bbox
from spherebench.cloud import Cloud, cloud_from_depth, depth_to_metres
from spherebench.datasets.reproject import colorize_depth
from spherebench.datasets.scene import Ball, Scene
from spherebench.errors import SphereBenchError, require

CATEGORY_ID = 1
DEFAULT_CATEGORY = "basketball"


# --------------------------------------------------------------------------- atomic, owned writes
#
# The tool replaces only what it wrote: an output folder is replaced when it is empty or holds the
# marker of its kind (a dataset's dataset.json, a results or training folder's OWNER_MARKER), a
# report's OUT.json when it names the report's kind, a file for the user to look at when it carries
# the mark (is_marked), and each is refused otherwise; nothing is written inside a dataset but by
# generate and prepare. Several files are written all or nothing (replace_files). Temporaries are
# siblings named .tmp-<name>.*; a temporary folder records the process that made it, so that a
# later run can remove one whose process died (SIGKILL, power).

#: Written into a folder that a command fills over time (evaluate's results, a training run).
OWNER_MARKER = ".spherebench-output.json"
_TMP_OWNER = ".spherebench-tmp.json"


def _umask() -> int:
    mask = os.umask(0o022)  # reading the umask means setting it: put it straight back
    os.umask(mask)
    return mask


def check_folders(path: str | Path, what: str = "--out") -> None:
    """A one-line error when a part of the folders above ``path`` is a file (where making them would
    only say "File exists" about that part)."""
    for parent in Path(path).parents:
        if parent.exists():
            if not parent.is_dir():
                raise SphereBenchError(f"{what} {path}: {parent} is a file, not a folder: give a path under a folder")
            return


def named_error(exc: OSError, path: str | Path) -> OSError:
    """``exc`` naming ``path``, the destination the user gave, rather than a temporary's name (or none,
    as a full disk's write error has)."""
    if exc.errno is None:
        return exc
    return OSError(exc.errno, exc.strerror or str(exc), str(path))


#: What a path is, by its stat mode, where it is neither a regular file nor a folder.
_SPECIAL_FILES = ((stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"),
                  (stat.S_ISFIFO, "a FIFO (named pipe)"), (stat.S_ISSOCK, "a socket"))


def check_regular(path: str | Path, what: str = "output") -> None:
    """A one-line error when ``path`` exists as anything but a regular file (a folder, a device, a
    FIFO, a socket; a link is followed): a write renames a new file over it, which would put a
    regular file in place of a device or pipe, and --force never allows that."""
    try:
        mode = Path(path).stat().st_mode
    except OSError:  # nothing there (or nothing this user may see): a new file
        return
    if stat.S_ISDIR(mode):
        raise SphereBenchError(f"{what} {path} is a folder: give a file name")
    kind = next((name for test, name in _SPECIAL_FILES if test(mode)), None if stat.S_ISREG(mode) else "not a file")
    if kind is not None:
        raise SphereBenchError(f"{what} {path} is {kind}, not a regular file: only a regular file is ever "
                               "replaced: give a file name")


def _stage(path: Path, data: bytes) -> Path:
    """``data`` in a new temporary sibling of ``path``, with the mode an ordinary write would give
    (0666 less the umask), not mkstemp's 0600; its name."""
    check_regular(path)
    check_folders(path, "output")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".tmp-{path.name}.", dir=path.parent)
    except OSError as exc:
        raise named_error(exc, path) from None
    try:
        with os.fdopen(fd, "wb") as f:
            os.fchmod(f.fileno(), 0o666 & ~_umask())
            f.write(data)
    except BaseException as exc:
        os.unlink(tmp)
        if isinstance(exc, OSError):
            raise named_error(exc, path) from None
        raise
    return Path(tmp)


def atomic_write_bytes(path: str | Path, data: bytes) -> None:
    """Write ``data`` to ``path`` through a temporary file in the same folder, then rename; an error
    names ``path``."""
    path = Path(path)
    tmp = _stage(path, data)
    try:
        os.replace(tmp, path)
    except BaseException as exc:
        tmp.unlink(missing_ok=True)
        if isinstance(exc, OSError):
            raise named_error(exc, path) from None
        raise


def replace_files(files: dict[Path, bytes]) -> None:
    """Write several files all or nothing: each is staged beside its destination, then renamed over
    it, a replaced file kept (a hard link, else a copy) until every one is in place; on any failure
    every destination is put back as it was. An error names the destination."""
    staged: dict[Path, Path] = {}
    done: list[tuple[Path, Path | None]] = []  # (destination, the file it replaced, set aside)
    current = None
    try:
        for current, data in files.items():
            staged[Path(current)] = _stage(Path(current), data)
        for current, tmp in staged.items():
            backup = None
            if current.is_file():
                backup = current.with_name(f".tmp-{current.name}.old-{os.getpid()}")
                try:
                    os.link(current, backup)
                except OSError:  # a file system without hard links
                    shutil.copy2(current, backup)
            try:
                os.replace(tmp, current)
            except BaseException:
                if backup is not None:  # a second link to the file still in place
                    backup.unlink()
                raise
            done.append((current, backup))
    except BaseException as exc:
        for path, backup in reversed(done):
            if backup is not None:
                os.replace(backup, path)
            else:
                path.unlink(missing_ok=True)
        for tmp in staged.values():
            tmp.unlink(missing_ok=True)
        if isinstance(exc, OSError):
            raise named_error(exc, current) from None
        raise
    for _, backup in done:
        if backup is not None:
            backup.unlink(missing_ok=True)


# A file a command writes for the user to look at (show, detect: --out-png, --out-ply) carries a
# mark, so that a later run may replace it, and no file that lacks it: a PNG's tEXt chunk right after
# the header, a PLY header's comment line.
_MARK = b"written by spherebench"
_PNG_MARK_CHUNK = (len(b"Software\x00" + _MARK).to_bytes(4, "big") + b"tEXtSoftware\x00" + _MARK
                   + zlib.crc32(b"tEXtSoftware\x00" + _MARK).to_bytes(4, "big"))
_PNG_HEADER_END = 33  # the signature (8 bytes) and the IHDR chunk (25)


def is_marked(path: Path) -> bool:
    """A PNG or PLY that a command wrote with the mark (encode_png's ``mark``, encode_ply)."""
    try:
        with open(path, "rb") as f:
            head = f.read(4096)
    except OSError:
        return False
    if head.startswith(_PNG_SIGNATURE):
        return head[_PNG_HEADER_END:_PNG_HEADER_END + len(_PNG_MARK_CHUNK)] == _PNG_MARK_CHUNK
    if head.startswith(b"ply"):
        return b"\ncomment " + _MARK + b"\n" in head.split(b"end_header")[0].replace(b"\r\n", b"\n")
    return False


def check_output_file(path, what: str, inputs=(), force: bool = False) -> Path:
    """``path`` as a file for the user (a picture, a cloud to view), or a one-line SphereBenchError:
    refused are an empty path, anything but a regular file (a folder, a device, a FIFO:
    ``check_regular``), an input of the command or a file inside an input folder, a file inside any
    dataset (a folder with dataset.json at or above it: only generate and prepare write there), and
    an existing file without the mark of ours (``is_marked``) unless ``force``."""
    if path is None or not str(path).strip():
        raise SphereBenchError(f"{what} is empty (an unset shell variable?): give a file name")
    path = Path(path)
    check_regular(path, what)
    check_folders(path, what)
    resolved = path.resolve()
    for source in inputs:
        src = Path(source).resolve()
        if resolved == src:
            raise SphereBenchError(f"{what} {path} is the input: give another file name")
        if src in resolved.parents:
            raise SphereBenchError(f"{what} {path} is inside the input scene folder {source}: write it elsewhere")
    check_not_in_dataset(path, what)
    if path.exists() and not force and not is_marked(path):
        raise SphereBenchError(f"{what} {path} exists and was not written by SphereBench: give a new name, or pass "
                               "--force to replace it")
    return path


def check_output_files(named: dict, inputs=(), force: bool = False) -> dict:
    """check_output_file for each {option: path}, and no two naming the same file."""
    checked = {what: check_output_file(p, what, inputs, force) for what, p in named.items()}
    seen: dict = {}
    for what, p in checked.items():
        if p.resolve() in seen:
            raise SphereBenchError(f"{seen[p.resolve()]} and {what} name the same file {p}: give two names")
        seen[p.resolve()] = what
    return checked


def check_not_in_dataset(path: str | Path, what: str = "--out") -> None:
    """A one-line error when ``path`` lies inside an existing dataset (below a folder holding
    dataset.json): writing there would break it."""
    for folder in Path(path).resolve().parents:
        try:
            inside = is_dataset_dir(folder)
        except OSError:  # a folder above that this user may not read: no dataset of theirs
            inside = False
        if inside:
            raise SphereBenchError(f"{what} {path} is inside the dataset {folder}, which generate and prepare "
                                   "write only whole: write it elsewhere")


def _report_is_ours(js: Path, kind: str) -> bool:
    """An existing OUT.json written by the same report: it names the kind ("report": kind, which only
    write_report writes; a key such as "seed" any JSON file may hold)."""
    try:
        old = json.loads(js.read_text())
    except (OSError, ValueError, UnicodeDecodeError):
        return False
    return isinstance(old, dict) and old.get("report") == kind


def check_report_out(out: str | Path, kind: str) -> tuple[Path, Path]:
    """OUT.md and OUT.json for a report of this kind, refused (SphereBenchError) before any work when
    OUT names a folder, lies inside a dataset, either file is a folder or a link, or an existing pair
    is not recognisably this report's (``_report_is_ours``): a file the user put there is never
    overwritten."""
    if not str(out).strip():
        raise SphereBenchError("--out is empty (an unset shell variable?): give a path for the report, e.g. "
                               f"results/{kind}")
    text, out = str(out), Path(out)
    if out.name in ("", ".", "..") or text.endswith(("/", os.sep)):  # Path drops a trailing slash
        raise SphereBenchError(f"--out {text} is a folder; give a path for the report's two files in it, e.g. "
                               f"{out / kind} (writes {kind}.md and {kind}.json)")
    md, js = out.with_suffix(".md"), out.with_suffix(".json")
    check_folders(out)
    check_not_in_dataset(md)
    for path in (md, js):
        if path.is_symlink() or path.is_dir():
            raise SphereBenchError(f"{path}: is a folder or a link: give --out a path for the report's two files")
        check_regular(path, "--out")
    if (md.exists() or js.exists()) and not (js.is_file() and _report_is_ours(js, kind)):
        raise SphereBenchError(f"--out {out}: {md.name} or {js.name} there was not written by this report; "
                               "give another --out (nothing was written)")
    return md, js


def write_report(out: str | Path, markdown: str, data: dict, kind: str) -> tuple[Path, Path]:
    """A script's report: OUT.md (the tables) and OUT.json (the figures, with "report": kind;
    infinities as null), each written atomically, after ``check_report_out``. Returns the two paths."""
    md, js = check_report_out(out, kind)
    data = {"report": kind, **data}
    replace_files({md: markdown.encode(),
                   js: json.dumps(data, indent=1, default=lambda x: None if x == math.inf else x).encode()})
    return md, js


def json_bytes(obj, indent: int | None = 1) -> bytes:
    """JSON text as write_json writes it; floats as Python writes them (shortest repr: byte-stable)."""
    return (json.dumps(obj, indent=indent, sort_keys=False) + "\n").encode()


def write_json(path: str | Path, obj, indent: int | None = 1) -> None:
    """JSON (json_bytes), atomically."""
    atomic_write_bytes(path, json_bytes(obj, indent))


def read_json(path: str | Path):
    path = Path(path)
    try:
        with open(path, "rb") as f:
            return json.load(f)
    except FileNotFoundError:
        raise SphereBenchError(f"{path}: file not found") from None
    except IsADirectoryError:
        raise SphereBenchError(f"{path}: is a folder, not a JSON file") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise SphereBenchError(f"{path}: not valid JSON ({exc}); is the file truncated?") from None


def is_dataset_dir(path: Path) -> bool:
    """A folder that `generate` or `prepare` wrote (its dataset.json)."""
    return (Path(path) / "dataset.json").is_file()


_DATASET_FILES = {"dataset.json", "coco_gt.json", "scenes", OWNER_MARKER}
#: colour.jpg / colour.png: a recording's colour frame registered to depth (a file kept as recorded,
#: or a RealSense colour frame aligned to the depth, colour.png);
#: image.json / colour.json: LabelMe annotations saved beside image.png / the colour frame
COLOUR_FILES = ("colour.jpg", "colour.png")
LABELME_FILES = ("image.json", "colour.json")
_SCENE_FILES = {"depth.png", "intrinsics.json", "cloud.ply", "image.png", "gt.json", *COLOUR_FILES, *LABELME_FILES}


def replaceable_dataset(path: Path, labelme_carried: bool = False) -> bool:
    """A dataset folder that may be replaced whole: ours (dataset.json) and holding nothing else than
    what `generate` and `prepare` write. A file added by hand is never deleted, nor are LabelMe
    annotations saved beside a scene's image (image.json) unless this run carries them over
    (``labelme_carried``: `prepare --labelme` reads this very folder): a one-line error names it."""
    path = Path(path)
    if not is_dataset_dir(path):
        return False
    for entry in path.iterdir():
        if entry.name not in _DATASET_FILES:
            raise SphereBenchError(f"{entry} was not written by SphereBench: move it out of {path} before "
                                   "replacing the dataset, or write elsewhere")
    for scene in (path / "scenes").iterdir() if (path / "scenes").is_dir() else ():
        for entry in scene.iterdir() if scene.is_dir() else (scene,):
            name = entry.name
            ours = name in _SCENE_FILES or (name.endswith(".png") and name.startswith(("mask_", "silhouette_")))
            if not ours:
                raise SphereBenchError(f"{entry} was not written by SphereBench: move it out of {path} before "
                                       "replacing the dataset, or write elsewhere")
            if name in LABELME_FILES and not labelme_carried:
                raise SphereBenchError(f"{entry} holds LabelMe annotations that replacing {path} would lose: "
                                       f"pass --labelme {path} to carry them over, or write elsewhere")
    return True


def owned_by_kind(kind: str, legacy: str | None = None):
    """A test for folders a command fills over time: its OWNER_MARKER names ``kind``, or (written before
    the marker existed) it holds the file ``legacy``."""
    def is_ours(path: Path) -> bool:
        marker = Path(path) / OWNER_MARKER
        if marker.is_file():
            with contextlib.suppress(OSError, ValueError, AttributeError):
                return json.loads(marker.read_text()).get("kind") == kind
            return False
        return legacy is not None and (Path(path) / legacy).is_file()
    return is_ours


def never_replace(path: Path) -> bool:
    """For folders built inside a temporary one: an existing folder there is a clash, never replaced."""
    return False


def check_output_dir(path: str | Path, is_ours, what: str = "--out", inputs=()) -> Path:
    """``path`` as an output folder, or a one-line SphereBenchError: refused are an empty path, the
    current folder or one above it, a file, a symbolic link, an input or a folder above or inside an
    input, and a non-empty folder that ``is_ours`` does not recognise (the tool never deletes or
    overwrites what it did not write). Returns the path."""
    text = str(path)
    if not text.strip():
        raise SphereBenchError(f"{what} is empty (an unset shell variable?): give the folder to write")
    path = Path(path)
    if path.is_symlink():
        raise SphereBenchError(f"{what} {path} is a symbolic link (to {os.readlink(path)}): give a real folder")
    resolved = path.resolve()
    cwd = Path.cwd().resolve()
    if resolved == cwd or resolved in cwd.parents:
        raise SphereBenchError(f"{what} {text} is the current folder or one above it: give a new folder, "
                               "e.g. data/mine")
    for source in inputs:
        src = Path(source).resolve()
        if resolved == src or resolved in src.parents or src in resolved.parents:
            raise SphereBenchError(f"{what} {text} is the input {source}, or a folder above or inside it: "
                                   "write the output somewhere else")
    check_folders(path, what)
    if path.exists():
        if not path.is_dir():
            raise SphereBenchError(f"{what} {text} is a file, not a folder: give a folder to write")
        if any(path.iterdir()) and not is_ours(path):
            raise SphereBenchError(f"{what} {text} holds files SphereBench did not write; it is never "
                                   "replaced: give a new or empty folder")
    return path


def claim_output_dir(path: str | Path, kind: str, legacy: str | None = None, what: str = "--out",
                     inputs=()) -> Path:
    """check_output_dir for a folder a command fills over time, then mark it as ours (OWNER_MARKER)."""
    path = check_output_dir(path, owned_by_kind(kind, legacy), what, inputs)
    path.mkdir(parents=True, exist_ok=True)
    if not (path / OWNER_MARKER).is_file():
        write_json(path / OWNER_MARKER, {"kind": kind, "written_by": "spherebench"})
    return path


@contextlib.contextmanager
def output_run(path: str | Path, kind: str, resumable=(), resume: str = "rerun the same command to resume",
               legacy: str | None = None, inputs=()):
    """claim_output_dir, refused inside a dataset, for the length of a run. On a failure or an
    interruption, the folder is removed if this run made it and it holds none of ``resumable`` (the
    names of the files or sub-folders a rerun reuses: evaluate's finished predictions, a training
    checkpoint); else the exception says what was kept (its ``kept``, which cli.run_guarded prints),
    so that no message claims a clean slate that is not there."""
    made = not Path(path).exists()
    check_not_in_dataset(path)
    path = claim_output_dir(path, kind, legacy, inputs=inputs)
    try:
        yield path
    except BaseException as exc:
        kept = [path / name for name in resumable
                if (path / name).is_file() or any(p.is_file() for p in (path / name).rglob("*"))]
        if kept:
            exc.kept = f"completed work is kept in {', '.join(map(str, kept))}: {resume}"
        elif made:
            shutil.rmtree(path, ignore_errors=True)
        raise


def _stale_temporaries(final: Path):
    """Temporary folders of ``final`` whose process on this machine has ended."""
    for tmp in final.parent.glob(f".tmp-{glob.escape(final.name)}.*"):
        owner = tmp / _TMP_OWNER
        try:
            info = json.loads(owner.read_text())
            pid, host = int(info["pid"]), str(info["host"])
        except (OSError, ValueError, KeyError, TypeError):
            continue  # not ours, or not readable: leave it
        if host != socket.gethostname() or pid == os.getpid():
            continue
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            yield tmp
        except PermissionError:
            pass  # alive, another user's


@contextlib.contextmanager
def atomic_directory(final: str | Path, is_ours):
    """Yield a temporary sibling folder; on success it replaces ``final``, on error (or a signal turned
    into KeyboardInterrupt) it is removed. ``final`` is replaced only if it is empty or ``is_ours``
    recognises it (see check_output_dir); stale temporaries of ``final`` from dead runs are removed."""
    final = check_output_dir(final, is_ours)
    final.parent.mkdir(parents=True, exist_ok=True)
    for stale in _stale_temporaries(final):
        shutil.rmtree(stale, ignore_errors=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".tmp-{final.name}.", dir=final.parent))
    try:
        os.chmod(tmp, 0o777 & ~_umask())
        (tmp / _TMP_OWNER).write_text(json.dumps({"pid": os.getpid(), "host": socket.gethostname()}))
        yield tmp
        (tmp / _TMP_OWNER).unlink()
        if final.exists():
            # check again: something may have appeared there while the work ran
            check_output_dir(final, is_ours)
            old = final.with_name(f".tmp-{final.name}.old-{os.getpid()}")
            os.replace(final, old)
            (old / _TMP_OWNER).write_text(json.dumps({"pid": os.getpid(), "host": socket.gethostname()}))
            os.replace(tmp, final)
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.replace(tmp, final)
    except BaseException as exc:
        shutil.rmtree(tmp, ignore_errors=True)
        if isinstance(exc, OSError) and exc.filename is None:  # a write's error (a full disk) names no file
            raise named_error(exc, final) from None
        raise


# --------------------------------------------------------------------------- schemas
#
# Every JSON file the tool reads is checked against its schema here (check_schema), so that a
# damaged or hand-edited file is refused in one line naming the file and the field, never met
# later as a TypeError. A schema is a dict of fields (a name ending in "?" may be absent or null),
# a one-item list (a list of such items) or the name of a kind of value (_KINDS).

#: Ball radii (m) taken anywhere (--radius, dataset.json, gt.json): from a 5 mm bead, at a depth
#: camera's nearest range still several pixels wide, to a 2 m balloon, twice the largest inflatable
#: ball made. Beyond these the number is a unit slip (mm for m), not a ball.
BALL_RADIUS_RANGE_M = (0.005, 2.0)


def _finite(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def _integer(v) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _numbers(v, n: int) -> bool:
    return isinstance(v, list) and len(v) == n and all(_finite(x) for x in v)


def is_ball_radius(v) -> bool:
    return _finite(v) and BALL_RADIUS_RANGE_M[0] <= v <= BALL_RADIUS_RANGE_M[1]


_KINDS = {
    "text": (lambda v: isinstance(v, str), "a string"),
    "bool": (lambda v: isinstance(v, bool), "true or false"),
    "int": (_integer, "an integer"),
    "number": (_finite, "a finite number"),
    "positive": (lambda v: _finite(v) and v > 0, "a finite number > 0"),
    "length": (lambda v: _finite(v) and v >= 0, "a finite number >= 0"),
    "fraction": (lambda v: _finite(v) and 0 <= v <= 1, "a number from 0 to 1"),
    "size": (lambda v: _integer(v) and 0 < v <= MAX_IMAGE_SIDE_PX,
             f"a whole number of pixels from 1 to {MAX_IMAGE_SIDE_PX}"),
    "radius": (is_ball_radius, "a ball radius in metres, {:g} to {:g}".format(*BALL_RADIUS_RANGE_M)),
    "xy": (lambda v: _numbers(v, 2), "[x, y], two finite numbers"),
    "xyz": (lambda v: _numbers(v, 3), "[x, y, z], three finite numbers"),
    "circle": (lambda v: _numbers(v, 3) and v[2] >= 0, "[cx, cy, r], three finite numbers, r >= 0"),
    "object": (lambda v: isinstance(v, dict), "a JSON object"),
    "list": (lambda v: isinstance(v, list), "a list"),
}


def _shown(value) -> str:
    """A value as the file spells it, or what it is where that is long."""
    text = json.dumps(value)
    if len(text) <= 40:
        return text
    return "a JSON object" if isinstance(value, dict) else "a list" if isinstance(value, list) else text[:37] + "..."


def check_schema(path: str | Path, value, schema, fix: str = "fix the file or rebuild the dataset", field: str = ""):
    """``value``, read from ``path``, checked against ``schema`` (above); returned as it is. A
    SphereBenchError names the file, the first wrong field (as balls[0].radius_m) and ``fix``."""
    where = field or "the file"
    if isinstance(schema, dict):
        if not isinstance(value, dict):
            raise SphereBenchError(f"{path}: {where} must be a JSON object, not {_shown(value)}; {fix}")
        for key, sub in schema.items():
            name = key.rstrip("?")
            inner = (f"{name} of {field}" if " " in field else f"{field}.{name}") if field else name
            if value.get(name) is None:
                if key.endswith("?"):
                    continue
                raise SphereBenchError(f"{path}: {inner} is missing; {fix}")
            check_schema(path, value[name], sub, fix, inner)
    elif isinstance(schema, list):
        if not isinstance(value, list):
            raise SphereBenchError(f"{path}: {where} must be a list, not {_shown(value)}; {fix}")
        for i, item in enumerate(value):
            check_schema(path, item, schema[0], fix, f"{field}[{i}]")
    else:
        ok, what = _KINDS[schema]
        if not ok(value):
            raise SphereBenchError(f"{path}: {where} must be {what}, not {_shown(value)}; {fix}")
    return value


def read_checked_json(path: str | Path, schema, fix: str = "fix the file or rebuild the dataset"):
    """A JSON file (``read_json``) checked against ``schema`` (``check_schema``)."""
    return check_schema(path, read_json(path), schema, fix)


def check_ball_radius(value: float, what: str = "--radius") -> float:
    """A ball radius given on the command line (m), within BALL_RADIUS_RANGE_M, or a one-line error."""
    if not is_ball_radius(value):
        lo, hi = BALL_RADIUS_RANGE_M
        raise SphereBenchError(f"{what} {value:g}: a ball radius is {lo:g} to {hi:g} metres (e.g. 0.12 for a "
                               "basketball)")
    return float(value)


# --------------------------------------------------------------------------- images

def encode_png(image: np.ndarray, what: str, mark: bool = False) -> bytes:
    """uint8/uint16 image (grey or BGR) -> PNG bytes; ``mark``: with the mark of a file written for
    the user (``is_marked``)."""
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(image))
    if not ok:
        raise SphereBenchError(f"{what}: OpenCV could not encode this image as PNG")
    data = buf.tobytes()
    return data[:_PNG_HEADER_END] + _PNG_MARK_CHUNK + data[_PNG_HEADER_END:] if mark else data


def write_png(path: str | Path, image: np.ndarray) -> None:
    """uint8/uint16 image (grey or BGR) -> PNG, atomically."""
    atomic_write_bytes(path, encode_png(image, str(path)))


_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def _header_size(data: bytes) -> tuple[int, int] | None:
    """(width, height) px from a PNG's IHDR or a JPEG's frame header; None for another format or
    a header cut short (OpenCV then says what it makes of the file)."""
    if data[:8] == _PNG_SIGNATURE and data[12:16] == b"IHDR" and len(data) >= 24:
        return int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big")
    i = 2 if data[:2] == b"\xff\xd8" else len(data)
    while i + 9 <= len(data) and data[i] == 0xFF:
        marker = data[i + 1]
        if marker == 0xFF or 0xD0 <= marker <= 0xD8 or marker == 0x01:  # fill byte, markers with no length
            i += 1 if marker == 0xFF else 2
            continue
        if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC):  # a start of frame
            return int.from_bytes(data[i + 7:i + 9], "big"), int.from_bytes(data[i + 5:i + 7], "big")
        i += 2 + int.from_bytes(data[i + 2:i + 4], "big")
    return None


def _check_frame_size(path: Path, width: int, height: int) -> None:
    if max(width, height) > MAX_IMAGE_SIDE_PX:
        raise SphereBenchError(f"{path}: the image header says {width}x{height} px, beyond any depth camera's "
                               f"({MAX_IMAGE_SIDE_PX} px a side at most): the file is damaged or not a camera frame")


@functools.cache
def _quiet_opencv() -> None:
    """OpenCV's own log off, once per process: of a damaged image it prints WARN and ERROR lines of
    its decoder before _imread's one line says what is wrong and what to do."""
    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)


def _imread(path: Path, flags: int) -> np.ndarray:
    if not path.is_file():
        raise SphereBenchError(f"{path}: file not found")
    _quiet_opencv()
    data = np.fromfile(path, dtype=np.uint8)
    size = _header_size(data[:1 << 16].tobytes())
    if size is not None:
        _check_frame_size(path, *size)  # before OpenCV allocates the frame
    try:
        img = cv2.imdecode(data, flags) if data.size else None
    except cv2.error:  # e.g. an unknown format's header promising more than CV_IO_MAX_IMAGE_PIXELS
        img = None
    if img is None:
        raise SphereBenchError(f"{path}: not a readable image (corrupt or truncated?)")
    return img


def image_size(path: str | Path) -> tuple[int, int]:
    """(width, height) px of an image file, from its header where it is a PNG or JPEG (nothing
    decoded), else from the image read."""
    path = Path(path)
    if not path.is_file():
        raise SphereBenchError(f"{path}: file not found")
    with open(path, "rb") as f:
        size = _header_size(f.read(1 << 16))
    if size is None:
        img = _imread(path, cv2.IMREAD_UNCHANGED)
        return img.shape[1], img.shape[0]
    _check_frame_size(path, *size)
    return size


def check_scene_image(scene_dir: str | Path, intr: Intrinsics) -> None:
    """A scene's image.png is there and of its intrinsics' size (its circles are in those pixels):
    read from the header, nothing decoded."""
    path = Path(scene_dir) / "image.png"
    if not path.is_file():
        raise SphereBenchError(f"{scene_dir}: image.png is missing though the scene has an image (its gt.json, "
                               "coco_gt.json): the folder is damaged; rebuild the dataset with the command that wrote it")
    w, h = image_size(path)
    if (h, w) != intr.shape:
        raise SphereBenchError(f"{scene_dir}: image.png is {w}x{h} but the intrinsics say {intr.width}x{intr.height}: "
                               "the circles would be off the image; rebuild the dataset with the command that wrote it")


def read_image(path: str | Path) -> np.ndarray:
    """A reprojected image (H, W, 3) uint8 BGR; a scene folder gives its image.png."""
    path = Path(path)
    if path.is_dir():
        path = path / "image.png"
    img = _imread(path, cv2.IMREAD_COLOR)
    return img


def read_image_as_stored(path: str | Path) -> np.ndarray:
    """An image file as it is stored: any bit depth and channels (OpenCV's order: BGR, BGRA)."""
    return _imread(Path(path), cv2.IMREAD_UNCHANGED)


def write_depth_png(path: str | Path, depth: np.ndarray) -> None:
    """(H, W) uint16 depth counts -> 16-bit PNG."""
    d = np.asarray(depth)
    if d.dtype != np.uint16 or d.ndim != 2:
        raise SphereBenchError(f"{path}: depth must be a 2D uint16 array, got {d.dtype} {d.shape}")
    write_png(path, d)


def read_depth_png(path: str | Path) -> np.ndarray:
    """16-bit single-channel PNG -> (H, W) uint16 depth counts."""
    path = Path(path)
    d = _imread(path, cv2.IMREAD_UNCHANGED)
    if d.ndim != 2 or d.dtype != np.uint16:
        raise SphereBenchError(f"{path}: a depth PNG must be 16-bit single-channel, this one is "
                               f"{d.dtype} with shape {d.shape} (a colourised image is not depth)")
    return d


def write_mask_png(path: str | Path, mask: np.ndarray) -> None:
    write_png(path, np.asarray(mask, dtype=bool).astype(np.uint8) * 255)


def read_mask_png(path: str | Path, shape: tuple[int, int] | None = None) -> np.ndarray:
    """A mask PNG (any depth; non-zero = inside) -> (H, W) bool, checked against ``shape``."""
    path = Path(path)
    m = _imread(path, cv2.IMREAD_UNCHANGED)
    if m.ndim == 3:
        m = m[..., :3].max(axis=2) if m.shape[2] >= 3 else m[..., 0]
    if shape is not None and m.shape[:2] != tuple(shape):
        raise SphereBenchError(f"{path}: mask is {m.shape[1]}x{m.shape[0]} but the depth image is "
                               f"{shape[1]}x{shape[0]}: masks must be drawn on the scene's own image")
    return m > 0


# --------------------------------------------------------------------------- intrinsics

def write_intrinsics(path: str | Path, intr: Intrinsics) -> None:
    write_json(path, intr.to_dict())


#: intrinsics.json's real-valued fields, JSON numbers (a string such as "nan" is none): what is
#: missing, and the sizes, Intrinsics.from_dict words.
INTRINSICS_NUMBERS = {"ppx?": "number", "ppy?": "number", "fx?": "positive", "fy?": "positive",
                      "depth_scale?": "positive"}


def read_intrinsics(path: str | Path) -> Intrinsics:
    """intrinsics.json (pyrealsense2 field names; a scene folder gives its own)."""
    path = Path(path)
    if path.is_dir():
        path = path / "intrinsics.json"
    d = read_json(path)
    if not isinstance(d, dict):
        raise SphereBenchError(f"{path}: intrinsics must be a JSON object with width, height, ppx, ppy, fx, fy")
    check_schema(path, d, INTRINSICS_NUMBERS)
    try:
        return Intrinsics.from_dict(d)
    except SphereBenchError as exc:
        raise SphereBenchError(f"{path}: {exc}") from None


# --------------------------------------------------------------------------- point clouds

def write_cloud_ply(path: str | Path, cloud: Cloud) -> None:
    """Binary PLY: float32 x, y, z (m) and, for organised clouds, int32 row, col per point."""
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    if cloud.rows is not None:
        fields += [("row", "<i4"), ("col", "<i4")]
    v = np.empty(len(cloud), dtype=fields)
    v["x"], v["y"], v["z"] = cloud.points[:, 0], cloud.points[:, 1], cloud.points[:, 2]
    if cloud.rows is not None:
        v["row"], v["col"] = cloud.rows, cloud.cols
    _write_ply_vertices(path, v)


def encode_ply(points_m: np.ndarray, colors: np.ndarray | None = None) -> bytes:
    """Binary PLY of points (N, 3) m with optional colours (N, 3) uint8 RGB, for MeshLab, with the
    mark of a file written for the user (``is_marked``)."""
    p = np.asarray(points_m, dtype=np.float32).reshape(-1, 3)
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    if colors is not None:
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    v = np.empty(len(p), dtype=fields)
    v["x"], v["y"], v["z"] = p[:, 0], p[:, 1], p[:, 2]
    if colors is not None:
        c = np.asarray(colors, dtype=np.uint8).reshape(-1, 3)
        v["red"], v["green"], v["blue"] = c[:, 0], c[:, 1], c[:, 2]
    return _ply_bytes(v, comments=[_MARK.decode()])


def write_ply(path: str | Path, points_m: np.ndarray, colors: np.ndarray | None = None) -> None:
    """encode_ply, written atomically."""
    atomic_write_bytes(path, encode_ply(points_m, colors))


def _write_ply_vertices(path: str | Path, vertices: np.ndarray) -> None:
    atomic_write_bytes(path, _ply_bytes(vertices))


def _ply_bytes(vertices: np.ndarray, comments=()) -> bytes:
    buf = io.BytesIO()
    PlyData([PlyElement.describe(vertices, "vertex")], byte_order="<", comments=list(comments)).write(buf)
    return buf.getvalue()


def read_ply(path: str | Path, intrinsics: Intrinsics | None = None) -> Cloud:
    """PLY (ASCII or binary) -> Cloud; organised when the vertices carry row and col."""
    path = Path(path)
    if not path.is_file():
        raise SphereBenchError(f"{path}: file not found")
    try:
        ply = PlyData.read(str(path))
        v = ply["vertex"].data
        pts = np.stack([v["x"], v["y"], v["z"]], axis=1).astype(np.float32)
    except (KeyError, ValueError) as exc:
        raise SphereBenchError(f"{path}: not a PLY point cloud with x, y, z vertices ({exc})") from None
    except Exception as exc:  # plyfile raises several types on truncated data
        raise SphereBenchError(f"{path}: unreadable PLY, corrupt or truncated ({type(exc).__name__}: {exc})") from None
    names = v.dtype.names
    if "row" in names and "col" in names:
        return Cloud(pts, v["row"], v["col"], intrinsics)
    return Cloud(pts, intrinsics=intrinsics)


def read_xyz(path: str | Path) -> Cloud:
    """Plain-text point list, one 'x y z [...]' per line (metres), unorganised."""
    path = Path(path)
    if not path.is_file():
        raise SphereBenchError(f"{path}: file not found")
    try:
        with warnings.catch_warnings():  # an empty file: numpy warns, and detect() says what is wrong
            warnings.simplefilter("ignore", UserWarning)
            data = np.loadtxt(path, dtype=np.float64, ndmin=2, comments="#", usecols=(0, 1, 2))
    except (ValueError, IndexError) as exc:
        raise SphereBenchError(f"{path}: not an XYZ text file with three numbers per line ({exc})") from None
    with np.errstate(over="ignore"):  # beyond float32 becomes inf, a non-finite point like NaN: callers drop them
        return Cloud(data.astype(np.float32))


CLOUD_READERS = {".ply": read_ply, ".xyz": read_xyz, ".txt": read_xyz}


def load_cloud(path: str | Path, intrinsics: Intrinsics | None = None) -> Cloud:
    """A cloud from a PLY/PCD/XYZ file or a scene folder (which supplies its own intrinsics): its
    cloud.ply, else its depth.png deprojected (the `train` preset ships no clouds; the two give the
    same points where a scene has both)."""
    path = Path(path)
    if path.is_dir():
        intr = intrinsics
        if intr is None and (path / "intrinsics.json").is_file():
            intr = read_intrinsics(path / "intrinsics.json")
        if (path / "cloud.ply").is_file():
            return read_ply(path / "cloud.ply", intr)
        if (path / "depth.png").is_file() and intr is not None:
            return cloud_from_depth(depth_to_metres(read_depth_png(path / "depth.png"), intr), intr)
        raise SphereBenchError(f"{path}: a folder must be a scene folder with cloud.ply, or depth.png and "
                               "intrinsics.json, in it")
    reader = CLOUD_READERS.get(path.suffix.lower())
    if reader is None:
        raise SphereBenchError(f"{path}: unknown point-cloud format '{path.suffix}' "
                               f"(use {', '.join(sorted(CLOUD_READERS))} or a scene folder)")
    cloud = reader(path) if reader is not read_ply else read_ply(path, intrinsics)
    if intrinsics is not None and cloud.intrinsics is None:
        cloud.intrinsics = intrinsics
    return cloud


# --------------------------------------------------------------------------- scenes

def _circle(c) -> list[float] | None:
    return None if c is None else [float(x) for x in c]


def colour_file_name(source: str | Path | np.ndarray) -> str:
    """The name a scene keeps a colour frame under: colour.png for a PNG or an image (an array),
    else colour.jpg."""
    if isinstance(source, np.ndarray):
        return COLOUR_FILES[1]
    return COLOUR_FILES[1] if Path(source).suffix.lower() == ".png" else COLOUR_FILES[0]


def write_scene(scenes_dir: str | Path, scene: Scene, ball_radius_m: float, write_cloud: bool = True,
                colour: Path | np.ndarray | None = None) -> Path:
    """Write one scene folder atomically under ``scenes_dir``; returns its path.

    write_cloud=False leaves cloud.ply out (it is depth.png deprojected; the training split of
    learned 2D baselines has no use for it and it is most of a scene's size).
    colour: a JPEG or PNG colour frame registered to the depth, copied byte for byte as colour.jpg
    or colour.png, or an image (H, W, 3) uint8 BGR, written as colour.png (the caller checks its
    size)."""
    final = Path(scenes_dir) / scene.scene_id
    with atomic_directory(final, never_replace) as tmp:
        balls = []
        for k, ball in enumerate(scene.balls):
            entry = {
                "center_m": None if ball.center_m is None else [float(x) for x in ball.center_m],
                "radius_m": float(ball.radius_m),
                "visible_fraction": None if ball.visible_fraction is None else float(ball.visible_fraction),
                "circle": _circle(ball.circle_px),
                "amodal_circle": _circle(ball.amodal_circle_px),
                "mask": None,
                "silhouette": None,
            }
            if ball.center_source is not None:  # a recorded ball's centre: how it was obtained, its error
                entry["center_source"] = ball.center_source
                entry["center_se_m"] = None if ball.center_se_m is None else [float(x) for x in ball.center_se_m]
            if ball.mask is not None:
                entry["mask"] = f"mask_{k}.png"
                write_mask_png(tmp / entry["mask"], ball.mask)
            if ball.silhouette is not None:
                entry["silhouette"] = f"silhouette_{k}.png"
                write_mask_png(tmp / entry["silhouette"], ball.silhouette)
            balls.append(entry)
        gt = {"scene_id": scene.scene_id, "family": scene.family, "seed": scene.seed,
              "annotated": bool(scene.annotated), "ball_radius_m": float(ball_radius_m),
              "has_image": scene.depth is not None, "balls": balls, "meta": scene.meta}
        if scene.depth is not None:
            write_depth_png(tmp / "depth.png", scene.depth)
            write_png(tmp / "image.png", colorize_depth(scene.depth_m()))
        if scene.intrinsics is not None:
            write_intrinsics(tmp / "intrinsics.json", scene.intrinsics)
        if write_cloud or scene.depth is None:
            write_cloud_ply(tmp / "cloud.ply", scene.to_cloud())
        if isinstance(colour, np.ndarray):
            write_png(tmp / colour_file_name(colour), colour)
        elif colour is not None:
            shutil.copyfile(colour, tmp / colour_file_name(colour))
        write_json(tmp / "gt.json", gt)
    return final


#: gt.json (write_scene): what the readers of a scene rely on.
BALL_SCHEMA = {"radius_m": "positive", "center_m?": "xyz", "circle?": "circle", "amodal_circle?": "circle",
               "visible_fraction?": "fraction", "mask?": "text", "silhouette?": "text", "center_source?": "text",
               "center_se_m?": "xyz"}
GT_SCHEMA = {"scene_id": "text", "family": "text", "annotated?": "bool", "has_image?": "bool",
             "ball_radius_m?": "radius", "balls": [BALL_SCHEMA], "meta?": "object"}


def read_scene_gt(scene_dir: str | Path) -> dict:
    """A scene folder's gt.json, checked against GT_SCHEMA."""
    return read_checked_json(Path(scene_dir) / "gt.json", GT_SCHEMA)


def read_scene(scene_dir: str | Path, load_masks: bool = True) -> Scene:
    """A scene folder -> Scene (depth, intrinsics, balls with masks)."""
    scene_dir = Path(scene_dir)
    gt = read_scene_gt(scene_dir)
    intr = read_intrinsics(scene_dir / "intrinsics.json") if (scene_dir / "intrinsics.json").is_file() else None
    depth = read_depth_png(scene_dir / "depth.png") if (scene_dir / "depth.png").is_file() else None
    if depth is not None and intr is not None and depth.shape != intr.shape:
        raise SphereBenchError(f"{scene_dir}: depth.png is {depth.shape[1]}x{depth.shape[0]} but intrinsics.json "
                               f"says {intr.width}x{intr.height}")
    cloud = None if depth is not None else read_ply(scene_dir / "cloud.ply", intr)
    balls = []
    for b in gt.get("balls", []):
        mask = sil = None
        if load_masks and b.get("mask"):
            mask = read_mask_png(scene_dir / b["mask"], depth.shape if depth is not None else None)
        if load_masks and b.get("silhouette"):
            sil = read_mask_png(scene_dir / b["silhouette"], depth.shape if depth is not None else None)
        balls.append(Ball(radius_m=b["radius_m"], mask=mask, silhouette=sil,
                          center_m=None if b.get("center_m") is None else tuple(b["center_m"]),
                          circle_px=None if b.get("circle") is None else tuple(b["circle"]),
                          amodal_circle_px=None if b.get("amodal_circle") is None else tuple(b["amodal_circle"]),
                          visible_fraction=b.get("visible_fraction"), center_source=b.get("center_source"),
                          center_se_m=None if b.get("center_se_m") is None else tuple(b["center_se_m"])))
    return Scene(scene_id=gt["scene_id"], family=gt["family"], intrinsics=intr, depth=depth, balls=balls,
                 seed=gt.get("seed"), annotated=gt.get("annotated", True), cloud=cloud, meta=gt.get("meta", {}))


# --------------------------------------------------------------------------- datasets

def list_scenes(dataset_dir: str | Path) -> list[Path]:
    """Scene folders of a dataset, sorted by scene id."""
    scenes = Path(dataset_dir) / "scenes"
    if not scenes.is_dir():
        raise SphereBenchError(f"{dataset_dir}: not a dataset (no scenes/ folder); build one with "
                               "'spherebench generate' or 'spherebench prepare'")
    return sorted(p for p in scenes.iterdir() if p.is_dir() and not p.name.startswith("."))


#: dataset.json (finish_dataset): the fields its readers use.
DATASET_SCHEMA = {"name?": "text", "preset?": "text", "category?": "text", "ball_radius_m?": "radius"}


def read_dataset_meta(dataset_dir: str | Path) -> dict:
    """A dataset's dataset.json, checked against DATASET_SCHEMA."""
    return read_checked_json(Path(dataset_dir) / "dataset.json", DATASET_SCHEMA)


def scene_dataset_meta(scene_dir: str | Path) -> dict:
    """The dataset.json of the dataset a scene folder lies in (DIR/scenes/<id>), checked; {} for a
    scene of no dataset. Read by whatever reads such a scene, so that a damaged one is refused in
    one line, never passed over."""
    scene_dir = Path(scene_dir)
    dataset = scene_dir.parent.parent
    return read_dataset_meta(dataset) if scene_dir.parent.name == "scenes" and is_dataset_dir(dataset) else {}


def build_coco_gt(dataset_dir: str | Path, category: str = DEFAULT_CATEGORY, name: str | None = None) -> dict:
    """COCO ground truth with CircleNet's circle fields, from the scenes' gt.json files.

    Image ids are 1-based in scene-id order. Unannotated scenes and scenes without an image are
    left out (they cannot be scored in 2D). Each annotation: circle_center [x, y] and
    circle_radius (px) of the visible mask's smallest enclosing circle, area = pi r^2, bbox of
    the circle, the amodal circle under amodal_circle_center / amodal_circle_radius, and the 3D
    centre (center_m) when known.
    """
    images, annotations = [], []
    for scene_dir in list_scenes(dataset_dir):
        gt = read_scene_gt(scene_dir)
        if not gt.get("annotated", True) or not gt.get("has_image", True):
            continue
        intr = read_intrinsics(scene_dir / "intrinsics.json")
        image_id = len(images) + 1
        images.append({"id": image_id, "file_name": f"scenes/{scene_dir.name}/image.png", "width": intr.width,
                       "height": intr.height, "scene_id": gt["scene_id"], "family": gt["family"]})
        for ball in gt["balls"]:
            if ball.get("circle") is None:
                continue  # wholly hidden: nothing to see in 2D
            cx, cy, r = ball["circle"]
            ann = {"id": len(annotations) + 1, "image_id": image_id, "category_id": CATEGORY_ID,
                   "circle_center": [cx, cy], "circle_radius": r, "area": math.pi * r * r,
                   "bbox": [cx - r, cy - r, 2 * r, 2 * r], "iscrowd": 0}
            if ball.get("amodal_circle") is not None:
                ax, ay, ar = ball["amodal_circle"]
                ann["amodal_circle_center"], ann["amodal_circle_radius"] = [ax, ay], ar
            if ball.get("center_m") is not None:
                ann["center_m"] = ball["center_m"]
            if ball.get("visible_fraction") is not None:
                ann["visible_fraction"] = ball["visible_fraction"]
            annotations.append(ann)
    return {"info": {"description": f"SphereBench dataset {name or Path(dataset_dir).name}"},
            "images": images, "annotations": annotations,
            "categories": [{"id": CATEGORY_ID, "name": category, "supercategory": "ball"}]}


def finish_dataset(dataset_dir: str | Path, meta: dict) -> None:
    """Write coco_gt.json and dataset.json once every scene is in place."""
    coco = build_coco_gt(dataset_dir, meta.get("category", DEFAULT_CATEGORY), meta.get("name"))
    write_json(Path(dataset_dir) / "coco_gt.json", coco, indent=None)
    write_json(Path(dataset_dir) / "dataset.json", meta)


#: coco_gt.json (build_coco_gt): COCO's lists with CircleNet's circle fields.
COCO_GT_SCHEMA = {"images": [{"id": "int", "width": "size", "height": "size", "file_name?": "text",
                              "scene_id?": "text"}],
                  "annotations": [{"image_id": "int", "category_id?": "int", "circle_center": "xy",
                                   "circle_radius": "length"}],
                  "categories": [{"id": "int", "name?": "text"}]}


def read_coco_gt(dataset_dir: str | Path) -> dict:
    """A dataset's coco_gt.json, checked against COCO_GT_SCHEMA."""
    path = Path(dataset_dir) / "coco_gt.json"
    if not path.is_file():
        raise SphereBenchError(f"{dataset_dir}: no coco_gt.json: the dataset is incomplete; rebuild it")
    coco = read_checked_json(path, COCO_GT_SCHEMA)
    # what scoring would otherwise meet only after every method has run
    rebuild = "the file is damaged; rebuild the dataset with the command that wrote it (generate or prepare)"
    if not coco["categories"]:
        raise SphereBenchError(f"{path}: categories is empty (it names the ball's category); {rebuild}")
    ids = {im["id"] for im in coco["images"]}
    for i, ann in enumerate(coco["annotations"]):
        if ann["image_id"] not in ids:
            raise SphereBenchError(f"{path}: annotations[{i}].image_id is {ann['image_id']}, which no image has; "
                                   f"{rebuild}")
    return coco


# --------------------------------------------------------------------------- recorded-data readers
# (added for `spherebench prepare`: raw frames, lenient camera JSON, PCD, LabelMe, RealSense bags)

RAW_DTYPES = {"uint16": "u2", "float32": "f4"}
RAW_BYTE_ORDERS = {"little": "<", "big": ">"}


def read_raw_depth(path: str | Path, width: int, height: int, dtype: str = "uint16",
                   byte_order: str = "little") -> np.ndarray:
    """A headerless row-major depth frame -> (height, width) array of ``dtype`` (native byte order).

    The file must hold exactly width * height values; anything else means a truncated file or a
    wrong size/dtype, reported as such.
    """
    path = Path(path)
    if dtype not in RAW_DTYPES or byte_order not in RAW_BYTE_ORDERS:
        raise SphereBenchError(f"raw depth dtype must be one of {', '.join(RAW_DTYPES)} and byte order one of "
                               f"{', '.join(RAW_BYTE_ORDERS)}, got {dtype} {byte_order}")
    if not path.is_file():
        raise SphereBenchError(f"{path}: file not found")
    dt = np.dtype(RAW_BYTE_ORDERS[byte_order] + RAW_DTYPES[dtype])
    expected = int(width) * int(height) * dt.itemsize
    size = path.stat().st_size
    if size != expected:
        other = next(k for k in RAW_DTYPES if k != dtype)
        if size == int(width) * int(height) * np.dtype(RAW_DTYPES[other]).itemsize:
            raise SphereBenchError(f"{path}: {size} bytes, but a {width}x{height} {dtype} frame is {expected} bytes; "
                                   f"it is exactly a {width}x{height} {other} frame: try --raw-dtype {other}")
        raise SphereBenchError(f"{path}: {size} bytes, but a {width}x{height} {dtype} frame is {expected} bytes: "
                               "the file is truncated, or --raw-size/--raw-dtype are wrong")
    data = np.fromfile(path, dtype=dt).reshape(int(height), int(width))
    return data.astype(dt.newbyteorder("="))


def _distortion_name(model) -> str:
    """'Brown Conrady', 'distortion.brown_conrady', 'RS2_DISTORTION_BROWN_CONRADY' -> 'brown_conrady'."""
    name = str(model).strip().lower().replace(" ", "_").replace("-", "_")
    return name.removeprefix("rs2_distortion_").removeprefix("distortion.") or "none"


def read_camera_json(path: str | Path) -> Intrinsics:
    """Intrinsics from a JSON object in pyrealsense2's field names (width, height, ppx, ppy, fx, fy,
    model, coeffs; depth_scale optional) or a scene's intrinsics.json.

    More lenient than ``read_intrinsics``: the distortion model may be spelled as pyrealsense2
    prints it ('Brown Conrady', 'distortion.brown_conrady'), and the object may be wrapped as
    {"intrinsics": {...}} or {"depth": {...}}.
    """
    path = Path(path)
    d = read_json(path)
    if isinstance(d, dict) and "fx" not in d:
        for key in ("intrinsics", "depth"):
            if isinstance(d.get(key), dict):
                d = d[key]
                break
    if not isinstance(d, dict):
        raise SphereBenchError(f"{path}: intrinsics must be a JSON object with width, height, ppx, ppy, fx, fy")
    d = dict(d)
    if "model" in d:
        d["model"] = _distortion_name(d["model"])
    try:
        return Intrinsics.from_dict(d)
    except SphereBenchError as exc:
        raise SphereBenchError(f"{path}: {exc}") from None


# PCD (the Point Cloud Library's format, v0.7): ascii, binary and binary_compressed data, read by
# Open3D's tensor reader (NaN points kept). Its header is also read here: Open3D keeps no WIDTH and
# HEIGHT, which say whether the cloud is an organised depth grid.

def _pcd_header(path: Path) -> tuple[int, int]:
    """(WIDTH, HEIGHT) of a PCD file's header, checked before any point is read: x, y, z fields,
    POINTS = WIDTH x HEIGHT within a camera's frame (MAX_IMAGE_SIDE_PX a side), and data holding
    that many points (Open3D pads a file cut short with zeros)."""
    if not path.is_file():
        raise SphereBenchError(f"{path}: file not found")
    header: dict[str, list[str]] = {}
    with open(path, "rb") as f:
        while "DATA" not in header:
            raw = f.readline()
            if not raw.endswith(b"\n"):
                raise SphereBenchError(f"{path}: not a PCD file (no DATA line in the header; truncated?)")
            line = raw.decode("ascii", errors="replace").strip()
            if not line or line.startswith("#"):
                continue
            key, *values = line.split()
            header[key.upper()] = values
            if len(header) == 1 and key.upper() not in ("VERSION", "FIELDS"):
                raise SphereBenchError(f"{path}: not a PCD file (it starts with '{line[:40]}')")
        offset = f.tell()
    try:
        names = header["FIELDS"]
        width, height = int(header["WIDTH"][0]), int(header["HEIGHT"][0])
        n_points = int(header.get("POINTS", [width * height])[0])
        mode = header["DATA"][0].lower()
        counts = [int(c) for c in header.get("COUNT", ["1"] * len(names))]
        point_bytes = sum(int(b) * c for b, c in zip(header.get("SIZE", []), counts, strict=True))
    except (KeyError, IndexError, ValueError) as exc:
        raise SphereBenchError(f"{path}: PCD header is incomplete or malformed ({exc})") from None
    if not {"x", "y", "z"} <= set(names):
        raise SphereBenchError(f"{path}: PCD header must list x, y and z fields")
    if n_points != width * height:
        raise SphereBenchError(f"{path}: PCD says POINTS {n_points} but WIDTH x HEIGHT = {width}x{height}")
    if mode not in ("ascii", "binary", "binary_compressed"):
        raise SphereBenchError(f"{path}: unknown PCD DATA type '{mode}' (ascii, binary or binary_compressed)")
    if n_points > MAX_IMAGE_SIDE_PX ** 2 or (height > 1 and max(width, height) > MAX_IMAGE_SIDE_PX):
        raise SphereBenchError(f"{path}: PCD header promises {width}x{height} points, beyond any depth camera's "
                               f"frame ({MAX_IMAGE_SIDE_PX} px a side at most): the file is damaged")
    held = _pcd_points_held(path, mode, offset, point_bytes)
    if held < n_points:
        raise SphereBenchError(f"{path}: PCD data holds {held} points, the header promises {n_points}: the file "
                               "is truncated or corrupt")
    return width, height


def _pcd_points_held(path: Path, mode: str, offset: int, point_bytes: int) -> int:
    """How many points a PCD file's data (from ``offset``) holds: its non-blank lines (ascii), its
    bytes (binary) or its stated uncompressed size (binary_compressed, whose compressed bytes
    must all be there)."""
    size = path.stat().st_size - offset
    if mode == "ascii":
        with open(path, "rb") as f:
            f.seek(offset)
            return sum(1 for line in f if line.strip())
    if point_bytes <= 0:
        raise SphereBenchError(f"{path}: PCD header gives no SIZE of its fields, needed for {mode} data")
    if mode == "binary":
        return size // point_bytes
    with open(path, "rb") as f:
        f.seek(offset)
        stated = f.read(8)
    packed, unpacked = (int.from_bytes(stated[:4], "little"), int.from_bytes(stated[4:], "little"))
    return unpacked // point_bytes if len(stated) == 8 and size - 8 >= packed else 0


def _read_pcd(path: Path) -> tuple[Cloud, int, int]:
    """(cloud, width, height) of a PCD file; NaN points are dropped, an organised one keeps pixels."""
    width, height = _pcd_header(path)
    # here, not at the top: open3d takes seconds to import, only PCD files need it, and it is an extra
    o3d = require("open3d", "viz", "reading PCD files")
    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)  # its failures are ours to say
    pcd = o3d.t.io.read_point_cloud(str(path), remove_nan_points=False, remove_infinite_points=False)
    n = width * height
    xyz = pcd.point.positions.numpy().astype(np.float64) if "positions" in pcd.point else np.zeros((0, 3))
    if len(xyz) != n:
        raise SphereBenchError(f"{path}: PCD data holds {len(xyz)} points, the header promises {n}: the file "
                               "is truncated or corrupt")
    valid = np.all(np.isfinite(xyz), axis=1)
    idx = np.nonzero(valid)[0]
    pts = xyz[valid].astype(np.float32)
    if height > 1:
        return Cloud(pts, (idx // width).astype(np.int32), (idx % width).astype(np.int32)), width, height
    return Cloud(pts), width, height


def read_pcd(path: str | Path, intrinsics: Intrinsics | None = None) -> Cloud:
    """PCD (ascii, binary, binary_compressed) -> Cloud in the file's units (metres by convention).

    WIDTH x HEIGHT with HEIGHT > 1 is an organised cloud: point i is pixel (i // WIDTH, i % WIDTH)
    and NaN points are the invalid pixels (dropped, the others keep their row/col). Given
    intrinsics, an organised cloud's size must match them.
    """
    path = Path(path)
    cloud, width, height = _read_pcd(path)
    if intrinsics is not None:
        if cloud.rows is not None and (width, height) != (intrinsics.width, intrinsics.height):
            raise SphereBenchError(f"{path}: organised PCD is {width}x{height} but the intrinsics are "
                                   f"{intrinsics.width}x{intrinsics.height}: give the intrinsics of this camera")
        cloud.intrinsics = intrinsics
    return cloud


CLOUD_READERS[".pcd"] = read_pcd


#: A LabelMe file and each of its shapes: the keys SphereBench uses.
LABELME_SCHEMA = {"imagePath?": "text", "imageWidth": "size", "imageHeight": "size", "shapes": ["object"]}
LABELME_SHAPE_SCHEMA = {"label?": "text", "shape_type?": "text", "points": "list"}


def read_labelme(path: str | Path) -> dict:
    """A LabelMe annotation file -> its JSON object, checked for the keys SphereBench uses
    (imagePath, imageWidth, imageHeight, shapes with label, shape_type, points)."""
    path = Path(path)
    d = read_json(path)
    if not isinstance(d, dict) or not isinstance(d.get("shapes"), list):
        raise SphereBenchError(f"{path}: not a LabelMe file (no 'shapes' list)")
    fix = "fix the shape in LabelMe or remove it"
    check_schema(path, d, LABELME_SCHEMA, fix)
    for i, shape in enumerate(d["shapes"]):
        name = f"LabelMe shape {i} ({shape.get('shape_type') or 'polygon'} {shape.get('label')!r})"
        check_schema(path, shape, LABELME_SHAPE_SCHEMA, fix, name)
        for k, point in enumerate(shape["points"]):
            check_schema(path, point, "xy", fix, f"point {k} of {name}")
    return d


#: The first bytes of a recording by suffix, and what they are.
RECORDING_MAGIC = {".bag": (b"#ROSBAG V2.0\n", "ROS1 bag"), ".db3": (b"SQLite format 3\x00", "ROS2 SQLite")}


def import_pyrealsense2():
    """pyrealsense2 (the ``realsense`` extra), or one line saying how to install it."""
    return require("pyrealsense2", "realsense", "reading RealSense recordings and cameras (also: apt-get install "
                   "libusb-1.0-0)")


#: Colour formats of a recording's colour stream that prepare keeps (pyrealsense2's rs.format
#: names) -> OpenCV's conversion to BGR (None: already BGR) and bytes per pixel.
BAG_COLOUR_FORMATS = {"rgb8": (cv2.COLOR_RGB2BGR, 3), "bgr8": (None, 3), "rgba8": (cv2.COLOR_RGBA2BGR, 4),
                      "bgra8": (cv2.COLOR_BGRA2BGR, 4), "yuyv": (cv2.COLOR_YUV2BGR_YUY2, 2),
                      "uyvy": (cv2.COLOR_YUV2BGR_UYVY, 2)}
#: Depth frames held back while the colour frame after them has not arrived yet; beyond this many
#: the oldest is paired with the colour frames seen so far (a colour stream that stops early).
BAG_PENDING_DEPTH_FRAMES = 8
#: Colour frames kept for pairing (the latest ones).
BAG_COLOUR_HISTORY = 8
#: Timestamp jitter (ms) allowed beyond half a colour frame period when pairing colour with depth.
BAG_COLOUR_SLACK_MS = 1.0


@dataclass
class BagFrame:
    """One depth frame of a recording or a live camera and, when the recording has a usable colour
    stream, the colour frame nearest to it in time. index counts depth frames from 0; timestamps
    are the frames' own (ms). colour: (h, w, 3) uint8 BGR at the colour stream's own size; None, with
    ``no_colour`` saying why, when no colour frame lies within BagColour.max_offset_ms (the nearest
    is then still named by colour_number and colour_timestamp_ms) or the two streams' timestamps
    are in different clock domains. All colour fields stay None without a colour stream."""

    index: int
    number: int
    timestamp_ms: float
    depth: np.ndarray
    intrinsics: Intrinsics
    colour: np.ndarray | None = None
    colour_number: int | None = None
    colour_timestamp_ms: float | None = None
    no_colour: str | None = None


@dataclass(frozen=True)
class BagColour:
    """A recording's colour stream: format (BAG_COLOUR_FORMATS), intrinsics (depth_scale unused),
    the depth-to-colour extrinsics (a depth point p is at rotation @ p + translation in the colour
    camera's frame, metres; from the recording's profile.get_extrinsics_to) and the largest time
    offset (ms) of a colour frame paired with a depth frame: half a colour frame period (the
    farthest the nearest frame of a regular stream can be) plus BAG_COLOUR_SLACK_MS."""

    format: str
    intrinsics: Intrinsics
    rotation: tuple[tuple[float, float, float], ...]
    translation: tuple[float, float, float]
    fps: int
    max_offset_ms: float


class BagRecording:
    """A RealSense recording (.bag, ROS1; .db3, ROS2) opened for pyrealsense2 playback: its depth
    stream, and its colour stream when it has one that can be kept (``colour``; else ``colour_note``
    says why there is none). Opening reads the file's description only; ``frames`` plays it back.

    The sensors are started directly (not through rs.pipeline, which drops frames when the consumer
    is slower than the file) with non-real-time playback and a small blocking queue: the playback
    thread waits for each frame to be taken, so none is lost and memory stays bounded. Colour is
    paired with depth by timestamp here, not by rs.syncer, which may emit a frame alone or drop it.
    """

    def __init__(self, path: str | Path):
        self.path = path = Path(path)
        if not path.is_file():
            raise SphereBenchError(f"{path}: file not found")
        magic, kind = RECORDING_MAGIC.get(path.suffix.lower(), (b"", ""))
        with path.open("rb") as f:
            head = f.read(len(magic))
        if head != magic:  # refused before librealsense starts (it writes ~/.rum/rum.json)
            raise SphereBenchError(f"{path}: not a RealSense recording (no {kind} header): "
                                   "give a .bag or .db3 file recorded by a RealSense camera")
        rs = import_pyrealsense2()
        try:
            self._device = rs.context().load_device(str(path))
            sensors = self._device.query_sensors()
            streams = [(i, s, p) for i, s in enumerate(sensors) for p in s.get_stream_profiles()]
        except RuntimeError as exc:
            raise SphereBenchError(f"{path}: not a readable RealSense recording, or one cut short ({exc})") from None
        depth = [(i, s, p) for i, s, p in streams if s.is_depth_sensor() and p.stream_type() == rs.stream.depth]
        if not depth:
            found = ", ".join(sorted({str(p.stream_type()).removeprefix("stream.") for *_, p in streams})) or "none"
            raise SphereBenchError(f"{path}: the recording has no depth stream (streams: {found}); "
                                   "record with depth enabled")
        self._depth_index, self._depth_sensor, self._depth_profile = depth[0]
        if self._depth_profile.format() != rs.format.z16:
            raise SphereBenchError(f"{path}: the depth stream is {self._depth_profile.format()}, "
                                   "only z16 depth is supported")
        self.depth_scale = float(self._depth_sensor.as_depth_sensor().get_depth_scale())
        self.colour: BagColour | None = None
        self.colour_note: str | None = None
        self._colour_index = self._colour_sensor = self._colour_profile = None
        colour = [(i, s, p) for i, s, p in streams if p.stream_type() == rs.stream.color]
        if not colour:
            self.colour_note = (f"{path.name}: the recording has no colour stream: its scenes keep no colour frame "
                                "(annotate --from-colour needs one)")
            return
        sensor_index, sensor, profile = colour[0]
        fmt = str(profile.format()).removeprefix("format.")
        if fmt not in BAG_COLOUR_FORMATS:
            self.colour_note = (f"{path.name}: the colour stream is {fmt}, which prepare does not convert "
                                f"({', '.join(BAG_COLOUR_FORMATS)}): its scenes keep no colour frame")
            return
        try:
            ext = self._depth_profile.get_extrinsics_to(profile)
            c_intr = profile.as_video_stream_profile().get_intrinsics()
            intr = Intrinsics.from_rs(c_intr, 1.0)
        except (RuntimeError, SphereBenchError) as exc:
            self.colour_note = (f"{path.name}: the colour stream's calibration cannot be used ({exc}): "
                                "its scenes keep no colour frame")
            return
        r = [float32_decimal(v) for v in ext.rotation]  # column-major, as rs2_extrinsics
        self.colour = BagColour(format=fmt, intrinsics=intr,
                                rotation=tuple((r[i], r[3 + i], r[6 + i]) for i in range(3)),
                                translation=tuple(float32_decimal(v) for v in ext.translation), fps=int(profile.fps()),
                                max_offset_ms=(500.0 / profile.fps() if profile.fps() > 0 else math.inf)
                                + BAG_COLOUR_SLACK_MS)
        self._colour_index, self._colour_sensor, self._colour_profile = sensor_index, sensor, profile

    def frames(self, stop_after: int | None = None, stall_timeout_s: float = 10.0, real_time: bool = False,
               with_colour: bool = True):
        """BagFrames in recording order; stop_after: stop once this many have been yielded;
        with_colour=False plays the depth stream alone (a detector needs no colour).

        real_time: play at the recording's rate, as a camera would deliver it: a frame that
        arrives while the consumer is still busy with earlier ones is dropped (counted in
        ``self.dropped``, by stream: "depth", "colour") rather than waited for."""

        rs = import_pyrealsense2()
        path = self.path
        playback = self._device.as_playback()
        playback.set_real_time(bool(real_time))
        items: queue.Queue = queue.Queue(maxsize=2 if real_time else 4)  # real time: hold little, drop the rest
        stopping = threading.Event()
        self.dropped = {"depth": 0, "colour": 0}
        colour = self.colour if with_colour else None
        convert, bpp = BAG_COLOUR_FORMATS[colour.format] if colour is not None else (None, 0)

        def on_frame(frame) -> None:
            # copy out and release the frame at once: librealsense's frame pool is small
            vp = frame.get_profile().as_video_stream_profile()
            is_depth = vp.stream_type() == rs.stream.depth
            data = np.asanyarray(frame.get_data())
            image = np.array(data, dtype=np.uint16, copy=True) if is_depth else np.array(data, copy=True)
            item = (is_depth, int(frame.get_frame_number()), float(frame.get_timestamp()), image,
                    vp.get_intrinsics() if is_depth else (vp.width(), vp.height()),
                    str(frame.get_frame_timestamp_domain()))
            if real_time:
                try:
                    items.put_nowait(item)
                except queue.Full:
                    self.dropped["depth" if is_depth else "colour"] += 1
                return
            while not stopping.is_set():
                try:
                    items.put(item, timeout=0.05)
                    return
                except queue.Full:
                    continue

        # each sensor opens all of its streams at once (a D405's colour is on its depth sensor)
        opened = [(self._depth_sensor, [self._depth_profile])]
        if colour is not None:
            if self._colour_index == self._depth_index:
                opened[0][1].append(self._colour_profile)
            else:
                opened.append((self._colour_sensor, [self._colour_profile]))
        started = []
        try:
            if colour is not None:
                playback.pause()  # until every sensor is started: none misses the first frames
            for sensor, profiles in opened:
                sensor.open(profiles if len(profiles) > 1 else profiles[0])
                sensor.start(on_frame)
                started.append(sensor)
            if colour is not None:
                playback.resume()
        except RuntimeError as exc:
            _stop_sensors(started)
            raise SphereBenchError(f"{path}: pyrealsense2 cannot play the recording back ({exc})") from None

        pending: collections.deque = collections.deque()  # depth items waiting for a later colour frame
        recent: collections.deque = collections.deque(maxlen=BAG_COLOUR_HISTORY)  # colour items
        domains: dict[str, str] = {}
        index = 0

        def paired(depth_item):
            nonlocal index
            number, stamp, image, rs_intr = depth_item
            frame = BagFrame(index, number, stamp, image, Intrinsics.from_rs(rs_intr, self.depth_scale))
            index += 1
            if colour is None:
                return frame
            if not recent:
                frame.no_colour = "no colour frame was recorded up to it"
                return frame
            if domains["depth"] != domains["colour"]:
                frame.no_colour = (f"its timestamp and the colour stream's are in different clock domains "
                                   f"({domains['depth'].removeprefix('timestamp_domain.')}, "
                                   f"{domains['colour'].removeprefix('timestamp_domain.')}): they cannot be paired")
                return frame
            # the colour stream is in time order: the first frame at or after the depth and the one before it
            after = next((i for i, c in enumerate(recent) if c[1] >= stamp), None)
            candidates = [recent[-1]] if after is None else [recent[after]] + ([recent[after - 1]] if after else [])
            best = min(candidates, key=lambda c: (abs(c[1] - stamp), c[1]))
            frame.colour_number, frame.colour_timestamp_ms = best[0], best[1]
            if abs(best[1] - stamp) <= colour.max_offset_ms:
                frame.colour = best[2]
            else:
                frame.no_colour = (f"the nearest colour frame is {abs(best[1] - stamp):.1f} ms away, more than "
                                   f"half a colour frame period and {BAG_COLOUR_SLACK_MS:g} ms "
                                   f"({colour.max_offset_ms:.1f} ms; a colour frame was lost?)")
            return frame

        def ready(final: bool = False):
            while pending and (final or colour is None or len(pending) > BAG_PENDING_DEPTH_FRAMES
                               or (recent and recent[-1][1] >= pending[0][1])):
                yield paired(pending.popleft())

        try:
            idle_s, step_s, last = 0.0, 0.05, {}
            while stop_after is None or index < stop_after:
                try:
                    is_depth, number, stamp, image, rs_intr, domain = items.get(timeout=step_s)
                except queue.Empty:
                    idle_s += step_s
                    if playback.current_status() == rs.playback_status.stopped and items.empty() and idle_s > 0.2:
                        break
                    if idle_s > stall_timeout_s:
                        raise SphereBenchError(f"{path}: playback stalled for {stall_timeout_s:g} s; "
                                               "the file may be damaged")
                    continue
                idle_s = 0.0
                kind = "depth" if is_depth else "colour"
                if last.get(kind) == (number, stamp):
                    continue
                last[kind] = (number, stamp)
                domains.setdefault(kind, domain)
                if is_depth:
                    pending.append((number, stamp, image, rs_intr))
                else:
                    recent.append((number, stamp, _colour_to_bgr(image, *rs_intr, bpp, convert, path)))
                for frame in ready():
                    yield frame
                    if stop_after is not None and index >= stop_after:
                        return
            for frame in ready(final=True):
                if stop_after is not None and frame.index >= stop_after:
                    return
                yield frame
        finally:
            stopping.set()
            _stop_sensors(started)


def _colour_to_bgr(data: np.ndarray, width: int, height: int, bpp: int, convert, path: Path) -> np.ndarray:
    """A colour frame's pixels (BAG_COLOUR_FORMATS, any array shape) -> (height, width, 3) uint8 BGR."""
    raw = np.ascontiguousarray(data).view(np.uint8).reshape(-1)
    if raw.size != width * height * bpp:
        raise SphereBenchError(f"{path}: a colour frame holds {raw.size} bytes, not the {width}x{height}x{bpp} of "
                               "its stream: the file is damaged")
    raw = raw.reshape(height, width, bpp)
    return raw.copy() if convert is None else cv2.cvtColor(raw, convert)


def _stop_sensors(sensors) -> None:
    for sensor in sensors:
        try:
            sensor.stop()
            sensor.close()
        except RuntimeError:
            pass  # already stopped at the end of the file


# --------------------------------------------------------------------------- detection records
#
# One JSON schema for every detector's output, 3D and 2D alike (docs/formats.md): what
# `spherebench detect` and `detect-2d` print, one line per input or frame.

def detection_record(score: float, circle_px=None, center_m=None, radius_m: float | None = None,
                     inliers: int | None = None, visible_fraction: float | None = None) -> dict:
    """One detection: score; circle_px {center [cx, cy], radius} px (None: it projects nowhere on
    the image) with its COCO bbox [x, y, w, h] px; center_m [x, y, z] and radius_m, metres, camera
    frame (None from a 2D detector); inliers, the points on the sphere, and visible_fraction, the
    share of its silhouette no nearer surface hides (None from a 2D detector or an unorganised cloud)."""
    circle = None if circle_px is None else [float(v) for v in circle_px[:3]]
    return {"score": round(float(score), 6),
            "center_m": None if center_m is None else [round(float(v), 6) for v in center_m],
            "radius_m": None if radius_m is None else round(float(radius_m), 6),
            "circle_px": None if circle is None else {"center": [round(circle[0], 3), round(circle[1], 3)],
                                                      "radius": round(circle[2], 3)},
            "bbox": None if circle is None else circle_bbox(*circle, decimals=3),
            "inliers": None if inliers is None else int(inliers),
            "visible_fraction": None if visible_fraction is None else round(float(visible_fraction), 3)}


def frame_record(source: str, detections: list[dict], ms: float, frame: int | None = None,
                 timestamp_ms: float | None = None, **extra) -> dict:
    """One input's (or one stream frame's) line: source, frame number and timestamp (ms; None for a
    file), detections (``detection_record``s, best first), ms (the detection alone), and any extra
    fields of the command (e.g. radius_m)."""
    return {"input": str(source), "frame": None if frame is None else int(frame),
            "timestamp_ms": None if timestamp_ms is None else round(float(timestamp_ms), 3),
            **extra, "detections": detections, "ms": round(float(ms), 3)}
