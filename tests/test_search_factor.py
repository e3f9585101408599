"""The classical detector's search reduction: ``search_megapixels`` and ``min_search_radius_px``."""
from __future__ import annotations

import numpy as np
import pytest

from cpdetect import get_detector
from cpdetect.classical import ClassicalSettings, search_factor

from detector_contract import marker_image


@pytest.mark.parametrize("size, settings, k", [
    ((640, 480), {}, 1),
    ((1920, 1080), {}, 1),
    ((4000, 3000), {}, 2),  # 3.0 MP at k = 2, and 8 px are 4 search pixels there
    ((6000, 4000), {}, 2),  # 6.0 MP at k = 2: over the cap, so k = 4 by megapixels, halved
    ((8192, 5460), {}, 2),
    ((8192, 5460), {"min_radius_px": 16.0}, 4),  # 16 px are 4 search pixels at k = 4
    ((8192, 5460), {"min_search_radius_px": None}, 4),  # the reduction of before
    ((8192, 5460), {"min_search_radius_px": 2.0}, 4),
    ((12000, 8400), {}, 4),  # k = 8 by megapixels: halved once only
    ((12000, 8400), {"min_radius_px": 32.0}, 8),
    ((12000, 8400), {"min_search_radius_px": None}, 8),
])
def test_search_factor(size, settings, k):
    assert search_factor(*size, ClassicalSettings(**settings)) == k


def test_search_factor_halves_at_most_once_and_never_below_one():
    s = ClassicalSettings(min_radius_px=2.0, min_search_radius_px=64.0)
    assert search_factor(8192, 5460, s) == 2
    assert search_factor(640, 480, s) == 1
    assert search_factor(1280, 960, ClassicalSettings(search_megapixels=0.5, min_radius_px=2.0,
                                                      min_search_radius_px=64.0)) == 1


@pytest.mark.parametrize("bad", [0.0, -1.0, 65.0, float("nan")])
def test_bad_min_search_radius_is_refused(bad):
    with pytest.raises(ValueError, match="min_search_radius_px"):
        ClassicalSettings(min_search_radius_px=bad)


def test_small_marker_is_found_only_by_the_finer_search():
    # 2400 x 3200 searched at k = 4 by search_megapixels 0.5: a marker of radius 9 px is 2.25 search
    # pixels there, under the X-corner search's reach; at k = 2 (4.5 search pixels) it is found
    centre = (1601.3, 1187.6)
    img = marker_image(center=centre, radius=9.0, angle=0.35, marker_type="circle", shape=(2400, 3200))
    finer = get_detector("classical", search_megapixels=0.5).detect(img)
    coarse = get_detector("classical", search_megapixels=0.5, min_search_radius_px=None).detect(img)
    assert finer.extras["search_factor"] == 2 and coarse.extras["search_factor"] == 4
    assert coarse.detections == []
    assert len(finer.detections) == 1
    m = finer.detections[0]
    assert np.hypot(m.x - centre[0], m.y - centre[1]) < 0.1
    assert 7.0 < m.radius_px < 11.0
    # the probability map is at the search image's size
    assert finer.probability.shape == (1200, 1600)
