"""A drone-like camera network around one corner of the synthetic pier.

Frames: poses are ``cam_from_site`` (:class:`geometry.transforms.Rigid3`), site frame as in
:mod:`cpdetect.synth_site_geometry` (metres, z up); camera frame x right, y down, z forward.

The drone flies horizontal strips at several heights along a path that keeps ``distance`` metres from
the pier's shaft (the outward offset of its cross-section, with arcs round its vertices), centred on one
corner. Stations along a strip are spaced for ``forward_overlap`` of the image footprint, strips for
``side_overlap``; every other strip looks slightly up or down (obliques), and every pose has a small
random jitter like a hand-flown drone.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from geometry.camera import Camera
from geometry.transforms import Rigid3

SENSOR_WIDTH_MM = 36.0  # full-frame, as the DJI Zenmuse P1 of the paper


def survey_camera(width: int, height: int, focal_mm: float = 35.0, distortion: bool = False,
                  rng: np.random.Generator | None = None) -> Camera:
    """A full-frame ``focal_mm`` camera at ``width`` x ``height`` pixels (OpenCV convention).

    The principal point sits a few pixels (scaled with the image) off the centre; with ``distortion``
    a moderate radial-tangential distortion (k1, k2, p1, p2) in normalised coordinates, the same for
    every image size."""
    f = focal_mm / SENSOR_WIDTH_MM * width
    s = width / 1024.0
    dx, dy = (1.7 * s, -1.1 * s) if rng is None else tuple(rng.uniform(-3, 3, 2) * s)
    dist = (-0.035, 0.012, 2.0e-4, -1.5e-4, 0.0) if distortion else (0.0,) * 5
    return Camera(int(width), int(height), f, f, (width - 1) / 2.0 + dx, (height - 1) / 2.0 + dy, dist)


def look_pose(center: np.ndarray, forward: np.ndarray, roll_rad: float = 0.0) -> Rigid3:
    """cam_from_site for a camera at ``center`` looking along ``forward`` with the image's up towards
    +z (then rolled by ``roll_rad`` about the viewing axis)."""
    z = np.asarray(forward, float) / np.linalg.norm(forward)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    c, s = math.cos(roll_rad), math.sin(roll_rad)
    x, y = c * x + s * y, -s * x + c * y
    R = np.stack([x, y, z])
    return Rigid3(R, -R @ np.asarray(center, float))


@dataclass(frozen=True)
class OffsetPath:
    """Polyline (n, 2) at constant distance from a convex footprint, with inward look directions."""

    points: np.ndarray
    inward: np.ndarray
    arclength: np.ndarray

    def at(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        s = np.mod(s, self.arclength[-1])
        x = np.interp(s, self.arclength, self.points[:, 0])
        y = np.interp(s, self.arclength, self.points[:, 1])
        ix = np.interp(s, self.arclength, self.inward[:, 0])
        iy = np.interp(s, self.arclength, self.inward[:, 1])
        d = np.stack([ix, iy], axis=1)
        return np.stack([x, y], axis=1), d / np.linalg.norm(d, axis=1, keepdims=True)


def offset_path(footprint: np.ndarray, distance: float, step: float = 0.02) -> OffsetPath:
    """The closed curve at ``distance`` from a convex counter-clockwise polygon (k, 2)."""
    pts, inward = [], []
    k = len(footprint)
    for i in range(k):
        p, q = footprint[i], footprint[(i + 1) % k]
        e = (q - p) / np.linalg.norm(q - p)
        n = np.array([e[1], -e[0]])
        # arc round vertex p from the previous edge's normal to this one's
        pp = footprint[i - 1]
        e0 = (p - pp) / np.linalg.norm(p - pp)
        n0 = np.array([e0[1], -e0[0]])
        a0, a1 = math.atan2(n0[1], n0[0]), math.atan2(n[1], n[0])
        da = (a1 - a0 + math.pi) % (2 * math.pi) - math.pi
        m = max(2, int(abs(da) * distance / step))
        for t in np.linspace(0, 1, m, endpoint=False):
            a = a0 + t * da
            nn = np.array([math.cos(a), math.sin(a)])
            pts.append(p + distance * nn)
            inward.append(-nn)
        m = max(2, int(np.linalg.norm(q - p) / step))
        for t in np.linspace(0, 1, m, endpoint=False):
            pts.append(p + t * (q - p) + distance * n)
            inward.append(-n)
    pts.append(pts[0])
    inward.append(inward[0])
    pts_a, inward_a = np.array(pts), np.array(inward)
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pts_a, axis=0), axis=1))])
    return OffsetPath(pts_a, inward_a, arc)


@dataclass(frozen=True)
class NetworkSettings:
    """Survey flight parameters: distance (m) to the shaft, overlaps (fractions of the footprint),
    lowest strip height (m), oblique tilt of alternate strips (deg), pose jitter (m, deg)."""

    distance: float = 2.0
    forward_overlap: float = 0.72
    side_overlap: float = 0.45
    lowest_strip: float = 1.1
    oblique_deg: float = 10.0
    jitter_m: float = 0.05
    jitter_deg: float = 3.0


def strip_layout(n_images: int) -> tuple[int, int]:
    """(strips, stations per strip) for ``n_images`` (the last strip may be shorter)."""
    strips = max(1, int(round(math.sqrt(n_images * 0.75))))
    return strips, int(math.ceil(n_images / strips))


def survey_network(footprint: np.ndarray, corner_index: int, camera: Camera, n_images: int,
                   rng: np.random.Generator, settings: NetworkSettings = NetworkSettings()
                   ) -> list[tuple[str, Rigid3]]:
    """``n_images`` (name, cam_from_site) poses flying strips round vertex ``corner_index`` of the
    shaft footprint. Names are ``IMG_0001.jpg``... in flight order (strip by strip, alternating
    direction like a lawn-mower pattern)."""
    if n_images < 1:
        raise ValueError("need at least one image")
    path = offset_path(footprint, settings.distance)
    fov_w = settings.distance * camera.width / camera.fx
    fov_h = settings.distance * camera.height / camera.fy
    spacing = (1.0 - settings.forward_overlap) * fov_w
    rise = (1.0 - settings.side_overlap) * fov_h
    strips, per = strip_layout(n_images)
    # arc-length position of the corner on the path: the path point closest to the chosen vertex
    corner = footprint[corner_index % len(footprint)]
    s_corner = path.arclength[int(np.argmin(np.linalg.norm(path.points - corner, axis=1)))]
    poses: list[tuple[str, Rigid3]] = []
    count = 0
    for k in range(strips):
        z = settings.lowest_strip + k * rise
        tilt = math.radians(settings.oblique_deg) * (1 if k % 2 else -1) if strips > 1 else 0.0
        stations = np.arange(per) - 0.5 * (per - 1)
        if k % 2:
            stations = stations[::-1]
        for st in stations:
            if count >= n_images:
                break
            s = s_corner + st * spacing + rng.normal(0.0, settings.jitter_m)
            xy, inward = path.at(np.array([s]))
            center = np.array([xy[0, 0], xy[0, 1], z]) + rng.normal(0.0, settings.jitter_m, 3)
            yaw = math.radians(rng.normal(0.0, settings.jitter_deg))
            pitch = tilt + math.radians(rng.normal(0.0, settings.jitter_deg))
            c, s_ = math.cos(yaw), math.sin(yaw)
            d2 = np.array([c * inward[0, 0] - s_ * inward[0, 1], s_ * inward[0, 0] + c * inward[0, 1]])
            forward = np.array([d2[0] * math.cos(pitch), d2[1] * math.cos(pitch), math.sin(pitch)])
            roll = math.radians(rng.normal(0.0, 0.5 * settings.jitter_deg))
            count += 1
            poses.append((f"IMG_{count:04d}.jpg", look_pose(center, forward, roll)))
    return poses


__all__ = ["survey_camera", "look_pose", "offset_path", "OffsetPath", "NetworkSettings", "strip_layout",
           "survey_network", "SENSOR_WIDTH_MM"]
