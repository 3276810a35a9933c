"""The resolution study of `make eval` (``eval.bench.resolution``): one scene per depth mode, its
layouts shared, the detector and its ceiling scored, the table's cells."""

from __future__ import annotations

import numpy as np
import pytest

from spherebench.datasets import inout, presets, simulate
from spherebench.errors import SphereBenchError
from spherebench.eval.bench import resolution


@pytest.fixture(scope="module")
def one_per_mode(tmp_path_factory):
    """`default-stereo`'s first two scenes at each depth mode, under one data folder."""
    data = tmp_path_factory.mktemp("data")
    for preset in resolution.RESOLUTION_PRESETS.values():
        simulate.generate_dataset(preset, data / preset, n=2, progress=False)
    return data


def test_the_modes_share_their_layouts(one_per_mode):
    chosen = [presets.PRESETS[p] for p in resolution.RESOLUTION_PRESETS.values()]
    assert all(p.resolution_of == "default-stereo" and p.code == chosen[0].code for p in chosen[1:])
    centres, sizes = {}, {}
    for mode, preset in resolution.RESOLUTION_PRESETS.items():
        scenes = inout.list_scenes(one_per_mode / preset)
        gts = [inout.read_scene_gt(s) for s in scenes]
        centres[mode] = np.array([b["center_m"] for gt in gts for b in gt["balls"]])
        sizes[mode] = {(i.width, i.height) for i in (inout.read_intrinsics(s / "intrinsics.json") for s in scenes)}
    assert sizes == {"424x240": {(424, 240)}, "848x480": {(848, 480)}, "1280x720": {(1280, 720)}}
    for mode in ("848x480", "1280x720"):  # the ball drawn in view: the image's border moves it a few mm
        assert centres[mode].shape == centres["424x240"].shape
        assert np.abs(centres[mode] - centres["424x240"]).max() < 0.01


def test_study_scores_the_detector_and_its_ceiling_per_mode(one_per_mode, tmp_path):
    sets = resolution.resolution_study(one_per_mode, tmp_path / "out", workers=1, log=lambda *_: None)
    assert list(sets) == list(resolution.RESOLUTION_PRESETS)
    assert all([s.output for s in scored] == list(resolution.METHODS) for scored in sets.values())
    table = resolution.resolution_table(sets)
    assert table.name == "resolution" and len(table.rows) == 6
    for row in table.rows:
        assert row[2] == "2"  # two balls per mode
        shares = [float(c.split(" (")[0]) for c in row[3:7] if c != "–"]
        assert shares and all(0.0 <= x <= 1.0 for x in shares)
        assert sum(int(c.split("(")[1].rstrip(")")) for c in row[3:7] if c != "–") == 2
    ceiling = [r for r in table.rows if r[1] == "own-pixel-fit"]
    assert all(r[-1] == "–" for r in ceiling) and all(r[-1] != "–" for r in table.rows if r[1] == "improved")


def test_missing_modes_are_named_with_the_make_target(tmp_path):
    assert resolution.missing_presets(tmp_path) == list(resolution.RESOLUTION_PRESETS.values())
    with pytest.raises(SphereBenchError, match="default-stereo-848.*make data-resolution"):
        resolution.resolution_study(tmp_path, tmp_path / "out", workers=1)
