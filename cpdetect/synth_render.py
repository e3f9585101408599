"""Ray-cast renderer of the synthetic pier site (Open3D ``RaycastingScene``).

Every image sample is a ray from the camera centre through a (distorted) pixel position, made with
the same :class:`geometry.camera.Camera` model that projects points, so rendering and projection agree
by construction. A hit gives a triangle, hence a pier face (or the ground); the surface colour is the
face's texture (a real background photograph, mirror-tiled at a physical texel size, bilinear) unless
the hit point lies on a printed marker, whose pattern comes from :meth:`MarkerSpec.classify` on the
marker-plane coordinates of the hit. Lambert shading with ambient light; misses see a blurred
environment photograph.

Anti-aliasing: each pixel corner is sampled once (corners are shared, so about one ray per pixel) and
a pixel is the mean of its four corners. A pixel whose four corner samples do not all see the same
surface label (face, marker quadrant, ground, sky) is re-rendered with ``supersample``^2 box-filtered
samples on a rank-1 lattice (every sample with its own x and y), so marker edges, silhouettes and face
edges are area-sampled and an edge of any direction is placed to about 1/supersample^2 of a pixel.

Frames: site frame (metres, z up); poses ``cam_from_site``; pixels in the OpenCV convention (the
centre of the top-left pixel is (0, 0)). Images are rendered in bands of rows, so memory stays bounded
for 8192 x 5460 images.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from geometry.camera import Camera
from geometry.transforms import Rigid3

from .markers import BRIGHT, DARK, MARGIN
from .synth_site_geometry import PierMesh, PlacedMarker

MISS, GROUND = -1, -2


@dataclass
class Appearance:
    """Surface and lighting parameters of a site.

    textures: float32 (h, w, 3) RGB in [0, 1]; face_texture (n_faces,) index into ``textures``;
    face_texel (n_faces,) metres per texel; face_offset (n_faces, 2) texel offset; face_gain
    (n_faces,) albedo factor; ground_texture index and ground_texel (m); environment float32 RGB
    panorama (blurred); sun (3,) unit vector towards the sun; ambient, diffuse: light weights;
    marker_dark, marker_paper (3,) RGB albedo of the printed ink and paper.
    """

    textures: list[np.ndarray]
    face_texture: np.ndarray
    face_texel: np.ndarray
    face_offset: np.ndarray
    face_gain: np.ndarray
    ground_texture: int
    ground_texel: float
    environment: np.ndarray
    sun: np.ndarray
    ambient: float = 0.5
    diffuse: float = 0.5
    marker_dark: tuple[float, float, float] = (0.06, 0.06, 0.065)
    marker_paper: tuple[float, float, float] = (0.86, 0.86, 0.84)


@dataclass(frozen=True)
class ImageEffects:
    """Per-image photometric effects: exposure gain, vignetting strength (fractional fall-off at the
    corners), Gaussian blur sigma (px, 0 = none), additive noise sigma (in 0..255 units, 0 = none)."""

    exposure: float = 1.0
    vignetting: float = 0.0
    blur_sigma: float = 0.0
    noise_sigma: float = 0.0

    @staticmethod
    def random(rng: np.random.Generator) -> "ImageEffects":
        return ImageEffects(exposure=float(rng.uniform(0.8, 1.2)), vignetting=float(rng.uniform(0.05, 0.2)),
                            blur_sigma=float(rng.uniform(0.3, 0.9)), noise_sigma=float(rng.uniform(1.0, 3.5)))


def transform_points(pose: Rigid3, points: np.ndarray) -> np.ndarray:
    """``pose(points)`` for (n, 3) points; einsum, because BLAS matmul of (n, 3) x (3, 3) is slow
    when its threads compete for a busy machine."""
    return np.einsum("ij,kj->ki", pose.R, points) + pose.t


def sample_texture(tex: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Bilinear lookup (n, 3) float32 in ``tex`` (h, w, 3) float32 at texel coordinates x, y (texel
    centres at integers), mirror-repeated beyond the image so tiles join without seams."""
    h, w = tex.shape[:2]

    def mirror(c, n):
        c = np.mod(c + 0.5, 2 * n)
        c = np.where(c > n, 2 * n - c, c) - 0.5
        return np.clip(c, 0.0, n - 1.0).astype(np.float32)

    n = len(x)
    cols = 1024
    rows = -(-n // cols)
    mx = np.zeros(rows * cols, np.float32)
    my = np.zeros(rows * cols, np.float32)
    mx[:n], my[:n] = mirror(x, w), mirror(y, h)
    out = np.empty((rows, cols, 3), np.float32)
    for r0 in range(0, rows, 16384):  # cv2.remap wants maps smaller than 32767 rows
        r1 = min(rows, r0 + 16384)
        cv2.remap(tex, mx.reshape(rows, cols)[r0:r1], my.reshape(rows, cols)[r0:r1], cv2.INTER_LINEAR,
                  dst=out[r0:r1], borderMode=cv2.BORDER_REPLICATE)
    return out.reshape(-1, 3)[:n]


def subpixel_pattern(n: int) -> np.ndarray:
    """``n`` sub-pixel offsets (n, 2) in (-0.5, 0.5)^2: a rank-1 (Fibonacci-like) lattice, x_k = (k + 0.5)/n,
    y_k = ((k g) mod n + 0.5)/n - 0.5 with g coprime to n near n / golden ratio.

    Unlike an S x S grid, every sample has its own x and its own y, so an edge parallel to the pixel
    axes is located to 1/n of a pixel rather than 1/S (a grid biases such edges by up to 1/(2S) px);
    both coordinates average exactly to the pixel centre."""
    if n <= 1:
        return np.zeros((1, 2))
    g = int(round(n / 1.6180339887))
    while math.gcd(g, n) != 1:
        g += 1
    k = np.arange(n)
    return np.stack([(k + 0.5) / n - 0.5, ((k * g) % n + 0.5) / n - 0.5], axis=1)


class SiteRenderer:
    """Renders images of a pier mesh with printed markers; also answers visibility queries."""

    def __init__(self, mesh: PierMesh, markers: list[PlacedMarker], appearance: Appearance,
                 ground_half_size: float = 60.0):
        import open3d as o3d

        self.mesh = mesh
        self.markers = [m for m in markers if m.printed]
        self.app = appearance
        faces = mesh.faces
        self._origin = np.array([f.origin for f in faces])
        self._eu = np.array([f.e_u for f in faces])
        self._ev = np.array([f.e_v for f in faces])
        self._normal = np.array([f.normal for f in faces])
        self._plane_d = np.einsum("ij,ij->i", self._normal, self._origin)
        self._scene = o3d.t.geometry.RaycastingScene()
        self._pier_id = self._scene.add_triangles(
            o3d.core.Tensor(mesh.vertices.astype(np.float32)), o3d.core.Tensor(mesh.triangles.astype(np.uint32)))
        g = ground_half_size
        gv = np.array([[-g, -g, 0], [g, -g, 0], [g, g, 0], [-g, g, 0]], np.float32)
        gt = np.array([[0, 1, 2], [0, 2, 3]], np.uint32)
        self._ground_id = self._scene.add_triangles(o3d.core.Tensor(gv), o3d.core.Tensor(gt))
        self._o3d = o3d

    # ----------------------------------------------------------------------------------- rays
    def cast(self, origin: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Cast rays from one ``origin`` (3,) along ``directions`` (n, 3) (any length); returns (surface
        code (n,) int32: face index, GROUND or MISS; hit points (n, 3) float64; ray parameter t (n,)
        float64 in units of the direction's length, inf for misses). The caster (float32) picks the
        surface; the hit point is then intersected exactly with that plane in float64."""
        o3d = self._o3d
        origin = np.asarray(origin, np.float64).reshape(3)
        n = len(directions)
        rays = np.empty((n, 6), np.float32)
        rays[:, :3] = origin
        rays[:, 3:] = directions
        out = self._scene.cast_rays(o3d.core.Tensor(rays))
        geom = out["geometry_ids"].numpy()
        prim = out["primitive_ids"].numpy()
        hit = geom != o3d.t.geometry.RaycastingScene.INVALID_ID
        code = np.full(n, MISS, np.int32)
        pier = hit & (geom == self._pier_id)
        code[pier] = self.mesh.tri_face[prim[pier]]
        code[hit & (geom == self._ground_id)] = GROUND
        t = np.full(n, np.inf)
        if pier.any():
            f = code[pier]
            dist = self._plane_d - self._normal @ origin  # signed distance of every face plane
            t[pier] = dist[f] / np.einsum("ij,ij->i", self._normal[f], directions[pier])
        gr = code == GROUND
        if gr.any():
            t[gr] = -origin[2] / directions[gr, 2]
        points = np.zeros((n, 3))
        points[hit] = origin + t[hit, None] * directions[hit]
        return code, points, t

    def albedo(self, code: np.ndarray, points: np.ndarray, directions: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray]:
        """Surface colour (n, 3) float32 RGB (unlit) and a label (n,) int32 that changes across every
        colour discontinuity: 4 * face + marker label for the pier, GROUND, MISS."""
        app = self.app
        n = len(code)
        rgb = np.zeros((n, 3), np.float32)
        label = code.astype(np.int32) * 4
        label[code == MISS] = MISS
        label[code == GROUND] = GROUND
        pier = code >= 0
        if pier.any():
            idx = np.nonzero(pier)[0]
            f = code[idx]
            d = points[idx] - self._origin[f]
            u = np.einsum("ij,ij->i", d, self._eu[f])
            v = np.einsum("ij,ij->i", d, self._ev[f])
            tid = app.face_texture[f]
            for k in np.unique(tid):
                sel = tid == k
                ff = f[sel]
                tx = u[sel] / app.face_texel[ff] + app.face_offset[ff, 0]
                ty = v[sel] / app.face_texel[ff] + app.face_offset[ff, 1]
                rgb[idx[sel]] = sample_texture(app.textures[k], tx, ty) * app.face_gain[ff, None].astype(np.float32)
            for m in self.markers:
                on = idx[(f == m.face)]
                if on.size == 0:
                    continue
                rel = points[on] - m.center
                near = np.einsum("ij,ij->i", rel, rel) <= m.outer_radius ** 2
                on, rel = on[near], rel[near]
                if on.size == 0:
                    continue
                lab = m.spec.classify(rel @ m.axis_u, rel @ m.axis_v)
                ink = lab == DARK
                paper = (lab == BRIGHT) | (lab == MARGIN)
                rgb[on[ink]] = app.marker_dark
                rgb[on[paper]] = app.marker_paper
                label[on] += lab.astype(np.int32)
        gr = np.nonzero(code == GROUND)[0]
        if gr.size:
            tex = app.textures[app.ground_texture]
            rgb[gr] = sample_texture(tex, points[gr, 0] / app.ground_texel, points[gr, 1] / app.ground_texel)
        miss = np.nonzero(code == MISS)[0]
        if miss.size:
            d = directions[miss] / np.linalg.norm(directions[miss], axis=1, keepdims=True)
            env = app.environment
            az = np.arctan2(d[:, 1], d[:, 0])
            el = np.arcsin(np.clip(d[:, 2], -1, 1))
            x = (az / (2 * math.pi) + 0.5) * (env.shape[1] - 1)
            y = (0.5 - el / math.pi) * (env.shape[0] - 1)
            rgb[miss] = sample_texture(env, x, y)
        return rgb, label

    def shading(self, code: np.ndarray) -> np.ndarray:
        """Lambert + ambient light factor (n,) float32 per surface code (1 for the environment)."""
        app = self.app
        normals = np.zeros((len(code), 3))
        pier = code >= 0
        normals[pier] = self._normal[code[pier]]
        normals[code == GROUND] = (0.0, 0.0, 1.0)
        lam = np.clip(np.einsum("ij,j->i", normals, app.sun), 0.0, None)
        s = (app.ambient + app.diffuse * lam).astype(np.float32)
        s[code == MISS] = 1.0
        return s

    def radiance(self, origin: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Lit colour (n, 3) float32 and surface label (n,) of rays from ``origin`` (3,)."""
        code, points, _ = self.cast(origin, directions)
        rgb, label = self.albedo(code, points, directions)
        rgb *= self.shading(code)[:, None]
        return rgb, label

    # --------------------------------------------------------------------------------- images
    @staticmethod
    def camera_rays(camera: Camera, xy: np.ndarray) -> np.ndarray:
        """Camera-frame ray directions (n, 3) float32 (z = 1) through image positions xy (n, 2)
        (OpenCV pixels of the distorted image): the inverse of ``camera.project``."""
        xd = np.empty((len(xy), 2))
        xd[:, 0] = (xy[:, 0] - camera.cx) / camera.fx
        xd[:, 1] = (xy[:, 1] - camera.cy) / camera.fy
        if camera.has_distortion:
            xd = camera.undistort_normalized(xd, iterations=12)
        d = np.ones((len(xy), 3), np.float32)
        d[:, :2] = xd
        return d

    def render(self, camera: Camera, cam_from_site: Rigid3, supersample: int = 6, band_rows: int = 128,
               progress=None, ray_cache: dict | None = None) -> np.ndarray:
        """RGB float32 image (h, w, 3) in [0, ~1] of the site (no photometric effects).

        Samples every pixel corner (shared between neighbours) and averages a pixel's four corners;
        pixels whose corners see different surface labels are re-sampled with ``supersample``^2
        sub-pixel rays (:func:`subpixel_pattern`). ``ray_cache`` (a dict kept by the
        caller across images of the same camera) stores the corner rays of small images.
        ``progress(rows_done)`` is called after each band."""
        w, h = camera.width, camera.height
        out = np.empty((h, w, 3), np.float32)
        sub = subpixel_pattern(int(supersample) ** 2)
        R = cam_from_site.R.astype(np.float32)
        origin = cam_from_site.center
        cacheable = ray_cache is not None and (w + 1) * (h + 1) <= 4_000_000
        for r0 in range(0, h, band_rows):
            r1 = min(h, r0 + band_rows)
            nb = r1 - r0
            key = (camera, r0, r1)
            d_cam = ray_cache.get(key) if cacheable else None
            if d_cam is None:
                KX, KY = np.meshgrid(np.arange(w + 1) - 0.5, np.arange(r0, r1 + 1) - 0.5)
                d_cam = self.camera_rays(camera, np.column_stack([KX.ravel(), KY.ravel()]))
                if cacheable:
                    ray_cache[key] = d_cam
            rgb, lab = self.radiance(origin, np.einsum("ij,jk->ik", d_cam, R))  # rows: R^T d
            k_rgb, k_lab = rgb.reshape(nb + 1, w + 1, 3), lab.reshape(nb + 1, w + 1)
            band = 0.25 * (k_rgb[:-1, :-1] + k_rgb[:-1, 1:] + k_rgb[1:, :-1] + k_rgb[1:, 1:])
            c = k_lab[:-1, :-1]
            mixed = (k_lab[:-1, 1:] != c) | (k_lab[1:, :-1] != c) | (k_lab[1:, 1:] != c)
            my, mx = np.nonzero(mixed)
            chunk = max(1, 1_000_000 // len(sub))
            for k in range(0, len(my), chunk):
                yy, xx = my[k:k + chunk], mx[k:k + chunk]
                pxy = np.stack([xx + 0.0, yy + r0 + 0.0], axis=1)
                sxy = (pxy[:, None, :] + sub[None]).reshape(-1, 2)
                srgb, _ = self.radiance(origin, np.einsum("ij,jk->ik", self.camera_rays(camera, sxy), R))
                band[yy, xx] = srgb.reshape(len(yy), len(sub), 3).mean(axis=1)
            out[r0:r1] = band
            if progress is not None:
                progress(r1)
        return out

    # ----------------------------------------------------------------------------- visibility
    def visible(self, camera: Camera, cam_from_site: Rigid3, points: np.ndarray, normals: np.ndarray,
                max_angle_deg: float = 75.0, border_px: float = 0.0, tol: float = 2e-3) -> np.ndarray:
        """Mask (n,) of site points that project inside the image (``border_px`` from its edges), face
        the camera within ``max_angle_deg`` of their (outward) normal, and are not occluded (the first
        hit along the ray is within ``tol`` metres of the point)."""
        points = np.asarray(points, float).reshape(-1, 3)
        normals = np.asarray(normals, float).reshape(-1, 3)
        center = cam_from_site.center
        to_cam = center - points
        dist = np.linalg.norm(to_cam, axis=1)
        cosang = np.einsum("ij,ij->i", to_cam, normals) / np.maximum(dist, 1e-12)
        ok = cosang >= math.cos(math.radians(max_angle_deg))
        idx = np.nonzero(ok)[0]
        if idx.size:
            uv, front = camera.project(transform_points(cam_from_site, points[idx]))
            ok[idx] = front & camera.in_image(uv, border=border_px)
        idx = np.nonzero(ok)[0]
        if idx.size:
            _, _, t = self.cast(center, -to_cam[idx] / dist[idx, None])
            ok[idx] = t >= dist[idx] - tol
        return ok


def apply_effects(image: np.ndarray, effects: ImageEffects, rng: np.random.Generator) -> np.ndarray:
    """Photometric effects on a float RGB image (h, w, 3) in [0, 1] -> uint8 BGR.

    Exposure and vignetting (per pixel), then optical blur, then additive Gaussian sensor noise,
    processed in bands of rows where possible so 45-MP images stay within memory."""
    h, w = image.shape[:2]
    out = np.empty((h, w, 3), np.uint8)
    band = 512
    cx, cy = (w - 1) / 2.0, (h - 1) / 2.0
    r2max = cx * cx + cy * cy
    xs2 = ((np.arange(w) - cx) ** 2)[None, :]
    for r0 in range(0, h, band):
        r1 = min(h, r0 + band)
        b = image[r0:r1] * np.float32(effects.exposure * 255.0)
        if effects.vignetting > 0:
            r2 = (xs2 + ((np.arange(r0, r1) - cy) ** 2)[:, None]) / r2max
            b *= (1.0 - effects.vignetting * r2).astype(np.float32)[..., None]
        out[r0:r1] = np.clip(b[..., ::-1] + 0.5, 0, 255).astype(np.uint8)
    if effects.blur_sigma > 0:
        cv2.GaussianBlur(out, (0, 0), effects.blur_sigma, dst=out)
    if effects.noise_sigma > 0:
        for r0 in range(0, h, band):
            r1 = min(h, r0 + band)
            noise = rng.standard_normal((r1 - r0, w, 3), dtype=np.float32)
            noisy = out[r0:r1].astype(np.float32) + np.float32(effects.noise_sigma) * noise
            out[r0:r1] = np.clip(noisy + 0.5, 0, 255).astype(np.uint8)
    return out


def box_edge_coverage(s: np.ndarray, theta: float) -> np.ndarray:
    """Fraction of a unit pixel on the positive side of a straight edge (exact area, box filter).

    ``s``: signed distance (px) of the pixel centre from the edge, positive on the covered side;
    ``theta``: direction of the edge (radians). The pixel's area projected on the edge normal has a
    trapezoidal density; the coverage is its cumulative distribution at ``s``."""
    nx, ny = abs(math.sin(theta)), abs(math.cos(theta))
    A, B = 0.5 * (nx + ny), 0.5 * abs(nx - ny)
    h = 1.0 / (A + B)
    ramp = max(A - B, 1e-12)
    t = -np.abs(s)  # evaluate the lower half and mirror
    low = np.where(t <= -A, 0.0,
                   np.where(t <= -B, h * (t + A) ** 2 / (2 * ramp), h * ramp / 2 + h * (t + B)))
    return np.where(s >= 0, 1.0 - low, low)


def fit_xcorner(image: np.ndarray, guess: tuple[float, float], radius: float, inner: float = 2.0
                ) -> np.ndarray:
    """Measure an X-corner (two straight edges crossing, opposite sectors alike) in a float gray image,
    independently of any projection model: a least-squares fit of two lines through a common point to
    the pixels between ``inner`` and ``radius`` pixels of ``guess``, each pixel modelled as the exact
    box-filtered (area) coverage of the sectors, as this renderer produces them. Used to check that
    rendered marker centres sit where the cameras project them.

    Every marker type is such a corner near its aiming point, under any perspective; ``radius`` must
    stay inside the printed pattern. Returns (x, y) in OpenCV pixels.
    """
    from scipy.optimize import least_squares

    gx, gy = float(guess[0]), float(guess[1])
    r = int(np.ceil(radius)) + 1
    x0, y0 = int(round(gx)), int(round(gy))
    ys, xs = np.mgrid[y0 - r:y0 + r + 1, x0 - r:x0 + r + 1]
    if ys.min() < 0 or xs.min() < 0 or ys.max() >= image.shape[0] or xs.max() >= image.shape[1]:
        raise ValueError("fit window leaves the image")
    vals = np.asarray(image, float)[ys, xs]
    rr = np.hypot(xs - gx, ys - gy)
    sel = (rr <= radius) & (rr >= inner)
    X, Y, V = xs[sel].astype(float), ys[sel].astype(float), vals[sel]

    def model(p):
        cx, cy, t1, t2, a, b = p
        p1 = box_edge_coverage((X - cx) * math.sin(t1) - (Y - cy) * math.cos(t1), t1)
        p2 = box_edge_coverage((X - cx) * math.sin(t2) - (Y - cy) * math.cos(t2), t2)
        return b + (a - b) * (p1 * p2 + (1 - p1) * (1 - p2))

    lo, hi = np.percentile(V, 5), np.percentile(V, 95)
    angles = np.deg2rad(np.arange(0.0, 180.0, 6.0))
    best = None
    for i, t1 in enumerate(angles):  # coarse search of the two edge directions
        for t2 in angles[i + 1:]:
            for a, b in ((lo, hi), (hi, lo)):
                p = (gx, gy, t1, t2, a, b)
                e = float(np.sum((model(p) - V) ** 2))
                if best is None or e < best[0]:
                    best = (e, p)
    res = least_squares(lambda p: model(p) - V, best[1], x_scale=[0.1, 0.1, 0.01, 0.01, 0.05, 0.05],
                        bounds=([gx - 3, gy - 3, -10, -10, -2, -2], [gx + 3, gy + 3, 10, 10, 3, 3]))
    return res.x[:2].copy()


__all__ = ["Appearance", "ImageEffects", "SiteRenderer", "sample_texture", "apply_effects", "fit_xcorner",
           "subpixel_pattern", "box_edge_coverage", "transform_points", "MISS", "GROUND"]
