"""Ray-mesh intersection for 2D detections (Open3D ``RaycastingScene``), model frame.

A detection at pixel ``uv`` of an image with pose ``cam_from_world`` defines the ray
``X(t) = C + t d`` (``C`` camera centre, ``d`` unit direction in the model frame, ``t`` >= 0 in model
units). Its first hit on the mesh is the detection's 3D position (seed paper section 5.1).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .camera import Camera
from .transforms import Rigid3


def load_mesh(path: str | Path):
    """Read a triangle mesh (PLY/OBJ/...) with Open3D; raises ``ValueError`` if it has no triangles."""
    import open3d as o3d

    mesh = o3d.io.read_triangle_mesh(str(path))
    if len(mesh.triangles) == 0:
        raise ValueError(f"{path}: no triangles in mesh (missing, unreadable or a point cloud)")
    return mesh


def make_raycasting_scene(mesh=None, vertices: np.ndarray | None = None, triangles: np.ndarray | None = None):
    """An ``open3d.t.geometry.RaycastingScene`` holding one mesh: a legacy ``TriangleMesh`` or
    ``vertices`` (n, 3) float and ``triangles`` (m, 3) int arrays."""
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    if mesh is not None:
        scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
    else:
        scene.add_triangles(o3d.core.Tensor(np.asarray(vertices, np.float32)),
                            o3d.core.Tensor(np.asarray(triangles, np.uint32)))
    return scene


def detection_rays(camera: Camera, cam_from_world: Rigid3, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Origins (n, 3) and unit directions (n, 3), model frame, of the viewing rays of pixels ``uv`` (n, 2)."""
    world_from_cam = cam_from_world.inverse()
    d = camera.pixel_to_ray(uv) @ world_from_cam.R.T
    return np.broadcast_to(world_from_cam.t, d.shape).copy(), d


@dataclass(frozen=True)
class RayHits:
    """points: (n, 3) first hits (NaN where missed); t: (n,) distances (inf where missed);
    normals: (n, 3) unit face normals of the hit triangles (NaN where missed); hit: (n,) bool."""

    points: np.ndarray
    t: np.ndarray
    normals: np.ndarray
    hit: np.ndarray


def cast(raycasting_scene, origins: np.ndarray, directions: np.ndarray) -> RayHits:
    """First intersections of rays (origins, unit directions; (n, 3) each, model frame) with the mesh."""
    import open3d as o3d

    o = np.asarray(origins, float).reshape(-1, 3)
    d = np.asarray(directions, float).reshape(-1, 3)
    if len(o) == 0:
        return RayHits(np.zeros((0, 3)), np.zeros(0), np.zeros((0, 3)), np.zeros(0, bool))
    ans = raycasting_scene.cast_rays(o3d.core.Tensor(np.concatenate([o, d], axis=1).astype(np.float32)))
    t = ans["t_hit"].numpy().astype(np.float64)
    hit = np.isfinite(t)
    pts = np.full_like(o, np.nan)
    pts[hit] = o[hit] + t[hit, None] * d[hit]
    normals = np.full_like(o, np.nan)
    n = ans["primitive_normals"].numpy().astype(np.float64)
    normals[hit] = n[hit] / np.maximum(np.linalg.norm(n[hit], axis=1, keepdims=True), 1e-12)
    return RayHits(pts, t, normals, hit)
