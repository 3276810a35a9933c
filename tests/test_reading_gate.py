"""The reading gate (``spherebench.reading``): every JSON reader on the same hostile set gives one
line naming the file, never a traceback."""

from __future__ import annotations

from pathlib import Path

import pytest

from spherebench import reading
from spherebench.baselines import hough_tuning
from spherebench.baselines.circlenet import data as circlenet_data
from spherebench.datasets import foreign_formats, inout
from spherebench.errors import SphereBenchError
from spherebench.eval.bench import cache, recorded
from spherebench.eval.metrics import coco_eval
from spherebench.options import parse_overrides

#: name -> text: what a hostile or damaged JSON file may hold
HOSTILE = {
    "nested 200,000 deep": "[" * 200_000 + "]" * 200_000,
    "an object nested 5,000 deep": '{"a": ' * 5_000 + "1" + "}" * 5_000,
    "an integer of 5,000 digits": '{"fx": ' + "9" * 5_000 + "}",
    "an integer of 400 digits": '{"width": ' + "1" * 400 + ', "fx": -' + "7" * 400 + "}",
    "truncated": '{"images": [1, 2',
    "empty": "",
    "not UTF-8": b"\xff\xfe\x00{",
    "a list": "[1, 2, 3]",
}

#: (reader, the file name it reads in a folder, or None: the file itself)
READERS = {
    "intrinsics": (inout.read_intrinsics, None),
    "camera json": (foreign_formats.read_camera_json, None),
    "LabelMe": (foreign_formats.read_labelme, None),
    "gt.json": (inout.read_scene_gt, "gt.json"),
    "dataset.json": (inout.read_dataset_meta, "dataset.json"),
    "coco_gt.json": (inout.read_coco_gt, "coco_gt.json"),
    "predictions": (cache.read_predictions, None),
    "--beside metrics": (lambda p: recorded.load_beside(p, "default"), None),
    "Hough configuration": (hough_tuning.load_hough_config, None),
    "COCO ground truth": (coco_eval.load_ground_truth, None),
    "CircleNet training folder": (circlenet_data.read_dataset, "coco_gt.json"),
}


def _write(folder: Path, name: str, text) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / name
    path.write_bytes(text if isinstance(text, bytes) else text.encode())
    return path


@pytest.mark.parametrize("case", list(HOSTILE))
@pytest.mark.parametrize("reader", list(READERS))
def test_every_reader_refuses_hostile_json_in_one_line(tmp_path, reader, case):
    read, inside = READERS[reader]
    if reader == "predictions" and case == "a list":
        pytest.skip("a list is what a predictions file holds")
    if reader == "predictions":  # its meta file beside it, well formed
        _write(tmp_path, "input.meta.json", "{}")
    if inside is None:
        target = path = _write(tmp_path, "input.json", HOSTILE[case])
    else:
        target, path = tmp_path, _write(tmp_path, inside, HOSTILE[case])
        if inside == "coco_gt.json" and reader == "CircleNet training folder":
            (tmp_path / "scenes").mkdir()
    with pytest.raises(SphereBenchError) as err:
        read(target)
    message = str(err.value)
    assert "\n" not in message and path.name in message, message


def test_the_gate_names_what_it_refuses(tmp_path, monkeypatch):
    assert reading.parse_json('{"seed": 18446744073709551615}', "x") == {"seed": 2 ** 64 - 1}  # a uint64 seed
    with pytest.raises(SphereBenchError, match="an integer of 21 digits"):
        reading.parse_json("[" + "1" * 21 + "]", "x")
    with pytest.raises(SphereBenchError, match="nested deeper"):
        reading.parse_json("[" * 100_000 + "]" * 100_000, "x")
    monkeypatch.setattr(reading, "MAX_JSON_BYTES", 10)
    big = _write(tmp_path, "big.json", "[" + "1, " * 10 + "1]")
    with pytest.raises(SphereBenchError, match="big.json: 33 bytes, more than a JSON file"):
        reading.read_json(big)
    monkeypatch.undo()
    assert reading.parse_json("[NaN, Infinity]", "x")[1] == float("inf")  # finiteness: the schema's to refuse


def test_a_setting_of_absurd_digits_is_a_string_for_the_configuration_to_refuse():
    from spherebench.method import config_for

    got = parse_overrides(["search.iterations=" + "9" * 5_000, "verification.min_score=0.5"])
    assert isinstance(got["search.iterations"], str) and got["verification.min_score"] == 0.5
    with pytest.raises(SphereBenchError, match="search.iterations=.* must be an integer"):
        config_for("improved", got)


def test_values_the_schemas_refuse(small_default, tmp_path):
    """Past the gate, each reader's schema: a category no category has, a focal length given as text
    to `prepare --intrinsics`, distortion coefficients no lens has."""
    import json
    import shutil

    data = tmp_path / "d"
    shutil.copytree(small_default, data)
    coco = json.loads((data / "coco_gt.json").read_text())
    coco["annotations"][0]["category_id"] = 7
    (data / "coco_gt.json").write_text(json.dumps(coco))
    with pytest.raises(SphereBenchError, match=r"annotations\[0\].category_id is 7, which no category has"):
        inout.read_coco_gt(data)
    intr = json.loads((inout.list_scenes(small_default)[0] / "intrinsics.json").read_text())
    for changed, says in (({"fx": "615.0"}, 'fx must be a finite number > 0, not "615.0"'),
                          ({"coeffs": [1e308, 0, 0, 0, 0]}, "coeffs must be five numbers")):
        path = _write(tmp_path, "camera.json", json.dumps({**intr, **changed}))
        with pytest.raises(SphereBenchError, match=says):
            foreign_formats.read_camera_json(path)
        with pytest.raises(SphereBenchError, match=says):
            inout.read_intrinsics(path)


def test_training_folders_check_every_scenes_gt_json(small_default, tmp_path):
    import shutil

    data = tmp_path / "d"
    shutil.copytree(small_default, data)
    assert len(circlenet_data.read_dataset(data)) == 6
    (inout.list_scenes(data)[2] / "gt.json").write_text("[]")
    with pytest.raises(SphereBenchError, match="gt.json: the file must be a JSON object, not"):
        circlenet_data.read_dataset(data)


def test_numbers_that_are_text_or_out_of_range_are_refused(small_default, tmp_path):
    """A number spelt as text ("37.7") is no number of a file of ours, a ball radius of 1e308 no
    ball's, and a LabelMe point at 1e300 px on no image."""
    import json
    import shutil

    from spherebench.eval.metrics.coco_eval import load_ground_truth, load_results
    from spherebench.scripts.show import scene_predictions

    data = tmp_path / "d"
    shutil.copytree(small_default, data)
    scene = inout.list_scenes(data)[0]
    result = {"image_id": 1, "category_id": 1, "circle_center": [100.0, 80.0], "circle_radius": 20.0, "score": 0.9,
              "scene_id": scene.name}
    preds = _write(tmp_path, "preds.json", json.dumps([{**result, "circle_radius": "20.0"}]))
    with pytest.raises(SphereBenchError, match=r"preds.json: circle_radius of result 0 must be"):
        scene_predictions(preds, scene.name, 0.0)
    gt = load_ground_truth(data / "coco_gt.json")
    for bad in ({"score": "0.9"}, {"circle_center": ["100", 80.0]}):
        with pytest.raises(SphereBenchError, match="result 0 lacks"):
            load_results(gt, [{**result, **bad}])
    assert len(load_results(gt, [result]).getAnnIds()) == 1
    metrics = _write(tmp_path, "metrics.json", json.dumps({"improved": {"default": {"mAP": "0.5"}}}))
    with pytest.raises(SphereBenchError, match=r"metrics.json: improved.default.mAP must be a finite number"):
        recorded.load_beside(metrics, "default")
    doc = json.loads((scene / "gt.json").read_text())
    doc["balls"][0]["radius_m"] = 1e308
    (scene / "gt.json").write_text(json.dumps(doc))
    with pytest.raises(SphereBenchError, match=r"balls\[0\].radius_m must be a ball radius"):
        inout.read_scene_gt(scene)
    labelme = {"imageWidth": 424, "imageHeight": 240, "shapes": [
        {"label": "ball", "shape_type": "polygon", "points": [[10, 10], [1e300, 10], [10, 50]]}]}
    path = _write(tmp_path, "lm.json", json.dumps(labelme))
    with pytest.raises(SphereBenchError, match="lies beyond any image"):
        foreign_formats.read_labelme(path)


def test_a_fifo_where_a_json_file_belongs_is_refused_without_waiting(small_default, tmp_path):
    import os
    import shutil

    fifo = tmp_path / "f.json"
    os.mkfifo(fifo)
    with pytest.raises(SphereBenchError, match="f.json: not a regular file"):
        reading.read_json(fifo)  # opening it would wait for a writer
    data = tmp_path / "d"
    shutil.copytree(small_default, data)
    (data / "dataset.json").unlink()
    os.mkfifo(data / "dataset.json")
    with pytest.raises(SphereBenchError, match="dataset.json: not a regular file"):
        inout.scene_dataset_meta(inout.list_scenes(data)[0])
