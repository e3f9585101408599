"""The probability map the ``hma`` detector returns, from the image and its mirror image.

The network is not mirror-symmetric: the map of a left-right mirrored image, mirrored back, differs
from the map of the image by a pixel or two along the marker outlines. Their mean follows the true
outlines more closely (on the train-split dev sets 808 and 909, 300 images each, pixel IoU 0.9333
-> 0.9409 and 0.9280 -> 0.9328, 2026-11-28). The markers themselves still come from the map of the
image alone (the instance model and the centre ranker were fitted on such maps; deciding on the
mean found 4 and 2 markers fewer there), so the mirror pass changes the returned map only.
It is opt-in (``HMASettings.mirror_map``): on six fresh test-split sets it helped three and hurt
three (a blob sure in one pass and not in the mean is cleared, marker or not).

Maps are P(marker) in [0, 1], float32, on the processing grid of :func:`learned.infer.probability_map`
(``f`` map pixels per image pixel); image points follow OpenCV (the centre of the top-left pixel is
(0, 0)).
"""
from __future__ import annotations

from collections.abc import Callable, Sequence

import cv2
import numpy as np

from cpdetect.types import MarkerDetection


def mirrored_mean(gray: np.ndarray, prob: np.ndarray, probability: Callable[[np.ndarray], np.ndarray]) -> np.ndarray:
    """The mean of ``prob`` (the map of ``gray``) and of the map of ``gray`` mirrored left to right,
    mirrored back; ``probability``: gray image -> its map, on the same grid as ``prob``."""
    mirrored = probability(np.ascontiguousarray(gray[:, ::-1]))
    if mirrored.shape != prob.shape:
        raise ValueError(f"the mirror image's map is {mirrored.shape}, the image's {prob.shape}")
    return np.ascontiguousarray(0.5 * (prob + mirrored[:, ::-1]), dtype=np.float32)


def keep_marker_blobs(prob: np.ndarray, markers: Sequence[MarkerDetection], f: float, threshold: float,
                      sure_mean_p: float, witnesses: Sequence[MarkerDetection] | None = None) -> np.ndarray:
    """``prob`` with the blobs (8-connected, P >= ``threshold``) that hold none of ``markers`` set to
    0, unless their mean P is at least ``sure_mean_p`` (and, when ``witnesses`` is given, one of
    those lies on them): the rule by which :class:`learned.adapter.HMADetector` clears the map of
    the blobs it rejects, applied to another map. A marker holds the blob under its centre."""
    binary = (prob >= threshold).astype(np.uint8)
    n, labels = cv2.connectedComponents(binary, connectivity=8)
    if n <= 1:
        return prob

    def labels_at(points: Sequence[MarkerDetection]) -> np.ndarray:
        h, w = labels.shape
        col = [min(max(int(round((d.x + 0.5) * f - 0.5)), 0), w - 1) for d in points]
        row = [min(max(int(round((d.y + 0.5) * f - 0.5)), 0), h - 1) for d in points]
        return labels[row, col] if points else np.zeros(0, np.int32)

    area = np.bincount(labels.ravel(), minlength=n)
    total = np.bincount(labels.ravel(), weights=prob.ravel(), minlength=n)
    keep = total >= sure_mean_p * np.maximum(area, 1)
    if witnesses is not None:
        witnessed = np.zeros(n, bool)
        witnessed[labels_at(witnesses)] = True
        keep &= witnessed
    keep[labels_at(markers)] = True
    keep[0] = True  # below the threshold: left as it is
    return np.where(keep[labels], prob, np.float32(0.0)).astype(np.float32, copy=False)


__all__ = ["mirrored_mean", "keep_marker_blobs"]
