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
from dataclasses import dataclass

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
    vals = _sample(gray, pts[:, :, 0], pts[:, :, 1])
    out: list[tuple[float, float] | None] = [None] * len(_CELLS)
    for k, v in enumerate(vals):
        if not np.isnan(v).any():
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
        counts["out" if cell is None else _level_label(*cell, dark, bright)] += 1
    return counts


def _level_label(median: float, mad: float, dark: float, bright: float) -> str:
    """A cell inside the image by its samples' median and median absolute deviation: "mix", "dark",
    "bright" or "other" (see :func:`grid_cells`)."""
    contrast = bright - dark
    if mad > UNIFORM_MAD * contrast:
        return "mix"
    if abs(median - dark) <= LEVEL_TOLERANCE * contrast:
        return "dark"
    if abs(median - bright) <= LEVEL_TOLERANCE * contrast:
        return "bright"
    return "other"


def is_tag_grid(counts: dict[str, int] | None, min_each: int = 2) -> bool:
    """Whether the cells around a square marker (:func:`grid_cells`) are a tag's bits: every cell
    inside the image uniform at one of the marker's two levels, and at least ``min_each`` of each."""
    if counts is None:
        return False
    return counts["mix"] == 0 and counts["other"] == 0 and counts["dark"] >= min_each \
        and counts["bright"] >= min_each


# ------------------------------------------------------------------------------------------------
# the lattice an X-corner's own sector edges span (no outline needed)
#
# The test above carries the grid on from the outline's four corners. Around a tag's bit corner the
# outline is often not one cell: the sectors' rays run on over bits of their own level, so the
# outline spans several cells, or closes as an ellipse, and the grid it carries on is not the tag's
# (on the seen 1920 x 1080 and 45 MP sets, 8 of 11 false markers were tag bit corners that passed
# it). Here the lattice comes from the corner itself: the directions of its four sector edges near
# the centre, and along each edge the distance at which either sector beside it first changes level
# (one cell in a tag, where a neighbouring bit differs; the outline for a printed marker).

LATTICE_ANGLES = 144  # samples per ring for the sector edges' directions
LATTICE_CELL_RATIO = 1.3  # a half-edge over this times its opposite one ran on over same-level bits
LATTICE_MAX_RATIO = 2.0  # neighbouring edges' cell lengths further apart than this: no lattice
LATTICE_ALIGNED = 0.15  # a boundary between two cells lies within this share of a cell of the lattice's


@dataclass
class LatticeCells:
    """The cells around an X-corner on the lattice of its own sector edges (:func:`lattice_cells`).

    counts: the twelve cells around the middle 2 x 2, by CELL_LABELS (as :func:`grid_cells`).
    inner_in / inner_ok: the middle four cells inside the image / of those, uniform at their sector's
    level. cell_px: the cell's length along each of the four half-edges (pixels, by angle).
    ratio: the largest ratio of two neighbouring half-edges' cell lengths. boundaries / aligned: the
    boundaries between neighbouring cells of the two levels that were looked at / of those, the ones
    whose level step lies within LATTICE_ALIGNED of a cell of the lattice's line. levels: (dark,
    bright) grey levels of the corner's sectors. stepless: the half-edges whose own cell length no
    change of level between the cells beside it shows (see :func:`lattice_cells`)."""

    counts: dict[str, int]
    inner_in: int
    inner_ok: int
    cell_px: tuple[float, float, float, float]
    ratio: float
    boundaries: int
    aligned: int
    levels: tuple[float, float]
    stepless: int = 0


def _sample(gray: np.ndarray, px: np.ndarray, py: np.ndarray) -> np.ndarray:
    """Bilinear grey levels at (px, py) (any equal shapes, pixels), NaN where a point lies outside
    the image; only the points' bounding window is read (cv2.remap takes no image of 32767 pixels a
    side or more, and a 45 MP image as float would be 180 MB)."""
    import cv2

    h, w = gray.shape[:2]
    px, py = np.asarray(px, float), np.asarray(py, float)
    out = np.full(px.shape, np.nan)
    inside = (px >= 0) & (py >= 0) & (px <= w - 1) & (py <= h - 1)
    if not inside.any():
        return out
    ux, uy = px[inside], py[inside]
    x0, y0 = int(math.floor(float(ux.min()))), int(math.floor(float(uy.min())))
    x1, y1 = min(int(math.ceil(float(ux.max()))) + 2, w), min(int(math.ceil(float(uy.max()))) + 2, h)
    win = np.ascontiguousarray(gray[y0:y1, x0:x1])
    out[inside] = cv2.remap(win, (ux - x0).astype(np.float32).reshape(1, -1),
                            (uy - y0).astype(np.float32).reshape(1, -1), cv2.INTER_LINEAR,
                            borderMode=cv2.BORDER_REPLICATE).astype(float).ravel()
    return out


def _edge_angles(gray: np.ndarray, x: float, y: float, r: float) -> tuple[np.ndarray, np.ndarray] | None:
    """The four angles (radians in [0, 2 pi), ascending; image frame, from +x toward +y) where the
    pattern around (x, y) changes between dark and bright on rings of 1-1.8 ``r``, and each sector's
    grey level (sector j from angle j to angle j + 1), or None unless exactly four changes."""
    step = 2.0 * math.pi / LATTICE_ANGLES
    th = (np.arange(LATTICE_ANGLES) + 0.5) * step
    rs = r * np.array([1.0, 1.4, 1.8])
    v = _sample(gray, x + rs[:, None] * np.cos(th), y + rs[:, None] * np.sin(th))
    if np.isnan(v).any():
        return None
    prof = (v - v.mean(1, keepdims=True)).mean(0)
    prof = 0.25 * np.roll(prof, 1) + 0.5 * prof + 0.25 * np.roll(prof, -1)
    pos = prof > 0
    ch = np.nonzero(pos != np.roll(pos, 1))[0]
    if len(ch) != 4:
        return None
    a, b = prof[ch - 1], prof[ch]
    frac = np.where(a != b, a / np.where(a != b, a - b, 1.0), 0.5)
    ang = np.sort(np.mod(th[ch - 1] + frac * step, 2.0 * math.pi))
    levels = np.empty(4)
    for j in range(4):
        span = (ang[(j + 1) % 4] - ang[j]) % (2.0 * math.pi)
        d = np.mod(th - ang[j], 2.0 * math.pi)
        mid = (d > 0.25 * span) & (d < 0.75 * span)
        levels[j] = float(np.median(v[:, mid])) if mid.any() else math.nan
    return ang, levels


def _cell_label(vals: np.ndarray, dark: float, bright: float) -> str:
    """A cell by its samples (NaN outside the image): "out", else :func:`_level_label`."""
    if np.isnan(vals).any():
        return "out"
    med = float(np.median(vals))
    return _level_label(med, float(np.median(np.abs(vals - med))), dark, bright)


def lattice_cells(gray: np.ndarray, x: float, y: float, radius_px: float) -> LatticeCells | None:
    """The cells around the X-corner at (x, y) (pixels, OpenCV convention) on the lattice of its own
    sector edges, or None where it has no such lattice (not four alternating sectors near the centre,
    no level change along an edge and its opposite within 3 ``radius_px``, or neighbouring cell
    lengths over LATTICE_MAX_RATIO apart). ``gray``: the uint8 image; ``radius_px``: the marker's
    apparent radius (sets the rings the edges are read on, 0.12 of it within 3-12 px, and how far
    along the edges a change is looked for). Each quadrant between two half-edges is its own
    parallelogram frame (so the lattice bends with perspective from quadrant to quadrant); its cells
    are sampled at 5 x 5 points over their middle 60 %."""
    if not (math.isfinite(radius_px) and radius_px > 0 and math.isfinite(x) and math.isfinite(y)):
        return None
    r_ang = float(np.clip(0.12 * radius_px, 3.0, 12.0))
    ts = np.arange(r_ang, 3.0 * radius_px, max(1.0, radius_px / 64.0))
    if ts.size < 3:
        return None  # a pattern too small to look past its rings
    got = _edge_angles(gray, x, y, r_ang)
    if got is None:
        return None
    ang, lv = got
    dark_sec = lv < np.median(lv)
    if not (np.isfinite(lv).all() and dark_sec.sum() == 2 and dark_sec[0] == dark_sec[2] != dark_sec[1]):
        return None
    dark, bright = float(lv[dark_sec].mean()), float(lv[~dark_sec].mean())
    if not bright > dark:
        return None
    mid = 0.5 * (dark + bright)
    e = np.stack([np.cos(ang), np.sin(ang)], 1)  # the four half-edges' directions
    # per sector two rays, a fifth of its angle in from each of its edges: the first distance at
    # which the sector's level changes (three samples past mid after a 3-sample mean), as a length
    # along that edge in the sector's own frame
    found: list[list[float]] = [[], [], [], []]
    for j in range(4):
        k = (j + 1) % 4
        span = (ang[k] - ang[j]) % (2.0 * math.pi)
        frame = np.array([e[j], e[k]]).T
        if abs(float(np.linalg.det(frame))) < 0.05:  # two edges within 3 degrees of one line
            return None
        to_frame = np.linalg.inv(frame)
        for frac, edge in ((0.2, j), (0.8, k)):
            phi = ang[j] + frac * span
            v = _sample(gray, x + ts * math.cos(phi), y + ts * math.sin(phi))
            out = np.nonzero(np.isnan(v))[0]
            vs = np.convolve(np.nan_to_num(v, nan=mid), np.ones(3) / 3.0, mode="same")
            changed = vs > mid if dark_sec[j] else vs < mid
            at = np.nonzero(changed[:-2] & changed[1:-1] & changed[2:])[0]
            if at.size and (not out.size or at[0] < out[0]):
                t = ts[at[0]]
                ab = to_frame @ np.array([t * math.cos(phi), t * math.sin(phi)])
                found[edge].append(float(ab[0] if edge == j else ab[1]))
    s = np.array([min(f) if f else math.nan for f in found])
    own = s.copy()
    for i in range(4):
        # both sectors beside a half-edge ran on over bits of their own level: its opposite's length
        o = s[(i + 2) % 4]
        if math.isfinite(o) and (not math.isfinite(s[i]) or s[i] > LATTICE_CELL_RATIO * o):
            s[i] = o
    if not np.isfinite(s).all():
        return None
    ratio = float(max(max(s[i], s[(i + 1) % 4]) / min(s[i], s[(i + 1) % 4]) for i in range(4)))
    if ratio > LATTICE_MAX_RATIO:
        return None

    def at(j: int, a, b) -> tuple[np.ndarray, np.ndarray]:  # quadrant j's frame -> pixels
        k = (j + 1) % 4
        a, b = np.asarray(a, float), np.asarray(b, float)
        return (x + a * s[j] * e[j, 0] + b * s[k] * e[k, 0], y + a * s[j] * e[j, 1] + b * s[k] * e[k, 1])

    uu, vv = (g.ravel() for g in np.meshgrid(_GRID, _GRID))
    quads = ((0, 0), (1, 0), (0, 1), (1, 1))
    vals = _sample(gray, *np.concatenate([np.stack(at(j, a0 + uu, b0 + vv)) for j in range(4) for a0, b0 in quads],
                                         axis=1))
    label: dict[tuple[int, int, int], str] = {}
    counts = dict.fromkeys(CELL_LABELS, 0)
    inner_in = inner_ok = 0
    for n, (j, (a0, b0)) in enumerate((j, q) for j in range(4) for q in quads):
        lab = _cell_label(vals[n * len(uu):(n + 1) * len(uu)], dark, bright)
        if (a0, b0) == (0, 0):
            inner_in += lab != "out"
            inner_ok += lab == ("dark" if dark_sec[j] else "bright")
            lab = "dark" if dark_sec[j] else "bright"
        else:
            counts[lab] += 1
        label[(j, a0, b0)] = lab
    # a half-edge's own length (not its opposite's) was read where a sector beside it changes level,
    # so one of the two cells one further along it must be of the other level than the cell before
    # it; where neither is, the change was no cell's side (an occluder over a printed marker's sector,
    # whose lattice would then lie inside the marker, its cells the marker's own)
    stepless = 0
    for i in range(4):
        if own[i] == s[i]:
            h = (i - 1) % 4
            steps = [label[(i, 1, 0)] != label[(i, 0, 0)], label[(h, 0, 1)] != label[(h, 0, 0)]]
            stepless += not any(steps) and "out" not in (label[(i, 1, 0)], label[(h, 0, 1)])
    # boundaries between neighbouring cells of the two levels: the mean profile across the shared
    # side (at 0.3, 0.5, 0.7 along it) crosses mid within LATTICE_ALIGNED of the lattice's line
    dd = np.linspace(-0.45, 0.45, 19)
    T, Dd = np.meshgrid(np.array([0.3, 0.5, 0.7]), dd, indexing="ij")
    pairs = []
    for j in range(4):
        k = (j + 1) % 4
        for b0 in (0, 1):
            pairs.append(((j, 0, b0), (j, 1, b0), at(j, 1 + Dd, b0 + T)))
        for a0 in (0, 1):
            pairs.append(((j, a0, 0), (j, a0, 1), at(j, a0 + T, 1 + Dd)))
        # across half-edge k, its outer pair of cells (the inner pair is the corner's own edge)
        pj, pk = at(j, -np.minimum(Dd, 0), 1 + T), at(k, 1 + T, np.maximum(Dd, 0))
        pairs.append(((j, 0, 1), (k, 1, 0), (np.where(Dd < 0, pj[0], pk[0]), np.where(Dd < 0, pj[1], pk[1]))))
    boundaries = aligned = 0
    for c1, c2, (px, py) in pairs:
        if {label[c1], label[c2]} != {"dark", "bright"}:
            continue
        prof = _sample(gray, px, py)
        if np.isnan(prof).any():
            continue
        prof = prof.mean(0)
        if label[c1] == "bright":
            prof = 2.0 * mid - prof
        boundaries += 1
        above = np.nonzero(prof > mid)[0]
        if above.size and above[0] > 0:
            i = int(above[0])
            f = (mid - prof[i - 1]) / (prof[i] - prof[i - 1])
            aligned += int(abs(dd[i - 1] + f * (dd[i] - dd[i - 1])) <= LATTICE_ALIGNED)
    return LatticeCells(counts, inner_in, inner_ok, tuple(float(z) for z in s), ratio, boundaries, aligned,
                        (dark, bright), stepless)


def is_tag_lattice(cells: LatticeCells | None, min_each: int = 2, min_boundaries: int = 3) -> bool:
    """Whether the cells around an X-corner on its own lattice (:func:`lattice_cells`) are a tag's bits:
    at least three of the middle four cells inside the image and every one of those uniform at its
    sector's level; every one of the twelve around them inside the image uniform at one of the two
    levels, at least ``min_each`` of each; at least ``min_boundaries`` boundaries between cells of
    the two levels, every one on the lattice's lines; and beside every half-edge that measured its
    own cell length, a change of level one cell out."""
    if cells is None:
        return False
    c = cells.counts
    return cells.inner_in >= 3 and cells.inner_ok == cells.inner_in and c["mix"] == 0 and c["other"] == 0 \
        and c["dark"] >= min_each and c["bright"] >= min_each \
        and cells.boundaries >= min_boundaries and cells.aligned == cells.boundaries and cells.stepless == 0
