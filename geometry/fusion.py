"""Cloud colorization (seed paper 4.2): fuse per-image marker probabilities into one score per point.

Fusion rule (documented contract)
---------------------------------
Every point ``i`` is projected into every image ``k``; where it is *visible* (in front, inside the image
and passing the depth test of :mod:`geometry.visibility`), the image's probability map is sampled
bilinearly at the projected pixel, giving ``p_ik`` in [0, 1]. Each such view gets the weight

    w_ik = (fx * fy / z_ik^2) * cos(theta_ik)      if cos(theta_ik) >= min_cos, else 0

i.e. the number of image pixels that one unit of surface area around the point covers in that image
(``z`` = camera depth, ``theta`` = angle between the point's normal and the direction to the camera).
Close and frontal views see the surface at a finer sampling and so weigh more; grazing views
(``cos theta < min_cos``) are ignored. Without normals ``cos theta`` is taken as 1. The fused score is
the weighted mean

    s_i = sum_k w_ik p_ik / sum_k w_ik        (0 where no image sees the point),

which stays a probability, is not pushed up by the mere number of views, and lets one close frontal
view dominate many distant oblique ones. ``weight`` (sum of w) and ``n_views`` are returned too, so a
caller can ignore points with too little evidence.

Everything is vectorised over points with numpy; one image is processed at a time, so memory stays
at a few arrays of the cloud's length however many images there are.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Iterable, Optional

import numpy as np

from .camera import Camera
from .transforms import Rigid3
from .visibility import DepthMap, visible_points


@dataclass(frozen=True)
class FusionView:
    """One image's inputs: its camera, pose, probability map (h, w) float in [0, 1] covering the whole
    image at any resolution (pixel centres aligned as in ``cv2.resize``) and an optional depth map."""

    camera: Camera
    cam_from_world: Rigid3
    probability: np.ndarray
    depth_map: Optional[DepthMap] = None


@dataclass(frozen=True)
class FusionResult:
    """score: (n,) fused probability; weight: (n,) sum of view weights; n_views: (n,) int32."""

    score: np.ndarray
    weight: np.ndarray
    n_views: np.ndarray


def sample_bilinear(image: np.ndarray, uv: np.ndarray, image_size: tuple[int, int]) -> np.ndarray:
    """Bilinear samples (n,) of ``image`` (h, w) at full-image pixels ``uv`` (n, 2) of an image of
    ``image_size`` = (width, height); ``image`` may be at a lower resolution (cv2.resize alignment)."""
    h, w = image.shape
    W, H = image_size
    x = (uv[:, 0] + 0.5) * (w / W) - 0.5
    y = (uv[:, 1] + 0.5) * (h / H) - 0.5
    x = np.clip(x, 0.0, w - 1.0)
    y = np.clip(y, 0.0, h - 1.0)
    x0 = np.minimum(np.floor(x).astype(np.int64), max(w - 2, 0))
    y0 = np.minimum(np.floor(y).astype(np.int64), max(h - 2, 0))
    x1 = np.minimum(x0 + 1, w - 1)
    y1 = np.minimum(y0 + 1, h - 1)
    fx = x - x0
    fy = y - y0
    img = np.asarray(image, dtype=np.float32)
    top = img[y0, x0] * (1 - fx) + img[y0, x1] * fx
    bot = img[y1, x0] * (1 - fx) + img[y1, x1] * fx
    return top * (1 - fy) + bot * fy


def view_weights(points_in_cam: np.ndarray, camera: Camera, normals_in_cam: Optional[np.ndarray],
                 min_cos: float) -> np.ndarray:
    """The weight ``fx fy cos(theta) / z^2`` of each point (n,) in one view (see module docstring)."""
    z = points_in_cam[:, 2]
    w = camera.fx * camera.fy / np.maximum(z, 1e-12) ** 2
    if normals_in_cam is not None:
        to_cam = -points_in_cam / np.maximum(np.linalg.norm(points_in_cam, axis=1, keepdims=True), 1e-12)
        cos = np.abs(np.einsum("ij,ij->i", normals_in_cam, to_cam))  # normals' sign is arbitrary in clouds
        w = np.where(cos >= min_cos, w * cos, 0.0)
    return w


def fuse_scores(points_in_world: np.ndarray, views: Iterable[FusionView],
                normals_in_world: Optional[np.ndarray] = None, min_cos: float = 0.2,
                rel_tol: float = 0.02, abs_tol: float = 0.0) -> FusionResult:
    """Fuse probability maps of ``views`` into a per-point score (see the module docstring).

    points_in_world: (n, 3) model frame; normals_in_world: (n, 3) unit normals or None.
    ``rel_tol``/``abs_tol``: depth-test tolerances (see :func:`visible_points`).
    """
    P = np.asarray(points_in_world, float).reshape(-1, 3)
    N = None if normals_in_world is None else np.asarray(normals_in_world, float).reshape(-1, 3)
    num = np.zeros(len(P))
    den = np.zeros(len(P))
    n_views = np.zeros(len(P), np.int32)
    for view in views:
        vis = visible_points(P, view.camera, view.cam_from_world, view.depth_map, rel_tol=rel_tol,
                             abs_tol=abs_tol)
        idx = np.flatnonzero(vis.visible)
        if len(idx) == 0:
            continue
        Pc = view.cam_from_world(P[idx])
        Nc = None if N is None else N[idx] @ view.cam_from_world.R.T
        w = view_weights(Pc, view.camera, Nc, min_cos)
        p = sample_bilinear(view.probability, vis.uv[idx], (view.camera.width, view.camera.height))
        num[idx] += w * p
        den[idx] += w
        n_views[idx] += (w > 0).astype(np.int32)
    score = np.divide(num, den, out=np.zeros_like(num), where=den > 0)
    return FusionResult(np.clip(score, 0.0, 1.0), den, n_views)
