"""Multi-scale X-corner candidates: where four sectors (dark, bright, dark, bright) meet.

Response: the negative determinant of the Hessian of the image smoothed with a Gaussian of scale
``sigma`` (pixels of the level). An X-corner is a saddle (det H < 0, in every orientation); a straight
edge has det H ~ 0 and a blob det H > 0. For an ideal X-corner of contrast c (bright minus dark),
Lxy = c / (pi sigma^2) at its centre, so ``c_hat = pi sigma^2 sqrt(-det H)`` estimates the contrast in
grey levels at any scale; thresholds are set in grey levels.

Levels: the search image and its 2x area-reduced copies; an X-corner is found at every level whose
sigma is below about half its quadrant size, so small markers show at fine levels and large ones at
all levels (the verifier decides the extent).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Candidate:
    """An X-corner candidate. x, y: position in the *search image* pixels (OpenCV convention);
    level: pyramid level it was found at (scale 2**level of the search image); contrast: c_hat."""

    x: float
    y: float
    level: int
    contrast: float


def build_pyramid(search: np.ndarray, min_side: int = 40) -> list[np.ndarray]:
    """[search, search/2, search/4, ...] as float32, area-averaged, while the short side >= min_side."""
    import cv2

    levels = [np.asarray(search, np.float32)]
    while min(levels[-1].shape) // 2 >= min_side:
        a = levels[-1]
        levels.append(cv2.resize(a, (a.shape[1] // 2, a.shape[0] // 2), interpolation=cv2.INTER_AREA))
    return levels


def xcorner_contrast(level: np.ndarray, sigma: float = 1.5) -> np.ndarray:
    """c_hat map (float32, grey levels, >= 0) of one level; see the module doc."""
    import cv2

    g = cv2.GaussianBlur(level, (0, 0), sigma)
    # second derivatives by 3x3 Sobel: Lxx, Lyy scaled by 1/4, Lxy by 1/4 as well
    lxx = cv2.Sobel(g, cv2.CV_32F, 2, 0, ksize=3, scale=0.25)
    lyy = cv2.Sobel(g, cv2.CV_32F, 0, 2, ksize=3, scale=0.25)
    lxy = cv2.Sobel(g, cv2.CV_32F, 1, 1, ksize=3, scale=0.25)
    # in place: fresh arrays of a 45 MP photograph's search image cost more than the arithmetic
    cv2.multiply(lxx, lyy, dst=lxx)
    cv2.multiply(lxy, lxy, dst=lxy)
    negdet = cv2.subtract(lxy, lxx, dst=lxy)
    cv2.max(negdet, 0.0, dst=negdet)
    cv2.sqrt(negdet, negdet)
    negdet *= np.float32(np.pi * sigma * sigma)
    return negdet


def _parabolic_offset(lo: np.ndarray, mid: np.ndarray, hi: np.ndarray, use: np.ndarray) -> np.ndarray:
    """Vertex offset in [-0.5, 0.5] of the parabola through (-1, lo), (0, mid), (1, hi); 0 where it is
    not a maximum or ``use`` is False."""
    den = lo - 2 * mid + hi
    ok = use & (den < 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        off = np.clip(0.5 * (lo - hi) / np.where(ok, den, -1), -0.5, 0.5)
    return np.where(ok, off, 0).astype(np.float64)


def find_candidates(levels: list[np.ndarray], min_contrast: float, max_per_level: int = 300,
                    sigma: float = 1.5, border: int = 3, maps: list | None = None) -> list[Candidate]:
    """Local maxima of c_hat above ``min_contrast`` on every level, strongest first per level,
    at most ``max_per_level`` each; positions mapped to search-image pixels. ``maps``, when given
    (a list), receives each level's c_hat map."""
    import cv2

    out: list[Candidate] = []
    nms = int(2 * round(sigma) + 1) | 1
    kernel = np.ones((nms, nms), np.uint8)
    for li, lev in enumerate(levels):
        c = xcorner_contrast(lev, sigma)
        if maps is not None:
            maps.append(c)
        # local maxima (equal to the nms x nms maximum) among the pixels above the threshold, as one
        # mask before any index array (on a textured 45 MP photograph's search image half a million
        # pixels pass the threshold); flat indices, since np.nonzero of a 2-D mask took 5-8 ms there
        body = (slice(border, c.shape[0] - border), slice(border, c.shape[1] - border))
        peak = c[body] >= min_contrast
        peak &= c[body] >= cv2.dilate(c, kernel)[body]
        ys, xs = np.divmod(np.flatnonzero(peak), peak.shape[1])
        ys += border
        xs += border
        vals = c[ys, xs]
        if xs.size == 0:
            continue
        order = np.argsort(-vals)[:max_per_level]
        xs, ys, vals = xs[order], ys[order], vals[order]
        # parabolic sub-pixel peak (enough to seed the verifier), all peaks at once in float32
        inner = (xs > 0) & (xs < c.shape[1] - 1) & (ys > 0) & (ys < c.shape[0] - 1)
        xi, yi = np.clip(xs, 1, c.shape[1] - 2), np.clip(ys, 1, c.shape[0] - 2)
        m = c[yi, xi]
        dx = _parabolic_offset(c[yi, xi - 1], m, c[yi, xi + 1], inner)
        dy = _parabolic_offset(c[yi - 1, xi], m, c[yi + 1, xi], inner)
        s = float(2 ** li)
        px = (xs + dx + 0.5) * s - 0.5
        py = (ys + dy + 0.5) * s - 0.5
        out.extend(Candidate(float(a), float(b), li, float(v)) for a, b, v in zip(px, py, vals))
    return out


def xcorner_seeds(gray: np.ndarray, box: tuple[int, int, int, int], radius_px: float,
                  inside: "callable | None" = None, max_seeds: int = 3) -> list[tuple[float, float, float]]:
    """The strongest X-corners in ``box`` = (x0, y0, x1, y1) (full-resolution pixels, end exclusive)
    of the gray image, for a marker of about ``radius_px``: up to ``max_seeds`` (x, y, c_hat), strongest
    first, at least a quarter radius apart, full-resolution pixels (OpenCV convention).

    The box is area-reduced so that the radius spans about 20 pixels (bounded work for any size) and
    c_hat is taken at sigma 1.5 there. ``inside(xs, ys)`` (full-res arrays -> bool array), when given,
    keeps only peaks it accepts (e.g. those on a segmented marker area). A blob's centroid is a poor
    centre seed under perspective, occlusion or the image border; its X-corner is not.
    """
    import cv2

    x0, y0, x1, y1 = (int(v) for v in box)
    h, w = gray.shape[:2]
    x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, w), min(y1, h)
    if x1 - x0 < 5 or y1 - y0 < 5:
        return []
    crop = np.asarray(gray[y0:y1, x0:x1], np.float32)
    d = max(1.0, float(radius_px) / 20.0)
    if d > 1.0:
        crop = cv2.resize(crop, (max(5, int(round(crop.shape[1] / d))), max(5, int(round(crop.shape[0] / d)))),
                          interpolation=cv2.INTER_AREA)
    dx, dy = (x1 - x0) / crop.shape[1], (y1 - y0) / crop.shape[0]
    c = xcorner_contrast(crop, 1.5)
    nms = 2 * max(1, int(round(0.25 * radius_px / max(dx, dy)))) + 1
    peak = (c >= cv2.dilate(c, np.ones((nms, nms), np.uint8))) & (c > 0)
    ys, xs = np.nonzero(peak)
    if xs.size == 0:
        return []
    fx = x0 + (xs + 0.5) * dx - 0.5
    fy = y0 + (ys + 0.5) * dy - 0.5
    vals = c[ys, xs]
    if inside is not None:
        keep = np.asarray(inside(fx, fy), bool)
        fx, fy, vals = fx[keep], fy[keep], vals[keep]
    order = np.argsort(-vals)[:max_seeds]
    return [(float(fx[i]), float(fy[i]), float(vals[i])) for i in order]


__all__ = ["Candidate", "build_pyramid", "xcorner_contrast", "find_candidates", "xcorner_seeds"]
