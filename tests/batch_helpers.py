"""Small inputs shared by the batch-detection tests (test_dask, test_interrupt, test_bad_input)."""
import json

import cv2
import numpy as np


def write_marker_images(folder, n, seed=0, size=(96, 72)):
    """``n`` small gray JPEGs ``0000.jpg`` ..., each with one 2x2 checker marker (half-side 12 px) at a
    place that varies with the index, on a mid-gray background with a little noise."""
    rng = np.random.default_rng(seed)
    folder.mkdir(parents=True, exist_ok=True)
    w, h = size
    for i in range(n):
        a = np.full((h, w), 128, np.uint8) + rng.integers(0, 6, (h, w), dtype=np.uint8)
        x, y, r = 26 + (7 * i) % 40, 24 + (5 * i) % 22, 12
        a[y - r:y, x - r:x] = 20
        a[y:y + r, x:x + r] = 20
        a[y - r:y, x:x + r] = 235
        a[y:y + r, x - r:x] = 235
        cv2.imwrite(str(folder / f"{i:04d}.jpg"), a)
    return folder


def without_timing(doc):
    """A copy of a cpdetect.detections/1 document without the per-image ``seconds``."""
    doc = json.loads(json.dumps(doc))
    for im in doc["images"]:
        im.pop("seconds", None)
    return doc
