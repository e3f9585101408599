"""What flows between the detection stages.

Pixel convention everywhere in cpdetect: OpenCV's. x goes right, y goes down, and the *centre* of the
top-left pixel is (0, 0), so its area spans [-0.5, 0.5] x [-0.5, 0.5]. Exporters convert to the
convention of each output format (see docs/formats.md).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal, Optional

import numpy as np

MarkerType = Literal["square", "circle", "diagonal"]
MARKER_TYPES: tuple[str, ...] = ("square", "circle", "diagonal")


def check_marker_type(value: str) -> str:
    if value not in MARKER_TYPES:
        raise ValueError(f"unknown marker type {value!r}; valid: {', '.join(MARKER_TYPES)}")
    return value


@dataclass(frozen=True)
class MarkerDetection:
    """One marker found in one image.

    x, y: the aiming point (central X-corner) in original-image pixels, OpenCV convention.
    score: confidence in [0, 1]. type: "square", "circle" or "diagonal".
    radius_px: apparent radius of the checker pattern (radius of the circle of equal image area).
    sigma_px: 1-sigma localisation uncertainty of (x, y) in pixels, used as a weight downstream.
    """

    x: float
    y: float
    score: float
    type: str
    radius_px: float
    sigma_px: float

    def __post_init__(self) -> None:
        check_marker_type(self.type)
        if not (np.isfinite(self.x) and np.isfinite(self.y)):
            raise ValueError("detection position must be finite")
        if not 0.0 <= self.score <= 1.0:
            raise ValueError(f"score {self.score} outside [0, 1]")
        if not (self.radius_px > 0 and self.sigma_px > 0):
            raise ValueError("radius_px and sigma_px must be positive")

    def to_dict(self) -> dict:
        return {"x": float(self.x), "y": float(self.y), "score": float(self.score), "type": self.type,
                "radius_px": float(self.radius_px), "sigma_px": float(self.sigma_px)}

    @classmethod
    def from_dict(cls, d: dict) -> "MarkerDetection":
        return cls(x=float(d["x"]), y=float(d["y"]), score=float(d["score"]), type=str(d["type"]),
                   radius_px=float(d["radius_px"]), sigma_px=float(d["sigma_px"]))


@dataclass
class DetectionResult:
    """Everything a detector says about one image.

    detections: markers found, best score first.
    image_size: (width, height) of the original image in pixels.
    probability: optional float32 map of P(marker) in [0, 1]. It covers the whole image and may be at a
        lower resolution than the image (e.g. the detector's search scale); :meth:`probability_at`
        resizes it to any size with pixel centres aligned (cv2.resize convention).
    """

    detections: list[MarkerDetection]
    image_size: tuple[int, int]
    probability: Optional[np.ndarray] = None
    seconds: float = 0.0
    extras: dict = field(default_factory=dict)

    def probability_at(self, width: int, height: int) -> Optional[np.ndarray]:
        """The probability map resampled to ``width`` x ``height`` (float32), or None."""
        if self.probability is None:
            return None
        import cv2

        p = np.asarray(self.probability, dtype=np.float32)
        if p.shape == (height, width):
            return p
        return np.clip(cv2.resize(p, (width, height), interpolation=cv2.INTER_LINEAR), 0.0, 1.0)
