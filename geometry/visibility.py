"""Which model points an image really sees: a depth test against a mesh or a point z-buffer.

"Inside the frustum" is not enough: a point behind a wall projects into the image too. Both tests here
build a *depth map* for one image at a reduced resolution and accept a point when its camera depth is
not farther than the depth map at its pixel (plus a tolerance).

Conventions: pixels in the OpenCV convention of the full image (centre of the top-left pixel = (0, 0));
a depth map of ``scale`` < 1 has its pixel centres aligned as in ``cv2.resize``: depth-map pixel
``(j, i)`` covers image pixel ``((j + 0.5) / scale - 0.5, (i + 0.5) / scale - 0.5)``. Depth is the camera
frame z coordinate (model units), ``inf`` where the map saw nothing.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np
from scipy import ndimage

from .camera import Camera
from .transforms import Rigid3


@dataclass(frozen=True)
class DepthMap:
    """Camera-frame depth (z, model units) on a grid of ``scale`` x the image resolution.

    depth: (h, w) float32, ``inf`` where empty. scale: depth-map pixels per image pixel (<= 1).
    """

    depth: np.ndarray
    scale: float

    def lookup(self, uv: np.ndarray) -> np.ndarray:
        """Depth (n,) at the depth-map cell nearest to each image pixel ``uv`` (n, 2); ``inf`` outside."""
        uv = np.asarray(uv, float).reshape(-1, 2)
        h, w = self.depth.shape
        fin = np.isfinite(uv).all(axis=1)
        j = np.floor((np.where(fin, uv[:, 0], -1e9) + 0.5) * self.scale)
        i = np.floor((np.where(fin, uv[:, 1], -1e9) + 0.5) * self.scale)
        inside = fin & (j >= 0) & (j < w) & (i >= 0) & (i < h)
        out = np.full(len(uv), np.inf)
        out[inside] = self.depth[i[inside].astype(np.int64), j[inside].astype(np.int64)]
        return out


def normalized_bounds(camera: Camera, margin: float = 0.05) -> np.ndarray:
    """(x0, y0, x1, y1): extremes of the undistorted normalised coordinates of the image border,
    widened by ``margin`` of the span. Points outside cannot project into the image, and checking it
    *before* applying the distortion polynomial avoids its fold-back far off-axis."""
    t = np.linspace(0.0, 1.0, 33)
    W, H = camera.width - 0.5, camera.height - 0.5
    bx = -0.5 + t * (W + 0.5)
    by = -0.5 + t * (H + 0.5)
    border = np.concatenate([np.column_stack([bx, np.full_like(t, -0.5)]), np.column_stack([bx, np.full_like(t, H)]),
                             np.column_stack([np.full_like(t, -0.5), by]), np.column_stack([np.full_like(t, W), by])])
    xn = camera.undistort_normalized(np.column_stack([(border[:, 0] - camera.cx) / camera.fx,
                                                      (border[:, 1] - camera.cy) / camera.fy]))
    (x0, y0), (x1, y1) = xn.min(0), xn.max(0)
    mx, my = margin * (x1 - x0), margin * (y1 - y0)
    return np.array([x0 - mx, y0 - my, x1 + mx, y1 + my])


def project_checked(camera: Camera, points_in_cam: np.ndarray, bounds: np.ndarray | None = None
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Pixels (n, 2) of camera-frame points (n, 3) and a mask of those in front of the camera, inside
    the image and within :func:`normalized_bounds` (pixels of the others are NaN)."""
    P = np.asarray(points_in_cam, float).reshape(-1, 3)
    b = normalized_bounds(camera) if bounds is None else bounds
    z = P[:, 2]
    ok = z > 1e-12
    zs = np.where(ok, z, 1.0)
    x, y = P[:, 0] / zs, P[:, 1] / zs
    ok &= (x >= b[0]) & (x <= b[2]) & (y >= b[1]) & (y <= b[3])
    uv = np.full((len(P), 2), np.nan)
    if ok.any():
        uv[ok] = camera.project(P[ok])[0]
        ok[ok] = camera.in_image(uv[ok])
    return uv, ok


def depth_map_shape(camera: Camera, max_side: int) -> tuple[float, int, int]:
    """(scale, h, w) of a depth map whose longer side is at most ``max_side`` pixels."""
    scale = min(1.0, float(max_side) / max(camera.width, camera.height))
    return scale, max(1, int(round(camera.height * scale))), max(1, int(round(camera.width * scale)))


def _cell_centres(camera: Camera, scale: float, h: int, w: int) -> np.ndarray:
    jj, ii = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    return np.column_stack([(jj.ravel() + 0.5) / scale - 0.5, (ii.ravel() + 0.5) / scale - 0.5])


def mesh_depth_map(raycasting_scene, camera: Camera, cam_from_world: Rigid3, max_side: int = 640) -> DepthMap:
    """Render the depth of a mesh by casting one ray per depth-map cell (Open3D ``RaycastingScene``).

    ``raycasting_scene``: an ``open3d.t.geometry.RaycastingScene`` holding the mesh in the model frame
    (see :func:`geometry.raycast.make_raycasting_scene`). Lens distortion is honoured (rays come from
    :meth:`Camera.pixel_to_ray`).
    """
    import open3d as o3d

    scale, h, w = depth_map_shape(camera, max_side)
    rays_cam = camera.pixel_to_ray(_cell_centres(camera, scale, h, w))          # unit, camera frame
    world_from_cam = cam_from_world.inverse()
    dirs = rays_cam @ world_from_cam.R.T
    origins = np.broadcast_to(world_from_cam.t, dirs.shape)
    rays = np.concatenate([origins, dirs], axis=1).astype(np.float32)
    t_hit = raycasting_scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy().astype(np.float64)
    depth = t_hit * rays_cam[:, 2]                                               # distance -> z
    return DepthMap(depth.reshape(h, w).astype(np.float32), scale)


def zbuffer_depth_map(points_in_world: np.ndarray, camera: Camera, cam_from_world: Rigid3,
                      max_side: int = 320, fill_px: int = 1) -> DepthMap:
    """Point-splat z-buffer: the nearest point depth per depth-map cell, then a ``(2 fill_px + 1)``-cell
    minimum filter that closes the holes between the splats of a sparse foreground.

    Choose ``max_side`` so that a cell is at least about one point spacing wide on the surfaces of
    interest; otherwise background points shine through the gaps of the foreground.
    """
    scale, h, w = depth_map_shape(camera, max_side)
    P = cam_from_world(np.asarray(points_in_world, float).reshape(-1, 3))
    uv, ok = project_checked(camera, P)
    j = np.clip(np.floor((uv[ok, 0] + 0.5) * scale).astype(np.int64), 0, w - 1)
    i = np.clip(np.floor((uv[ok, 1] + 0.5) * scale).astype(np.int64), 0, h - 1)
    depth = np.full(h * w, np.inf, dtype=np.float64)
    np.minimum.at(depth, i * w + j, P[ok, 2])
    depth = depth.reshape(h, w)
    if fill_px > 0:
        depth = ndimage.minimum_filter(depth, size=2 * fill_px + 1, mode="nearest")
    return DepthMap(depth.astype(np.float32), scale)


@dataclass(frozen=True)
class Visibility:
    """Per-point result of projecting (n,) points into one image.

    uv: (n, 2) pixels (NaN for points that cannot project into the image); depth: (n,) camera z;
    visible: (n,) bool (in front, inside the image, and passing the depth test if one was given).
    """

    uv: np.ndarray
    depth: np.ndarray
    visible: np.ndarray


def visible_points(points_in_world: np.ndarray, camera: Camera, cam_from_world: Rigid3,
                   depth_map: Optional[DepthMap] = None, rel_tol: float = 0.01, abs_tol: float = 0.0,
                   border_px: float = 0.0) -> Visibility:
    """Project points (n, 3, model frame) into an image and test them against ``depth_map``.

    A point is visible when it is in front of the camera, inside the image (``border_px`` away from its
    edge) and ``z <= d * (1 + rel_tol) + abs_tol`` where ``d`` is the depth map at its pixel. Without a
    depth map only the frustum test is made. ``abs_tol``: model units, a scalar or one per point (n,).
    """
    P = cam_from_world(np.asarray(points_in_world, float).reshape(-1, 3))
    uv, vis = project_checked(camera, P)
    if border_px > 0:
        vis[vis] = camera.in_image(uv[vis], border=border_px)
    if depth_map is not None and vis.any():
        d = depth_map.lookup(uv[vis])
        idx = np.flatnonzero(vis)
        tol = np.broadcast_to(np.asarray(abs_tol, float), (len(P),))[idx]
        vis[idx] = P[idx, 2] <= d * (1.0 + rel_tol) + tol
    return Visibility(uv, P[:, 2], vis)
