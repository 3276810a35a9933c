"""COCO evaluation with circle IoU: CircleNet's official protocol, on pycocotools.

pycocotools' ``COCOeval`` does the matching and the accumulation; only its IoU changes:
``CircleCOCOeval.computeIoU`` returns the exact circle IoU (``circle_iou``) of the
``circle_center`` / ``circle_radius`` fields instead of box IoU. Parameters: IoU thresholds
0.50:0.05:0.95, 101 recall points (0:0.01:1, COCO's interpolated precision), maxDets
[1, 10, 1000], one area = pi r^2 per circle (ground truth and detections alike), so that COCO's
area ranges (small < 32^2 px^2 < medium < 96^2 px^2 < large) apply to circles.

Inputs
- Ground truth: a COCO dict or JSON file: images [{id, ...}], categories [{id, name}],
  annotations [{id, image_id, category_id, circle_center [x, y], circle_radius, iscrowd}]
  (``area`` and ``bbox`` are recomputed from the circle). An image with no annotation is a
  negative: every detection on it is a false positive.
- Results: a list of {image_id, category_id, circle_center [x, y], circle_radius, score}, pixels.

Quirks of pycocotools handled here
- ``COCO.loadRes`` needs ``bbox`` (or ``segmentation``) and fails on an empty list; it sets a
  detection's area to the box area (4 r^2). Results get a bbox from the circle, an empty list
  gets an empty result set, and areas are reset to pi r^2 after loading.
- ``evaluateImg`` records a match as the matched annotation id, 0 meaning "none": ground-truth
  ids must be non-zero and unique, so they are renumbered 1..N when they are not.
- ``getAnnIds(imgIds=[])`` means *all* images, so an empty subset is refused.
- ``summarize`` reads its first AP at maxDets 100, absent here; the summary is computed from
  ``eval['precision']`` / ``eval['recall']`` the same way (mean over entries > -1) instead.
- pycocotools prints progress; it is silenced unless ``verbose``.
A figure with no ground truth to score against (e.g. a family of negatives only) is NaN.
"""

from __future__ import annotations

import contextlib
import copy
import io
import math
import numbers
from pathlib import Path
from typing import Callable

import numpy as np
from pycocotools.coco import COCO
from pycocotools.cocoeval import COCOeval

from spherebench.circles import circle_bbox
from spherebench.errors import SphereBenchError
from spherebench.eval.metrics.circle_iou import circle_intersection_matrix, circle_iou_matrix
from spherebench.reading import read_json

#: COCO's IoU thresholds, 0.50:0.05:0.95 (linspace, as pycocotools, to avoid arange drift).
IOU_THRESHOLDS = np.linspace(0.5, 0.95, 10)
#: CircleNet's maximum detections per image.
MAX_DETS = (1, 10, 1000)
#: COCO's area ranges (px^2), applied to pi r^2.
AREA_RANGES = {"all": (0.0, 1e10), "small": (0.0, 32.0 ** 2), "medium": (32.0 ** 2, 96.0 ** 2),
               "large": (96.0 ** 2, 1e10)}


def _quiet(verbose: bool):
    return contextlib.nullcontext() if verbose else contextlib.redirect_stdout(io.StringIO())


def _is_number(v) -> bool:
    """A number (Python's or numpy's), not a bool and not a text that spells one."""
    return isinstance(v, numbers.Real) and not isinstance(v, bool)


def _circle_of(ann: dict, what: str) -> tuple[float, float, float]:
    """(cx, cy, r) px of an annotation or result, checked."""
    try:
        (cx, cy), r = ann["circle_center"], ann["circle_radius"]
    except (KeyError, TypeError, ValueError):
        cx = cy = r = None
    if not all(_is_number(v) for v in (cx, cy, r)):  # "37.5", a text, is no radius of a file of ours
        raise SphereBenchError(f"{what} lacks a valid circle_center [x, y] and circle_radius "
                               "(CircleNet's fields, pixels, as numbers)")
    cx, cy, r = float(cx), float(cy), float(r)
    if not (math.isfinite(cx) and math.isfinite(cy) and math.isfinite(r)) or r < 0:
        raise SphereBenchError(f"{what} has a non-finite circle or a negative radius: {ann['circle_center']}, {r}")
    return cx, cy, r


def _with_circle_geometry(ann: dict, circle: tuple[float, float, float]) -> dict:
    cx, cy, r = circle
    ann["bbox"] = circle_bbox(cx, cy, r)
    ann["area"] = math.pi * r * r
    return ann


def load_ground_truth(gt: dict | str | Path, verbose: bool = False) -> COCO:
    """A pycocotools COCO object from a circle GT dict or JSON file (the dict is not modified)."""
    source = "ground truth"
    if isinstance(gt, (str, Path)):
        source = f"{gt}: ground truth"
        gt = read_json(gt)  # the reading gate: one line for a missing, damaged or hostile file
    keys = ("images", "annotations", "categories")
    if not isinstance(gt, dict) or not all(isinstance(gt.get(k), list) for k in keys):
        raise SphereBenchError(f"{source} must be a COCO dict with lists 'images', 'annotations' and 'categories'")
    if not all(isinstance(x, dict) and ("id" in x or k == "annotations") for k in keys for x in gt[k]):
        raise SphereBenchError(f"{source}: its images, annotations and categories must be dicts (images and "
                               "categories with an 'id')")
    if not gt["images"] or not gt["categories"]:
        raise SphereBenchError(f"{source} has no images or no categories: nothing to evaluate on")
    data = {k: copy.deepcopy(gt[k]) for k in ("images", "annotations", "categories")}
    image_ids = {img.get("id") for img in data["images"]}
    ids = [a.get("id") for a in data["annotations"]]
    renumber = any(not isinstance(i, int) or i == 0 for i in ids) or len(set(ids)) != len(ids)
    for k, ann in enumerate(data["annotations"]):
        if ann.get("image_id") not in image_ids:
            raise SphereBenchError(f"ground-truth annotation {ann.get('id')} refers to image {ann.get('image_id')}, "
                                   "which is not in 'images'")
        _with_circle_geometry(ann, _circle_of(ann, f"ground-truth annotation {ann.get('id')}"))
        ann["iscrowd"] = int(ann.get("iscrowd", 0))
        if renumber:  # a match is stored as the gt id, 0 = none: ids must be non-zero and unique
            ann["id"] = k + 1
    coco = COCO()
    coco.dataset = data
    with _quiet(verbose):
        coco.createIndex()
    return coco


def load_results(coco_gt: COCO, results: list[dict], verbose: bool = False) -> COCO:
    """Detections as a pycocotools result set (``loadRes``), with bbox and area from the circle.

    results: [{image_id, category_id, circle_center [x, y], circle_radius, score}], pixels; the
    list is not modified. An empty list gives an empty result set.
    """
    if not isinstance(results, list):
        raise SphereBenchError("results must be a list of {image_id, category_id, circle_center, circle_radius, score}")
    known_images = set(coco_gt.getImgIds())
    known_cats = set(coco_gt.getCatIds())
    anns = []
    for i, res in enumerate(results):
        if not isinstance(res, dict):
            raise SphereBenchError(f"result {i} is not a dict")
        circle = _circle_of(res, f"result {i}")
        if res.get("image_id") not in known_images:
            raise SphereBenchError(f"result {i} is on image {res.get('image_id')}, which the ground truth does not "
                                   "have: score results against the dataset they were computed on")
        if res.get("category_id") not in known_cats:
            raise SphereBenchError(f"result {i} has category_id {res.get('category_id')}, not one of the ground "
                                   f"truth's {sorted(known_cats)}")
        if not _is_number(res.get("score")):
            raise SphereBenchError(f"result {i} lacks a numeric score")
        score = float(res["score"])
        if not math.isfinite(score):
            raise SphereBenchError(f"result {i} has a non-finite score")
        ann = {k: v for k, v in res.items() if k not in ("bbox", "segmentation", "area", "id")}
        ann["score"] = score
        anns.append(_with_circle_geometry(ann, circle))
    if not anns:  # loadRes indexes anns[0]
        coco = COCO()
        coco.dataset = {"images": list(coco_gt.dataset["images"]), "annotations": [],
                        "categories": copy.deepcopy(coco_gt.dataset["categories"])}
        with _quiet(verbose):
            coco.createIndex()
        return coco
    with _quiet(verbose):
        coco = coco_gt.loadRes(anns)
    for ann in coco.dataset["annotations"]:  # loadRes set the box area, 4 r^2
        ann["area"] = math.pi * float(ann["circle_radius"]) ** 2
    return coco


class CircleCOCOeval(COCOeval):
    """pycocotools' COCOeval with circle IoU and CircleNet's parameters (maxDets 1, 10, 1000).

    keep_gt: None, or a predicate on a ground-truth annotation: the annotations it rejects become
    COCO's ignored ground truth (as those outside an area range): a detection matched to one
    counts neither as a true nor as a false positive, and an unmatched detection stays a false
    positive.
    """

    def __init__(self, coco_gt: COCO, coco_dt: COCO, keep_gt: Callable[[dict], bool] | None = None):
        super().__init__(coco_gt, coco_dt, iouType="bbox")  # 'bbox' selects the detection params
        self.params.iouThrs = IOU_THRESHOLDS.copy()
        self.params.maxDets = list(MAX_DETS)
        self.params.areaRng = [list(v) for v in AREA_RANGES.values()]
        self.params.areaRngLbl = list(AREA_RANGES)
        self.keep_gt = keep_gt

    def _prepare(self):
        super()._prepare()  # sets every annotation's 'ignore' to its iscrowd, each evaluation anew
        if self.keep_gt is not None:
            for gts in self._gts.values():
                for g in gts:
                    if not self.keep_gt(g):
                        g["ignore"] = 1

    def computeIoU(self, imgId, catId):  # noqa: N802 (pycocotools' name)
        """Circle IoU (D, G) of one image's detections (score order, top maxDets) and ground truths."""
        p = self.params
        if p.useCats:
            gt, dt = self._gts[imgId, catId], self._dts[imgId, catId]
        else:
            gt = [g for c in p.catIds for g in self._gts[imgId, c]]
            dt = [d for c in p.catIds for d in self._dts[imgId, c]]
        if len(gt) == 0 and len(dt) == 0:
            return []
        order = np.argsort([-d["score"] for d in dt], kind="mergesort")  # as evaluateImg orders them
        dt = [dt[i] for i in order[:p.maxDets[-1]]]
        d_c = np.array([[*d["circle_center"], d["circle_radius"]] for d in dt], dtype=np.float64).reshape(-1, 3)
        g_c = np.array([[*g["circle_center"], g["circle_radius"]] for g in gt], dtype=np.float64).reshape(-1, 3)
        ious = circle_iou_matrix(d_c, g_c)
        crowd = np.array([bool(g["iscrowd"]) for g in gt], dtype=bool)
        if crowd.any() and len(dt):  # COCO's crowd rule: intersection over the detection's area
            det_area = np.pi * d_c[:, 2:3] ** 2
            inter = circle_intersection_matrix(d_c, g_c[crowd])
            ious[:, crowd] = np.divide(inter, det_area, out=np.zeros_like(inter), where=det_area > 0)
        return ious


def _mean_valid(values: np.ndarray) -> float:
    """Mean over entries > -1 (pycocotools' summary rule); NaN when there are none."""
    v = values[values > -1]
    return float(np.mean(v)) if v.size else float("nan")


def evaluate_circles(gt: dict | str | Path | COCO, results: list[dict], image_ids=None,
                     verbose: bool = False, keep_gt: Callable[[dict], bool] | None = None) -> dict:
    """COCO metrics with circle IoU of ``results`` against ``gt``, optionally on a subset of images.

    gt: a COCO dict, a JSON file, or a COCO object from ``load_ground_truth``.
    results: [{image_id, category_id, circle_center [x, y], circle_radius, score}], pixels.
    image_ids: the images to score (detections elsewhere are ignored); None = all.
    keep_gt: score only the ground truth this predicate accepts (an annotation dict, with its own
    fields such as center_m); the rest is ignored ground truth (``CircleCOCOeval``), e.g. the
    balls outside a range band. None = all.
    Returns floats (NaN where no ground truth is in scope):
      mAP (AP at IoU .50:.95, maxDets 1000), mAP50, mAP75, mAP_small/medium/large,
      mAR (AR at IoU .50:.95, maxDets 1000), mAR1, mAR10, mAR_small/medium/large,
      n_images, n_gt, n_detections (in scope);
    and arrays for figures: precision (T, R, K, A, M) as pycocotools (-1 = undefined),
      scores (T, R, K, A, M), pr_precision (T, R) = precision at area 'all' and maxDets 1000,
      averaged over categories (NaN undefined), recall_thresholds (R,), iou_thresholds (T,),
      max_dets (M,), area_labels (A,).
    """
    coco_gt = gt if isinstance(gt, COCO) else load_ground_truth(gt, verbose=verbose)
    coco_dt = load_results(coco_gt, results, verbose=verbose)
    ev = CircleCOCOeval(coco_gt, coco_dt, keep_gt=keep_gt)
    all_ids = sorted(coco_gt.getImgIds())
    if image_ids is not None:
        subset = sorted(set(image_ids))
        if not subset:
            raise SphereBenchError("the image subset is empty: pass at least one image id (or None for all)")
        missing = set(subset) - set(all_ids)
        if missing:
            raise SphereBenchError(f"image ids {sorted(missing)[:5]} are not in the ground truth")
        ev.params.imgIds = subset
    with _quiet(verbose):
        ev.evaluate()
        ev.accumulate()
    p = ev.params
    precision, recall = ev.eval["precision"], ev.eval["recall"]
    a_all, m_max = p.areaRngLbl.index("all"), len(p.maxDets) - 1
    t50 = int(np.argmin(np.abs(p.iouThrs - 0.5)))
    t75 = int(np.argmin(np.abs(p.iouThrs - 0.75)))
    out = {
        "mAP": _mean_valid(precision[:, :, :, a_all, m_max]),
        "mAP50": _mean_valid(precision[t50, :, :, a_all, m_max]),
        "mAP75": _mean_valid(precision[t75, :, :, a_all, m_max]),
        "mAR": _mean_valid(recall[:, :, a_all, m_max]),
        "mAR1": _mean_valid(recall[:, :, a_all, p.maxDets.index(1)]),
        "mAR10": _mean_valid(recall[:, :, a_all, p.maxDets.index(10)]),
    }
    for lbl in ("small", "medium", "large"):
        a = p.areaRngLbl.index(lbl)
        out[f"mAP_{lbl}"] = _mean_valid(precision[:, :, :, a, m_max])
        out[f"mAR_{lbl}"] = _mean_valid(recall[:, :, a, m_max])
    scope = set(p.imgIds)
    out["n_images"] = len(scope)
    out["n_gt"] = sum(1 for a in coco_gt.dataset["annotations"] if a["image_id"] in scope and not a["iscrowd"]
                      and (keep_gt is None or keep_gt(a)))
    out["n_detections"] = sum(1 for a in coco_dt.dataset["annotations"] if a["image_id"] in scope)
    pr = precision[:, :, :, a_all, m_max].astype(np.float64)  # (T, R, K)
    valid = pr > -1
    with np.errstate(invalid="ignore"):
        out["pr_precision"] = np.where(valid.any(axis=2), np.where(valid, pr, 0.0).sum(axis=2) / valid.sum(axis=2),
                                       np.nan)
    out["precision"] = precision
    out["scores"] = ev.eval["scores"]
    out["recall_thresholds"] = np.asarray(p.recThrs, dtype=np.float64)
    out["iou_thresholds"] = np.asarray(p.iouThrs, dtype=np.float64)
    out["max_dets"] = np.asarray(p.maxDets)
    out["area_labels"] = list(p.areaRngLbl)
    if verbose:
        print(format_summary(out))
    return out


def evaluate_by_family(gt: dict | str | Path, results: list[dict], verbose: bool = False) -> dict[str, dict]:
    """``evaluate_circles`` over all images ("all") and per scene family (images' ``family`` field)."""
    coco_gt = load_ground_truth(gt, verbose=verbose)
    families: dict[str, list] = {}
    for img in coco_gt.dataset["images"]:
        families.setdefault(str(img.get("family", "unknown")), []).append(img["id"])
    out = {"all": evaluate_circles(coco_gt, results, verbose=verbose)}
    for fam in sorted(families):
        out[fam] = evaluate_circles(coco_gt, results, image_ids=families[fam], verbose=verbose)
    return out


def scalar_metrics(metrics: dict) -> dict:
    """The JSON-ready part of ``evaluate_circles``' output: floats (NaN -> None) and counts."""
    out = {}
    for k, v in metrics.items():
        if isinstance(v, (float, int, np.floating, np.integer)) and not isinstance(v, bool):
            v = float(v) if isinstance(v, (float, np.floating)) else int(v)
            out[k] = None if isinstance(v, float) and math.isnan(v) else v
    return out


def format_summary(metrics: dict) -> str:
    """COCO-style summary lines of ``evaluate_circles``' output."""
    rows = [("AP", "0.50:0.95", "all", 1000, "mAP"), ("AP", "0.50", "all", 1000, "mAP50"),
            ("AP", "0.75", "all", 1000, "mAP75"), ("AP", "0.50:0.95", "small", 1000, "mAP_small"),
            ("AP", "0.50:0.95", "medium", 1000, "mAP_medium"), ("AP", "0.50:0.95", "large", 1000, "mAP_large"),
            ("AR", "0.50:0.95", "all", 1, "mAR1"), ("AR", "0.50:0.95", "all", 10, "mAR10"),
            ("AR", "0.50:0.95", "all", 1000, "mAR"), ("AR", "0.50:0.95", "small", 1000, "mAR_small"),
            ("AR", "0.50:0.95", "medium", 1000, "mAR_medium"), ("AR", "0.50:0.95", "large", 1000, "mAR_large")]
    return "\n".join(f" {'Average Precision' if kind == 'AP' else 'Average Recall':<18} ({kind}) @[ cIoU={iou:<9} | "
                     f"area={area:>6s} | maxDets={md:>4d} ] = {metrics[key]:0.3f}" for kind, iou, area, md, key in rows)


def coco_from_circles(circles_per_image, category_id: int = 1, category_name: str = "basketball",
                      image_size: tuple[int, int] | None = None) -> dict:
    """A circle GT dict from per-image circles: a list of (G_i, 3) arrays (cx, cy, r) px.

    Image ids are 0..N-1 in list order; ``image_size`` = (width, height) is recorded if given.
    For tuning and tests; datasets have their own coco_gt.json.
    """
    images, anns = [], []
    for img_id, circles in enumerate(circles_per_image):
        img = {"id": img_id, "file_name": f"{img_id}.png"}
        if image_size is not None:
            img["width"], img["height"] = int(image_size[0]), int(image_size[1])
        images.append(img)
        for cx, cy, r in np.asarray(circles, dtype=np.float64).reshape(-1, 3):
            anns.append(_with_circle_geometry({"id": len(anns) + 1, "image_id": img_id, "category_id": category_id,
                                               "circle_center": [float(cx), float(cy)], "circle_radius": float(r),
                                               "iscrowd": 0}, (cx, cy, r)))
    return {"images": images, "annotations": anns, "categories": [{"id": category_id, "name": category_name}]}


def results_from_circles(detections_per_image, category_id: int = 1) -> list[dict]:
    """Results list from per-image detections: a list of (D_i, 4) arrays (cx, cy, r, score), pixels.

    Image ids are 0..N-1 in list order, matching ``coco_from_circles``.
    """
    out = []
    for img_id, dets in enumerate(detections_per_image):
        for cx, cy, r, s in np.asarray(dets, dtype=np.float64).reshape(-1, 4):
            out.append({"image_id": img_id, "category_id": category_id, "circle_center": [float(cx), float(cy)],
                        "circle_radius": float(r), "score": float(s)})
    return out
