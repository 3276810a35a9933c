"""matplotlib for files: the figures of the benchmark and of training are drawn through ``pyplot``."""

from __future__ import annotations


def pyplot():
    """matplotlib's pyplot on the Agg backend (files only), imported at the first figure drawn: its
    import builds matplotlib's font cache in the user's cache folder (``~/.cache/matplotlib``), which
    a command that refuses its input, or draws nothing, has no reason to do."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt
