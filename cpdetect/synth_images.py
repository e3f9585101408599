"""Synthetic marker images with exact truth: markers of the three types rendered onto real photographs.

Each image is built in this order (the physical order of light, optics and sensor):

1. a random crop, flip and resize of a background photograph (:mod:`cpdetect.backgrounds`), with a
   small colour jitter;
2. confusers (:mod:`cpdetect.confusers`: windows, louvres, tiles, holes, text, railings, calibration
   grids, fiducials), tilted and placed away from the markers;
3. markers, each seen through a true 3D tilt: a pinhole camera K (virtual focal length) looks at a
   plane rotated by up to ``tilt_max_deg`` from facing the viewing ray, H = K [r1 r2 t]
   (:func:`cpdetect.markers.plane_homography`). Markers never overlap. Optional white printed margin,
   partial shine-through of the surface texture, and partial occlusion by a piece of another surface;
4. illumination: global level, a linear gradient and an optional soft cast shadow (multiplicative);
5. optics: defocus (disk or Gaussian) and motion blur;
6. sensor: Poisson-Gaussian noise, then 8-bit quantisation and JPEG (quality 60..95) or PNG.

Truth per marker: x, y = the projected aiming point (exact, OpenCV pixel convention), type, radius_px =
:func:`cpdetect.markers.projected_radius`. The mask marks pixels whose pattern coverage is >= 0.5 and
which are not covered by an occluder (the printed margin is not part of the mask).

Determinism: image ``i`` of seed ``s`` uses only ``numpy.random.default_rng([s, i])``, so the set made
with ``n = 20`` is a prefix of the set made with ``n = 40``, and parallel workers give the same bytes.
"""
from __future__ import annotations

import dataclasses
import logging
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import cv2
import numpy as np

from .backgrounds import SPLITS, BackgroundLibrary, list_backgrounds
from .confusers import CONFUSER_KINDS, draw_confuser
from .dataset import MARKERS_JSON, TrueMarker, image_record, write_markers_json
from .errors import InputError
from .fileio import cannot_write, write_bytes_atomic
from .markers import MarkerSpec, apply_homography, plane_homography, projected_radius, render_marker
from .types import MARKER_TYPES

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class SynthImageOptions:
    """Knobs of the image generator. Sizes in pixels, angles in degrees, probabilities in [0, 1].

    radius_max_frac: largest marker radius as a fraction of the image radius min(width, height) / 2.
    markers: (min, max) markers per image; empty_prob: chance of an image with no marker at all.
    noise_read: (min, max) Gaussian read-noise sigma (DN); noise_gain: max Poisson gain (DN per DN).
    """

    width: int = 640
    height: int = 480
    markers: tuple[int, int] = (1, 4)
    empty_prob: float = 0.15
    types: tuple[str, ...] = MARKER_TYPES
    radius_min_px: float = 8.0
    radius_max_frac: float = 1.0 / 3.0
    tilt_max_deg: float = 60.0
    focal_frac: tuple[float, float] = (0.7, 2.0)
    margin_prob: float = 0.4
    margin_frac: tuple[float, float] = (0.08, 0.5)
    contrast: tuple[float, float] = (35.0, 230.0)
    colour_prob: float = 0.15
    texture_prob: float = 0.3
    texture_max: float = 0.35
    occlusion_prob: float = 0.15
    border_cut_prob: float = 0.08
    occlusion_max: float = 0.4
    gradient_max: float = 0.5
    level: tuple[float, float] = (0.55, 1.25)
    shadow_prob: float = 0.3
    defocus_prob: float = 0.3
    defocus_max_px: float = 2.5
    motion_prob: float = 0.2
    motion_max_px: float = 7.0
    noise_read: tuple[float, float] = (0.5, 5.0)
    noise_gain: float = 0.4
    jpeg_quality: tuple[int, int] = (60, 95)
    image_format: str = "jpg"
    confusers: tuple[int, int] = (0, 4)
    confuser_kinds: tuple[str, ...] = CONFUSER_KINDS
    split: str = "all"
    supersample: int = 8

    def __post_init__(self) -> None:
        if self.width < 32 or self.height < 32:
            raise ValueError("image size must be at least 32x32")
        if not 0 <= self.markers[0] <= self.markers[1]:
            raise ValueError("markers must be (min, max) with 0 <= min <= max")
        if not 0 <= self.confusers[0] <= self.confusers[1]:
            raise ValueError("confusers must be (min, max) with 0 <= min <= max")
        if not 0 < self.radius_min_px <= self.radius_max_px:
            raise ValueError(f"radius range empty: {self.radius_min_px} .. {self.radius_max_px:.1f} px")
        if not 0 <= self.tilt_max_deg < 85:
            raise ValueError("tilt_max_deg must be in [0, 85)")
        if self.image_format not in ("jpg", "png"):
            raise ValueError("image_format must be 'jpg' or 'png'")
        if not 1 <= self.jpeg_quality[0] <= self.jpeg_quality[1] <= 100:
            raise ValueError("jpeg_quality must be (lo, hi) within 1..100")
        if self.split not in SPLITS:
            raise ValueError(f"split must be one of {', '.join(SPLITS)}")
        for t in self.types:
            if t not in MARKER_TYPES:
                raise ValueError(f"unknown marker type {t!r}")
        for k in self.confuser_kinds:
            if k not in CONFUSER_KINDS:
                raise ValueError(f"unknown confuser {k!r}; valid: {', '.join(CONFUSER_KINDS)}")
        for name in ("empty_prob", "colour_prob", "margin_prob", "texture_prob", "occlusion_prob",
                     "border_cut_prob", "shadow_prob", "defocus_prob", "motion_prob", "occlusion_max"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(f"{name} must be in [0, 1]")

    @property
    def radius_max_px(self) -> float:
        return self.radius_max_frac * min(self.width, self.height) / 2.0

    def to_dict(self) -> dict:
        return {f.name: (list(v) if isinstance(v := getattr(self, f.name), tuple) else v)
                for f in dataclasses.fields(self)}


@dataclass
class SynthImage:
    """One generated image: ``image`` uint8 BGR (H, W, 3), ``mask`` uint8 (H, W) 0/255, the markers'
    truth, and ``meta`` (background, category, blur, confusers, ...) for markers.json."""

    image: np.ndarray
    mask: np.ndarray
    markers: list[TrueMarker]
    meta: dict = field(default_factory=dict)
    jpeg_quality: int = 90


# ----------------------------------------------------------------------------------------- geometry

def _rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    return cv2.Rodrigues((np.asarray(axis, float) * angle).reshape(3, 1))[0]


def _align_z_to(d: np.ndarray) -> np.ndarray:
    """Smallest rotation taking the z axis onto unit vector ``d``."""
    z = np.array([0.0, 0.0, 1.0])
    axis = np.cross(z, d)
    s = np.linalg.norm(axis)
    if s < 1e-12:
        return np.eye(3)
    return _rotation(axis / s, math.atan2(s, float(np.dot(z, d))))


@dataclass(frozen=True)
class _Pose:
    """A plane seen by camera K: ``R`` (cam_from_plane rotation) and ``ray`` (unit viewing direction
    of the plane origin), ``tilt_deg`` = angle between the plane normal and the viewing ray."""

    R: np.ndarray
    ray: np.ndarray
    tilt_deg: float


def _random_pose(rng: np.random.Generator, K: np.ndarray, xy: tuple[float, float], tilt_max_deg: float) -> _Pose:
    ray = np.linalg.solve(K, np.array([xy[0], xy[1], 1.0]))
    ray /= np.linalg.norm(ray)
    # tilt: uniform in angle between facing the ray and tilt_max_deg, about a random axis
    tilt = math.radians(tilt_max_deg) * rng.random()
    azim = rng.uniform(0, 2 * math.pi)
    roll = rng.uniform(0, 2 * math.pi)
    R_tilt = _rotation(np.array([math.cos(azim), math.sin(azim), 0.0]), tilt)
    R = _align_z_to(ray) @ R_tilt @ _rotation(np.array([0.0, 0.0, 1.0]), roll)
    return _Pose(R=R, ray=ray, tilt_deg=math.degrees(tilt))


def _homography_at_radius(spec: MarkerSpec, K: np.ndarray, pose: _Pose, radius_px: float) -> np.ndarray:
    """H (image from plane metres) whose projected pattern has equal-area radius ``radius_px``: the
    plane origin slides along the viewing ray, which keeps its image exactly where it was."""
    f = K[0, 0]
    r_unit = spec.half if spec.type == "circle" else spec.size_m / math.sqrt(math.pi)
    dist = f * r_unit / radius_px
    H = plane_homography(K, pose.R, dist * pose.ray)
    for _ in range(3):
        r = projected_radius(spec, H)
        dist *= r / radius_px
        H = plane_homography(K, pose.R, dist * pose.ray)
    return H


def _in_front(spec: MarkerSpec, K: np.ndarray, H: np.ndarray) -> bool:
    """True when the whole sheet lies in front of the camera (positive projective depth)."""
    pts = spec.outline(32, with_margin=True)
    w = pts @ H[2, :2] + H[2, 2]
    return bool(np.all(w > 0))


# ----------------------------------------------------------------------------------------- background

def _background(rng: np.random.Generator, lib: BackgroundLibrary, w: int, h: int) -> tuple[np.ndarray, dict]:
    idx = int(rng.integers(len(lib)))
    src = lib.image(idx)
    if rng.random() < 0.5:
        src = src[:, ::-1]
    if rng.random() < 0.15:
        src = src[::-1]
    H0, W0 = src.shape[:2]
    aspect = w / h
    cw_max = min(W0, H0 * aspect)
    cw = cw_max * rng.uniform(0.4, 1.0)
    ch = cw / aspect
    x0 = rng.uniform(0, W0 - cw)
    y0 = rng.uniform(0, H0 - ch)
    sx, sy = w / cw, h / ch
    A = np.array([[sx, 0, -x0 * sx + 0.5 * sx - 0.5], [0, sy, -y0 * sy + 0.5 * sy - 0.5]], np.float64)
    interp = cv2.INTER_AREA if sx < 1 else cv2.INTER_LINEAR
    if interp == cv2.INTER_AREA:
        crop = np.ascontiguousarray(src[int(y0):int(math.ceil(y0 + ch)), int(x0):int(math.ceil(x0 + cw))])
        img = cv2.resize(crop, (w, h), interpolation=cv2.INTER_AREA)
    else:
        img = cv2.warpAffine(np.ascontiguousarray(src), A, (w, h), flags=cv2.INTER_LINEAR,
                             borderMode=cv2.BORDER_REFLECT)
    img = img.astype(np.float32)
    img *= (1.0 + rng.uniform(-0.08, 0.08, 3)).astype(np.float32)
    bg = lib.backgrounds[idx]
    return img, {"background": bg.file, "category": bg.category, "split": bg.split,
                 "crop": [round(float(x0), 2), round(float(y0), 2), round(float(cw), 2), round(float(ch), 2)]}


# ----------------------------------------------------------------------------------------- compositing

def _warp_patch(img: np.ndarray, patch: np.ndarray, alpha: np.ndarray, H: np.ndarray) -> None:
    """Composite ``patch`` (s, s, 3) with ``alpha`` through homography H (image from canvas pixels)."""
    s = patch.shape[0]
    corners = apply_homography(H, np.array([[-0.5, -0.5], [s - 0.5, -0.5], [s - 0.5, s - 0.5], [-0.5, s - 0.5]]))
    Hh, Ww = img.shape[:2]
    x0 = max(int(math.floor(corners[:, 0].min())) - 1, 0)
    y0 = max(int(math.floor(corners[:, 1].min())) - 1, 0)
    x1 = min(int(math.ceil(corners[:, 0].max())) + 2, Ww)
    y1 = min(int(math.ceil(corners[:, 1].max())) + 2, Hh)
    if x1 <= x0 or y1 <= y0:
        return
    T = np.array([[1, 0, -x0], [0, 1, -y0], [0, 0, 1]], float) @ H
    size = (x1 - x0, y1 - y0)
    p = cv2.warpPerspective(patch, T, size, flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
    a = cv2.warpPerspective(alpha, T, size, flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)[..., None]
    roi = img[y0:y1, x0:x1]
    roi *= 1.0 - a
    roi += a * p


def _disk_kernel(radius: float) -> np.ndarray:
    n = int(math.ceil(radius)) * 2 + 3
    c = (n - 1) / 2
    S = 8
    yy, xx = np.mgrid[0:n * S, 0:n * S]
    inside = ((xx + 0.5) / S - 0.5 - c) ** 2 + ((yy + 0.5) / S - 0.5 - c) ** 2 <= radius * radius
    k = inside.reshape(n, S, n, S).mean(axis=(1, 3)).astype(np.float32)
    return k / k.sum()


def _motion_kernel(length: float, angle: float) -> np.ndarray:
    n = int(math.ceil(length)) + 3
    n += 1 - n % 2
    c = (n - 1) / 2
    k = np.zeros((n, n), np.uint8)
    dx, dy = 0.5 * length * math.cos(angle), 0.5 * length * math.sin(angle)
    sh = 4
    p0 = (int(round((c - dx) * 16)), int(round((c - dy) * 16)))
    p1 = (int(round((c + dx) * 16)), int(round((c + dy) * 16)))
    cv2.line(k, p0, p1, 255, 1, cv2.LINE_AA, sh)
    kf = k.astype(np.float32)
    return kf / kf.sum()


def _shadow_polygon(rng: np.random.Generator, sw: int, sh: int) -> np.ndarray:
    """The corners (4, 2) of a shadow region on a ``sw`` x ``sh`` grid: a half-plane-like region cut
    by a slanted line, or a big random quadrilateral; always a simple polygon."""
    if rng.random() < 0.5:
        p = rng.uniform([0, 0], [sw, sh])
        ang = rng.uniform(0, 2 * math.pi)
        d = np.array([math.cos(ang), math.sin(ang)]) * 4 * max(sw, sh)
        n = np.array([-d[1], d[0]])
        return np.array([p - d, p + d, p + d + n, p - d + n])
    c = rng.uniform([0, 0], [sw, sh])
    poly = c + rng.uniform(-0.6, 0.6, (4, 2)) * np.array([sw, sh])
    # in the order drawn, nearly half of such quadrilaterals cross themselves: a bowtie, whose two
    # dark triangles meet at a perfect X-corner (in about 4.6 % of images the crossing is in frame), a
    # shadow no flat object casts (the projection of a simple polygon is simple) and one both
    # detectors took for a marker of a thousand pixels (stop 63). A bowtie's corners are in convex
    # position, so ordered by angle about their mean they make the one simple quadrilateral on them;
    # the random draws, and every quadrilateral drawn simple, stay as they were
    if _crosses(poly[0], poly[1], poly[2], poly[3]) or _crosses(poly[1], poly[2], poly[3], poly[0]):
        mid = poly.mean(axis=0)
        poly = poly[np.argsort(np.arctan2(poly[:, 1] - mid[1], poly[:, 0] - mid[0]))]
    return poly


def _crosses(p1: np.ndarray, p2: np.ndarray, p3: np.ndarray, p4: np.ndarray) -> bool:
    """Whether segments p1-p2 and p3-p4 cross at a point inside both."""
    def side(a, b, c) -> float:
        return float((b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0]))
    return side(p1, p2, p3) * side(p1, p2, p4) < 0 and side(p3, p4, p1) * side(p3, p4, p2) < 0


def _soft_polygon_mask(rng: np.random.Generator, w: int, h: int, scale: int = 4) -> np.ndarray:
    """A soft-edged random shadow region (float32 0..1, HxW), drawn at 1/scale and upsampled."""
    sw, sh = max(w // scale, 2), max(h // scale, 2)
    m = np.zeros((sh, sw), np.uint8)
    poly = _shadow_polygon(rng, sw, sh)
    cv2.fillPoly(m, [np.round(poly * 16).astype(np.int32).reshape(-1, 1, 2)], 255, cv2.LINE_AA, 4)
    mf = m.astype(np.float32) / 255.0
    blur = rng.uniform(0.3, 4.0)
    mf = cv2.GaussianBlur(mf, (0, 0), blur)
    return cv2.resize(mf, (w, h), interpolation=cv2.INTER_LINEAR)


# ----------------------------------------------------------------------------------------- one image

@dataclass
class _Placed:
    spec: MarkerSpec
    H: np.ndarray
    centre: np.ndarray
    extent: float  # radius of the sheet's bounding circle about the centre, pixels
    pose: _Pose
    inside: bool = True  # the whole sheet lies inside the image


def _place_markers(rng: np.random.Generator, opt: SynthImageOptions, K: np.ndarray) -> list[_Placed]:
    if rng.random() < opt.empty_prob:
        n = 0
    else:
        n = int(rng.integers(max(opt.markers[0], 1) if opt.markers[1] > 0 else 0, opt.markers[1] + 1))
    w, h = opt.width, opt.height
    placed: list[_Placed] = []
    lo, hi = math.log(opt.radius_min_px), math.log(opt.radius_max_px)
    for _ in range(n):
        mtype = str(opt.types[int(rng.integers(len(opt.types)))])
        margin = 0.0
        if rng.random() < opt.margin_prob:
            margin = float(rng.uniform(*opt.margin_frac))
        spec = MarkerSpec(mtype, size_m=1.0, margin_m=margin)
        # small markers are the hard and common case: log-uniform radius
        cut = rng.random() < opt.border_cut_prob
        for _attempt in range(25):
            r = math.exp(rng.uniform(lo, hi))
            if cut:  # centre inside the image, close enough to an edge that the frame cuts the marker
                inset = rng.uniform(2.0, max(0.8 * r, 2.5))
                side = int(rng.integers(4))
                along = rng.uniform(inset, (h if side < 2 else w) - 1 - inset)  # y on left/right sides
                if side >= 2:
                    xy = (along, inset) if side == 2 else (along, h - 1 - inset)
                else:
                    xy = (inset, along) if side == 0 else (w - 1 - inset, along)
            else:
                xy = (rng.uniform(0, w - 1), rng.uniform(0, h - 1))
            pose = _random_pose(rng, K, xy, opt.tilt_max_deg)
            H = _homography_at_radius(spec, K, pose, r)
            rr = projected_radius(spec, H)
            if not (opt.radius_min_px - 1e-6 <= rr <= opt.radius_max_px + 1e-6) or not _in_front(spec, K, H):
                continue
            sheet = apply_homography(H, spec.outline(64, with_margin=True))
            inside = not (sheet[:, 0].min() < 1 or sheet[:, 1].min() < 1 or sheet[:, 0].max() > w - 2
                          or sheet[:, 1].max() > h - 2)
            if not inside and not cut:
                continue
            c = np.array(xy)
            extent = float(np.max(np.hypot(*(sheet - c).T)))
            if any(np.hypot(*(c - q.centre)) < extent + q.extent + 2.0 for q in placed):
                continue
            placed.append(_Placed(spec, H, c, extent, pose, inside))
            break
    return placed


def _levels(rng: np.random.Generator, opt: SynthImageOptions) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    contrast = rng.uniform(*opt.contrast)
    dark = rng.uniform(3.0, max(255.0 - contrast, 4.0) * 0.45 + 3.0)
    bright = min(dark + contrast, 252.0)
    tint = lambda: (1.0 + rng.uniform(-0.07, 0.07, 3)).astype(np.float32)  # noqa: E731
    d = np.float32(dark) * tint()
    b = np.clip(np.float32(bright) * tint(), 0, 255)
    m = np.clip(np.float32(bright) * rng.uniform(0.93, 1.05) * tint(), 0, 255)
    if rng.random() < opt.colour_prob:
        # coloured paint for the bright quadrants (yellow, orange, red, pink; BGR), white margin
        hue = _MARKER_COLOURS[int(rng.integers(len(_MARKER_COLOURS)))]
        b = np.clip(np.float32(bright) * hue * tint(), 0, 255).astype(np.float32)
    return d, b, m


_MARKER_COLOURS = np.array([[0.15, 0.9, 1.0], [0.1, 0.55, 1.0], [0.15, 0.15, 0.95], [0.7, 0.45, 1.0]], np.float32)


def _occluder(rng: np.random.Generator, centre: np.ndarray, radius: float, shape: tuple[int, int],
              box: tuple[int, int, int, int]) -> np.ndarray:
    """A random occluder polygon near a marker, as float32 coverage over ``box`` (x0, y0, w, h)."""
    x0, y0, bw, bh = box
    m = np.zeros((bh, bw), np.uint8)
    ang = rng.uniform(0, 2 * math.pi)
    dist = radius * rng.uniform(0.5, 1.6)
    c = centre + dist * np.array([math.cos(ang), math.sin(ang)]) - np.array([x0, y0])
    if rng.random() < 0.4:  # a branch, cable or pole: long thin quad
        t = rng.uniform(0, math.pi)
        L, W = radius * 4, radius * rng.uniform(0.15, 0.5)
        u, v = np.array([math.cos(t), math.sin(t)]), np.array([-math.sin(t), math.cos(t)])
        c = centre + radius * rng.uniform(-0.9, 0.9) * v - np.array([x0, y0])
        poly = np.array([c - L * u - W * v, c + L * u - W * v, c + L * u + W * v, c - L * u + W * v])
    else:  # a blob: random convex-ish polygon
        k = int(rng.integers(4, 8))
        th = np.sort(rng.uniform(0, 2 * math.pi, k))
        rad = radius * rng.uniform(0.5, 1.2, k)
        poly = c + np.stack([rad * np.cos(th), rad * np.sin(th)], 1)
    cv2.fillPoly(m, [np.round(poly * 16).astype(np.int32).reshape(-1, 1, 2)], 255, cv2.LINE_AA, 4)
    return m.astype(np.float32) / 255.0


def generate_image(index: int, seed: int, opt: SynthImageOptions, lib: BackgroundLibrary) -> SynthImage:
    """Generate image ``index`` of the set made with ``seed`` (depends on nothing else)."""
    rng = np.random.default_rng([int(seed), int(index)])
    w, h = opt.width, opt.height
    img, meta = _background(rng, lib, w, h)
    f = w * rng.uniform(*opt.focal_frac)
    K = np.array([[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1.0]])
    placed = _place_markers(rng, opt, K)

    # confusers, away from the markers
    confusers = []
    n_conf = int(rng.integers(opt.confusers[0], opt.confusers[1] + 1)) if opt.confuser_kinds else 0
    for _ in range(n_conf):
        kind = str(opt.confuser_kinds[int(rng.integers(len(opt.confuser_kinds)))])
        frac = rng.uniform(0.12, 0.5) if kind == "grid" else rng.uniform(0.06, 0.35)
        size = max(int(frac * min(w, h)), 12)
        patch, alpha = draw_confuser(kind, rng, size)
        for _attempt in range(10):
            xy = np.array([rng.uniform(0, w - 1), rng.uniform(0, h - 1)])
            extent = size * 0.75
            if all(np.hypot(*(xy - q.centre)) > extent + q.extent + 2.0 for q in placed):
                break
        else:
            continue
        pose = _random_pose(rng, K, tuple(xy), opt.tilt_max_deg)
        dist = f / size  # canvas pixel = 1/size plane units; about ``size`` pixels across at this distance
        Hp = plane_homography(K, pose.R, dist * pose.ray)
        c = (size - 1) / 2
        Hc = Hp @ np.array([[1.0 / size, 0, -c / size], [0, 1.0 / size, -c / size], [0, 0, 1]])
        _warp_patch(img, patch, alpha, Hc)
        confusers.append({"kind": kind, "x": round(float(xy[0]), 2), "y": round(float(xy[1]), 2),
                          "size_px": size})

    # markers
    mask = np.zeros((h, w), np.uint8)
    texture = None
    drawn: list[tuple[int, int, int, int]] = []  # boxes (x0, y0, w, h) of the markers drawn so far
    truths: list[TrueMarker] = []
    for q in placed:
        rm = render_marker(q.spec, q.H, (h, w), supersample=opt.supersample)
        bh, bw = rm.dark.shape
        box = img[rm.y0:rm.y0 + bh, rm.x0:rm.x0 + bw]
        before = box.copy()
        d, b, m = _levels(rng, opt)
        rm.composite(img, d, b, m)
        drawn.append((rm.x0, rm.y0, bw, bh))
        tex_amount = 0.0
        if rng.random() < opt.texture_prob:
            tex_amount = float(rng.uniform(0.05, opt.texture_max))
            if texture is None:
                texture = img - cv2.GaussianBlur(img, (0, 0), 3.0)  # local surface relief
            sheet = rm.sheet[..., None]
            box += tex_amount * sheet * texture[rm.y0:rm.y0 + bh, rm.x0:rm.x0 + bw]
        pattern = rm.pattern
        occ = np.zeros_like(pattern)
        occluded_frac = 0.0
        radius = projected_radius(q.spec, q.H)
        if rng.random() < opt.occlusion_prob and pattern.sum() > 0:
            for _attempt in range(6):
                cand = _occluder(rng, q.centre, radius, (h, w), (rm.x0, rm.y0, bw, bh))
                fr = float(((pattern >= 0.5) & (cand >= 0.5)).sum() / max((pattern >= 0.5).sum(), 1))
                if 0.02 <= fr <= opt.occlusion_max:
                    occ, occluded_frac = cand, fr
                    break
            if occluded_frac > 0:
                # the occluder shows the surface from elsewhere in the photograph, a little darker
                sy = int(rng.integers(0, max(h - bh, 1)))
                sx = int(rng.integers(0, max(w - bw, 1)))
                other = img[sy:sy + bh, sx:sx + bw].copy()
                # a patch with a marker drawn in it (this one included) would copy that marker, one
                # the truth does not list (before stop 70 it did: a Secchi disk on a panel, counted
                # false for every detector); the surface under this marker shows then, shaded
                if other.shape[:2] != (bh, bw) or any(
                        sx < x0 + ww and x0 < sx + bw and sy < y0 + hh and y0 < sy + bh for x0, y0, ww, hh in drawn):
                    other = before
                shade = np.float32(rng.uniform(0.5, 1.0))
                a = occ[..., None]
                box *= 1.0 - a
                box += a * other * shade
        mbox = mask[rm.y0:rm.y0 + bh, rm.x0:rm.x0 + bw]
        mbox[(pattern >= 0.5) & (occ < 0.5)] = 255
        # an occluder over the aiming point leaves nothing to measure it by, whatever the detector
        centre_hidden = bool(occluded_frac > 0 and cv2.getRectSubPix(
            occ, (1, 1), (float(q.centre[0] - rm.x0), float(q.centre[1] - rm.y0)))[0, 0] >= 0.5)
        truths.append(TrueMarker(
            x=float(q.centre[0]), y=float(q.centre[1]), type=q.spec.type, radius_px=radius,
            extra={"tilt_deg": round(q.pose.tilt_deg, 3), "margin": round(q.spec.margin_m, 4),
                   "contrast": round(float(np.mean(b - d)), 2), "texture": round(tex_amount, 3),
                   "occluded_frac": round(occluded_frac, 4), "centre_hidden": centre_hidden,
                   "visible_frac": 1.0 if q.inside else round(min(float(pattern.sum()) / (math.pi * radius ** 2),
                                                                  1.0), 4)}))

    # illumination: level, gradient, shadow
    level = rng.uniform(*opt.level)
    g = rng.uniform(-opt.gradient_max, opt.gradient_max)
    ang = rng.uniform(0, 2 * math.pi)
    xs = (np.arange(w, dtype=np.float32) - (w - 1) / 2) * (math.cos(ang) / (w / 2))
    ys = (np.arange(h, dtype=np.float32) - (h - 1) / 2) * (math.sin(ang) / (h / 2))
    illum = np.float32(level) * (1.0 + np.float32(g / 2) * (ys[:, None] + xs[None, :]))
    shadow = 0.0
    if rng.random() < opt.shadow_prob:
        shadow = float(rng.uniform(0.25, 0.65))
        illum = illum * (1.0 - np.float32(shadow) * _soft_polygon_mask(rng, w, h))
    img *= np.clip(illum, 0.05, None)[..., None]

    # optics
    defocus = motion = 0.0
    blur_sigma2 = 0.0
    if rng.random() < opt.defocus_prob:
        defocus = float(rng.uniform(0.5, opt.defocus_max_px))
        if rng.random() < 0.5:
            img = cv2.filter2D(img, -1, _disk_kernel(defocus), borderType=cv2.BORDER_REFLECT)
            blur_sigma2 += (defocus / 2) ** 2
        else:
            img = cv2.GaussianBlur(img, (0, 0), defocus / 2, borderType=cv2.BORDER_REFLECT)
            blur_sigma2 += (defocus / 2) ** 2
    if rng.random() < opt.motion_prob:
        motion = float(rng.uniform(1.0, opt.motion_max_px))
        img = cv2.filter2D(img, -1, _motion_kernel(motion, rng.uniform(0, math.pi)), borderType=cv2.BORDER_REFLECT)
        blur_sigma2 += motion ** 2 / 12
    blur_px = math.sqrt(blur_sigma2)

    # sensor
    read = rng.uniform(*opt.noise_read)
    gain = rng.uniform(0, opt.noise_gain)
    np.clip(img, 0, 255, out=img)
    sigma = np.sqrt(gain * img + np.float32(read * read))
    img += sigma * rng.standard_normal(img.shape, dtype=np.float32)
    out = np.clip(img + 0.5, 0, 255).astype(np.uint8)
    q_jpeg = int(rng.integers(opt.jpeg_quality[0], opt.jpeg_quality[1] + 1))

    truths = [dataclasses.replace(t, extra={**t.extra, "blur_px": round(blur_px, 3)}) for t in truths]
    meta.update({"confusers": confusers, "defocus_px": round(defocus, 3), "motion_px": round(motion, 3),
                 "blur_px": round(blur_px, 3), "noise_read": round(float(read), 3),
                 "noise_gain": round(float(gain), 4), "shadow": round(shadow, 3),
                 "jpeg_quality": q_jpeg if opt.image_format == "jpg" else None})
    return SynthImage(image=out, mask=mask, markers=truths, meta=meta, jpeg_quality=q_jpeg)


# ----------------------------------------------------------------------------------------- writing

def _encode(img: np.ndarray, ext: str, quality: int = 90) -> bytes:
    if ext == "jpg":
        ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    else:
        ok, buf = cv2.imencode(".png", img, [cv2.IMWRITE_PNG_COMPRESSION, 3])
    if not ok:
        raise RuntimeError(f"cannot encode image as {ext}")
    return buf.tobytes()


def write_image(out: Path, index: int, sample: SynthImage, ext: str) -> dict:
    """Write one generated image and its mask atomically; return its markers.json record."""
    stem = f"{index:06d}"
    file, mask = f"images/{stem}.{ext}", f"masks/{stem}.png"
    write_bytes_atomic(out / file, _encode(sample.image, ext, sample.jpeg_quality))
    write_bytes_atomic(out / mask, _encode(sample.mask, "png"))
    return image_record(file, mask, sample.markers, **sample.meta)


_WORKER: dict = {}


def _worker_init(seed: int, opt: SynthImageOptions, out: str) -> None:
    cv2.setNumThreads(1)
    _WORKER.clear()
    try:
        _WORKER.update(seed=seed, opt=opt, out=Path(out), lib=BackgroundLibrary(list_backgrounds(opt.split)))
    except Exception as exc:  # noqa: BLE001 - handed to the first task, see below
        # an initializer that raises makes multiprocessing.Pool start new workers forever (a hang);
        # the first task raises it instead, and the error reaches the caller
        _WORKER["error"] = exc


def _worker_make(index: int) -> dict:
    w = _WORKER
    if "error" in w:
        raise w["error"]
    return write_image(w["out"], index, generate_image(index, w["seed"], w["opt"], w["lib"]), w["opt"].image_format)


def write_synth_images(out: str | os.PathLike, n: int, seed: int, opt: SynthImageOptions | None = None,
                       workers: int = 1, progress: Callable[[int], None] | None = None) -> Path:
    """Generate ``n`` images into folder ``out`` (images/, masks/, markers.json written last).

    ``workers`` > 1 uses a process pool; the files are identical to a serial run. ``progress`` is
    called with the number of images done. Returns the path of markers.json.
    """
    opt = opt or SynthImageOptions()
    if n < 0:
        raise ValueError("n must be >= 0")
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise InputError("output must be a folder, found a file", out)
    # an interrupted run must not leave an old markers.json describing a mix of old and new images
    try:
        (out / MARKERS_JSON).unlink(missing_ok=True)
    except OSError as exc:  # e.g. a folder on the way is a file (the folder itself is made later)
        raise cannot_write(exc, out) from None
    records: list[dict] = []
    if workers <= 1 or n < 4:
        lib = BackgroundLibrary(list_backgrounds(opt.split))
        for i in range(n):
            records.append(write_image(out, i, generate_image(i, seed, opt, lib), opt.image_format))
            if progress:
                progress(i + 1)
    else:
        import multiprocessing as mp

        list_backgrounds(opt.split)  # missing or broken backgrounds: the error here, before any worker
        # spawn, not fork: forking a process whose OpenCV/OpenMP thread pools already run can deadlock
        ctx = mp.get_context("spawn")
        with ctx.Pool(workers, initializer=_worker_init, initargs=(seed, opt, str(out))) as pool:
            for k, rec in enumerate(pool.imap(_worker_make, range(n), chunksize=4)):
                records.append(rec)
                if progress:
                    progress(k + 1)
    bgs = {b.file: b for b in list_backgrounds("all")}
    used = sorted({r["background"] for r in records})
    attribution = [{"file": f, "category": bgs[f].category, "license": bgs[f].license,
                    "attribution": bgs[f].attribution} for f in used if f in bgs]
    return write_markers_json(out, records, generator={"name": "cpdetect synth images", "seed": int(seed),
                                                       "n": int(n), "options": opt.to_dict()},
                              backgrounds=attribution)


__all__ = ["SynthImageOptions", "SynthImage", "generate_image", "write_image", "write_synth_images"]
