"""Bundle adjustment of marker points *and* camera poses from marker observations (seed paper 5.1).

Markers alone rarely constrain a pose (an image sees one to three markers), so every pose is tied to
its reconstruction value by a prior: the adjusted pose is ``R = exp([w]x) R0`` with camera centre
``C = C0 + dc``, and the priors are the residuals ``w / sigma_rot`` and ``dc / sigma_pos``. These priors
also fix the gauge (datum), so no camera is held fixed. Intrinsics are fixed.

Unknowns: 6 per image (w in radians, dc in model units) and 3 per marker (model frame). Residuals:
whitened reprojection errors ``(project(X_j; pose_i) - uv_ij) / sigma_ij`` (2 per observation) and the
6 prior residuals per image. Solved with ``scipy.optimize.least_squares`` (trf, a sparse Jacobian
pattern, finite differences, ``x_scale="jac"``); the robust ``loss`` applies to every residual, and the
priors stay in its quadratic zone as long as the poses move by less than ``f_scale`` sigmas.

Marker covariance: the 3x3 blocks of ``s0^2 (J^T J)^-1`` over all unknowns (so pose uncertainty is
included), with ``J`` the loss-weighted Jacobian at the solution and ``s0^2 = sum r^2 / redundancy``.
Dense inverse: meant for marker-sized problems (hundreds of images, tens of markers).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import lil_matrix
from scipy.spatial.transform import Rotation

from .camera import Camera
from .transforms import Rigid3
from .triangulate import project_batch


@dataclass(frozen=True)
class MarkerObservation:
    """Marker ``point`` index seen in image ``image`` (a key of ``poses``) at pixel ``uv`` (2,)."""

    point: int
    image: str
    uv: np.ndarray
    sigma_px: float = 1.0


@dataclass
class AdjustResult:
    """points (m, 3) model frame; poses: image -> adjusted cam_from_world; rms_px (m,) per-marker RMS
    of the reprojection residual lengths; covariance (m, 3, 3) model units^2; residuals_px (n_obs, 2);
    success and message from the solver; s0 the a-posteriori standard deviation of unit weight."""

    points: np.ndarray
    poses: dict[str, Rigid3]
    rms_px: np.ndarray
    covariance: np.ndarray
    residuals_px: np.ndarray
    success: bool
    message: str
    s0: float
    n_evaluations: int


def bundle_adjust(points: np.ndarray, observations: list[MarkerObservation], poses: dict[str, Rigid3],
                  cameras: dict[str, Camera], sigma_rot_rad: float = 1e-3, sigma_pos: float = 0.01,
                  loss: str = "huber", f_scale: float = 3.0, max_nfev: int = 200, ftol: float = 1e-6) -> AdjustResult:
    """Adjust marker points (m, 3) and the poses of the images that observe them.

    ``poses`` and ``cameras`` map image keys to cam_from_world and to the image's camera;
    ``sigma_rot_rad`` / ``sigma_pos`` (model units) are the 1-sigma priors on the poses; ``ftol`` and
    ``max_nfev``: stopping rules of ``least_squares`` (relative cost change, evaluations).
    """
    X0 = np.asarray(points, float).reshape(-1, 3)
    m = len(X0)
    if not observations:
        raise ValueError("bundle adjustment needs observations")
    if not (sigma_rot_rad > 0 and sigma_pos > 0):
        raise ValueError("pose prior sigmas must be positive")
    names = sorted({o.image for o in observations})
    img_index = {n: i for i, n in enumerate(names)}
    n_img = len(names)
    R0 = np.stack([poses[n].R for n in names])
    C0 = np.stack([poses[n].center for n in names])
    oi = np.array([img_index[o.image] for o in observations])
    pj = np.array([o.point for o in observations])
    if pj.min() < 0 or pj.max() >= m:
        raise ValueError("observation refers to a point index out of range")
    uv = np.array([np.asarray(o.uv, float).reshape(2) for o in observations])
    sig = np.array([float(o.sigma_px) for o in observations])
    f = np.array([[cameras[n].fx, cameras[n].fy] for n in names])[oi]
    c = np.array([[cameras[n].cx, cameras[n].cy] for n in names])[oi]
    dist = np.array([cameras[n].dist for n in names])[oi]
    n_obs = len(observations)

    def unpack(x):
        w = x[: 3 * n_img].reshape(-1, 3)
        dc = x[3 * n_img: 6 * n_img].reshape(-1, 3)
        X = x[6 * n_img:].reshape(-1, 3)
        R = Rotation.from_rotvec(w).as_matrix() @ R0
        C = C0 + dc
        t = -np.einsum("kij,kj->ki", R, C)
        return w, dc, X, R, t

    def fun(x):
        w, dc, X, R, t = unpack(x)
        pix, _ = project_batch(X[pj], R[oi], t[oi], f, c, dist)
        r = ((pix - uv) / sig[:, None]).ravel()
        return np.concatenate([r, (w / sigma_rot_rad).ravel(), (dc / sigma_pos).ravel()])

    A = lil_matrix((2 * n_obs + 6 * n_img, 6 * n_img + 3 * m), dtype=int)
    rows = np.arange(n_obs)
    for k in range(3):
        for r in (2 * rows, 2 * rows + 1):
            A[r, 3 * oi + k] = 1
            A[r, 3 * n_img + 3 * oi + k] = 1
            A[r, 6 * n_img + 3 * pj + k] = 1
    for k in range(6 * n_img):
        A[2 * n_obs + k, k] = 1
    x0 = np.concatenate([np.zeros(6 * n_img), X0.ravel()])
    sol = least_squares(fun, x0, jac_sparsity=A, x_scale="jac", loss=loss, f_scale=f_scale, method="trf",
                        max_nfev=max_nfev, ftol=ftol)
    w, dc, X, R, t = unpack(sol.x)
    pix, _ = project_batch(X[pj], R[oi], t[oi], f, c, dist)
    res_px = pix - uv
    rms = np.full(m, np.nan)
    for j in range(m):
        sel = pj == j
        if sel.any():
            rms[j] = float(np.sqrt(np.mean(np.sum(res_px[sel] ** 2, axis=1))))
    r_all = fun(sol.x)
    redundancy = max(len(r_all) - len(sol.x), 1)
    s0sq = float(r_all @ r_all / redundancy)
    # sol.jac is the loss-weighted Jacobian: J^T J is the Gauss-Newton Hessian of the robust cost
    J = sol.jac.toarray() if hasattr(sol.jac, "toarray") else np.asarray(sol.jac)
    cov = np.full((m, 3, 3), np.nan)
    try:
        Ninv = np.linalg.inv(J.T @ J) * s0sq
        for j in range(m):
            s = 6 * n_img + 3 * j
            cov[j] = Ninv[s:s + 3, s:s + 3]
    except np.linalg.LinAlgError:
        pass
    new_poses = {n: Rigid3(R[i], t[i]) for n, i in img_index.items()}
    return AdjustResult(X, new_poses, rms, cov, res_px, bool(sol.success), str(sol.message),
                        float(np.sqrt(s0sq)), int(sol.nfev))

