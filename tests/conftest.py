"""Shared fixtures: small generated datasets, built once per test session."""

from __future__ import annotations

import re

import pytest

from spherebench import caches

# the command's cache folders for the tests that run in this process too, before numba is imported:
# the kernels are compiled once for both, and the commands run as subprocesses inherit them
caches.use_cache_folder()

from spherebench.datasets import simulate  # noqa: E402


@pytest.fixture(scope="session")
def paper_dataset(tmp_path_factory):
    """The paper preset (3 scenes, 424x240)."""
    return simulate.generate_dataset("paper", tmp_path_factory.mktemp("data") / "paper", progress=False)


@pytest.fixture(scope="session")
def small_default(tmp_path_factory):
    """Six scenes of the default preset (3 clean, 3 cluttered)."""
    return simulate.generate_dataset("default", tmp_path_factory.mktemp("data") / "default6", n=6, progress=False)


def markdown_cells(text: str) -> str:
    """Markdown with every table cell's padding reduced to one space: pandas pads a column's cells
    to one width, and a test looks for the cells' text."""
    return re.sub(r" +\|", " |", re.sub(r"\| +", "| ", text))
