"""Things that look a little like control-point markers but are not: drawn as flat patches that the
image generator (:mod:`cpdetect.synth_images`) tilts, places and composites onto a photograph.

Every drawing function has the signature ``draw(rng, size) -> (bgr, alpha)``: a square canvas of
``size`` x ``size`` pixels, ``bgr`` float32 (size, size, 3) in 0..255 and ``alpha`` float32 (size, size)
in [0, 1] (1 = the confuser fully covers the background). Randomness comes only from ``rng``
(a numpy Generator), so a confuser is reproducible from its generator state.

Kinds: ``window`` (dark panes with crossed mullions), ``louver`` (shaded slats), ``tiles`` (tiles with
grout crosses), ``holes`` (dark anchor/drain holes), ``text`` (letters and digits, cv2.putText),
``railing`` (bars and rails), ``grid`` (calibration checkerboards, e.g. 5x7 squares, whose inner
X-corners are *not* markers), ``fiducial`` (ArUco/AprilTag-like bit patterns).
"""
from __future__ import annotations

from typing import Callable

import cv2
import numpy as np

Patch = tuple[np.ndarray, np.ndarray]
_SHIFT = 4  # cv2 drawing with 4 fractional bits (1/16 pixel)
_F = float(1 << _SHIFT)


def _pts(coords) -> np.ndarray:
    return np.round(np.asarray(coords, float) * _F).astype(np.int32).reshape(-1, 1, 2)


def _fill_rect(img: np.ndarray, x0: float, y0: float, x1: float, y1: float, color) -> None:
    """Anti-aliased filled axis-aligned rectangle with sub-pixel corners (pixel-centre convention)."""
    cv2.fillPoly(img, [_pts([[x0, y0], [x1, y0], [x1, y1], [x0, y1]])], color, cv2.LINE_AA, _SHIFT)


def _colour(rng: np.random.Generator, lo: float, hi: float, tint: float = 0.08) -> tuple[float, float, float]:
    base = rng.uniform(lo, hi)
    g = base * (1.0 + rng.uniform(-tint, tint, 3))
    return tuple(float(v) for v in np.clip(g, 0, 255))


def _canvas(size: int, color) -> tuple[np.ndarray, np.ndarray]:
    img = np.empty((size, size, 3), np.float32)
    img[:] = color
    return img, np.zeros((size, size), np.float32)


def draw_window(rng: np.random.Generator, size: int) -> Patch:
    """A window: bright frame, dark glass with a reflection gradient, crossed mullions (a bright cross
    between four dark panes, the classic false positive for checkerboard detectors)."""
    aspect = rng.uniform(0.55, 1.0)
    w, h = (size - 1) * aspect, size - 1.0
    if rng.random() < 0.5:
        w, h = h, w
    x0, y0 = (size - 1 - w) / 2, (size - 1 - h) / 2
    frame = _colour(rng, 150, 245)
    glass = np.array(_colour(rng, 15, 80), np.float32)
    img, alpha = _canvas(size, frame)
    a8 = np.zeros((size, size), np.uint8)
    _fill_rect(a8, x0, y0, x0 + w, y0 + h, 255)
    fw = max(1.0, rng.uniform(0.04, 0.1) * min(w, h))
    gx0, gy0, gx1, gy1 = x0 + fw, y0 + fw, x0 + w - fw, y0 + h - fw
    pane = np.zeros((size, size), np.uint8)
    _fill_rect(pane, gx0, gy0, gx1, gy1, 255)
    yy, xx = np.mgrid[0:size, 0:size].astype(np.float32)
    ang = rng.uniform(0, np.pi)
    refl = 1.0 + rng.uniform(0.0, 1.2) * np.clip(np.cos(ang) * xx + np.sin(ang) * yy, 0, None) / (2 * size)
    pane_f = pane.astype(np.float32)[..., None] / 255.0
    img = img * (1 - pane_f) + pane_f * glass[None, None, :] * refl[..., None]
    # mullions: one vertical, one horizontal (not always through the middle)
    mw = max(1.0, rng.uniform(0.5, 1.5) * fw)
    mx = gx0 + (gx1 - gx0) * rng.choice([0.5, rng.uniform(0.3, 0.7)])
    my = gy0 + (gy1 - gy0) * rng.choice([0.5, 1 / 3, rng.uniform(0.25, 0.75)])
    mull = np.zeros((size, size), np.uint8)
    _fill_rect(mull, mx - mw / 2, gy0, mx + mw / 2, gy1, 255)
    _fill_rect(mull, gx0, my - mw / 2, gx1, my + mw / 2, 255)
    mf = mull.astype(np.float32)[..., None] / 255.0
    img = img * (1 - mf) + mf * np.asarray(frame, np.float32)
    alpha[:] = a8 / 255.0
    return img.astype(np.float32), alpha


def draw_louver(rng: np.random.Generator, size: int) -> Patch:
    """A louvre / vent: a frame of parallel slats, each shaded from bright to dark."""
    n = int(rng.integers(5, 16))
    frame = _colour(rng, 60, 220)
    img, alpha = _canvas(size, frame)
    a8 = np.zeros((size, size), np.uint8)
    _fill_rect(a8, 0, 0, size - 1, size - 1, 255)
    fw = max(1.0, rng.uniform(0.03, 0.08) * size)
    inner = size - 1 - 2 * fw
    slat = inner / n
    hi, lo = rng.uniform(150, 250), rng.uniform(10, 90)
    yy = np.arange(size, dtype=np.float32)
    phase = np.clip((yy - fw) / slat, 0, n - 1e-6)
    frac = phase - np.floor(phase)
    shade = (hi + (lo - hi) * frac ** rng.uniform(0.5, 2.0)).astype(np.float32)
    tint = 1.0 + rng.uniform(-0.06, 0.06, 3).astype(np.float32)
    s0, s1 = int(np.ceil(fw)), int(np.floor(size - 1 - fw)) + 1
    img[s0:s1, s0:s1] = shade[s0:s1, None, None] * tint[None, None, :]
    if rng.random() < 0.5:  # vertical slats
        img = np.ascontiguousarray(img.transpose(1, 0, 2))
    alpha[:] = a8 / 255.0
    return img, alpha


def draw_tiles(rng: np.random.Generator, size: int) -> Patch:
    """Tiles with grout lines: the grout crossings are X-shaped but no quadrant alternates."""
    k = int(rng.integers(2, 8))
    base = _colour(rng, 60, 240, tint=0.2)
    grout = _colour(rng, 20, 250)
    img, alpha = _canvas(size, grout)
    pitch = (size - 1) / k
    gw = max(0.8, rng.uniform(0.03, 0.12) * pitch)
    jitter = rng.uniform(0.0, 0.12)
    stagger = rng.random() < 0.3  # running bond: T-junctions instead of crosses
    for i in range(k):
        off = -pitch / 2 if (stagger and i % 2) else 0.0
        for j in range(k + (1 if off else 0)):
            c = np.asarray(base) * (1 + rng.uniform(-jitter, jitter))
            _fill_rect(img, j * pitch + gw / 2 + off, i * pitch + gw / 2, (j + 1) * pitch - gw / 2 + off,
                       (i + 1) * pitch - gw / 2, tuple(float(v) for v in np.clip(c, 0, 255)))
    alpha[:] = 1.0
    return img, alpha


def draw_holes(rng: np.random.Generator, size: int) -> Patch:
    """Dark holes (anchor holes, drains, bolt heads): one to six soft dark ellipses."""
    img, alpha = _canvas(size, _colour(rng, 5, 45))
    a8 = np.zeros((size, size), np.uint8)
    for _ in range(int(rng.integers(1, 7))):
        r = rng.uniform(0.06, 0.3) * size
        cx, cy = rng.uniform(r, size - 1 - r, 2)
        ax = (int(round(r * _F)), int(round(r * rng.uniform(0.6, 1.0) * _F)))
        cv2.ellipse(a8, (int(round(cx * _F)), int(round(cy * _F))), ax, float(rng.uniform(0, 180)), 0, 360,
                    255, -1, cv2.LINE_AA, _SHIFT)
    a = a8.astype(np.float32) / 255.0
    soft = rng.uniform(0.0, 0.03) * size
    if soft > 0.3:
        a = cv2.GaussianBlur(a, (0, 0), soft)
    alpha[:] = np.clip(a, 0.0, 1.0)
    return img, alpha


_FONTS = (cv2.FONT_HERSHEY_SIMPLEX, cv2.FONT_HERSHEY_DUPLEX, cv2.FONT_HERSHEY_COMPLEX,
          cv2.FONT_HERSHEY_TRIPLEX, cv2.FONT_HERSHEY_PLAIN)
_CHARS = np.array(list("ABCDEFGHKLMNPRSTUVWXZ0123456789+-/"))


def draw_text(rng: np.random.Generator, size: int) -> Patch:
    """A sign or stencilled text: one to three lines of letters and digits, on a plate or bare."""
    plate = rng.random() < 0.5
    dark_text = rng.random() < 0.6
    fg = _colour(rng, 5, 70) if dark_text else _colour(rng, 180, 250)
    bg = _colour(rng, 170, 250) if dark_text else _colour(rng, 10, 90)
    img, alpha = _canvas(size, fg)
    lines = int(rng.integers(1, 4))
    font = int(rng.choice(_FONTS))
    thick = int(rng.integers(1, 4))
    words = ["".join(rng.choice(_CHARS, int(rng.integers(2, 7)))) for _ in range(lines)]
    (tw, th), base = cv2.getTextSize(max(words, key=len), font, 1.0, thick)
    scale = 0.9 * size / max(tw, 1) if tw > 0 else 1.0
    scale = min(scale, 0.9 * size / (lines * (th + base) * 1.3))
    t8 = np.zeros((size, size), np.uint8)
    line_h = (th + base) * scale * 1.3
    y = (size - lines * line_h) / 2 + th * scale
    for wd in words:
        cv2.putText(t8, wd, (int(0.05 * size), int(round(y))), font, scale, 255,
                    max(1, int(round(thick * scale * 0.8))), cv2.LINE_AA)
        y += line_h
    t = t8.astype(np.float32)[..., None] / 255.0
    if plate:
        img = (1 - t) * np.asarray(bg, np.float32) + t * np.asarray(fg, np.float32)
        alpha[:] = 1.0
    else:
        alpha[:] = t[..., 0]
    return img.astype(np.float32), alpha


def draw_railing(rng: np.random.Generator, size: int) -> Patch:
    """A railing or fence: evenly spaced bars between one or two rails (thin dark or bright lines)."""
    col = _colour(rng, 10, 80) if rng.random() < 0.6 else _colour(rng, 170, 245)
    img, alpha = _canvas(size, col)
    a8 = np.zeros((size, size), np.uint8)
    n = int(rng.integers(4, 14))
    bw = max(0.8, rng.uniform(0.01, 0.04) * size)
    for k in range(n):
        x = (k + 0.5) * (size - 1) / n
        _fill_rect(a8, x - bw / 2, 0, x + bw / 2, size - 1, 255)
    rails = [0.05] if rng.random() < 0.3 else [0.05, rng.uniform(0.6, 0.95)]
    rw = bw * rng.uniform(1.0, 2.5)
    for r in rails:
        y = r * (size - 1)
        _fill_rect(a8, 0, y - rw / 2, size - 1, y + rw / 2, 255)
    alpha[:] = a8 / 255.0
    return img, alpha


_GRID_SHAPES = ((4, 6), (5, 7), (6, 8), (7, 9), (3, 5), (4, 5), (6, 9))


def draw_grid(rng: np.random.Generator, size: int) -> Patch:
    """A calibration checkerboard (e.g. 5x7 squares) on a white sheet: many X-corners, none a marker."""
    rows, cols = _GRID_SHAPES[int(rng.integers(len(_GRID_SHAPES)))]
    if rng.random() < 0.5:
        rows, cols = cols, rows
    white = _colour(rng, 170, 250, tint=0.03)
    black = _colour(rng, 5, 60, tint=0.03)
    img, alpha = _canvas(size, white)
    border = rng.uniform(0.03, 0.1) * size
    sq = (size - 1 - 2 * border) / max(rows, cols)
    ox = (size - 1 - cols * sq) / 2
    oy = (size - 1 - rows * sq) / 2
    for i in range(rows):
        for j in range(cols):
            if (i + j) % 2 == 0:
                _fill_rect(img, ox + j * sq, oy + i * sq, ox + (j + 1) * sq, oy + (i + 1) * sq, black)
    a8 = np.zeros((size, size), np.uint8)
    _fill_rect(a8, ox - border, oy - border, ox + cols * sq + border, oy + rows * sq + border, 255)
    alpha[:] = a8 / 255.0
    return img, alpha


def draw_fiducial(rng: np.random.Generator, size: int) -> Patch:
    """An ArUco/AprilTag-like square: quiet zone, black border, random n x n bit cells (n = 4..6)."""
    n = int(rng.integers(4, 7))
    cells = n + 4  # quiet zone + border on each side
    white = _colour(rng, 180, 250, tint=0.03)
    black = _colour(rng, 5, 50, tint=0.03)
    img, alpha = _canvas(size, white)
    c = (size - 1) / cells
    _fill_rect(img, c, c, (cells - 1) * c, (cells - 1) * c, black)
    bits = rng.random((n, n)) < 0.5
    for i in range(n):
        for j in range(n):
            if bits[i, j]:
                _fill_rect(img, (j + 2) * c, (i + 2) * c, (j + 3) * c, (i + 3) * c, white)
    alpha[:] = 1.0
    return img, alpha


CONFUSERS: dict[str, Callable[[np.random.Generator, int], Patch]] = {
    "window": draw_window,
    "louver": draw_louver,
    "tiles": draw_tiles,
    "holes": draw_holes,
    "text": draw_text,
    "railing": draw_railing,
    "grid": draw_grid,
    "fiducial": draw_fiducial,
}
CONFUSER_KINDS: tuple[str, ...] = tuple(CONFUSERS)


def draw_confuser(kind: str, rng: np.random.Generator, size: int) -> Patch:
    """Draw a ``kind`` confuser on a ``size`` x ``size`` canvas (see module docstring)."""
    if kind not in CONFUSERS:
        raise ValueError(f"unknown confuser {kind!r}; valid: {', '.join(CONFUSER_KINDS)}")
    if size < 8:
        raise ValueError("confuser canvas must be at least 8 pixels")
    return CONFUSERS[kind](rng, int(size))
