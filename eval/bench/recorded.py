"""Recorded datasets in the reports: what their ground truth is, and the reading that says so.

A dataset made by ``spherebench prepare`` (every scene of family "recorded") has no simulator
behind it. Its 2D ground truth is the masks given to ``prepare`` (the LabelMe files it keeps in
the scene folders say, shape by shape, how they were made; the repository's reviewed sets, under
``datasets/annotations/<name>/``, have a card beside them), and its 3D centres, where it has
any, are fits to those masks' depth pixels (``center_source`` "mask-fit", with a standard
error): a reference, not a ground truth.

- ``facts``: what dataset.json and the scenes say about that, with the figures that bound what
  the reference can tell: its standard errors, and how the fitted sphere of the stated radius
  projects against the mask (a ratio below 1: the ball looks larger than its stated radius to
  the sensor, or the radius is small, and the fixed-radius centre then sits too near the camera);
- ``reading``: the sentences of the results README for such a dataset;
- ``beside_table`` / ``beside_reading``: a dataset's Table 3 beside another evaluation's
  (its metrics.json), e.g. the simulated ``default`` preset.

Every number in a sentence is computed here from the files; none is typed in.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np

from spherebench.circles import sphere_circle_exact
from spherebench.datasets import inout, outputs
from spherebench.errors import SphereBenchError
from spherebench.eval.bench.cache import meta_path
from spherebench.eval.bench.registry import PAPER_CIRCLE, ROLE_LEARNED_2D, methods_with_role, training_presets
from spherebench.eval.bench.tables import Table, fmt, rule_label
from spherebench.eval.bench.tasks import dataset_scenes
from spherebench.provenance import REPO_ROOT, file_sha256
from spherebench.reading import check_schema

#: Methods whose Table 3 figures the beside reading quotes, in this order, where present.
BESIDE_READING = ("improved", "circlenet", "circlenet-analytic", "circlenet-full", "circlenet-hg", "hough")
#: The repository's reviewed annotation sets: <this>/<dataset name>/<scene_id>.json and a README.md card.
ANNOTATION_SETS = REPO_ROOT / "datasets" / "annotations"
#: LabelMe shapes that are balls (``datasets.annotate.BALL_SHAPE_TYPES``).
BALL_SHAPES = ("circle", "polygon")


def _median(values) -> float | None:
    v = np.asarray(list(values), np.float64)
    return float(np.median(v)) if v.size else None


def _labelme_copies(scenes) -> dict[str, dict]:
    """{scene id: the LabelMe document prepare kept in the scene folder} of the annotated scenes."""
    out = {}
    for s in scenes:
        for name in outputs.LABELME_FILES:
            if s.annotated and (s.path / name).is_file():
                out[s.scene_id] = inout.read_json(s.path / name)
                break
    return out


def annotation_source(name: str, scenes) -> dict:
    """Where a recorded dataset's masks came from, as far as its files say: the descriptions its ball
    shapes carry ({text: count}) and, when every annotated scene's LabelMe shapes are those of the
    repository's reviewed set of that name (``ANNOTATION_SETS``), that set's folder and card."""
    docs = _labelme_copies(scenes)
    descriptions: dict[str, int] = {}
    for doc in docs.values():
        for shape in doc.get("shapes") or []:
            text = str(shape.get("description") or "").strip()
            if (shape.get("shape_type") or "polygon") in BALL_SHAPES and text:
                descriptions[text] = descriptions.get(text, 0) + 1
    out = {"descriptions": dict(sorted(descriptions.items(), key=lambda kv: (-kv[1], kv[0]))),
           "labelme_scenes": len(docs), "set": None, "card": None}
    folder = ANNOTATION_SETS / str(name)
    annotated = [s for s in scenes if s.annotated]
    if docs and folder.is_dir() and len(docs) == len(annotated) and all(
            (folder / f"{sid}.json").is_file() and inout.read_json(folder / f"{sid}.json").get("shapes") == doc.get("shapes")
            for sid, doc in docs.items()):
        out["set"] = str(folder.relative_to(REPO_ROOT))
        if (folder / "README.md").is_file():
            out["card"] = str((folder / "README.md").relative_to(REPO_ROOT))
    return out


def facts(data_dir: str | Path) -> dict | None:
    """What a recorded dataset's files say about its ground truth; None for a simulated one.

    Keys: name, camera (the source's camera or sensor), source_kind, radius_m, radius_source,
    n_scenes, annotated, image_less, resolution ("WxH" of the first scene with intrinsics, or
    None), colour (scenes with a colour frame), annotations (``annotation_source``),
    n_balls (annotated balls), mask_fit (balls with a mask-fit centre), se_median_m, se_max_m (3D
    standard error of those centres), fit_circle_ratio (median mask circle radius over the
    fitted sphere's projected circle: the fitted sphere of the stated radius against the mask),
    fit_circle_offset_px (median distance of the two circles' centres), authors_n /
    authors_distance_m (scenes with the recording's own reference fit, and the median distance of
    the mask fit from it).
    """
    root = Path(data_dir)
    scenes = dataset_scenes(root)
    if not scenes or any(s.family != "recorded" for s in scenes):
        return None
    meta = inout.read_dataset_meta(root) if (root / "dataset.json").is_file() else {}
    source = meta.get("source") or {}
    radius = float(meta.get("ball_radius_m", 0.12))
    out = {"name": meta.get("name") or root.name, "camera": source.get("camera") or source.get("sensor"),
           "source_kind": source.get("kind"), "radius_m": radius, "radius_source": source.get("radius_source"),
           "n_scenes": len(scenes), "annotated": sum(s.annotated for s in scenes),
           "image_less": sum(not s.has_image for s in scenes),
           "resolution": next((s.resolution for s in scenes if s.resolution), None),
           "colour": sum(any((s.path / name).is_file() for name in outputs.COLOUR_FILES) for s in scenes),
           "annotations": annotation_source(meta.get("name") or root.name, scenes)}
    se, ratios, offsets, authors = [], [], [], []
    n_balls = n_fit = 0
    for s in scenes:
        if not s.annotated:
            continue
        gt = inout.read_scene_gt(s.path)
        intr = inout.read_intrinsics(s.path) if (s.path / "intrinsics.json").is_file() else None
        for b in gt.get("balls", []):
            n_balls += 1
            if b.get("center_source") != "mask-fit" or b.get("center_m") is None:
                continue
            n_fit += 1
            if b.get("center_se_m") is not None:
                se.append(float(np.linalg.norm(b["center_se_m"])))
            fit = sphere_circle_exact(intr, b["center_m"], float(b.get("radius_m", radius))) if intr else None
            if fit is not None and b.get("circle") is not None and fit[2] > 0:
                ratios.append(float(b["circle"][2]) / fit[2])
                offsets.append(float(np.hypot(b["circle"][0] - fit[0], b["circle"][1] - fit[1])))
            ref = (gt.get("meta") or {}).get("reference_center_m")
            if ref is not None:
                authors.append(float(np.linalg.norm(np.subtract(b["center_m"], ref))))
    out.update({"n_balls": n_balls, "mask_fit": n_fit,
                "se_median_m": _median(se), "se_max_m": max(se) if se else None,
                "fit_circle_ratio": _median(ratios), "fit_circle_offset_px": _median(offsets),
                "authors_n": len(authors), "authors_distance_m": _median(authors)})
    return out


def reference_note(f: dict) -> str | None:
    """The 3D table's note on a recorded dataset's centres (``facts``), or None without mask fits."""
    if not f.get("mask_fit"):
        return None
    se = f" (standard error median {1000 * f['se_median_m']:.1f} mm)" if f.get("se_median_m") is not None else ""
    return (f"The centres here are references, not a ground truth: a sphere of R = {f['radius_m']:g} m fitted to each "
            f"ball's mask's depth pixels{se}; errors of a few mm are within the reference's own error.")


def _get(sets: Sequence, output: str):
    return next((s for s in sets if s.output == output), None)


def _ran(s) -> bool:
    n = s.metrics.get("n_scenes_run", 0)
    return bool(n) and s.metrics.get("scenes_refused", 0) != n


def reading(label: str, f: dict, sets: Sequence) -> list[str]:
    """Sentences on a recorded dataset (``facts``) for the results README: what the recording is,
    what its 2D ground truth and its 3D reference are, and what that bounds."""
    out = [_what_it_is(label, f)]
    if f["image_less"] == f["n_scenes"]:
        out.append(f"`{label}` has no images (point clouds only): no 2D method runs on it and no circle mAP is "
                   "scored; " + ("without ground truth its rows count detections and the free radius, not accuracy."
                                 if not f["annotated"] else "only the 3D figures score it."))
        return out
    out.append(_ground_truth_2d(label, f))
    if f["mask_fit"]:
        out.extend(_reference_3d(f, sets))
    out.extend(_found_3d(label, sets))
    out.extend(_domain_gap(label, sets))
    return out


def _what_it_is(label: str, f: dict) -> str:
    camera = f" from {f['camera']}" if f.get("camera") else ""
    res = f" at {f['resolution']}" if f.get("resolution") and not f["image_less"] else ""
    radius_src = f" ({f['radius_source']})" if f.get("radius_source") else ""
    not_d435 = ("" if f.get("source_kind") == "realsense-recording" else
                ", not a RealSense D435: the simulated presets and the improved detector's noise allowances are "
                "a D435's" + ("" if f["image_less"] == f["n_scenes"] else ", and so are the CircleNets' training images"))
    return (f"`{label}` is a recording, not a simulation: {f['n_scenes']} frames{camera}{res}{not_d435}; its "
            f"ball has the stated radius R = {f['radius_m']:g} m{radius_src}, which the 3D methods are given.")


def _ground_truth_2d(label: str, f: dict) -> str:
    if not f["annotated"]:
        return f"`{label}` is not annotated: no circle mAP is scored; its rows count detections, not accuracy."
    a = f.get("annotations") or {}
    where = f", the repository's reviewed set `{a['set']}`" if a.get("set") else ""
    descs = a.get("descriptions") or {}
    said = ""
    if descs:
        text, count = next(iter(descs.items()))
        said = (f"; each ball shape says how it was made: '{text}'" if len(descs) == 1 and count == f["n_balls"]
                else f"; {count} of its {f['n_balls']} ball shapes say how they were made: '{text}'")
    card = f"; how they were made and reviewed: `{a['card']}`" if a.get("card") else ""
    on = (" drawn on the registered colour frames" if f["colour"] == f["n_scenes"] else "")
    return (f"Its 2D ground truth is the ball masks given to `prepare`{where} ({f['annotated']} of "
            f"{f['n_scenes']} frames, {f['n_balls']} balls){on}{said}{card}. A ball's circle is its mask's "
            "smallest enclosing circle; the 2D methods are given the reprojected depth image of the same "
            "pixel grid (image.png), not the colour frame.")


def _reference_3d(f: dict, sets: Sequence) -> list[str]:
    """What the mask-fit reference centres are, and how their sphere projects against the masks."""
    se = (f" (standard error median {1000 * f['se_median_m']:.1f} mm, at most {1000 * f['se_max_m']:.1f} mm)"
          if f["se_median_m"] is not None else "")
    text = (f"The 3D figures are measured against a reference centre, not a ground truth: a sphere of R = "
            f"{f['radius_m']:g} m fitted to each mask's depth pixels, {f['mask_fit']} balls{se}; centre "
            "errors of that size are not resolved.")
    ratio = f.get("fit_circle_ratio")
    if ratio is not None:
        text += _apparent_radius(f, ratio, sets)
    if f.get("authors_n"):
        text += (f" It lies a median {1000 * f['authors_distance_m']:.1f} mm from the recording's own reference "
                 f"fit in the {f['authors_n']} frames that have one.")
    out = [text]
    if ratio is not None and ratio > 1.02:
        out.append("So circles drawn with the stated radius (the 3D methods' exact silhouette and the paper's "
                   "projection) are smaller than the masks', which caps their IoU below 1; the strict IoU "
                   "thresholds of mAP count this.")
    return out


def _apparent_radius(f: dict, ratio: float, sets: Sequence) -> str:
    """The radius the sensor shows the ball at (the fitted sphere's circle against the mask's)."""
    size = "smaller" if ratio > 1 else "larger"
    apparent = f["radius_m"] * ratio
    text = (f" That sphere projects to a circle a median {100 * abs(1 - 1 / ratio):.0f} % {size} than the "
            f"mask's (centres a median {f['fit_circle_offset_px']:.1f} px apart, the colour-to-depth "
            f"registration among it): to this sensor the ball looks about {apparent:.3f} m in radius")
    imp = _get(sets, "improved")
    d = (imp.metrics.get("3d") or {}) if imp is not None and _ran(imp) else {}
    med = (d.get("radius_error_m") or {}).get("median")
    if med is not None and math.isfinite(med):
        text += f", and the improved detector's free-radius fit finds a median {f['radius_m'] + med:.3f} m"
    if abs(apparent - f["radius_m"]) >= 0.002:
        text += (f". If the stated radius is {1000 * abs(apparent - f['radius_m']):.0f} mm too "
                 f"{'small' if apparent > f['radius_m'] else 'large'}, the fixed-radius reference centre "
                 f"sits up to that much too {'near' if apparent > f['radius_m'] else 'far from'} the camera, "
                 "which its standard error does not include")
    return text + "."


def _found_3d(label: str, sets: Sequence) -> list[str]:
    found = []
    for s in sets:
        d = s.metrics.get("3d")
        if s.kind == "3d" and s.rule != "paper" and d and _ran(s) and d.get("n_gt"):
            n2 = round(d["within_2cm"] * d["n_gt"])
            med = (d.get("centre_error_m") or {}).get("median")
            found.append(f"{s.method} {n2}" + (f" (median distance {1000 * med:.1f} mm)" if n2 and med is not None
                                               and math.isfinite(med) else "")
                         + f", {d['false_detections']} false detection{'s' if d['false_detections'] != 1 else ''}")
    if not found:
        return []
    n = next(s.metrics["3d"]["n_gt"] for s in sets if s.metrics.get("3d"))
    return [f"In 3D, balls of `{label}` matched within 2 cm of the reference centre, of {n}: " + "; ".join(found) + "."]


def _domain_gap(label: str, sets: Sequence) -> list[str]:
    """The learned and tuned 2D methods meet another sensor here: say what they were trained on."""
    learned = {m.name for m in methods_with_role(ROLE_LEARNED_2D)}
    nets = [s for s in sets if s.method in learned and _ran(s) and s.metrics.get("mAP") is not None]
    hough = any(s.method == "hough" and _ran(s) for s in sets)
    if not (nets or hough):
        return []
    trained = "; ".join(f"`{s.method}` on {training_presets(s.method, s.extra_fingerprint) or 'simulated frames'}"
                        for s in nets)
    return [(f"The learned 2D methods were trained on simulated D435 frames only ({trained})" if nets else "")
            + (" and " if nets and hough else "") + ("Hough's parameters were tuned on `train`" if hough else "")
            + f": on `{label}` {'they meet' if len(nets) + hough > 1 else 'it meets'} another sensor's depth "
            "images, the domain gap a user meets."]


# --------------------------------------------------------------------------- beside another evaluation

#: Settings of a prediction set that depend on the dataset, not on the method (left out of the comparison).
DATASET_SETTINGS = ("radius_m",)


@dataclass
class Beside:
    """Another evaluation to set each Table 3 beside: its metrics.json content, the dataset label
    there, where it came from (a phrase for the tables), and per output the settings its
    prediction set ran with ({output: {"config", "extra_fingerprint"}}, from its predictions' meta
    files; an output without them is compared by its note)."""

    metrics: dict
    label: str
    source: str
    settings: dict = field(default_factory=dict)


#: The figures of another evaluation's metrics.json that a table beside ours reads.
BESIDE_FIGURES = {"mAP?": "number", "mAP50?": "number", "mAP75?": "number"}


def load_beside(path: str | Path, label: str) -> tuple[Beside, dict]:
    """(``Beside``, a provenance record) of another evaluation's metrics.json, its ``label`` dataset;
    a one-line error when the file is unreadable, not a metrics.json, or has no mAP on ``label``."""
    path = Path(path)
    if not path.is_file():
        raise SphereBenchError(f"--beside {path}: file not found (give another evaluation's metrics.json)")
    metrics = inout.read_json(path)
    if not isinstance(metrics, dict) or not all(isinstance(v, dict) for v in metrics.values()):
        raise SphereBenchError(f"--beside {path}: not a metrics.json of `spherebench evaluate`")
    for output, by in metrics.items():  # the figures read beside ours are numbers, as evaluate writes them
        if isinstance(by.get(label), dict):
            check_schema(path, by[label], BESIDE_FIGURES, "give a metrics.json of `spherebench evaluate`",
                                 f"{output}.{label}")
    if not any(isinstance(by.get(label), dict) and by[label].get("mAP") is not None for by in metrics.values()):
        found = sorted({k for by in metrics.values() for k, v in by.items() if isinstance(v, dict) and "mAP" in v})
        raise SphereBenchError(f"--beside {path}: no circle mAP on a dataset `{label}` there (it has "
                               f"{', '.join(found) or 'none'}): choose one with --beside-label")
    settings = {}
    for output in metrics:
        meta_file = meta_path(path.parent / "predictions" / label / f"{output}.json")
        if meta_file.is_file():
            meta = inout.read_json(meta_file)
            if isinstance(meta, dict):
                settings[output] = {"config": meta.get("config"), "extra_fingerprint": meta.get("extra_fingerprint")}
    git = {}
    if path.with_name("provenance.json").is_file():
        prov = inout.read_json(path.with_name("provenance.json"))
        git = (prov.get("git") or {}) if isinstance(prov, dict) else {}
    commit = git.get("commit")
    where = f"`{path}`" + (f" (made at commit {commit[:10]}{', with uncommitted changes' if git.get('dirty') else ''})"
                           if commit else "")
    record = {"path": str(path), "label": label, "sha256": file_sha256(path), "commit": commit,
              "dirty": git.get("dirty"), "settings_from_meta_files": len(settings)}
    return Beside(metrics, label, where, settings), record


def _method_settings(config: dict | None) -> dict | None:
    return None if config is None else {k: v for k, v in config.items() if k not in DATASET_SETTINGS}


def same_settings(s, o: dict, settings: dict | None) -> bool:
    """Did the other evaluation run this set's method as this one did? By its configuration (less the
    dataset's radius) and model file's hash where the other's meta file gives them, else by the note
    (which quotes a CircleNet's model card); a figure that is not there says nothing."""
    if not o:
        return True
    if settings is not None and s.config is not None:
        return (_method_settings(settings.get("config")) == _method_settings(s.config)
                and (settings.get("extra_fingerprint") or "") == (s.extra_fingerprint or ""))
    return (s.metrics.get("note") or "") == (o.get("note") or "")


def beside_rows(sets: Sequence, beside: Beside) -> list[tuple]:
    """(set, its figures on this dataset, the same output's figures on the other dataset, whether it
    ran there with the same settings) for every set with a circle mAP."""
    rows = []
    for s in sets:
        if s.metrics.get("mAP") is None or not _ran(s):
            continue
        o = (beside.metrics.get(s.output) or {}).get(beside.label) or {}
        rows.append((s, s.metrics, o, same_settings(s, o, beside.settings.get(s.output))))
    return rows


def beside_table(label: str, sets: Sequence, beside: Beside):
    """Table 3 on ``label`` beside the same methods' Table 3 on the other evaluation's dataset; None
    without rows. A figure from a run with other settings (another model file, another tuning) is
    marked."""
    other = beside.label
    found = beside_rows(sets, beside)
    rows = [[s.output, rule_label(s.kind, s.rule), fmt(m.get("mAP")), fmt(m.get("mAP50")), fmt(m.get("mAP75")),
             *(fmt(o.get(k)) + ("" if same else " *") for k in ("mAP", "mAP50", "mAP75"))]
            for s, m, o, same in found]
    if not rows:
        return None
    notes = [f"`{other}`: the same methods in another evaluation, {beside.source}; '–' where it has none.",
             "Same protocol (COCO, circle IoU), other data: the columns compare how each method carries over, not "
             "one dataset's difficulty with the other's."]
    if not all(same for *_, same in found):
        notes.append(f"*: there the method ran with other settings (another model file or configuration): not the "
                     f"same detector on both datasets. Rerun the evaluation of `{other}` to compare.")
    return Table(name=f"table3_{label}_beside_{other}", title=f"Table 3 on `{label}` beside `{other}`",
                 columns=["method", "2D rule", f"`{label}` mAP", "mAP.50", "mAP.75", f"`{other}` mAP",
                          "mAP.50", "mAP.75"], rows=rows, notes=notes)


def beside_reading(label: str, sets: Sequence, beside: Beside) -> list[str]:
    """One sentence: the main methods' mAP / mAP.50 / mAP.75 on ``label`` against the other dataset."""
    other = beside.label
    by = {s.output: (m, o, same) for s, m, o, same in beside_rows(sets, beside)}
    parts = []
    for name in BESIDE_READING:
        if name in by and by[name][1].get("mAP") is not None:
            m, o, same = by[name]
            parts.append(f"{name} {m['mAP']:.3f} / {m['mAP50']:.3f} / {m['mAP75']:.3f} against "
                         f"{o['mAP']:.3f} / {o['mAP50']:.3f} / {o['mAP75']:.3f}"
                         + ("" if same else f" (run with other settings on `{other}`: not comparable)"))
    if not parts:
        return []
    ip = by.get("improved" + PAPER_CIRCLE)
    tail = ""
    if ip is not None and ip[1].get("mAP") is not None and ip[2]:
        tail = (f"; the improved detector with the paper's projection {ip[0]['mAP']:.3f} against "
                f"{ip[1]['mAP']:.3f}")
    return [f"Table 3 on `{label}` beside `{other}` (mAP / mAP.50 / mAP.75): " + "; ".join(parts) + tail + "."]
