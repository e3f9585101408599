"""Point tables as CSV: ``name,x,y,z`` (surveyed points) or ``id,x,y,z`` (detected marker points).

* A header line is required. The name column is called ``name``, ``id`` or ``label``; the coordinate
  columns ``x``, ``y``, ``z`` (aliases: ``easting``/``e``/``lon``, ``northing``/``n``/``lat``,
  ``height``/``h``/``elevation``/``alt``). Names are matched case-insensitively; columns may come in any
  order; extra columns are ignored.
* Separator: comma, or semicolon / tab when the header has no comma. Quoting follows RFC 4180.
  A UTF-8 BOM is stripped; empty lines and lines starting with ``#`` are skipped.
* Coordinates are read as float64 (never float32). Units and CRS are the caller's business
  (``--crs``; see docs/formats.md "Surveyed points and CRS").
* Every problem raises :class:`~cpdetect.errors.InputError` naming the file and the 1-based line:
  non-UTF-8 bytes, a missing column, a short row, a non-numeric / NaN / infinite coordinate, an empty
  or duplicate name, or fewer points than the caller needs (``min_points``).
"""
from __future__ import annotations

import csv
import io
import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..fileio import write_text_atomic

NAME_COLUMNS = ("name", "id", "label")
COORD_COLUMNS = (("x", "easting", "e", "lon", "longitude"),
                 ("y", "northing", "n", "lat", "latitude"),
                 ("z", "height", "h", "elevation", "alt", "altitude"))


@dataclass
class PointTable:
    """Named 3D points read from a file.

    names: point names in file order (unique); xyz: (n, 3) float64; lines: 1-based line of each point;
    path: the file they came from.
    """

    names: list[str]
    xyz: np.ndarray
    lines: list[int]
    path: str | None = None

    def __len__(self) -> int:
        return len(self.names)


def _decode(path: Path) -> str:
    if not path.exists():
        raise InputError("file not found", path)
    if path.is_dir():
        raise InputError("expected a CSV file, found a folder", path)
    if not path.is_file():  # reading a pipe or a device could block or never end
        raise InputError("expected a CSV file, found a device, pipe or socket", path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise InputError(f"cannot read: {exc.strerror or exc}", path) from None
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as exc:
        line = data[:exc.start].count(b"\n") + 1
        raise InputError(f"not UTF-8 text (byte {exc.start}); save the file as UTF-8", path, line) from None


def _find(header: list[str], candidates: tuple[str, ...]) -> int | None:
    for c in candidates:
        if c in header:
            return header.index(c)
    return None


def read_points_csv(path: str | os.PathLike, *, min_points: int = 0, what: str = "points") -> PointTable:
    """Read a ``name,x,y,z`` CSV (see the module docstring); ``min_points``: fewest points accepted."""
    path = Path(path)
    text = _decode(path).lstrip("\ufeff")
    raw_lines = text.splitlines()
    # the header: first line that is neither empty nor a comment
    header_idx = next((i for i, l in enumerate(raw_lines) if l.strip() and not l.lstrip().startswith("#")), None)
    if header_idx is None:
        raise InputError(f"empty {what} file (expected a header such as 'name,x,y,z')", path, 1)
    head_line = raw_lines[header_idx]
    delim = "," if "," in head_line else ";" if ";" in head_line else "\t" if "\t" in head_line else ","
    rows = csv.reader(io.StringIO("\n".join(raw_lines)), delimiter=delim, skipinitialspace=True, strict=True)
    header = None
    cols: list[int] = []
    names: list[str] = []
    xyz: list[list[float]] = []
    lines: list[int] = []
    seen: dict[str, int] = {}
    try:
        for row in rows:
            lineno = rows.line_num
            if not row or all(not f.strip() for f in row) or row[0].lstrip().startswith("#"):
                continue
            if header is None:
                header = [h.strip().lower() for h in row]
                name_col = _find(header, NAME_COLUMNS)
                coord_cols = [_find(header, c) for c in COORD_COLUMNS]
                missing = [c[0] for c, i in zip(COORD_COLUMNS, coord_cols) if i is None]
                if name_col is None:
                    missing.insert(0, "name")
                if missing:
                    if all(_is_number(f) for f in row[1:4]) and len(row) >= 4:
                        raise InputError("the first line must be a header such as 'name,x,y,z' "
                                         "(found numbers instead)", path, lineno)
                    raise InputError(f"header lacks column(s) {', '.join(missing)} (found: {', '.join(header)}; "
                                     "expected 'name,x,y,z')", path, lineno)
                cols = [name_col, *coord_cols]
                continue
            if len(row) <= max(cols):
                raise InputError(f"row has {len(row)} field(s), need at least {max(cols) + 1} "
                                 f"(columns {', '.join(header[c] for c in cols)})", path, lineno)
            name = row[cols[0]].strip()
            if not name:
                raise InputError("empty point name", path, lineno)
            vals = []
            for axis, c in zip("xyz", cols[1:]):
                v = row[c].strip()
                try:
                    f = float(v)
                except ValueError:
                    raise InputError(f"{axis} of {name!r} is not a number: {v!r}", path, lineno) from None
                if not math.isfinite(f):
                    raise InputError(f"{axis} of {name!r} is not finite ({v})", path, lineno)
                vals.append(f)
            if name in seen:
                raise InputError(f"duplicate point name {name!r} (first on line {seen[name]})", path, lineno)
            seen[name] = lineno
            names.append(name)
            xyz.append(vals)
            lines.append(lineno)
    except csv.Error as exc:
        raise InputError(f"malformed CSV: {exc}", path, rows.line_num) from None
    if len(names) < min_points:
        raise InputError(f"need at least {min_points} {what}, found {len(names)}", path)
    arr = np.array(xyz, dtype=np.float64).reshape(-1, 3)
    return PointTable(names, arr, lines, str(path))


def _is_number(s: str) -> bool:
    try:
        float(s)
        return True
    except ValueError:
        return False


def format_points_csv(names, xyz, name_column: str = "name") -> str:
    """CSV text ``name,x,y,z`` with round-trip (repr) float64 values."""
    xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    out = io.StringIO()
    w = csv.writer(out, lineterminator="\n")
    w.writerow([name_column, "x", "y", "z"])
    for n, p in zip(names, xyz):
        w.writerow([n, *(repr(float(v)) for v in p)])
    return out.getvalue()


def write_points_csv(path: str | os.PathLike, names, xyz, name_column: str = "name") -> Path:
    """Write a point table atomically; returns the path."""
    write_text_atomic(path, format_points_csv(names, xyz, name_column))
    return Path(path)
