"""``hma`` with ``colour_centres``: markers painted in colours of one luminance, centred on the paint image."""
from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from learned.adapter import HMADetector
from test_learned_detector import OracleBackend, SoftBackend, rendered

CENTRE = (131.3, 118.6)
GREY = np.array([76.0, 76.0, 76.0])  # the luminance of pure red (0.299 x 255)
RED = np.array([0.0, 0.0, 255.0])    # BGR


def _painted(marker_type: str = "circle"):
    """(BGR image, pattern mask): a marker whose dark sectors are grey 76 and bright ones pure red,
    the same luminance (no checker in gray), on the gray textured background of ``rendered``."""
    gray, mask, _ = rendered(marker_type, center=CENTRE, radius=26.0, angle=0.5)
    inside = cv2.dilate(mask, np.ones((3, 3), np.uint8)) > 0
    lo, hi = np.percentile(gray[mask > 0], [5, 95])
    t = np.clip((gray.astype(np.float64) - lo) / (hi - lo), 0.0, 1.0)[..., None]
    bgr = np.repeat(gray[..., None], 3, axis=2).astype(np.float64)
    bgr[inside] = ((1.0 - t) * GREY + t * RED)[inside]
    return np.clip(np.round(bgr), 0, 255).astype(np.uint8), mask


def test_a_marker_without_gray_contrast_is_found_on_the_paint_image(tmp_path):
    bgr, mask = _painted("circle")
    gray = cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY)
    assert np.ptp(gray[mask > 0]) < 12  # nothing to refine in gray
    plain = HMADetector.with_backend(OracleBackend(mask), mirror_map="never", colour_centres=False).detect(bgr)
    assert plain.detections == [] and plain.extras["colour_found"] == 0
    det = HMADetector.with_backend(OracleBackend(mask), mirror_map="never")
    assert det.settings.colour_centres == "small"  # the default since stop 48: this 256 x 256 image is small
    assert det.colour_centres_for(256, 256) and not det.colour_centres_for(8192, 5460)
    assert HMADetector.with_backend(OracleBackend(mask), colour_centres=True).colour_centres_for(8192, 5460)
    assert HMADetector.with_backend(OracleBackend(mask), colour_centres=False).settings.colour_centres == "never"
    with pytest.raises(ValueError, match="colour_centres must be"):
        HMADetector.with_backend(OracleBackend(mask), colour_centres="yes")
    res = det.detect(bgr)
    assert res.extras["colour_found"] == 1 and len(res.detections) == 1
    d = res.detections[0]
    assert math.hypot(d.x - CENTRE[0], d.y - CENTRE[1]) < 0.15 and d.type == "circle"
    # its blob is in the returned map (the network is sure of it, so the gray pass kept it too)
    assert res.probability[mask > 0].mean() > 0.95
    # a gray image has no paint to look at
    assert det.detect(gray).detections == []
    # a file is read in gray for the network and again in colour for the paint
    cv2.imwrite(str(tmp_path / "painted.png"), bgr)
    cv2.imwrite(str(tmp_path / "gray.png"), gray)
    from_file = det.detect(tmp_path / "painted.png")
    assert from_file.detections == res.detections and from_file.extras["colour_found"] == 1
    assert det.detect(tmp_path / "gray.png").detections == []


def test_markers_found_in_gray_are_not_looked_at_again():
    gray, mask, _ = rendered("square", center=CENTRE, radius=26.0, angle=0.5)
    bgr = np.repeat(gray[..., None], 3, axis=2)
    plain = HMADetector.with_backend(OracleBackend(mask), mirror_map="never", colour_centres=False).detect(bgr)
    res = HMADetector.with_backend(OracleBackend(mask), mirror_map="never", colour_centres=True).detect(bgr)
    assert res.extras["colour_found"] == 0 and res.detections == plain.detections and len(plain.detections) == 1


def test_only_blobs_the_network_is_sure_of_are_looked_at():
    bgr, mask = _painted("circle")
    unsure = mask.astype(np.float32) * 0.8  # mean P 0.8, under colour_min_mean_p (0.9)
    res = HMADetector.with_backend(SoftBackend(unsure), mirror_map="never", colour_centres=True).detect(bgr)
    assert res.detections == [] and res.extras["colour_found"] == 0
    res = HMADetector.with_backend(SoftBackend(unsure), mirror_map="never", colour_centres=True,
                                   colour_min_mean_p=0.75).detect(bgr)
    assert res.extras["colour_found"] == 1


def test_the_colour_look_does_not_follow_the_map_clearing_cut():
    # which blobs are cleared from the returned map is a choice about the map alone: it must not
    # change which blobs get the colour look, and so not the markers
    bgr, mask = _painted("circle")
    sure = mask.astype(np.float32) * 0.95  # mean P 0.95
    for clear in (0.9, 0.97, 1.0):
        res = HMADetector.with_backend(SoftBackend(sure), mirror_map="never", colour_centres=True,
                                       clear_rejected_below=clear).detect(bgr)
        assert res.extras["colour_found"] == 1 and len(res.detections) == 1
    res = HMADetector.with_backend(SoftBackend(sure), mirror_map="never", colour_centres=True,
                                   colour_min_mean_p=0.97).detect(bgr)
    assert res.extras["colour_found"] == 0 and res.detections == []
