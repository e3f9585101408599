"""The classical marker detector (``classical``): CPU only, numpy + OpenCV, no torch.

Pipeline for one image:

1. **Search image.** The gray image reduced by k in {1, 2, 4, 8} (area averaging) so that it has at
   most ``search_megapixels``; for a path, the full-resolution gray image is decoded once (it is
   needed for refinement anyway) and the search copy is made with ``cv2.resize(INTER_AREA)``.
2. **Candidates** (:mod:`cpdetect.xcorner`): multi-scale Hessian-determinant X-corner response on the
   search image pyramid, local maxima above a contrast threshold.
3. **Verification** against the marker model, by polar sampling around the candidate (rings sampled
   from the pyramid level that matches their spacing, so any marker size costs the same):
   a core of rings whose angular profile is two dark and two bright sectors (second angular harmonic
   dominant, constant phase: under perspective, lines through the centre stay lines through it),
   exactly four alternating sectors, opposite sectors of equal level, uniform sectors, enough contrast;
   then per-ray boundaries of the sectors (where the pattern ends), the outline model fitted to them
   (square: two straight sides per sector; diagonal: one straight side; circle: an ellipse), and an
   outer ring beyond the outline that must not continue the checker (rejects X-corners inside larger
   checkerboards and tag bit patterns). Grout and mullion crosses fail the sector test (thin lines,
   not solid wedges); edges, text and texture fail the core or the outline.
4. **Type** from the outline model with the smallest residual; **radius_px** from the outline area.
5. **Centre** by :func:`cpdetect.refine.refine_center` on the full-resolution image, window adapted to
   the radius; **sigma_px** from the fit.
6. **Probability map** at search resolution: the filled outline of each accepted marker (1 inside).

All positions reported are full-resolution pixels, OpenCV convention.
"""
from __future__ import annotations

import math
import os
import time
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from .detector import as_gray_uint8, settings_from_dataclass
from .refine import refine_center
from .types import DetectionResult, MarkerDetection
from .xcorner import Candidate, build_pyramid, find_candidates

TWO_PI = 2.0 * np.pi


@dataclass(frozen=True)
class ClassicalSettings:
    """Settings of the classical detector (all lengths in full-resolution pixels unless noted).

    min_radius_px: smallest marker radius reported (smaller ones are found only down to ~3 search
        pixels, i.e. 3 * k full-resolution pixels for search reduction k).
    max_radius_frac: largest marker radius as a fraction of the image's short side.
    min_contrast: least bright-minus-dark difference of a marker (grey levels, 0..255).
    search_megapixels: size cap of the search image (sets the reduction k).
    max_candidates_per_level: cap on X-corner candidates per pyramid level.
    min_score: detections below this score are dropped.
    refine_method: "auto", "symmetry", "saddle" or "hough" (see cpdetect.refine).
    probability_map: compute the probability map (filled outlines).
    """

    min_radius_px: float = 8.0
    max_radius_frac: float = 1.0 / 3.0
    min_contrast: float = 25.0
    search_megapixels: float = 3.2
    max_candidates_per_level: int = 300
    min_score: float = 0.3
    refine_method: str = "auto"
    probability_map: bool = True

    def __post_init__(self) -> None:
        if not self.min_radius_px > 0:
            raise ValueError("min_radius_px must be positive")
        if not 0 < self.max_radius_frac <= 1:
            raise ValueError("max_radius_frac must be in (0, 1]")
        if not self.min_contrast > 0:
            raise ValueError("min_contrast must be positive")
        if not self.search_megapixels > 0.05:
            raise ValueError("search_megapixels must be > 0.05")
        if self.refine_method not in ("auto", "symmetry", "saddle", "hough"):
            raise ValueError(f"unknown refine_method {self.refine_method!r}")


# ------------------------------------------------------------------------------------------------
# multi-resolution sampling


class _Levels:
    """Images of one photo at several scales: (scale s, float32 image); level pixel = (full + .5)/s - .5."""

    def __init__(self, full: np.ndarray | None, search_k: int, pyramid: list[np.ndarray]):
        self.items: list[tuple[float, np.ndarray]] = []
        if full is not None and search_k > 1:
            self.items.append((1.0, full))
        for i, lev in enumerate(pyramid):
            self.items.append((float(search_k * 2 ** i), lev))

    def pick(self, spacing: float) -> tuple[float, np.ndarray]:
        """The coarsest level whose pixel is no larger than ``spacing`` full-res pixels."""
        best = self.items[0]
        for s, img in self.items:
            if s <= max(spacing, self.items[0][0]):
                best = (s, img)
        return best

    def sample(self, xs: np.ndarray, ys: np.ndarray, spacing: np.ndarray) -> np.ndarray:
        """Bilinear samples at full-res points (xs, ys) (same shape), each from the level matched to
        its ``spacing`` (broadcast to the shape); outside the image -> NaN."""
        import cv2

        spacing = np.broadcast_to(spacing, xs.shape)
        out = np.full(xs.shape, np.nan, np.float32)
        scales = [s for s, _ in self.items]
        idx = np.zeros(xs.shape, np.intp)
        for i, s in enumerate(scales):
            idx[spacing >= s] = i
        for i in np.unique(idx):
            s, img = self.items[i]
            m = idx == i
            lx = ((xs[m] + 0.5) / s - 0.5).astype(np.float32).reshape(-1, 1)
            ly = ((ys[m] + 0.5) / s - 0.5).astype(np.float32).reshape(-1, 1)
            v = cv2.remap(img, lx, ly, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=np.nan)
            out[m] = v.ravel()
        return out


# ------------------------------------------------------------------------------------------------
# verification


@dataclass
class _Verified:
    x: float
    y: float
    type: str
    radius: float
    score: float
    outline: np.ndarray  # (k, 2) full-res polygon of the pattern


def _wrap(a: np.ndarray | float) -> np.ndarray | float:
    return (np.asarray(a) + np.pi) % TWO_PI - np.pi


def _line_fit(pts: np.ndarray) -> tuple[np.ndarray, float]:
    """TLS line (a, b, c) with a x + b y + c = 0, |(a, b)| = 1, and its RMS residual."""
    m = pts.mean(0)
    q = pts - m
    _, s, vt = np.linalg.svd(q, full_matrices=False)
    n = vt[-1]
    line = np.array([n[0], n[1], -n @ m])
    return line, float(s[-1] / math.sqrt(max(len(pts), 1)))


def _two_line_fit(pts: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Best split of an ordered polyline into two straight parts: (rms, line1, line2)."""
    n = len(pts)
    best = (np.inf, None, None)
    for k in range(max(3, n // 5), min(n - 2, n - n // 5)):
        # the points next to the corner are rounded by blur: leave one out on each side
        l1, e1 = _line_fit(pts[:k - 1])
        l2, e2 = _line_fit(pts[k:])
        e = math.sqrt((e1 * e1 * (k - 1) + e2 * e2 * (n - k)) / (n - 1))
        if e < best[0]:
            best = (e, l1, l2)
    return best


def _ellipse_residual(pts: np.ndarray) -> tuple[float, Any]:
    import cv2

    if len(pts) < 6:
        return np.inf, None
    try:
        (cx, cy), (a, b), ang = cv2.fitEllipse(pts.astype(np.float32))
    except cv2.error:
        return np.inf, None
    if not (a > 0 and b > 0):
        return np.inf, None
    t = math.radians(ang)
    c, s = math.cos(t), math.sin(t)
    dx, dy = pts[:, 0] - cx, pts[:, 1] - cy
    u = (c * dx + s * dy) / (a / 2)
    v = (-s * dx + c * dy) / (b / 2)
    rho = np.hypot(u, v)
    res = (rho - 1.0) * math.sqrt(a * b) / 2
    return float(np.sqrt(np.mean(res * res))), ((cx, cy), (a, b), ang)


def _intersect(l1: np.ndarray, l2: np.ndarray) -> np.ndarray | None:
    p = np.cross(l1, l2)
    if abs(p[2]) < 1e-9:
        return None
    return p[:2] / p[2]


class _Verifier:
    """Checks candidates against the marker model; see the module doc, step 3."""

    N_THETA = 72

    def __init__(self, levels: _Levels, settings: ClassicalSettings, image_size: tuple[int, int]):
        self.levels = levels
        self.s = settings
        self.w, self.h = image_size
        self.max_radius = settings.max_radius_frac * min(self.w, self.h)
        self.theta = (np.arange(self.N_THETA) + 0.5) * TWO_PI / self.N_THETA
        self.cos, self.sin = np.cos(self.theta), np.sin(self.theta)

    def polar(self, x: float, y: float, radii: np.ndarray, spacing: np.ndarray) -> np.ndarray:
        """(n_radii, N_THETA) samples on rings around (x, y) (full-res pixels)."""
        xs = x + radii[:, None] * self.cos[None, :]
        ys = y + radii[:, None] * self.sin[None, :]
        return self.levels.sample(xs, ys, np.broadcast_to(spacing[:, None], xs.shape))

    # -- step 3a: the four-sector core --------------------------------------------------------
    def core(self, x: float, y: float, r_start: float):
        """Sector structure from rings starting at ``r_start``: returns a dict or a reason string."""
        r_hi = max(self.max_radius * 1.7, r_start * 2)
        n = int(math.ceil(math.log(r_hi / r_start) / math.log(1.08))) + 1
        radii = r_start * 1.08 ** np.arange(n)
        P = self.polar(x, y, radii, radii * (TWO_PI / self.N_THETA))
        valid_ring = ~np.isnan(P).any(1)
        if not valid_ring[:3].all():
            return "too close to the border"
        mean = np.nanmean(P, 1, keepdims=True)
        std = np.nanstd(P, 1) + 1e-6
        e2 = np.exp(-2j * self.theta)
        h2 = np.nanmean((P - mean) * e2[None, :], 1)
        q = math.sqrt(2) * np.abs(h2) / std
        phi = np.angle(h2)
        # the core: consecutive rings from the start with a strong, steady second harmonic
        if q[0] < 0.55:
            return "no four-sector pattern"
        ref = phi[0]
        end = 0
        for i in range(1, n):
            if not valid_ring[i] or q[i] < 0.55 or abs(_wrap(phi[i] - ref)) > math.radians(25):
                break
            end = i
            ref = np.angle(np.exp(1j * ref) * 0.7 + np.exp(1j * phi[i]) * 0.3)
        if end < 2:
            return "four-sector core too small"
        core = slice(0, end + 1)
        Pn = (P[core] - mean[core]) / std[core, None]
        T = Pn.mean(0)
        sign = T > 0
        changes = np.nonzero(sign != np.roll(sign, 1))[0]  # index i: sign differs from i-1
        if len(changes) != 4:
            return f"{len(changes)} sectors, not 4"
        # sector boundaries (angles) by linear interpolation of T between samples i-1 and i
        bounds = []
        for i in changes:
            t0, t1 = T[i - 1], T[i]
            f = t0 / (t0 - t1)
            bounds.append(self.theta[i - 1] + f * (TWO_PI / self.N_THETA))
        bounds = np.sort(np.mod(np.array(bounds), TWO_PI))
        widths = np.diff(np.concatenate([bounds, bounds[:1] + TWO_PI]))
        if widths.min() < math.radians(25) or widths.max() > math.radians(155):
            return "sector widths implausible"
        # sector levels (raw grey), skipping 8 degrees next to each boundary
        Praw = P[core]
        levels, spreads, dark_flags = [], [], []
        for k in range(4):
            a0, a1 = bounds[k], bounds[k] + widths[k]
            rel = np.mod(self.theta - a0, TWO_PI)
            m = (rel > math.radians(8)) & (rel < widths[k] - math.radians(8))
            if m.sum() < 2:
                return "sector too narrow"
            vals = Praw[:, m]
            levels.append(float(np.nanmedian(vals)))
            spreads.append(float(np.nanmedian(np.abs(vals - levels[-1]))))
            mid = np.mod(a0 + 0.5 * widths[k], TWO_PI)
            dark_flags.append(T[int(mid / (TWO_PI / self.N_THETA)) % self.N_THETA] < 0)
        dark_flags = np.array(dark_flags)
        if dark_flags.sum() != 2 or dark_flags[0] == dark_flags[1]:
            return "sectors do not alternate"
        lv = np.array(levels)
        D, B = lv[dark_flags].mean(), lv[~dark_flags].mean()
        C = B - D
        if C < self.s.min_contrast:
            return f"contrast {C:.0f} below {self.s.min_contrast:.0f}"
        if abs(np.diff(lv[dark_flags])[0]) > 0.35 * C or abs(np.diff(lv[~dark_flags])[0]) > 0.35 * C:
            return "opposite sectors differ"
        if max(spreads) > 0.2 * C:
            return "sectors not uniform"
        return dict(radii=radii, P=P, core_end=end, bounds=bounds, widths=widths, dark=dark_flags,
                    D=D, B=B, C=C, q=float(np.mean(q[core])))

    # -- step 3b: boundaries, outline model, outer ring -----------------------------------------
    def ray_boundaries(self, P: np.ndarray, radii: np.ndarray, start: int, polarity_dark: bool,
                       level: float, C: float):
        """Per ray: where the sector (grey ``level``) ends, outward from ring ``start``.

        The ray departs when it differs from ``level`` by more than C/4 (brighter for a dark ray,
        darker for a bright one); the boundary is the crossing of the mid-value between ``level`` and
        the value just outside, interpolated between rings. Returns (boundary radius, step size); NaN
        where the sector does not end inside the sampled range.
        """
        sgn = 1.0 if polarity_dark else -1.0
        dev = sgn * (P - level)
        beyond = dev > 0.25 * C
        beyond[:start] = False
        nr, nt = P.shape
        out = np.full(nt, np.nan)
        steps = np.full(nt, np.nan)
        has = beyond.any(0)
        first = np.argmax(beyond, 0)
        for j in np.nonzero(has)[0]:
            i = int(first[j])
            col = dev[:, j]
            outside = float(np.nanmedian(col[i:min(i + 3, nr)]))
            if not np.isfinite(outside):
                continue
            t = 0.5 * outside
            i0 = i
            while i0 > max(start - 1, 0) and col[i0 - 1] > t:
                i0 -= 1
            if i0 == 0 or not (col[i0 - 1] <= t < col[i0]) and not col[i0 - 1] <= t:
                continue
            v0, v1 = col[i0 - 1], col[i0]
            f = (t - v0) / (v1 - v0) if v1 != v0 else 0.5
            out[j] = radii[i0 - 1] + float(np.clip(f, 0, 1)) * (radii[i0] - radii[i0 - 1])
            steps[j] = outside
        return out, steps

    def sector_of(self, bounds: np.ndarray, widths: np.ndarray):
        """Per ray: sector index and relative position f in [0, 1] within it."""
        sec = np.zeros(self.N_THETA, np.intp)
        f = np.zeros(self.N_THETA)
        for k in range(4):
            rel = np.mod(self.theta - bounds[k], TWO_PI)
            m = rel < widths[k]
            sec[m] = k
            f[m] = rel[m] / widths[k]
        return sec, f

    def verify(self, x: float, y: float, r_start: float) -> _Verified | str:
        core = self.core(x, y, r_start)
        if isinstance(core, str):
            return core
        D, B, C = core["D"], core["B"], core["C"]
        sec, f = self.sector_of(core["bounds"], core["widths"])
        inner = (f > 0.12) & (f < 0.88)
        # rough extent from the geometric rings, for either polarity
        best = None
        for pol_dark in (True, False):
            rays = inner & (core["dark"][sec] == pol_dark)
            b, st = self.ray_boundaries(core["P"], core["radii"], core["core_end"] // 2 + 1, pol_dark,
                                        D if pol_dark else B, C)
            b, st = b[rays], st[rays]
            frac = np.mean(np.isfinite(b)) if b.size else 0.0
            strength = frac * (np.nanmedian(st) if np.isfinite(st).any() else 0.0)
            if best is None or strength > best[0]:
                best = (strength, pol_dark, b, frac)
        _, pol_dark, b, frac = best
        if frac < 0.75:
            return "marker boundary not found"
        r0 = float(np.sqrt(np.nanmean(b ** 2)))  # rough: rms boundary distance of one polarity
        if r0 < 0.6 * self.s.min_radius_px or r0 > 1.5 * self.max_radius:
            return "size out of range"
        # precise pass: linear rings 0.25 r0 .. 2.2 r0
        n_r = 72
        radii = np.linspace(0.25 * r0, 2.2 * r0, n_r)
        step = radii[1] - radii[0]
        P = self.polar(x, y, radii, np.full(n_r, max(step, 1.0)))
        rays = inner & (core["dark"][sec] == pol_dark)
        bnd, _ = self.ray_boundaries(P, radii, 1, pol_dark, D if pol_dark else B, C)
        ok = rays & np.isfinite(bnd)
        if ok.sum() < 0.7 * rays.sum():
            return "marker boundary not found (fine pass)"
        # outline model per sector of the boundary polarity
        pts_by_sector = {}
        for k in np.nonzero(core["dark"] == pol_dark)[0]:
            m = ok & (sec == k)
            order = np.argsort(f[m])
            js = np.nonzero(m)[0][order]
            pts = np.stack([x + bnd[js] * self.cos[js], y + bnd[js] * self.sin[js]], 1)
            if len(pts) < 6:
                return "too few boundary points"
            pts_by_sector[k] = pts
        all_pts = np.concatenate(list(pts_by_sector.values()))
        e1 = [_line_fit(p) for p in pts_by_sector.values()]
        e2 = [_two_line_fit(p) for p in pts_by_sector.values()]
        e_line = math.sqrt(np.mean([e[1] ** 2 for e in e1]))
        e_two = math.sqrt(np.mean([e[0] ** 2 for e in e2]))
        e_ell, ell = _ellipse_residual(all_pts)
        floor = 0.12 + 0.01 * r0
        self.last_fit = (e_line, e_two, e_ell, r0)
        if e_line <= max(2.0 * e_two, floor) and e_line < 0.05 * r0:
            mtype = "diagonal"
        elif e_two < e_ell:
            mtype = "square"
        else:
            mtype = "circle"
        e_model = {"diagonal": e_line, "square": e_two, "circle": e_ell}[mtype]
        if not e_model < 0.08 * r0 + 0.3:
            return f"outline does not fit ({mtype})"
        outline = self.outline(mtype, x, y, core, pol_dark, e1, e2, ell)
        if outline is None:
            return "outline degenerate"
        area = 0.5 * abs(np.dot(outline[:, 0], np.roll(outline[:, 1], -1))
                         - np.dot(outline[:, 1], np.roll(outline[:, 0], -1)))
        radius = math.sqrt(area / math.pi)
        if radius < 0.8 * self.s.min_radius_px or radius > self.max_radius * 1.1:
            return "size out of range"
        reason = self.outer_ring(x, y, outline, D, B, C)
        if reason:
            return reason
        fit_q = max(0.0, 1.0 - e_model / (0.08 * r0 + 0.3))
        score = float(np.clip(min(1.0, core["q"] / 0.8) * min(1.0, C / (2.5 * self.s.min_contrast))
                              * (0.5 + 0.5 * fit_q) * (0.6 + 0.4 * ok.sum() / max(rays.sum(), 1)), 0, 1))
        return _Verified(x, y, mtype, radius, score, outline)

    def outline(self, mtype, x, y, core, pol_dark, e1, e2, ell) -> np.ndarray | None:
        import cv2

        if mtype == "circle":
            (cx, cy), (a, b), ang = ell
            poly = cv2.ellipse2Poly((0, 0), (int(a * 8), int(b * 8)), int(round(ang)), 0, 360, 5)
            return poly.astype(np.float64) / 16.0 + np.array([cx, cy])
        secs = np.nonzero(core["dark"] == pol_dark)[0]
        if mtype == "square":
            (l1a, l1b), (l2a, l2b) = (e2[0][1], e2[0][2]), (e2[1][1], e2[1][2])
            c1, c3 = _intersect(l1a, l1b), _intersect(l2a, l2b)
            # the other two corners: each side of one sector meets the non-parallel side of the other
            def par(l, m):
                return abs(l[0] * m[1] - l[1] * m[0])
            m_for_a = l2a if par(l1a, l2a) > par(l1a, l2b) else l2b
            m_for_b = l2b if m_for_a is l2a else l2a
            c2, c4 = _intersect(l1a, m_for_a), _intersect(l1b, m_for_b)
            pts = [c for c in (c1, c2, c3, c4) if c is not None]
            if len(pts) < 4:
                return None
            pts = np.array(pts)
        else:  # diagonal: each sector's side ends on the sector boundary rays
            pts = []
            for k, (line, _) in zip(secs, e1):
                for ang in (core["bounds"][k], core["bounds"][k] + core["widths"][k]):
                    ray = np.cross([x, y, 1.0], [x + math.cos(ang), y + math.sin(ang), 1.0])
                    p = _intersect(line, ray)
                    if p is None:
                        return None
                    pts.append(p)
            pts = np.array(pts)
        # order counter-clockwise around the centre
        ang = np.arctan2(pts[:, 1] - y, pts[:, 0] - x)
        pts = pts[np.argsort(ang)]
        if np.hypot(pts[:, 0] - x, pts[:, 1] - y).max() > 4 * self.max_radius:
            return None
        return pts

    def outer_ring(self, x, y, outline, D, B, C) -> str:
        """Beyond the outline (1.3..1.6 times its distance) the checker must not continue."""
        ang = self.theta
        # distance from the centre to the outline polygon along each ray
        dist = np.full(self.N_THETA, np.nan)
        P = outline - np.array([x, y])
        Q = np.roll(P, -1, 0)
        for j, (c, s) in enumerate(zip(self.cos, self.sin)):
            best = np.inf
            for p, q in zip(P, Q):
                e = q - p
                den = c * e[1] - s * e[0]
                if abs(den) < 1e-12:
                    continue
                t = (p[0] * e[1] - p[1] * e[0]) / den
                u = (p[0] * s - p[1] * c) / den
                if t > 0 and -1e-9 <= u <= 1 + 1e-9:
                    best = min(best, t)
            dist[j] = best
        if not np.isfinite(dist).all():
            return "outline does not enclose the centre"
        radii = np.array([1.35, 1.6])
        xs = x + radii[:, None] * dist[None, :] * self.cos[None, :]
        ys = y + radii[:, None] * dist[None, :] * self.sin[None, :]
        V = self.levels.sample(xs, ys, np.maximum(dist[None, :] * 0.087, 1.0) * np.ones_like(xs))
        for row in V:
            row = row[np.isfinite(row)]
            if row.size < 0.5 * self.N_THETA:
                continue
            cls = np.where(row < D + 0.25 * C, -1, np.where(row > B - 0.25 * C, 1, 0))
            seq = cls[cls != 0]
            if seq.size == 0:
                continue
            alternations = int(np.sum(seq != np.roll(seq, 1)))
            fd, fb = np.mean(cls == -1), np.mean(cls == 1)
            if alternations >= 6 and fd > 0.15 and fb > 0.15:
                return "checker continues beyond the outline (checkerboard or tag)"
        return ""


# ------------------------------------------------------------------------------------------------


class ClassicalDetector:
    """Finds 2x2 markers (square, circle, diagonal) with classical image processing; see module doc.

    ``detect(image)`` takes a uint8 gray (HxW) or BGR (HxWx3) array, or a path to an image file
    (decoded once in gray). Keyword settings: see :class:`ClassicalSettings`.
    """

    name = "classical"
    Settings = ClassicalSettings

    def __init__(self, **settings: Any):
        self.settings = settings_from_dataclass(ClassicalSettings, settings)

    def settings_dict(self) -> dict:
        return asdict(self.settings)

    def detect(self, image: Any) -> DetectionResult:
        t0 = time.perf_counter()
        if isinstance(image, (str, os.PathLike)):
            from .imageio import read_image

            gray = read_image(image, gray=True)
        else:
            a = np.asarray(image)
            if a.dtype != np.uint8:
                raise ValueError(f"expected a uint8 image, got {a.dtype}")
            gray = as_gray_uint8(a)
        res = self._detect_gray(gray)
        res.seconds = time.perf_counter() - t0
        return res

    def _search_factor(self, w: int, h: int) -> int:
        for k in (1, 2, 4, 8):
            if (w / k) * (h / k) <= self.settings.search_megapixels * 1e6:
                return k
        return 8

    def _detect_gray(self, gray: np.ndarray) -> DetectionResult:
        import cv2

        s = self.settings
        h, w = gray.shape
        k = self._search_factor(w, h)
        if k > 1:
            search = cv2.resize(gray, ((w + k - 1) // k, (h + k - 1) // k), interpolation=cv2.INTER_AREA)
        else:
            search = gray
        # levels fine enough for the smallest marker, coarse enough for the largest
        pyramid = build_pyramid(search)
        full = gray.astype(np.float32) if k > 1 else None
        levels = _Levels(full, k, pyramid)
        cands = find_candidates(pyramid, 0.5 * s.min_contrast, s.max_candidates_per_level)
        verifier = _Verifier(levels, s, (w, h))
        accepted: list[tuple[_Verified, Any]] = []
        rejected = 0
        # coarse levels first: big markers are settled before their centres show again at fine levels
        cands.sort(key=lambda c: (-c.level, -c.contrast))
        for c in cands:
            scale = k * 2 ** c.level
            cx, cy = (c.x + 0.5) * k - 0.5, (c.y + 0.5) * k - 0.5
            if any(math.hypot(cx - v.x, cy - v.y) < max(0.5 * v.radius, 2.0 * scale) for v, _ in accepted):
                continue
            r_start = max(1.5, 1.5 * scale)
            v = verifier.verify(cx, cy, r_start)
            if isinstance(v, str):
                rejected += 1
                continue
            ref = refine_center(gray, v.x, v.y, v.radius, method=s.refine_method,
                                max_shift_px=max(2.0 * scale, 0.3 * v.radius))
            if ref.ok:
                if any(math.hypot(ref.x - a.x, ref.y - a.y) < 0.5 * a.radius for a, _ in accepted):
                    continue
                v = _Verified(ref.x, ref.y, v.type, v.radius, v.score, v.outline + [ref.x - v.x, ref.y - v.y])
                sigma = ref.sigma_px
            else:
                sigma = max(0.5 * scale, 0.5)
                v.score *= 0.7
            if v.score < s.min_score:
                continue
            accepted.append((v, sigma))
        accepted.sort(key=lambda t: -t[0].score)
        dets = [MarkerDetection(float(np.clip(v.x, -0.5, w - 0.5)), float(np.clip(v.y, -0.5, h - 0.5)),
                                float(v.score), v.type, float(v.radius), float(sigma)) for v, sigma in accepted]
        prob = None
        if s.probability_map:
            sh, sw = search.shape
            prob = np.zeros((sh, sw), np.float32)
            for v, _ in accepted:
                poly = ((v.outline + 0.5) / k - 0.5) * 16.0
                cv2.fillPoly(prob, [np.round(poly).astype(np.int32)], 1.0, lineType=cv2.LINE_AA, shift=4)
            np.clip(prob, 0.0, 1.0, out=prob)
        extras = {"search_factor": k, "candidates": len(cands), "rejected": rejected}
        return DetectionResult(dets, (w, h), prob, 0.0, extras)


__all__ = ["ClassicalDetector", "ClassicalSettings"]
