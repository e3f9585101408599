"""Do a candidate's sector edges run on past its outline, as a checkerboard's lines do?

A marker's four sector edges end where its pattern ends: past the outline lie the printed margin or
the background, and no edge of the same polarity carries on along the same line. A corner inside a
larger checkerboard has the same four edges, but they run on to the next corners, a whole cell
away. Where the detector's outline closes well inside the cells (a cast shadow whose edge runs
through the corner, shading across a cell), the checker shows no neighbouring saddle within reach
and no inverted surroundings just outside the outline; its edges still run on. This module counts
the sector edges that do, from 1.3 to 3 times the outline's distance along each edge.

Pixel coordinates follow OpenCV (the centre of the top-left pixel is (0, 0)); distances are in pixels
of the image given; angles are in radians in the image frame (x right, y down).
"""
from __future__ import annotations

import math

import cv2
import numpy as np

EDGE_RINGS = (0.4, 0.6)  # rings the sector edges are read on, times the marker radius
RING_MIN_PX = 3.0
# Chosen on ten seen sets (46000-47100: 9,419 true and 67 false markers kept by the gray pass): with
# these, no true marker shows four edges running on, and four false ones do (47100/61). Stopping at
# 2.0 instead of 3.0 outline distances added a true diagonal whose outline had closed at half its
# pattern (its edges ran on to its corners, about twice as far, and stopped there), and wider
# tolerances across the line (0.06, 0.12) or smaller steps (0.35) true markers on textured walls.
ALONG = np.linspace(1.3, 3.0, 11)  # where along an edge it is looked for, times the outline distance
ACROSS = 0.03  # how far to either side of the edge's line (times the distance along it), plus 1.5 px
STEP_HALF = 0.05  # half-width of the step measured across the edge, times the distance (at least 2 px)
STEP_MIN = 0.5  # a step of at least this share of the marker's contrast, with the edge's own sign
PRESENT_MIN = 10  # of the len(ALONG) places along an edge: then it runs on (one may miss: noise, a twig)


def sector_edges(gray: np.ndarray, x: float, y: float, radius: float,
                 levels: tuple[float, float]) -> tuple[np.ndarray, np.ndarray] | None:
    """The four sector edges of the candidate at (x, y): their directions (radians) and signs (+1
    where the grey rises across the edge towards larger angles, clockwise on the screen with y
    down, -1 where it falls). Read where rings of EDGE_RINGS times ``radius`` cross the middle of
    the dark and bright ``levels``; None unless both rings cross it exactly four times, alternately,
    at directions that agree within 10 degrees."""
    mid = 0.5 * (float(levels[0]) + float(levels[1]))
    found = []
    for f in EDGE_RINGS:
        r = max(RING_MIN_PX, f * radius)
        n = int(np.clip(round(2.0 * math.pi * r), 64, 1024))
        th = np.arange(n) * (2.0 * math.pi / n)
        v = _sample(gray, x + r * np.cos(th), y + r * np.sin(th))
        if not np.isfinite(v).all():
            return None
        above = v > mid
        cross = np.nonzero(above != np.roll(above, -1))[0]  # between sample i and i + 1
        if len(cross) != 4:
            return None
        v0, v1 = v[cross] - mid, v[(cross + 1) % n] - mid
        frac = v0 / (v0 - v1)
        found.append(((cross + frac) * (2.0 * math.pi / n), np.where(v1 > v0, 1.0, -1.0)))
    (a0, s0), (a1, s1) = found
    turn = np.angle(np.exp(1j * (a1 - a0)))
    if not (np.array_equal(s0, s1) and np.abs(turn).max() < math.radians(10.0)):
        return None
    return np.angle(np.exp(1j * (a0 + 0.5 * turn))), s0


def edges_running_on(gray: np.ndarray, x: float, y: float, radius: float, levels: tuple[float, float],
                     outline: np.ndarray | None = None) -> int:
    """How many of the candidate's four sector edges (:func:`sector_edges`) run on past its outline:
    at PRESENT_MIN or more of the places ALONG times the outline's distance along the edge (``radius``
    where no ``outline``, a closed (k, 2) polygon around (x, y), is given), a step across the edge's
    line of at least STEP_MIN of the contrast, with the edge's own sign, within ACROSS of the line.
    Samples outside the image count as no step (a marker at the border keeps its edges). 0 where the
    edges cannot be read."""
    got = sector_edges(gray, x, y, radius, levels)
    C = float(levels[1]) - float(levels[0])
    if got is None or not C > 0:
        return 0
    phi, sign = got
    if outline is None:
        dist = np.full(4, float(radius))
    else:
        dist = ray_distances(outline - [x, y], np.cos(phi), np.sin(phi))
    t = dist[:, None] * ALONG[None, :]  # (4, m) distances along each edge
    half = np.maximum(2.0, STEP_HALF * t)
    reach = ACROSS * t + 1.5
    k = 17  # positions across the line, each side of the step sampled at +-half
    u = np.linspace(-1.0, 1.0, k)[None, None, :] * reach[..., None]  # (4, m, k)
    ex, ey = np.cos(phi)[:, None, None], np.sin(phi)[:, None, None]
    nx, ny = -ey, ex  # towards larger angles
    px, py = x + t[..., None] * ex, y + t[..., None] * ey
    hi = _sample(gray, px + (u + half[..., None]) * nx, py + (u + half[..., None]) * ny)
    lo = _sample(gray, px + (u - half[..., None]) * nx, py + (u - half[..., None]) * ny)
    step = sign[:, None, None] * (hi - lo)
    present = np.nan_to_num(step, nan=-np.inf).max(axis=2) >= STEP_MIN * C
    return int((present.sum(axis=1) >= PRESENT_MIN).sum())


def ray_distances(poly: np.ndarray, cos: np.ndarray, sin: np.ndarray) -> np.ndarray:
    """Distance from the origin to the polygon ``poly`` (k, 2, relative to the centre) along each ray
    of direction (``cos``, ``sin``), all rays against all edges at once; inf where a ray does not
    meet it."""
    E = np.roll(poly, -1, 0) - poly  # edges p -> p + e
    c, s = cos[:, None], sin[:, None]
    den = c * E[None, :, 1] - s * E[None, :, 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (poly[None, :, 0] * E[None, :, 1] - poly[None, :, 1] * E[None, :, 0]) / den
        w = (poly[None, :, 0] * s - poly[None, :, 1] * c) / den
    hit = (np.abs(den) >= 1e-12) & (t > 0) & (w >= -1e-9) & (w <= 1 + 1e-9)
    return np.where(hit, t, np.inf).min(1)


def _sample(gray: np.ndarray, xs: np.ndarray, ys: np.ndarray) -> np.ndarray:
    """Bilinear samples of ``gray`` at (xs, ys), any shape; NaN outside the image. Only the window the
    points span is converted, never the whole image; for :func:`edges_running_on` that is up to 6
    outline distances across (a diagonal marker of 400 px radius at 45 MP: about 45 MB of float32,
    for a few milliseconds)."""
    xs, ys = np.asarray(xs, np.float64), np.asarray(ys, np.float64)
    h, w = gray.shape[:2]
    out = np.full(xs.shape, np.nan)
    inside = (xs >= 0) & (ys >= 0) & (xs <= w - 1) & (ys <= h - 1)
    if not inside.any():
        return out
    x0, y0 = int(math.floor(xs[inside].min())), int(math.floor(ys[inside].min()))
    x1, y1 = min(int(math.ceil(xs[inside].max())) + 2, w), min(int(math.ceil(ys[inside].max())) + 2, h)
    win = np.asarray(gray[y0:y1, x0:x1], np.float32)
    mx = (xs[inside] - x0).astype(np.float32).reshape(1, -1)
    my = (ys[inside] - y0).astype(np.float32).reshape(1, -1)
    out[inside] = cv2.remap(win, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)[0]
    return out


__all__ = ["sector_edges", "edges_running_on", "ray_distances"]
