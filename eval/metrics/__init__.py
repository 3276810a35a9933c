"""The pure metrics: arrays and COCO dictionaries in, figures out; they import only the core, so
the baselines may score with them. ``spherebench.eval`` re-exports the common ones.

    circle_iou   circle intersection and IoU, one pair or all pairs
    coco_eval    COCO evaluation with circle IoU (CircleNet's protocol, on pycocotools)
    metrics3d    3D centre matching, detection rates and errors
    table2       the paper's Table 2 (sphere RMSE, barycentre)
    sensor_grid  rates per sensor condition and range band of a grid preset
    targets      the robustness targets and verdicts of the improved detector
    calibration  the scores' calibration: correct detections, reliability bins, ECE
"""
