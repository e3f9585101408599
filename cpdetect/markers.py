"""The three marker types, their geometry in the marker plane, and an anti-aliased renderer.

Marker-plane frame: origin at the aiming point (the central X-corner), u to the right, v down when the
marker is seen from the front and upright, units metres; the plane normal z = u x v points away from
the viewer (into the surface it is stuck on), as in OpenCV's camera frame.

Patterns (value 0 = dark, 1 = bright):
- ``square``: a square of side ``size_m``, quadrants dark where u*v > 0 (top-left and bottom-right).
- ``circle``: a Secchi disk of diameter ``size_m``, the same quadrants.
- ``diagonal``: a square of side ``size_m`` whose checker is rotated 45 degrees: the four triangles
  between the diagonals; left and right dark (|u| > |v|), top and bottom bright.
An optional white printed margin of width ``margin_m`` surrounds the pattern (square sheet for square
and diagonal, a ring for circle).

The renderer samples each pixel exactly once where the pattern is constant over it and supersamples
(``supersample`` x ``supersample`` sub-pixel samples) every pixel that an edge crosses, so its cost
grows with the marker's perimeter, not its area; coverage error per pixel is below 1/supersample^2.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .types import MARKER_TYPES, check_marker_type

OUTSIDE, MARGIN, DARK, BRIGHT = 0, 1, 2, 3


@dataclass(frozen=True)
class MarkerSpec:
    """A printed marker: ``type``, pattern size ``size_m`` (side or diameter, metres), white margin."""

    type: str
    size_m: float = 0.2
    margin_m: float = 0.0

    def __post_init__(self) -> None:
        check_marker_type(self.type)
        if not self.size_m > 0:
            raise ValueError("marker size must be positive")
        if self.margin_m < 0:
            raise ValueError("marker margin must be >= 0")

    @property
    def half(self) -> float:
        return 0.5 * self.size_m

    def classify(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Label plane points: OUTSIDE, MARGIN, DARK or BRIGHT (uint8, same shape as u)."""
        h, m = self.half, self.margin_m
        if self.type == "circle":
            r2 = u * u + v * v
            in_pattern = r2 <= h * h
            in_sheet = r2 <= (h + m) ** 2
        else:
            au, av = np.abs(u), np.abs(v)
            in_pattern = (au <= h) & (av <= h)
            in_sheet = (au <= h + m) & (av <= h + m)
        if self.type == "diagonal":
            dark = np.abs(u) > np.abs(v)
        else:
            dark = u * v > 0
        out = np.full(u.shape, OUTSIDE, np.uint8)
        out[in_sheet] = MARGIN
        out[in_pattern & dark] = DARK
        out[in_pattern & ~dark] = BRIGHT
        return out

    def outline(self, n: int = 256, with_margin: bool = False) -> np.ndarray:
        """Closed outline of the pattern (or sheet) in the plane, shape (k, 2), counter-clockwise."""
        r = self.half + (self.margin_m if with_margin else 0.0)
        if self.type == "circle":
            t = np.linspace(0, 2 * np.pi, n, endpoint=False)
            return np.stack([r * np.cos(t), r * np.sin(t)], axis=1)
        return np.array([[-r, -r], [r, -r], [r, r], [-r, r]], float)


def apply_homography(H: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Map (n, 2) points through a 3x3 homography."""
    pts = np.asarray(pts, float)
    ph = pts @ H[:, :2].T + H[:, 2]
    return ph[:, :2] / ph[:, 2:3]


def projected_center(H: np.ndarray) -> np.ndarray:
    """Image position (x, y) of the aiming point for image_from_plane homography ``H``."""
    return H[:2, 2] / H[2, 2]


def projected_radius(spec: MarkerSpec, H: np.ndarray) -> float:
    """Radius of the circle with the same image area as the projected pattern (pixels)."""
    poly = apply_homography(H, spec.outline(256))
    x, y = poly[:, 0], poly[:, 1]
    area = 0.5 * abs(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))
    return float(np.sqrt(area / np.pi))


@dataclass
class RenderedMarker:
    """Per-pixel coverages of one rendered marker inside the box starting at pixel (x0, y0).

    dark, bright, margin: float32 fractions of each pixel's area (sum <= 1; 1 - sum is background).
    """

    x0: int
    y0: int
    dark: np.ndarray
    bright: np.ndarray
    margin: np.ndarray

    @property
    def pattern(self) -> np.ndarray:
        return self.dark + self.bright

    @property
    def sheet(self) -> np.ndarray:
        return self.dark + self.bright + self.margin

    def composite(self, image: np.ndarray, dark_level: float | np.ndarray, bright_level: float | np.ndarray,
                  margin_level: float | np.ndarray | None = None) -> None:
        """Paint onto a float image (HxW or HxWxC) in place; levels are scalars or per-channel."""
        if margin_level is None:
            margin_level = bright_level
        h, w = self.dark.shape
        H, W = image.shape[:2]
        ys, xs = slice(max(self.y0, 0), min(self.y0 + h, H)), slice(max(self.x0, 0), min(self.x0 + w, W))
        if ys.start >= ys.stop or xs.start >= xs.stop:
            return
        cy = slice(ys.start - self.y0, ys.stop - self.y0)
        cx = slice(xs.start - self.x0, xs.stop - self.x0)
        d, b, m = self.dark[cy, cx], self.bright[cy, cx], self.margin[cy, cx]
        if image.ndim == 3:
            d, b, m = d[..., None], b[..., None], m[..., None]
        roi = image[ys, xs]
        roi *= 1.0 - (d + b + m)
        roi += d * np.asarray(dark_level) + b * np.asarray(bright_level) + m * np.asarray(margin_level)


def _label_at(spec: MarkerSpec, Hinv: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    w = Hinv[2, 0] * x + Hinv[2, 1] * y + Hinv[2, 2]
    u = (Hinv[0, 0] * x + Hinv[0, 1] * y + Hinv[0, 2]) / w
    v = (Hinv[1, 0] * x + Hinv[1, 1] * y + Hinv[1, 2]) / w
    lab = spec.classify(u, v)
    lab[w <= 0] = OUTSIDE  # behind the camera's horizon of the plane
    return lab


def render_marker(spec: MarkerSpec, H: np.ndarray, image_shape: tuple[int, int] | None = None,
                  supersample: int = 16) -> RenderedMarker:
    """Render ``spec`` seen through ``H`` (3x3, image pixels from plane metres, OpenCV convention).

    Returns coverages over the bounding box of the projected sheet, clipped to ``image_shape`` (h, w)
    when given. Sub-pixel samples sit at x + (i + 0.5)/S - 0.5, symmetric about the pixel centre.
    """
    H = np.asarray(H, float)
    Hinv = np.linalg.inv(H)
    outline = apply_homography(H, spec.outline(256, with_margin=True))
    x0 = int(np.floor(outline[:, 0].min() - 1))
    y0 = int(np.floor(outline[:, 1].min() - 1))
    x1 = int(np.ceil(outline[:, 0].max() + 1))
    y1 = int(np.ceil(outline[:, 1].max() + 1))
    if image_shape is not None:
        x0, y0 = max(x0, 0), max(y0, 0)
        x1, y1 = min(x1, image_shape[1] - 1), min(y1, image_shape[0] - 1)
    w, h = max(x1 - x0 + 1, 0), max(y1 - y0 + 1, 0)
    dark = np.zeros((h, w), np.float32)
    bright = np.zeros((h, w), np.float32)
    margin = np.zeros((h, w), np.float32)
    if w == 0 or h == 0:
        return RenderedMarker(x0, y0, dark, bright, margin)
    # labels at pixel corners (h+1, w+1) and centres (h, w): a pixel whose five labels agree is uniform
    cx = np.arange(x0, x0 + w + 1, dtype=float) - 0.5
    cy = np.arange(y0, y0 + h + 1, dtype=float) - 0.5
    CX, CY = np.meshgrid(cx, cy)
    corners = _label_at(spec, Hinv, CX, CY)
    PX, PY = np.meshgrid(np.arange(x0, x0 + w, dtype=float), np.arange(y0, y0 + h, dtype=float))
    centre = _label_at(spec, Hinv, PX, PY)
    mixed = ((corners[:-1, :-1] != centre) | (corners[1:, :-1] != centre)
             | (corners[:-1, 1:] != centre) | (corners[1:, 1:] != centre))
    # the aiming point itself: four sectors meet, always supersample around it
    c = projected_center(H)
    ix, iy = int(round(c[0])) - x0, int(round(c[1])) - y0
    mixed[max(iy - 1, 0):iy + 2, max(ix - 1, 0):ix + 2] = True
    for lab, arr in ((DARK, dark), (BRIGHT, bright), (MARGIN, margin)):
        arr[(centre == lab) & ~mixed] = 1.0
    my, mx = np.nonzero(mixed)
    if my.size:
        S = int(supersample)
        offs = (np.arange(S) + 0.5) / S - 0.5
        ox, oy = np.meshgrid(offs, offs)
        ox, oy = ox.ravel(), oy.ravel()
        chunk = max(1, 2_000_000 // (S * S))
        for k in range(0, my.size, chunk):
            yy, xx = my[k:k + chunk], mx[k:k + chunk]
            sx = (xx + x0)[:, None] + ox[None, :]
            sy = (yy + y0)[:, None] + oy[None, :]
            lab = _label_at(spec, Hinv, sx, sy)
            n = float(S * S)
            dark[yy, xx] = (lab == DARK).sum(1) / n
            bright[yy, xx] = (lab == BRIGHT).sum(1) / n
            margin[yy, xx] = (lab == MARGIN).sum(1) / n
    return RenderedMarker(x0, y0, dark, bright, margin)


def frontal_homography(center_xy: tuple[float, float], radius_px: float, angle_rad: float = 0.0,
                       spec: MarkerSpec | None = None) -> np.ndarray:
    """Homography of an upright (rotated by ``angle_rad``) frontal marker with pattern half-size
    ``radius_px`` pixels (half-side or circle radius), centred at ``center_xy``."""
    half = spec.half if spec is not None else 1.0
    s = radius_px / half
    c, si = np.cos(angle_rad), np.sin(angle_rad)
    return np.array([[s * c, -s * si, center_xy[0]], [s * si, s * c, center_xy[1]], [0, 0, 1.0]])


def plane_homography(K: np.ndarray, cam_from_plane_R: np.ndarray, cam_from_plane_t: np.ndarray) -> np.ndarray:
    """H = K [r1 r2 t]: image pixels from plane points (u, v) for a pinhole camera (no distortion)."""
    R = np.asarray(cam_from_plane_R, float)
    t = np.asarray(cam_from_plane_t, float).reshape(3)
    return np.asarray(K, float) @ np.column_stack([R[:, 0], R[:, 1], t])


def render_frontal(marker_type: str, size_px: int, radius_px: float, angle_rad: float = 0.0,
                   dark: float = 0.0, bright: float = 1.0, background: float = 0.5,
                   center: tuple[float, float] | None = None, margin_frac: float = 0.0) -> np.ndarray:
    """A size_px x size_px float32 image with one frontal marker (handy for tests and templates)."""
    spec = MarkerSpec(marker_type, size_m=2.0, margin_m=2.0 * margin_frac)
    if center is None:
        center = ((size_px - 1) / 2.0, (size_px - 1) / 2.0)
    H = frontal_homography(center, radius_px, angle_rad, spec)
    img = np.full((size_px, size_px), background, np.float32)
    render_marker(spec, H, img.shape).composite(img, dark, bright)
    return img


__all__ = ["MarkerSpec", "RenderedMarker", "render_marker", "render_frontal", "frontal_homography",
           "plane_homography", "projected_center", "projected_radius", "apply_homography", "MARKER_TYPES"]
