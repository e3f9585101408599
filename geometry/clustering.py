"""Cluster marker points in 3D (DBSCAN) and take their centroids as first marker estimates.

Parameters are in model units and derive from two lengths of the scene, never from absolute numbers:
the cloud's point spacing and the marker size (both in model units; the pipeline estimates the marker
size from the detections' apparent radius and camera depth). See :func:`dbscan_params`.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree


def point_spacing(points: np.ndarray, sample: int = 20000, rng: np.random.Generator | None = None) -> float:
    """Median nearest-neighbour distance (model units) of a random subsample of ``points`` (n, 3)."""
    P = np.asarray(points, float).reshape(-1, 3)
    if len(P) < 2:
        raise ValueError("need at least two points to measure spacing")
    rng = np.random.default_rng(0) if rng is None else rng
    sub = P if len(P) <= sample else P[rng.choice(len(P), sample, replace=False)]
    tree = cKDTree(P)
    d, _ = tree.query(sub, k=2)
    return float(np.median(d[:, 1]))


@dataclass(frozen=True)
class DbscanParams:
    """eps: neighbourhood radius (model units); min_samples: core-point neighbour count;
    max_extent: clusters wider than this (model units) are rejected as not marker-like."""

    eps: float
    min_samples: int
    max_extent: float


def dbscan_params(spacing: float, marker_size: float) -> DbscanParams:
    """Parameters from the point spacing and the marker size (both model units).

    eps = max(2.5 * spacing, 0.1 * marker_size) but at most 0.5 * marker_size (two markers are rarely
    closer than a marker size). min_samples: about a quarter of the points a marker's disc of radius
    ``eps`` would hold at that spacing, at least 3. max_extent = 3 * marker_size.
    """
    if not (spacing > 0 and marker_size > 0):
        raise ValueError("spacing and marker size must be positive")
    eps = min(max(2.5 * spacing, 0.1 * marker_size), 0.5 * marker_size)
    expected = np.pi * eps ** 2 / spacing ** 2
    return DbscanParams(eps=float(eps), min_samples=int(max(3, min(50, round(0.25 * expected)))),
                        max_extent=float(3.0 * marker_size))


@dataclass(frozen=True)
class Cluster:
    """One marker candidate: centroid (3,) model frame (score-weighted), the member count, the mean
    score, the extent (largest distance of a member from the centroid) and member indices."""

    centroid: np.ndarray
    n_points: int
    mean_score: float
    extent: float
    members: np.ndarray


def cluster_points(points: np.ndarray, scores: np.ndarray, params: DbscanParams,
                   threshold: float = 0.5) -> list[Cluster]:
    """DBSCAN (scikit-learn) on the points whose score >= ``threshold``; returns clusters with the
    best mean score x size first. Clusters wider than ``params.max_extent`` are dropped."""
    from sklearn.cluster import DBSCAN

    P = np.asarray(points, float).reshape(-1, 3)
    s = np.asarray(scores, float).reshape(-1)
    cand = np.flatnonzero(s >= threshold)
    if len(cand) < params.min_samples:
        return []
    labels = DBSCAN(eps=params.eps, min_samples=params.min_samples).fit_predict(P[cand])
    out = []
    for lab in np.unique(labels[labels >= 0]):
        members = cand[labels == lab]
        w = s[members]
        c = (P[members] * w[:, None]).sum(0) / w.sum()
        extent = float(np.linalg.norm(P[members] - c, axis=1).max())
        if extent > params.max_extent:
            continue
        out.append(Cluster(c, len(members), float(w.mean()), extent, members))
    out.sort(key=lambda c: -c.mean_score * c.n_points)
    return out


def cluster_centres(points: np.ndarray, eps: float, min_samples: int = 2,
                    weights: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """DBSCAN on a small set of 3D points (e.g. ray hits or pairwise triangulations).

    Returns (centres (k, 3) weighted means of each cluster, labels (n,) with -1 for noise)."""
    from sklearn.cluster import DBSCAN

    P = np.asarray(points, float).reshape(-1, 3)
    if len(P) == 0:
        return np.zeros((0, 3)), np.zeros(0, np.int64)
    w = np.ones(len(P)) if weights is None else np.asarray(weights, float)
    labels = DBSCAN(eps=eps, min_samples=min_samples).fit_predict(P)
    centres = []
    for lab in range(labels.max() + 1):
        m = labels == lab
        centres.append((P[m] * w[m, None]).sum(0) / w[m].sum())
    return np.array(centres).reshape(-1, 3), labels
