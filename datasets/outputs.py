"""What SphereBench may write and replace, and how it writes so that nothing is left half-done.

The tool replaces only what it wrote: an output folder is replaced when it is empty or holds the
marker of its kind (a dataset's dataset.json, a results or training folder's OWNER_MARKER), a
report's OUT.json when it names the report's kind, a file for the user to look at when it carries
the mark (is_marked), and each is refused otherwise; nothing is written inside a dataset but by
generate and prepare. A file is written to a temporary name and renamed (atomic_write_bytes);
several files are written all or nothing (replace_files); a scene folder and a whole dataset are
built under a temporary name and renamed when complete (atomic_directory). Temporaries are
siblings named .tmp-<name>.*; a temporary folder records the process that made it, so that a
later run can remove one whose process died (SIGKILL, power).

The file formats themselves are ``spherebench.datasets.inout``'s; it writes through this module.
"""

from __future__ import annotations

import contextlib
import glob
import json
import math
import os
import shutil
import socket
import stat
import tempfile
import zlib
from pathlib import Path

from spherebench.errors import SphereBenchError
from spherebench.reading import read_json

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
MARK = b"written by spherebench"
#: The first bytes of every PNG file.
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_PNG_MARK_CHUNK = (len(b"Software\x00" + MARK).to_bytes(4, "big") + b"tEXtSoftware\x00" + MARK
                   + zlib.crc32(b"tEXtSoftware\x00" + MARK).to_bytes(4, "big"))
_PNG_HEADER_END = 33  # the signature (8 bytes) and the IHDR chunk (25)


def mark_png(data: bytes) -> bytes:
    """A PNG file's bytes with the mark: its tEXt chunk right after the header."""
    return data[:_PNG_HEADER_END] + _PNG_MARK_CHUNK + data[_PNG_HEADER_END:]


def is_marked(path: Path) -> bool:
    """A PNG or PLY that a command wrote with the mark (``mark_png``; inout's encode_png with
    ``mark``, encode_ply)."""
    try:
        with open(path, "rb") as f:
            head = f.read(4096)
    except OSError:
        return False
    if head.startswith(PNG_SIGNATURE):
        return head[_PNG_HEADER_END:_PNG_HEADER_END + len(_PNG_MARK_CHUNK)] == _PNG_MARK_CHUNK
    if head.startswith(b"ply"):
        return b"\ncomment " + MARK + b"\n" in head.split(b"end_header")[0].replace(b"\r\n", b"\n")
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
        old = read_json(js)
    except SphereBenchError:
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


def is_dataset_dir(path: Path) -> bool:
    """A folder that `generate` or `prepare` wrote (its dataset.json)."""
    return (Path(path) / "dataset.json").is_file()


# The names of what generate and prepare write in a dataset (inout writes the files): a dataset
# holding anything else is never replaced.
_DATASET_FILES = {"dataset.json", "coco_gt.json", "scenes", "sequences", OWNER_MARKER}
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


def write_owner_marker(folder: str | Path, kind: str) -> None:
    """Mark ``folder`` as a SphereBench output of ``kind`` (its OWNER_MARKER, which owned_by_kind reads)."""
    marker = {"kind": kind, "written_by": "spherebench"}
    atomic_write_bytes(Path(folder) / OWNER_MARKER, (json.dumps(marker, indent=1) + "\n").encode())


def owned_by_kind(kind: str, legacy: str | None = None):
    """A test for folders a command fills over time: its OWNER_MARKER names ``kind``, or (written before
    the marker existed) it holds the file ``legacy``."""
    def is_ours(path: Path) -> bool:
        marker = Path(path) / OWNER_MARKER
        if marker.is_file():
            with contextlib.suppress(SphereBenchError, AttributeError):
                return read_json(marker).get("kind") == kind
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
        write_owner_marker(path, kind)
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
    parents = missing_parents(Path(path))
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
            remove_if_empty(parents)
        raise


def _stale_temporaries(final: Path):
    """Temporary folders of ``final`` whose process on this machine has ended."""
    for tmp in final.parent.glob(f".tmp-{glob.escape(final.name)}.*"):
        owner = tmp / _TMP_OWNER
        try:
            info = read_json(owner)
            pid, host = int(info["pid"]), str(info["host"])
        except (SphereBenchError, ValueError, KeyError, TypeError):
            continue  # not ours, or not readable: leave it
        if host != socket.gethostname() or pid == os.getpid():
            continue
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            yield tmp
        except PermissionError:
            pass  # alive, another user's


def missing_parents(path: Path) -> list[Path]:
    """The folders above ``path`` that do not exist yet, nearest first: what making it creates."""
    out = []
    for parent in Path(path).absolute().parents:
        if parent.exists():
            break
        out.append(parent)
    return out


def remove_if_empty(folders) -> None:
    """Remove each folder of ``folders`` (nearest first) that is empty: the parents a stopped or
    failed run created for an output it did not finish, and nothing anyone put there since."""
    for folder in folders:
        try:
            folder.rmdir()
        except OSError:  # not empty, or gone: what is there is kept
            return


@contextlib.contextmanager
def atomic_directory(final: str | Path, is_ours):
    """Yield a temporary sibling folder; on success it replaces ``final``, on error (or a signal turned
    into KeyboardInterrupt) it is removed. ``final`` is replaced only if it is empty or ``is_ours``
    recognises it (see check_output_dir); stale temporaries of ``final`` from dead runs are removed."""
    final = check_output_dir(final, is_ours)
    made = missing_parents(final)
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
        remove_if_empty(made)
        if isinstance(exc, OSError) and exc.filename is None:  # a write's error (a full disk) names no file
            raise named_error(exc, final) from None
        raise
