"""The benchmark's evaluation. The package exports its pure metrics (circle IoU, COCO evaluation
with circle IoU, CircleNet's protocol; 3D centre metrics; the paper's Table 2), which import
nothing above them: the baselines use them. The runner and the reports (``eval.registry``,
``runner``, ``report``, ...) sit above the detector and the baselines, and are imported by name,
never from here."""

from spherebench.eval.circle_iou import (circle_intersection_area, circle_intersection_matrix, circle_iou,
                                        circle_iou_matrix)
from spherebench.eval.coco_eval import (CircleCOCOeval, coco_from_circles, evaluate_by_family, evaluate_circles,
                                        format_summary, load_ground_truth, load_results, results_from_circles,
                                        scalar_metrics)
from spherebench.eval.metrics3d import (SceneMatch, detection_counts, detection_rates, error_stats, error_vs_distance,
                                        match_scene, scene_counts, signed_error_stats, summarize_3d)
from spherebench.eval.table2 import barycentre, sphere_rmse, table2_row

__all__ = [
    "circle_intersection_area", "circle_intersection_matrix", "circle_iou", "circle_iou_matrix",
    "CircleCOCOeval", "coco_from_circles", "evaluate_by_family", "evaluate_circles", "format_summary",
    "load_ground_truth", "load_results", "results_from_circles", "scalar_metrics",
    "SceneMatch", "detection_counts", "detection_rates", "error_stats", "error_vs_distance", "match_scene",
    "scene_counts", "signed_error_stats", "summarize_3d", "barycentre", "sphere_rmse", "table2_row",
]
