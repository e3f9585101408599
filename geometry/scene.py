"""The small in-memory scene every reader produces and every stage reads.

Frames: ``cam_from_world`` maps model ("world" of the reconstruction) points into the camera frame;
the reconstruction frame is called the *model* frame, and ``world_from_model`` (a Sim3) takes it to
the surveyed (local Cartesian) frame.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from .camera import Camera
from .transforms import Rigid3


@dataclass
class ImageRecord:
    """One registered image: its file name (relative to the image folder), camera id and pose."""

    name: str
    camera_id: int
    cam_from_world: Rigid3

    @property
    def center(self) -> np.ndarray:
        return self.cam_from_world.center


@dataclass
class Scene:
    """Cameras, posed images and (optionally) a point cloud, in the model frame.

    points: (n, 3) float64; colors: (n, 3) uint8 RGB; normals: (n, 3) float64, or None.
    mesh_path: optional path to a triangle mesh of the same model frame.
    """

    cameras: dict[int, Camera]
    images: dict[str, ImageRecord]
    points: Optional[np.ndarray] = None
    colors: Optional[np.ndarray] = None
    normals: Optional[np.ndarray] = None
    mesh_path: Optional[str] = None
    meta: dict = field(default_factory=dict)

    def camera_of(self, image_name: str) -> Camera:
        return self.cameras[self.images[image_name].camera_id]

    def project(self, image_name: str, points_in_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixels (n, 2) of model-frame points in an image, and a mask of points in front and inside."""
        rec = self.images[image_name]
        cam = self.cameras[rec.camera_id]
        uv, front = cam.project(rec.cam_from_world(np.asarray(points_in_world, float).reshape(-1, 3)))
        return uv, front & cam.in_image(uv)
