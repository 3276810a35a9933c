"""Bad input to detect, show, evaluate and train: a one-line error before any work, or the right answer.

Each test asserts the exit status, a single error line on stderr (no traceback), that nothing was
printed or written before the error, and that nothing outside the command's own output changed.
"""

from __future__ import annotations

import json
import math
import random
import shutil
from pathlib import Path

import numpy as np
import pytest

from spherebench import provenance
from spherebench.scripts import cli
from spherebench.baselines import pyransac3d_peer as peer
from spherebench.baselines.circlenet.infer import DEFAULT_MODEL
from spherebench.camera import Intrinsics, image_rays
from spherebench.cloud import Cloud, in_front_of_camera
from spherebench.datasets import fingerprint, inout, simulate
from spherebench.errors import SphereBenchError
from spherebench.eval.bench import registry, report, seeds
from spherebench.method import config_for
from conftest import markdown_cells  # noqa: E402  (tests/ is on sys.path under pytest)

CAM = Intrinsics(width=160, height=120, ppx=79.5, ppy=59.5, fx=140.0, fy=140.0)
BALL_CENTRE_M = np.array([0.05, -0.03, 1.4])


def _listing(root) -> dict:
    """Every file under root with its bytes: what a failed command must leave as it was."""
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def _fails(capsys, argv, *words) -> str:
    """Run argv; it must exit 2 with one error line naming ``words`` and print nothing on stdout."""
    status = cli.main([str(a) for a in argv])
    cap = capsys.readouterr()
    lines = cap.err.strip().splitlines()
    assert status == 2, cap.err
    assert len(lines) == 1 and "error:" in lines[0] and "Traceback" not in cap.err, cap.err
    assert cap.out == "", cap.out
    for w in words:
        assert w in lines[0], lines[0]
    return lines[0]


def _ball_depth(radius_m: float, intr: Intrinsics = CAM, wall_m: float = 2.2) -> np.ndarray:
    """uint16 depth (mm) of a ball of radius_m at BALL_CENTRE_M before a wall at wall_m."""
    u = image_rays(intr)
    u = u / np.linalg.norm(u, axis=-1, keepdims=True)
    tc = u @ BALL_CENTRE_M
    m2 = BALL_CENTRE_M @ BALL_CENTRE_M - tc * tc
    t = tc - np.sqrt(np.maximum(radius_m ** 2 - m2, 0.0))
    z = np.where(m2 < radius_m ** 2, t * u[..., 2], wall_m)
    return np.round(z * 1000).astype(np.uint16)


@pytest.fixture(scope="module")
def big_ball(tmp_path_factory):
    """A dataset prepared with --radius 0.2 from one depth frame of a 0.2 m ball."""
    root = tmp_path_factory.mktemp("bigball")
    (root / "pngs").mkdir()
    inout.write_depth_png(root / "pngs" / "f.png", _ball_depth(0.2))
    (root / "cam.json").write_text(json.dumps(CAM.to_dict()))
    out = root / "ds"
    assert cli.main(["prepare", str(root / "pngs"), "--intrinsics", str(root / "cam.json"), "--radius", "0.2",
                     "--out", str(out)]) == 0
    return out


def _json_lines(text: str) -> list[dict]:
    return [json.loads(x) for x in text.strip().splitlines()]


# ---------------------------------------------------------------- detect: the radius

def test_detect_takes_the_radius_of_the_dataset_and_says_so(big_ball, tmp_path, capsys):
    scene = big_ball / "scenes" / "f"
    capsys.readouterr()
    assert cli.main(["detect", str(scene), "--json"]) == 0
    rec = _json_lines(capsys.readouterr().out)[0]
    assert rec["radius_m"] == 0.2 and rec["radius_source"] == "dataset"
    assert np.linalg.norm(np.array(rec["detections"][0]["center_m"]) - BALL_CENTRE_M) < 0.01
    # a scene folder on its own: its gt.json; --radius wins over both; a bare cloud: 0.12
    alone = tmp_path / "alone"
    shutil.copytree(scene, alone)
    np.savetxt(tmp_path / "bare.xyz", inout.load_cloud(scene).points[::3])
    assert cli.main(["detect", str(alone), str(scene), str(tmp_path / "bare.xyz"), "--json"]) == 0
    recs = _json_lines(capsys.readouterr().out)
    assert [(r["radius_m"], r["radius_source"]) for r in recs] == [(0.2, "scene"), (0.2, "dataset"), (0.12, "default")]
    assert cli.main(["detect", str(scene), "--radius", "0.12"]) == 0
    assert "radius 0.12 m (--radius)" in capsys.readouterr().out
    assert cli.main(["detect", str(scene)]) == 0
    assert "radius 0.2 m (the dataset's)" in capsys.readouterr().out


def test_detect_refuses_a_dataset_folder_and_a_radius_below_the_tolerance(big_ball, capsys):
    _fails(capsys, ["detect", big_ball], "is a dataset", "scenes/*")
    # the tolerance the user never gave is named as the default, and the radius as the problem
    _fails(capsys, ["detect", big_ball / "scenes" / "f", "--radius", "0.005"], "--radius 0.005", "smaller --eps")
    _fails(capsys, ["detect", big_ball / "scenes" / "f", "--eps", "0.3"], "--eps 0.3", "0.2 m (from its dataset.json)")


# ---------------------------------------------------------------- detect: everything checked first

def test_detect_out_png_without_intrinsics_fails_before_any_result(big_ball, tmp_path, capsys):
    cloud = tmp_path / "c.xyz"
    np.savetxt(cloud, inout.load_cloud(big_ball / "scenes" / "f").points[::5])
    before = _listing(tmp_path)
    _fails(capsys, ["detect", cloud, "--out-png", tmp_path / "x.png"], "--out-png needs an organised cloud")
    _fails(capsys, ["detect", cloud, cloud, "--out-ply", tmp_path / "x.ply"], "one input")
    _fails(capsys, ["detect", cloud, "--out-ply", tmp_path], "is a folder")
    _fails(capsys, ["detect", cloud, "--out-ply", cloud], "is the input")
    _fails(capsys, ["detect", cloud, "--out-ply", tmp_path / "x", "--out-png", tmp_path / "x"], "same file")
    # a missing or unknown input among several: one line for it, the others detected, exit 2
    # (tests/test_bad_input_files.py has the batch)
    (tmp_path / "notes.txt.bak").write_text("x")
    for bad, says in (("missing.ply", "not found"), ("notes.txt.bak", "unknown point-cloud format")):
        assert cli.main(["detect", str(cloud), str(tmp_path / bad)]) == 2
        cap = capsys.readouterr()
        assert cap.out.startswith(f"{cloud}: ") and len(cap.out.splitlines()) == 1
        assert len(cap.err.splitlines()) == 1 and bad in cap.err and says in cap.err
    assert _listing(tmp_path) == {**before, "notes.txt.bak": b"x"}


def test_detect_refuses_an_image_of_another_size_than_the_intrinsics(big_ball, tmp_path, capsys):
    scene = tmp_path / "scene"
    shutil.copytree(big_ball / "scenes" / "f", scene)
    inout.write_png(scene / "image.png", np.zeros((60, 80, 3), np.uint8))
    before = _listing(tmp_path)
    _fails(capsys, ["detect", scene, "--out-png", tmp_path / "x.png"], "image.png is 80x60", "160x120")
    _fails(capsys, ["detect", scene, "--out-ply", scene / "cloud.ply"], "inside the input scene folder")
    assert _listing(tmp_path) == before


# ---------------------------------------------------------------- detect: what no depth camera gives

def test_intrinsics_with_the_principal_point_off_the_image_or_absurd_focal_lengths_are_refused(tmp_path, capsys):
    for bad, words in (({"ppx": 900.0}, ("principal point", "outside the 160x120 image")),
                       ({"ppy": -3.0}, ("principal point",)),
                       ({"fx": 0.5, "fy": 0.5}, ("focal lengths",)),
                       ({"fx": 1e6, "fy": 1e6}, ("focal lengths",)),
                       ({"fx": 140.0, "fy": 1400.0}, ("differ more than",))):
        with pytest.raises(SphereBenchError, match=words[0]):
            Intrinsics(**{**CAM.to_dict(), **bad})
        (tmp_path / "cam.json").write_text(json.dumps({**CAM.to_dict(), **bad}))
        np.savetxt(tmp_path / "c.xyz", [[0, 0, 1.0]] * 10)
        _fails(capsys, ["detect", tmp_path / "c.xyz", "--intrinsics", tmp_path / "cam.json"], "cam.json", *words)
    Intrinsics(**{**CAM.to_dict(), "ppx": -0.5, "ppy": 119.5})  # the image's edges are still on it


def test_detect_leaves_out_points_behind_a_depth_camera_and_refuses_a_cloud_mostly_behind(big_ball, tmp_path, capsys):
    scene = big_ball / "scenes" / "f"
    cloud = inout.load_cloud(scene)
    pts = cloud.points.copy()
    pts[:40] = [0.0, 0.0, -1.0]  # a clump behind the camera, where a sphere would otherwise be reported
    inout.write_cloud_ply(tmp_path / "some.ply", Cloud(pts, cloud.rows, cloud.cols))
    capsys.readouterr()
    assert cli.main(["detect", str(tmp_path / "some.ply"), "--intrinsics", str(scene), "--radius", "0.2",
                     "--json"]) == 0
    cap = capsys.readouterr()
    assert cap.err.count("\n") == 1 and "40 points at z <= 0 left out" in cap.err
    centres = [s["center_m"] for s in _json_lines(cap.out)[0]["detections"]]
    assert centres and all(c[2] > 0 for c in centres)
    assert np.linalg.norm(np.array(centres[0]) - BALL_CENTRE_M) < 0.01
    inout.write_cloud_ply(tmp_path / "flipped.ply", Cloud(cloud.points * [1, 1, -1], cloud.rows, cloud.cols))
    _fails(capsys, ["detect", tmp_path / "flipped.ply"], "behind the camera", "z > 0")
    # an unorganised cloud (a LiDAR's) keeps its points on every side
    lidar = Cloud(cloud.points * [1, 1, -1])
    assert in_front_of_camera(lidar)[0] is lidar


# ---------------------------------------------------------------- show

def test_show_refuses_an_image_of_another_size_than_the_intrinsics(big_ball, tmp_path, capsys):
    scene = tmp_path / "scene"
    shutil.copytree(big_ball / "scenes" / "f", scene)
    inout.write_png(scene / "image.png", np.zeros((120, 200, 3), np.uint8))
    before = _listing(tmp_path)
    _fails(capsys, ["show", scene, "--out-png", tmp_path / "s.png", "--out-ply", tmp_path / "s.ply"],
           "image.png is 200x120", "160x120")
    assert _listing(tmp_path) == before


# ---------------------------------------------------------------- evaluate

def _shipped_model():
    if not DEFAULT_MODEL.is_file():
        pytest.skip("no shipped CircleNet model")
    return DEFAULT_MODEL


def _copy(src, dst):
    shutil.copytree(src, dst)
    return dst


def test_evaluate_refuses_a_corrupt_model_before_any_method_runs(big_ball, tmp_path, capsys):
    data = _copy(big_ball, tmp_path / "data")
    model = tmp_path / "corrupt.onnx"
    model.write_bytes(_shipped_model().read_bytes()[:4000])
    before = _listing(tmp_path)
    _fails(capsys, ["evaluate", "--data", data, "--out", tmp_path / "out", "--methods", "improved", "circlenet",
                    "--model", model, "--workers", "1", "--quiet", "--no-figures"], "corrupt.onnx", "not a valid ONNX")
    foreign = tmp_path / "foreign.onnx"
    foreign.write_text("not a model")
    _fails(capsys, ["evaluate", "--data", data, "--out", tmp_path / "out", "--model", foreign, "--workers", "1",
                    "--quiet"], "foreign.onnx")
    assert _listing(tmp_path) == {**before, "foreign.onnx": b"not a model"}


def test_evaluate_refuses_a_truncated_coco_gt_of_any_dataset_before_running(big_ball, tmp_path, capsys):
    good = _copy(big_ball, tmp_path / "good")
    bad = _copy(big_ball, tmp_path / "bad")
    (bad / "coco_gt.json").write_bytes((bad / "coco_gt.json").read_bytes()[:40])
    before = _listing(tmp_path)
    _fails(capsys, ["evaluate", "--data", good, "--data", bad, "--out", tmp_path / "out", "--methods", "improved",
                    "--workers", "1", "--quiet", "--no-figures"], "coco_gt.json", "not valid JSON")
    assert _listing(tmp_path) == before
    with pytest.raises(SphereBenchError, match="truncated"):  # the path that read it with json.loads
        fingerprint.dataset_fingerprint(bad)


def test_evaluate_says_a_method_that_refused_every_image_was_not_run(big_ball, tmp_path, capsys, monkeypatch):
    def refuse(self, image, seed):
        raise SphereBenchError("the image is 160x120 px, not this method's")
    monkeypatch.setattr(registry.HoughAdapter, "detect", refuse)  # --workers 1: the adapters run in this process
    hough = tmp_path / "hough.json"
    hough.write_text("{}")
    capsys.readouterr()
    assert cli.main(["evaluate", "--data", str(big_ball), "--out", str(tmp_path / "out"), "--methods", "improved",
                     "hough", "--hough-config", str(hough), "--workers", "1", "--quiet", "--no-figures"]) == 0
    out = capsys.readouterr().out
    line = next(x for x in out.splitlines() if " hough " in x)
    assert "refused 1/1: the image is 160x120 px" in line and "detections in" not in line and " ms" not in line
    assert "detections in 1/1" in next(x for x in out.splitlines() if " improved " in x)
    readme = markdown_cells((tmp_path / "out" / "README.md").read_text())
    assert "hough was not run: it refused 1/1 scenes" in readme
    assert "| hough | 1 | not run (the image is 160x120 px" in readme
    assert "| hough | ds |" not in readme  # no time for a method that did not run


# ---------------------------------------------------------------- train

@pytest.fixture(scope="module")
def train_data(tmp_path_factory):
    return simulate.generate_dataset("train", tmp_path_factory.mktemp("train") / "train", n=3, progress=False)


@pytest.mark.parametrize("option, words", [(["--device", "tpu7"], ("tpu7", "auto, cpu, cuda")),
                                           (["--device", "cuda:x"], ("cuda:x",)),
                                           (["--workers", "-1"], ("--workers", "-1", "give 0"))])
def test_train_refuses_a_bad_device_or_worker_count_before_creating_its_folder(train_data, tmp_path, capsys,
                                                                               option, words):
    before = _listing(train_data)
    _fails(capsys, ["train", "--data", train_data, "--out", tmp_path / "run" / "model", "--quiet", *option], *words)
    assert not (tmp_path / "run").exists() and _listing(train_data) == before


def test_train_failing_in_its_first_steps_removes_the_folder_it_created(train_data, tmp_path, capsys, monkeypatch):
    def refuse(*a, **k):
        raise SphereBenchError("an image cannot be read")
    monkeypatch.setattr("spherebench.baselines.circlenet.train.CircleDataset", refuse)
    _fails(capsys, ["train", "--data", train_data, "--out", tmp_path / "run", "--quiet"], "cannot be read")
    assert not (tmp_path / "run").exists()
    (tmp_path / "mine").mkdir()  # a folder that was there before is left as it was
    _fails(capsys, ["train", "--data", train_data, "--out", tmp_path / "mine", "--quiet"], "cannot be read")
    assert (tmp_path / "mine").is_dir()


# ---------------------------------------------------------------- reproducible peers

def test_pyransac3d_fits_depend_on_the_scene_seed_only(big_ball, small_default):
    clouds = [inout.load_cloud(s) for s in [big_ball / "scenes" / "f", *inout.list_scenes(small_default)[:3]]]
    scene_seeds = [seeds.detection_seed(0, k) for k in range(len(clouds))]

    def fits(order, disturb):
        out = {}
        for k in order:
            random.seed(disturb + k)  # whatever the caller (or the scene before) left in the global generator
            np.random.seed(disturb + k)
            state = random.getstate()
            got = peer.detect(clouds[k], points=600, iterations=80, seed=scene_seeds[k])
            assert random.getstate() == state  # and the caller's generator is left as it was
            out[k] = [(d["center_m"].tolist(), d["radius_m"], d["inliers"]) for d in got]
        return out

    assert fits(range(len(clouds)), 1) == fits(reversed(range(len(clouds))), 99)


def test_provenance_names_what_the_peers_arithmetic_depends_on():
    assert "onnxruntime" in provenance.PACKAGES and "pyransac3d" in provenance.PACKAGES
    info = provenance.machine_info()
    assert "blas" in info
    if info["blas"] is not None:  # numpy's bundled OpenBLAS: its version and the kernel chosen for this CPU
        assert info["blas"].startswith("OpenBLAS")


# ---------------------------------------------------------------- the benchmark's subcommands

@pytest.mark.parametrize("argv, says", [
    (["eval", "--data", "{tmp}/none"], "is missing"),
    (["eval", "--data", "{tmp}/none", "--workers", "0"], "--workers: 0: give 1 or more"),
    (["sweep", "{tmp}/none"], "none"),
    (["robustness", "{tmp}/none"], "none"),
    (["bench", "{tmp}/none"], "none"),
])
def test_benchmark_subcommands_refuse_bad_input_in_one_line(tmp_path, capsys, argv, says):
    argv = [a.format(tmp=tmp_path) for a in argv] + ["--out", str(tmp_path / "out")]
    assert cli.main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"spherebench {argv[0]}: error:") and len(err.strip().splitlines()) == 1 and says in err
    assert not (tmp_path / "out").exists() and not (tmp_path / "out.md").exists()


@pytest.mark.parametrize("setting, says", [
    ("retry.retry_disc=maybe", "retry.retry_disc='maybe' must be true or false"),  # a string would pass as on
    ("refinement.size_check=1", "refinement.size_check=1 must be true or false"),
    ("verification.max_spheres=0", "verification.max_spheres=0 must be >= 1"),
    ("verification.nms_distance_fraction=2", "verification.nms_distance_fraction=2 must be within [0, 1]"),
    ("evidence.occlusion_discount=0.5", "evidence.occlusion_discount (no longer a setting"),
    ("outline.outline_noise_fraction=-inf", "outline.outline_noise_fraction=-inf must be >= 0"),
    ("verification.min_scor=0.4", "unknown detector parameter verification.min_scor"),
    # a value of 120 KB (nested too deep to be JSON: a string) is not repeated back whole
    ("verification.min_score=" + "[" * 120_000, "verification.min_score='[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[..."),
])
def test_sweep_refuses_a_bad_setting_in_one_line(small_default, tmp_path, capsys, setting, says):
    argv = ["sweep", str(small_default), "--seeds", "0", "--set", setting, "--out", str(tmp_path / "out")]
    assert cli.main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("spherebench sweep: error:") and len(err.strip().splitlines()) == 1 and says in err
    assert len(err) < 300
    assert not (tmp_path / "out.md").exists() and not (tmp_path / "out.json").exists()


def test_sweep_reads_a_bare_name_of_before_the_groups_with_one_deprecation_line(capsys):
    from spherebench.eval.bench.sweep import read_settings

    got = read_settings(["min_score=0.4", "verification.rank_floor=0.1", "radius_m=0.2"], "sweep")
    assert got == {"verification.min_score": 0.4, "verification.rank_floor": 0.1, "radius_m": 0.2}
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["spherebench sweep: deprecated: name settings by their path: min_score -> verification.min_score"]
    assert config_for("improved", got).verification.min_score == 0.4


def test_set_reads_infinity_where_a_field_means_never():
    """"inf for never" (outline_noise_fraction) is what --set takes: inf and
    -inf are numbers, as JSON's Infinity is; other words stay strings for the configuration to refuse."""
    from spherebench.options import parse_overrides

    got = parse_overrides(["outline_noise_fraction=inf", "e=+Inf", "a=-inf", "b=Infinity", "c=nan", "d=infinite"])
    assert got["outline_noise_fraction"] == got["e"] == got["b"] == math.inf
    assert got["a"] == -math.inf and got["c"] == "nan" and got["d"] == "infinite"
    config_for("improved", outline={"outline_noise_fraction": got["outline_noise_fraction"]})  # accepted


def test_engine_options_are_checked_before_any_work(small_default, tmp_path, capsys):
    base = ["evaluate", "--data", str(small_default), "--out", str(tmp_path / "out"), "--methods", "improved"]
    assert cli.main([*base, "--engine", "spark"]) == 2  # argparse's choices
    assert cli.main([*base, "--address", "ray://head:10001"]) == 2
    err = capsys.readouterr().err
    assert "--address is the Ray cluster's: give it with --engine ray" in err


def test_provenance_dirty_means_changed_code_not_the_runs_own_outputs(tmp_path):
    """git_state: a tracked file changed in the run's output folder leaves the tree clean; one
    elsewhere makes it dirty."""
    import subprocess

    def git(*args):
        subprocess.run(["git", *args], cwd=tmp_path, check=True, capture_output=True)

    git("init", "-q")
    (tmp_path / "results").mkdir()
    (tmp_path / "results" / "table.md").write_text("old\n")
    (tmp_path / "code.py").write_text("x = 1\n")
    git("add", ".")
    git("-c", "user.name=t", "-c", "user.email=t@t", "commit", "-q", "-m", "init")
    (tmp_path / "results" / "table.md").write_text("new\n")
    assert provenance.git_state(tmp_path, outputs=(tmp_path / "results",))["dirty"] is False
    assert provenance.git_state(tmp_path)["dirty"] is True
    (tmp_path / "code.py").write_text("x = 2\n")
    assert provenance.git_state(tmp_path, outputs=(tmp_path / "results",))["dirty"] is True



def test_an_evaluation_after_make_eval_is_not_dirty_for_what_make_eval_wrote(tmp_path):
    """evaluate leaves what `make eval` writes (results/, a single file: the Hough copy) out of its
    dirty check; a changed file beside them still counts."""
    import subprocess

    from spherebench.eval.bench import evaluate as ev

    def git(*args):
        subprocess.run(["git", *args], cwd=tmp_path, check=True, capture_output=True)

    assert provenance.REPO_ROOT / "results" in ev.BENCHMARK_OUTPUTS
    git("init", "-q")
    (tmp_path / "results").mkdir()
    (tmp_path / "baselines").mkdir()
    for name in ("results/table.md", "baselines/hough_config.json", "baselines/other.json"):
        (tmp_path / name).write_text("old\n")
    git("add", ".")
    git("-c", "user.name=t", "-c", "user.email=t@t", "commit", "-q", "-m", "init")
    outputs = (tmp_path / "results", tmp_path / "baselines" / "hough_config.json")
    for name in ("results/table.md", "baselines/hough_config.json"):
        (tmp_path / name).write_text("new\n")
    assert provenance.git_state(tmp_path, outputs=outputs)["dirty"] is False
    (tmp_path / "baselines" / "other.json").write_text("new\n")
    assert provenance.git_state(tmp_path, outputs=outputs)["dirty"] is True


# ---------------------------------------------------------------- refusals the docs promise

def test_open_seed_ranges_absurd_widths_and_cloudless_benches_are_refused(small_default, tmp_path, capsys):
    _fails(capsys, ["sweep", small_default, "--seeds", "1-", "--out", tmp_path / "s"], "--seeds '1-'", "has no end")
    assert not list(tmp_path.glob("s*"))
    # a seed a dataset.json could not hold and the reading gate would not read back (over 20 digits)
    _fails(capsys, ["generate", "--preset", "default", "--n", "1", "--out", tmp_path / "g", "--seed", str(2 ** 64)],
           "at most 2^64 - 1")
    _fails(capsys, ["generate", "--preset", "default", "--n", "1", "--out", tmp_path / "g", "--seed", "9" * 400],
           "at most 2^64 - 1")
    _fails(capsys, ["sweep", small_default, "--seeds", f"0,{2 ** 64}", "--out", tmp_path / "s"], "at most 2^64 - 1")
    assert not list(tmp_path.glob("[gs]*"))
    _fails(capsys, ["train", "--data", small_default, "--out", tmp_path / "t", "--resnet-width", "100000"],
           "--resnet-width 100000", "1 to 256")
    assert not (tmp_path / "t").exists()
    cloudless = simulate.generate_dataset("train", tmp_path / "cloudless", n=2, progress=False)  # train writes none
    _fails(capsys, ["bench", cloudless, "--out", tmp_path / "b"], "no scene has a cloud.ply")
    assert not list(tmp_path.glob("b*"))


def test_results_are_never_written_inside_the_data_they_read(small_default, tmp_path, capsys):
    from spherebench.eval.bench.report import results_run

    data = tmp_path / "data"
    shutil.copytree(small_default, data / "default")
    before = _listing(data)
    _fails(capsys, ["evaluate", "--data", data / "default", "--out", data / "default" / "res", "--methods",
                    "improved"], "inside the dataset")
    with pytest.raises(SphereBenchError, match="is the input"):
        with results_run(data / "results", inputs=(data,)):  # `eval --data data --out data/results`
            pass
    assert _listing(data) == before and not (data / "results").exists()


def test_a_cloud_given_by_its_path_ignores_another_tools_gt_json_beside_it(small_default, tmp_path, capsys):
    scene = inout.list_scenes(small_default)[0]
    shutil.copy(scene / "cloud.ply", tmp_path / "cloud.ply")
    shutil.copy(scene / "intrinsics.json", tmp_path / "intrinsics.json")
    (tmp_path / "gt.json").write_text('{"annotations": [], "tool": "another one"}')
    assert cli.main(["detect", str(tmp_path / "cloud.ply"), "--json"]) == 0
    cap = capsys.readouterr()
    assert _json_lines(cap.out)[0]["radius_source"] == "default" and _json_lines(cap.out)[0]["detections"]
    assert len(cap.err.strip().splitlines()) == 1 and "not a SphereBench scene's, so it is ignored" in cap.err
    # a scene folder given as such is still read strictly
    (tmp_path / "scenes").mkdir()
    _fails(capsys, ["detect", tmp_path], "gt.json")


@pytest.mark.parametrize("signal_name", ["SIGINT", "SIGTERM"])
def test_a_signal_while_the_drivers_load_is_one_line(monkeypatch, capsys, signal_name):
    """Before a command runs, its driver's imports (numpy, OpenCV, torch) take a few tenths of a
    second; a signal then is one line and 128 + the signal, as during the run."""
    import signal

    def interrupted(_name):
        if signal_name == "SIGINT":
            raise KeyboardInterrupt
        signal.raise_signal(signal.SIGTERM)  # the handler main installed turns it into an interrupt

    monkeypatch.setattr(cli, "build_parser", interrupted)
    status = cli.main(["detect", "x.ply"])
    err = capsys.readouterr().err.strip().splitlines()
    assert status == 128 + int(getattr(signal, signal_name))
    word = "interrupted" if signal_name == "SIGINT" else "stopped by SIGTERM"
    assert err == [f"spherebench detect: {word}; no partial output is left"]


def test_a_help_that_cannot_be_written_is_one_line_and_status_2():
    """argparse drops a failed write; sent to a full disk, the help was lost with status 0."""
    import subprocess
    import sys

    if not Path("/dev/full").exists():
        pytest.skip("no /dev/full on this system")
    for argv in (["--help"], ["detect", "--help"]):
        with open("/dev/full", "w") as full:
            run = subprocess.run([sys.executable, "-m", "spherebench.scripts.cli", *argv], stdout=full, stderr=subprocess.PIPE,
                                 text=True, timeout=120)
        assert run.returncode == 2, run.stderr
        assert run.stderr.strip().splitlines() == [
            "spherebench: error: cannot write to standard output (No space left on device): free space or write "
            "somewhere else"]


def test_a_refused_or_stopped_run_leaves_no_folder_it_made(tmp_path, capsys, monkeypatch):
    """Neither the --labelme-out folder of a run whose every input was refused, nor the parents a
    stopped run created for its output."""
    _fails(capsys, ["detect", tmp_path / "absent.ply", "--labelme-out", tmp_path / "new" / "lm"], "absent.ply")
    assert list(tmp_path.iterdir()) == []

    def stopped(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(simulate, "simulate_scene", stopped)
    assert cli.main(["generate", "--preset", "paper", "--out", str(tmp_path / "n1" / "n2" / "g")]) == 130
    assert "interrupted" in capsys.readouterr().err and list(tmp_path.iterdir()) == []


def test_a_thread_count_beyond_the_machine_is_refused(capsys):
    import os

    most = max(64, 4 * (os.cpu_count() or 1))
    for argv in (["detect-2d", "x.png", "--threads", "999999"], ["train", "--data", "d", "--out", "o", "--threads",
                                                                  str(most + 1)]):
        assert cli.main(argv) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and f"give at most {most} threads" in err[0], err


def test_detect_writes_nothing_under_home(small_default, tmp_path):
    """ONNX Runtime (the fitted verdict) would write a telemetry device id under ~/.cache; the package
    asks it not to (ORT_DISABLE_TELEMETRY), keeping a user's own setting."""
    import os
    import subprocess
    import sys

    home = tmp_path / "home"
    home.mkdir()
    env = {k: v for k, v in os.environ.items() if k not in ("ORT_DISABLE_TELEMETRY", "XDG_CACHE_HOME")}
    env["HOME"] = str(home)
    run = subprocess.run([sys.executable, "-m", "spherebench.scripts.cli", "detect", str(inout.list_scenes(small_default)[0])],
                         env=env, capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    assert sorted(str(p.relative_to(home)) for p in home.rglob("*")) == []


def test_a_link_loop_a_nan_tolerance_and_an_ignored_distortion_are_refused(small_default, tmp_path, capsys):
    scene = inout.list_scenes(small_default)[0]
    loop = tmp_path / "loop.ply"
    loop.symlink_to(loop)  # pathlib's resolve() raises RuntimeError, not OSError, for it
    _fails(capsys, ["detect", loop, "--json"], "loop.ply", "leads back to itself")
    _fails(capsys, ["show", scene, "--tolerance", "nan", "--out-png", tmp_path / "s.png"], "--tolerance",
           "a finite number from 0")
    pngs = tmp_path / "pngs"
    pngs.mkdir()
    shutil.copy(scene / "depth.png", pngs / "f.png")
    _fails(capsys, ["prepare", pngs, "--intrinsics", scene / "intrinsics.json", "--coeffs", "1", "2", "3", "4", "5",
                    "--out", tmp_path / "p"], "--coeffs go with --fx")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["loop.ply", "pngs"]
