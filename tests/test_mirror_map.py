"""The returned map of ``hma`` as the mean of the image's and its mirror image's (learned.mirror_map)."""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from learned.adapter import HMADetector
from learned.mirror_map import keep_blobs_of, mirrored_mean
from test_learned_detector import OracleBackend, rendered


class ContrastBackend:
    """A network whose logits grow with the local contrast (standard deviation over a symmetric box,
    mirrored borders), so mirroring the image mirrors its map."""

    name = "contrast"

    def trunk(self, x: np.ndarray):
        x = x.astype(np.float32)
        mean, mean_sq = cv2.blur(x, (9, 9)), cv2.blur(x * x, (9, 9))
        logit = 40.0 * (np.sqrt(np.maximum(mean_sq - mean * mean, 0.0)) - 0.12)
        return np.stack([np.zeros_like(logit), logit]), np.full(x.shape, 0.5, np.float32)


def test_a_map_that_mirrors_with_the_image_is_its_own_mean():
    gray = np.random.default_rng(3).integers(0, 256, (37, 53)).astype(np.uint8)
    pointwise = lambda g: (g.astype(np.float32) / 255.0) ** 2  # noqa: E731
    prob = pointwise(gray)
    assert np.array_equal(mirrored_mean(gray, prob, pointwise), prob)


def test_a_map_that_ignores_the_image_is_averaged_with_its_mirror():
    gray = np.zeros((20, 30), np.uint8)
    fixed = np.random.default_rng(4).random((20, 30)).astype(np.float32)
    mean = mirrored_mean(gray, fixed, lambda g: fixed)
    assert mean.dtype == np.float32 and mean.flags.c_contiguous
    assert np.allclose(mean, 0.5 * (fixed + fixed[:, ::-1]), atol=1e-7)
    assert not np.allclose(mean, fixed)
    with pytest.raises(ValueError, match="mirror image's map"):
        mirrored_mean(gray, fixed, lambda g: fixed[:, 1:])


def test_the_image_map_decides_which_blobs_of_the_mean_stay():
    mean = np.zeros((60, 80), np.float32)
    mean[5:15, 5:15] = 0.7    # kept in the image's map, larger in the mean: stays whole
    mean[5:15, 40:50] = 0.95  # cleared in the image's map, sure in the mean: cleared
    mean[40:50, 5:15] = 0.6   # under the threshold in the image's map, a blob in the mean: cleared
    mean[40:50, 40:50] = 0.3  # under the threshold: no blob, left as it is
    kept = np.zeros_like(mean)
    kept[7:13, 7:13] = 0.8
    kept[40:50, 5:15] = 0.4
    kept[45, 45] = 0.9        # under the mean's threshold there: keeps nothing
    out = keep_blobs_of(mean, kept, 0.5)
    assert out.dtype == np.float32
    assert np.array_equal(out[5:15, 5:15], mean[5:15, 5:15])
    assert not out[5:15, 40:50].any() and not out[40:50, 5:15].any()
    assert np.array_equal(out[40:50, 40:50], mean[40:50, 40:50])
    # one shared pixel is enough; the threshold applies to both maps
    kept2 = np.zeros_like(mean)
    kept2[14, 49] = 0.5
    assert np.array_equal(keep_blobs_of(mean, kept2, 0.5)[5:15, 40:50], mean[5:15, 40:50])
    assert not keep_blobs_of(mean, kept2, 0.51)[5:15, 40:50].any()
    # nothing over the threshold: the map itself
    low = np.full((10, 10), 0.2, np.float32)
    assert keep_blobs_of(low, low, 0.5) is low
    with pytest.raises(ValueError, match="kept map"):
        keep_blobs_of(mean, kept[1:], 0.5)


def test_the_markers_come_from_the_image_map_and_only_the_returned_map_changes():
    # the marker's mirror image overlaps it (centred on the mirror axis): one blob, holding the marker
    img, mask, _ = rendered("square", center=(127.5, 128.0), radius=24.0, angle=0.4)
    never = HMADetector.with_backend(OracleBackend(mask), mirror_map="never").detect(img)
    small = HMADetector.with_backend(OracleBackend(mask), mirror_map="small").detect(img)
    default = HMADetector.with_backend(OracleBackend(mask)).detect(img)
    assert never.extras["mirrored_map"] is False and small.extras["mirrored_map"] is True
    # a 256 x 256 image is seen at small_scales: the default averages its map
    assert default.extras["mirrored_map"] is True and np.array_equal(default.probability, small.probability)
    assert len(never.detections) == 1 and small.detections == never.detections
    # this backend does not mirror with its input: its mirror image's map is the mask mirrored
    expected = 0.5 * (never.probability + never.probability[:, ::-1])
    assert np.allclose(small.probability, expected, atol=1e-5)


def test_a_mirror_symmetric_network_gives_the_same_map_either_way():
    img, _, _ = rendered("circle", center=(120.0, 131.0), radius=30.0, angle=0.2)
    never = HMADetector.with_backend(ContrastBackend(), mirror_map="never", scales=(1.0,)).detect(img)
    always = HMADetector.with_backend(ContrastBackend(), mirror_map="always", scales=(1.0,)).detect(img)
    assert len(never.detections) == 1 and (never.probability >= 0.5).any()
    assert always.extras["mirrored_map"] is True
    assert always.detections == never.detections
    assert np.abs(always.probability - never.probability).max() < 1e-4


def test_small_mirrors_only_images_seen_at_the_small_scales():
    assert not HMADetector.with_backend(OracleBackend(np.zeros((8, 8))), mirror_map="never").mirrors(640, 480)
    det = HMADetector.with_backend(OracleBackend(np.zeros((8, 8))))  # "small", the default
    assert det.settings.mirror_map == "small"
    assert det.mirrors(640, 480) and det.mirrors(1024, 1024)
    assert not det.mirrors(8192, 5460) and not det.mirrors(1025, 700)
    assert HMADetector.with_backend(OracleBackend(np.zeros((8, 8))), mirror_map="always").mirrors(8192, 5460)
    assert not HMADetector.with_backend(OracleBackend(np.zeros((8, 8))), mirror_map="small",
                                        small_scales=None).mirrors(640, 480)
    with pytest.raises(ValueError, match="mirror_map must be"):
        HMADetector.with_backend(OracleBackend(np.zeros((8, 8))), mirror_map="yes")
