"""The marker type from the grey levels of the whole marker area: each type's outline, drawn in the
frame of the marker's four checker half-lines and blurred as the image is, fitted to the pixels.

The type trees (:mod:`cpdetect.marker_type`) read the type from boundary points. On a small marker
(radius 8-12 px) under blur those are few and rounded, and a third of such markers' wrong types are
there (stops 78-80's sets: 20 of 585 uncovered markers under 10 px typed wrong against 23 of 5,238
above). The three outlines differ in large areas even there: in the frame where the half-lines are
the axes (s, t >= 0 in each quadrant, 1 at the outline along a half-line), a diagonal fills
s + t <= 1, a circle s^2 + t^2 <= 1 and a square max(s, t) <= 1, so the circle exceeds the diagonal
by (pi - 2) / 4 and the square the circle by (4 - pi) / 4 of each quadrant's s-t unit square: about
70 and 50 px^2 of an 8 px marker, at the level of the sector inside and of the background outside.

Model per type: every pixel of a disk around the centre is the mean over 4 x 4 sub-pixel samples of
five levels (the four sectors inside the outline, the background outside), blurred with a Gaussian of
the marker's measured edge blur; the five levels are fitted by least squares, at the best of several
scales of the half-lines' measured lengths, and the residual is the RMS difference in grey levels,
over the whole disk and over the pixels where the types' models differ ("focus_"). Pixels follow
OpenCV (the centre of the top-left pixel is (0, 0)).

Used by the classical detector's opt-in ``type_template_max_radius_px``. Alone it types 95 % of the
markers of up to 24 px right on seen sets (the trees 98 %), but it is right on about 40 % of the
trees' errors there; weighed with the trees' probabilities it set 27 types right and 19 wrong over
ten fresh sets (stop 81, rules 46 and 47), which was not enough to make it the default. Known
weakness: :func:`cpdetect.centre_reach.edge_blur_px` reads 1.36-1.42 px on a 10 px marker blurred
by 1.8 px, so heavily blurred diagonals, whose tips the too-sharp model keeps, fit a circle better.
"""
from __future__ import annotations

import math

import numpy as np

from .marker_type import TYPES

SUBSAMPLES = 4  # per pixel and axis
# of the half-line lengths, tried coarse to fine (every other one, then the two beside the best)
SCALES = tuple(float(v) for v in np.round(np.arange(0.8, 1.31, 0.05), 2))
FOCUS = 0.2  # of the contrast: where two types' models differ more, a pixel tells them apart
WINDOW = 1.4  # window radius over the equal-area radius: a square's corners lie at 1.25 of it
SAMPLING_BLUR_PX = 0.5  # what edge_blur_px reads on a sharp edge, beyond the pixel area drawn here


def _inside(mtype: str, s: np.ndarray, t: np.ndarray) -> np.ndarray:
    if mtype == "circle":
        return s * s + t * t <= 1.0
    if mtype == "diagonal":
        return s + t <= 1.0
    return np.maximum(s, t) <= 1.0


def template_residuals(gray: np.ndarray, x: float, y: float, bounds: np.ndarray, widths: np.ndarray,
                       lengths: np.ndarray, blur_px: float, radius: float) -> dict[str, float]:
    """RMS residual (grey levels) of each type's model (see the module doc) around (x, y) (pixels),
    the best over :data:`SCALES` of the half-line ``lengths``.

    ``bounds``, ``widths`` (4,) radians: sector k lies between the half-lines at ``bounds[k]`` and
    ``bounds[k] + widths[k]`` (image frame, x right, y down, as :class:`cpdetect.classical._Verifier`
    measures them); ``lengths`` (4,) pixels: how far half-line j runs to the outline
    (:func:`half_line_lengths`), which every type's outline crosses there; ``blur_px``: the edges'
    Gaussian sigma as :func:`cpdetect.centre_reach.edge_blur_px` reads it; ``radius``: the marker's
    equal-area radius (pixels). All types are fitted on one window: the disk of :data:`WINDOW`
    radii around the centre, grown by the blur. An empty dict where the lengths are not finite and
    positive or the window leaves the image."""
    import cv2

    L = np.asarray(lengths, float)
    if not np.all(np.isfinite(L) & (L > 0)):
        return {}
    h, w = gray.shape[:2]
    sig = math.sqrt(max(blur_px * blur_px - SAMPLING_BLUR_PX ** 2, 0.0))
    reach = WINDOW * radius + 2.0 * sig + 1.0
    x0, x1 = int(math.floor(x - reach)), int(math.ceil(x + reach))
    y0, y1 = int(math.floor(y - reach)), int(math.ceil(y + reach))
    if x0 < 0 or y0 < 0 or x1 >= w or y1 >= h:
        return {}
    n = SUBSAMPLES
    off = (np.arange(n) + 0.5) / n - 0.5
    rows, cols = y1 - y0 + 1, x1 - x0 + 1
    sub = _frame(x, y, bounds, widths, L, (np.arange(x0, x1 + 1)[:, None] + off[None, :]).ravel(),
                 (np.arange(y0, y1 + 1)[:, None] + off[None, :]).ravel())
    if sub is None:
        return {}
    gy, gx = np.mgrid[y0:y1 + 1, x0:x1 + 1]
    window = (gx - x) ** 2 + (gy - y) ** 2 <= reach * reach
    b = gray[y0:y1 + 1, x0:x1 + 1][window].astype(np.float64)
    k, s, t = sub
    # each sub-sample's pixel, times five: one bincount gives the five levels' shares of every pixel
    block = (np.arange(rows)[:, None, None, None] * cols + np.arange(cols)[None, None, :, None])
    block = np.broadcast_to(block, (rows, n, cols, n)).reshape(rows * n, cols * n) * 5
    out: dict[str, float] = {}
    pred: dict[str, np.ndarray] = {}
    contrast = []

    def fit(mtype: str, scale: float):
        label = np.where(_inside(mtype, s / scale, t / scale), k, 4)
        shares = np.bincount((block + label).ravel(), minlength=rows * cols * 5).reshape(rows, cols, 5)
        shares = shares.astype(np.float32) / float(n * n)
        if sig > 0.2:
            shares = cv2.GaussianBlur(shares, (0, 0), sig)
        A = shares[window].astype(np.float64)
        AtA = A.T @ A
        try:
            coef = np.linalg.solve(AtA + 1e-9 * np.eye(5), A.T @ b)
        except np.linalg.LinAlgError:
            coef = np.linalg.lstsq(A, b, rcond=None)[0]
        p = A @ coef
        return float(np.sqrt(np.mean((p - b) ** 2))), p, coef

    for mtype in TYPES:
        # coarse to fine over the scales: every other one, then the two beside the best
        tried = {sc: fit(mtype, sc) for sc in SCALES[::2]}
        i = SCALES.index(min(tried, key=lambda sc: tried[sc][0]))
        for j in (i - 1, i + 1):
            if 0 <= j < len(SCALES) and SCALES[j] not in tried:
                tried[SCALES[j]] = fit(mtype, SCALES[j])
        best = min(tried.values(), key=lambda r: r[0])
        out[mtype] = best[0]
        pred[mtype] = best[1]
        c = best[2]
        contrast.append(abs(0.5 * (c[1] + c[3]) - 0.5 * (c[0] + c[2])))
    # the pixels where the types' models differ: the evidence, apart from what none of them explains
    P = np.stack(list(pred.values()))
    differ = (P.max(0) - P.min(0)) > FOCUS * float(np.median(contrast))
    if differ.sum() >= 8:
        for mtype in TYPES:
            out["focus_" + mtype] = float(np.sqrt(np.mean((pred[mtype][differ] - b[differ]) ** 2)))
    return out


def _frame(x: float, y: float, bounds: np.ndarray, widths: np.ndarray, L: np.ndarray, xs: np.ndarray,
           ys: np.ndarray):
    """For the grid of points xs (cols,) x ys (rows,): the sector k each lies in and its coordinates
    (s, t) along that sector's two half-lines in units of their lengths (rows, cols); None where two
    half-lines are parallel."""
    dx, dy = np.meshgrid(xs - x, ys - y)
    ang = np.mod(np.arctan2(dy, dx), 2.0 * math.pi)
    k = np.zeros(dx.shape, np.int64)
    s = np.zeros(dx.shape)
    t = np.zeros(dx.shape)
    for j in range(4):
        a1, a2 = float(bounds[j]), float(bounds[j] + widths[j])
        sec = np.mod(ang - a1, 2.0 * math.pi) < (a2 - a1)
        M = np.array([[math.cos(a1) * L[j], math.cos(a2) * L[(j + 1) % 4]],
                      [math.sin(a1) * L[j], math.sin(a2) * L[(j + 1) % 4]]])
        if abs(np.linalg.det(M)) < 1e-6:
            return None
        Mi = np.linalg.inv(M)
        k[sec] = j
        s[sec] = Mi[0, 0] * dx[sec] + Mi[0, 1] * dy[sec]
        t[sec] = Mi[1, 0] * dx[sec] + Mi[1, 1] * dy[sec]
    return k, s, t


def half_line_lengths(gray: np.ndarray, x: float, y: float, bounds: np.ndarray, radius: float) -> np.ndarray:
    """(4,) pixels: how far each checker half-line at angle ``bounds[j]`` (radians, image frame) runs
    from (x, y) before the sector edge along it ends, the same for every type (each type's outline
    crosses its half-lines at its extents). Read as the first distance past 0.5 ``radius`` where the
    grey step across the half-line (samples 0.12 ``radius``, at least 1 px, either side) falls under
    half its value near the centre; a half-line whose step is too weak to read takes its opposite's
    length, else the others' median (NaN where none can be read)."""
    import cv2

    d = np.arange(0.3 * radius, 2.2 * radius, 0.25)
    delta = max(1.0, 0.12 * radius)
    out = np.full(4, np.nan)
    # a crop around the marker: the samples reach 2.2 radii and delta across (no full-size copy)
    h, w = gray.shape[:2]
    reach = float(d[-1]) + delta + 2.0 if d.size else 2.0
    cx0, cy0 = max(int(math.floor(x - reach)), 0), max(int(math.floor(y - reach)), 0)
    cx1, cy1 = min(int(math.ceil(x + reach)), w - 1), min(int(math.ceil(y + reach)), h - 1)
    if cx1 <= cx0 or cy1 <= cy0:
        return out
    crop = np.asarray(gray[cy0:cy1 + 1, cx0:cx1 + 1], np.float32)
    for j, a in enumerate(np.asarray(bounds, float)):
        ux, uy = math.cos(a), math.sin(a)
        px, py = x - cx0 + d * ux, y - cy0 + d * uy
        xs = np.stack([px - delta * uy, px + delta * uy]).astype(np.float32)
        ys = np.stack([py + delta * ux, py - delta * ux]).astype(np.float32)
        v = cv2.remap(crop, xs, ys, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=float("nan"))
        step = v[1] - v[0]
        near = step[d <= 0.6 * radius]
        ref = float(np.median(near)) if near.size else math.nan
        if not (abs(ref) >= 8.0):
            continue
        rel = step / ref
        past = np.nonzero((d > 0.5 * radius) & ~(rel >= 0.5))[0]
        if past.size:
            i = int(past[0])
            # linear interpolation of the half-level crossing between samples i-1 and i
            r0, r1 = rel[i - 1], rel[i] if np.isfinite(rel[i]) else 0.0
            f = (r0 - 0.5) / (r0 - r1) if r0 != r1 else 0.0
            out[j] = float(d[i - 1] + np.clip(f, 0.0, 1.0) * (d[i] - d[i - 1]))
    # a half-line that cannot be read (a sector on a background of its level, an occluder) takes its
    # opposite's length, as point symmetry gives under weak perspective, else the others' median
    for j in range(4):
        if not np.isfinite(out[j]):
            opp = out[(j + 2) % 4]
            out[j] = opp if np.isfinite(opp) else (np.nanmedian(out) if np.isfinite(out).any() else np.nan)
    return out


def combined_type(probabilities: dict[str, float], residuals: dict[str, float], weight: float) -> str:
    """The type of the largest log ``probabilities[t]`` (the type trees') less ``weight`` x 100 x
    the relative excess of ``residuals["focus_" + t]`` (:func:`template_residuals`) over the least of
    them; the trees' own type where the focused residuals are missing."""
    focus = {t: residuals.get("focus_" + t) for t in TYPES}
    if any(v is None for v in focus.values()):
        return max(probabilities, key=probabilities.get)
    lo = min(focus.values())
    return max(TYPES, key=lambda t: math.log(max(probabilities.get(t, 0.0), 1e-12))
               - weight * 100.0 * (focus[t] - lo) / max(lo, 1.0))


__all__ = ["TYPES", "combined_type", "half_line_lengths", "template_residuals"]
