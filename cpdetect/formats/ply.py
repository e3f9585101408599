"""PLY point clouds and meshes: read vertices, write clouds, apply a similarity to a whole file.

Coordinates are always written as ``double``: a float32 PLY loses 0.25-0.5 m at UTM or ECEF magnitudes
(ODM issue 522). ``transform_ply`` rewrites only the vertex element (x, y, z become double, normals
nx, ny, nz are rotated) and copies every other property and element (faces, colours, labels)
unchanged, so a textured mesh or an ODM cloud keeps what it carries. Formats: ``ascii``,
``binary_little_endian`` and ``binary_big_endian``.
"""
from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

import numpy as np

from geometry.transforms import Sim3

from ..errors import InputError
from ..fileio import write_bytes_atomic

_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
          "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
          "float": "f4", "float32": "f4", "double": "f8", "float64": "f8"}
_FORMATS = {"ascii": None, "binary_little_endian": "<", "binary_big_endian": ">"}


@dataclass
class _Element:
    name: str
    count: int
    props: list[tuple[str, str]] = field(default_factory=list)  # (name, type) ; lists: ("name", "list")
    has_list: bool = False
    line: int = 0


@dataclass
class _Header:
    fmt: str
    elements: list[_Element]
    lines: list[str]  # raw header lines (without trailing newline), "ply" ... "end_header"
    data_offset: int  # byte offset of the body


@dataclass
class PlyPoints:
    """Vertices of a PLY: xyz (n, 3) float64; rgb (n, 3) uint8 or None; normals (n, 3) float64 or None."""

    xyz: np.ndarray
    rgb: Optional[np.ndarray] = None
    normals: Optional[np.ndarray] = None


def _read_header(path: Path, data: bytes) -> _Header:
    if not data.startswith(b"ply"):
        raise InputError("not a PLY file (does not start with 'ply')", path, 1)
    end = data.find(b"end_header")
    if end < 0:
        raise InputError("PLY header has no end_header (truncated?)", path)
    nl = data.find(b"\n", end)
    if nl < 0:
        raise InputError("PLY file ends right after its header", path)
    try:
        text = data[:nl].decode("ascii")
    except UnicodeDecodeError:
        raise InputError("PLY header is not ASCII", path) from None
    lines = [l.rstrip("\r") for l in text.split("\n")]
    fmt = None
    elements: list[_Element] = []
    for i, line in enumerate(lines, 1):
        f = line.split()
        if not f or f[0] in ("ply", "comment", "obj_info", "end_header"):
            continue
        if f[0] == "format":
            if len(f) < 2 or f[1] not in _FORMATS:
                raise InputError(f"unknown PLY format {line!r}", path, i)
            fmt = f[1]
        elif f[0] == "element":
            try:
                elements.append(_Element(f[1], int(f[2]), line=i))
            except (IndexError, ValueError):
                raise InputError(f"bad element line {line!r}", path, i) from None
        elif f[0] == "property":
            if not elements:
                raise InputError("property before any element", path, i)
            el = elements[-1]
            if len(f) >= 5 and f[1] == "list":
                if f[2] not in _TYPES or f[3] not in _TYPES:
                    raise InputError(f"unknown PLY type in {line!r}", path, i)
                el.props.append((f[4], f"list {f[2]} {f[3]}"))
                el.has_list = True
            elif len(f) == 3 and f[1] in _TYPES:
                el.props.append((f[2], _TYPES[f[1]]))
            else:
                raise InputError(f"bad property line {line!r}", path, i)
        else:
            raise InputError(f"unknown PLY header line {line!r}", path, i)
    if fmt is None:
        raise InputError("PLY header has no format line", path)
    return _Header(fmt, elements, lines, nl + 1)


def _vertex(path: Path, header: _Header) -> tuple[_Element, int]:
    for k, el in enumerate(header.elements):
        if el.name == "vertex":
            names = [n for n, _ in el.props]
            if not all(a in names for a in "xyz"):
                raise InputError("PLY vertex element has no x, y, z properties", path, el.line)
            if el.has_list:
                raise InputError("PLY vertex element with list properties is not supported", path, el.line)
            return el, k
    raise InputError("PLY file has no vertex element", path)


def _dtype(el: _Element, endian: str) -> np.dtype:
    return np.dtype([(n, endian + t) for n, t in el.props])


def _load(path: Path):
    """(header, vertex element index, vertex structured array, bytes before it, bytes after it).
    For ASCII files the 'bytes' are lists of body lines."""
    path = Path(path)
    if not path.is_file():
        raise InputError("PLY file not found" if not path.exists() else "expected a PLY file", path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise InputError(f"cannot read: {exc.strerror or exc}", path) from None
    header = _read_header(path, data)
    vel, k = _vertex(path, header)
    body = data[header.data_offset:]
    endian = _FORMATS[header.fmt]
    if endian is None:
        text_lines = body.decode("ascii", errors="replace").splitlines()
        before = sum(e.count for e in header.elements[:k])
        rows = text_lines[before:before + vel.count]
        if len(rows) < vel.count:
            raise InputError(f"PLY body is truncated: {len(rows)} of {vel.count} vertex lines",
                             path, len(header.lines) + 1 + before + len(rows))
        dt = _dtype(vel, "<")
        arr = np.empty(vel.count, dt)
        for i, row in enumerate(rows):
            f = row.split()
            if len(f) != len(vel.props):
                raise InputError(f"vertex line has {len(f)} values, expected {len(vel.props)}",
                                 path, len(header.lines) + 1 + before + i)
            try:
                arr[i] = tuple(float(v) if dt[j].kind == "f" else int(v) for j, v in enumerate(f))
            except ValueError:
                raise InputError("vertex line has a non-number", path,
                                 len(header.lines) + 1 + before + i) from None
        return header, k, arr, text_lines[:before], text_lines[before + vel.count:]
    start = 0
    for el in header.elements[:k]:
        if el.has_list:
            raise InputError(f"PLY element {el.name!r} with list properties before the vertices is "
                             "not supported", path, el.line)
        start += el.count * _dtype(el, endian).itemsize
    dt = _dtype(vel, endian)
    stop = start + vel.count * dt.itemsize
    if len(body) < stop:
        raise InputError(f"PLY body is truncated: {len(body)} bytes, the {vel.count} vertices need "
                         f"{stop}", path)
    arr = np.frombuffer(body[start:stop], dt).copy()
    return header, k, arr, body[:start], body[stop:]


def read_ply_points(path: str | os.PathLike) -> PlyPoints:
    """Vertices of a PLY file (cloud or mesh) as float64 xyz, uint8 rgb (red/green/blue or r/g/b,
    if present) and float64 normals (nx/ny/nz, if present). Raises InputError naming the file."""
    path = Path(path)
    _, _, arr, _, _ = _load(path)
    xyz = np.column_stack([arr["x"], arr["y"], arr["z"]]).astype(np.float64)
    if not np.all(np.isfinite(xyz)):
        raise InputError(f"{int((~np.isfinite(xyz).all(axis=1)).sum())} vertices have non-finite "
                         "coordinates", path)
    names = arr.dtype.names or ()
    rgb = None
    for trio in (("red", "green", "blue"), ("r", "g", "b"), ("diffuse_red", "diffuse_green", "diffuse_blue")):
        if all(n in names for n in trio):
            rgb = np.column_stack([arr[n] for n in trio])
            if rgb.dtype.kind == "f":  # some writers store colours as 0..1 floats
                rgb = np.clip(np.rint(rgb * (255.0 if rgb.max() <= 1.0 else 1.0)), 0, 255)
            rgb = rgb.astype(np.uint8)
            break
    normals = None
    if all(n in names for n in ("nx", "ny", "nz")):
        normals = np.column_stack([arr["nx"], arr["ny"], arr["nz"]]).astype(np.float64)
    return PlyPoints(xyz, rgb, normals)


def ply_points_bytes(xyz: np.ndarray, rgb: Optional[np.ndarray] = None, normals: Optional[np.ndarray] = None,
                     comments: tuple[str, ...] = ()) -> bytes:
    """Binary little-endian PLY of points: ``double x y z``, ``float nx ny nz``, ``uchar red green blue``."""
    xyz = np.asarray(xyz, np.float64).reshape(-1, 3)
    n = len(xyz)
    if not np.all(np.isfinite(xyz)):
        raise ValueError("xyz has non-finite coordinates")
    fields = [("x", "<f8"), ("y", "<f8"), ("z", "<f8")]
    if normals is not None:
        normals = np.asarray(normals, np.float64).reshape(-1, 3)
        if len(normals) != n:
            raise ValueError(f"normals has {len(normals)} rows, xyz has {n}")
        fields += [("nx", "<f4"), ("ny", "<f4"), ("nz", "<f4")]
    if rgb is not None:
        rgb = np.asarray(rgb)
        if rgb.shape != (n, 3):
            raise ValueError(f"rgb must have shape ({n}, 3), got {rgb.shape}")
        if rgb.dtype != np.uint8:
            raise ValueError(f"rgb must be uint8, got {rgb.dtype}")
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    arr = np.empty(n, np.dtype(fields))
    arr["x"], arr["y"], arr["z"] = xyz.T
    if normals is not None:
        arr["nx"], arr["ny"], arr["nz"] = normals.T
    if rgb is not None:
        arr["red"], arr["green"], arr["blue"] = rgb.T
    names = {"<f8": "double", "<f4": "float", "u1": "uchar"}
    head = ["ply", "format binary_little_endian 1.0", *[f"comment {c}" for c in comments],
            f"element vertex {n}", *[f"property {names[t]} {nm}" for nm, t in fields], "end_header"]
    return ("\n".join(head) + "\n").encode("ascii") + arr.tobytes()


def write_ply_points(path: str | os.PathLike, xyz: np.ndarray, rgb: Optional[np.ndarray] = None,
                     normals: Optional[np.ndarray] = None, comments: tuple[str, ...] = ()) -> Path:
    """Write points (n, 3) float64 (+ uint8 rgb, + normals) as a binary PLY with double coordinates,
    atomically. Returns ``path``."""
    write_bytes_atomic(path, ply_points_bytes(xyz, rgb, normals, comments))
    return Path(path)


def transform_ply(path_in: str | os.PathLike, sim: Sim3, path_out: str | os.PathLike) -> Path:
    """Apply ``sim`` (new_from_old, e.g. ``world_from_model``) to a PLY cloud or mesh: x' = s R x + t
    for the vertices (written as double), normals rotated by R; everything else copied unchanged.
    The output keeps the input's format (ascii or binary) and is written atomically."""
    path_in, path_out = Path(path_in), Path(path_out)
    header, k, arr, before, after = _load(path_in)
    vel = header.elements[k]
    xyz = np.column_stack([arr["x"], arr["y"], arr["z"]]).astype(np.float64)
    if not np.all(np.isfinite(xyz)):
        raise InputError("vertices with non-finite coordinates", path_in)
    new_xyz = sim(xyz)
    names = arr.dtype.names or ()
    has_normals = all(n in names for n in ("nx", "ny", "nz"))
    endian = _FORMATS[header.fmt] or "<"
    new_props = [(n, "f8" if n in ("x", "y", "z") else t) for n, t in vel.props]
    out = np.empty(len(arr), np.dtype([(n, endian + t) for n, t in new_props]))
    for n in names:
        out[n] = arr[n]
    out["x"], out["y"], out["z"] = new_xyz.T
    if has_normals:
        nrm = np.column_stack([arr["nx"], arr["ny"], arr["nz"]]).astype(np.float64) @ sim.R.T
        out["nx"], out["ny"], out["nz"] = nrm.T
    # Header: the vertex x/y/z property lines now say double; every other line is kept.
    lines = list(header.lines)
    prop_i = 0
    for i in range(vel.line, len(lines)):
        f = lines[i].split()
        if not f or f[0] != "property":
            if f and f[0] in ("element", "end_header"):
                break
            continue
        name = vel.props[prop_i][0]
        if name in ("x", "y", "z"):
            lines[i] = f"property double {name}"
        prop_i += 1
    fmt_at = next(i for i, l in enumerate(lines) if l.startswith("format"))
    lines.insert(fmt_at + 1, "comment transformed by cpdetect (similarity, double coordinates)")
    head = ("\n".join(lines) + "\n").encode("ascii")
    if header.fmt == "ascii":
        body_lines = list(before)
        fmt_cols = [(n, out.dtype[n].kind) for n in out.dtype.names]
        for row in out:
            body_lines.append(" ".join(repr(float(row[n])) if kind == "f" else str(int(row[n]))
                                       for n, kind in fmt_cols))
        body_lines += list(after)
        data = head + ("\n".join(body_lines) + "\n").encode("ascii")
    else:
        data = head + before + out.tobytes() + after
    write_bytes_atomic(path_out, data)
    return path_out
