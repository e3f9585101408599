"""The tree ensembles behind the classical marker score and type: export, evaluation, the shipped files."""
from __future__ import annotations

import json

import numpy as np
import pytest

from cpdetect.tree_ensemble import (CLASSES_FORMAT, FORMAT, class_ensembles_from_dict, export_class_ensembles,
                                    export_tree_ensemble, load_class_ensembles, load_tree_ensemble,
                                    tree_ensemble_from_dict)


def _fitted(nan: bool = False):
    from sklearn.ensemble import HistGradientBoostingClassifier

    rng = np.random.default_rng(3)
    X = rng.normal(size=(600, 4))
    y = ((X[:, 0] * X[:, 1] > 0) ^ (X[:, 2] > 1.0)).astype(int)
    if nan:
        X[rng.random(X.shape) < 0.1] = np.nan
    return HistGradientBoostingClassifier(max_depth=4, max_iter=30, random_state=0).fit(X, y), X


@pytest.mark.parametrize("nan", [False, True])
def test_export_reproduces_scikit_learn(tmp_path, nan):
    clf, X = _fitted(nan)
    path = tmp_path / "m.json"
    path.write_text(json.dumps(export_tree_ensemble(clf, ["a", "b", "c", "d"], note="test")))
    ens = load_tree_ensemble(path)
    want = clf.predict_proba(X)[:, 1]
    assert np.abs(ens.probability(X) - want).max() < 1e-12
    # one sample at a time gives the same as the batch
    assert abs(ens.probability(X[5]) - want[5]) < 1e-12
    assert ens.features == ("a", "b", "c", "d") and ens.info["note"] == "test"
    # an interaction no single feature explains: the trees learned it
    assert ((ens.probability(X) >= 0.5) == clf.predict(X).astype(bool)).all()


def test_a_split_on_missing_values_survives_strict_json(tmp_path):
    # a feature missing for one class: scikit-learn splits "has a value" from "misses it" at an
    # infinite threshold, which strict JSON (the atomic writer's) cannot hold as a number
    from sklearn.ensemble import HistGradientBoostingClassifier

    from cpdetect.fileio import write_json_atomic

    rng = np.random.default_rng(5)
    X = rng.normal(size=(400, 2))
    y = (rng.random(400) < 0.5).astype(int)
    X[y == 1, 1] = np.nan
    clf = HistGradientBoostingClassifier(max_depth=2, max_iter=5, random_state=0).fit(X, y)
    doc = export_tree_ensemble(clf, ["a", "b"])
    assert any(t == "inf" for tree in doc["trees"] for t in tree["threshold"])
    path = tmp_path / "m.json"
    write_json_atomic(path, doc, indent=None)
    ens = load_tree_ensemble(path)
    assert np.isinf(ens.threshold).any()
    assert np.abs(ens.probability(X) - clf.predict_proba(X)[:, 1]).max() < 1e-12
    assert ((ens.probability(X) >= 0.5) == y.astype(bool)).all()


def test_hand_made_tree_routes_by_threshold_and_missing():
    doc = {"format": FORMAT, "features": ["u"], "baseline": 0.0,
           "trees": [{"feature": [0, 0, 0], "threshold": [1.0, 0.0, 0.0], "left": [1, 0, 0], "right": [2, 0, 0],
                      "missing_left": [False, True, True], "leaf": [False, True, True], "value": [0.0, -2.0, 3.0]}]}
    ens = tree_ensemble_from_dict(doc)
    assert ens.log_odds(np.array([1.0])) == -2.0  # <= threshold goes left
    assert ens.log_odds(np.array([1.0 + 1e-9])) == 3.0
    assert ens.log_odds(np.array([np.nan])) == 3.0  # missing_left False at the root
    assert ens.probability(np.array([5.0])) == pytest.approx(1 / (1 + np.exp(-3.0)), abs=1e-15)
    with pytest.raises(ValueError, match="expected 1 features"):
        ens.log_odds(np.zeros(2))


@pytest.mark.parametrize("change, message", [
    (lambda d: d.update(format="other/1"), "not a cpdetect.tree-ensemble/1"),
    (lambda d: d.pop("trees"), "malformed"),
    (lambda d: d["trees"][0].update(left=[7, 0, 0]), "out of range"),
    (lambda d: d["trees"][0].update(feature=[3, 0, 0]), "out of range"),
])
def test_malformed_files_are_named(tmp_path, change, message):
    doc = {"format": FORMAT, "features": ["u"], "baseline": 0.0,
           "trees": [{"feature": [0, 0, 0], "threshold": [1.0, 0.0, 0.0], "left": [1, 0, 0], "right": [2, 0, 0],
                      "missing_left": [True, True, True], "leaf": [False, True, True], "value": [0.0, -2.0, 3.0]}]}
    change(doc)
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(doc))
    with pytest.raises(ValueError, match=message) as e:
        load_tree_ensemble(path)
    assert str(path) in str(e.value)


def _ideal_patch(inside: float = 0.9, background: float = 0.45) -> dict:
    """PATCH_FEATURES of a frontal marker: dark (0) then bright (1) quarter turns up to ``inside`` of
    the outline radius, the background level (over the marker's contrast) beyond it."""
    from cpdetect.classical import PATCH_ANGLES, PATCH_FEATURES, PATCH_RINGS

    quarter = PATCH_ANGLES // 4
    values = [float((j // quarter) % 2) if f <= inside else background
              for f in PATCH_RINGS for j in range(PATCH_ANGLES)]
    return dict(zip(PATCH_FEATURES, values))


def test_shipped_marker_score_matches_the_detector_features():
    from cpdetect.classical import PATCH_FEATURES, SCORE_FEATURES, marker_score, score_model

    ens = score_model()
    assert ens.features == SCORE_FEATURES + PATCH_FEATURES
    assert ens.info["fitted_on"] and ens.info["script"] == "bench/fit_score.py"
    # typical features of a clean marker and of a texture saddle that passed the core test
    marker = dict(q=0.93, agree=0.97, logC=4.6, spread=0.08, e_rel=0.01, frac=0.98, widths_min=0.95,
                  mid_share=0.15, core_ratio=0.7, log_r=3.0, opp=0.05, inverted=0.0, alternations=0.0,
                  outer_mixed=0.1, hull_fallback=0.0, fill=0.97, alt_far=0.2, dark_surround=0.0, **_ideal_patch())
    # its marker area: the four-sector pattern fades into texture a third of the way out
    rng = np.random.default_rng(3)
    texture = {k: (v if i < 2 * 24 else float(rng.uniform(0.0, 1.0))) for i, (k, v) in enumerate(_ideal_patch().items())}
    saddle = dict(marker, agree=0.72, spread=0.3, e_rel=0.06, frac=0.78, widths_min=0.6, mid_share=0.4,
                  opp=0.3, inverted=0.6, alternations=1.0, outer_mixed=0.5, fill=0.7, alt_far=0.9,
                  dark_surround=0.6, **texture)
    assert marker_score(marker) > 0.9 and marker_score(saddle) < 0.1
    # the trees read the marker area: the same summary features with it all mid-grey are far less
    # likely a marker (in log-odds: both probabilities lie near 1)
    flat = dict(marker, **dict.fromkeys(PATCH_FEATURES, 0.5))
    odds = [float(ens.log_odds(np.array([f[k] for k in ens.features], float))) for f in (marker, flat)]
    assert odds[1] < odds[0] - 2.0


def _fitted_three_classes():
    from sklearn.ensemble import HistGradientBoostingClassifier

    rng = np.random.default_rng(5)
    X = rng.normal(size=(900, 3))
    X[rng.random(X.shape) < 0.05] = np.nan
    y = np.where(np.nan_to_num(X[:, 0]) > 0.5, "b", np.where(np.nan_to_num(X[:, 1] * X[:, 2]) > 0, "a", "c"))
    return HistGradientBoostingClassifier(max_depth=3, max_iter=40, random_state=0).fit(X, y), X


def test_class_ensembles_reproduce_scikit_learn(tmp_path):
    clf, X = _fitted_three_classes()
    path = tmp_path / "t.json"
    path.write_text(json.dumps(export_class_ensembles(clf, ["u", "v", "w"], note="test")))
    model = load_class_ensembles(path)
    assert model.classes == ("a", "b", "c") and model.features == ("u", "v", "w") and model.info["note"] == "test"
    # the raw scores are scikit-learn's decision function, so the predictions are its own
    assert np.abs(model.scores(X) - clf.decision_function(X)).max() < 1e-12
    assert (model.predict(X) == clf.predict(X)).all()
    assert model.predict(X[7]) == clf.predict(X[7:8])[0]
    assert len(set(model.predict(X))) == 3


def test_binary_and_class_exports_refuse_each_other():
    clf, _ = _fitted_three_classes()
    with pytest.raises(ValueError, match="only binary"):
        export_tree_ensemble(clf, ["u", "v", "w"])
    binary, _ = _fitted()
    with pytest.raises(ValueError, match="multi-class"):
        export_class_ensembles(binary, ["a", "b", "c", "d"])


@pytest.mark.parametrize("change, message", [
    (lambda d: d.update(format=FORMAT), "not a cpdetect.tree-classes/1"),
    (lambda d: d["classes"].pop(), "do not match"),
    (lambda d: d.pop("ensembles"), "malformed"),
    (lambda d: d["ensembles"][1].update(features=["x", "y", "z"]), "do not match"),
])
def test_malformed_class_ensembles_are_named(change, message):
    clf, _ = _fitted_three_classes()
    doc = export_class_ensembles(clf, ["u", "v", "w"])
    assert doc["format"] == CLASSES_FORMAT
    change(doc)
    with pytest.raises(ValueError, match=message) as e:
        class_ensembles_from_dict(doc, "types.json")
    assert "types.json" in str(e.value)


def test_shipped_score_files_serve_their_users():
    """The classical detector's score (over the summary features and the marker area), the trees before
    it (summary features alone, which hma's classical pass keeps) and the one the hma models were
    fitted on: all loadable as package data, each with its own trees."""
    from cpdetect.classical import BASE_SCORE_FILE, PATCH_FEATURES, SCORE_FEATURES, score_model
    from learned.adapter import MODEL_SCORE_FILE

    own, base, pinned = score_model(), score_model(BASE_SCORE_FILE), score_model(MODEL_SCORE_FILE)
    assert own.features == SCORE_FEATURES + PATCH_FEATURES
    assert base.features == pinned.features == SCORE_FEATURES
    # the same 6,900 images: the detector of stop 83 verifies more candidates than that of 2026-11-26
    assert own.info["rows"] > base.info["rows"] > pinned.info["rows"]
    assert own.info["fitted_on"] == base.info["fitted_on"]
    x = np.array([0.9, 0.95, 4.2, 0.1, 0.02, 0.95, 0.9, 0.2, 0.8, 2.8, 0.08, 0.0, 0.0, 0.2, 0.0, 0.95, 0.3, 0.1])
    assert base.probability(x) != pinned.probability(x)
