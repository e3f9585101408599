"""OpenDroneMap / OpenSfM ``gcp_list.txt``: ground control points and their image observations.

File layout (docs/formats.md, "ODM gcp_list.txt")::

    <CRS header>
    geo_x geo_y geo_z im_x im_y image_name [gcp_name] [extra ...]

* Header forms (as ODM's ``location.parse_srs_header`` and OpenSfM's ``_parse_projection``): a PROJ string
  (``+proj=utm +zone=10 ...``), ``EPSG:<code>``, ``WGS84 UTM <zone><N|S>``, or the bare word ``WGS84``
  (OpenSfM only; longitude, latitude, ellipsoidal height). A UTF-8 BOM is stripped.
* ``geo_x, geo_y`` are in "traditional GIS order": easting/northing, or **longitude/latitude** for
  geographic CRSs such as EPSG:4326 (build pyproj transformers with ``always_xy=True``).
* Fields are separated by blanks (spaces or tabs), so names cannot contain blanks; ``#`` comment lines and
  empty lines are skipped.
* Pixels: OpenSfM, which ODM runs, normalises ``im_x, im_y`` with
  ``(x + 0.5 - w/2) / max(w, h)`` (``features.normalized_image_coordinates``), i.e. the centre of the
  top-left pixel is (0, 0): the OpenCV convention that cpdetect uses. The conversion is therefore the
  identity (``PIXEL_SHIFT = 0``), applied explicitly on read and write so it is visible and testable.
"""
from __future__ import annotations

import logging
import math
import os
import re
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable, Optional, Sequence

import numpy as np

from ..errors import CpdetectError, InputError
from ..fileio import read_text_utf8, write_text_atomic

log = logging.getLogger(__name__)

#: x_gcp_list = x_opencv + PIXEL_SHIFT (ODM/OpenSfM pixel centres are on integers, like OpenCV).
PIXEL_SHIFT = 0.0

_UTM_RE = re.compile(r"^WGS84\s+UTM\s+(\d{1,2})([NS]?)$", re.IGNORECASE)


@dataclass(frozen=True, eq=False)
class GcpObservation:
    """One line of a gcp_list: a surveyed point seen in one image.

    geo: (3,) float64 coordinates in the file's CRS, (x, y, z) in traditional GIS order (x = easting or
    longitude). im_x, im_y: pixel position in the OpenCV convention (top-left pixel centre = (0, 0)).
    image: image file name as written (case-sensitive). name: GCP label (7th column) or None.
    extras: further columns, verbatim. line: 1-based line in the file it came from (None if built).
    """

    geo: np.ndarray
    im_x: float
    im_y: float
    image: str
    name: Optional[str] = None
    extras: tuple[str, ...] = ()
    line: Optional[int] = field(default=None, compare=False)

    def __post_init__(self) -> None:
        geo = np.asarray(self.geo, dtype=np.float64).reshape(3)
        object.__setattr__(self, "geo", geo)
        object.__setattr__(self, "im_x", float(self.im_x))
        object.__setattr__(self, "im_y", float(self.im_y))
        object.__setattr__(self, "extras", tuple(str(e) for e in self.extras))

    def __eq__(self, other: object) -> bool:
        """Exact equality of every field but ``line``."""
        if not isinstance(other, GcpObservation):
            return NotImplemented
        return (np.array_equal(self.geo, other.geo) and (self.im_x, self.im_y, self.image, self.name,
                self.extras) == (other.im_x, other.im_y, other.image, other.name, other.extras))

    __hash__ = None  # mutable-content array inside


@dataclass
class GcpList:
    """A parsed gcp_list.txt: its CRS (pyproj.CRS), the header line verbatim, and the observations."""

    crs: "object"  # pyproj.CRS
    header: str
    observations: list[GcpObservation]
    path: Optional[str] = None


# ----------------------------------------------------------------------------------------------------
# CRS


def parse_crs(text: str, path: str | os.PathLike | None = None, line: Optional[int] = None,
              error: type[CpdetectError] = InputError):
    """pyproj.CRS of a CRS text: ``EPSG:<code>``, a PROJ string, ``WGS84 UTM <zone><N|S>`` or ``WGS84``.

    Used for gcp_list headers and for ``--crs`` options (pass ``error=UsageError`` there). Unknown EPSG
    codes and anything else raise ``error`` naming ``path``/``line``.
    """
    from pyproj import CRS
    from pyproj.exceptions import CRSError

    s = text.strip().strip("'\"").strip()
    m = _UTM_RE.match(s)
    try:
        if s.upper() == "WGS84":
            return CRS.from_epsg(4326)
        if m:
            zone, hemi = int(m.group(1)), m.group(2).upper()
            if not 1 <= zone <= 60:
                raise error(f"UTM zone {zone} is not in 1..60", path, line)
            if not hemi:
                log.warning("%s: 'WGS84 UTM %d' has no hemisphere letter; assuming north (ODM needs "
                            "N or S)", path, zone)
            return CRS.from_epsg((32700 if hemi == "S" else 32600) + zone)
        if "+proj" in s:
            return CRS.from_proj4(s)
        if s.upper().startswith("EPSG:"):
            code = s[5:].strip()
            if not code.isdigit():
                raise error(f"EPSG code must be a number, got {code!r}", path, line)
            return CRS.from_epsg(int(code))
    except CRSError as exc:
        reason = str(exc).split(": (")[0]
        raise error(f"unknown or invalid CRS {s!r} ({reason})", path, line) from None
    shown = s if len(s) <= 60 else s[:57] + "..."
    raise error(f"not a CRS header: {shown!r} (expected EPSG:<code>, a +proj string, "
                "'WGS84 UTM <zone><N|S>' or 'WGS84')", path, line)


def crs_header(crs) -> str:
    """The gcp_list header line for a CRS: ``EPSG:<code>`` when it has one, else a PROJ string.
    A ``str`` is checked with :func:`parse_crs` and returned stripped."""
    if isinstance(crs, str):
        parse_crs(crs, error=InputError)
        return crs.strip()
    code = crs.to_epsg()
    if code is not None:
        return f"EPSG:{code}"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # "lose projection information" is expected here
        proj = crs.to_proj4()
    if not proj:
        raise ValueError(f"CRS {crs.name!r} has neither an EPSG code nor a PROJ string for a gcp_list header")
    return proj


# ----------------------------------------------------------------------------------------------------
# Reading


def read_gcp_list(path: str | os.PathLike) -> GcpList:
    """Read an ODM/OpenSfM gcp_list.txt.

    Raises :class:`InputError` naming file and line for: missing/unreadable file, a header that is not a
    CRS or names an unknown EPSG code, a data line with fewer than 6 fields, a non-numeric or non-finite
    number, or a file without observations.
    """
    path = Path(path)
    text = read_text_utf8(path, "gcp_list")
    lines = text.replace("\ufeff", "").splitlines()
    header_no = next((i for i, l in enumerate(lines) if l.strip()), None)
    if header_no is None:
        raise InputError("empty gcp_list (expected a CRS header line)", path, 1)
    header = lines[header_no].strip()
    crs = parse_crs(header, path, header_no + 1)
    obs = []
    for i in range(header_no + 1, len(lines)):
        s = lines[i].strip()
        if not s or s.startswith("#"):
            continue
        obs.append(_parse_line(s, path, i + 1))
    if not obs:
        raise InputError("gcp_list has a header but no observation lines", path, len(lines))
    return GcpList(crs=crs, header=header, observations=obs, path=str(path))


def _parse_line(s: str, path: Path, lineno: int) -> GcpObservation:
    parts = s.split()
    if len(parts) < 6:
        raise InputError(f"malformed GCP line: {len(parts)} fields, need at least 6 "
                         "(geo_x geo_y geo_z im_x im_y image_name [gcp_name])", path, lineno)
    vals = []
    for k, (label, v) in enumerate(zip(("geo_x", "geo_y", "geo_z", "im_x", "im_y"), parts[:5])):
        try:
            f = float(v)
        except ValueError:
            raise InputError(f"{label} is not a number: {v!r}", path, lineno) from None
        if not math.isfinite(f):
            raise InputError(f"{label} is not finite ({v})", path, lineno)
        vals.append(f)
    return GcpObservation(geo=np.array(vals[:3]), im_x=vals[3] - PIXEL_SHIFT, im_y=vals[4] - PIXEL_SHIFT,
                          image=parts[5], name=parts[6] if len(parts) > 6 else None,
                          extras=tuple(parts[7:]), line=lineno)


def gcp_survey_points(gcps: GcpList, tol: float = 1e-6) -> dict[str, np.ndarray]:
    """Surveyed points of a gcp_list: {gcp name: (3,) float64 geo coordinates}, in first-seen order.

    Lines without a name are grouped by coordinates (as OpenSfM does) and named ``unnamed-<k>``.
    A name whose lines disagree on the coordinates by more than ``tol`` raises :class:`InputError`
    naming the line.
    """
    out: dict[str, np.ndarray] = {}
    unnamed: dict[tuple, str] = {}
    for o in gcps.observations:
        name = o.name
        if name is None:
            key = tuple(o.geo.tolist())
            name = unnamed.setdefault(key, f"unnamed-{len(unnamed) + 1}")
        if name in out:
            if np.abs(out[name] - o.geo).max() > tol:
                raise InputError(f"GCP {name!r} has coordinates {o.geo.tolist()} here but "
                                 f"{out[name].tolist()} on an earlier line", gcps.path, o.line)
        else:
            out[name] = o.geo.copy()
    return out


# ----------------------------------------------------------------------------------------------------
# Writing


def _fmt(v: float) -> str:
    """Shortest text that reads back to the same float64."""
    return repr(float(v))


def format_gcp_list(crs, observations: Iterable[GcpObservation]) -> str:
    """The text of a gcp_list.txt (see :func:`write_gcp_list`)."""
    lines = [crs_header(crs)]
    for o in observations:
        vals = [*o.geo.tolist(), o.im_x + PIXEL_SHIFT, o.im_y + PIXEL_SHIFT]
        if not all(math.isfinite(v) for v in vals):
            raise ValueError(f"observation of {o.name!r} in {o.image!r} has non-finite numbers")
        words = [o.image] + ([o.name] if o.name is not None else []) + list(o.extras)
        if o.name is None and o.extras:
            raise ValueError("extras need a GCP name before them (7th column)")
        for w in words:
            if not w or any(c.isspace() for c in w):
                raise ValueError(f"gcp_list names cannot be empty or contain blanks: {w!r}")
        lines.append(" ".join([_fmt(v) for v in vals] + words))
    return "\n".join(lines) + "\n"


def write_gcp_list(path: str | os.PathLike, crs_header_or_crs, observations: Sequence[GcpObservation]) -> Path:
    """Write an ODM gcp_list.txt atomically.

    ``crs_header_or_crs``: the header text (checked with :func:`parse_crs`) or a pyproj.CRS (written as
    ``EPSG:<code>`` when it has one). One line per observation, ``geo_x geo_y geo_z im_x im_y image
    [name [extras]]``, numbers written with full float64 precision, pixels converted from OpenCV to the
    ODM convention (identity, see module docstring). Names must not contain blanks (ValueError).
    """
    text = format_gcp_list(crs_header_or_crs, observations)
    write_text_atomic(path, text)
    return Path(path)
