"""The reading gate: every JSON file and JSON text that SphereBench takes goes through ``read_json``
or ``parse_json``, which bound what a file may hold before any reader looks at it (its size, its
integers' digits, its nesting) and turn whatever is no JSON into one line naming the file. The
readers then check the values against their schema (``check_schema``): types, finiteness and
ranges, naming the field.
"""

from __future__ import annotations

import json
import math
import stat
from pathlib import Path

from spherebench.camera import MAX_IMAGE_SIDE_PX
from spherebench.errors import SphereBenchError

#: The reading gate's limits (``parse_json``): a file larger than this is no file of SphereBench's
#: (a 20,000-scene dataset's coco_gt.json is about 10 MB; a benchmark's predictions about 50 MB) ...
MAX_JSON_BYTES = 1 << 30
#: ... nor one with an integer of more digits (a uint64 seed has 20): no count, size or seed is longer.
#: Nesting is bounded by the parser's own recursion guard (about a thousand levels; ours go six deep).
MAX_JSON_INT_DIGITS = 20


class _TooLong(ValueError):
    pass


def _bounded_int(text: str) -> int:
    digits = len(text.lstrip("-"))
    if digits > MAX_JSON_INT_DIGITS:
        raise _TooLong(digits)
    return int(text)


def _too_big(source: str, size: int) -> SphereBenchError:
    return SphereBenchError(f"{source}: {size:,} bytes, more than a JSON file of SphereBench holds "
                            f"({MAX_JSON_BYTES:,}); is it the right file?")


def parse_json(data: bytes | str, source: str):
    """JSON text through the reading gate: at most MAX_JSON_BYTES, integers of at most
    MAX_JSON_INT_DIGITS digits, nested no deeper than the parser's recursion guard; anything else,
    or text that is no JSON, a one-line SphereBenchError naming ``source``. NaN and Infinity parse
    as floats: what may not be infinite is the schema's to refuse (``check_schema``)."""
    if len(data) > MAX_JSON_BYTES:
        raise _too_big(source, len(data))
    try:
        return json.loads(data, parse_int=_bounded_int)
    except _TooLong as exc:
        raise SphereBenchError(f"{source}: an integer of {exc.args[0]} digits, longer than any count, size or "
                               f"seed ({MAX_JSON_INT_DIGITS}); fix the file") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise SphereBenchError(f"{source}: not valid JSON ({exc}); is the file truncated?") from None
    except RecursionError:
        raise SphereBenchError(f"{source}: nested deeper than the JSON reader goes (about 1,000 levels; a file "
                               "of SphereBench goes six); is it the right file?") from None
    except (MemoryError, ValueError) as exc:
        raise SphereBenchError(f"{source}: cannot be read as JSON ({type(exc).__name__}); is it the right "
                               "file?") from None


def read_json(path: str | Path):
    """A JSON file through the reading gate (``parse_json``); a missing, unreadable or oversized file,
    a folder, or no regular file (a FIFO would hold the reader until something writes to it), one
    line."""
    path = Path(path)
    try:
        st = path.stat()
        if stat.S_ISDIR(st.st_mode):
            raise IsADirectoryError
        if not stat.S_ISREG(st.st_mode):
            raise SphereBenchError(f"{path}: not a regular file (a FIFO, a device or a socket): give a JSON file")
        if st.st_size > MAX_JSON_BYTES:
            raise _too_big(str(path), st.st_size)
        with open(path, "rb") as f:
            data = f.read()
    except FileNotFoundError:
        raise SphereBenchError(f"{path}: file not found") from None
    except IsADirectoryError:
        raise SphereBenchError(f"{path}: is a folder, not a JSON file") from None
    except PermissionError:
        raise SphereBenchError(f"{path}: not readable (permission denied)") from None
    return parse_json(data, str(path))


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


def shown(value, spell=json.dumps) -> str:
    """A value in a one-line message, spelt by ``spell`` (as a JSON file spells it, or ``repr`` as
    Python does), or what it is where that is long (a 120 KB --set value is not repeated back)."""
    try:
        text = spell(value)
    except (TypeError, ValueError):
        text = repr(value)
    if len(text) <= 40:
        return text
    return "a JSON object" if isinstance(value, dict) else "a list" if isinstance(value, list) else text[:37] + "..."


def check_schema(path: str | Path, value, schema, fix: str = "fix the file or rebuild the dataset", field: str = ""):
    """``value``, read from ``path``, checked against ``schema`` (above); returned as it is. A
    SphereBenchError names the file, the first wrong field (as balls[0].radius_m) and ``fix``."""
    where = field or "the file"
    if isinstance(schema, dict):
        if not isinstance(value, dict):
            raise SphereBenchError(f"{path}: {where} must be a JSON object, not {shown(value)}; {fix}")
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
            raise SphereBenchError(f"{path}: {where} must be a list, not {shown(value)}; {fix}")
        for i, item in enumerate(value):
            check_schema(path, item, schema[0], fix, f"{field}[{i}]")
    else:
        ok, what = _KINDS[schema]
        if not ok(value):
            raise SphereBenchError(f"{path}: {where} must be {what}, not {shown(value)}; {fix}")
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
