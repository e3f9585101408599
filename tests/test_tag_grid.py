"""The cells around a square marker's checker (cpdetect.tag_grid), on analytic images."""
from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from cpdetect.tag_grid import CELL_LABELS, grid_cells, is_tag_grid

DARK, BRIGHT = 30.0, 220.0


def render_cells(cells: np.ndarray, cell_px: float, centre: tuple[float, float], angle_deg: float,
                 shape=(480, 640), outside: float | np.ndarray = 128.0, noise: float = 1.5, seed: int = 0):
    """An image of a block of ``cells`` (n x n of 0 dark / 1 bright, n even) of ``cell_px`` pixels, its
    middle corner at ``centre`` (pixels), turned by ``angle_deg``; ``outside``: the grey level (or an
    image) beyond the block. Returns the uint8 image and the outline (4, 2) of the middle 2 x 2."""
    n = cells.shape[0]
    h, w = shape
    ss = 4
    yy, xx = np.mgrid[0:h * ss, 0:w * ss].astype(np.float64)
    xx, yy = (xx + 0.5) / ss - 0.5, (yy + 0.5) / ss - 0.5
    c, s = math.cos(math.radians(angle_deg)), math.sin(math.radians(angle_deg))
    u = (c * (xx - centre[0]) + s * (yy - centre[1])) / cell_px
    v = (-s * (xx - centre[0]) + c * (yy - centre[1])) / cell_px
    i, j = np.floor(u).astype(int) + n // 2, np.floor(v).astype(int) + n // 2
    inside = (i >= 0) & (i < n) & (j >= 0) & (j < n)
    big = np.broadcast_to(np.asarray(outside, np.float64), (h, w))
    img = cv2.resize(big, (w * ss, h * ss), interpolation=cv2.INTER_NEAREST).copy()
    img[inside] = np.where(cells[j[inside], i[inside]] > 0, BRIGHT, DARK)
    img = cv2.resize(img.astype(np.float32), (w, h), interpolation=cv2.INTER_AREA)
    img += np.random.default_rng(seed).normal(0, noise, img.shape).astype(np.float32)
    corners = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], float) * cell_px
    outline = np.stack([centre[0] + c * corners[:, 0] - s * corners[:, 1],
                        centre[1] + s * corners[:, 0] + c * corners[:, 1]], 1)
    return np.clip(img + 0.5, 0, 255).astype(np.uint8), outline


def checker_in(block: np.ndarray) -> np.ndarray:
    """``block`` (4 x 4 or larger, even) with a 2x2 checker in its middle."""
    b = block.copy()
    m = b.shape[0] // 2
    b[m - 1:m + 1, m - 1:m + 1] = [[0, 1], [1, 0]]
    return b



def ring_of(bits: np.ndarray) -> list[int]:
    """The twelve bits around the middle 2 x 2 of a 6 x 6 block (rows and columns 1-4, less 2-3)."""
    return [int(bits[j, i]) for j in range(1, 5) for i in range(1, 5) if not (j in (2, 3) and i in (2, 3))]


TAG_BITS = np.array([[0, 0, 0, 0, 0, 0],
                     [0, 1, 0, 1, 1, 0],
                     [0, 1, 0, 0, 1, 0],
                     [0, 0, 1, 1, 0, 0],
                     [0, 1, 1, 0, 1, 0],
                     [0, 0, 0, 0, 0, 0]])


@pytest.mark.parametrize("angle", [0.0, 17.0, 38.0])
def test_the_cells_around_a_tag_bit_corner_are_bits(angle):
    img, outline = render_cells(checker_in(TAG_BITS), 30.0, (320.3, 240.7), angle)
    counts = grid_cells(img, outline, 320.3, 240.7, (DARK, BRIGHT))
    # the twelve cells around the middle 2 x 2 of the 6 x 6 bits: rows 1-4, columns 1-4 of TAG_BITS
    ring = ring_of(TAG_BITS)
    assert counts == {"dark": ring.count(0), "bright": ring.count(1), "mix": 0, "other": 0, "out": 0}
    assert is_tag_grid(counts, 3) and is_tag_grid(counts, 2)
    assert not is_tag_grid(counts, min(ring.count(0), ring.count(1)) + 1)


def test_a_marker_on_its_margin_or_on_a_wall_is_no_tag():
    # a margin of one cell or more all around: twelve bright cells
    margin = checker_in(np.ones((4, 4), int))
    img, outline = render_cells(margin, 25.0, (300.0, 250.0), 12.0, outside=90.0)
    counts = grid_cells(img, outline, 300.0, 250.0, (DARK, BRIGHT))
    assert counts["bright"] == 12 and not is_tag_grid(counts, 1)
    # no margin, on a wall of another grey: "other"
    bare = checker_in(np.ones((2, 2), int))
    img, outline = render_cells(bare, 25.0, (300.0, 250.0), 12.0, outside=120.0)
    counts = grid_cells(img, outline, 300.0, 250.0, (DARK, BRIGHT))
    assert counts["other"] == 12 and not is_tag_grid(counts, 1)
    # a margin of 0.4 cell on a dark wall at the ink's level: most of each cell's samples lie on the
    # wall, so every cell reads dark (the median), none bright
    img, outline = render_cells(bare, 25.0, (300.0, 250.0), 12.0, outside=DARK)
    yy, xx = np.mgrid[0:480, 0:640]
    c, s = math.cos(math.radians(12.0)), math.sin(math.radians(12.0))
    ring = np.maximum(np.abs(c * (xx - 300) + s * (yy - 250)), np.abs(-s * (xx - 300) + c * (yy - 250))) / 25.0
    img[(ring >= 1.0) & (ring < 1.4)] = np.uint8(BRIGHT)
    counts = grid_cells(img, outline, 300.0, 250.0, (DARK, BRIGHT))
    assert counts["bright"] == 0 and counts["dark"] + counts["mix"] == 12 and not is_tag_grid(counts, 1)


def test_a_textured_background_is_no_tag():
    rng = np.random.default_rng(3)
    texture = cv2.GaussianBlur(rng.uniform(0, 255, (480, 640)).astype(np.float32), (0, 0), 3.0) * 4 - 384
    img, outline = render_cells(checker_in(np.ones((2, 2), int)), 25.0, (300.0, 250.0), 5.0,
                                outside=np.clip(texture, 0, 255))
    counts = grid_cells(img, outline, 300.0, 250.0, (DARK, BRIGHT))
    assert counts["dark"] + counts["bright"] < 12 and not is_tag_grid(counts, 3)


def test_cells_outside_the_image_are_out_and_do_not_count():
    img, outline = render_cells(checker_in(TAG_BITS), 30.0, (70.2, 240.4), 0.0)
    counts = grid_cells(img, outline, 70.2, 240.4, (DARK, BRIGHT))
    # the left column of cells (x from 70 - 60 = 10 px) is inside; moved 25 px left, it leaves
    assert counts["out"] == 0
    img, outline = render_cells(checker_in(TAG_BITS), 30.0, (45.2, 240.4), 0.0)
    counts = grid_cells(img, outline, 45.2, 240.4, (DARK, BRIGHT))
    assert counts["out"] == 4 and counts["mix"] == 0 and counts["other"] == 0
    assert sum(counts.values()) == 12 and set(counts) == set(CELL_LABELS)


def test_an_outline_without_four_corners_or_levels_gives_no_cells():
    img = np.full((100, 100), 128, np.uint8)
    assert grid_cells(img, np.array([[10.0, 10.0], [20.0, 10.0], [15.0, 20.0]]), 15.0, 13.0, (DARK, BRIGHT)) is None
    ellipse = cv2.ellipse2Poly((50, 50), (20, 14), 0, 0, 360, 5).astype(float)
    assert grid_cells(img, ellipse, 50.0, 50.0, (DARK, BRIGHT)) is None
    square = np.array([[40.0, 40.0], [60.0, 40.0], [60.0, 60.0], [40.0, 60.0]])
    assert grid_cells(img, square, 50.0, 50.0, (120.0, 120.0)) is None
    assert not is_tag_grid(None)


def test_the_detector_drops_a_tag_bit_corner_by_its_grid(tmp_path):
    # image 22 of the 45 MP test-split set of seed 39900 (`--size 8192x5460 --radius-min 32`): the
    # X-corner between bit cells of a large tag kept as a square (radius 60 px, score 0.75); its
    # twelve surrounding cells are bits, 8 dark and 4 bright, every one uniform
    from photo_helpers import write_generated_jpeg

    from cpdetect.classical import BASE_SCORE_FILE, ClassicalDetector
    # the tests' parts, with the score trees under which they were chosen (before stop 83); the
    # defaults' result last

    path = tmp_path / "tag.jpg"
    markers = write_generated_jpeg(path, 22, 39900, width=8192, height=5460, radius_min_px=32, split="test")
    corner = (4747.8, 1311.8)
    truth = [(m.x, m.y) for m in markers]

    def split(dets):
        at = [d for d in dets if math.hypot(d.x - corner[0], d.y - corner[1]) < 10]
        true = [d for d in dets if min(math.hypot(d.x - x, d.y - y) for x, y in truth) < 0.2]
        return at, true

    trace: list = []
    # the lattice test (stop 77) takes it for a tag's bits too: off here, to see the grid test's part
    at, true = split(ClassicalDetector(score_trees=BASE_SCORE_FILE, tag_grid_min_each=None, tag_lattice=False).detect(path).detections)
    assert len(at) == 1 and at[0].type == "square" and len(true) == len(truth)
    at, true = split(ClassicalDetector(score_trees=BASE_SCORE_FILE, tag_grid_min_each=3, tag_lattice=False).detect(path, trace=trace).detections)
    assert at == [] and len(true) == len(truth)
    assert split(ClassicalDetector().detect(path).detections)[0] == []  # the defaults: 3, and the lattice
    assert any(t["stage"] == "tag grid" and math.hypot(t["x"] - corner[0], t["y"] - corner[1]) < 20 for t in trace)
    # at 5 of each (8 dark, 4 bright) it stays
    at, _ = split(ClassicalDetector(score_trees=BASE_SCORE_FILE, tag_grid_min_each=5, tag_lattice=False).detect(path).detections)
    assert len(at) == 1
    trace = []
    at, true = split(ClassicalDetector(score_trees=BASE_SCORE_FILE, tag_grid_min_each=None).detect(path, trace=trace).detections)
    assert at == [] and len(true) == len(truth)
    assert any(t["stage"] == "tag lattice" and math.hypot(t["x"] - corner[0], t["y"] - corner[1]) < 20 for t in trace)


def test_the_tag_grid_setting_is_checked():
    from cpdetect import get_detector
    from cpdetect.errors import UsageError

    for bad in (0, 7):
        with pytest.raises(UsageError, match=r"tag_grid_min_each must be an integer in \[1, 6\] or null"):
            get_detector("classical", tag_grid_min_each=bad)
    for bad in (2.5, True, "3"):  # the settings' own type check
        with pytest.raises(UsageError, match=r"setting tag_grid_min_each=.*: expected int or null"):
            get_detector("classical", tag_grid_min_each=bad)
    assert get_detector("classical", tag_grid_min_each=3).settings.tag_grid_min_each == 3
    assert get_detector("classical", tag_grid_min_each=None).settings.tag_grid_min_each is None


# ------------------------------------------------------------------------------------------------
# the lattice of the corner's own sector edges (lattice_cells, is_tag_lattice)


# a tag whose middle corner has a bit of the other level one cell out along each of its four edges
# (a cell's length is read where either sector beside an edge first changes level; where both run on
# for two cells, along an edge and its opposite, the lattice is taken as two cells long that way and
# its neighbouring lengths are LATTICE_MAX_RATIO apart: no lattice, the corner is not called a tag)
LATTICE_BITS = np.array([[0, 0, 0, 0, 0, 0],
                         [0, 1, 1, 1, 1, 0],
                         [0, 1, 0, 1, 0, 0],
                         [0, 0, 1, 0, 1, 0],
                         [0, 1, 1, 1, 1, 0],
                         [0, 0, 0, 0, 0, 0]])


@pytest.mark.parametrize("angle", [0.0, 17.0, 38.0])
@pytest.mark.parametrize("radius", [30.0, 90.0])
def test_a_tag_bit_corner_sits_on_a_lattice_of_bits(angle, radius):
    from cpdetect.tag_grid import is_tag_lattice, lattice_cells

    # radius 90: an outline three cells out, as where the sectors' rays ran on over bits of their level
    img, _ = render_cells(checker_in(LATTICE_BITS), 30.0, (320.3, 240.7), angle)
    cells = lattice_cells(img, 320.3, 240.7, radius)
    ring = ring_of(LATTICE_BITS)
    assert cells.counts == {"dark": ring.count(0), "bright": ring.count(1), "mix": 0, "other": 0, "out": 0}
    assert cells.inner_in == cells.inner_ok == 4
    assert all(abs(s - 30.0) < 1.5 for s in cells.cell_px), cells.cell_px
    assert cells.ratio < 1.1 and cells.boundaries >= 3 and cells.aligned == cells.boundaries
    assert abs(cells.levels[0] - DARK) < 3 and abs(cells.levels[1] - BRIGHT) < 3
    assert is_tag_lattice(cells)
    assert not is_tag_lattice(cells, min_each=min(ring.count(0), ring.count(1)) + 1)
    assert not is_tag_lattice(cells, min_boundaries=cells.boundaries + 1)


def test_printed_markers_are_not_on_a_lattice_of_bits():
    from cpdetect.tag_grid import is_tag_lattice, lattice_cells

    # a margin of a cell or more: twelve bright cells; no margin on a wall of another grey: "other"
    for block, outside, label in ((np.ones((4, 4), int), 90.0, "bright"), (np.ones((2, 2), int), 120.0, "other")):
        img, _ = render_cells(checker_in(block), 25.0, (300.0, 250.0), 12.0, outside=outside)
        cells = lattice_cells(img, 300.0, 250.0, 25.0)
        assert cells.counts[label] == 12 and not is_tag_lattice(cells, min_each=1)
    # a textured wall
    rng = np.random.default_rng(3)
    texture = cv2.GaussianBlur(rng.uniform(0, 255, (480, 640)).astype(np.float32), (0, 0), 3.0) * 4 - 384
    img, _ = render_cells(checker_in(np.ones((2, 2), int)), 25.0, (300.0, 250.0), 5.0, outside=np.clip(texture, 0, 255))
    assert not is_tag_lattice(lattice_cells(img, 300.0, 250.0, 25.0))


def test_a_round_margin_on_a_dark_wall_is_not_a_lattice_of_bits():
    # a circle marker (radius 30 px) with a bright margin to 2 radii on a wall at the ink's level:
    # the cells beside the edges fall on the margin (bright) and those at the corners on the wall
    # (dark), every one uniform, so the counts alone would call it a tag; but the boundaries between
    # margin and wall are round, not on the lattice's lines
    from cpdetect.tag_grid import is_tag_lattice, lattice_cells

    ss, h, w, cx, cy, r = 4, 300, 300, 150.3, 149.6, 30.0
    yy, xx = np.mgrid[0:h * ss, 0:w * ss].astype(np.float64)
    xx, yy = (xx + 0.5) / ss - 0.5 - cx, (yy + 0.5) / ss - 0.5 - cy
    rho = np.hypot(xx, yy)
    img = np.full(xx.shape, DARK)
    img[rho < 2.0 * r] = BRIGHT
    inside = rho < r
    img[inside] = np.where((xx[inside] > 0) == (yy[inside] > 0), DARK, BRIGHT)
    img = cv2.resize(img.astype(np.float32), (w, h), interpolation=cv2.INTER_AREA)
    img = np.clip(img + np.random.default_rng(1).normal(0, 1.5, img.shape) + 0.5, 0, 255).astype(np.uint8)
    cells = lattice_cells(img, cx, cy, r)
    assert all(abs(s - r) < 2.0 for s in cells.cell_px), cells.cell_px
    assert cells.counts["dark"] >= 2 and cells.counts["bright"] >= 2
    assert cells.aligned < cells.boundaries and not is_tag_lattice(cells)


def test_no_lattice_without_four_alternating_sectors_or_with_unequal_cells():
    from cpdetect.tag_grid import lattice_cells

    assert lattice_cells(np.full((200, 200), 128, np.uint8), 100.0, 100.0, 20.0) is None
    # a single edge: two sectors
    img = np.full((200, 200), DARK, np.uint8)
    img[:, 100:] = np.uint8(BRIGHT)
    assert lattice_cells(img, 99.5, 100.0, 20.0) is None
    # a centre too near the border for the rings the edges are read on
    img, _ = render_cells(checker_in(LATTICE_BITS), 30.0, (2.0, 240.0), 0.0)
    assert lattice_cells(img, 2.0, 240.0, 30.0) is None
    # a radius too small to look past the rings, or none at all
    img, _ = render_cells(checker_in(LATTICE_BITS), 30.0, (320.3, 240.7), 0.0)
    assert lattice_cells(img, 320.3, 240.7, 1.0) is None and lattice_cells(img, 320.3, 240.7, float("nan")) is None
    # cells three times as long one way as the other: no lattice (at most LATTICE_MAX_RATIO)
    img = np.full((300, 400), 128, np.uint8)
    xx = np.arange(400)[None, :] - 200.0
    yy = np.arange(300)[:, None] - 150.0
    cell = ((np.floor(xx / 60.0) + np.floor(yy / 20.0)) % 2).astype(bool)
    img[:] = np.where(cell, np.uint8(BRIGHT), np.uint8(DARK))
    img[(np.abs(xx) > 60) | (np.abs(yy) > 20)] = 128
    assert lattice_cells(img, 199.5, 149.5, 30.0) is None


def test_the_detector_drops_a_tag_bit_corner_on_its_lattice(tmp_path):
    # image 53 of the 1920 x 1080 test-split set of seed 44300: the X-corner between bit cells of a
    # tag, kept as a square (radius 54 px, score 0.66) whose outline spans more than one cell, so the
    # tag-grid test does not take it for one; on its own lattice its twelve cells are 5 dark and 7
    # bright bits, every boundary on the lattice's lines
    from photo_helpers import write_generated_jpeg

    from cpdetect.classical import BASE_SCORE_FILE, ClassicalDetector
    # the tests' parts, with the score trees under which they were chosen (before stop 83); the
    # defaults' result last

    path = tmp_path / "tag.jpg"
    markers = write_generated_jpeg(path, 53, 44300, width=1920, height=1080, split="test")
    corner = (494.2, 509.5)
    truth = [(m.x, m.y) for m in markers]

    def split(dets):
        at = [d for d in dets if math.hypot(d.x - corner[0], d.y - corner[1]) < 10]
        true = [d for d in dets if min(math.hypot(d.x - x, d.y - y) for x, y in truth) < 0.3]
        return at, true

    at, true = split(ClassicalDetector(score_trees=BASE_SCORE_FILE, tag_lattice=False).detect(path).detections)
    assert len(at) == 1 and at[0].type == "square" and len(true) == len(truth) >= 1
    trace: list = []
    at, true2 = split(ClassicalDetector(score_trees=BASE_SCORE_FILE, tag_lattice=True).detect(path, trace=trace).detections)
    assert at == [] and [(d.x, d.y) for d in true2] == [(d.x, d.y) for d in true]
    assert any(t["stage"] == "tag lattice" and math.hypot(t["x"] - corner[0], t["y"] - corner[1]) < 20 for t in trace)
    assert split(ClassicalDetector().detect(path).detections)[0] == []  # the default since rule 39


def test_a_printed_marker_whose_lattice_an_occluder_shortened_is_kept(tmp_path):
    # image 162 of the 1920 x 1080 test-split set of seed 45300 (rule 38's): a square of radius 29 px,
    # 15 % covered. Where the occluder crosses a dark sector the level changes at about half the
    # sector's length, so the lattice along that edge is half a sector long and its cells lie inside
    # the marker: 2 dark and 10 bright, uniform, the marker's own edges on its lines. The cells one
    # further along that edge are of their sector's level on both sides (no bit changes there), which
    # a tag's lattice cannot show, so it is no tag; rule 38 had dropped it for one
    from photo_helpers import write_generated_jpeg

    from cpdetect.classical import ClassicalDetector
    from cpdetect.tag_grid import is_tag_lattice, lattice_cells

    path = tmp_path / "occluded.jpg"
    markers = write_generated_jpeg(path, 162, 45300, width=1920, height=1080, split="test")
    m = min(markers, key=lambda m: math.hypot(m.x - 318.74, m.y - 926.75))
    assert math.hypot(m.x - 318.74, m.y - 926.75) < 0.01 and m.type == "square"
    cells = lattice_cells(cv2.imread(str(path), cv2.IMREAD_GRAYSCALE), m.x, m.y, 33.8)
    assert cells.stepless >= 1 and cells.counts["mix"] == cells.counts["other"] == 0
    assert min(cells.counts["dark"], cells.counts["bright"]) >= 2 and cells.aligned == cells.boundaries >= 3
    assert not is_tag_lattice(cells)
    found = [d for d in ClassicalDetector(tag_lattice=True).detect(path).detections
             if math.hypot(d.x - m.x, d.y - m.y) < 0.3]
    assert len(found) == 1 and found[0].type == "square"


def test_the_tag_lattice_setting_is_checked():
    from cpdetect import get_detector
    from cpdetect.errors import UsageError

    for bad in (1, "yes", None):
        with pytest.raises(UsageError, match=r"setting tag_lattice=.*: expected bool"):
            get_detector("classical", tag_lattice=bad)
    assert get_detector("classical", tag_lattice=True).settings.tag_lattice is True
