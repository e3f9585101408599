"""Does a marker's four-sector pattern reach all the way into its centre?

A marker's aiming point is an X-corner: the two dark and the two bright sectors meet in one point, so
the pattern's second angular harmonic is as strong on a small ring around the centre as on the marker
body, up to the blur. Shapes that only look like a marker from farther out do not: two dark blobs
diagonal to each other with a bright gap between them (holes, stains), a window's panes around a
bright mullion cross. This module measures that ratio, with the small ring's radius scaled to the
blur of the marker's own sector edges, so that a blurred X-corner is not taken for a gap; and the
grey at the centre against the sectors' mean (:func:`centre_level_offset`), which a gap too narrow
for the ring, a grid's grout crossing or a checker corner beside an occluder gets wrong.

Pixel coordinates follow OpenCV (the centre of the top-left pixel is (0, 0)); radii are in pixels of
the image given.
"""
from __future__ import annotations

import math

import cv2
import numpy as np

BAND = (0.85, 0.925, 1.0, 1.075, 1.15)  # radii of the edge-blur rings, times half the marker radius
SMOOTH_PX = 1.0  # Gaussian smoothing along them (pixels of arc)
INNER_RADIUS_MIN_PX = 3.0  # the small ring: at least this, and at least INNER_RADIUS_BLURS blur scales
# at 2 blur sigmas a Gaussian-blurred X-corner keeps more than half of its amplitude, whatever sigma
INNER_RADIUS_BLURS = 2.0
# the detectors' cut: analytic markers give 0.55 or more at any blur (0.95 sharp), two blobs 8 to 16 px
# apart 0.22 or less; of the markers the classical detector found on the train-split sets (dev505,
# fit11, train101) one fell below it, found 3.9 px off its partly covered centre
CENTRE_REACH_MIN = 0.3


def ring_samples(gray: np.ndarray, x: float, y: float, radius: float, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Angles (n,) and bilinear samples (n,) of ``gray`` on the circle of ``radius`` around (x, y),
    the image border reflected."""
    th = np.arange(n) * (2.0 * math.pi / n)
    # only the window the circle passes through is converted (a 45 MP image would cost 0.1 s a ring)
    h, w = gray.shape[:2]
    x0, y0 = max(int(math.floor(x - radius)) - 2, 0), max(int(math.floor(y - radius)) - 2, 0)
    x1, y1 = min(int(math.ceil(x + radius)) + 3, w), min(int(math.ceil(y + radius)) + 3, h)
    if x1 <= x0 or y1 <= y0:  # the whole circle lies outside the image: the border reflected
        x0, y0, x1, y1 = 0, 0, w, h
    win = np.asarray(gray[y0:y1, x0:x1], np.float32)
    xs = (x - x0 + radius * np.cos(th)).astype(np.float32)[None, :]
    ys = (y - y0 + radius * np.sin(th)).astype(np.float32)[None, :]
    v = cv2.remap(win, xs, ys, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    return th, v[0].astype(np.float64)


def second_harmonic(gray: np.ndarray, x: float, y: float, radius: float, n: int = 64) -> float:
    """Amplitude of the cos 2t component of the ring of ``radius`` around (x, y) (grey levels)."""
    th, v = ring_samples(gray, x, y, radius, n)
    return math.sqrt(2.0) * abs(np.mean(v * np.exp(-2j * th)))


def edge_blur_px(gray: np.ndarray, x: float, y: float, radius: float) -> float:
    """The blur sigma (pixels) of the sector edges on the ring of half the marker radius (at least
    4 px): the spread of the ring's levels (10th to 90th percentile) over sqrt(2 pi) times the median
    of the four steepest edge gradients along it. Within a few percent of the sigma of a Gaussian
    blur from 1 to 5 px; about 0.6 px on a sharp edge (pixel sampling)."""
    ro = max(4.0, 0.5 * radius)
    n = int(np.clip(round(2.0 * math.pi * ro / 0.5), 64, 4096))  # about 0.5 px of arc per sample
    step = 2.0 * math.pi * ro / n
    # noise would steepen the gradients (a blurred, noisy marker taken for a sharp one): the ring is
    # averaged over a band of radii (the edges are radial) and smoothed along the arc, and that
    # smoothing is taken out of the result again
    v = np.mean([ring_samples(gray, x, y, ro * f, n)[1] for f in BAND], axis=0)
    half = 6  # samples, 3 px of arc: three smoothing sigmas
    k = np.exp(-0.5 * (np.arange(-half, half + 1) * step / SMOOTH_PX) ** 2)
    v = np.convolve(np.concatenate([v[-half:], v, v[:half]]), k / k.sum(), mode="valid")  # around the ring
    grad = np.abs(np.roll(v, -1) - np.roll(v, 1)) / (2.0 * step)
    peaks: list[int] = []
    for i in np.argsort(-grad):
        # one peak per edge: the four steepest at least a sixteenth of a turn apart
        if all(min(abs(int(i) - j), n - abs(int(i) - j)) > n / 16 for j in peaks):
            peaks.append(int(i))
            if len(peaks) == 4:
                break
    g = float(np.median(grad[peaks]))
    spread = float(np.percentile(v, 90) - np.percentile(v, 10))
    sigma = spread / (math.sqrt(2.0 * math.pi) * max(g, 1e-6))
    return math.sqrt(max(sigma ** 2 - SMOOTH_PX ** 2, 0.0))


def centre_reach(gray: np.ndarray, x: float, y: float, radius: float) -> float:
    """Second-harmonic amplitude on a small ring around (x, y) over that on the ring of half the
    marker ``radius``: the small ring's radius is ``INNER_RADIUS_MIN_PX`` or ``INNER_RADIUS_BLURS``
    times the edge blur of :func:`edge_blur_px`, whichever is larger. About 0.55 to 1 on an analytic
    marker at any blur, near 0 where the sectors stop short of the centre."""
    outer = second_harmonic(gray, x, y, max(4.0, 0.5 * radius))
    small = max(INNER_RADIUS_MIN_PX, INNER_RADIUS_BLURS * edge_blur_px(gray, x, y, radius))
    return second_harmonic(gray, x, y, small) / max(outer, 1e-6)


def centre_level_offset(gray: np.ndarray, x: float, y: float, levels: tuple[float, float], dark_share: float,
                        sigma_px: float = 1.0) -> float:
    """How far the grey at the centre (x, y) is from the one an X-corner of those sectors has there,
    in units of the contrast: (G - (D s + B (1 - s))) / (B - D), with G the Gaussian-weighted mean
    (``sigma_px``) of ``gray`` around (x, y), D, B the dark and bright ``levels`` and s the share of
    the full turn the dark sectors take (``dark_share``).

    Straight sector edges through one point make the pattern a cone (its grey depends only on the
    direction), and any isotropic blur, the weighting here included, leaves the grey at the apex equal
    to the pattern's mean over the directions: about 0 on a marker whatever its blur or tilt (a
    perspective view keeps lines through the centre straight). Two dark blobs beside a bright gap
    give up to +0.5, two bright ones beside a dark gap down to -0.5. NaN when the window leaves the
    image or the levels do not differ."""
    D, B = float(levels[0]), float(levels[1])
    h, w = gray.shape[:2]
    n = int(math.ceil(3.0 * sigma_px))
    ix, iy = int(math.floor(x)), int(math.floor(y))
    if not (B - D > 1e-6 and ix - n >= 0 and iy - n >= 0 and ix + n + 1 < w and iy + n + 1 < h):
        return math.nan
    win = np.asarray(gray[iy - n:iy + n + 2, ix - n:ix + n + 2], np.float64)
    gx = np.exp(-0.5 * ((np.arange(ix - n, ix + n + 2) - x) / sigma_px) ** 2)
    gy = np.exp(-0.5 * ((np.arange(iy - n, iy + n + 2) - y) / sigma_px) ** 2)
    g = float(gy @ win @ gx) / float(gy.sum() * gx.sum())
    return (g - (D * dark_share + B * (1.0 - dark_share))) / (B - D)


__all__ = ["ring_samples", "second_harmonic", "edge_blur_px", "centre_reach", "centre_level_offset",
           "INNER_RADIUS_MIN_PX", "INNER_RADIUS_BLURS", "CENTRE_REACH_MIN"]
