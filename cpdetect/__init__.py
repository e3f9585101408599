"""cpdetect: find 2x2 checkerboard control-point markers in photographs and georeference 3D models.

Importing cpdetect never imports torch; the learned detector is loaded only when asked for.
"""
from .detector import Detector, available_detectors, get_detector, register_detector
from .types import MARKER_TYPES, DetectionResult, MarkerDetection

__version__ = "0.1.0"
__all__ = ["Detector", "DetectionResult", "MarkerDetection", "MARKER_TYPES", "available_detectors",
           "get_detector", "register_detector", "__version__"]
