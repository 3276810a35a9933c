"""argparse types shared by the subcommands: each turns bad text into argparse's one-line usage error."""

from __future__ import annotations

import argparse


def _integer(text: str, least: int, what: str, too_small: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not an integer{what}") from None
    if value < least:
        raise argparse.ArgumentTypeError(f"{value}: {too_small}")
    return value


def seed(text: str) -> int:
    """A run seed: an integer from 0 (numpy's SeedSequence takes no negative seed)."""
    return _integer(text, 0, " seed", "a seed is an integer from 0 up")


def count(text: str) -> int:
    """A positive count (scenes, passes): an integer from 1."""
    return _integer(text, 1, "", "give 1 or more")


def out_path(text: str) -> str:
    """An output path: never empty (an unset shell variable in `--out "$OUT"` would mean the current
    folder)."""
    if not text.strip():
        raise argparse.ArgumentTypeError("is empty (an unset shell variable?): give the path to write")
    return text
