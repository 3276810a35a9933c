"""SphereBench: known-radius sphere detection in depth-camera point clouds.

Import map (the repository's top-level folders, installed under one root):
    spherebench.datasets   <- datasets/   scene simulator, recorded-data preparation, all file I/O
    spherebench.method     <- method/     the 3D sphere detector (arrays in, spheres out)
    spherebench.baselines  <- baselines/  2D and 3D baselines (CircleNet-style, Hough, pyransac3d)
    spherebench.eval       <- eval/       metrics (circle IoU, COCO mAP, 3D errors) and tables
    spherebench.camera     pinhole camera with librealsense's distortion models
    spherebench.cloud      the point-cloud container that flows between the stages
"""

import os

__version__ = "0.1.0"

# ONNX Runtime (the fitted verdict, CircleNet) writes a device id and an event store for its telemetry
# under ~/.cache/Microsoft/DeveloperTools/.onnxruntime when it loads, unless told not to: set here, at
# the package's import, before any module loads it (worker processes inherit it). A user's own
# setting is kept (docs/formats.md, "Files outside the output").
os.environ.setdefault("ORT_DISABLE_TELEMETRY", "1")
