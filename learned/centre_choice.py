"""Which refined seed is a blob's marker centre: a logistic score over each candidate's evidence.

A blob of the HMA map gets several centre candidates: its probability-weighted centroid and the
strongest X-corners on it, each refined (:func:`cpdetect.refine.refine_center_coarse_to_fine`). On a
partly covered or low-contrast marker the first candidate the classical marker model verifies, or the
sharpest one, is often an occluder's corner or a corner of the marker's outline. A checker's centre
differs from those corners in ways that are cheap to measure:

- ``sym180``: the gray image is point-symmetric about it (opposite sectors have the same shade): the
  correlation of the image with itself rotated by 180 degrees about the candidate, on rings from 0.15
  to 0.8 of the marker radius (about 0.9 at true centres, -0.2 at other candidates on train-split
  data);
- ``sym90``: and anti-symmetric under a quarter turn (about -0.9 against -0.15);
- ``blob_sym``: the blob itself is point-symmetric about it: the share of blob pixels whose
  reflection through the candidate is a blob pixel (0.9 against 0.04).

:class:`CentreRanker` scores every candidate from these and the refinement's own evidence
(:data:`CANDIDATE_FEATURES`) and the detector takes the best. It is fitted on generated images with
train-split backgrounds (``bench/fit_hma_centres.py``) and stored as ``centre_rank.json`` beside the
weights; without that file the detector keeps its rules.
"""
from __future__ import annotations

import math

import cv2
import numpy as np

from .instances import InstanceModel, fit_standardised_logistic

CENTRE_FILE = "centre_rank.json"
CANDIDATE_FEATURES = ("log_sigma", "offset", "verified", "model_score", "reach", "blob_sym", "sym180", "sym90",
                      "centroid_seed", "seed_strength")
_RING_FRACTIONS = np.linspace(0.15, 0.8, 8)
_RING_ANGLES = np.linspace(0.0, 2.0 * np.pi, 48, endpoint=False)


def point_symmetry(gray: np.ndarray, x: float, y: float, radius: float) -> tuple[float, float]:
    """(sym180, sym90): correlation of the gray image around (x, y) (full-resolution pixels, OpenCV
    convention) with itself turned by 180 and by 90 degrees about that point, sampled bilinearly on 8
    rings from 0.15 to 0.8 ``radius`` (pixels) at 48 angles; 0 where the rings are flat."""
    r, t = np.meshgrid(_RING_FRACTIONS * float(radius), _RING_ANGLES)
    # only the window the rings reach is converted, so a 45 MP image costs no more than a small one
    reach = int(math.ceil(0.8 * radius)) + 2
    h, w = gray.shape[:2]
    x0, y0 = max(0, int(x) - reach), max(0, int(y) - reach)
    x1, y1 = min(w, int(x) + reach + 2), min(h, int(y) + reach + 2)
    if x1 - x0 < 2 or y1 - y0 < 2:
        return 0.0, 0.0
    win = np.ascontiguousarray(gray[y0:y1, x0:x1], np.float32)

    def ring(turn: float) -> np.ndarray:
        xs = (x - x0 + r * np.cos(t + turn)).astype(np.float32)
        ys = (y - y0 + r * np.sin(t + turn)).astype(np.float32)
        return cv2.remap(win, xs, ys, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT).ravel()

    a = ring(0.0)
    return _correlation(a, ring(np.pi)), _correlation(a, ring(0.5 * np.pi))


def _correlation(u: np.ndarray, v: np.ndarray) -> float:
    u = u - u.mean()
    v = v - v.mean()
    d = math.sqrt(float((u * u).sum()) * float((v * v).sum()))
    return float((u * v).sum()) / d if d > 1e-6 else 0.0


def blob_symmetry(comp: np.ndarray, u: float, v: float) -> float:
    """Share of the pixels of ``comp`` (bool, a blob in its bounding box) whose point reflection
    through (u, v) (pixels of that box, OpenCV convention) is also a blob pixel."""
    m = comp.astype(np.uint8)
    n = int(m.sum())
    if n == 0:
        return 0.0
    turn = np.float32([[-1, 0, 2 * u], [0, -1, 2 * v]])
    reflected = cv2.warpAffine(m, turn, (m.shape[1], m.shape[0]), flags=cv2.INTER_NEAREST, borderValue=0)
    return float(np.count_nonzero(reflected & m)) / n


def candidate_features(sigma_px: float, offset: float, verified: bool, model_score: float, reach: float,
                       blob_sym: float, sym180: float, sym90: float, centroid_seed: bool,
                       seed_strength: float) -> dict:
    """The feature dict of one centre candidate (:data:`CANDIDATE_FEATURES`): ``offset`` from the
    blob's centroid over its radius, ``reach`` of :func:`cpdetect.centre_reach.centre_reach`,
    ``seed_strength`` the X-corner contrast of its seed over the blob's strongest (0 for the centroid)."""
    return {"log_sigma": math.log(max(float(sigma_px), 1e-2)), "offset": float(min(offset, 2.0)),
            "verified": float(bool(verified)), "model_score": float(model_score), "reach": float(min(reach, 3.0)),
            "blob_sym": float(blob_sym), "sym180": float(sym180), "sym90": float(sym90),
            "centroid_seed": float(bool(centroid_seed)), "seed_strength": float(seed_strength)}


class CentreRanker(InstanceModel):
    """Logistic score of a centre candidate (:data:`CANDIDATE_FEATURES`); the detector takes the
    candidate with the highest. Same file layout as the instance model, another format name."""

    FILE = CENTRE_FILE
    FORMAT = "cpdetect-hma-centres"
    KIND = "centre ranker"
    KNOWN_FEATURES = CANDIDATE_FEATURES


def load_centre_ranker(model_dir) -> CentreRanker | None:
    """The ranker stored beside the weights in ``model_dir``, or None when there is none."""
    return CentreRanker.load(model_dir)


def fit_centre_ranker(rows, labels, regularisation: float = 1.0, fitted: dict | None = None) -> CentreRanker:
    """Logistic regression of ``labels`` (1: the candidate lies within the evaluation tolerance of
    the true centre of a marker on its blob) on candidate feature dicts ``rows``."""
    mean, std, weights, bias, _ = fit_standardised_logistic(rows, np.asarray(labels, int), CANDIDATE_FEATURES,
                                                            regularisation, "candidates")
    info = dict(fitted or {}, candidates=len(labels), positives=int(np.sum(labels)))
    return CentreRanker(mean=mean, std=std, weights=weights, bias=bias, threshold=0.5, features=CANDIDATE_FEATURES,
                        fitted=info)


__all__ = ["CANDIDATE_FEATURES", "CENTRE_FILE", "CentreRanker", "blob_symmetry", "candidate_features",
           "fit_centre_ranker", "load_centre_ranker", "point_symmetry"]
