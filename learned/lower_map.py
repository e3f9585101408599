"""The returned probability map of an image the network sees downscaled, corrected by a lower scale.

A 45 MP photograph reaches the network at 2048 pixels; a large marker is then several times the
256-pixel crops the network was trained on, and the (0.5, 1.0) passes leave parts of its inside
under P 0.5. One more pass at a lower scale (0.25: 512 pixels, about the training images' own
scale), fused below the others by the same hierarchical attention (:func:`learned.infer.fuse_lower`),
sees such a marker whole. Deciding the markers on that fused map lost markers cut by the image
border and made a false marker with a huge blob (seen 45 MP sets 30100 / 30200: pixel IoU 0.944 ->
0.920 and 0.974 -> 0.597), so the markers still come from the map of ``scales`` alone, and the
lower map only corrects the map the detector returns (:func:`corrected_by_lower`): a kept marker's
blob takes the lower map's extent where that is higher, and a blob that yields no marker is
cleared where the lower map does not confirm it. The default for images seen downscaled since stop
63 (``large_lower_scale`` 0.25; on fresh 45 MP sets 32000-32500 mean pixel IoU 0.9335 -> 0.9428).

Maps are P(marker) in [0, 1], float32, on the processing grid of
:func:`learned.infer.probability_map`; ``points`` are (column, row) indices on that grid.
"""
from __future__ import annotations

import cv2
import numpy as np


def corrected_by_lower(prob: np.ndarray, lower: np.ndarray, points: list[tuple[int, int]],
                       threshold: float) -> np.ndarray:
    """``prob`` (the map as the detector returns it, rejected blobs already cleared) corrected by
    ``lower`` (the map fused one scale further down). Blobs are 8-connected regions at P >=
    ``threshold``; a blob is kept when one of ``points`` (the detected markers' centres) lies on it.

    - a kept blob, with the blobs of ``lower`` that touch it, becomes the pixel-wise max of both maps
      (the lower map adds a large marker's inside; it never removes a kept marker's pixel);
    - any other blob of ``prob`` whose mean in ``lower`` is under ``threshold`` is cleared;
    - a blob of ``lower`` that touches no kept blob adds nothing (markers come from ``prob``).
    """
    if prob.shape != lower.shape:
        raise ValueError(f"the lower map is {lower.shape}, the returned map {prob.shape}")
    n, labels = cv2.connectedComponents((prob >= threshold).astype(np.uint8), connectivity=8)
    if n <= 1:
        return prob
    kept = np.zeros(n, bool)
    for c, r in points:
        kept[labels[r, c]] = True
    kept[0] = False
    out = prob
    if kept.any():
        on_kept = kept[labels]
        _, grown = cv2.connectedComponents(((lower >= threshold) | on_kept).astype(np.uint8), connectivity=8)
        touching = np.zeros(int(grown.max()) + 1, bool)
        touching[grown[on_kept]] = True
        touching[0] = False
        out = np.where(touching[grown], np.maximum(prob, lower), prob)
    area = np.bincount(labels.ravel(), minlength=n)
    mean_lower = np.bincount(labels.ravel(), weights=lower.ravel(), minlength=n) / np.maximum(area, 1)
    clear = (mean_lower < threshold) & ~kept
    clear[0] = False
    if clear.any():
        out = np.where(clear[labels], np.float32(0.0), out)
    return np.ascontiguousarray(out, dtype=np.float32)


__all__ = ["corrected_by_lower"]
