"""The 3D sphere detector: the paper's pipeline (section 2.5) and the improved one.

    from spherebench.method import detect, config_for
    spheres = detect(cloud, config_for("improved", radius_m=0.12), seed=0)

Arrays in, results out: this package reads no files (see ``spherebench.datasets.inout``).
"""

from spherebench.method.config import IMPROVED, PAPER, PAPER_LSTSQ, PRESETS, DetectorConfig, config_for
from spherebench.method.detector import Sphere, detect, warm_up
from spherebench.method.paper import PaperTrace

__all__ = ["DetectorConfig", "PAPER", "PAPER_LSTSQ", "IMPROVED", "PRESETS", "config_for", "detect", "Sphere",
           "PaperTrace", "warm_up"]
