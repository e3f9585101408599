"""The ``hma`` instance model (learned/instances.py): the logistic model, its file, its fit, and how
the detector uses it to keep or drop blobs."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest

from cpdetect.errors import InputError
from learned.adapter import HMADetector
from learned.instances import (INSTANCE_FEATURES, INSTANCE_FILE, SYMMETRY_FEATURES, InstanceModel, blob_features,
                               fit_instance_model, load_instance_model)
from test_learned_detector import OracleBackend, SoftBackend, blurred_noisy_marker, rendered


def _model(bias: float, threshold: float = 0.5, **weights: float) -> InstanceModel:
    n = len(INSTANCE_FEATURES)
    w = [weights.get(k, 0.0) for k in INSTANCE_FEATURES]
    return InstanceModel(mean=(0.0,) * n, std=(1.0,) * n, weights=tuple(w), bias=bias, threshold=threshold)


def _feats(**over) -> dict:
    f = blob_features(20.0, 0.95, 1.0, 0.9, 0.98, False, "verified", 0.05, 0.1, 0.8)
    f.update(over)
    return f


def test_blob_features_are_the_documented_ones():
    f = blob_features(20.0, 0.9, 0.99, 0.7, 1.5, True, "seed", 0.001, 5.0, 0.0)
    assert tuple(f) == INSTANCE_FEATURES + SYMMETRY_FEATURES
    assert (f["sym180"], f["sym90"], f["blob_sym"]) == (0.0, 0.0, 0.0)  # not measured: no evidence
    assert f["log_radius"] == pytest.approx(math.log(20.0))
    assert f["solidity"] == 1.3 and f["offset"] == 2.0  # capped
    assert f["log_sigma"] == pytest.approx(math.log(0.01))  # floored
    assert (f["verified"], f["centroid"], f["seed"], f["at_border"]) == (0.0, 0.0, 1.0, 1.0)
    with pytest.raises(ValueError, match="kind"):
        blob_features(20.0, 0.9, 0.99, 0.7, 1.0, False, "guess", 0.1, 0.1, 0.0)


def test_probability_is_the_logistic_of_the_standardised_features():
    n = len(INSTANCE_FEATURES)
    rng = np.random.default_rng(1)
    mean, std, w = rng.normal(size=n), rng.uniform(0.5, 2.0, n), rng.normal(size=n)
    m = InstanceModel(tuple(mean), tuple(std), tuple(w), bias=-0.3, threshold=0.4)
    f = _feats()
    x = np.array([f[k] for k in INSTANCE_FEATURES])
    z = ((x - mean) / std) @ w - 0.3
    assert m.probability(f) == pytest.approx(1.0 / (1.0 + math.exp(-z)), rel=1e-12)
    # the extremes stay finite
    assert 0.0 <= _model(1e6).probability(f) <= 1.0 and 0.0 <= _model(-1e6).probability(f) <= 1.0


def test_model_file_round_trip_and_bad_files(tmp_path):
    m = _model(0.7, threshold=0.35, mean_p=2.0, verified=1.5)
    path = m.save(tmp_path)
    assert path.name == INSTANCE_FILE
    back = load_instance_model(tmp_path)
    assert back == m
    assert load_instance_model(tmp_path / "nowhere") is None and load_instance_model(None) is None
    (tmp_path / INSTANCE_FILE).write_text("{not json")
    with pytest.raises(InputError, match=INSTANCE_FILE):
        load_instance_model(tmp_path)
    bad = m.to_dict()
    bad["weights"] = bad["weights"][:-1]
    (tmp_path / INSTANCE_FILE).write_text(json.dumps(bad))
    with pytest.raises(InputError, match="weights"):
        load_instance_model(tmp_path)
    bad = dict(m.to_dict(), format="something-else")
    (tmp_path / INSTANCE_FILE).write_text(json.dumps(bad))
    with pytest.raises(InputError, match="format"):
        load_instance_model(tmp_path)
    with pytest.raises(ValueError, match="threshold"):
        _model(0.0, threshold=1.0)


def test_fit_separates_what_the_features_separate():
    rng = np.random.default_rng(4)
    rows, labels = [], []
    for i in range(400):
        marker = i % 2 == 0
        kind = "verified" if marker and rng.random() < 0.8 else ("seed" if not marker else "centroid")
        mean_p = float(np.clip(rng.normal(0.93 if marker else 0.75, 0.05), 0, 1))
        rows.append(blob_features(rng.uniform(8, 60), mean_p, min(1.0, mean_p + 0.05), mean_p - 0.1,
                                  rng.uniform(0.85, 1.0), False, kind, rng.uniform(0.02, 0.5), rng.uniform(0, 0.5),
                                  float(rng.uniform(0.3, 1.0)) if kind == "verified" else 0.0))
        labels.append(int(marker))
    m = fit_instance_model(rows, labels, n_markers=220)
    w = dict(zip(m.features, m.weights))
    assert w["mean_p"] > 0 and w["verified"] > 0 and w["seed"] < 0
    p = np.array([m.probability(r) for r in rows])
    y = np.array(labels)
    keep = p >= m.threshold
    tp, fp = int(np.sum(keep & (y == 1))), int(np.sum(keep & (y == 0)))
    assert tp >= 190 and fp <= 10
    # the stored F1 is the marker-level one, with the 20 markers no blob reached counted as misses
    assert m.fitted["f1_at_threshold"] == pytest.approx(2 * tp / (2 * tp + fp + 220 - tp), abs=1e-4)
    # the threshold: the highest on the grid whose F1 is within the tolerance of the best
    def f1_at(t):
        k = p >= t
        tp_t, fp_t = int(np.sum(k & (y == 1))), int(np.sum(k & (y == 0)))
        return 2 * tp_t / (2 * tp_t + fp_t + 220 - tp_t)

    grid = [round(t, 2) for t in np.arange(0.2, 0.81, 0.02)]
    top = max(f1_at(t) for t in grid)
    assert m.threshold == max(t for t in grid if f1_at(t) >= top - 0.001)
    strict = fit_instance_model(rows, labels, n_markers=220, f1_tolerance=0.0)
    assert f1_at(strict.threshold) == pytest.approx(top) and strict.threshold <= m.threshold
    with pytest.raises(ValueError, match="both kinds"):
        fit_instance_model(rows[:50], [1] * 50, 50)


def _own_map(mask, **settings) -> HMADetector:
    """The detector over the oracle network, returning the image's own map: the oracle gives its mask
    whatever the input, so the default mean with the mirror image's map (``mirror_map``) would mix
    the mask with its mirror image; tests/test_mirror_map.py tests that mean."""
    return HMADetector.with_backend(OracleBackend(mask), mirror_map="never", **settings)


def test_the_detector_keeps_or_drops_by_the_model_and_scores_with_it():
    img, mask, _ = rendered("circle", center=(121.3, 133.6), radius=26.0, angle=0.5)
    rules = _own_map(mask).detect(img).detections
    assert len(rules) == 1 and rules[0].score > 0.99  # the rules' score: mean P
    keep = _model(0.0, verified=2.0)  # P = 1 / (1 + exp(-2)) for a verified centre
    kept = _own_map(mask, instances=keep).detect(img).detections
    assert len(kept) == 1 and kept[0].score == pytest.approx(1.0 / (1.0 + math.exp(-2.0)))
    assert (kept[0].x, kept[0].y, kept[0].type) == (rules[0].x, rules[0].y, rules[0].type)
    drop = _model(-1.0, verified=0.5)  # P = 0.38 < 0.5
    res = _own_map(mask, instances=drop).detect(img)
    assert res.detections == []
    assert res.probability[mask > 0].mean() > 0.95  # the network is sure: its map stays
    # a cut of the caller's beats the stored one; the setting "none" ignores the model
    assert len(_own_map(mask, instances=drop, instance_threshold=0.3).detect(img).detections) == 1
    assert len(_own_map(mask, instances=drop, instance_model="none").detect(img).detections) == 1


def test_with_a_model_an_unverified_seed_is_judged_instead_of_dropped():
    # heavy blur and noise: the X-corner refines, but more loosely than the rules accept
    noisy, mask = blurred_noisy_marker()
    # (the verified centre of the loose run is not fitted again on its outline: the same fit as the seed's)
    loose = HMADetector.with_backend(OracleBackend(mask), max_sigma_px=100.0,
                                     outline_window=0.0).detect(noisy).detections
    sigma = loose[0].sigma_px
    strict = dict(max_sigma_px=0.5 * sigma, max_sigma_verified_px=0.5 * sigma)
    assert HMADetector.with_backend(OracleBackend(mask), **strict).detect(noisy).detections == []
    det = HMADetector.with_backend(OracleBackend(mask), instances=_model(3.0, seed=-1.0), **strict)
    blobs, _ = det.candidates(noisy, det.probability(noisy).prob, 1.0)
    assert len(blobs) == 1 and blobs[0].centre.kind == "seed"
    assert blobs[0].features["seed"] == 1.0 and blobs[0].features["model_score"] == 0.0
    found = det.detect(noisy).detections
    assert len(found) == 1 and found[0].score == pytest.approx(1.0 / (1.0 + math.exp(-2.0)))
    assert math.hypot(found[0].x - loose[0].x, found[0].y - loose[0].y) < 1e-9
    # beyond max_sigma_seed_px even the model gets nothing to judge
    det = HMADetector.with_backend(OracleBackend(mask), instances=_model(3.0), max_sigma_seed_px=0.5 * sigma,
                                   **strict)
    assert det.detect(noisy).detections == []


def _two_markers():
    """(image, mask of the first marker only, the two true centres): a square and a circle."""
    a, mask, _ = rendered("square", center=(70.4, 80.7), radius=22.0, angle=0.4, shape=(200, 320))
    b, _, _ = rendered("circle", center=(240.2, 110.3), radius=24.0, angle=1.1, shape=(200, 320))
    img = a.copy()
    img[:, 170:] = b[:, 170:]
    return img, mask, ((70.4, 80.7), (240.2, 110.3))


def test_classical_seeds_keep_a_confirmed_blob_and_add_no_blob_of_their_own():
    img, mask, (first, second) = _two_markers()
    drop = _model(-5.0)  # the instance model drops every blob
    assert HMADetector.with_backend(OracleBackend(mask), instances=drop).detect(img).detections == []
    det = HMADetector.with_backend(OracleBackend(mask), instances=drop, classical_seeds=True)
    found = det.detect(img).detections
    seeds = det._classical(img, False).detections
    assert sorted(round(d.x) for d in seeds) == [round(first[0]), round(second[0])]
    # the classical detector finds both markers; only the one on the network's blob is kept
    assert len(found) == 1
    assert math.hypot(found[0].x - first[0], found[0].y - first[1]) < 0.1
    assert found[0].type == "square"
    blobs, _ = det.candidates(img, det.probability(img).prob, 1.0, seeds=seeds)
    assert [b.centre.classical for b in blobs] == [True]
    # without seeds the same call marks nothing as confirmed
    blobs, _ = det.candidates(img, det.probability(img).prob, 1.0)
    assert [b.centre.classical for b in blobs] == [False]


def _first_and_faint_second():
    """The two markers, and a P(marker) map: 1 on the first marker, 0.2 on the second (below the
    blob threshold: the network has a hint of it but no instance)."""
    img, mask, centres = _two_markers()
    _, mask_b, _ = rendered("circle", center=centres[1], radius=24.0, angle=1.1, shape=(200, 320))
    soft = np.where(mask > 0, 1.0, np.where(mask_b > 0, 0.2, 0.0)).astype(np.float32)
    soft[:, :170] = np.where(mask[:, :170] > 0, 1.0, 0.0)
    return img, mask, soft, centres


def test_classical_markers_add_what_the_network_missed():
    # the network's map shows the first marker only, and a hint of the second: with
    # classical_markers the classical detector's second marker is added, with its outline in the
    # map; the first stays exactly as it was
    img, _, soft, (first, second) = _first_and_faint_second()
    keep = _model(5.0)
    alone = HMADetector.with_backend(SoftBackend(soft), instances=keep).detect(img)
    both = HMADetector.with_backend(SoftBackend(soft), instances=keep, classical_markers=True).detect(img)
    assert len(alone.detections) == 1 and len(both.detections) == 2
    assert alone.detections[0] in both.detections
    added = [d for d in both.detections if d not in alone.detections][0]
    assert math.hypot(added.x - second[0], added.y - second[1]) < 0.1 and added.type == "circle"
    cx, cy = round(second[0]), round(second[1])
    assert alone.probability[cy, cx] < 0.3 and both.probability[cy, cx] > 0.9
    assert np.array_equal(alone.probability[:, :170], both.probability[:, :170])
    # a marker the network found already (within half the smaller radius) is not added twice
    from cpdetect.types import DetectionResult, MarkerDetection
    from learned.adapter import _with_classical_markers

    mine = [MarkerDetection(100.0, 50.0, 0.9, "square", 20.0, 0.05)]
    theirs = DetectionResult([MarkerDetection(108.0, 50.0, 0.8, "square", 20.0, 0.05),
                              MarkerDetection(111.0, 50.0, 0.8, "square", 20.0, 0.05)], (200, 100), None)
    got, prob = _with_classical_markers(mine, np.zeros((100, 200), np.float32), 1.0, theirs)
    assert [d.x for d in got] == [100.0, 111.0] and not prob.any()


def test_a_classical_marker_the_network_sees_nothing_of_is_not_added():
    # no trace of the second marker in the network's map (P about 3e-4 there): the network vetoes it,
    # unless classical_min_support is 0
    img, mask, (first, second) = _two_markers()
    keep = _model(5.0)
    vetoed = HMADetector.with_backend(OracleBackend(mask), instances=keep, classical_markers=True).detect(img)
    assert len(vetoed.detections) == 1
    assert math.hypot(vetoed.detections[0].x - first[0], vetoed.detections[0].y - first[1]) < 0.1
    cx, cy = round(second[0]), round(second[1])
    assert vetoed.probability[cy, cx] < 0.01
    union = HMADetector.with_backend(OracleBackend(mask), instances=keep, classical_markers=True,
                                     classical_min_support=0.0).detect(img)
    assert len(union.detections) == 2 and union.probability[cy, cx] > 0.9


def test_with_classical_markers_a_blob_no_marker_comes_from_stays_only_where_one_is_seen():
    # a blob the network is sure of over plain background (no X-corner: no marker) stays in the map
    # by default (clear_rejected_below); with classical_markers it is cleared, as no classical marker
    # lies on it, while a rejected blob the classical detector does see a marker on stays
    img, mask, (first, second) = _two_markers()
    img[140:200, 10:70] = 116  # flat: no corner to refine a centre on
    sure = mask.astype(np.float32).copy()
    sure[150:190, 20:60] = 1.0
    keep, drop = _model(5.0), _model(-5.0)
    alone = _own_map(sure, instances=keep).detect(img)
    assert len(alone.detections) == 1 and alone.probability[170, 40] > 0.9
    union = _own_map(sure, instances=keep, classical_markers=True).detect(img)
    assert len(union.detections) == 1 and union.probability[170, 40] < 0.01
    cx, cy = round(first[0]), round(first[1])
    assert union.probability[cy, cx] > 0.9
    # the instance model drops the marker's blob too: the classical marker on it keeps it in the map
    dropped = _own_map(sure, instances=drop, classical_markers=True).detect(img)
    assert dropped.probability[170, 40] < 0.01 and dropped.probability[cy, cx] > 0.9
    assert [round(d.x) for d in dropped.detections] == [round(first[0])]


def test_network_support_is_the_mean_over_the_classical_outline():
    from cpdetect.types import MarkerDetection
    from learned.adapter import _network_support

    theirs = np.zeros((100, 200), np.float32)
    theirs[30:70, 80:120] = 1.0  # the classical outline: a 40 x 40 square around (99.5, 49.5)
    network = np.zeros_like(theirs)
    network[30:50, 80:120] = 0.5  # the network sees the upper half at P 0.5
    network[0:10, :] = 1.0  # elsewhere, outside the outline: does not count
    c = MarkerDetection(99.5, 49.5, 0.9, "square", 20.0, 0.05)
    assert _network_support(network, theirs, 1.0, c) == pytest.approx(0.25, abs=1e-6)
    # the maps at half the image's resolution: the same marker, twice as large in image pixels
    big = MarkerDetection(199.5, 99.5, 0.9, "square", 40.0, 0.05)
    assert _network_support(network, theirs, 0.5, big) == pytest.approx(0.25, abs=1e-6)
    # no classical map: a disc of half the radius (10 px) around the centre, whose top two rows
    # (about 10 of its 317 pixels) lie above the part the network sees
    c2 = MarkerDetection(99.5, 38.5, 0.9, "square", 20.0, 0.05)
    assert 0.47 <= _network_support(network, None, 1.0, c2) < 0.5


def test_a_classical_marker_off_the_centre_does_not_confirm_it():
    from cpdetect.types import MarkerDetection
    from learned.adapter import _Centre, _with_classical

    c = _Centre(100.0, 50.0, 0.05, "seed")
    near = MarkerDetection(100.9, 50.0, 0.9, "circle", 20.0, 0.05)
    far = MarkerDetection(103.0, 50.0, 0.9, "square", 20.0, 0.05)
    assert _with_classical(c, [far, near], 20.0).classical
    assert not _with_classical(c, [far], 20.0).classical  # 3 px > max(1.5, 2.0)
    assert _with_classical(c, [far], 40.0).classical  # within a tenth of 40 px


def test_verified_centres_are_fitted_again_on_their_outline():
    import cv2
    from test_refine import render

    rng = np.random.default_rng(4)
    err = {0.0: [], 1.0: []}
    for _ in range(8):
        c0 = (100.0 + rng.uniform(-0.5, 0.5), 100.0 + rng.uniform(-0.5, 0.5))
        img, c, r, poly = render(c0, 24.0, angle=rng.uniform(0, np.pi), tilt_deg=50.0, tilt_axis=rng.uniform(0, np.pi),
                                 noise=6.0, blur=1.0, rng=rng, shape=(200, 200), outline=True)
        mask = np.zeros(img.shape, np.uint8)
        cv2.fillPoly(mask, [np.round(poly).astype(np.int32)], 1)
        found = {}
        for frac in err:
            det = HMADetector.with_backend(OracleBackend(mask), instance_model="none", outline_window=frac)
            d = det.detect(img.astype(np.uint8)).detections
            assert len(d) == 1
            found[frac] = d[0]
            err[frac].append(math.hypot(d[0].x - c[0], d[0].y - c[1]))
        assert found[1.0].sigma_px <= found[0.0].sigma_px  # the second fit is kept only when it is surer
    assert 0.005 < np.mean(err[1.0]) < 0.85 * np.mean(err[0.0]) and np.mean(err[0.0]) < 0.15
