"""learned.blob_tone: the grey spread inside a blob, on images with known tones."""
from __future__ import annotations

import numpy as np
import pytest

from learned.blob_tone import interior_spread

F = 0.25  # map pixels per image pixel, as for a 45 MP image seen at 2048 px


def _disc_blob(radius_px: float, size: int = 1200):
    """(bool mask over the map grid, its bbox, the image grid's centre and pixel coordinates)."""
    n = int(size * F)
    yy, xx = np.mgrid[0:n, 0:n]
    c = (n - 1) / 2.0
    inside = (xx - c) ** 2 + (yy - c) ** 2 <= (radius_px * F) ** 2
    iy, ix = np.mgrid[0:size, 0:size].astype(np.float32)
    return inside, (0, 0, n, n), (size - 1) / 2.0, ix, iy


def test_a_plain_panel_is_flat_under_sensor_noise():
    inside, bbox, c, _, _ = _disc_blob(400.0)
    rng = np.random.default_rng(0)
    panel = np.clip(40.0 + rng.normal(0.0, 4.0, (1200, 1200)), 0, 255).astype(np.uint8)
    spread = interior_spread(panel, inside, bbox, F, 400.0)
    assert spread is not None and 0.0 <= spread < 1.0


@pytest.mark.parametrize("contrast", [4.0, 30.0, 150.0])
def test_a_checker_shows_its_contrast(contrast):
    # the two tones of a 2 x 2 checker inside the blob, each over half of it: the spread is the contrast
    inside, bbox, c, ix, iy = _disc_blob(400.0)
    rng = np.random.default_rng(1)
    dark = np.where((ix - c) * (iy - c) > 0, 0.0, contrast)
    img = np.clip(60.0 + dark + rng.normal(0.0, 4.0, dark.shape), 0, 255).astype(np.uint8)
    spread = interior_spread(img, inside, bbox, F, 400.0)
    assert 0.85 * contrast - 0.5 <= spread <= 1.02 * contrast + 0.5


def test_the_surround_does_not_count():
    # a flat blob on a much brighter ground: its outline is eroded away before the spread is taken
    inside, bbox, c, ix, iy = _disc_blob(300.0)
    img = np.where((ix - c) ** 2 + (iy - c) ** 2 <= 300.0 ** 2, 20, 220).astype(np.uint8)
    assert interior_spread(img, inside, bbox, F, 300.0) < 0.5


def test_a_blob_too_small_to_erode_says_nothing():
    inside, bbox, _, _, _ = _disc_blob(12.0, size=200)
    assert interior_spread(np.zeros((200, 200), np.uint8), inside, bbox, F, 12.0) is None


def test_a_marker_showing_one_sector_is_one_tone():
    # the known cost of the rule: where an occluder leaves one dark sector of a marker in view, the blob
    # over that sector shows one tone, like a plain panel (three such blobs on 36 seen 45 MP sets)
    inside, bbox, c, ix, iy = _disc_blob(400.0)
    inside &= np.mgrid[0:inside.shape[0], 0:inside.shape[1]][1] < (c * F)  # the blob over one quadrant only
    inside &= np.mgrid[0:inside.shape[0], 0:inside.shape[1]][0] < (c * F)
    img = np.where((ix - c) * (iy - c) > 0, 40, 200).astype(np.uint8)
    assert interior_spread(img, inside, bbox, F, 200.0) < 1.0
