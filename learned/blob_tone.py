"""How many grey tones the inside of a probability-map blob shows.

A marker shows its dark and its bright paint wherever more than one of its sectors is visible, so a
blob of the HMA map over a marker (a covered one, or one of low contrast, too) has two tones inside
it. The blobs the network is sure of that yield no marker on 45 MP images are mostly plain panels and
dark splotches, one tone from edge to edge (stop 61; the setting ``large_clear_flat_below`` of
learned.adapter). A marker of which only one sector shows is one tone too: its blob is cleared.
"""
from __future__ import annotations

import cv2
import numpy as np

ERODE_FRAC = 0.2  # the blob is eroded by this share of its radius: its outline mixes in the surround
SMOOTH_FRAC = 0.05  # Gaussian sigma over the radius: smooths the sensor noise, keeps the sectors
MIN_PIXELS = 20  # fewer eroded map pixels than this say nothing


def interior_spread(gray: np.ndarray, inside: np.ndarray, bbox: tuple[int, int, int, int], f: float,
                    radius_px: float) -> float | None:
    """The grey spread (levels of an 8-bit image) inside one blob: the 95th minus the 5th percentile of
    the image resampled to the map's grid (INTER_AREA) and smoothed by a Gaussian of sigma
    max(1, 0.05 r), over the blob eroded by a disc of 0.2 r, r being its equal-area radius in map pixels.

    gray: the full-resolution image (H x W); inside: the blob's boolean mask over ``bbox`` (x0, y0, w, h
    in map pixels); f: map pixels per image pixel; radius_px: the blob's equal-area radius in image
    pixels. None when the eroded blob keeps fewer than 20 map pixels or the box holds no image pixel.
    """
    x0, y0, bw, bh = bbox
    h, w = gray.shape[:2]
    ix0, iy0 = max(0, int(x0 / f)), max(0, int(y0 / f))
    ix1, iy1 = min(w, int(np.ceil((x0 + bw) / f))), min(h, int(np.ceil((y0 + bh) / f)))
    if ix1 <= ix0 or iy1 <= iy0 or bw <= 0 or bh <= 0:
        return None
    g = cv2.resize(gray[iy0:iy1, ix0:ix1], (bw, bh), interpolation=cv2.INTER_AREA).astype(np.float32)
    r = radius_px * f
    e = max(1, int(round(ERODE_FRAC * r)))
    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * e + 1, 2 * e + 1))
    core = cv2.erode(inside.astype(np.uint8), disc, borderValue=0).astype(bool)
    if int(core.sum()) < MIN_PIXELS:
        return None
    v = cv2.GaussianBlur(g, (0, 0), max(1.0, SMOOTH_FRAC * r))[core]
    lo, hi = np.percentile(v, (5.0, 95.0))
    return float(hi - lo)
