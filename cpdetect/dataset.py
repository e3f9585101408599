"""Marker image datasets on disk: the contract that ``cpdetect synth images`` writes and
``cpdetect eval`` (and the learned model's trainer) reads. See docs/formats.md, "Synthetic marker
image datasets".

Layout of a dataset folder ``DIR``::

    DIR/images/<stem>.jpg|png   the photographs (8-bit BGR or gray)
    DIR/masks/<stem>.png        uint8, 255 = marker pixel, 0 = anything else (same size as the image)
    DIR/markers.json            {"images": [{"file": "images/a.jpg", "mask": "masks/a.png",
                                  "markers": [{"x":.., "y":.., "type": "square|circle|diagonal",
                                               "radius_px":..}, ...]}, ...]}

x, y: the aiming point in image pixels, OpenCV convention (centre of the top-left pixel = (0, 0)).
radius_px: radius of the circle with the projected pattern's area (pixels). Paths are relative to DIR.
``mask`` may be null (no pixel truth for that image). Every other key, at the top level, per image or
per marker, is kept as ``meta`` / ``extra`` and ignored by the contract.

Stable API: :func:`load_dataset`, :func:`read_mask`, :class:`Dataset`, :class:`DatasetImage`,
:class:`TrueMarker`, :func:`write_markers_json`, :func:`image_record`.
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath
from typing import Any

import numpy as np

from .errors import InputError
from .fileio import read_json, write_json_atomic
from .types import MARKER_TYPES

MARKERS_JSON = "markers.json"
FORMAT_NAME = "cpdetect-markers"
FORMAT_VERSION = 1
REQUIRED_MARKER_KEYS = ("x", "y", "type", "radius_px")


@dataclass(frozen=True)
class TrueMarker:
    """A marker's truth: aiming point ``x, y`` (pixels, OpenCV convention), ``type`` and ``radius_px``
    (equal-area radius of the projected pattern, pixels); ``extra`` holds optional fields such as
    ``tilt_deg``, ``blur_px``, ``occluded_frac`` (see docs/formats.md)."""

    x: float
    y: float
    type: str
    radius_px: float
    extra: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        d = {"x": float(self.x), "y": float(self.y), "type": self.type, "radius_px": float(self.radius_px)}
        d.update(self.extra)
        return d


@dataclass(frozen=True)
class DatasetImage:
    """One image of a dataset: ``file`` and ``mask`` relative to the dataset root (POSIX separators;
    ``mask`` may be None), its ``markers`` and the record's other keys in ``meta``."""

    file: str
    mask: str | None
    markers: tuple[TrueMarker, ...]
    meta: dict = field(default_factory=dict)

    @property
    def stem(self) -> str:
        return PurePosixPath(self.file).stem


@dataclass
class Dataset:
    """A loaded dataset: ``root`` folder, ``images`` in file order, top-level extra keys in ``meta``."""

    root: Path
    images: list[DatasetImage]
    meta: dict = field(default_factory=dict)

    def image_path(self, item: DatasetImage) -> Path:
        return self.root / item.file

    def mask_path(self, item: DatasetImage) -> Path | None:
        return None if item.mask is None else self.root / item.mask

    @property
    def n_markers(self) -> int:
        return sum(len(im.markers) for im in self.images)


def _fail(where: str, message: str, path: Path) -> InputError:
    return InputError(f"{where}: {message}", path)


def _number(value: Any, where: str, key: str, path: Path, positive: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise _fail(where, f"'{key}' must be a number, got {type(value).__name__}", path)
    if not math.isfinite(value):
        raise _fail(where, f"'{key}' must be finite, got {value}", path)
    if positive and not value > 0:
        raise _fail(where, f"'{key}' must be positive, got {value}", path)
    return float(value)


def _relative_file(value: Any, where: str, key: str, path: Path, root: Path) -> str:
    if not isinstance(value, str) or not value:
        raise _fail(where, f"'{key}' must be a non-empty path string", path)
    p = PurePosixPath(value.replace("\\", "/"))
    if p.is_absolute() or ".." in p.parts:
        raise _fail(where, f"'{key}' must be a path inside the dataset folder, got {value!r}", path)
    if not (root / p).is_file():
        raise InputError(f"file listed in {path.name} ({where}.{key}) not found", root / p)
    return str(p)


def _parse_marker(m: Any, where: str, path: Path) -> TrueMarker:
    if not isinstance(m, dict):
        raise _fail(where, f"must be an object, got {type(m).__name__}", path)
    for key in REQUIRED_MARKER_KEYS:
        if key not in m:
            raise _fail(where, f"missing '{key}'", path)
    x = _number(m["x"], where, "x", path)
    y = _number(m["y"], where, "y", path)
    r = _number(m["radius_px"], where, "radius_px", path, positive=True)
    t = m["type"]
    if t not in MARKER_TYPES:
        raise _fail(where, f"'type' must be one of {', '.join(MARKER_TYPES)}, got {t!r}", path)
    extra = {k: v for k, v in m.items() if k not in REQUIRED_MARKER_KEYS}
    return TrueMarker(x, y, t, r, extra)


def load_dataset(folder: str | os.PathLike, check_files: bool = True) -> Dataset:
    """Read and validate ``folder/markers.json``.

    Every problem raises a one-line :class:`InputError` naming the file and the field, e.g.
    ``DIR/markers.json: images[3].markers[1]: missing 'radius_px'``; with ``check_files`` every listed
    image and mask must exist (they are decoded later, by :func:`cpdetect.imageio.read_image` and
    :func:`read_mask`, which name the file when it cannot be read).
    """
    root = Path(folder)
    if not root.exists():
        raise InputError("dataset folder not found", root)
    if not root.is_dir():
        raise InputError("expected a dataset folder (with markers.json), found a file", root)
    path = root / MARKERS_JSON
    doc = read_json(path, what="markers.json")
    if not isinstance(doc, dict):
        raise InputError(f"top level must be an object with 'images', got {type(doc).__name__}", path)
    if "images" not in doc:
        raise InputError("missing 'images'", path)
    images = doc["images"]
    if not isinstance(images, list):
        raise InputError(f"'images' must be a list, got {type(images).__name__}", path)
    out: list[DatasetImage] = []
    seen: set[str] = set()
    for i, rec in enumerate(images):
        where = f"images[{i}]"
        if not isinstance(rec, dict):
            raise _fail(where, f"must be an object, got {type(rec).__name__}", path)
        for key in ("file", "markers"):
            if key not in rec:
                raise _fail(where, f"missing '{key}'", path)
        if check_files:
            file = _relative_file(rec["file"], where, "file", path, root)
        else:
            file = str(PurePosixPath(str(rec["file"])))
        if file in seen:
            raise _fail(where, f"image {file!r} is listed twice", path)
        seen.add(file)
        mask = rec.get("mask")
        if mask is not None:
            mask = (_relative_file(mask, where, "mask", path, root) if check_files
                    else str(PurePosixPath(str(mask))))
        markers = rec["markers"]
        if not isinstance(markers, list):
            raise _fail(where, f"'markers' must be a list, got {type(markers).__name__}", path)
        parsed = tuple(_parse_marker(m, f"{where}.markers[{j}]", path) for j, m in enumerate(markers))
        meta = {k: v for k, v in rec.items() if k not in ("file", "mask", "markers")}
        out.append(DatasetImage(file=file, mask=mask, markers=parsed, meta=meta))
    meta = {k: v for k, v in doc.items() if k != "images"}
    return Dataset(root=root, images=out, meta=meta)


def read_mask(path: str | os.PathLike, shape: tuple[int, int] | None = None) -> np.ndarray:
    """Read a marker mask as a bool array (H, W), True where the stored value is >= 128.

    ``shape`` (H, W), when given, must match the mask's size. Raises :class:`InputError` naming the
    file when it is missing, unreadable, not single-channel 8-bit, or of the wrong size.
    """
    import cv2

    p = Path(path)
    try:
        data = np.fromfile(str(p), dtype=np.uint8)
    except FileNotFoundError:
        raise InputError("mask not found", p) from None
    except OSError as exc:
        raise InputError(f"cannot read mask: {exc.strerror or exc}", p) from None
    if data.size == 0:
        raise InputError("mask file is empty (0 bytes)", p)
    m = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
    if m is None:
        raise InputError("corrupt mask (cannot decode as an image)", p)
    if m.ndim == 3 and m.shape[2] == 1:
        m = m[:, :, 0]
    if m.ndim != 2 or m.dtype != np.uint8:
        raise InputError(f"mask must be single-channel uint8, got shape {m.shape} {m.dtype}", p)
    if shape is not None and tuple(m.shape) != tuple(shape):
        # images are read as stored, an EXIF orientation not applied (see cpdetect.imageio); a mask
        # drawn on the upright view of a portrait photograph is the transposed size
        hint = ("; drawn on the photo turned upright by its EXIF orientation? masks follow the image as "
                "stored" if tuple(m.shape) == tuple(shape)[::-1] else "")
        raise InputError(f"mask size {m.shape[1]}x{m.shape[0]} differs from the image's "
                         f"{shape[1]}x{shape[0]}{hint}", p)
    return m >= 128


def image_record(file: str, mask: str | None, markers: list[TrueMarker], **meta: Any) -> dict:
    """One ``images[]`` entry of markers.json (required keys first, then ``meta``)."""
    rec: dict[str, Any] = {"file": file, "mask": mask, "markers": [m.to_dict() for m in markers]}
    rec.update(meta)
    return rec


def write_markers_json(folder: str | os.PathLike, records: list[dict], **meta: Any) -> Path:
    """Write ``folder/markers.json`` atomically from :func:`image_record` entries; returns its path.

    Top-level ``meta`` (e.g. the generator's settings) is stored beside ``format``/``version``.
    """
    doc: dict[str, Any] = {"format": FORMAT_NAME, "version": FORMAT_VERSION}
    doc.update(meta)
    doc["images"] = records
    path = Path(folder) / MARKERS_JSON
    write_json_atomic(path, doc, indent=1)
    return path


__all__ = ["TrueMarker", "DatasetImage", "Dataset", "load_dataset", "read_mask", "image_record",
           "write_markers_json", "MARKERS_JSON"]
