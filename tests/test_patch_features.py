"""The marker-area score features (cpdetect.classical.PATCH_FEATURES) on rendered markers with known levels."""
from __future__ import annotations

import math

import numpy as np
import pytest

import cpdetect.classical as C
from cpdetect.markers import MarkerSpec, frontal_homography, render_marker

DARK, BRIGHT, BACK = 35.0, 220.0, 128.0
SHAPE = (200, 240)


def frontal(marker_type: str, angle: float, center=(120.3, 99.6), radius=30.0) -> np.ndarray:
    img = np.full(SHAPE, BACK, np.float32)
    spec = MarkerSpec(marker_type, size_m=1.0)
    render_marker(spec, frontal_homography(center, radius, angle, spec), SHAPE).composite(img, DARK, BRIGHT)
    return np.clip(img + 0.5, 0, 255).astype(np.uint8)


def patch_of(gray: np.ndarray, center=(120.3, 99.6)):
    verifier = C._Verifier(C._search_levels(gray, 1)[2], C.ClassicalSettings(), gray.shape[::-1])
    v = verifier.verify(center[0], center[1], 1.5)
    assert not isinstance(v, str), v
    feats = verifier.patch_features(v.x, v.y, v.radius, v.bounds, v.widths, *v.levels)
    assert tuple(feats) == C.PATCH_FEATURES
    return np.array(list(feats.values())).reshape(len(C.PATCH_RINGS), C.PATCH_ANGLES), v


@pytest.mark.parametrize("marker_type", ["circle", "square", "diagonal"])
def test_patch_reads_the_sectors_dark_first_and_the_background(marker_type):
    P, v = patch_of(frontal(marker_type, 0.3))
    rings = np.array(C.PATCH_RINGS)
    n0 = int(round(float(v.widths[0]) / (2 * math.pi) * C.PATCH_ANGLES))
    assert 5 <= n0 <= 7  # about a quarter turn per sector, frontal
    inner = P[(rings >= 0.3) & (rings <= 0.6)]
    # the middle of the first sector (dark) and of the second (bright), clear of their edges
    assert np.abs(inner[:, 1:n0 - 1] - 0.0).max() < 0.06
    assert np.abs(inner[:, n0 + 1:2 * n0 - 1] - 1.0).max() < 0.06
    back = (BACK - DARK) / (BRIGHT - DARK)
    assert np.abs(P[rings >= 1.6] - back).max() < 0.06


def test_patch_is_the_same_whatever_the_markers_turn():
    # a quarter turn makes the first sector a bright one: the patch then starts one sector on
    base, _ = patch_of(frontal("circle", 0.2))
    for angle in (0.2 + math.pi / 2, 0.2 + 0.9, 0.2 + math.pi):
        P, _ = patch_of(frontal("circle", angle))
        assert np.abs(P - base).max() < 0.12  # one angular bin is 15 degrees: edges move within it
        assert np.abs(P - base).mean() < 0.02


def test_patch_rings_outside_the_image_are_nan_and_still_score():
    center = (18.4, 99.6)  # the outer rings (1.4 radii of 30 px and more) leave the image on the left
    gray = frontal("square", 0.25, center=center)
    P, v = patch_of(gray, center)
    rings = np.array(C.PATCH_RINGS)
    assert np.isnan(P[rings >= 1.4]).any() and np.isfinite(P[rings <= 0.45]).all()
    feats = dict(zip(C.PATCH_FEATURES, P.ravel()))
    model = C.score_model()
    x = np.array([feats.get(k, 0.5) for k in model.features], float)
    assert 0.0 <= float(model.probability(x)) <= 1.0


def test_score_trees_setting_names_a_shipped_file():
    with pytest.raises(ValueError, match="score_trees"):
        C.ClassicalSettings(score_trees="nosuch.json")
    gray = frontal("diagonal", 0.4)
    for name in (C.SCORE_FILE, C.BASE_SCORE_FILE):
        res = C.ClassicalDetector(score_trees=name).detect(gray)
        assert len(res.detections) == 1
        d = res.detections[0]
        assert d.type == "diagonal" and d.score > 0.9
        assert math.hypot(d.x - 120.3, d.y - 99.6) < 0.05
