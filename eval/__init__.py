"""The benchmark's evaluation, in two layers: ``eval.metrics``, the pure metrics (circle IoU, COCO
evaluation with circle IoU, CircleNet's protocol; 3D centre metrics; the paper's Table 2), which
import only the core, so that the baselines may use them; and ``eval.bench``, the benchmark (the
registry, the task loop, the reports, ...), above the detector and the baselines, imported by name,
never from here. This package re-exports the common metrics."""

from spherebench.eval.metrics.circle_iou import (circle_intersection_area, circle_intersection_matrix, circle_iou,
                                                 circle_iou_matrix)
from spherebench.eval.metrics.coco_eval import (CircleCOCOeval, coco_from_circles, evaluate_by_family, evaluate_circles,
                                                format_summary, load_ground_truth, load_results, results_from_circles,
                                                scalar_metrics)
from spherebench.eval.metrics.metrics3d import (SceneMatch, detection_counts, detection_rates, error_stats, error_vs_distance,
                                                match_scene, scene_counts, signed_error_stats, summarize_3d)
from spherebench.eval.metrics.table2 import barycentre, sphere_rmse, table2_row

__all__ = [
    "circle_intersection_area", "circle_intersection_matrix", "circle_iou", "circle_iou_matrix",
    "CircleCOCOeval", "coco_from_circles", "evaluate_by_family", "evaluate_circles", "format_summary",
    "load_ground_truth", "load_results", "results_from_circles", "scalar_metrics",
    "SceneMatch", "detection_counts", "detection_rates", "error_stats", "error_vs_distance", "match_scene",
    "scene_counts", "signed_error_stats", "summarize_3d", "barycentre", "sphere_rmse", "table2_row",
]
