"""Which blobs of the HMA probability map are markers: a logistic model over one blob's evidence.

The network says where marker pixels are; whether a blob is a marker also depends on what the image
says at its centre (a sharp X-corner, the classical marker model fitting there) and on the blob's own
shape and confidence. Rules on each of these alone trade misses for false markers; a logistic model
over all of them (:data:`INSTANCE_FEATURES`) weighs them together. It is fitted per network (the
network's confidence is one of the inputs) on generated images with *train*-split backgrounds
(``bench/fit_hma_instances.py``) and stored as ``instance_score.json`` beside the weights it was
fitted for. Without that file the detector keeps its rules (a verified centre, or a sharp one at the
blob's centroid).

Features of one blob (:func:`blob_features`):

- ``log_radius``: log of the blob's equal-area radius (image pixels);
- ``mean_p``, ``max_p``, ``frac_p90``: the network's mean and largest P(marker) on the blob, and the
  share of its pixels with P >= 0.9;
- ``solidity``: blob area over its convex hull's area (occluders and merged neighbours lower it);
- ``at_border``: 1 when the blob touches the image border;
- ``verified``, ``centroid``, ``seed``: how the centre was found (one-hot): the classical marker model
  fits there; a sharp refinement from the blob's centroid; another X-corner seed's refinement;
- ``log_sigma``: log of the refined centre's uncertainty (pixels);
- ``offset``: distance of the centre from the blob's centroid, over the radius (capped at 2);
- ``model_score``: the classical marker model's score at the centre (0 when it does not fit);
- ``sym180``, ``sym90``, ``blob_sym`` (optional, :data:`SYMMETRY_FEATURES`): how symmetric the image
  and the blob are about the centre (:mod:`learned.centre_choice`); a model fitted before they existed
  does not use them.
"""
from __future__ import annotations

import json
import math
import os
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

INSTANCE_FILE = "instance_score.json"
FORMAT = "cpdetect-hma-instances"
FORMAT_VERSION = 1
INSTANCE_FEATURES = ("log_radius", "mean_p", "max_p", "frac_p90", "solidity", "at_border", "verified", "centroid",
                     "seed", "log_sigma", "offset", "model_score")
SYMMETRY_FEATURES = ("sym180", "sym90", "blob_sym")
CENTRE_KINDS = ("verified", "centroid", "seed")


def blob_features(radius_px: float, mean_p: float, max_p: float, frac_p90: float, solidity: float,
                  at_border: bool, kind: str, sigma_px: float, offset: float, model_score: float,
                  sym180: float = 0.0, sym90: float = 0.0, blob_sym: float = 0.0) -> dict:
    """The feature dict of one blob (see the module doc); ``kind`` one of :data:`CENTRE_KINDS`."""
    if kind not in CENTRE_KINDS:
        raise ValueError(f"kind must be one of {', '.join(CENTRE_KINDS)}, got {kind!r}")
    return {"log_radius": math.log(max(float(radius_px), 1e-3)), "mean_p": float(mean_p), "max_p": float(max_p),
            "frac_p90": float(frac_p90), "solidity": float(min(solidity, 1.3)), "at_border": float(bool(at_border)),
            "verified": float(kind == "verified"), "centroid": float(kind == "centroid"),
            "seed": float(kind == "seed"), "log_sigma": math.log(max(float(sigma_px), 1e-2)),
            "offset": float(min(offset, 2.0)), "model_score": float(model_score),
            "sym180": float(sym180), "sym90": float(sym90), "blob_sym": float(blob_sym)}


@dataclass(frozen=True)
class InstanceModel:
    """P(marker | blob features) = 1 / (1 + exp(-(w . (f - mean) / std + bias))); a blob is kept when
    P >= ``threshold``. ``fitted``: where the model came from (data, counts, figures).
    ``features`` defaults to the twelve of the first fitted models, so their files load unchanged."""

    FILE = INSTANCE_FILE
    FORMAT = FORMAT
    KIND = "instance model"
    KNOWN_FEATURES = INSTANCE_FEATURES + SYMMETRY_FEATURES

    mean: tuple[float, ...]
    std: tuple[float, ...]
    weights: tuple[float, ...]
    bias: float
    threshold: float = 0.5
    features: tuple[str, ...] = INSTANCE_FEATURES
    fitted: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        n = len(self.features)
        if not (len(self.mean) == len(self.std) == len(self.weights) == n):
            raise ValueError(f"{self.KIND}: mean, std and weights need {n} values each")
        unknown = sorted(set(self.features) - set(self.KNOWN_FEATURES))
        if unknown:
            raise ValueError(f"{self.KIND}: unknown features {unknown}")
        if not all(s > 0 for s in self.std):
            raise ValueError(f"{self.KIND}: std must be positive")
        if not 0.0 < self.threshold < 1.0:
            raise ValueError(f"{self.KIND}: threshold must be in (0, 1)")

    def probability(self, feats: Mapping[str, float]) -> float:
        """P(marker) of one blob from its feature dict (:func:`blob_features`)."""
        x = np.array([feats[k] for k in self.features], float)
        z = float(((x - np.array(self.mean)) / np.array(self.std)) @ np.array(self.weights)) + self.bias
        return 1.0 / (1.0 + math.exp(-min(max(z, -50.0), 50.0)))

    def to_dict(self) -> dict:
        d = asdict(self)
        return {"format": self.FORMAT, "version": FORMAT_VERSION, **{k: list(v) if isinstance(v, tuple) else v
                                                                  for k, v in d.items()}}

    @classmethod
    def from_dict(cls, d: dict) -> "InstanceModel":
        d = dict(d)
        fmt, version = d.pop("format", None), d.pop("version", None)
        if fmt != cls.FORMAT or not isinstance(version, int) or version > FORMAT_VERSION:
            raise ValueError(f"not a {cls.FORMAT} v<={FORMAT_VERSION} file (format {fmt!r}, version {version!r})")
        known = set(cls.__dataclass_fields__)
        unknown = sorted(set(d) - known)
        if unknown:
            raise ValueError(f"unknown keys {unknown}")
        for k in ("mean", "std", "weights", "features"):
            if k in d:
                d[k] = tuple(d[k])
        return cls(**d)

    def save(self, model_dir: str | os.PathLike) -> Path:
        from cpdetect.fileio import write_json_atomic

        path = Path(model_dir) / self.FILE
        write_json_atomic(path, self.to_dict())
        return path

    @classmethod
    def load(cls, model_dir: str | os.PathLike | None):
        """The model of this kind stored in ``model_dir`` (its ``FILE``), or None when there is none.
        A file that is there but unreadable is an error naming it."""
        if model_dir is None:
            return None
        path = Path(model_dir) / cls.FILE
        if not path.exists():
            return None
        from cpdetect.errors import InputError

        try:
            return cls.from_dict(json.loads(path.read_text(encoding="utf-8")))
        except (OSError, ValueError, TypeError) as exc:
            raise InputError(f"not a valid {cls.KIND}: {exc}", path) from None


def load_instance_model(model_dir: str | os.PathLike | None) -> InstanceModel | None:
    """The instance model stored beside the weights in ``model_dir``, or None when there is none.
    A file that is there but unreadable is an error naming it."""
    return InstanceModel.load(model_dir)


def fit_instance_model(rows: Sequence[Mapping[str, float]], labels: Sequence[int], n_markers: int,
                       regularisation: float = 1.0, fitted: dict | None = None,
                       features: Sequence[str] = INSTANCE_FEATURES, f1_tolerance: float = 0.001) -> InstanceModel:
    """Logistic regression of ``labels`` (1: the blob's centre matches a true marker) on the feature
    dicts ``rows``; the threshold (0.20 to 0.80 in steps of 0.02) is the highest whose marker-level F1
    on these rows is within ``f1_tolerance`` of the best, where ``n_markers`` true markers are to be
    found (the ones no blob reaches count as misses)."""
    features = tuple(features)
    y = np.asarray(labels, int)
    mean, std, weights, bias, p = fit_standardised_logistic(rows, y, features, regularisation, "blobs")
    curve = []
    for t in np.arange(0.2, 0.81, 0.02):
        keep = p >= t
        tp = int(np.sum(keep & (y == 1)))
        fp = int(np.sum(keep & (y == 0)))
        curve.append((2 * tp / max(2 * tp + fp + (n_markers - tp), 1), float(round(t, 2))))
    # the F1 curve is flat over a wide range (on 600 train-split images within 0.001 from 0.30 to
    # 0.58), where its argmax is noise: take the highest threshold that close to the best, since a
    # false marker costs a georeferencing more than a missed one (it biases the fit; a miss only
    # removes redundancy)
    top = max(f1 for f1, _ in curve)
    best = max(((f1, t) for f1, t in curve if f1 >= top - f1_tolerance), key=lambda c: c[1])
    info = dict(fitted or {}, blobs=int(len(y)), positives=int(y.sum()), markers=int(n_markers),
                f1_at_threshold=round(best[0], 4))
    return InstanceModel(mean=mean, std=std, weights=weights, bias=bias, threshold=best[1], features=features,
                         fitted=info)


def fit_standardised_logistic(rows: Sequence[Mapping[str, float]], labels: np.ndarray, features: Sequence[str],
                              regularisation: float, what: str):
    """Logistic regression of ``labels`` (0 / 1) on the ``features`` of the dicts ``rows``, each
    standardised by its mean and std over the rows: (mean, std, weights, bias) as float tuples and
    floats, and the fitted probabilities of the rows. ``what`` names the rows in the error raised
    when there are fewer than 20 or only one kind."""
    from sklearn.linear_model import LogisticRegression

    X = np.array([[r[k] for k in features] for r in rows], float)
    y = np.asarray(labels, int)
    if len(y) < 20 or y.min() == y.max():
        raise ValueError(f"need at least 20 {what} of both kinds to fit")
    mean, std = X.mean(0), X.std(0)
    std = np.where(std > 1e-9, std, 1.0)
    clf = LogisticRegression(C=regularisation, max_iter=5000).fit((X - mean) / std, y)
    p = clf.predict_proba((X - mean) / std)[:, 1]
    return (tuple(float(v) for v in mean), tuple(float(v) for v in std), tuple(float(v) for v in clf.coef_[0]),
            float(clf.intercept_[0]), p)


__all__ = ["INSTANCE_FEATURES", "SYMMETRY_FEATURES", "INSTANCE_FILE", "CENTRE_KINDS", "InstanceModel", "blob_features",
           "load_instance_model", "fit_instance_model", "fit_standardised_logistic"]
