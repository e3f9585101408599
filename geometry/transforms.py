"""Rigid and similarity transforms, named ``target_from_source`` (COLMAP style).

``Rigid3``: x_target = R @ x_source + t. ``Sim3``: x_target = s * R @ x_source + t. Both are float64,
act on (3,) or (n, 3) arrays, compose with ``@`` (``a_from_c = a_from_b @ b_from_c``) and invert exactly.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def _check_translation(t) -> np.ndarray:
    t = np.asarray(t, dtype=np.float64).reshape(3)
    if not np.all(np.isfinite(t)):
        raise ValueError("translation has non-finite entries")
    return t


def _check_rotation(R: np.ndarray, tol: float = 1e-6) -> np.ndarray:
    R = np.asarray(R, dtype=np.float64).reshape(3, 3)
    if not np.all(np.isfinite(R)):
        raise ValueError("rotation has non-finite entries")
    if np.abs(R @ R.T - np.eye(3)).max() > tol or abs(np.linalg.det(R) - 1.0) > tol:
        raise ValueError("matrix is not a rotation (R R^T != I or det R != 1)")
    return R


def project_to_rotation(M: np.ndarray) -> np.ndarray:
    """Nearest rotation matrix to ``M`` (Frobenius norm), via SVD with det = +1."""
    U, _, Vt = np.linalg.svd(np.asarray(M, float))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    return U @ D @ Vt


def quat_wxyz_to_matrix(q) -> np.ndarray:
    """Rotation matrix of a Hamilton quaternion (w, x, y, z); it is normalised first."""
    w, x, y, z = np.asarray(q, float) / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def matrix_to_quat_wxyz(R: np.ndarray) -> np.ndarray:
    """Hamilton quaternion (w, x, y, z) with w >= 0 of a rotation matrix."""
    from scipy.spatial.transform import Rotation

    x, y, z, w = Rotation.from_matrix(np.asarray(R, float)).as_quat()
    q = np.array([w, x, y, z])
    return q if q[0] >= 0 else -q


@dataclass(frozen=True)
class Rigid3:
    """x_target = R @ x_source + t (metres or model units)."""

    R: np.ndarray
    t: np.ndarray

    def __post_init__(self) -> None:
        object.__setattr__(self, "R", _check_rotation(self.R))
        object.__setattr__(self, "t", _check_translation(self.t))

    @classmethod
    def identity(cls) -> "Rigid3":
        return cls(np.eye(3), np.zeros(3))

    @classmethod
    def from_matrix(cls, M: np.ndarray) -> "Rigid3":
        M = np.asarray(M, float)
        return cls(M[:3, :3], M[:3, 3])

    def __call__(self, x: np.ndarray) -> np.ndarray:
        x = np.asarray(x, dtype=np.float64)
        return x @ self.R.T + self.t

    def inverse(self) -> "Rigid3":
        return Rigid3(self.R.T, -self.R.T @ self.t)

    def __matmul__(self, other: "Rigid3") -> "Rigid3":
        if isinstance(other, Sim3):
            return Sim3.from_rigid(self) @ other
        return Rigid3(self.R @ other.R, self.R @ other.t + self.t)

    @property
    def matrix(self) -> np.ndarray:
        M = np.eye(4)
        M[:3, :3], M[:3, 3] = self.R, self.t
        return M

    @property
    def center(self) -> np.ndarray:
        """For a cam_from_world pose: the camera centre in world coordinates."""
        return -self.R.T @ self.t


@dataclass(frozen=True)
class Sim3:
    """x_target = scale * R @ x_source + t: the 7-parameter similarity (Helmert) transform."""

    scale: float
    R: np.ndarray
    t: np.ndarray

    def __post_init__(self) -> None:
        s = float(self.scale)
        if not (np.isfinite(s) and s > 0):
            raise ValueError(f"similarity scale must be finite and positive, got {s}")
        object.__setattr__(self, "scale", s)
        object.__setattr__(self, "R", _check_rotation(self.R))
        object.__setattr__(self, "t", _check_translation(self.t))

    @classmethod
    def identity(cls) -> "Sim3":
        return cls(1.0, np.eye(3), np.zeros(3))

    @classmethod
    def from_rigid(cls, rigid: Rigid3, scale: float = 1.0) -> "Sim3":
        return cls(scale, rigid.R, rigid.t)

    @classmethod
    def from_matrix(cls, M: np.ndarray) -> "Sim3":
        """From a 4x4 matrix [[s R, t], [0, 1]]."""
        M = np.asarray(M, float)
        A = M[:3, :3]
        s = float(np.cbrt(np.linalg.det(A)))
        if not s > 0:
            raise ValueError("matrix is not a proper similarity (det <= 0)")
        return cls(s, A / s, M[:3, 3])

    def __call__(self, x: np.ndarray) -> np.ndarray:
        x = np.asarray(x, dtype=np.float64)
        return self.scale * (x @ self.R.T) + self.t

    def inverse(self) -> "Sim3":
        inv_s = 1.0 / self.scale
        return Sim3(inv_s, self.R.T, -inv_s * (self.R.T @ self.t))

    def __matmul__(self, other: "Sim3 | Rigid3") -> "Sim3":
        if isinstance(other, Rigid3):
            other = Sim3.from_rigid(other)
        return Sim3(self.scale * other.scale, self.R @ other.R, self.scale * (self.R @ other.t) + self.t)

    @property
    def matrix(self) -> np.ndarray:
        M = np.eye(4)
        M[:3, :3], M[:3, 3] = self.scale * self.R, self.t
        return M

    def to_dict(self) -> dict:
        return {"scale": self.scale, "rotation": self.R.tolist(), "translation": self.t.tolist(),
                "matrix": self.matrix.tolist()}

    @classmethod
    def from_dict(cls, d: dict) -> "Sim3":
        return cls(float(d["scale"]), np.asarray(d["rotation"], float), np.asarray(d["translation"], float))
