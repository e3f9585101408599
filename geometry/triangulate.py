"""Multi-view triangulation of one point from its pixel observations: DLT, then robust least squares.

Observations are pixels in the OpenCV convention of *distorted* images; the full camera model
(:class:`geometry.camera.Camera`, including distortion) is used for the residuals, and the DLT
works on undistorted normalised coordinates. Residuals are whitened by each observation's
``sigma_px``, so the robust loss (Huber or Cauchy, scale ``f_scale`` in sigmas) and the covariance are
in consistent units.

Covariance: ``s0^2 (J^T J)^-1`` of the whitened residuals at the solution, over inlier observations,
with the a-posteriori variance factor ``s0^2 = sum r^2 / (2 n - 3)`` (1 when there is no redundancy);
units: model units squared, model frame.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from itertools import combinations
from typing import Sequence

import numpy as np
from scipy.optimize import least_squares

from .camera import Camera
from .transforms import Rigid3


@dataclass(frozen=True)
class Observation:
    """One image's measurement of a point: pixel ``uv`` (2,), its 1-sigma ``sigma_px``, and the
    camera and pose (``cam_from_world``, model frame) of that image; ``image`` is a free label."""

    camera: Camera
    cam_from_world: Rigid3
    uv: np.ndarray
    sigma_px: float = 1.0
    image: str = ""


@dataclass
class TriangulationResult:
    """point: (3,) model frame (NaN when not ok); residuals_px: (k, 2) reprojection error per
    observation in pixels; inliers: (k,) bool; rms_px: RMS of the inliers' residual vectors' lengths;
    covariance: (3, 3) model units^2; ok False with a ``reason`` when triangulation failed."""

    point: np.ndarray
    ok: bool
    reason: str = ""
    residuals_px: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    inliers: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))
    rms_px: float = float("nan")
    covariance: np.ndarray = field(default_factory=lambda: np.full((3, 3), np.nan))
    max_angle_deg: float = 0.0

    @property
    def n_inliers(self) -> int:
        return int(self.inliers.sum())

    def __bool__(self) -> bool:
        return self.ok


def project_batch(X: np.ndarray, R: np.ndarray, t: np.ndarray, f: np.ndarray, c: np.ndarray,
                  dist: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Project k points with k poses and k cameras at once (the model of :class:`Camera`).

    X (k, 3) model frame; R (k, 3, 3), t (k, 3) cam_from_world; f, c (k, 2) focal lengths and principal
    points in pixels; dist (k, 5) k1, k2, p1, p2, k3. Returns pixels (k, 2) and camera depths z (k,).
    """
    P = np.einsum("kij,kj->ki", R, X) + t
    z = P[:, 2]
    xn = P[:, :2] / np.where(np.abs(z) > 1e-12, z, 1e-12)[:, None]
    k1, k2, p1, p2, k3 = np.asarray(dist, float).T
    x, y = xn[:, 0], xn[:, 1]
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return np.stack([xd, yd], 1) * f + c, z


class _Stack:
    """Observations as arrays for vectorised projection."""

    def __init__(self, obs: Sequence[Observation]):
        self.R = np.stack([o.cam_from_world.R for o in obs])
        self.t = np.stack([o.cam_from_world.t for o in obs])
        self.f = np.array([[o.camera.fx, o.camera.fy] for o in obs])
        self.c = np.array([[o.camera.cx, o.camera.cy] for o in obs])
        self.dist = np.array([o.camera.dist for o in obs])
        self.uv = np.array([np.asarray(o.uv, float).reshape(2) for o in obs])
        self.sigma = np.array([float(o.sigma_px) for o in obs])
        self.centers = np.stack([o.cam_from_world.center for o in obs])
        # undistorted normalised coordinates of the measurements
        self.xn = np.stack([o.camera.undistort_normalized(((np.asarray(o.uv, float).reshape(1, 2)
                                                            - [o.camera.cx, o.camera.cy])
                                                           / [o.camera.fx, o.camera.fy]))[0] for o in obs])

    def project(self, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixels (k, 2) of X in every view and the camera depths (k,)."""
        return project_batch(np.broadcast_to(X, self.t.shape), self.R, self.t, self.f, self.c, self.dist)

    def residuals(self, X: np.ndarray, idx: np.ndarray | None = None) -> np.ndarray:
        uv, _ = self.project(X)
        r = (uv - self.uv) / self.sigma[:, None]
        return (r if idx is None else r[idx]).ravel()


def dlt(observations: Sequence[Observation]) -> np.ndarray:
    """Linear (DLT) triangulation (3,) from >= 2 observations, on undistorted normalised coordinates."""
    if len(observations) < 2:
        raise ValueError("DLT needs at least two observations")
    return _dlt(_Stack(observations), np.arange(len(observations)))


def _dlt(st: _Stack, idx: np.ndarray) -> np.ndarray:
    rows = []
    for k in idx:
        P = np.hstack([st.R[k], st.t[k][:, None]])
        x, y = st.xn[k]
        rows.append(x * P[2] - P[0])
        rows.append(y * P[2] - P[1])
    A = np.array(rows)
    A /= np.maximum(np.linalg.norm(A, axis=1, keepdims=True), 1e-300)
    _, _, Vt = np.linalg.svd(A)
    Xh = Vt[-1]
    if abs(Xh[3]) < 1e-15:
        return np.full(3, np.nan)
    return Xh[:3] / Xh[3]


def _angle_deg(st: _Stack, X: np.ndarray, idx: np.ndarray) -> float:
    """Largest angle (degrees) between the rays from the cameras ``idx`` to X."""
    d = X - st.centers[idx]
    d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-300)
    cos = np.clip(d @ d.T, -1.0, 1.0)
    return float(np.degrees(np.arccos(cos.min())))


def triangulate(observations: Sequence[Observation], loss: str = "huber", f_scale: float = 2.0,
                outlier_sigma: float = 6.0, min_angle_deg: float = 1.0, max_pairs: int = 200,
                rng: np.random.Generator | None = None, outlier_px=0.0) -> TriangulationResult:
    """Robust multi-view triangulation.

    1. Hypotheses: DLT of observation pairs whose rays meet at >= ``min_angle_deg`` (all pairs, or
       ``max_pairs`` random ones drawn with ``rng``); keep the one with most observations within
       the outlier threshold that are in front of their camera. The threshold of observation i is
       ``max(outlier_sigma * sigma_i, outlier_px_i)`` pixels (``outlier_px``: scalar or (k,); a floor
       that tolerates pose errors of the reconstruction larger than the measurement noise).
    2. Nonlinear least squares over all observations from there (``loss`` "huber", "cauchy",
       "soft_l1" or "linear"; ``f_scale`` in sigmas), then drop observations beyond ``outlier_sigma``
       and refit on the inliers.
    Returns a falsy result with a ``reason`` when fewer than two consistent views remain.
    """
    k = len(observations)
    nan3 = np.full(3, np.nan)
    if k < 2:
        return TriangulationResult(nan3, False, "fewer than two observations")
    st = _Stack(observations)
    thr = np.maximum(outlier_sigma, np.broadcast_to(np.asarray(outlier_px, float), (k,)) / st.sigma)
    pairs = list(combinations(range(k), 2))
    if len(pairs) > max_pairs:
        rng = np.random.default_rng(0) if rng is None else rng
        pairs = [pairs[i] for i in rng.choice(len(pairs), max_pairs, replace=False)]
    best, best_key = None, (-1, np.inf)
    for a, b in pairs:
        X = _dlt(st, np.array([a, b]))
        if not np.all(np.isfinite(X)) or _angle_deg(st, X, np.array([a, b])) < min_angle_deg:
            continue
        r = np.linalg.norm(st.residuals(X).reshape(-1, 2), axis=1)
        _, z = st.project(X)
        inl = (r < thr) & (z > 0)
        key = (int(inl.sum()), float(np.minimum(r / thr, 1.0).sum()))
        if key[0] > best_key[0] or (key[0] == best_key[0] and key[1] < best_key[1]):
            best, best_key = X, key
    if best is None or best_key[0] < 2:
        return TriangulationResult(nan3, False, "no pair of views with enough baseline agrees")

    X = best
    idx = np.arange(k)
    for _ in range(3):
        sol = least_squares(lambda x: st.residuals(x, idx), X, loss=loss, f_scale=f_scale, method="trf",
                            x_scale="jac")
        X = sol.x
        r = np.linalg.norm(st.residuals(X).reshape(-1, 2), axis=1)
        _, z = st.project(X)
        new_idx = np.flatnonzero((r < thr) & (z > 0))
        if len(new_idx) < 2:
            return TriangulationResult(nan3, False, "fewer than two inlier views after the robust fit")
        if np.array_equal(new_idx, idx):
            break
        idx = new_idx
    inliers = np.zeros(k, bool)
    inliers[idx] = True
    angle = _angle_deg(st, X, idx)
    uv, _ = st.project(X)
    res_px = uv - st.uv
    rms = float(np.sqrt(np.mean(np.sum(res_px[idx] ** 2, axis=1))))
    cov = _covariance(st, X, idx)
    if angle < min_angle_deg:
        return TriangulationResult(X, False, f"inlier rays meet at {angle:.2f} deg < {min_angle_deg} deg",
                                   res_px, inliers, rms, cov, angle)
    return TriangulationResult(X, True, "", res_px, inliers, rms, cov, angle)


def _covariance(st: _Stack, X: np.ndarray, idx: np.ndarray) -> np.ndarray:
    h = 1e-6 * max(1.0, float(np.linalg.norm(X - st.centers[idx].mean(0))))
    r0 = st.residuals(X, idx)
    J = np.empty((len(r0), 3))
    for j in range(3):
        e = np.zeros(3)
        e[j] = h
        J[:, j] = (st.residuals(X + e, idx) - st.residuals(X - e, idx)) / (2 * h)
    dof = len(r0) - 3
    s0sq = float(r0 @ r0 / dof) if dof > 0 else 1.0
    try:
        return s0sq * np.linalg.inv(J.T @ J)
    except np.linalg.LinAlgError:
        return np.full((3, 3), np.nan)
