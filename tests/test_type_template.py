"""The template fit of small markers' types (cpdetect/type_template.py) on rendered markers whose
half-lines, lengths and type are known exactly."""
from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from cpdetect.centre_reach import edge_blur_px
from cpdetect.classical import ClassicalSettings, _template_checked, _Verified
from cpdetect.markers import MarkerSpec, apply_homography, plane_homography, projected_center, render_marker
from cpdetect.type_template import TYPES, combined_type, half_line_lengths, template_residuals


def rendered(mtype: str, radius: float = 10.0, tilt_deg: float = 0.0, blur: float = 0.0, noise: float = 2.0,
             seed: int = 0, shape=(96, 96), centre=(47.3, 48.6)):
    """A marker of half-size ``radius`` px on a flat grey wall (dark 30, bright 215, wall 120), tilted
    about an axis at 0.7 rad, spun 0.3 rad; with its centre, the four half-lines (ascending angles,
    the sectors' widths) and their exact lengths to the outline."""
    f = 800.0
    K = np.array([[f, 0, centre[0]], [0, f, centre[1]], [0, 0, 1.0]])
    axis = np.array([math.cos(0.7), math.sin(0.7), 0.0]) * math.radians(tilt_deg)
    R = cv2.Rodrigues(axis)[0] @ cv2.Rodrigues(np.array([0.0, 0.0, 0.3]))[0]
    H = plane_homography(K, R, np.array([0.0, 0.0, f * 0.5 / radius]))
    img = np.full(shape, 120.0)
    render_marker(MarkerSpec(mtype, size_m=1.0), H, shape).composite(img, 30.0, 215.0, 120.0)
    if blur > 0:
        img = cv2.GaussianBlur(img, (0, 0), blur)
    img += np.random.default_rng(seed).normal(0.0, noise, shape)
    h = 0.5  # the checker lines run to the side midpoints (square, circle) or the corners (diagonal)
    tips = np.array([[h, h], [-h, h], [-h, -h], [h, -h]]) if mtype == "diagonal" else \
        np.array([[h, 0], [0, h], [-h, 0], [0, -h]])
    c = projected_center(H)
    P = apply_homography(H, tips) - c
    ang = np.mod(np.arctan2(P[:, 1], P[:, 0]), 2 * math.pi)
    order = np.argsort(ang)
    bounds = ang[order]
    widths = np.mod(np.roll(bounds, -1) - bounds, 2 * math.pi)
    return np.clip(img + 0.5, 0, 255).astype(np.uint8), c, bounds, widths, np.hypot(*P[order].T)


@pytest.mark.parametrize("mtype", TYPES)
@pytest.mark.parametrize("tilt", [0.0, 40.0])
@pytest.mark.parametrize("blur", [0.0, 1.0])
def test_half_line_lengths_of_rendered_markers(mtype, tilt, blur):
    img, c, bounds, _, truth = rendered(mtype, tilt_deg=tilt, blur=blur)
    rel = half_line_lengths(img, c[0], c[1], bounds, 10.0) / truth - 1.0
    if mtype == "diagonal":
        # the step across a half-line fades before a diagonal's tip, where its two sectors narrow
        # to nothing: short by about the sampling offset plus the blur (SCALES makes up for it)
        assert np.all((rel > -0.2) & (rel < -0.05)), rel
    else:
        assert np.all((rel > -0.05) & (rel < 0.03)), rel


@pytest.mark.parametrize("mtype", TYPES)
@pytest.mark.parametrize("tilt", [0.0, 40.0])
@pytest.mark.parametrize("blur", [0.0, 1.0])
def test_the_true_type_fits_best_and_to_the_noise(mtype, tilt, blur):
    img, c, bounds, widths, _ = rendered(mtype, tilt_deg=tilt, blur=blur, noise=2.0)
    lengths = half_line_lengths(img, c[0], c[1], bounds, 10.0)
    res = template_residuals(img, c[0], c[1], bounds, widths, lengths, edge_blur_px(img, c[0], c[1], 10.0), 10.0)
    others = [res["focus_" + t] for t in TYPES if t != mtype]
    assert min(others) > 2.0 * res["focus_" + mtype]
    # noise of 2 grey levels and rounding to integers: the fit of the true type is about that good
    assert 1.5 < res[mtype] < 4.5


def test_no_residuals_where_the_window_leaves_the_image_or_lengths_fail():
    img, c, bounds, widths, truth = rendered("square", centre=(8.0, 48.6))
    assert template_residuals(img, c[0], c[1], bounds, widths, truth, 0.8, 10.0) == {}
    img, c, bounds, widths, truth = rendered("square")
    bad = truth.copy()
    bad[1] = np.nan
    assert template_residuals(img, c[0], c[1], bounds, widths, bad, 0.8, 10.0) == {}


def test_a_half_line_that_cannot_be_read_takes_its_opposites_length():
    img, c, bounds, _, truth = rendered("circle", noise=0.5)
    # the wall over one sector's half of half-line 1: the step across it is gone
    a = bounds[1]
    pts = np.array([[c[0], c[1]]]) + np.outer(np.arange(0, 40, 0.5), [math.cos(a), math.sin(a)])
    for x, y in pts:
        cv2.circle(img, (int(round(x)), int(round(y))), 3, 120, -1)
    got = half_line_lengths(img, c[0], c[1], bounds, 10.0)
    assert abs(got[1] - got[3]) < 1e-9
    assert abs(got[3] / truth[3] - 1.0) < 0.05


def test_combined_type_weighs_the_trees_against_the_template():
    res = {"focus_circle": 10.0, "focus_diagonal": 20.0, "focus_square": 5.0}
    # unsure trees: the square's residual is half the circle's, 100 % more, 0.1 x 100 = 10 in log
    assert combined_type({"circle": 0.6, "diagonal": 0.01, "square": 0.39}, res, 0.1) == "square"
    # sure trees: a probability of 1e-6 against 0.999999 is 13.8 in log, more than 10
    assert combined_type({"circle": 0.999999, "diagonal": 0.0, "square": 1e-6}, res, 0.1) == "circle"
    # a residual 5 % better is worth 0.5 in log: enough against 0.6 / 0.4 (0.41), not 0.7 / 0.3 (0.85)
    close = {"focus_circle": 10.5, "focus_diagonal": 20.0, "focus_square": 10.0}
    assert combined_type({"circle": 0.6, "diagonal": 0.0, "square": 0.4}, close, 0.1) == "square"
    assert combined_type({"circle": 0.7, "diagonal": 0.0, "square": 0.3}, close, 0.1) == "circle"
    assert combined_type({"circle": 0.6, "diagonal": 0.0, "square": 0.4}, {"circle": 1.0}, 0.1) == "circle"


def test_the_detector_step_retypes_only_small_unsure_markers():
    img, c, bounds, widths, _ = rendered("square", blur=1.0)
    s = ClassicalSettings(type_template_max_radius_px=16.0)
    v = _Verified(float(c[0]), float(c[1]), "circle", 11.3, 0.9, np.zeros((4, 2)),
                  type_probs={"circle": 0.55, "diagonal": 0.05, "square": 0.4}, bounds=bounds, widths=widths)
    assert _template_checked(img, v, s).type == "square"
    sure = {"circle": 0.995, "diagonal": 0.001, "square": 0.004}  # the second type under the 0.01 gate
    assert _template_checked(img, _replace(v, type_probs=sure), s).type == "circle"
    assert _template_checked(img, _replace(v, radius=17.0), s).type == "circle"  # over the radius
    assert _template_checked(img, _replace(v, type_probs=None), s).type == "circle"  # trees did not decide
    moved = _template_checked(img, v, s)
    assert (moved.x, moved.y, moved.radius, moved.score) == (v.x, v.y, v.radius, v.score)


def _replace(v, **kw):
    from dataclasses import replace

    return replace(v, **kw)


@pytest.mark.parametrize("name, value", [("type_template_max_radius_px", 0.0), ("type_template_max_radius_px", 300.0),
                                         ("type_template_weight", 0.0), ("type_template_gate", 1.0),
                                         ("type_template_gate", -0.1)])
def test_template_settings_are_checked(name, value):
    with pytest.raises(ValueError, match=name):
        ClassicalSettings(**{name: value})
