"""The four-sector pattern must reach the centre: analytic markers against two blobs with a gap."""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from cpdetect.centre_reach import (CENTRE_REACH_MIN, centre_level_offset, centre_reach, edge_blur_px, ring_samples,
                                  second_harmonic)
from cpdetect.markers import MarkerSpec, frontal_homography, projected_center, projected_radius, render_marker


def render(center, radius, angle=0.0, marker_type="square", blur=0.0, size=160):
    """A frontal marker (dark 40, bright 210) on a grey field: image, centre, equal-area radius."""
    spec = MarkerSpec(marker_type, size_m=1.0)
    H = frontal_homography(center, radius, angle, spec)
    img = np.full((size, size), 120.0, np.float32)
    render_marker(spec, H, (size, size)).composite(img, 40.0, 210.0)
    if blur > 0:
        img = cv2.GaussianBlur(img, (0, 0), blur)
    return img, projected_center(H), projected_radius(spec, H)


def two_blobs(gap: float, blur: float, size: int = 160) -> np.ndarray:
    """Two dark discs on a bright field, diagonal to each other, ``gap`` px apart at the centre."""
    img = np.full((size, size), 210.0, np.float32)
    c = (size - 1) / 2.0
    r = 30.0
    off = (r + gap / 2.0) / np.sqrt(2.0)
    for s in (-1, 1):
        cv2.circle(img, (int(round((c + s * off) * 16)), int(round((c + s * off) * 16))), int(r * 16), 40.0, -1,
                   cv2.LINE_AA, 4)
    return cv2.GaussianBlur(img, (0, 0), blur) if blur > 0 else img


@pytest.mark.parametrize("marker_type", ["square", "circle", "diagonal"])
@pytest.mark.parametrize("blur", [0.0, 1.0, 2.5, 4.0])
def test_markers_reach_their_centre_sharp_or_blurred(marker_type, blur):
    img, (cx, cy), radius = render((80.3, 79.6), 40.0, angle=0.4, marker_type=marker_type, blur=blur)
    reach = centre_reach(img, cx, cy, radius)
    assert CENTRE_REACH_MIN + 0.2 < reach < 1.2


def test_a_gap_between_two_blobs_does_not_reach_the_centre():
    for gap, blur in ((8.0, 0.0), (10.0, 1.0), (16.0, 2.0)):
        reach = centre_reach(two_blobs(gap, blur), 79.5, 79.5, 45.0)
        assert reach < CENTRE_REACH_MIN, (gap, blur, reach)


def test_edge_blur_grows_with_the_blur_and_harmonic_of_a_uniform_ring_is_zero():
    scales = []
    for blur in (0.5, 1.5, 3.0):
        img, (cx, cy), radius = render((80.0, 80.0), 40.0, blur=blur)
        scales.append(edge_blur_px(img, cx, cy, radius))
    assert scales[0] < scales[1] < scales[2]
    assert 0.9 < scales[1] / 1.5 < 1.15 and 0.9 < scales[2] / 3.0 < 1.1
    assert second_harmonic(np.full((50, 50), 100.0, np.float32), 25.0, 25.0, 10.0) < 1e-6


def test_a_blurred_noisy_marker_still_reaches_its_centre():
    # noise steepens the edge gradients; without the band average and smoothing the blur estimate
    # fell to 1.6 px for a 6 px blur and the small ring saw only 0.15 of the pattern
    img, (cx, cy), radius = render((80.0, 80.0), 26.0, angle=0.3, blur=6.0)
    noisy = img + np.random.default_rng(3).normal(0.0, 12.0, img.shape).astype(np.float32)
    assert 3.5 < edge_blur_px(noisy, cx, cy, radius) < 7.0
    assert centre_reach(noisy, cx, cy, radius) > CENTRE_REACH_MIN + 0.15


def test_ring_samples_from_a_window_equal_those_from_the_whole_image():
    rng = np.random.default_rng(1)
    img = cv2.GaussianBlur(rng.uniform(0, 255, (120, 150)).astype(np.float32), (0, 0), 2.0)
    for x, y, r in ((75.3, 60.2, 20.0), (4.5, 7.0, 12.0), (148.0, 118.5, 30.0)):  # inside, across corners
        th = np.arange(90) * (2 * np.pi / 90)
        xs = (x + r * np.cos(th)).astype(np.float32)[None]
        ys = (y + r * np.sin(th)).astype(np.float32)[None]
        full = cv2.remap(img, xs, ys, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)[0]
        assert np.allclose(ring_samples(img, x, y, r, 90)[1], full, atol=1e-3)


def dark_share_of(img: np.ndarray, cx: float, cy: float, radius: float) -> float:
    """The dark sectors' share of the turn, read on a ring at half the radius of a sharp rendering."""
    _, v = ring_samples(img, cx, cy, 0.5 * radius, 720)
    return float(np.mean(v < 125.0))


@pytest.mark.parametrize("marker_type", ["square", "circle", "diagonal"])
@pytest.mark.parametrize("blur", [0.0, 1.0, 2.5])
def test_the_grey_at_a_markers_centre_is_its_sectors_mean_sharp_or_blurred(marker_type, blur):
    sharp, (cx, cy), radius = render((80.3, 79.6), 40.0, angle=0.4, marker_type=marker_type)
    img = cv2.GaussianBlur(sharp, (0, 0), blur) if blur > 0 else sharp
    off = centre_level_offset(img, cx, cy, (40.0, 210.0), dark_share_of(sharp, cx, cy, radius))
    assert abs(off) < 0.03, off


def test_a_sheared_marker_keeps_its_centre_grey_at_the_sectors_mean():
    # an affine view about the centre: the sector edges stay straight lines through it, the dark
    # share is no longer one half
    spec = MarkerSpec("square", size_m=1.0)
    c = np.array([80.2, 79.7])
    A = np.array([[1.0, 0.55, 0.0], [0.0, 0.6, 0.0], [0.0, 0.0, 1.0]])
    T = np.array([[1.0, 0.0, c[0]], [0.0, 1.0, c[1]], [0.0, 0.0, 1.0]])
    H = T @ A @ np.linalg.inv(T) @ frontal_homography(tuple(c), 40.0, 0.3, spec)
    sharp = np.full((160, 160), 120.0, np.float32)
    render_marker(spec, H, (160, 160)).composite(sharp, 40.0, 210.0)
    (cx, cy), radius = projected_center(H), projected_radius(spec, H)
    share = dark_share_of(sharp, cx, cy, radius)
    assert abs(share - 0.5) > 0.1  # the shear made the sectors unequal
    for blur in (0.0, 1.5):
        img = cv2.GaussianBlur(sharp, (0, 0), blur) if blur > 0 else sharp
        assert abs(centre_level_offset(img, cx, cy, (40.0, 210.0), share)) < 0.03
        # the wrong share (that of a frontal view) is seen
        assert abs(centre_level_offset(img, cx, cy, (40.0, 210.0), 0.5)) > abs(share - 0.5) - 0.03


def test_a_gap_between_two_blobs_is_brighter_than_a_centre_and_an_overlap_darker():
    # a narrower gap under more blur fades towards the mean (3 px at 1 px blur: 0.04); the
    # classical detector's cut is 0.3
    for gap, blur in ((6.0, 0.0), (6.0, 1.0), (10.0, 2.0)):
        off = centre_level_offset(two_blobs(gap, blur), 79.5, 79.5, (40.0, 210.0), 0.4)
        assert 0.3 < off <= 0.4 + 1e-3, (gap, blur, off)
    off = centre_level_offset(two_blobs(2.0, 1.0), 79.5, 79.5, (40.0, 210.0), 0.4)  # they touch
    assert -0.6 < off < -0.3
    # and a point 4 px from a marker's centre, inside a sector, is not taken for its centre
    img, (cx, cy), radius = render((80.0, 80.0), 30.0, angle=0.2)
    for k in range(4):
        a = 0.2 + np.pi / 4 + k * np.pi / 2
        assert abs(centre_level_offset(img, cx + 4 * np.cos(a), cy + 4 * np.sin(a), (40.0, 210.0), 0.5)) > 0.4


def test_centre_level_offset_is_nan_off_the_image_or_without_contrast():
    img, (cx, cy), _ = render((80.0, 80.0), 30.0)
    assert np.isnan(centre_level_offset(img, 1.0, 80.0, (40.0, 210.0), 0.5))
    assert np.isnan(centre_level_offset(img, 80.0, 158.5, (40.0, 210.0), 0.5))
    assert np.isnan(centre_level_offset(img, cx, cy, (100.0, 100.0), 0.5))


@pytest.mark.parametrize("radius", [10.0, 25.0])
def test_motion_blur_along_a_bisector_moves_the_centre_grey_and_shows_as_edge_blur(radius):
    # a line kernel is not isotropic: along a sector bisector it averages two opposite sectors of
    # one colour into the centre. The classical detector's test of the centre grey therefore only
    # applies below an edge blur of 1.2 px (ClassicalSettings.centre_offset_max_blur_px)
    from cpdetect.synth_images import _motion_kernel

    img, (cx, cy), r = render((80.3, 79.6), radius, angle=0.4)
    offs = []
    for k, sign in ((0, -1), (1, 1)):
        blurred = cv2.filter2D(img, -1, _motion_kernel(7.0, 0.4 + np.pi / 4 + k * np.pi / 2),
                               borderType=cv2.BORDER_REFLECT)
        offs.append(centre_level_offset(blurred, cx, cy, (40.0, 210.0), 0.5))
        assert 0.18 < sign * offs[-1] < 0.3
        assert 1.5 < edge_blur_px(blurred, cx, cy, r) < 2.2
    # across the bisector (along a sector edge) the two colours still balance
    along = cv2.filter2D(img, -1, _motion_kernel(7.0, 0.4), borderType=cv2.BORDER_REFLECT)
    assert abs(centre_level_offset(along, cx, cy, (40.0, 210.0), 0.5)) < 0.03
