"""The returned map corrected by a pass at a lower scale (learned.lower_map, ``large_lower_scale``)."""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from learned.adapter import HMADetector
from learned.infer import probability_map
from learned.lower_map import corrected_by_lower

from test_learned_detector import rendered


def _maps():
    """A returned map with a kept blob (rows 10-19, columns 10-19), a blob without a marker
    (rows 40-49, 40-49) and a lower map that extends the kept blob, denies the other and has a blob
    of its own (rows 40-49, columns 5-14) that touches neither."""
    prob = np.zeros((64, 64), np.float32)
    prob[10:20, 10:20] = 0.9
    prob[40:50, 40:50] = 0.95
    lower = np.zeros_like(prob)
    lower[8:24, 8:24] = 0.8   # the kept marker, larger
    lower[12:16, 12:16] = 0.3  # and lower than prob inside: the max keeps prob there
    lower[40:50, 40:50] = 0.2  # denies the blob without a marker
    lower[40:50, 5:15] = 0.99  # its own blob, touching no kept one
    return prob, lower


def test_a_kept_blob_takes_the_lower_extent_and_keeps_its_own_pixels():
    prob, lower = _maps()
    out = corrected_by_lower(prob, lower, [(15, 15)], 0.5)
    assert out.dtype == np.float32 and out.shape == prob.shape
    np.testing.assert_array_equal(out[8:24, 8:24] >= 0.5, True)  # grown to the lower blob
    assert out[12:16, 12:16].min() == pytest.approx(0.9)  # max of both: never lowered
    assert out[20:24, 20:24].min() == pytest.approx(0.8)
    assert out[:8].max() == 0.0 and out[24:40].max() == 0.0  # nothing beyond the lower blob


def test_a_blob_without_a_marker_is_cleared_unless_the_lower_map_confirms_it():
    prob, lower = _maps()
    out = corrected_by_lower(prob, lower, [(15, 15)], 0.5)
    assert out[40:50, 40:50].max() == 0.0
    confirmed = lower.copy()
    confirmed[40:50, 40:50] = 0.6
    kept = corrected_by_lower(prob, confirmed, [(15, 15)], 0.5)
    np.testing.assert_array_equal(kept[40:50, 40:50], prob[40:50, 40:50])  # confirmed: as it was
    # a lower map under the cut on a kept blob leaves it as it was (markers never change)
    denied = np.zeros_like(prob)
    np.testing.assert_array_equal(corrected_by_lower(prob, denied, [(15, 15)], 0.5)[10:20, 10:20], prob[10:20, 10:20])


def test_a_lower_blob_touching_no_kept_blob_adds_nothing():
    prob, lower = _maps()
    out = corrected_by_lower(prob, lower, [(15, 15)], 0.5)
    assert out[40:50, 5:15].max() == 0.0
    # without a marker nothing grows: the blob the lower map confirms (mean 0.72) stays as it was
    none = corrected_by_lower(prob, lower, [], 0.5)
    np.testing.assert_array_equal(none[10:20, 10:20], prob[10:20, 10:20])
    assert none[8:10, 8:24].max() == 0.0 and none[40:50, 5:15].max() == 0.0
    assert none[40:50, 40:50].max() == 0.0


def test_maps_of_two_sizes_are_refused():
    with pytest.raises(ValueError, match="lower map"):
        corrected_by_lower(np.zeros((8, 8), np.float32), np.zeros((8, 9), np.float32), [], 0.5)


class TwoScaleBackend:
    """Stands in for the network: P(marker) ``hi`` for passes at least ``width`` wide, ``lo`` for the
    narrower ones, whose attention is 1 (the fusion then takes the lower pass where it runs)."""

    name = "two-scale"

    def __init__(self, hi: np.ndarray, lo: np.ndarray, width: int):
        self.hi, self.lo, self.width = hi, lo, width

    def trunk(self, x: np.ndarray):
        m = self.hi if x.shape[1] >= self.width else self.lo
        m = cv2.resize(m, (x.shape[1], x.shape[0]), interpolation=cv2.INTER_NEAREST)
        logit = np.log(np.clip(m, 1e-4, 1 - 1e-4) / np.clip(1 - m, 1e-4, 1))
        return np.stack([np.zeros_like(logit), logit]), np.ones(x.shape, np.float32)


def _detector_pair(max_side: int):
    img, mask, _ = rendered("square", center=(80.0, 128.0), radius=22.0, angle=0.4)
    hi = cv2.erode(mask, np.ones((7, 7), np.uint8)).astype(np.float32)  # the marker's blob, too small
    hi[30:60, 180:210] = 0.97  # sure, and no marker there
    lo = cv2.dilate(mask, np.ones((3, 3), np.uint8)).astype(np.float32)
    lo[200:240, 180:220] = 0.99  # the lower pass's own blob, touching nothing
    common = dict(scales=(1.0,), small_scales=None, mirror_map="never", max_side=max_side)
    # the processing image is max_side wide: the lower pass (0.5) is narrower
    plain = HMADetector.with_backend(TwoScaleBackend(hi, lo, min(max_side, 256)), large_lower_scale=None, **common)
    lower = HMADetector.with_backend(TwoScaleBackend(hi, lo, min(max_side, 256)), large_lower_scale=0.5, **common)
    return img, mask, plain, lower


def test_images_seen_downscaled_get_the_lower_extent_and_lose_unconfirmed_blobs():
    img, mask, plain, lower = _detector_pair(max_side=128)  # 256 x 256 seen at 128
    a, b = plain.detect(img), lower.detect(img)
    assert [d.to_dict() for d in a.detections] == [d.to_dict() for d in b.detections]  # markers never change
    assert len(b.detections) == 1 and b.detections[0].type == "square"
    truth = mask > 0
    pa, pb = a.probability_at(256, 256) >= 0.5, b.probability_at(256, 256) >= 0.5
    assert (pb & truth).sum() > (pa & truth).sum() + 0.1 * truth.sum()  # the marker's inside filled
    assert pa[35:55, 185:205].all() and not pb[35:55, 185:205].any()  # the sure blob without a marker
    assert not pa[205:235, 185:215].any() and not pb[205:235, 185:215].any()  # the lower pass's own blob


def test_images_not_seen_downscaled_are_not_touched_by_the_lower_scale():
    img, _, plain, lower = _detector_pair(max_side=512)
    a, b = plain.detect(img), lower.detect(img)
    np.testing.assert_array_equal(a.probability, b.probability)
    assert [d.to_dict() for d in a.detections] == [d.to_dict() for d in b.detections]
    assert lower.probability(img, lower=True).lower is None


def test_the_lower_scale_is_on_by_default_and_checked():
    blank = TwoScaleBackend(np.zeros((4, 4)), np.zeros((4, 4)), 4)
    assert HMADetector.with_backend(blank).settings.large_lower_scale == 0.25
    for bad in (0.0, 1.0, -0.25):
        with pytest.raises(ValueError, match="large_lower_scale"):
            HMADetector.with_backend(blank, large_lower_scale=bad)
    with pytest.raises(ValueError, match="lower_scale"):
        probability_map(np.zeros((32, 32), np.uint8), blank, (0.5, 1.0), lower_scale=0.5)


def test_a_lower_scale_the_scales_reach_already_runs_no_pass():
    img = np.full((256, 256), 128, np.uint8)
    blank = TwoScaleBackend(np.zeros((4, 4)), np.zeros((4, 4)), 4)
    # seen downscaled (256 over max_side 128); scales down to 0.25 already: no lower pass, no error
    det = HMADetector.with_backend(blank, scales=(0.25, 1.0), max_side=128, small_scales=None)
    assert det.probability(img, lower=True).lower is None
    det = HMADetector.with_backend(blank, scales=(0.5, 1.0), max_side=128, small_scales=None)
    assert det.probability(img, lower=True).lower is not None
    assert det.probability(img).lower is None  # asked for only by detect
