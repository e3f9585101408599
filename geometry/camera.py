"""Pinhole cameras with OpenCV-model lens distortion.

Intrinsics are stored in the OpenCV pixel convention (centre of the top-left pixel is (0, 0)); readers
convert from each format's convention (COLMAP and Metashape put that centre at (0.5, 0.5)).
Distortion follows OpenCV / COLMAP ``FULL_OPENCV`` order: k1, k2, p1, p2, k3 (missing ones are 0).
Camera frame: x right, y down, z forward (viewing direction).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class Camera:
    """Intrinsics of one physical camera. Focal lengths and principal point in pixels."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    dist: tuple[float, ...] = field(default=(0.0, 0.0, 0.0, 0.0, 0.0))  # k1, k2, p1, p2, k3

    def __post_init__(self) -> None:
        if self.width <= 0 or self.height <= 0:
            raise ValueError("camera size must be positive")
        if not (self.fx > 0 and self.fy > 0):
            raise ValueError("focal lengths must be positive")
        d = tuple(float(v) for v in self.dist) + (0.0,) * max(0, 5 - len(self.dist))
        object.__setattr__(self, "dist", d[:5])

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def has_distortion(self) -> bool:
        return any(v != 0.0 for v in self.dist)

    def distort_normalized(self, xn: np.ndarray) -> np.ndarray:
        """Apply the distortion to normalised coordinates (n, 2) -> (n, 2)."""
        k1, k2, p1, p2, k3 = self.dist
        x, y = xn[:, 0], xn[:, 1]
        r2 = x * x + y * y
        radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        return np.stack([xd, yd], axis=1)

    def undistort_normalized(self, xd: np.ndarray, iterations: int = 20) -> np.ndarray:
        """Invert :meth:`distort_normalized` by fixed-point iteration (accurate to ~1e-12 for
        the moderate distortions of survey cameras)."""
        if not self.has_distortion:
            return np.array(xd, float)
        x = np.array(xd, float)
        for _ in range(iterations):
            err = self.distort_normalized(x) - xd
            x = x - err
        return x

    def project(self, points_in_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixels (n, 2) of camera-frame points (n, 3), and a mask of points in front (z > 0)."""
        P = np.asarray(points_in_cam, float).reshape(-1, 3)
        z = P[:, 2]
        front = z > 1e-12
        zs = np.where(front, z, 1.0)
        xn = P[:, :2] / zs[:, None]
        if self.has_distortion:
            xn = self.distort_normalized(xn)
        uv = np.empty_like(xn)
        uv[:, 0] = self.fx * xn[:, 0] + self.cx
        uv[:, 1] = self.fy * xn[:, 1] + self.cy
        return uv, front

    def pixel_to_ray(self, uv: np.ndarray) -> np.ndarray:
        """Unit viewing rays (n, 3) in the camera frame for pixels (n, 2)."""
        uv = np.asarray(uv, float).reshape(-1, 2)
        xd = np.stack([(uv[:, 0] - self.cx) / self.fx, (uv[:, 1] - self.cy) / self.fy], axis=1)
        xn = self.undistort_normalized(xd)
        rays = np.column_stack([xn, np.ones(len(xn))])
        return rays / np.linalg.norm(rays, axis=1, keepdims=True)

    def in_image(self, uv: np.ndarray, border: float = 0.0) -> np.ndarray:
        uv = np.asarray(uv, float).reshape(-1, 2)
        return ((uv[:, 0] >= -0.5 + border) & (uv[:, 0] <= self.width - 0.5 - border)
                & (uv[:, 1] >= -0.5 + border) & (uv[:, 1] <= self.height - 0.5 - border))
