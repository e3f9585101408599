"""bench/hma_miss_stages.py: the stage it names for a missed marker is the detector's own decision."""
from __future__ import annotations

import math

from bench_loader import load_bench
from learned.adapter import HMADetector
from test_hma_instances import _model, _two_markers
from test_learned_detector import OracleBackend

stages = load_bench("hma_miss_stages")


def _stages(det, img):
    pm = det.probability(img)
    blobs, labels = det.candidates(img, pm.prob, pm.factor)
    return lambda x, y, r: stages.stage_of(det, img, blobs, labels, pm.factor, {"x": x, "y": y, "radius_px": r})


def test_a_found_marker_is_kept_and_one_without_a_blob_has_no_blob():
    img, mask, (first, second) = _two_markers()  # the network's map shows the first marker only
    det = HMADetector.with_backend(OracleBackend(mask), instances=_model(3.0), mirror_map="never")
    found = det.detect(img).detections
    assert len(found) == 1 and math.hypot(found[0].x - first[0], found[0].y - first[1]) < 0.1
    stage = _stages(det, img)
    kept = stage(*first, 22.0)
    assert kept["stage"] == "kept" and kept["centre_offset_px"] < 0.1 and kept["blob_mean_p"] > 0.9
    assert stage(*second, 24.0)["stage"] == "no blob"


def test_the_instance_models_drop_is_named():
    img, mask, (first, _) = _two_markers()
    det = HMADetector.with_backend(OracleBackend(mask), instances=_model(-5.0), mirror_map="never")
    assert det.detect(img).detections == []
    got = _stages(det, img)(*first, 22.0)
    assert got["stage"] == "instance model" and got["instance_p"] < 0.01


def test_a_blob_whose_centre_is_elsewhere_is_named():
    img, mask, (first, _) = _two_markers()
    det = HMADetector.with_backend(OracleBackend(mask), instances=_model(3.0), mirror_map="never")
    # a true marker said to lie 6 px from the centre the blob yields, still on the blob
    got = _stages(det, img)(first[0] + 6.0, first[1], 22.0)
    assert got["stage"] == "centre on another corner" and 5.9 < got["centre_offset_px"] < 6.1


def test_an_unsure_blob_with_nothing_point_symmetric_is_named():
    import numpy as np
    from test_centre_choice import _edge_image, _keep_all, _ranker
    from test_learned_detector import SoftBackend, rendered

    _, mask, _ = rendered("square", center=(121.3, 133.6), radius=26.0, angle=0.5)
    img = _edge_image(mask.shape)  # under a blob the network is unsure of (mean P 0.75)
    ranker = _ranker(sym180=3.0, sym90=-3.0, blob_sym=3.0)
    det = HMADetector.with_backend(SoftBackend(mask.astype(np.float32) * 0.75), _keep_all(), ranker,
                                   scales=(1.0,), mirror_map="never")
    got = _stages(det, img)(121.3, 133.6, 26.0)
    assert got["stage"] == "no point-symmetric seed" and 0.7 < got["blob_mean_p"] < 0.8
    low = HMADetector.with_backend(SoftBackend(mask.astype(np.float32) * 0.55), _keep_all(), ranker,
                                   scales=(1.0,), mirror_map="never")
    assert _stages(low, img)(121.3, 133.6, 26.0)["stage"] == "blob mean P low"
