"""argparse types shared by the subcommands: each turns bad text into argparse's one-line usage error."""

from __future__ import annotations

import argparse


def seed(text: str) -> int:
    """A run seed: an integer from 0 (numpy's SeedSequence takes no negative seed)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not an integer seed") from None
    if value < 0:
        raise argparse.ArgumentTypeError(f"{value}: a seed is an integer from 0 up")
    return value


def out_path(text: str) -> str:
    """An output path: never empty (an unset shell variable in `--out "$OUT"` would mean the current
    folder)."""
    if not text.strip():
        raise argparse.ArgumentTypeError("is empty (an unset shell variable?): give the path to write")
    return text
