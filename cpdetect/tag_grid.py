"""The cells around a square marker's 2x2 checker: does it sit inside a larger grid of cells?

A square marker's outline holds four cells of its checker. Carried on by one cell on every side,
that grid has twelve more cells around it (a 4 x 4 block less the middle 2 x 2). Around a printed
marker they lie on its margin (one bright level), on the background (anything, rarely uniform at
the ink's level and the paper's level at once) or partly on both. Around the X-corner between the
bit cells of a fiducial tag (ArUco, AprilTag) they are more bit cells: each one uniform, each at
one of the two levels of the "marker", and of both levels. That is what :func:`grid_cells` measures
and :func:`is_tag_grid` tests.

Pixel coordinates follow OpenCV (the centre of the top-left pixel is (0, 0)).
"""
from __future__ import annotations

import math

import numpy as np

# the unit square the outline's four corners are mapped from, and the twelve cells around the
# middle 2 x 2 of the 4 x 4 block over [-2, 2]^2 (each by its corner of least u and v, unit size)
_UNIT = np.array([[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]])
_CELLS = [(i, j) for i in range(-2, 2) for j in range(-2, 2) if not (i in (-1, 0) and j in (-1, 0))]
_GRID = np.linspace(0.2, 0.8, 5)  # 5 x 5 samples in the middle 60 % of a cell: clear of its edges' blur

CELL_LABELS = ("dark", "bright", "mix", "other", "out")
# a cell whose samples' median absolute deviation exceeds this share of the contrast is "mix", and a
# uniform cell within LEVEL_TOLERANCE of the contrast of a level is at that level. A tag's bits are
# printed like its field: the bit corners kept as markers on seen 45 MP sets (37700, 39900, 40300)
# deviate 0.011-0.023 of the contrast in level and 0.016-0.036 within a cell; a dark wall 0.21 off the
# ink's level beside a white patch is no tag (0.15 / 0.25 had taken one for it)
UNIFORM_MAD = 0.08
LEVEL_TOLERANCE = 0.10


def _quad(outline: np.ndarray) -> np.ndarray | None:
    """Four corners (4, 2) of a square outline polygon: the polygon itself when it has four points,
    else its four-point approximation (within 4 % of the perimeter), else None."""
    import cv2

    poly = np.asarray(outline, float)
    if len(poly) == 4:
        return poly
    if len(poly) < 4:
        return None
    p32 = poly.astype(np.float32)
    approx = cv2.approxPolyDP(p32, 0.04 * cv2.arcLength(p32, True), True).reshape(-1, 2)
    return approx.astype(float) if len(approx) == 4 else None


def cell_levels(gray: np.ndarray, outline: np.ndarray, x: float, y: float) -> list[tuple[float, float] | None] | None:
    """(median, median absolute deviation) of the grey levels in each of the twelve cells around a
    square marker's checker (None for a cell with a sample outside the image), or None when the
    outline has no four corners. ``gray``: the uint8 image; ``outline``: the marker's outline
    polygon (n, 2), pixels; (x, y): its centre. The outline's corners are mapped from the unit
    square by a homography, so the cells follow the marker's perspective; each cell is sampled at
    5 x 5 points (bilinear)."""
    import cv2

    quad = _quad(outline)
    if quad is None:
        return None
    quad = quad[np.argsort(np.arctan2(quad[:, 1] - y, quad[:, 0] - x))]
    unit = _UNIT[np.argsort(np.arctan2(_UNIT[:, 1], _UNIT[:, 0]))]
    H = cv2.getPerspectiveTransform(unit.astype(np.float32), quad.astype(np.float32))
    uu, vv = np.meshgrid(_GRID, _GRID)
    pts = np.concatenate([np.stack([(i + uu).ravel(), (j + vv).ravel()], 1) for i, j in _CELLS])
    pts = cv2.perspectiveTransform(pts[None].astype(np.float32), H)[0].reshape(len(_CELLS), -1, 2)
    h, w = gray.shape[:2]
    inside = ~((pts < 0).any(axis=(1, 2)) | (pts[:, :, 0] > w - 1).any(1) | (pts[:, :, 1] > h - 1).any(1))
    out: list[tuple[float, float] | None] = [None] * len(_CELLS)
    if not inside.any():
        return out
    # sampled in a window around the cells: cv2.remap takes no image of 32767 pixels a side or more
    use = pts[inside]
    x0, y0 = (int(math.floor(float(use[:, :, k].min()))) for k in (0, 1))
    x1, y1 = (int(math.ceil(float(use[:, :, k].max()))) + 2 for k in (0, 1))
    win = np.ascontiguousarray(gray[y0:min(y1, h), x0:min(x1, w)])
    vals = cv2.remap(win, (use[:, :, 0] - x0).astype(np.float32), (use[:, :, 1] - y0).astype(np.float32),
                     cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE).astype(float)
    for k, v in zip(np.nonzero(inside)[0], vals):
        med = float(np.median(v))
        out[k] = (med, float(np.median(np.abs(v - med))))
    return out


def grid_cells(gray: np.ndarray, outline: np.ndarray, x: float, y: float,
               levels: tuple[float, float]) -> dict[str, int] | None:
    """How many of the twelve cells around a square marker's checker (:func:`cell_levels`) are of
    each of CELL_LABELS, given its (dark, bright) grey ``levels``: "out" when a sample lies outside
    the image, "mix" when the samples are not uniform (deviation over UNIFORM_MAD of the contrast),
    else "dark" / "bright" within LEVEL_TOLERANCE of the contrast of that level, or "other". None
    when the outline has no four corners or the levels no contrast."""
    dark, bright = float(levels[0]), float(levels[1])
    contrast = bright - dark
    if not (contrast > 0 and math.isfinite(contrast)):
        return None
    cells = cell_levels(gray, outline, x, y)
    if cells is None:
        return None
    counts = dict.fromkeys(CELL_LABELS, 0)
    for cell in cells:
        if cell is None:
            counts["out"] += 1
        elif cell[1] > UNIFORM_MAD * contrast:
            counts["mix"] += 1
        elif abs(cell[0] - dark) <= LEVEL_TOLERANCE * contrast:
            counts["dark"] += 1
        elif abs(cell[0] - bright) <= LEVEL_TOLERANCE * contrast:
            counts["bright"] += 1
        else:
            counts["other"] += 1
    return counts


def is_tag_grid(counts: dict[str, int] | None, min_each: int = 2) -> bool:
    """Whether the cells around a square marker (:func:`grid_cells`) are a tag's bits: every cell
    inside the image uniform at one of the marker's two levels, and at least ``min_each`` of each."""
    if counts is None:
        return False
    return counts["mix"] == 0 and counts["other"] == 0 and counts["dark"] >= min_each \
        and counts["bright"] >= min_each
