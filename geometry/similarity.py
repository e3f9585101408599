"""Closed-form 7-parameter similarity (Umeyama 1991 / Horn 1987) with weights and degeneracy checks.

``fit_similarity(src, dst)`` returns a :class:`SimilarityFit` holding ``target_from_source`` (a
:class:`~geometry.transforms.Sim3`, x_dst ≈ s·R·x_src + t) or, for degenerate data, ``sim=None`` and a
``reason``. Degenerate data (fewer than 3 points, coincident points, collinear points, non-finite
values) is a *result*, not an exception: the fit is falsy and says why. Wrongly shaped arrays are
programming errors and raise ``ValueError``.

All arithmetic is float64. Centre large coordinates (UTM, ECEF) in a local frame first (see
``geometry.crs.LocalFrame``); the fit itself centres the data, so it is exact up to float64 rounding
of the inputs.

Scale: ``scale_method="umeyama"`` (default) is the least-squares scale of the Umeyama fit
(s = tr(D S) / σ²_src); it minimises Σ w‖dst − (sRx + t)‖² but is not symmetric under swapping
source and target. ``"symmetric"`` is Horn's s = sqrt(σ²_dst / σ²_src), independent of R, so the
fit of (dst, src) is exactly the inverse of the fit of (src, dst).

``fit_similarity_batch`` solves many tiny problems (e.g. the (h, 3, 3) triplets of a hypothesis
search) at once without the checks, for speed.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .transforms import Sim3

#: Smallest ratio of the second to the first singular value of the centred source points below which
#: the points are called collinear (rotation about the line undetermined). OpenSfM uses an eigenvalue
#: ratio of 5e3 (singular value ratio ~1.4e-2); we are more permissive because our callers check
#: triangle shapes against the measurement noise themselves.
COLLINEAR_RATIO = 1e-6


@dataclass(frozen=True)
class SimilarityFit:
    """Outcome of a similarity fit.

    sim: ``target_from_source`` or None when the data is degenerate; reason: why it failed ("" if ok);
    residuals: (n,) distances ‖dst − sim(src)‖ in target units (None on failure); rms: their
    root-mean-square (weighted by ``weights`` if given; nan on failure). A fit is truthy iff ``sim``
    is not None.
    """

    sim: Sim3 | None
    reason: str = ""
    residuals: np.ndarray | None = None
    rms: float = float("nan")

    def __bool__(self) -> bool:
        return self.sim is not None


def _as_points(x, name: str) -> np.ndarray:
    a = np.asarray(x, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != 3:
        raise ValueError(f"{name} must be an (n, 3) array, got shape {a.shape}")
    return a


def degeneracy_reason(points: np.ndarray, tol: float = 0.0) -> str:
    """Why ``points`` (n, 3) cannot fix a similarity, or "" when they can.

    ``tol`` is the point noise in the points' units: the points are "coincident" when their RMS
    spread about the centroid is ≤ tol (or zero), and "collinear" when their spread off the best line
    is ≤ tol or below ``COLLINEAR_RATIO`` of the spread along it.
    """
    points = _as_points(points, "points")
    n = len(points)
    if n < 3:
        return f"need at least 3 points, got {n}"
    if not np.all(np.isfinite(points)):
        return "points contain NaN or infinite values"
    centred = points - points.mean(axis=0)
    sv = np.linalg.svd(centred, compute_uv=False) / np.sqrt(n)  # RMS spread along principal axes
    if sv[0] <= tol or sv[0] <= 1e-12 * max(1.0, float(np.abs(points).max())):
        return "points are coincident (no spread)"
    if sv[1] <= tol or sv[1] <= COLLINEAR_RATIO * sv[0]:
        return "points are collinear (the rotation about their line is undetermined)"
    return ""


def fit_similarity(src, dst, weights=None, *, scale_method: str = "umeyama",
                   noise: float = 0.0) -> SimilarityFit:
    """Least-squares similarity ``dst ≈ s·R·src + t`` (proper rotation, det R = +1).

    src, dst: (n, 3) corresponding points (float64; source and target units may differ);
    weights: optional (n,) non-negative weights (e.g. 1/σ²); scale_method: "umeyama" or "symmetric";
    noise: point noise in *source* units used by the coincident/collinear checks (0: exact checks).
    """
    src = _as_points(src, "src")
    dst = _as_points(dst, "dst")
    if src.shape != dst.shape:
        raise ValueError(f"src and dst must have the same shape, got {src.shape} and {dst.shape}")
    if scale_method not in ("umeyama", "symmetric"):
        raise ValueError(f"scale_method must be 'umeyama' or 'symmetric', got {scale_method!r}")
    n = len(src)
    if weights is None:
        w = np.full(n, 1.0)
    else:
        w = np.asarray(weights, dtype=np.float64).reshape(-1)
        if w.shape != (n,):
            raise ValueError(f"weights must have shape ({n},), got {w.shape}")
        if not np.all(np.isfinite(w)) or np.any(w < 0):
            return SimilarityFit(None, "weights must be finite and non-negative")
    if not (np.all(np.isfinite(src)) and np.all(np.isfinite(dst))):
        return SimilarityFit(None, "points contain NaN or infinite values")
    active = w > 0
    if active.sum() < 3:
        return SimilarityFit(None, f"need at least 3 point pairs with positive weight, got {int(active.sum())}")
    reason = degeneracy_reason(src[active], noise)
    if reason:
        return SimilarityFit(None, "source " + reason)
    reason = degeneracy_reason(dst[active], 0.0)
    if reason:
        return SimilarityFit(None, "target " + reason)

    wn = w / w.sum()
    mu_s = wn @ src
    mu_d = wn @ dst
    xs = src - mu_s
    xd = dst - mu_d
    var_s = float(wn @ np.einsum("ij,ij->i", xs, xs))
    var_d = float(wn @ np.einsum("ij,ij->i", xd, xd))
    cov = (xd * wn[:, None]).T @ xs  # Σ = Σ_i w_i y_i x_iᵀ
    U, D, Vt = np.linalg.svd(cov)
    S = np.ones(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2] = -1.0
    R = (U * S) @ Vt
    if scale_method == "umeyama":
        s = float((D * S).sum() / var_s)
    else:
        s = float(np.sqrt(var_d / var_s))
    if not (np.isfinite(s) and s > 0):
        return SimilarityFit(None, "the points give no positive scale (target is a point reflection of the source)")
    t = mu_d - s * R @ mu_s
    sim = Sim3(s, R, t)
    res = np.linalg.norm(dst - sim(src), axis=1)
    rms = float(np.sqrt(wn @ res**2))
    return SimilarityFit(sim, "", res, rms)


def fit_similarity_batch(src: np.ndarray, dst: np.ndarray):
    """Unweighted Umeyama fits of many small problems at once, without degeneracy checks.

    src, dst: (h, k, 3) with k ≥ 3. Returns (scale (h,), R (h, 3, 3), t (h, 3)); a degenerate
    source gives a non-finite or zero scale, which the caller must reject (``np.isfinite(s) & (s > 0)``).
    """
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    mu_s = src.mean(axis=1, keepdims=True)
    mu_d = dst.mean(axis=1, keepdims=True)
    xs = src - mu_s
    xd = dst - mu_d
    k = src.shape[1]
    var_s = np.einsum("hij,hij->h", xs, xs) / k
    cov = np.einsum("hki,hkj->hij", xd, xs) / k
    U, D, Vt = np.linalg.svd(cov)
    sign = np.sign(np.linalg.det(U) * np.linalg.det(Vt))
    sign[sign == 0] = 1.0
    S = np.ones((len(src), 3))
    S[:, 2] = sign
    R = np.einsum("hij,hj,hjk->hik", U, S, Vt)
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (D * S).sum(axis=1) / var_s
    t = mu_d[:, 0, :] - s[:, None] * np.einsum("hij,hj->hi", R, mu_s[:, 0, :])
    return s, R, t
