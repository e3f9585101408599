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
- ``model_score``: the classical marker model's score at the centre (0 when it does not fit).
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
CENTRE_KINDS = ("verified", "centroid", "seed")


def blob_features(radius_px: float, mean_p: float, max_p: float, frac_p90: float, solidity: float,
                  at_border: bool, kind: str, sigma_px: float, offset: float, model_score: float) -> dict:
    """The feature dict of one blob (see the module doc); ``kind`` one of :data:`CENTRE_KINDS`."""
    if kind not in CENTRE_KINDS:
        raise ValueError(f"kind must be one of {', '.join(CENTRE_KINDS)}, got {kind!r}")
    return {"log_radius": math.log(max(float(radius_px), 1e-3)), "mean_p": float(mean_p), "max_p": float(max_p),
            "frac_p90": float(frac_p90), "solidity": float(min(solidity, 1.3)), "at_border": float(bool(at_border)),
            "verified": float(kind == "verified"), "centroid": float(kind == "centroid"),
            "seed": float(kind == "seed"), "log_sigma": math.log(max(float(sigma_px), 1e-2)),
            "offset": float(min(offset, 2.0)), "model_score": float(model_score)}


@dataclass(frozen=True)
class InstanceModel:
    """P(marker | blob features) = 1 / (1 + exp(-(w . (f - mean) / std + bias))); a blob is kept when
    P >= ``threshold``. ``fitted``: where the model came from (data, counts, figures)."""

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
            raise ValueError(f"instance model: mean, std and weights need {n} values each")
        unknown = sorted(set(self.features) - set(INSTANCE_FEATURES))
        if unknown:
            raise ValueError(f"instance model: unknown features {unknown}")
        if not all(s > 0 for s in self.std):
            raise ValueError("instance model: std must be positive")
        if not 0.0 < self.threshold < 1.0:
            raise ValueError("instance model: threshold must be in (0, 1)")

    def probability(self, feats: Mapping[str, float]) -> float:
        """P(marker) of one blob from its feature dict (:func:`blob_features`)."""
        x = np.array([feats[k] for k in self.features], float)
        z = float(((x - np.array(self.mean)) / np.array(self.std)) @ np.array(self.weights)) + self.bias
        return 1.0 / (1.0 + math.exp(-min(max(z, -50.0), 50.0)))

    def to_dict(self) -> dict:
        d = asdict(self)
        return {"format": FORMAT, "version": FORMAT_VERSION, **{k: list(v) if isinstance(v, tuple) else v
                                                                  for k, v in d.items()}}

    @classmethod
    def from_dict(cls, d: dict) -> "InstanceModel":
        d = dict(d)
        fmt, version = d.pop("format", None), d.pop("version", None)
        if fmt != FORMAT or not isinstance(version, int) or version > FORMAT_VERSION:
            raise ValueError(f"not a {FORMAT} v<={FORMAT_VERSION} file (format {fmt!r}, version {version!r})")
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

        path = Path(model_dir) / INSTANCE_FILE
        write_json_atomic(path, self.to_dict())
        return path


def load_instance_model(model_dir: str | os.PathLike | None) -> InstanceModel | None:
    """The instance model stored beside the weights in ``model_dir``, or None when there is none.
    A file that is there but unreadable is an error naming it."""
    if model_dir is None:
        return None
    path = Path(model_dir) / INSTANCE_FILE
    if not path.exists():
        return None
    from cpdetect.errors import InputError

    try:
        return InstanceModel.from_dict(json.loads(path.read_text(encoding="utf-8")))
    except (OSError, ValueError, TypeError) as exc:
        raise InputError(f"not a valid instance model: {exc}", path) from None


def fit_instance_model(rows: Sequence[Mapping[str, float]], labels: Sequence[int], n_markers: int,
                       regularisation: float = 1.0, fitted: dict | None = None) -> InstanceModel:
    """Logistic regression of ``labels`` (1: the blob's centre matches a true marker) on the feature
    dicts ``rows``; the threshold is the one with the best marker-level F1 on these rows, where
    ``n_markers`` true markers are to be found (the ones no blob reaches count as misses)."""
    from sklearn.linear_model import LogisticRegression

    X = np.array([[r[k] for k in INSTANCE_FEATURES] for r in rows], float)
    y = np.asarray(labels, int)
    if len(y) < 20 or y.min() == y.max():
        raise ValueError("need at least 20 blobs of both kinds to fit the instance model")
    mean, std = X.mean(0), X.std(0)
    std = np.where(std > 1e-9, std, 1.0)
    clf = LogisticRegression(C=regularisation, max_iter=5000).fit((X - mean) / std, y)
    p = clf.predict_proba((X - mean) / std)[:, 1]
    best = (-1.0, 0.5)
    for t in np.arange(0.2, 0.81, 0.02):
        keep = p >= t
        tp = int(np.sum(keep & (y == 1)))
        fp = int(np.sum(keep & (y == 0)))
        f1 = 2 * tp / max(2 * tp + fp + (n_markers - tp), 1)
        if f1 > best[0] + 1e-12:
            best = (f1, float(round(t, 2)))
    info = dict(fitted or {}, blobs=int(len(y)), positives=int(y.sum()), markers=int(n_markers),
                f1_at_threshold=round(best[0], 4))
    return InstanceModel(mean=tuple(float(v) for v in mean), std=tuple(float(v) for v in std),
                         weights=tuple(float(v) for v in clf.coef_[0]), bias=float(clf.intercept_[0]),
                         threshold=best[1], fitted=info)


__all__ = ["INSTANCE_FEATURES", "INSTANCE_FILE", "CENTRE_KINDS", "InstanceModel", "blob_features",
           "load_instance_model", "fit_instance_model"]
