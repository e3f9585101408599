"""Coordinate reference systems of surveyed points, and the metric local frame registration works in.

Never fit a similarity in (easting, northing, height) over a large site (map-projection scale and
earth curvature leave centimetres to decimetres of model error at 0.5–3 km) and never hold projected
or geocentric coordinates in float32 (0.25–0.5 m ulp). Instead:

* ``crs_from_user(text)`` parses ``EPSG:<code>`` (or a bare code), a PROJ string, WKT or any other
  pyproj user input into a ``pyproj.CRS``; unknown codes raise :class:`CRSInputError` (a ValueError)
  with a one-line message.
* :class:`LocalFrame` converts surveyed coordinates in that CRS to a **local ENU frame** (x east,
  y north, z up, metres, float64) with its origin at a chosen point (by default the centroid of the
  surveyed points), via geocentric (ECEF) coordinates of the CRS' own datum, and back. Axis order is
  always (x, y, z) = (easting or longitude, northing or latitude, height): pyproj transformers are
  built with ``always_xy=True``.
* Without a CRS (plain Cartesian surveyed coordinates, e.g. a local site grid) the frame is just a
  float64 offset: local = xyz − origin.

Height assumption: the third coordinate of a projected or geographic CRS is taken as the height
above the CRS' **ellipsoid** (pyproj's 3D promotion of a 2D CRS). Survey heights are often orthometric
(above the geoid); used as ellipsoidal heights they shift the local frame by the geoid undulation N
(tens of metres) along the vertical. Because the same assumption is used on the way back, points
round-trip exactly and the shift cancels; what remains is the change of N across the site (the geoid
slope, typically mm–cm per km) and a relative scale error N/R ≈ 1e-5. Use a compound CRS with a
vertical datum (e.g. ``EPSG:25832+7837``) when pyproj has the geoid grid, to make heights exact.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


class CRSInputError(ValueError):
    """A CRS text pyproj does not know, or coordinates it cannot transform (one-line message)."""


def crs_from_user(text):
    """``pyproj.CRS`` of a user's CRS text: ``EPSG:<code>``, a bare code, a PROJ string, WKT, ...

    Raises :class:`CRSInputError` ("unknown CRS 'EPSG:999999'") for anything pyproj rejects.
    """
    from pyproj import CRS
    from pyproj.exceptions import CRSError

    if isinstance(text, CRS):
        return text
    s = str(text).strip()
    if not s:
        raise CRSInputError("empty CRS (expected e.g. EPSG:32632)")
    if s.isdigit():
        s = f"EPSG:{s}"
    if s.upper().startswith("EPSG:") and not s[5:].strip().isdigit():
        raise CRSInputError(f"EPSG code must be a number, got {s!r}")
    try:
        return CRS.from_user_input(s)
    except CRSError as exc:
        detail = str(exc).split(": (")[0].splitlines()[0]
        shown = s if len(s) <= 60 else s[:57] + "..."
        raise CRSInputError(f"unknown CRS {shown!r} ({detail})") from None


def _enu_from_ecef_rotation(lon_deg: float, lat_deg: float) -> np.ndarray:
    """Rows: east, north, up unit vectors in ECEF at geodetic (lon, lat)."""
    lam, phi = np.radians(lon_deg), np.radians(lat_deg)
    sl, cl, sp, cp = np.sin(lam), np.cos(lam), np.sin(phi), np.cos(phi)
    return np.array([[-sl, cl, 0.0],
                     [-sp * cl, -sp * sl, cp],
                     [cp * cl, cp * sl, sp]])


def _ecef_from_geodetic(llh: np.ndarray, a: float, e2: float) -> np.ndarray:
    """(n, 3) (lon°, lat°, ellipsoidal height m) -> (n, 3) geocentric XYZ (m) on the ellipsoid (a, e²)."""
    lam, phi, h = np.radians(llh[:, 0]), np.radians(llh[:, 1]), llh[:, 2]
    sp, cp = np.sin(phi), np.cos(phi)
    n = a / np.sqrt(1.0 - e2 * sp * sp)
    return np.stack([(n + h) * cp * np.cos(lam), (n + h) * cp * np.sin(lam), (n * (1.0 - e2) + h) * sp], axis=1)


def _geodetic_from_ecef(xyz: np.ndarray, a: float, e2: float) -> np.ndarray:
    """Inverse of :func:`_ecef_from_geodetic` (fixed-point iteration; < 1e-9 m after 6 steps on Earth)."""
    x, y, z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    p = np.hypot(x, y)
    lam = np.arctan2(y, x)
    phi = np.arctan2(z, p * (1.0 - e2))
    for _ in range(8):
        sp, cp = np.sin(phi), np.cos(phi)
        n = a / np.sqrt(1.0 - e2 * sp * sp)
        h = p * cp + z * sp - a * a / n  # stable at all latitudes
        phi = np.arctan2(z, p * (1.0 - e2 * n / (n + h)))
    sp, cp = np.sin(phi), np.cos(phi)
    n = a / np.sqrt(1.0 - e2 * sp * sp)
    h = p * cp + z * sp - a * a / n
    return np.stack([np.degrees(lam), np.degrees(phi), h], axis=1)


def _crs_kind(crs) -> str:
    if crs is None:
        return "cartesian"
    if crs.is_geocentric:
        return "geocentric"
    if crs.is_projected or crs.is_geographic or crs.is_compound:
        return "geodetic"
    return "cartesian"  # engineering / local CRS: metric Cartesian as given


@dataclass(frozen=True)
class LocalFrame:
    """A metric Cartesian local frame for surveyed points (float64, metres).

    crs: the surveyed points' ``pyproj.CRS`` or None (plain Cartesian coordinates, metres);
    origin: (3,) the origin in the CRS' own coordinates (x, y, z; x = easting or longitude).
    For a projected, geographic, compound or geocentric CRS the local frame is ENU (east, north, up)
    at the origin; otherwise local = xyz − origin. Build with :meth:`from_points`.
    """

    crs: object
    origin: np.ndarray

    def __post_init__(self) -> None:
        origin = np.asarray(self.origin, dtype=np.float64).reshape(3)
        if not np.all(np.isfinite(origin)):
            raise CRSInputError("local frame origin is not finite")
        object.__setattr__(self, "origin", origin)
        kind = _crs_kind(self.crs)
        object.__setattr__(self, "_kind", kind)
        if kind == "cartesian":
            return
        from pyproj import Transformer

        if kind == "geocentric":
            ell = self.crs.ellipsoid
            to_geog = from_geog = None
        else:
            src = self.crs if self.crs.is_compound else self.crs.to_3d()
            geog = self.crs.geodetic_crs.to_3d()
            ell = geog.ellipsoid
            to_geog = Transformer.from_crs(src, geog, always_xy=True)
            from_geog = Transformer.from_crs(geog, src, always_xy=True)
        if ell is None:
            raise CRSInputError(f"CRS {self.crs.name!r} has no ellipsoid")
        a = float(ell.semi_major_metre)
        b = float(ell.semi_minor_metre)
        object.__setattr__(self, "_ell", (a, 1.0 - (b * b) / (a * a)))
        object.__setattr__(self, "_to_geog", to_geog)
        object.__setattr__(self, "_from_geog", from_geog)
        origin_ecef = self._ecef(origin[None])[0]
        lon, lat, _ = _geodetic_from_ecef(origin_ecef[None], *self._ell)[0]
        object.__setattr__(self, "origin_ecef", origin_ecef)
        object.__setattr__(self, "R_enu_from_ecef", _enu_from_ecef_rotation(lon, lat))

    @classmethod
    def from_points(cls, points, crs=None) -> "LocalFrame":
        """Frame with its origin at the centroid of ``points`` (n, 3) given in ``crs`` (None: Cartesian)."""
        pts = np.asarray(points, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) == 0:
            raise ValueError(f"points must be a non-empty (n, 3) array, got shape {pts.shape}")
        if not np.all(np.isfinite(pts)):
            raise CRSInputError("surveyed coordinates contain NaN or infinite values")
        return cls(crs, pts.mean(axis=0))

    @property
    def kind(self) -> str:
        """"enu" (a CRS was given) or "offset" (plain Cartesian)."""
        return "offset" if self._kind == "cartesian" else "enu"

    def _ecef(self, xyz: np.ndarray) -> np.ndarray:
        if self._to_geog is None:
            return np.array(xyz, dtype=np.float64)
        lon, lat, h = self._to_geog.transform(xyz[:, 0], xyz[:, 1], xyz[:, 2])
        out = _ecef_from_geodetic(np.stack([lon, lat, h], axis=1), *self._ell)
        if not np.all(np.isfinite(out)):
            raise CRSInputError(f"cannot transform coordinates from {self.crs.name} to geocentric "
                                "(outside the CRS' area, or a missing PROJ grid)")
        return out

    def to_local(self, xyz) -> np.ndarray:
        """(n, 3) coordinates in ``crs`` -> (n, 3) local frame coordinates (metres, float64)."""
        xyz = np.atleast_2d(np.asarray(xyz, dtype=np.float64))
        if self._kind == "cartesian":
            return xyz - self.origin
        return (self._ecef(xyz) - self.origin_ecef) @ self.R_enu_from_ecef.T

    def from_local(self, local) -> np.ndarray:
        """(n, 3) local frame coordinates -> (n, 3) coordinates in ``crs``."""
        local = np.atleast_2d(np.asarray(local, dtype=np.float64))
        if self._kind == "cartesian":
            return local + self.origin
        ecef = local @ self.R_enu_from_ecef + self.origin_ecef
        if self._from_geog is None:
            return ecef
        llh = _geodetic_from_ecef(ecef, *self._ell)
        x, y, z = self._from_geog.transform(llh[:, 0], llh[:, 1], llh[:, 2])
        out = np.stack([x, y, z], axis=1).astype(np.float64)
        if not np.all(np.isfinite(out)):
            raise CRSInputError(f"cannot transform local coordinates back to {self.crs.name}")
        return out

    def to_dict(self) -> dict:
        """JSON-ready description: {"kind", "crs" (WKT-free short form or None), "origin"}."""
        crs = None
        if self.crs is not None:
            auth = self.crs.to_authority()
            crs = f"{auth[0]}:{auth[1]}" if auth else self.crs.to_proj4() or self.crs.to_wkt()
        d = {"kind": self.kind, "crs": crs, "origin": self.origin.tolist()}
        if self.kind == "enu":
            d["origin_ecef"] = self.origin_ecef.tolist()
            d["enu_from_ecef"] = self.R_enu_from_ecef.tolist()
        return d
