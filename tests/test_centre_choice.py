"""The hma centre ranker: symmetry features on analytic images, its file, and that it decides."""
from __future__ import annotations

import json
import math

import cv2
import numpy as np
import pytest

from cpdetect.errors import InputError
from learned.adapter import HMADetector
from learned.centre_choice import (CANDIDATE_FEATURES, CentreRanker, blob_symmetry, load_centre_ranker,
                                   point_symmetry)
from learned.instances import INSTANCE_FEATURES, SYMMETRY_FEATURES, InstanceModel, blob_features, load_instance_model
from test_learned_detector import SoftBackend, rendered


def test_a_checker_centre_is_point_symmetric_and_turns_to_its_negative():
    img, _, _ = rendered("square", center=(128.3, 127.6), radius=24.0, angle=0.4)
    s180, s90 = point_symmetry(img, 128.3, 127.6, 24.0)
    assert s180 > 0.9 and s90 < -0.8
    # half a radius off the centre, on a dark/bright boundary: neither
    off180, off90 = point_symmetry(img, 128.3 + 12.0 * math.cos(0.4), 127.6 + 12.0 * math.sin(0.4), 24.0)
    assert off180 < 0.5 and off90 > -0.5
    assert point_symmetry(np.full((50, 50), 90, np.uint8), 25.0, 25.0, 10.0) == (0.0, 0.0)  # flat: no evidence


def test_blob_symmetry_of_a_disk_about_its_centre_and_half_a_radius_off():
    disk = np.zeros((101, 101), bool)
    yy, xx = np.mgrid[:101, :101]
    disk[(xx - 50) ** 2 + (yy - 50) ** 2 <= 30 ** 2] = True
    assert blob_symmetry(disk, 50.0, 50.0) > 0.99
    # reflected through a point r/2 off the centre the disk moves by r: lens of two unit disks one
    # radius apart over a disk, (2 / pi) (acos(1/2) - sqrt(3) / 4) = 0.391
    assert 0.37 < blob_symmetry(disk, 65.0, 50.0) < 0.41
    assert blob_symmetry(np.zeros((5, 5), bool), 2.0, 2.0) == 0.0


def test_the_ranker_file_round_trips_and_refuses_an_instance_model(tmp_path):
    n = len(CANDIDATE_FEATURES)
    ranker = CentreRanker(mean=(0.1,) * n, std=(2.0,) * n, weights=tuple(np.linspace(-1, 1, n)), bias=0.3,
                          features=CANDIDATE_FEATURES)
    ranker.save(tmp_path)
    back = load_centre_ranker(tmp_path)
    feats = dict(zip(CANDIDATE_FEATURES, np.linspace(0.0, 2.0, n)))
    assert isinstance(back, CentreRanker) and back.probability(feats) == pytest.approx(ranker.probability(feats))
    assert load_instance_model(tmp_path) is None  # a ranker is not an instance model
    k = len(INSTANCE_FEATURES)
    instance = InstanceModel(mean=(0.0,) * k, std=(1.0,) * k, weights=(0.0,) * k, bias=0.0)
    (tmp_path / "centre_rank.json").write_text(json.dumps(instance.to_dict()), encoding="utf-8")
    with pytest.raises(InputError, match="centre_rank.json.*not a valid centre ranker"):
        load_centre_ranker(tmp_path)
    with pytest.raises(ValueError, match="centre ranker: unknown features"):
        CentreRanker(mean=(0.0,), std=(1.0,), weights=(0.0,), bias=0.0, features=("mean_p",))


def test_instance_features_gain_the_symmetry_ones_and_old_models_ignore_them():
    f = blob_features(20.0, 0.9, 1.0, 0.8, 1.0, False, "verified", 0.05, 0.1, 0.9, 0.95, -0.9, 0.97)
    assert set(f) == set(INSTANCE_FEATURES + SYMMETRY_FEATURES) and f["blob_sym"] == 0.97
    k = len(INSTANCE_FEATURES)
    old = InstanceModel(mean=(0.0,) * k, std=(1.0,) * k, weights=(1.0,) * k, bias=0.0)
    assert old.features == INSTANCE_FEATURES
    assert old.probability(f) == pytest.approx(old.probability({**f, "sym180": -1.0, "blob_sym": 0.0}))


def _ranker(**weights) -> CentreRanker:
    n = len(CANDIDATE_FEATURES)
    return CentreRanker(mean=(0.0,) * n, std=(1.0,) * n, weights=tuple(weights.get(k, 0.0) for k in CANDIDATE_FEATURES),
                        bias=0.0, features=CANDIDATE_FEATURES)


def _keep_all() -> InstanceModel:
    """An instance model that keeps every blob (P about 0.99 whatever its features)."""
    n = len(INSTANCE_FEATURES)
    return InstanceModel(mean=(0.0,) * n, std=(1.0,) * n, weights=(0.0,) * n, bias=5.0, threshold=0.5)


def test_the_ranker_chooses_the_blob_centre():
    img, mask, _ = rendered("square", center=(121.3, 133.6), radius=26.0, angle=0.5)
    keep_all = _keep_all()
    soft = mask.astype(np.float32) * 0.97
    chosen = {}
    for name, ranker in (("symmetry", _ranker(sym180=3.0, sym90=-3.0, blob_sym=3.0)), ("far", _ranker(offset=5.0))):
        det = HMADetector.with_backend(SoftBackend(soft), keep_all, ranker, scales=(1.0,), rank_stop=1.0)
        pm = det.probability(img)
        blobs, _ = det.candidates(img, pm.prob, pm.factor)
        (blob,) = blobs
        assert len(blob.options) >= 2  # the centroid's refinement and X-corner seeds on the outline
        best = max(blob.options, key=lambda o: ranker.probability(o[1]))[0]
        assert (blob.centre.x, blob.centre.y) == (best.x, best.y)
        assert all(score == ranker.probability(feats) for _, feats, score in blob.options)
        assert blob.features["sym180"] == best.sym180 and blob.features["blob_sym"] == best.blob_sym
        chosen[name] = blob.centre
    assert math.hypot(chosen["symmetry"].x - 121.3, chosen["symmetry"].y - 133.6) < 0.15
    assert math.hypot(chosen["far"].x - 121.3, chosen["far"].y - 133.6) > 5.0
    # by default the search stops at the first candidate scored >= rank_stop: here the centroid's
    sure = _ranker(sym180=3.0, sym90=-3.0, blob_sym=3.0)
    det = HMADetector.with_backend(SoftBackend(soft), keep_all, sure, scales=(1.0,))
    pm = det.probability(img)
    (blob,), _ = det.candidates(img, pm.prob, pm.factor)
    assert len(blob.options) == 1 and blob.options[0][2] >= 0.9
    assert (blob.centre.x, blob.centre.y) == (chosen["symmetry"].x, chosen["symmetry"].y)
    # "none" (or no instance model) keeps the rules: the first verified centre
    rules = HMADetector.with_backend(SoftBackend(soft), keep_all, _ranker(offset=5.0), scales=(1.0,),
                                     centre_ranker="none").detect(img).detections
    assert len(rules) == 1 and math.hypot(rules[0].x - 121.3, rules[0].y - 133.6) < 0.15
    no_model = HMADetector.with_backend(SoftBackend(soft), None, _ranker(offset=5.0), scales=(1.0,))
    assert no_model.centre_ranker is None


def test_the_search_goes_on_past_a_candidate_the_marker_model_barely_fits(monkeypatch):
    import cpdetect.classical as C

    img, mask, _ = rendered("square", center=(121.3, 133.6), radius=26.0, angle=0.5)
    keep_all = _keep_all()
    soft = mask.astype(np.float32) * 0.97
    sure = _ranker(sym180=3.0, sym90=-3.0, blob_sym=3.0)

    def options(**settings):
        det = HMADetector.with_backend(SoftBackend(soft), keep_all, sure, scales=(1.0,), **settings)
        pm = det.probability(img)
        (blob,), _ = det.candidates(img, pm.prob, pm.factor)
        return blob.options

    # the model fits the centroid's refinement (score near 1): the search stops there either way
    assert len(options(rank_stop_model=0.0)) == 1 and len(options(rank_stop_model=0.5)) == 1
    assert options(rank_stop_model=0.5)[0][0].model_score > 0.9
    # where it barely fits (as at an occluder's corner), only rank_stop_model lets the search go on
    real = C.verify_marker_at

    def weak(*a, **k):
        v = real(*a, **k)
        return None if v is None else (v[0], v[1], 0.05) + tuple(v[3:])

    monkeypatch.setattr(C, "verify_marker_at", weak)
    assert len(options(rank_stop_model=0.0)) == 1
    assert len(options(rank_stop_model=0.5)) >= 2
    assert all(o[0].model_score == 0.05 for o in options(rank_stop_model=0.5) if o[0].kind == "verified")


@pytest.mark.parametrize("sym180, setting, kept", [(0.05, 0.1, False), (0.5, 0.1, True), (0.05, -1.0, True)])
def test_an_unverified_centre_must_be_point_symmetric(monkeypatch, sym180, setting, kept):
    # a blob whose centre the marker model does not fit and about which the image is not
    # point-symmetric is no marker (an occluder's corner beside a covered centre); as if so measured
    import cpdetect.classical as C
    import learned.centre_choice as CC

    img, mask, _ = rendered("square", center=(121.3, 133.6), radius=26.0, angle=0.5)
    keep_all = _keep_all()
    monkeypatch.setattr(C, "verify_marker_at", lambda *a, **k: None)
    monkeypatch.setattr(CC, "point_symmetry", lambda *a, **k: (sym180, -0.5))
    det = HMADetector.with_backend(SoftBackend(mask.astype(np.float32) * 0.97), keep_all,
                                   _ranker(sym180=3.0, sym90=-3.0, blob_sym=3.0), scales=(1.0,),
                                   min_sym180_unverified=setting)
    found = det.detect(img).detections
    assert len(found) == (1 if kept else 0)
    if kept:
        assert math.hypot(found[0].x - 121.3, found[0].y - 133.6) < 0.15


def test_the_most_point_symmetric_seeds_are_refined_first():
    from learned.adapter import _most_symmetric, _seed_symmetry

    cx, cy, r, a = 121.3, 133.6, 26.0, 0.5
    img, _, _ = rendered("square", center=(cx, cy), radius=r, angle=a)
    # the centre as the weakest seed among points of the outline and the sectors, all stronger
    others = [(cx + f * r * math.cos(a + t), cy + f * r * math.sin(a + t), 50.0 - k)
              for k, (f, t) in enumerate([(0.95, 0.0), (0.95, 1.2), (1.0, 0.785), (0.5, 0.3), (0.6, 2.4), (0.9, 3.9)])]
    seeds = others + [(cx + 0.3, cy - 0.2, 5.0)]
    q = [_seed_symmetry(img, x, y, r) for x, y, _ in seeds]
    assert q == [float(np.subtract(*point_symmetry(img, x, y, r))) for x, y, _ in seeds]
    assert q[-1] > 1.6 and max(q[:-1]) < 1.0
    picked = _most_symmetric(seeds, q, 3)
    assert len(picked) == 3 and picked[0] == seeds[-1]
    everything = _most_symmetric(seeds, q, 10)
    assert sorted(everything) == sorted(seeds)  # all of them when n exceeds the pool, none twice


def test_ranker_settings_are_checked():
    from cpdetect import get_detector
    from cpdetect.errors import UsageError

    with pytest.raises(UsageError, match="centre_ranker"):
        get_detector("hma", centre_ranker="best")
    with pytest.raises(UsageError, match="rank_stop"):
        get_detector("hma", rank_stop=0.0)
    with pytest.raises(UsageError, match="min_sym180_unverified"):
        get_detector("hma", min_sym180_unverified=2.0)
    with pytest.raises(UsageError, match="rank_stop_model"):
        get_detector("hma", rank_stop_model=1.5)
    with pytest.raises(UsageError, match="rank_seeds"):
        get_detector("hma", rank_seeds=-1)
    with pytest.raises(UsageError, match="seed_pool"):
        get_detector("hma", seed_pool=-1)


def test_fitting_the_ranker_learns_what_separates_the_candidates():
    from learned.centre_choice import candidate_features, fit_centre_ranker

    rng = np.random.default_rng(3)
    rows, labels = [], []
    for k in range(200):
        right = k % 4 == 0
        s180 = rng.normal(0.9 if right else -0.1, 0.1)
        rows.append(candidate_features(rng.uniform(0.02, 0.5), rng.uniform(0, 1.5), rng.random() < 0.5, rng.random(),
                                       rng.uniform(0, 2), rng.random(), s180, -s180, k % 7 == 0, rng.random()))
        labels.append(int(right))
    m = fit_centre_ranker(rows, labels, fitted={"data": "synthetic"})
    w = dict(zip(m.features, m.weights))
    assert w["sym180"] > 1.0 and w["sym90"] < -1.0 and abs(w["seed_strength"]) < 0.5
    assert m.fitted["candidates"] == 200 and m.fitted["positives"] == 50
    ranked = sorted(range(200), key=lambda i: -m.probability(rows[i]))
    assert sum(labels[i] for i in ranked[:50]) >= 48
    with pytest.raises(ValueError, match="20 candidates"):
        fit_centre_ranker(rows[:10], labels[:10])


def _edge_image(shape: tuple[int, int]) -> np.ndarray:
    """A blurred straight edge on a ramp (an occluder's edge) through about (120, 130): turned 180
    degrees about any point on it, its own negative (sym180 - sym90 about -1; 1.8 at a checker's
    centre)."""
    yy, xx = np.mgrid[:shape[0], :shape[1]]
    edge = np.where(0.8 * (xx - 120) + 0.6 * (yy - 130) > 0, 200.0, 60.0).astype(np.float32)
    return np.clip(cv2.GaussianBlur(edge, (0, 0), 1.5) + 0.2 * xx, 0, 255).astype(np.uint8)


def _blob_search(monkeypatch):
    """A square marker (centre (121.3, 133.6), radius 26), the edge image of its size, and
    ``blob_on(image, p_marker, seeds=None, **settings)``: the one blob of the marker's mask at P =
    ``p_marker`` searched on ``image`` by the centre ranker, with the seeds refined (x, y) in order."""
    import cpdetect.refine as R

    img, mask, _ = rendered("square", center=(121.3, 133.6), radius=26.0, angle=0.5)
    ranker = _ranker(sym180=3.0, sym90=-3.0, blob_sym=3.0)
    calls = []
    real = R.refine_center_coarse_to_fine
    monkeypatch.setattr(R, "refine_center_coarse_to_fine", lambda *a, **k: calls.append(a[1:3]) or real(*a, **k))

    def blob_on(image, p_marker, seeds=None, **settings):
        calls.clear()
        det = HMADetector.with_backend(SoftBackend(mask.astype(np.float32) * p_marker), _keep_all(), ranker,
                                       scales=(1.0,), **settings)
        pm = det.probability(image)
        (blob,), _ = det.candidates(image, pm.prob, pm.factor, seeds=seeds)
        return blob, list(calls)

    return img, _edge_image(img.shape), blob_on


def test_an_unsure_blob_with_nothing_point_symmetric_on_it_is_not_refined(monkeypatch):
    from cpdetect.types import MarkerDetection

    img, texture, search = _blob_search(monkeypatch)

    def blob_on(image, p_marker, seeds=None, **settings):
        blob, calls = search(image, p_marker, seeds, **settings)
        return blob, len(calls)

    # an unsure blob (mean P 0.75 < rank_sure_mean_p) on the edge: skipped before any refinement
    for settings in ({}, {"unsure_min_symmetry": 0.9}):  # the default gate (0.5) and a stricter one
        blob, n = blob_on(texture, 0.75, **settings)
        assert blob.hopeless and blob.centre is None and n == 0
    blob, n = blob_on(texture, 0.75, unsure_min_symmetry=None)  # None: every blob is searched
    assert not blob.hopeless and n >= 1
    blob, n = blob_on(texture, 0.97, unsure_min_symmetry=0.9)  # a blob the network is sure of
    assert not blob.hopeless and n >= 1
    # a classical marker on the blob is evidence enough to look
    seed = MarkerDetection(x=121.0, y=133.0, score=1.0, type="square", radius_px=26.0, sigma_px=0.1)
    blob, n = blob_on(texture, 0.75, seeds=[seed], unsure_min_symmetry=0.9)
    assert not blob.hopeless and n >= 1
    # on the marker itself the gate lets the blob through, and it finds the same centre
    gated, _ = blob_on(img, 0.75, unsure_min_symmetry=0.9)
    plain, _ = blob_on(img, 0.75)
    assert not gated.hopeless and (gated.centre.x, gated.centre.y) == (plain.centre.x, plain.centre.y)
    assert math.hypot(gated.centre.x - 121.3, gated.centre.y - 133.6) < 0.15
    # a blob whose best symmetry lies between stop 53's cut (0.2) and the default since stop 54 (0.5)
    import learned.adapter as A

    monkeypatch.setattr(A, "_seed_symmetry", lambda *a: 0.35)
    blob, n = blob_on(img, 0.75)
    assert blob.hopeless and n == 0
    blob, n = blob_on(img, 0.75, unsure_min_symmetry=0.2)
    assert not blob.hopeless and n >= 1


def test_seeds_with_nothing_point_symmetric_about_them_are_not_refined(monkeypatch):
    from cpdetect.types import MarkerDetection

    img, texture, search = _blob_search(monkeypatch)

    def blob_on(image, seeds=None, **settings):
        # a blob the network is sure of (mean P 0.97): the unsure-blob gate does not apply
        return search(image, 0.97, seeds, **settings)

    # on the edge (sym180 - sym90 about -1 everywhere) every X-corner seed is refined without the cut,
    # and only the centroid with it: at the default (0.0 since stop 55) as at 0.5
    _, plain = blob_on(texture, min_seed_symmetry=None)
    for settings in ({}, {"min_seed_symmetry": 0.5}):
        blob, cut = blob_on(texture, **settings)
        assert len(plain) >= 3 and len(cut) == 1 and cut[0] == plain[0]
        assert not blob.hopeless  # the blob itself is still searched (its centroid)
    _, low = blob_on(texture, min_seed_symmetry=-1.9)  # a cut under every seed changes nothing
    assert low == plain
    # a classical marker on the blob is refined whatever its symmetry
    seed = MarkerDetection(x=121.0, y=133.0, score=1.0, type="square", radius_px=26.0, sigma_px=0.1)
    _, with_seed = blob_on(texture, seeds=[seed], min_seed_symmetry=0.5)
    assert len(with_seed) == 2 and with_seed[1] == (121.0, 133.0)
    # on the marker the centre is the same with the cut as without
    a, _ = blob_on(img, min_seed_symmetry=None)
    b, _ = blob_on(img)
    assert (a.centre.x, a.centre.y) == (b.centre.x, b.centre.y)
    assert math.hypot(b.centre.x - 121.3, b.centre.y - 133.6) < 0.15


@pytest.mark.parametrize("value", [2.5, -3.0])
def test_the_symmetry_gate_setting_is_checked(value):
    from cpdetect import get_detector
    from cpdetect.errors import UsageError

    with pytest.raises(UsageError, match="unsure_min_symmetry"):
        get_detector("hma", unsure_min_symmetry=value)
    with pytest.raises(UsageError, match="min_seed_symmetry"):
        get_detector("hma", min_seed_symmetry=value)
