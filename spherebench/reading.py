"""The reading gate: every JSON file and JSON text that SphereBench takes goes through ``read_json``
or ``parse_json``, which bound what a file may hold before any reader looks at it (its size, its
integers' digits, its nesting) and turn whatever is no JSON into one line naming the file. The
readers then check the values against their schema (``datasets.inout.check_schema``): types,
finiteness and ranges, naming the field.
"""

from __future__ import annotations

import json
from pathlib import Path

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
    or a folder, one line."""
    path = Path(path)
    try:
        size = path.stat().st_size
        if size > MAX_JSON_BYTES:
            raise _too_big(str(path), size)
        with open(path, "rb") as f:
            data = f.read()
    except FileNotFoundError:
        raise SphereBenchError(f"{path}: file not found") from None
    except IsADirectoryError:
        raise SphereBenchError(f"{path}: is a folder, not a JSON file") from None
    except PermissionError:
        raise SphereBenchError(f"{path}: not readable (permission denied)") from None
    return parse_json(data, str(path))
