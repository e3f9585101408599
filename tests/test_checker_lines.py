"""Sector edges that run on past a candidate's outline (cpdetect.checker_lines), on analytic images."""
from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from cpdetect.checker_lines import edges_running_on, sector_edges
from cpdetect.markers import MarkerSpec, apply_homography, plane_homography, projected_center, render_marker
from cpdetect.types import MARKER_TYPES

from detector_contract import textured_background

LEVELS = (30.0, 215.0)


def marker_scene(marker_type, radius, tilt_deg, angle, margin=0.0, shape=(480, 640), seed=0):
    """A tilted marker on a textured wall: the image, its centre, its outline polygon (pixels)."""
    spec = MarkerSpec(marker_type, size_m=1.0, margin_m=margin)
    centre = (shape[1] / 2 + 0.3, shape[0] / 2 - 0.2)
    f = 800.0
    K = np.array([[f, 0, centre[0]], [0, f, centre[1]], [0, 0, 1.0]])
    R = cv2.Rodrigues(np.array([0.6, 0.8, 0.0]) * math.radians(tilt_deg))[0] @ cv2.Rodrigues(
        np.array([0.0, 0.0, angle]))[0]
    H = plane_homography(K, R, np.array([0.0, 0.0, f * 0.5 / radius]))
    img = textured_background(shape, seed)
    render_marker(spec, H, shape).composite(img, LEVELS[0], LEVELS[1], 235.0)
    img += np.random.default_rng(seed + 1).normal(0.0, 2.0, img.shape)
    outline = apply_homography(H, spec.outline(256))
    return np.clip(img + 0.5, 0, 255).astype(np.uint8), projected_center(H), outline


def board(cell, angle_deg, corner, shape=(480, 640), shade_line=None, shade=0.45):
    """A checkerboard (grey 30 / 215) filling the image, one corner at ``corner``, turned by
    ``angle_deg``; with ``shade_line`` = (point, direction in degrees) a cast shadow's edge (2 px
    soft) along that line, the greys on its left side ``shade`` times as bright."""
    h, w = shape
    yy, xx = np.mgrid[0:h * 4, 0:w * 4].astype(np.float32) / 4.0 - 0.375  # 4x supersampled
    c, s = math.cos(math.radians(angle_deg)), math.sin(math.radians(angle_deg))
    u = (c * (xx - corner[0]) + s * (yy - corner[1])) / cell
    v = (-s * (xx - corner[0]) + c * (yy - corner[1])) / cell
    img = np.where((np.floor(u) + np.floor(v)) % 2 == 0, LEVELS[1], LEVELS[0]).astype(np.float32)
    img = cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA)
    if shade_line is not None:
        (px, py), a = shade_line
        yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
        side = (xx - px) * math.sin(math.radians(a)) - (yy - py) * math.cos(math.radians(a))
        img *= 1.0 - (1.0 - shade) / (1.0 + np.exp(np.clip(side / 1.0, -30, 30)))
    img += np.random.default_rng(1).normal(0, 1.5, img.shape).astype(np.float32)
    return np.clip(img + 0.5, 0, 255).astype(np.uint8)


def circle(x, y, r, n=64):
    t = np.linspace(0, 2 * np.pi, n, endpoint=False)
    return np.stack([x + r * np.cos(t), y + r * np.sin(t)], 1)


@pytest.mark.parametrize("angle", [0.0, 0.3, 0.785])
def test_sector_edges_of_a_frontal_checker_corner(angle):
    img = board(100, math.degrees(angle), (320.4, 240.7))
    phi, sign = sector_edges(img, 320.4, 240.7, 30.0, LEVELS)
    # the corner's four lines, every quarter turn from the board's angle, alternately rising and falling
    want = angle + np.arange(4) * 0.5 * np.pi
    off = np.abs(np.angle(np.exp(1j * (phi[:, None] - want[None, :]))))
    assert np.all(off.min(axis=0) < math.radians(1.0)) and np.all(off.min(axis=1) < math.radians(1.0))
    assert set(sign) == {-1.0, 1.0} and np.all(sign * np.roll(sign, 1) < 0)


@pytest.mark.parametrize("marker_type", MARKER_TYPES)
@pytest.mark.parametrize("radius, tilt, margin", [(12.0, 0.0, 0.0), (30.0, 45.0, 0.0), (30.0, 55.0, 0.3),
                                                  (80.0, 30.0, 0.0)])
def test_a_markers_edges_end_at_its_outline(marker_type, radius, tilt, margin):
    img, (x, y), outline = marker_scene(marker_type, radius, tilt, 0.4, margin)
    assert sector_edges(img, x, y, radius, LEVELS) is not None
    assert edges_running_on(img, x, y, radius, LEVELS, outline) == 0


@pytest.mark.parametrize("angle", [0.0, 20.0, 40.0])
@pytest.mark.parametrize("outline_r", [15.0, 30.0])
def test_a_checkerboard_corners_edges_run_on(angle, outline_r):
    # an outline closed far inside 120 px cells: all four lines run on to the next corners
    x, y = 320.4, 240.7
    img = board(120, angle, (x, y))
    assert edges_running_on(img, x, y, outline_r, LEVELS, circle(x, y, outline_r)) == 4
    # where they run on only as far as the outline's 1.5 times (cells of 1.5 outline radii, beyond
    # which the next cells' lines cross them), no edge runs on all the way to 2 times
    small = board(1.5 * outline_r, angle, (x, y))
    assert edges_running_on(small, x, y, outline_r, LEVELS, circle(x, y, outline_r)) < 4


def test_a_cast_shadow_through_a_checkerboard_corner_leaves_its_edges_running_on():
    # the shadow's edge through the corner at 2-8 degrees to one of the board's lines (47100/61);
    # the shade keeps 0.6 of the contrast, over STEP_MIN of the sunlit levels given here
    x, y = 320.4, 240.7
    for turn in (22.0, 24.0, 28.0):
        img = board(200, 20.0, (x, y), shade_line=((x, y), turn), shade=0.6)
        assert edges_running_on(img, x, y, 25.0, LEVELS, circle(x, y, 25.0)) == 4
    # a deeper shade (0.45) leaves steps under half the sunlit contrast on the shaded stretches
    img = board(200, 20.0, (x, y), shade_line=((x, y), 28.0), shade=0.45)
    assert edges_running_on(img, x, y, 25.0, LEVELS, circle(x, y, 25.0)) < 4


def test_edges_past_the_image_border_do_not_count():
    # a corner 20 px from the right border: the edge running right leaves the image at once
    x, y = 620.3, 240.7
    img = board(120, 0.0, (x, y))
    assert edges_running_on(img, x, y, 15.0, LEVELS, circle(x, y, 15.0)) == 3


def test_no_edges_on_a_plain_wall():
    img = np.full((200, 200), 120, np.uint8)
    assert sector_edges(img, 100.0, 100.0, 20.0, LEVELS) is None
    assert edges_running_on(img, 100.0, 100.0, 20.0, LEVELS, circle(100, 100, 20)) == 0
    # a candidate outside the image, or levels that do not differ, count none either
    assert edges_running_on(img, -50.0, 100.0, 20.0, LEVELS) == 0
    corner = board(120, 0.0, (100.0, 100.0), shape=(200, 200))
    assert edges_running_on(corner, 100.0, 100.0, 20.0, (90.0, 90.0)) == 0
