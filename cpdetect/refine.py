"""Sub-pixel refinement of a marker's centre (its central X-corner) in one image.

Pure functions of an image and an approximate centre. The 3D back end reuses them: it projects a
control point into every image where it is visible and calls :func:`refine_center` on the full-
resolution image around the projected point.

Pixel convention: OpenCV's (the centre of the top-left pixel is (0, 0)); x right, y down.

Methods (``method=``):

``"hough"``
    The seed paper's method (section 4.3): Canny edges in a patch around the seed, Hough transform
    for straight lines (normal form x cos(theta) + y sin(theta) = rho), the line with most votes l1 and
    the best second line l2 at 45..135 degrees to it, intersection p = l1 x l2 by the cross product
    of the homogeneous lines. Each Hough line is then re-fitted by least squares to the gradient-
    weighted pixels next to it, which makes the intersection sub-pixel.
``"saddle"``
    A weighted least-squares quadratic surface I ~ a dx^2 + b dx dy + c dy^2 + d dx + e dy + f on the
    image smoothed at a scale adapted to the marker, with Gaussian weights centred at the current
    estimate; the saddle point of the surface is the new estimate; iterated to convergence.
``"symmetry"``
    Point-symmetry fit: two straight lines crossing at p split the plane into four wedges that are
    mapped onto each other by the point reflection about p, so a 2x2 marker (dark, bright, dark,
    bright) seen under any perspective and any isotropic blur satisfies I(p + d) = I(p - d) inside
    the pattern. Gauss-Newton minimises sum_d w(d) (I(p + d) - I(p - d) - 2 g.d)^2 over p (and a
    linear illumination gradient g), with d on a disc (or, given a perspective hint, an ellipse)
    adapted to the marker size. Seeded by ``"saddle"``.
``"model"``
    Least-squares fit of a blurred two-line checker to the raw pixels of the window (disc or ellipse
    as for ``"symmetry"``): I = m + A erf(u / (sqrt 2 b)) erf(v / (sqrt 2 b)) + g.(q - p), with u, v
    the signed distances of pixel q from two straight lines crossing at p (straight under any
    perspective), blur b and a linear illumination gradient g; Levenberg-Marquardt with analytic
    derivatives, first with Tukey weights on the difference between each pixel and its mirror
    image through the seed, then on the first fit's residuals (an occluder in the window). The
    model's error near the centre under unequal blur along non-orthogonal lines is point symmetric
    about p, so it does not move p. Unlike the symmetry fit, which compares the image with itself
    turned 180 degrees (each noise sample counted twice) on a smoothed copy, it uses every raw
    pixel once: on the noisy tilted markers of tests/test_refine.py 0.024 px mean error against the
    symmetry fit's 0.030 on the same outline window, and in the classical detector (``model_fit``)
    0.034 / 0.036 against 0.044 / 0.047 px on two train-split dev sets. It needs a seed within about
    a pixel: ``refine_center(method="model")`` runs ``"auto"`` first and keeps whichever of the two
    has the smaller sigma.
``"auto"`` (default)
    ``"symmetry"`` seeded by ``"saddle"`` on the full window and, when that fit's sigma is over
    0.05 px, on 0.7, 0.5 and 0.35 of it seeded at the caller's point; the fit with the smallest sigma
    is kept (an occluder or the image border spoils the large windows first). When none holds,
    whichever of ``"saddle"`` and ``"hough"`` succeeded with the smaller uncertainty. When symmetry
    succeeds but is uncertain (sigma over 0.15 px: a shadow edge or occluder across the centre),
    ``"hough"`` replaces it if it agrees within 1 px at under half the sigma (a shadow along a
    boundary line: 0.40 -> 0.22 px). Lines crossing farther off replace it only through
    ``"model"``, fitted from their crossing again and again until it settles, within 2 px of the
    crossing and at under half the sigma: one of the lines may be an occluder's edge, which the
    checker model does not fit. An occluder's tip beside the centre can hold every symmetry window
    several pixels off: on the 480 such analytic markers of bench/refine_bench.py, seeds up to 3 px
    off, mean error 0.520 -> 0.290 px, p95 5.06 -> 0.79 px (cv2.cornerSubPix 0.448 / 1.51). On the
    train-split dev sets the classical detector's markers are the same, one of them 3.8 -> 0.06 px
    off; hma found 1 marker more on dev909, its centre mean 0.060 / 0.060 -> 0.059 / 0.060 px.

The window is always derived from the marker's apparent radius (``radius_px``; a fraction of it,
clamped), never fixed: a fixed window either straddles the marker boundary on small markers or
wastes signal on large ones.

A seed that may be tens of pixels off (a detector's coarse pyramid level on a large marker) goes
through :func:`refine_center_coarse_to_fine`: the same refinement on an area-reduced window first,
then at full resolution within half a reduced pixel (on the 45 MP bench image a 450 px marker from
a seed 60 px off: 150-270 ms -> 10-50 ms, and a symmetry fit of sigma 0.010 px where the wide window
fell back on the Hough lines at 0.058).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

METHODS = ("auto", "symmetry", "saddle", "hough", "model")
# "auto" also fits the symmetry on these fractions of the window, unless the full window's fit is
# already this certain (px), and keeps the fit with the smallest sigma
SMALLER_WINDOWS = (0.7, 0.5, 0.35)
CONFIDENT_SIGMA_PX = 0.05
# refine_center_painted tries the paint image when the gray fit's sigma is over this (px)
PAINT_RETRY_SIGMA_PX = 0.1


@dataclass(frozen=True)
class RefineResult:
    """Outcome of one refinement.

    x, y: refined centre (pixels, OpenCV convention); the seed when ``ok`` is False.
    sigma_px: 1-sigma uncertainty of the position (pixels), from the fit residuals and geometry.
    method: the method that produced (x, y). ok: whether it succeeded; reason: why not (or "").
    """

    x: float
    y: float
    sigma_px: float
    method: str
    ok: bool
    reason: str = ""


def _fail(x0: float, y0: float, method: str, reason: str, sigma: float = 1.0) -> RefineResult:
    return RefineResult(float(x0), float(y0), float(sigma), method, False, reason)


def default_window(radius_px: float) -> float:
    """Half-size (pixels) of the fitting window for a marker of apparent radius ``radius_px``.

    About half the radius keeps the window inside the pattern down to ~60 degrees of tilt; clamped to
    [2.5, 40] px (larger windows add little accuracy and cost time).
    """
    return float(np.clip(0.5 * radius_px, 2.5, 40.0))


def default_shift(radius_px: float) -> float:
    """How far (pixels) a refinement may move from its seed unless told: max(2, 0.35 radius)."""
    return max(2.0, 0.35 * radius_px)


class _Patch:
    """A float32 copy of the image around a point, with its origin (x of column 0, y of row 0)."""

    def __init__(self, gray: np.ndarray, cx: float, cy: float, half: int):
        h, w = gray.shape[:2]
        ix, iy = int(round(cx)), int(round(cy))
        self.x0, self.y0 = max(ix - half, 0), max(iy - half, 0)
        x1, y1 = min(ix + half + 1, w), min(iy + half + 1, h)
        self.data = np.asarray(gray[self.y0:y1, self.x0:x1], dtype=np.float32)
        self.valid = self.data.shape[0] >= 5 and self.data.shape[1] >= 5


def _check_inputs(gray: np.ndarray, x0: float, y0: float, radius_px: float) -> np.ndarray:
    a = np.asarray(gray)
    if a.ndim != 2:
        raise ValueError(f"refine_center expects a 2-D gray image, got shape {a.shape}")
    if not (np.isfinite(x0) and np.isfinite(y0)):
        raise ValueError("seed position must be finite")
    if not (np.isfinite(radius_px) and radius_px > 0):
        raise ValueError("radius_px must be positive")
    return a


# --------------------------------------------------------------------------------------------------
# quadratic saddle fit


def refine_saddle(gray: np.ndarray, x0: float, y0: float, radius_px: float, window_px: float | None = None,
                  max_shift_px: float | None = None, max_iter: int = 12) -> RefineResult:
    """Saddle point of a weighted quadratic surface fitted to the smoothed image (see module doc)."""
    import cv2

    gray = _check_inputs(gray, x0, y0, radius_px)
    w = float(window_px) if window_px is not None else default_window(radius_px)
    max_shift = float(max_shift_px) if max_shift_px is not None else default_shift(radius_px)
    # the quadratic model of an X-corner holds within about one blur scale of its centre
    sb = max(0.8, 0.5 * w)
    half = int(math.ceil(w + max_shift + 3 * sb + 2))
    patch = _Patch(gray, x0, y0, half)
    if not patch.valid:
        return _fail(x0, y0, "saddle", "too close to the image border")
    img = cv2.GaussianBlur(patch.data, (0, 0), sb, borderType=cv2.BORDER_REFLECT)
    hh, ww = img.shape
    X, Y = np.meshgrid(np.arange(ww, dtype=np.float64) + patch.x0, np.arange(hh, dtype=np.float64) + patch.y0)
    # pixels whose smoothing reached past the image border saw a mirror image: a marker whose centre
    # is a few pixels from the border would be pulled toward it (0.85 px at 4 px, with a 0.09 px sigma)
    H_img, W_img = gray.shape[:2]
    edge = 2.0 * sb
    usable = (X >= edge) & (X <= W_img - 1 - edge) & (Y >= edge) & (Y <= H_img - 1 - edge)
    d0 = (X - x0) ** 2 + (Y - y0) ** 2 <= w * w
    if usable[d0].sum() < 0.5 * d0.sum():
        return _fail(x0, y0, "saddle", "too close to the image border")
    px, py = float(x0), float(y0)
    sw = max(0.8, 0.5 * w)
    sol = None
    for _ in range(max_iter):
        dx, dy = X - px, Y - py
        r2 = dx * dx + dy * dy
        m = (r2 <= w * w) & usable
        if m.sum() < 12:
            return _fail(x0, y0, "saddle", "window too small")
        wt = np.exp(-0.5 * r2[m] / (sw * sw))
        a, b = dx[m], dy[m]
        A = np.stack([a * a, a * b, b * b, a, b, np.ones_like(a)], axis=1)
        sq = np.sqrt(wt)
        sol, *_ = np.linalg.lstsq(A * sq[:, None], img[m] * sq, rcond=None)
        H = np.array([[2 * sol[0], sol[1]], [sol[1], 2 * sol[2]]])
        if np.linalg.det(H) >= 0:
            return _fail(x0, y0, "saddle", "no saddle point (not an X-corner)")
        step = -np.linalg.solve(H, sol[3:5])
        if np.hypot(*step) > w:
            step *= w / np.hypot(*step)
        px, py = px + step[0], py + step[1]
        if np.hypot(px - x0, py - y0) > max_shift:
            return _fail(x0, y0, "saddle", "moved too far from the seed")
        if np.hypot(*step) < 1e-4:
            break
    # uncertainty: residual noise propagated through the saddle equations (gradient of the surface)
    dx, dy = X - px, Y - py
    r2 = dx * dx + dy * dy
    m = (r2 <= w * w) & usable
    wt = np.exp(-0.5 * r2[m] / (sw * sw))
    a, b = dx[m], dy[m]
    A = np.stack([a * a, a * b, b * b, a, b, np.ones_like(a)], axis=1)
    res = img[m] - A @ sol
    s2 = float(np.sum(wt * res * res) / max(np.sum(wt) - 6, 1.0))
    try:
        cov = s2 * np.linalg.inv((A * wt[:, None]).T @ A)[3:5, 3:5]
        Hinv = np.linalg.inv(np.array([[2 * sol[0], sol[1]], [sol[1], 2 * sol[2]]]))
        pc = Hinv @ cov @ Hinv.T
        sigma = math.sqrt(max(0.5 * np.trace(pc), 0.0))
    except np.linalg.LinAlgError:
        sigma = 1.0
    # the quadratic model is only approximate on a real (blurred step) X-corner: add a model floor
    sigma = math.sqrt(sigma * sigma + 0.05 ** 2)
    return RefineResult(px, py, sigma, "saddle", True)


# --------------------------------------------------------------------------------------------------
# point-symmetry fit


def _cubic_weights(t: float) -> np.ndarray:
    """Keys (a = -0.5) cubic interpolation weights for taps at -1, 0, 1, 2 and fraction t in [0, 1)."""
    t2, t3 = t * t, t * t * t
    return np.array([-0.5 * t3 + t2 - 0.5 * t, 1.5 * t3 - 2.5 * t2 + 1.0,
                     -1.5 * t3 + 2.0 * t2 + 0.5 * t, 0.5 * t3 - 0.5 * t2], np.float32)


def _subpixel_shift(img: np.ndarray, fx: float, fy: float) -> np.ndarray:
    """S[j, i] = img(i + fx, j + fy) by separable cubic interpolation (edges replicated)."""
    import cv2

    kx = _cubic_weights(fx).reshape(1, 4)
    ky = _cubic_weights(fy).reshape(4, 1)
    # filter2D correlates: output(i) = sum_k k[k] img(i + k - anchor); anchor 1 gives taps -1..2
    return cv2.sepFilter2D(img, cv2.CV_32F, kx, ky, anchor=(1, 1), borderType=cv2.BORDER_REPLICATE)


def _symmetry_offsets(w: float, shape_hint: np.ndarray | None) -> np.ndarray:
    """Integer offsets d (n, 2) in one half-plane covering the fitting window (disc or hint ellipse)."""
    n = int(math.ceil(w))
    gx, gy = np.meshgrid(np.arange(-n, n + 1), np.arange(-n, n + 1))
    d = np.stack([gx.ravel(), gy.ravel()], axis=1).astype(np.float64)
    half = (d[:, 1] > 0) | ((d[:, 1] == 0) & (d[:, 0] > 0))
    d = d[half]
    return d[_in_window(d.T, w, shape_hint)]


def _in_window(d: np.ndarray, w: float, shape_hint: np.ndarray | None) -> np.ndarray:
    """Which offsets d (2, n) lie in the fitting window: the disc of radius w, or the hint's ellipse
    with its larger axis normalised to w pixels."""
    if shape_hint is None:
        return np.einsum("ij,ij->j", d, d) <= w * w
    J = np.asarray(shape_hint, float).reshape(2, 2)
    u = np.linalg.solve(J / np.linalg.svd(J, compute_uv=False)[0] * w, d)
    return np.einsum("ij,ij->j", u, u) <= 1.0


def _symmetry_smoothing(window_px: float) -> float:
    """The Gaussian sigma (px) :func:`refine_symmetry` smooths with: light, for stable interpolation
    and gradients."""
    return float(np.clip(0.12 * window_px, 0.7, 2.5))


def refine_symmetry(gray: np.ndarray, x0: float, y0: float, radius_px: float, window_px: float | None = None,
                    max_shift_px: float | None = None, shape_hint: np.ndarray | None = None,
                    max_iter: int = 20) -> RefineResult:
    """Point-symmetry Gauss-Newton fit (see module doc). ``shape_hint``: optional 2x2 matrix mapping
    marker-plane directions to image directions near the centre (e.g. the local Jacobian of the
    image-from-plane homography); only its shape is used, to make the window an ellipse that stays
    inside a foreshortened pattern."""
    import cv2

    gray = _check_inputs(gray, x0, y0, radius_px)
    w = float(window_px) if window_px is not None else default_window(radius_px)
    max_shift = float(max_shift_px) if max_shift_px is not None else default_shift(radius_px)
    ss = _symmetry_smoothing(w)
    half = int(math.ceil(w + max_shift + 3 * ss + 3))
    patch = _Patch(gray, x0, y0, half)
    if not patch.valid:
        return _fail(x0, y0, "symmetry", "too close to the image border")
    img = cv2.GaussianBlur(patch.data, (0, 0), ss, borderType=cv2.BORDER_REFLECT)
    d = _symmetry_offsets(w, shape_hint)
    if len(d) < 8:
        return _fail(x0, y0, "symmetry", "window too small")
    di = d.astype(np.intp)
    n_off = int(np.abs(di).max())
    rr = np.sqrt(np.einsum("ij,ij->i", d, d))
    rmax = rr.max()
    wt = np.where(rr < 0.7 * rmax, 1.0, 0.5 + 0.5 * np.cos(np.pi * (rr - 0.7 * rmax) / (0.3 * rmax + 1e-9)))
    px, py = float(x0), float(y0)
    hh, ww = img.shape
    converged = False
    sn = np.inf
    robust = np.ones(len(d))
    n_robust = 0  # robust weights are updated a few times, then frozen (no oscillation)
    adi = np.abs(di)
    w_all = float(np.sum(wt))
    at = None  # the integer position the offsets' bookkeeping below was made for
    for it in range(max_iter):
        lx, ly = px - patch.x0, py - patch.y0
        ix, iy = int(math.floor(lx)), int(math.floor(ly))
        # every sample p +- d shares the fractional part of p: shift the patch once by exact cubic
        # weights (cv2.remap quantises positions to 1/32 px, which would floor the accuracy)
        # only the window around the current point is filtered: the patch also holds the allowed
        # shift, often far larger (a 450 px marker: 370 px patch, 80 px window). The 5 px margin
        # covers the taps of the shift and the Sobel, so values are those of the whole patch.
        cx0, cy0 = max(ix - n_off - 5, 0), max(iy - n_off - 5, 0)
        sub = img[cy0:min(iy + n_off + 6, hh), cx0:min(ix + n_off + 6, ww)]
        if at != (ix, iy):
            # which offsets count and where their samples lie depend only on the integer position,
            # which stays put over most iterations
            at = (ix, iy)
            # offsets whose pair falls off the patch (marker at the image border) are dropped
            inside = ((ix - adi[:, 0] >= 2) & (ix + adi[:, 0] <= ww - 3)
                      & (iy - adi[:, 1] >= 2) & (iy + adi[:, 1] <= hh - 3))
            every = bool(inside.all())
            if (w_all if every else np.sum(wt[inside])) < 0.4 * w_all:
                return _fail(x0, y0, "symmetry", "window leaves the image")
            dd, dv, wt_in = (d, di, wt) if every else (d[inside], di[inside], wt[inside])
            jx, jy, sw = ix - cx0, iy - cy0, sub.shape[1]
            at_p = (jy + dv[:, 1]) * sw + (jx + dv[:, 0])  # flat indices of p + d and p - d
            at_m = (jy - dv[:, 1]) * sw + (jx - dv[:, 0])
            fixed = -2 * dd
        sh = _subpixel_shift(sub, lx - ix, ly - iy)
        gx = cv2.Sobel(sh, cv2.CV_32F, 1, 0, ksize=3, scale=0.125)
        gy = cv2.Sobel(sh, cv2.CV_32F, 0, 1, ksize=3, scale=0.125)
        sp0 = sh.ravel().take(at_p).astype(np.float64)
        r = sp0 - sh.ravel().take(at_m)
        gxr, gyr = gx.ravel(), gy.ravel()
        J = np.column_stack([gxr.take(at_p).astype(np.float64) - gxr.take(at_m),
                             gyr.take(at_p).astype(np.float64) - gyr.take(at_m), fixed])
        wi = wt_in * (robust if every else robust[inside])
        JW = J * wi[:, None]
        N = JW.T @ J
        try:
            delta = -np.linalg.solve(N, JW.T @ r)
        except np.linalg.LinAlgError:
            return _fail(x0, y0, "symmetry", "degenerate fit (no structure in the window)")
        step = delta[:2]
        sn = float(np.hypot(*step))
        if sn > 0.5 * w:
            step = step * (0.5 * w / sn)
        px, py = px + step[0], py + step[1]
        if np.hypot(px - x0, py - y0) > max_shift:
            return _fail(x0, y0, "symmetry", "moved too far from the seed")
        if sn < 0.05 and n_robust < 3:
            n_robust += 1
            # near the answer: down-weight pairs that are not symmetric at all (an occluder, a
            # neighbouring object) with Tukey weights on the residual after the gradient nuisance
            res_all = np.zeros(len(d))
            res_all[inside] = r + J @ delta - J[:, :2] @ delta[:2]
            scale = 1.4826 * float(np.median(np.abs(res_all[inside]))) + 1e-3
            c = 4.685 * max(scale, 1.0)
            u = np.clip(np.abs(res_all) / c, 0, 1)
            robust = (1 - u * u) ** 2
        if sn < 1e-4 and n_robust >= 1:
            converged = True
            break
    if not converged and sn > 1e-2:
        return _fail(x0, y0, "symmetry", "did not converge")
    wt_f = wt[inside] * robust[inside]
    # residual after solving for the gradient nuisance at the final position
    g = np.linalg.lstsq(J[:, 2:] * np.sqrt(wt_f)[:, None], r * np.sqrt(wt_f), rcond=None)[0]
    res = r - J[:, 2:] @ g
    dof = max(float(np.sum(wt_f)) - 4.0, 1.0)
    s2 = float(np.sum(wt_f * res * res) / dof)
    try:
        cov = s2 * np.linalg.inv(N)[:2, :2]
        sigma = math.sqrt(max(0.5 * float(np.trace(cov)), 0.0))
    except np.linalg.LinAlgError:
        return _fail(x0, y0, "symmetry", "degenerate fit")
    if np.sum(wt_f) < 0.5 * np.sum(wt):
        return RefineResult(px, py, sigma, "symmetry", False, "most of the window is not point symmetric")
    # neighbouring samples are correlated by the smoothing (about 4*pi*ss^2 samples per independent one)
    sigma *= math.sqrt(max(1.0, 4.0 * math.pi * ss * ss))
    sigma = math.sqrt(sigma * sigma + 0.01 ** 2)
    # a pattern that is not point symmetric leaves large residuals relative to its contrast
    contrast = float(np.percentile(np.abs(sp0 - np.median(sp0)), 90)) + 1e-6
    if math.sqrt(s2) > 0.35 * contrast:
        return RefineResult(px, py, sigma, "symmetry", False, "window is not point symmetric")
    return RefineResult(px, py, sigma, "symmetry", True)


# --------------------------------------------------------------------------------------------------
# blurred two-line checker model


def _window_pixels(shape: tuple[int, int], x0: float, y0: float, w: float,
                   shape_hint: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """Integer pixel coordinates (X, Y) inside the image within the window of :func:`refine_symmetry`
    (a disc of radius w, or the hint's ellipse of semi-major axis w) centred at (x0, y0)."""
    n = int(math.ceil(w)) + 1
    ix, iy = int(round(x0)), int(round(y0))
    X, Y = np.meshgrid(np.arange(ix - n, ix + n + 1), np.arange(iy - n, iy + n + 1))
    X, Y = X.ravel(), Y.ravel()
    inside = _in_window(np.stack([X - x0, Y - y0]), w, shape_hint)
    inside &= (X >= 0) & (Y >= 0) & (X < shape[1]) & (Y < shape[0])
    return X[inside], Y[inside]


def _sector_bounds(gray: np.ndarray, x0: float, y0: float, r: float) -> np.ndarray | None:
    """The four angles (radians, image frame, from +x toward +y) where the pattern around (x0, y0)
    changes between dark and bright, from the mean of three rings of radius 0.6-1.0 r (each less its
    own mean, lightly smoothed along the ring); None unless exactly four."""
    import cv2

    th = (np.arange(72) + 0.5) * (2.0 * math.pi / 72)
    rs = r * np.array([0.6, 0.8, 1.0])
    # only the rings' neighbourhood is read (a 45 MP image as float would be 180 MB)
    patch = _Patch(gray, x0, y0, int(math.ceil(r)) + 2)
    mx = (x0 - patch.x0 + rs[:, None] * np.cos(th)[None, :]).astype(np.float32)
    my = (y0 - patch.y0 + rs[:, None] * np.sin(th)[None, :]).astype(np.float32)
    v = cv2.remap(patch.data, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    v = (v - v.mean(1, keepdims=True)).mean(0)
    v = 0.25 * np.roll(v, 1) + 0.5 * v + 0.25 * np.roll(v, -1)
    s = v > 0
    changes = np.nonzero(s != np.roll(s, 1))[0]
    return th[changes] - math.pi / 72 if len(changes) == 4 else None


# refine_model's window is at most this (px, semi-major axis): a fit on its ~6,400 pixels takes
# about 10 ms, and wider ones add little (as for default_window)
MODEL_MAX_WINDOW_PX = 45.0
# refine_in_outline(model=True) fits the model only where the centre's sigma so far is over this
# (px): on the train-split dev sets the 76 markers under it gained 0.0006 px on average (0.0142 ->
# 0.0136), those over 0.02 px 0.005-0.038; the six markers of the 45 MP bench images are all under
# it (0.0104-0.0133), and the fit costs 10-15 ms on each of them (+0.08 s)
MODEL_MIN_SIGMA_PX = 0.015
# the model's blur sigma (px) is sqrt(MODEL_MIN_BLUR_PX^2 + exp(2 log_blur)): a sharp edge still spans
# a pixel (a box of 1 px has sigma 0.29), and the fit never divides by a vanishing blur
MODEL_MIN_BLUR_PX = 0.3


def _model_blur(log_blur: float) -> float:
    return math.sqrt(MODEL_MIN_BLUR_PX ** 2 + math.exp(2.0 * min(max(log_blur, -20.0), 10.0)))


class _CheckerModel:
    """Residuals and Jacobian of :func:`refine_model`'s blurred two-line checker on pixels (X, Y) of
    grey values ``obs``, each residual times ``weights``; parameters p: centre (px, py), the two
    lines' angles, mean level, half contrast, log blur, illumination gradient (gx, gy)."""

    def __init__(self, X: np.ndarray, Y: np.ndarray, obs: np.ndarray):
        self.X, self.Y, self.obs = X, Y, obs
        self.weights = np.ones(X.size)
        self.last = None  # (p, parts): LM asks for the Jacobian where it just took the residuals

    def _parts(self, p: np.ndarray) -> tuple:
        from scipy.special import erf

        if self.last is not None and np.array_equal(self.last[0], p):
            return self.last[1]
        ex, ey = self.X - p[0], self.Y - p[1]
        u = math.cos(p[2]) * ey - math.sin(p[2]) * ex  # signed distances from the two lines (px)
        v = math.cos(p[3]) * ey - math.sin(p[3]) * ex
        s = math.sqrt(2.0) * _model_blur(p[6])
        out = (ex, ey, u, v, s, erf(u / s), erf(v / s))
        self.last = (p.copy(), out)
        return out

    def residuals(self, p: np.ndarray) -> np.ndarray:
        ex, ey, _, _, _, eu, ev = self._parts(p)
        return (p[4] + p[5] * eu * ev + p[7] * ex + p[8] * ey - self.obs) * self.weights

    def jacobian(self, p: np.ndarray) -> np.ndarray:
        ex, ey, u, v, s, eu, ev = self._parts(p)
        amp, t1, t2 = p[5], p[2], p[3]
        du = amp * ev * (2.0 / math.sqrt(math.pi)) * np.exp(-(u / s) ** 2) / s  # d model / d u
        dv = amp * eu * (2.0 / math.sqrt(math.pi)) * np.exp(-(v / s) ** 2) / s
        J = np.empty((self.X.size, 9))
        J[:, 0] = du * math.sin(t1) + dv * math.sin(t2) - p[7]
        J[:, 1] = -du * math.cos(t1) - dv * math.cos(t2) - p[8]
        J[:, 2] = -du * (math.sin(t1) * ey + math.cos(t1) * ex)
        J[:, 3] = -dv * (math.sin(t2) * ey + math.cos(t2) * ex)
        J[:, 4] = 1.0
        J[:, 5] = eu * ev
        b = _model_blur(p[6])
        J[:, 6] = -(du * u + dv * v) * (b * b - MODEL_MIN_BLUR_PX ** 2) / (b * b)  # d/d log_blur
        J[:, 7] = ex
        J[:, 8] = ey
        return J * self.weights[:, None]


def _tukey_sqrt(r: np.ndarray, least_cut: float = 0.0) -> np.ndarray:
    """The square roots of Tukey's biweights of residuals ``r`` (NaN: weight 1) cut at 4.685 robust
    standard deviations (from their median absolute value), or at ``least_cut`` if that is more,
    for weighting residuals directly."""
    a = np.abs(r)
    known = np.isfinite(a)
    if not known.any():
        return np.ones(r.shape)
    c = max(4.685 * (1.4826 * float(np.median(a[known])) + 1e-3), least_cut)
    return np.where(known, 1.0 - np.clip(np.where(known, a, 0.0) / c, 0.0, 1.0) ** 2, 1.0)


def _mirrored(gray: np.ndarray, X: np.ndarray, Y: np.ndarray, x0: float, y0: float, w: float) -> np.ndarray:
    """The image at the mirror images (2 x0 - X, 2 y0 - Y) of pixels (X, Y) through (x0, y0), bilinear;
    NaN where they fall off the image."""
    import cv2

    patch = _Patch(gray, x0, y0, int(math.ceil(w)) + 3)
    mx = (2.0 * x0 - X - patch.x0).astype(np.float32).reshape(1, -1)
    my = (2.0 * y0 - Y - patch.y0).astype(np.float32).reshape(1, -1)
    out = cv2.remap(patch.data, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)[0].astype(np.float64)
    hh, ww = patch.data.shape
    out[(mx[0] < 0) | (my[0] < 0) | (mx[0] > ww - 1) | (my[0] > hh - 1)] = np.nan
    return out


def _lm_fit(model: "_CheckerModel", p: np.ndarray) -> np.ndarray | None:
    """Levenberg-Marquardt fit of ``model`` from ``p`` (at most 60 evaluations); None where it
    diverged: a step to a non-finite parameter (an angle of inf has no cosine, which raises inside
    the residuals) or a non-finite result."""
    from scipy.optimize import least_squares

    try:
        p = least_squares(model.residuals, p, jac=model.jacobian, method="lm", max_nfev=60).x
    except (ValueError, OverflowError):
        return None
    return p if np.all(np.isfinite(p)) else None


def refine_model(gray: np.ndarray, x0: float, y0: float, radius_px: float, window_px: float | None = None,
                 max_shift_px: float | None = None, shape_hint: np.ndarray | None = None) -> RefineResult:
    """Least-squares fit of a blurred two-line checker to the raw pixels of the window (see module
    doc); the seed (x0, y0) must already lie within about a pixel of the centre (e.g. a symmetry
    fit's). window_px: the window's radius, or semi-major axis with ``shape_hint`` (as for
    :func:`refine_symmetry`; default :func:`default_window`, at most MODEL_MAX_WINDOW_PX);
    max_shift_px: how far the centre may move from the seed (default 1 px)."""
    gray = _check_inputs(gray, x0, y0, radius_px)
    w = min(float(window_px) if window_px is not None else default_window(radius_px), MODEL_MAX_WINDOW_PX)
    max_shift = float(max_shift_px) if max_shift_px is not None else 1.0
    X, Y = _window_pixels(gray.shape, x0, y0, w, shape_hint)
    if X.size < 30:
        return _fail(x0, y0, "model", "window too small or off the image")
    obs = gray[Y, X].astype(np.float64)
    # the rings stay inside the window's minor axis
    minor = w if shape_hint is None else w * float(np.divide(*np.linalg.svd(np.asarray(shape_hint, float),
                                                                           compute_uv=False)[::-1]))
    bounds = None
    for frac in (0.7, 0.5, 0.9):
        bounds = _sector_bounds(gray, x0, y0, max(frac * minor, 2.0))
        if bounds is not None:
            break
    if bounds is None:
        return _fail(x0, y0, "model", "no four sectors around the seed")
    # the two lines: boundaries k and k + 2 are the two halves of one line
    a1 = math.atan2(math.sin(bounds[0]) - math.sin(bounds[2]), math.cos(bounds[0]) - math.cos(bounds[2]))
    a2 = math.atan2(math.sin(bounds[1]) - math.sin(bounds[3]), math.cos(bounds[1]) - math.cos(bounds[3]))
    ex0, ey0 = X - x0, Y - y0
    sign = np.sign(math.cos(a1) * ey0 - math.sin(a1) * ex0) * np.sign(math.cos(a2) * ey0 - math.sin(a2) * ex0)
    mean = float(obs.mean())
    # parameters: centre (px), line angles, mean level, half contrast, log blur sigma (px), gradient
    p = np.array([x0, y0, a1, a2, mean, float(np.mean((obs - mean) * sign)), 0.0, 0.0, 0.0])
    full = _CheckerModel(X, Y, obs)
    # the first fit down-weights the pixels unlike their mirror image through the seed (an occluder
    # or a neighbour in the window: the pattern itself is point symmetric), as the symmetry fit does;
    # cut at half the contrast at least: a seed a fraction of a pixel off leaves differences at the
    # edges of a sharp, noise-free pattern, whose other pixels match to 0
    full.weights = _tukey_sqrt(obs - _mirrored(gray, X, Y, x0, y0, w), least_cut=abs(p[5]))
    p = _lm_fit(full, p)
    if p is None:
        return _fail(x0, y0, "model", "fit diverged")
    # the second, from there, those far from the first fit (its residuals taken unweighted)
    full.weights = np.ones(X.size)
    full.weights = _tukey_sqrt(full.residuals(p))
    p = _lm_fit(full, p)
    if p is None:
        return _fail(x0, y0, "model", "fit diverged")
    if math.hypot(p[0] - x0, p[1] - y0) > max_shift:
        return _fail(x0, y0, "model", "moved too far from the seed")
    r, J = full.residuals(p), full.jacobian(p)
    s2 = float(r @ r) / max(float(np.count_nonzero(full.weights)) - 9.0, 1.0)
    try:
        cov = s2 * np.linalg.inv(J.T @ J)
    except np.linalg.LinAlgError:
        return _fail(x0, y0, "model", "degenerate fit")
    if abs(math.remainder(p[2] - p[3], math.pi)) < math.radians(20):
        return _fail(x0, y0, "model", "the two lines are nearly parallel")
    if abs(p[5]) < 3.0 * math.sqrt(s2):
        return _fail(x0, y0, "model", "no checker contrast above the residuals")
    sigma = math.sqrt(max(0.5 * float(cov[0, 0] + cov[1, 1]), 0.0) + 0.005 ** 2)
    return RefineResult(float(p[0]), float(p[1]), sigma, "model", True)


# --------------------------------------------------------------------------------------------------
# Hough lines (seed paper, section 4.3)


def _refit_line(mag: np.ndarray, X: np.ndarray, Y: np.ndarray, theta: float, rho: float, band: float,
                centre: tuple[float, float], hole: float):
    """Weighted total-least-squares line through the gradient-magnitude mass within ``band`` of the
    Hough line (normal form), skipping a ``hole`` around ``centre`` where the two edges mix."""
    c, s = math.cos(theta), math.sin(theta)
    dist = X * c + Y * s - rho
    m = (np.abs(dist) <= band) & (np.hypot(X - centre[0], Y - centre[1]) > hole)
    wts = mag[m].astype(np.float64)
    if wts.size < 6 or wts.sum() <= 0:
        return None
    xs, ys = X[m], Y[m]
    mx, my = np.average(xs, weights=wts), np.average(ys, weights=wts)
    cxx = np.average((xs - mx) ** 2, weights=wts)
    cyy = np.average((ys - my) ** 2, weights=wts)
    cxy = np.average((xs - mx) * (ys - my), weights=wts)
    evals, evecs = np.linalg.eigh(np.array([[cxx, cxy], [cxy, cyy]]))
    normal = evecs[:, 0]
    line = np.array([normal[0], normal[1], -(normal[0] * mx + normal[1] * my)])
    n_eff = wts.sum() ** 2 / np.sum(wts ** 2)
    length = math.sqrt(max(evals[1], 1e-9))
    spread = math.sqrt(max(evals[0], 0.0))
    return line, spread, n_eff, length


def refine_hough(gray: np.ndarray, x0: float, y0: float, radius_px: float, window_px: float | None = None,
                 max_shift_px: float | None = None) -> RefineResult:
    """The seed paper's Hough-line intersection, with a least-squares re-fit of both lines."""
    import cv2

    gray = _check_inputs(gray, x0, y0, radius_px)
    max_shift = float(max_shift_px) if max_shift_px is not None else default_shift(radius_px)
    # lines need length: use most of the pattern, but stay inside it
    R = float(window_px) * 1.4 if window_px is not None else float(np.clip(0.7 * radius_px, 5.0, 80.0))
    half = int(math.ceil(R + max_shift + 2))
    patch = _Patch(gray, x0, y0, half)
    if not patch.valid:
        return _fail(x0, y0, "hough", "too close to the image border")
    img = cv2.GaussianBlur(patch.data, (0, 0), 1.0)
    gx = cv2.Sobel(img, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(img, cv2.CV_32F, 0, 1, ksize=3)
    mag = cv2.magnitude(gx, gy)
    hh, ww = img.shape
    X, Y = np.meshgrid(np.arange(ww, dtype=np.float64) + patch.x0, np.arange(hh, dtype=np.float64) + patch.y0)
    inside = np.hypot(X - x0, Y - y0) <= R
    hi = float(np.percentile(mag[inside], 95))
    if hi <= 1e-3:
        return _fail(x0, y0, "hough", "no edges")
    u8 = np.clip(img, 0, 255).astype(np.uint8)
    edges = cv2.Canny(u8, 0.2 * hi / 4, 0.5 * hi / 4, L2gradient=True)  # Sobel ksize 3 scales by 4
    edges[~inside] = 0
    votes_min = max(5, int(0.5 * R))
    lines = cv2.HoughLines(edges, 0.5, np.pi / 360, votes_min)
    if lines is None:
        return _fail(x0, y0, "hough", "no lines")
    lines = lines[:, 0, :]  # (rho, theta) in patch coordinates, most votes first
    cands = []
    for rho, theta in lines:
        rho_img = rho + patch.x0 * math.cos(theta) + patch.y0 * math.sin(theta)
        if abs(x0 * math.cos(theta) + y0 * math.sin(theta) - rho_img) <= max_shift + 1.0:
            cands.append((float(rho_img), float(theta)))
    if not cands:
        return _fail(x0, y0, "hough", "no line through the seed")
    l1 = cands[0]
    l2 = None
    for c in cands[1:]:
        dth = math.degrees(abs(c[1] - l1[1])) % 180.0
        if 45.0 < dth < 135.0:
            l2 = c
            break
    if l2 is None:
        return _fail(x0, y0, "hough", "no second line at 45..135 degrees")
    hole = max(1.5, 0.12 * R)
    fits = []
    for rh, th in (l1, l2):
        fit = None
        for _ in range(3):  # re-centre the band on the re-fitted line: the Hough line is coarse
            fit = _refit_line(mag, X, Y, th, rh, 2.5, (x0, y0), hole)
            if fit is None:
                return _fail(x0, y0, "hough", "line re-fit failed")
            a, b, c = fit[0]
            th, rh = math.atan2(b, a), -c
        fits.append(fit)
    p = np.cross(fits[0][0], fits[1][0])
    if abs(p[2]) < 1e-9:
        return _fail(x0, y0, "hough", "parallel lines")
    x, y = p[0] / p[2], p[1] / p[2]
    if np.hypot(x - x0, y - y0) > max_shift:
        return _fail(x0, y0, "hough", "moved too far from the seed")
    n1, n2 = fits[0][0][:2], fits[1][0][:2]
    sin_a = abs(n1[0] * n2[1] - n1[1] * n2[0])
    # each line's offset uncertainty ~ edge spread / sqrt(effective samples)
    s_lines = [f[1] / math.sqrt(max(f[2], 1.0)) for f in fits]
    sigma = math.sqrt(s_lines[0] ** 2 + s_lines[1] ** 2) / max(sin_a, 0.3)
    sigma = math.sqrt(sigma * sigma + 0.05 ** 2)
    return RefineResult(float(x), float(y), float(sigma), "hough", True)


# --------------------------------------------------------------------------------------------------


def _unless_lines_do_better(gray: np.ndarray, sym: RefineResult, x0: float, y0: float, radius_px: float,
                            kw: dict, shift: float) -> RefineResult:
    """The symmetry fit, or the Hough-line fit where the window is clearly not point symmetric (sigma
    over 0.15 px: a shadow edge or an occluder across the centre breaks the symmetry everywhere,
    while the boundary lines stay straight) and the lines agree with it within 1 px at a sigma under
    half of its; lines crossing farther off count only through :func:`_settled_model` from their
    crossing (within MODEL_SETTLE_REACH_PX of it and ``shift`` px of the seed (x0, y0), at a sigma
    under half of the symmetry fit's)."""
    if sym.sigma_px <= 0.15:
        return sym
    hough = refine_hough(gray, x0, y0, radius_px, **kw)
    if not (hough.ok and hough.sigma_px < 0.5 * sym.sigma_px):
        return sym
    if np.hypot(hough.x - sym.x, hough.y - sym.y) <= 1.0:
        return hough
    # farther off, one of the lines may be an occluder's edge: the crossing is kept only where the
    # checker model, fitted from it again and again (each fit weighs the pixels by their mirror
    # images through its seed, so a seed a pixel off holds it back), settles near it
    model = _settled_model(gray, hough.x, hough.y, radius_px)
    if model is not None and math.hypot(model.x - hough.x, model.y - hough.y) <= MODEL_SETTLE_REACH_PX \
            and math.hypot(model.x - x0, model.y - y0) <= shift and model.sigma_px < 0.5 * sym.sigma_px:
        return model
    return sym


# _settled_model: refine_model again from its own result until a fit moves less than this (px), at
# most MODEL_SETTLE_FITS times; _unless_lines_do_better keeps it within MODEL_SETTLE_REACH_PX of the
# lines' crossing
MODEL_SETTLE_STEP_PX = 0.05
MODEL_SETTLE_FITS = 8
MODEL_SETTLE_REACH_PX = 2.0


def _settled_model(gray: np.ndarray, x: float, y: float, radius_px: float) -> RefineResult | None:
    """:func:`refine_model` from (x, y), repeated from each result until it settles, or None where a
    fit fails or it has not settled after MODEL_SETTLE_FITS fits."""
    for _ in range(MODEL_SETTLE_FITS):
        fit = refine_model(gray, x, y, radius_px, max_shift_px=1.0)
        if not fit.ok:
            return None
        step = math.hypot(fit.x - x, fit.y - y)
        x, y = fit.x, fit.y
        if step < MODEL_SETTLE_STEP_PX:
            return fit
    return None


def refine_center(gray: np.ndarray, x0: float, y0: float, radius_px: float, method: str = "auto", *,
                  window_px: float | None = None, max_shift_px: float | None = None,
                  shape_hint: np.ndarray | None = None) -> RefineResult:
    """Refine the centre of the marker seen near (``x0``, ``y0``) in ``gray``.

    gray: HxW image (uint8 or float), full resolution; only a window around the seed is read.
    x0, y0: approximate centre (pixels, OpenCV convention), within ``max_shift_px`` of the truth.
    radius_px: approximate apparent radius of the pattern (pixels); sets the window (``window_px``,
        default :func:`default_window`) and the allowed shift (default max(2, 0.35 radius)).
    method: "auto", "symmetry", "saddle", "hough" or "model" (see module doc).
    shape_hint: optional 2x2 local perspective (image directions from marker-plane directions).

    Returns a :class:`RefineResult`; ``ok`` is False (with a ``reason``) when no X-corner was found,
    in which case (x, y) is the seed.
    """
    if method not in METHODS:
        raise ValueError(f"unknown refinement method {method!r}; valid: {', '.join(METHODS)}")
    kw = dict(window_px=window_px, max_shift_px=max_shift_px)
    if method == "saddle":
        return refine_saddle(gray, x0, y0, radius_px, **kw)
    if method == "hough":
        return refine_hough(gray, x0, y0, radius_px, **kw)
    if method == "symmetry":
        return refine_symmetry(gray, x0, y0, radius_px, shape_hint=shape_hint, **kw)
    if method == "model":
        first = refine_center(gray, x0, y0, radius_px, "auto", shape_hint=shape_hint, **kw)
        return _smaller_sigma(first, refine_model(gray, first.x, first.y, radius_px, window_px=window_px,
                                                  shape_hint=shape_hint)) if first.ok else first
    w = float(window_px) if window_px is not None else default_window(radius_px)
    # the saddle seed only needs the X-corner's core: a small window keeps it cheap on big markers
    sad = refine_saddle(gray, x0, y0, radius_px, window_px=min(w, 6.0), max_shift_px=max_shift_px)
    seed = (sad.x, sad.y) if sad.ok else (x0, y0)
    shift = max_shift_px if max_shift_px is not None else default_shift(radius_px)
    # the window that fits best: a full one uses most signal, but an occluder, the image border or a
    # strong tilt spoil large windows first, and the fit's sigma says which held (on 2,461 detector
    # seeds near occluders and image borders, dev and train-split sets: mean error 0.078 -> 0.054 px,
    # on the occluded markers 0.161 -> 0.075 px; bench/refine_bench.py repeats it on 400 images)
    fits = [refine_symmetry(gray, seed[0], seed[1], radius_px, window_px=w, max_shift_px=shift,
                            shape_hint=shape_hint)]
    if not (fits[0].ok and fits[0].sigma_px <= CONFIDENT_SIGMA_PX):  # else smaller ones add only noise
        for frac in SMALLER_WINDOWS:
            if frac * w < 2.5:
                break
            # from the caller's seed: an occluder at the centre can pull the saddle seed off (same
            # seeds, before the saddle border fix: 0.057 px; both seeds for every window 0.059, the
            # saddle seed for all 0.063)
            fits.append(refine_symmetry(gray, x0, y0, radius_px, window_px=frac * w, max_shift_px=shift,
                                        shape_hint=shape_hint))
    held = [f for f in fits if f.ok and np.hypot(f.x - x0, f.y - y0) <= shift]
    if held:
        return _unless_lines_do_better(gray, min(held, key=lambda f: f.sigma_px), x0, y0, radius_px, kw, shift)
    # fall-backs are less robust: keep them only close to the seed
    others = [r for r in (sad, refine_hough(gray, x0, y0, radius_px, **kw))
              if r.ok and np.hypot(r.x - x0, r.y - y0) <= 0.5 * shift]
    if not others:
        return _fail(x0, y0, "auto", f"symmetry: {fits[0].reason}; saddle: {sad.reason}")
    return min(others, key=lambda r: r.sigma_px)


def outline_window(outline: np.ndarray, x: float, y: float, frac: float = 1.0,
                   margin_px: float = 1.0, max_px: float = 40.0) -> tuple[np.ndarray, float] | None:
    """An elliptical symmetry window that stays inside a marker's outline, for :func:`refine_symmetry`.

    outline: the pattern's outline polygon ((n, 2) pixels, OpenCV convention), star-shaped about the
    centre (x, y). The ellipse has the shape of the outline's second moments (a tilted marker's
    foreshortening) and is centred at (x, y); it is scaled so that in every direction both d and -d
    stay within ``frac`` of the outline's distance from the centre, less ``margin_px`` and twice the
    smoothing :func:`refine_symmetry` applies (blur at the outline breaks the point symmetry first),
    and to at most ``max_px`` (as :func:`default_window`: wider adds little and costs time).
    Returns (shape_hint, window_px) as :func:`refine_symmetry` takes them (window_px: the ellipse's
    semi-major axis), or None when the outline is degenerate or does not surround the centre.
    """
    import cv2

    P = np.asarray(outline, float).reshape(-1, 2)
    if len(P) < 3 or not np.all(np.isfinite(P)):
        return None
    P32 = P.astype(np.float32)
    if cv2.pointPolygonTest(P32.reshape(-1, 1, 2), (float(x), float(y)), False) <= 0:
        return None
    mo = cv2.moments(P32)
    if mo["m00"] <= 1e-9:
        return None
    cov = np.array([[mo["mu20"], mo["mu11"]], [mo["mu11"], mo["mu02"]]]) / mo["m00"]
    ev, V = np.linalg.eigh(cov)
    if ev[0] <= 1e-9:
        return None
    J = V @ np.diag(np.sqrt(ev / ev[1])) @ V.T  # unit disc -> the moment ellipse, semi-major 1
    # the outline's distance from the centre by direction: the perimeter sampled densely
    Q = np.vstack([P, P[:1]])
    t = np.linspace(0.0, 1.0, 16, endpoint=False)
    D = (Q[:-1, None, :] + t[None, :, None] * (Q[1:] - Q[:-1])[:, None, :]).reshape(-1, 2) - (x, y)
    ang, rad = np.arctan2(D[:, 1], D[:, 0]), np.hypot(D[:, 0], D[:, 1])
    order = np.argsort(ang)
    th = np.linspace(-math.pi, math.pi, 72, endpoint=False)
    rho = np.interp(th, ang[order], rad[order], period=2 * math.pi)
    rho_sym = np.minimum(rho, np.roll(rho, 36))  # d and -d both inside
    u = np.stack([np.cos(th), np.sin(th)])
    e = 1.0 / np.linalg.norm(np.linalg.solve(J, u), axis=0)  # the unit ellipse's radius by direction
    reach = float(np.min(frac * rho_sym / e)) - margin_px
    # refine_symmetry smooths the image first: keep two of its smoothing sigmas off the outline too
    w = reach
    for _ in range(3):
        w = reach - 2.0 * _symmetry_smoothing(w)
    w = min(w, float(max_px))
    if not w >= 2.5:
        return None
    return J, w


def refine_in_outline(gray: np.ndarray, x: float, y: float, radius_px: float, sigma_px: float,
                      outline: np.ndarray, frac: float = 1.0, model: bool = False) -> RefineResult | None:
    """A refined centre (x, y) of uncertainty ``sigma_px`` fitted again by :func:`refine_symmetry` on
    the :func:`outline_window` of the marker's ``outline`` (image pixels, around that centre); the
    new fit when it holds within 1 px with a smaller sigma, else None (keep the first). A disc sized
    by the radius alone must stay inside the pattern at any tilt, so on most markers it uses a
    fraction of the signal this window does. With ``model``, :func:`refine_model` is then fitted on
    the same ellipse widened by 1.5 px (the symmetry fit keeps 1 px and two of its smoothing sigmas
    off the outline; the model reads raw pixels) from the better of the two, and kept where its
    sigma is the smallest; only where that sigma is over MODEL_MIN_SIGMA_PX (sharp centres gain
    nothing)."""
    win = outline_window(outline, x, y, frac)
    if win is None:
        return None
    res = refine_symmetry(gray, x, y, radius_px, window_px=win[1], max_shift_px=1.0, shape_hint=win[0])
    best = res if res.ok and res.sigma_px < sigma_px and math.hypot(res.x - x, res.y - y) < 1.0 else None
    if model and (best.sigma_px if best is not None else sigma_px) > MODEL_MIN_SIGMA_PX:
        bx, by = (best.x, best.y) if best is not None else (x, y)
        win = outline_window(outline, bx, by, frac)
        if win is not None:
            fit = refine_model(gray, bx, by, radius_px, window_px=win[1] + 1.5, max_shift_px=1.0,
                               shape_hint=win[0])
            if fit.ok and fit.sigma_px < (best.sigma_px if best is not None else sigma_px):
                best = fit
    return best


def _smaller_sigma(a: RefineResult, b: RefineResult) -> RefineResult:
    """``b`` where it succeeded with a smaller sigma than ``a``, else ``a``."""
    return b if b.ok and (not a.ok or b.sigma_px < a.sigma_px) else a


# refine_center_coarse_to_fine settles the centre on a reduced copy first when the seed may be
# further than this from it (px): a full-resolution window that wide costs tens of times a narrow one
COARSE_SHIFT_PX = 16.0


def refine_center_coarse_to_fine(gray: np.ndarray, x0: float, y0: float, radius_px: float, method: str = "auto",
                                 *, max_shift_px: float | None = None) -> RefineResult:
    """:func:`refine_center` for a seed up to ``max_shift_px`` off (default, as there,
    max(2, 0.35 radius)), which can be tens of pixels on a large marker (a detector's coarse
    pyramid level, a projected 3D point). Where the shift exceeds
    COARSE_SHIFT_PX, the window around the seed is first area-reduced by the largest power of two
    that leaves the shift 8 and the radius 8 reduced pixels, refined there, then refined at full
    resolution within half a reduced pixel (at least 2 px); where either step fails, the direct
    refinement over the whole shift. Same conventions and result as :func:`refine_center`."""
    import cv2

    gray = _check_inputs(gray, x0, y0, radius_px)
    shift = float(max_shift_px) if max_shift_px is not None else default_shift(radius_px)
    f = 1
    while 2 * f <= shift / 8.0 and radius_px / (2 * f) >= 8.0:
        f *= 2
    if shift > COARSE_SHIFT_PX and f > 1:
        # a window whose corner and size are multiples of f: reduced pixel j covers full pixels
        # [x0c + j f, x0c + (j + 1) f) exactly, at any position in the image
        half = shift + default_window(radius_px / f) * f + 4 * f
        h, w = gray.shape
        xa, ya = max(0, int(x0 - half) // f * f), max(0, int(y0 - half) // f * f)
        xb, yb = min(w, int(x0 + half) + 1), min(h, int(y0 + half) + 1)
        xb, yb = xa + (xb - xa) // f * f, ya + (yb - ya) // f * f
        if xb - xa >= 8 * f and yb - ya >= 8 * f:
            crop = cv2.resize(np.asarray(gray[ya:yb, xa:xb], np.float32), ((xb - xa) // f, (yb - ya) // f),
                              interpolation=cv2.INTER_AREA)
            c = refine_center(crop, (x0 - xa + 0.5) / f - 0.5, (y0 - ya + 0.5) / f - 0.5, radius_px / f,
                              method=method, max_shift_px=max(shift / f, 1.0))
            cx, cy = xa + (c.x + 0.5) * f - 0.5, ya + (c.y + 0.5) * f - 0.5
            if c.ok and math.hypot(cx - x0, cy - y0) <= shift:
                fine = refine_center(gray, cx, cy, radius_px, method=method, max_shift_px=max(2.0, 0.5 * f))
                if fine.ok:
                    return fine
    return refine_center(gray, x0, y0, radius_px, method=method, max_shift_px=shift)


def refine_center_painted(gray: np.ndarray, paint, x0: float, y0: float, radius_px: float, method: str = "auto",
                          retry_sigma_px: float = PAINT_RETRY_SIGMA_PX, max_shift_px: float | None = None
                          ) -> RefineResult:
    """:func:`refine_center_coarse_to_fine` on ``gray`` and, where that fails or is uncertain (sigma
    over ``retry_sigma_px``), also on the *paint* image of the same photo (the max of its channels,
    see :func:`cpdetect.imageio.paint_image`); the fit with the smaller sigma wins. A marker painted
    red on black can have almost no luminance contrast while its paint stands out. ``paint``: an
    array of the gray image's size, or a callable returning one (called only when needed), or None.
    ``max_shift_px``: as in :func:`refine_center` (default max(2, 0.35 radius))."""
    res = refine_center_coarse_to_fine(gray, x0, y0, radius_px, method=method, max_shift_px=max_shift_px)
    if paint is None or (res.ok and res.sigma_px <= retry_sigma_px):
        return res
    img = paint() if callable(paint) else paint
    return _smaller_sigma(res, refine_center_coarse_to_fine(img, x0, y0, radius_px, method=method,
                                                            max_shift_px=max_shift_px))


__all__ = ["RefineResult", "outline_window", "refine_center", "refine_center_coarse_to_fine", "refine_center_painted",
           "refine_in_outline", "refine_model", "refine_saddle", "refine_symmetry", "refine_hough", "default_window",
           "METHODS"]
