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
    ring = [TAG_BITS[j, i] for j in range(1, 5) for i in range(1, 5) if not (j in (2, 3) and i in (2, 3))]
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

    from cpdetect.classical import ClassicalDetector

    path = tmp_path / "tag.jpg"
    markers = write_generated_jpeg(path, 22, 39900, width=8192, height=5460, radius_min_px=32, split="test")
    corner = (4747.8, 1311.8)
    truth = [(m.x, m.y) for m in markers]

    def split(dets):
        at = [d for d in dets if math.hypot(d.x - corner[0], d.y - corner[1]) < 10]
        true = [d for d in dets if min(math.hypot(d.x - x, d.y - y) for x, y in truth) < 0.2]
        return at, true

    trace: list = []
    at, true = split(ClassicalDetector(tag_grid_min_each=None).detect(path).detections)
    assert len(at) == 1 and at[0].type == "square" and len(true) == len(truth)
    at, true = split(ClassicalDetector(tag_grid_min_each=3).detect(path, trace=trace).detections)
    assert at == [] and len(true) == len(truth)
    assert split(ClassicalDetector().detect(path).detections)[0] == []  # the default: 3
    assert any(t["stage"] == "tag grid" and math.hypot(t["x"] - corner[0], t["y"] - corner[1]) < 20 for t in trace)
    # at 5 of each (8 dark, 4 bright) it stays
    at, _ = split(ClassicalDetector(tag_grid_min_each=5).detect(path).detections)
    assert len(at) == 1


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
