"""Gradient-boosted decision trees for binary and multi-class decisions, evaluated with NumPy from a JSON file.

A fitted scikit-learn ``HistGradientBoostingClassifier`` is written out by :func:`export_tree_ensemble`
(a fitting script's job) and read back by :func:`load_tree_ensemble` at run time, so the package needs
no pickle (which ties a model to one scikit-learn version) and no scikit-learn call per decision.

File layout (``format`` "cpdetect.tree-ensemble/1"): ``features`` (names, in the order of the input
vector), ``baseline`` (log-odds before the trees), ``trees``: per tree, node arrays ``feature``,
``threshold``, ``left``, ``right``, ``missing_left`` (a NaN feature goes left), ``leaf`` and ``value``
(the leaf's log-odds contribution). A sample goes left where ``x[feature] <= threshold``, as in
scikit-learn. Anything else in the file (how it was fitted) is kept in :attr:`TreeEnsemble.info`.

A multi-class classifier is written by :func:`export_class_ensembles` (``format``
"cpdetect.tree-classes/1"): ``classes`` (names) and ``ensembles``, one such document per class whose
log-odds is that class's raw score; :class:`ClassEnsembles` predicts the class of the highest score.
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import numpy as np

FORMAT = "cpdetect.tree-ensemble/1"


@dataclass(frozen=True)
class TreeEnsemble:
    """Trees padded to one node count: arrays (n_trees, n_nodes); ``depth`` the longest root-to-leaf path."""

    features: tuple[str, ...]
    baseline: float
    feature: np.ndarray
    threshold: np.ndarray
    left: np.ndarray
    right: np.ndarray
    missing_left: np.ndarray
    leaf: np.ndarray
    value: np.ndarray
    depth: int
    info: dict = field(default_factory=dict)

    def log_odds(self, x: np.ndarray) -> np.ndarray:
        """Log-odds for samples ``x`` (n, n_features) or one sample (n_features,)."""
        x = np.asarray(x, float)
        one = x.ndim == 1
        X = x.reshape(1, -1) if one else x
        if X.shape[1] != len(self.features):
            raise ValueError(f"expected {len(self.features)} features, got {X.shape[1]}")
        feature, threshold, missing_left, left, right = self._flat
        n_trees, n_nodes = self.feature.shape
        # flat node indices (tree * n_nodes + node) into arrays where a leaf points to itself, so
        # every sample walks ``depth`` steps without asking whether it has arrived
        node = np.broadcast_to(np.arange(n_trees) * n_nodes, (len(X), n_trees)).copy()
        rows = np.arange(len(X))[:, None]
        nan = bool(np.isnan(X).any())
        for _ in range(self.depth):
            v = X[rows, feature[node]]
            go_left = v <= threshold[node]
            if nan:
                go_left = np.where(np.isnan(v), missing_left[node], go_left)
            node = np.where(go_left, left[node], right[node])
        out = self.baseline + self.value.ravel()[node].sum(1)
        return out[0] if one else out

    @cached_property
    def _flat(self) -> tuple[np.ndarray, ...]:
        """feature, threshold, missing_left, left, right raveled, children as flat indices, a leaf's
        children itself."""
        n_trees, n_nodes = self.feature.shape
        base = (np.arange(n_trees) * n_nodes)[:, None]
        own = base + np.arange(n_nodes)[None, :]
        left = np.where(self.leaf, own, base + self.left)
        right = np.where(self.leaf, own, base + self.right)
        return (self.feature.ravel(), self.threshold.ravel(), self.missing_left.ravel(), left.ravel(),
                right.ravel())

    def probability(self, x: np.ndarray) -> np.ndarray | float:
        """P(positive class) in [0, 1] for ``x`` as in :meth:`log_odds`."""
        p = 1.0 / (1.0 + np.exp(-np.clip(self.log_odds(x), -700.0, 700.0)))
        return float(p) if np.ndim(p) == 0 else p


def _tree_depth(left: np.ndarray, right: np.ndarray, leaf: np.ndarray) -> int:
    """Longest root-to-leaf path; ValueError when a path is longer than the node count (a cycle)."""
    depth, stack = 0, [(0, 0)]
    while stack:
        i, d = stack.pop()
        if d > len(leaf):
            raise ValueError("a tree's nodes form a cycle")
        if leaf[i]:
            depth = max(depth, d)
        else:
            stack += [(int(left[i]), d + 1), (int(right[i]), d + 1)]
    return depth


def tree_ensemble_from_dict(doc: dict, source: str = "tree ensemble") -> TreeEnsemble:
    """A :class:`TreeEnsemble` from the parsed JSON document; ValueError naming ``source`` if malformed."""
    if doc.get("format") != FORMAT:
        raise ValueError(f"{source}: not a {FORMAT} file")
    try:
        feats = tuple(str(f) for f in doc["features"])
        trees = doc["trees"]
        n = max(len(t["feature"]) for t in trees)
        pad = lambda key, fill, dtype: np.array([list(t[key]) + [fill] * (n - len(t[key])) for t in trees], dtype)
        leaf = pad("leaf", True, bool)
        left, right = pad("left", 0, np.intp), pad("right", 0, np.intp)
        feature, threshold = pad("feature", 0, np.intp), pad("threshold", 0.0, float)
        missing_left, value = pad("missing_left", True, bool), pad("value", 0.0, float)
        inner = ~leaf
        if (feature[inner] >= len(feats)).any() or (feature[inner] < 0).any() or (left[inner] >= n).any() \
                or (right[inner] >= n).any() or (left[inner] < 0).any() or (right[inner] < 0).any():
            raise ValueError("node index out of range")
        depth = max(_tree_depth(left[t], right[t], leaf[t]) for t in range(len(trees)))
        ens = TreeEnsemble(feats, float(doc["baseline"]), feature, threshold, left, right, missing_left, leaf,
                           value, depth, {k: v for k, v in doc.items()
                                          if k not in ("format", "features", "baseline", "trees")})
    except (KeyError, TypeError, ValueError, IndexError) as e:
        raise ValueError(f"{source}: malformed tree ensemble ({e})") from None
    return ens


def load_tree_ensemble(path: str | Path) -> TreeEnsemble:
    """Read a tree ensemble written by :func:`export_tree_ensemble`."""
    with open(path, encoding="utf-8") as f:
        return tree_ensemble_from_dict(json.load(f), str(path))


def _json_float(v: float) -> float | str:
    """``v`` as JSON holds it: an infinite threshold (scikit-learn's split of the samples that have a
    value from those that miss it) as the string "inf" / "-inf", which float() reads back."""
    v = float(v)
    return v if math.isfinite(v) else ("inf" if v > 0 else "-inf")


def _trees_doc(predictors: list) -> list[dict]:
    trees = []
    for pred in predictors:
        nd = pred.nodes
        if nd["is_categorical"].any():
            raise ValueError("categorical splits are not supported")
        trees.append({"feature": nd["feature_idx"].astype(int).tolist(),
                      "threshold": [_json_float(t) for t in nd["num_threshold"]],
                      "left": nd["left"].astype(int).tolist(), "right": nd["right"].astype(int).tolist(),
                      "missing_left": nd["missing_go_to_left"].astype(bool).tolist(),
                      "leaf": nd["is_leaf"].astype(bool).tolist(), "value": [float(v) for v in nd["value"]]})
    return trees


def export_tree_ensemble(clf, features: list[str] | tuple[str, ...], **info) -> dict:
    """The JSON document of a fitted binary scikit-learn ``HistGradientBoostingClassifier`` (numerical
    features only); ``info`` is stored alongside (how it was fitted)."""
    if getattr(clf, "n_trees_per_iteration_", 1) != 1:
        raise ValueError("only binary classifiers can be exported (see export_class_ensembles)")
    baseline = float(np.ravel(clf._baseline_prediction)[0])
    return {"format": FORMAT, "features": list(features), "baseline": baseline,
            "trees": _trees_doc([p for (p,) in clf._predictors]), **info}


# ------------------------------------------------------------------------------------------------
# several classes: one ensemble of raw scores per class, the class with the highest score wins

CLASSES_FORMAT = "cpdetect.tree-classes/1"


@dataclass(frozen=True)
class ClassEnsembles:
    """A multi-class ``HistGradientBoostingClassifier``: per class in ``classes`` a
    :class:`TreeEnsemble` whose :meth:`TreeEnsemble.log_odds` is that class's raw score (softmax
    input); the prediction is the class of the highest score, as scikit-learn's ``predict``."""

    classes: tuple[str, ...]
    ensembles: tuple[TreeEnsemble, ...]
    info: dict = field(default_factory=dict)

    @property
    def features(self) -> tuple[str, ...]:
        return self.ensembles[0].features

    def scores(self, x: np.ndarray) -> np.ndarray:
        """Raw scores (n, n_classes) for samples ``x`` (n, n_features), or (n_classes,) for one."""
        return np.stack([np.asarray(e.log_odds(x), float) for e in self.ensembles], -1)

    def predict(self, x: np.ndarray) -> str | np.ndarray:
        """The class name for one sample (n_features,), or an array of names for (n, n_features)."""
        s = self.scores(x)
        if s.ndim == 1:
            return self.classes[int(np.argmax(s))]
        return np.array(self.classes, dtype=object)[np.argmax(s, axis=1)]


def export_class_ensembles(clf, features: list[str] | tuple[str, ...], **info) -> dict:
    """The JSON document of a fitted multi-class scikit-learn ``HistGradientBoostingClassifier``
    (three classes or more, numerical features only); ``info`` is stored alongside."""
    k = getattr(clf, "n_trees_per_iteration_", 1)
    if k < 3:
        raise ValueError("a multi-class classifier (three classes or more) is expected")
    base = np.ravel(clf._baseline_prediction)
    ensembles = [{"format": FORMAT, "features": list(features), "baseline": float(base[c]),
                  "trees": _trees_doc([it[c] for it in clf._predictors])} for c in range(k)]
    return {"format": CLASSES_FORMAT, "classes": [str(c) for c in clf.classes_], "ensembles": ensembles, **info}


def class_ensembles_from_dict(doc: dict, source: str = "class ensembles") -> ClassEnsembles:
    """A :class:`ClassEnsembles` from the parsed JSON document; ValueError naming ``source`` if malformed."""
    if not isinstance(doc, dict) or doc.get("format") != CLASSES_FORMAT:
        raise ValueError(f"{source}: not a {CLASSES_FORMAT} document")
    try:
        classes = tuple(str(c) for c in doc["classes"])
        ens = tuple(tree_ensemble_from_dict(e, source) for e in doc["ensembles"])
    except (KeyError, TypeError) as e:
        raise ValueError(f"{source}: malformed class ensembles ({e})") from None
    if len(classes) < 2 or len(classes) != len(ens) or len({e.features for e in ens}) != 1:
        raise ValueError(f"{source}: classes and ensembles do not match")
    info = {k: v for k, v in doc.items() if k not in ("format", "classes", "ensembles")}
    return ClassEnsembles(classes, ens, info)


def load_class_ensembles(path: str | Path) -> ClassEnsembles:
    """Read class ensembles written by :func:`export_class_ensembles`."""
    with open(path, encoding="utf-8") as f:
        return class_ensembles_from_dict(json.load(f), str(path))


__all__ = ["TreeEnsemble", "load_tree_ensemble", "tree_ensemble_from_dict", "export_tree_ensemble",
           "ClassEnsembles", "export_class_ensembles", "class_ensembles_from_dict", "load_class_ensembles"]
