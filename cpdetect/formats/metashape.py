"""Agisoft Metashape XML: camera export (sensors, calibrations, poses, chunk transform) and markers.

Conventions (docs/formats.md, "Metashape XML"):

* Frame camera model (Metashape manual, appendix "Camera models")::

      x = X/Z, y = Y/Z, r^2 = x^2 + y^2
      x' = x (1 + k1 r^2 + k2 r^4 + k3 r^6) + P1 (r^2 + 2 x^2) + 2 P2 x y
      y' = y (1 + k1 r^2 + k2 r^4 + k3 r^6) + P2 (r^2 + 2 y^2) + 2 P1 x y
      u = w/2 + cx + x' (f + B1) + y' B2,   v = h/2 + cy + y' f

  with (u, v) measured from the top-left image *corner* (centre of the top-left pixel = (0.5, 0.5)).
  Hence, in cpdetect's OpenCV convention: ``fx = f + b1``, ``fy = f``, ``cx = w/2 + cx_ms - 0.5``,
  ``cy = h/2 + cy_ms - 0.5``, and OpenCV ``(p1, p2) = (P2, P1)`` (swapped). Skew B2, k4 and P3/P4 are
  not representable in our Camera: a non-zero value is an error.
* ``<camera><transform>``: 16 numbers, row-major 4x4 **camera -> chunk** (so ``cam_from_world`` is its
  inverse; the chunk-local frame is our model frame). Cameras without a transform (not aligned) or
  with ``enabled="false"`` are skipped.
* Chunk georeference: ``<components><component><transform>`` (or, in older files,
  ``<chunk><transform>``) with ``rotation`` (9 numbers, row-major), ``translation`` and ``scale``:
  the similarity chunk -> ECEF (EPSG:4978) when the chunk is georeferenced, stored as
  ``scene.meta["chunk_transform"]`` (a Sim3, ``ecef_from_chunk``). ``<reference>`` holds the chunk CRS
  as WKT (``scene.meta["crs_wkt"]``; ``LOCAL_CS[...]`` means not georeferenced).
* Markers: ``<markers><marker id label><reference x y z enabled/></marker>`` (reference coordinates in
  the chunk CRS; x = longitude for geographic CRSs) and ``<frames><frame><markers><marker marker_id>
  <location camera_id pinned x y/>`` (pixels, corner convention: x_ms = x_opencv + 0.5).
"""
from __future__ import annotations

import io
import logging
import math
import os
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable, Mapping, Optional, Sequence

import numpy as np

from geometry.camera import Camera
from geometry.scene import ImageRecord, Scene
from geometry.transforms import Rigid3, Sim3, project_to_rotation

from ..errors import InputError
from ..fileio import write_bytes_atomic

log = logging.getLogger(__name__)

#: x_metashape = x_opencv + PIXEL_SHIFT (Metashape measures pixels from the top-left image corner).
PIXEL_SHIFT = 0.5
DOCUMENT_VERSION = "1.5.0"


# ----------------------------------------------------------------------------------------------------
# XML parsing with line numbers


class _XmlDoc:
    """A parsed XML file that remembers the source line of every element (for error messages)."""

    def __init__(self, path: Path):
        self.path = path
        self.lines: dict[int, int] = {}
        if not path.exists():
            raise InputError("Metashape XML file not found", path)
        if not path.is_file():
            raise InputError("expected a Metashape XML file, found a "
                             + ("folder" if path.is_dir() else "device, pipe or socket"), path)
        try:
            data = path.read_bytes()
        except OSError as exc:
            raise InputError(f"cannot read: {exc.strerror or exc}", path) from None
        from xml.parsers import expat

        parser = expat.ParserCreate()
        builder = ET.TreeBuilder()
        lines = self.lines

        def start(tag, attrs):
            lines[id(builder.start(tag, attrs))] = parser.CurrentLineNumber

        def no_entities(*_args):
            raise InputError("XML entity declarations are not allowed", path, parser.CurrentLineNumber)

        parser.StartElementHandler = start
        parser.EntityDeclHandler = no_entities
        parser.EndElementHandler = builder.end
        parser.CharacterDataHandler = builder.data
        try:
            parser.Parse(data, True)
            self.root = builder.close()
        except expat.ExpatError as exc:
            raise InputError(f"invalid XML ({expat.ErrorString(exc.code)}, column {exc.offset + 1})",
                             path, exc.lineno) from None
        except AssertionError:  # TreeBuilder.close() on an unfinished tree
            raise InputError("invalid XML (document ends early)", path, parser.CurrentLineNumber) from None

    def line(self, el: ET.Element) -> Optional[int]:
        return self.lines.get(id(el))

    def error(self, msg: str, el: Optional[ET.Element]) -> InputError:
        return InputError(msg, self.path, None if el is None else self.line(el))

    def number(self, el: ET.Element, what: str, text: Optional[str] = None) -> float:
        s = el.text if text is None else text
        try:
            v = float((s or "").strip())
        except ValueError:
            raise self.error(f"{what} is not a number: {(s or '').strip()!r}", el) from None
        if not math.isfinite(v):
            raise self.error(f"{what} is not finite", el)
        return v

    def numbers(self, el: ET.Element, what: str, n: int) -> np.ndarray:
        parts = (el.text or "").split()
        if len(parts) != n:
            raise self.error(f"{what} needs {n} numbers, got {len(parts)}", el)
        return np.array([self.number(el, what, p) for p in parts])

    def attr_number(self, el: ET.Element, name: str, what: str) -> float:
        return self.number(el, f"{what} attribute {name}", el.get(name))


def _chunk(doc: _XmlDoc) -> ET.Element:
    root = doc.root
    if root.tag == "chunk":
        return root
    if root.tag != "document":
        raise doc.error(f"not a Metashape XML export (root element <{root.tag}>, expected <document>)", root)
    chunks = root.findall("chunk")
    if not chunks:
        raise doc.error("no <chunk> in this Metashape document", root)
    if len(chunks) > 1:
        log.warning("%s: %d chunks, reading the first", doc.path, len(chunks))
    return chunks[0]


# ----------------------------------------------------------------------------------------------------
# Sensors <-> cameras


def camera_from_metashape(width: int, height: int, f: float, cx: float = 0.0, cy: float = 0.0,
                          k1: float = 0.0, k2: float = 0.0, k3: float = 0.0, p1: float = 0.0,
                          p2: float = 0.0, b1: float = 0.0) -> Camera:
    """Our Camera (OpenCV convention) from Metashape frame calibration values (see module docstring)."""
    return Camera(int(width), int(height), f + b1, f, width / 2.0 + cx - PIXEL_SHIFT,
                  height / 2.0 + cy - PIXEL_SHIFT, (k1, k2, p2, p1, k3))


def camera_to_metashape(cam: Camera) -> dict[str, float]:
    """Metashape calibration values {f, cx, cy, b1, k1, k2, k3, p1, p2} of one of our cameras."""
    k1, k2, p1, p2, k3 = cam.dist
    return {"f": cam.fy, "cx": cam.cx + PIXEL_SHIFT - cam.width / 2.0,
            "cy": cam.cy + PIXEL_SHIFT - cam.height / 2.0, "b1": cam.fx - cam.fy,
            "k1": k1, "k2": k2, "k3": k3, "p1": p2, "p2": p1}


def _read_sensor(doc: _XmlDoc, s: ET.Element) -> Optional[Camera]:
    label = s.get("label") or s.get("id")
    stype = s.get("type", "frame")
    cals = s.findall("calibration")
    cal = next((c for c in cals if c.get("class") == "adjusted"), None) or \
        next((c for c in cals if c.get("class") == "initial"), None) or (cals[0] if cals else None)
    if cal is None:
        return None
    if stype != "frame" or cal.get("type", "frame") != "frame":
        raise doc.error(f"sensor {label!r}: type {stype!r} is not supported (only frame cameras)", s)
    res = cal.find("resolution")
    if res is None:
        res = s.find("resolution")
    if res is None:
        raise doc.error(f"sensor {label!r}: no <resolution>", s)
    w = doc.attr_number(res, "width", "resolution")
    h = doc.attr_number(res, "height", "resolution")
    vals = {}
    for tag in ("f", "cx", "cy", "b1", "b2", "k1", "k2", "k3", "k4", "p1", "p2", "p3", "p4"):
        el = cal.find(tag)
        vals[tag] = 0.0 if el is None else doc.number(el, f"sensor {label!r} {tag}")
    if "f" not in {c.tag for c in cal}:
        raise doc.error(f"sensor {label!r}: calibration has no <f>", cal)
    for tag in ("b2", "k4", "p3", "p4"):
        if vals[tag] != 0.0:
            raise doc.error(f"sensor {label!r}: {tag} = {vals[tag]} is not supported by cpdetect's "
                            "camera model (k1-k3, p1, p2, b1 only)", cal.find(tag))
    try:
        return camera_from_metashape(w, h, vals["f"], vals["cx"], vals["cy"], vals["k1"], vals["k2"],
                                     vals["k3"], vals["p1"], vals["p2"], vals["b1"])
    except ValueError as exc:
        raise doc.error(f"sensor {label!r}: {exc}", cal) from None


def _read_similarity(doc: _XmlDoc, tr: ET.Element) -> Optional[Sim3]:
    rot, tra, sca = tr.find("rotation"), tr.find("translation"), tr.find("scale")
    if rot is None and tra is None and sca is None:
        if tr.text and len(tr.text.split()) == 16:  # a 4x4 matrix form
            M = doc.numbers(tr, "chunk transform", 16).reshape(4, 4)
            try:
                return Sim3.from_matrix(M)
            except ValueError as exc:
                raise doc.error(f"chunk transform is not a similarity ({exc})", tr) from None
        return None
    R = np.eye(3) if rot is None else doc.numbers(rot, "chunk rotation", 9).reshape(3, 3)
    t = np.zeros(3) if tra is None else doc.numbers(tra, "chunk translation", 3)
    s = 1.0 if sca is None else doc.number(sca, "chunk scale")
    if np.abs(R @ R.T - np.eye(3)).max() > 1e-5 or np.linalg.det(R) <= 0:
        raise doc.error("chunk rotation is not a rotation matrix", rot)
    try:
        return Sim3(s, project_to_rotation(R), t)
    except ValueError as exc:
        raise doc.error(f"chunk transform: {exc}", tr) from None


# ----------------------------------------------------------------------------------------------------
# Cameras XML


def read_metashape_cameras(path: str | os.PathLike) -> Scene:
    """Read a Metashape "Export Cameras" XML into a Scene (model frame = chunk-local frame).

    cameras: {sensor id: Camera} (adjusted calibration, else initial); images: {camera label:
    ImageRecord} for enabled cameras that have a transform (aligned). Labels are image file names
    without folder (Metashape drops the extension by default; match them to files by stem).
    meta: ``format``, ``source``, ``chunk_transform`` (Sim3 chunk -> ECEF, or absent; also stored as
    ``ecef_from_model`` like the OpenSfM reader does), ``crs_wkt``
    (chunk CRS, or absent), ``metashape_camera_ids`` ({label: camera id}), ``metashape_sensor_labels``.
    Raises :class:`InputError` naming file and line on malformed content.
    """
    path = Path(path)
    doc = _XmlDoc(path)
    chunk = _chunk(doc)
    sensors_el = chunk.find("sensors")
    cams_el = chunk.find("cameras")
    if sensors_el is None or cams_el is None:
        raise doc.error("no <sensors> or <cameras> in the chunk (not a camera export?)", chunk)
    sensors: dict[int, Camera] = {}
    sensor_labels: dict[int, str] = {}
    for s in sensors_el.findall("sensor"):
        sid = int(doc.attr_number(s, "id", "sensor"))
        cam = _read_sensor(doc, s)
        if cam is not None:
            sensors[sid] = cam
            sensor_labels[sid] = s.get("label", str(sid))
    components: dict[str, Sim3] = {}
    comps_el = chunk.find("components")
    if comps_el is not None:
        for comp in comps_el.findall("component"):
            tr = comp.find("transform")
            if tr is not None:
                sim = _read_similarity(doc, tr)
                if sim is not None:
                    components[comp.get("id", "0")] = sim
    chunk_tr = chunk.find("transform")
    chunk_sim = _read_similarity(doc, chunk_tr) if chunk_tr is not None else None
    images: dict[str, ImageRecord] = {}
    ids: dict[str, int] = {}
    comp_used: set[str] = set()
    skipped = 0
    for c in cams_el.iter("camera"):
        label = c.get("label")
        if not label:
            raise doc.error("camera without a label", c)
        tr = c.find("transform")
        if tr is None or c.get("enabled", "true").lower() in ("false", "0"):
            skipped += 1
            continue
        sid = int(doc.attr_number(c, "sensor_id", f"camera {label!r}"))
        if sid not in sensors:
            raise doc.error(f"camera {label!r} uses sensor {sid}, which is missing or has no calibration",
                            c)
        M = doc.numbers(tr, f"camera {label!r} transform", 16).reshape(4, 4)
        if np.abs(M[3] - [0, 0, 0, 1]).max() > 1e-9:
            raise doc.error(f"camera {label!r}: transform's last row is not 0 0 0 1", tr)
        try:
            chunk_from_cam = Rigid3(M[:3, :3], M[:3, 3])
        except ValueError as exc:
            raise doc.error(f"camera {label!r}: transform is not rigid ({exc})", tr) from None
        if label in images:
            raise doc.error(f"camera label {label!r} appears twice", c)
        images[label] = ImageRecord(label, sid, chunk_from_cam.inverse())
        ids[label] = int(doc.attr_number(c, "id", f"camera {label!r}"))
        comp_used.add(c.get("component_id", "0"))
    if skipped:
        log.info("%s: %d disabled or unaligned cameras skipped", path, skipped)
    meta: dict = {"format": "metashape", "source": str(path), "metashape_camera_ids": ids,
                  "metashape_sensor_labels": sensor_labels}
    sim = chunk_sim
    if components:
        used = [components[k] for k in sorted(comp_used) if k in components]
        if len(used) > 1:
            log.warning("%s: aligned cameras span %d components; using the first one's transform",
                        path, len(used))
        sim = used[0] if used else next(iter(components.values()))
    if sim is not None:
        meta["chunk_transform"] = sim
        meta["ecef_from_model"] = sim  # the same similarity under the name every reader uses
    ref = chunk.find("reference")
    if ref is not None and (ref.text or "").strip():
        meta["crs_wkt"] = ref.text.strip()
    return Scene(cameras=sensors, images=images, meta=meta)


def _fmt(v: float) -> str:
    return repr(float(v))


def _write_xml(path: str | os.PathLike, root: ET.Element) -> Path:
    ET.indent(root, space="  ")
    buf = io.BytesIO()
    ET.ElementTree(root).write(buf, encoding="UTF-8", xml_declaration=True)
    write_bytes_atomic(path, buf.getvalue() + b"\n")
    return Path(path)


def _camera_ids(scene: Scene) -> dict[str, int]:
    ids = dict(scene.meta.get("metashape_camera_ids") or {})
    ids = {k: v for k, v in ids.items() if k in scene.images}
    if len(set(ids.values())) != len(ids):
        ids = {}
    nxt = max(ids.values(), default=-1) + 1
    for name in scene.images:
        if name not in ids:
            ids[name] = nxt
            nxt += 1
    return ids


def _transform_el(parent: ET.Element, sim: Sim3) -> None:
    tr = ET.SubElement(parent, "transform")
    ET.SubElement(tr, "rotation", locked="false").text = " ".join(_fmt(v) for v in sim.R.ravel())
    ET.SubElement(tr, "translation", locked="false").text = " ".join(_fmt(v) for v in sim.t)
    ET.SubElement(tr, "scale", locked="false").text = _fmt(sim.scale)


def write_metashape_cameras(scene: Scene, path: str | os.PathLike, chunk_label: str = "Chunk 1",
                            camera_labels: str = "name") -> Path:
    """Write a Scene as a Metashape camera XML (the layout of "Export Cameras"), atomically.

    One sensor per scene camera (id = camera id), one camera per image (transform = camera -> chunk =
    inverse of ``cam_from_world``), ``scene.meta["chunk_transform"]`` (Sim3) as the component
    transform and ``scene.meta["crs_wkt"]`` as the chunk reference, when present. Camera labels are
    the image names (``camera_labels="name"``, exact round trip) or their stems (``"stem"``, what
    Metashape shows, for importing into a chunk).
    """
    if camera_labels not in ("stem", "name"):
        raise ValueError("camera_labels must be 'stem' or 'name'")
    root = ET.Element("document", version=DOCUMENT_VERSION)
    chunk = ET.SubElement(root, "chunk", label=chunk_label, enabled="true")
    sensors = ET.SubElement(chunk, "sensors", next_id=str(max(scene.cameras, default=-1) + 1))
    labels = scene.meta.get("metashape_sensor_labels") or {}
    for sid, cam in scene.cameras.items():
        s = ET.SubElement(sensors, "sensor", id=str(int(sid)), label=str(labels.get(sid, f"camera {sid}")),
                          type="frame")
        ET.SubElement(s, "resolution", width=str(cam.width), height=str(cam.height))
        cal = ET.SubElement(s, "calibration", type="frame", **{"class": "adjusted"})
        ET.SubElement(cal, "resolution", width=str(cam.width), height=str(cam.height))
        vals = camera_to_metashape(cam)
        for tag in ("f", "cx", "cy", "b1", "k1", "k2", "k3", "p1", "p2"):
            if tag in ("f", "cx", "cy") or vals[tag] != 0.0:
                ET.SubElement(cal, tag).text = _fmt(vals[tag])
    sim = scene.meta.get("chunk_transform")
    comps = ET.SubElement(chunk, "components", next_id="1", active_id="0")
    comp = ET.SubElement(comps, "component", id="0", label="Component 1")
    if isinstance(sim, Sim3):
        _transform_el(comp, sim)
    ids = _camera_ids(scene)
    cams = ET.SubElement(chunk, "cameras", next_id=str(max(ids.values(), default=-1) + 1),
                         next_group_id="0")
    for name, rec in scene.images.items():
        if rec.camera_id not in scene.cameras:
            raise ValueError(f"image {name!r} uses camera {rec.camera_id}, which the scene lacks")
        c = ET.SubElement(cams, "camera", id=str(ids[name]), sensor_id=str(int(rec.camera_id)),
                          component_id="0", label=Path(name).stem if camera_labels == "stem" else name)
        ET.SubElement(c, "transform").text = " ".join(
            _fmt(v) for v in rec.cam_from_world.inverse().matrix.ravel())
    wkt = scene.meta.get("crs_wkt")
    if wkt:
        ET.SubElement(chunk, "reference").text = str(wkt)
    return _write_xml(path, root)


# ----------------------------------------------------------------------------------------------------
# Markers


@dataclass
class MarkerRecord:
    """One Metashape marker: label, surveyed reference (3,) float64 in the chunk CRS (or None), and
    image projections {image name: (x, y)} in the OpenCV pixel convention."""

    label: str
    reference: Optional[np.ndarray] = None
    projections: dict[str, tuple[float, float]] = field(default_factory=dict)
    pinned: bool = True

    def __post_init__(self) -> None:
        if self.reference is not None:
            self.reference = np.asarray(self.reference, np.float64).reshape(3)


@dataclass
class MetashapeMarkers:
    """Markers read from a Metashape XML, with the chunk CRS WKT (None if absent)."""

    markers: list[MarkerRecord]
    crs_wkt: Optional[str] = None
    path: Optional[str] = None

    def crs(self):
        """The chunk CRS as a pyproj.CRS, or None when the file has none or it is ``LOCAL_CS``
        (not georeferenced). An unreadable WKT raises :class:`InputError` naming the file."""
        if not self.crs_wkt or self.crs_wkt.lstrip().upper().startswith("LOCAL_CS"):
            return None
        from pyproj import CRS
        from pyproj.exceptions import CRSError

        try:
            return CRS.from_wkt(self.crs_wkt)
        except CRSError as exc:
            raise InputError(f"chunk <reference> is not a readable CRS ({str(exc).split(': (')[0]})",
                             self.path) from None

    def survey_points(self) -> dict[str, np.ndarray]:
        """{label: reference (3,)} of the markers that have reference coordinates."""
        return {m.label: m.reference for m in self.markers if m.reference is not None}


def _crs_wkt(crs) -> Optional[str]:
    if crs is None:
        return None
    if isinstance(crs, str):
        if crs.lstrip().upper().startswith(("GEOGCS", "PROJCS", "LOCAL_CS", "COMPD_CS", "GEOCCS")):
            return crs.strip()  # already WKT1, as Metashape writes it
        from .odm import parse_crs

        crs = parse_crs(crs, error=InputError)
    from pyproj.enums import WktVersion
    from pyproj.exceptions import CRSError

    # Metashape writes WKT1 (GDAL flavour); CRSs that WKT1 cannot express fall back to WKT2.
    try:
        wkt = crs.to_wkt(WktVersion.WKT1_GDAL)
    except CRSError:
        wkt = None
    return wkt or crs.to_wkt(WktVersion.WKT2_2019)


def write_metashape_markers(path: str | os.PathLike, markers: Sequence[MarkerRecord],
                            scene: Optional[Scene] = None, crs=None,
                            camera_labels: str = "stem") -> Path:
    """Write markers as a Metashape XML that File > Import > Markers loads into a chunk, atomically.

    markers: labels, reference coordinates (chunk CRS; x = longitude for geographic CRSs) and
    projections {image name: (x, y) OpenCV pixels}, written with x_ms = x + 0.5. ``crs``: pyproj.CRS or
    CRS text (EPSG:xxxx ...), written as WKT in ``<reference>``. Cameras are listed with ids (from
    ``scene.meta["metashape_camera_ids"]`` when the scene came from Metashape, else in scene order) and
    labels: ``camera_labels="stem"`` drops the extension as Metashape does, ``"name"`` keeps it.
    Projections onto images missing from ``scene`` (when given) raise ValueError.
    """
    if camera_labels not in ("stem", "name"):
        raise ValueError("camera_labels must be 'stem' or 'name'")
    names: list[str] = list(scene.images) if scene is not None else []
    for m in markers:
        for img in m.projections:
            if img not in names:
                if scene is not None:
                    raise ValueError(f"marker {m.label!r}: image {img!r} is not in the scene")
                names.append(img)
    if scene is not None:
        ids = _camera_ids(scene)
    else:
        ids = {n: i for i, n in enumerate(names)}
    root = ET.Element("document", version=DOCUMENT_VERSION)
    chunk = ET.SubElement(root, "chunk", label="Chunk 1", enabled="true")
    cams = ET.SubElement(chunk, "cameras", next_id=str(max(ids.values(), default=-1) + 1),
                         next_group_id="0")
    used = {img for m in markers for img in m.projections}
    for name in names:
        if name in used:
            label = Path(name).stem if camera_labels == "stem" else name
            ET.SubElement(cams, "camera", id=str(ids[name]), label=label)
    mk = ET.SubElement(chunk, "markers", next_id=str(len(markers)), next_group_id="0")
    for i, m in enumerate(markers):
        e = ET.SubElement(mk, "marker", id=str(i), label=m.label)
        if m.reference is not None:
            if not np.all(np.isfinite(m.reference)):
                raise ValueError(f"marker {m.label!r} has non-finite reference coordinates")
            x, y, z = m.reference
            ET.SubElement(e, "reference", x=_fmt(x), y=_fmt(y), z=_fmt(z), enabled="true")
    frames = ET.SubElement(chunk, "frames", next_id="1")
    fmk = ET.SubElement(ET.SubElement(frames, "frame", id="0"), "markers")
    for i, m in enumerate(markers):
        if not m.projections:
            continue
        e = ET.SubElement(fmk, "marker", marker_id=str(i))
        for img, (x, y) in m.projections.items():
            if not (math.isfinite(x) and math.isfinite(y)):
                raise ValueError(f"marker {m.label!r} in {img!r}: non-finite pixel")
            ET.SubElement(e, "location", camera_id=str(ids[img]), pinned="true" if m.pinned else "false",
                          x=_fmt(x + PIXEL_SHIFT), y=_fmt(y + PIXEL_SHIFT))
    wkt = _crs_wkt(crs)
    if wkt:
        ET.SubElement(chunk, "reference").text = wkt
    return _write_xml(path, root)


def read_metashape_markers(path: str | os.PathLike) -> MetashapeMarkers:
    """Read the markers of a Metashape XML (a markers export or a full chunk document).

    Projections are keyed by camera label (or ``"camera <id>"`` when the file lists no cameras), in the
    OpenCV pixel convention; ``valid="0"`` locations are skipped. Reference coordinates are in the chunk
    CRS (``crs_wkt``). Raises :class:`InputError` naming file and line on malformed content.
    """
    path = Path(path)
    doc = _XmlDoc(path)
    chunk = _chunk(doc)
    mk = chunk.find("markers")
    if mk is None:
        raise doc.error("no <markers> in the chunk", chunk)
    labels: dict[str, str] = {}
    cams_el = chunk.find("cameras")
    if cams_el is not None:
        for c in cams_el.iter("camera"):
            if c.get("id") is not None:
                labels[c.get("id")] = c.get("label") or f"camera {c.get('id')}"
    markers: dict[str, MarkerRecord] = {}
    order: list[str] = []
    for e in mk.iter("marker"):
        label = e.get("label")
        mid = e.get("id")
        if not label or mid is None:
            raise doc.error("marker without id or label", e)
        if label in {markers[k].label for k in markers}:
            raise doc.error(f"marker label {label!r} appears twice", e)
        ref = e.find("reference")
        xyz = None
        if ref is not None and all(ref.get(a) is not None for a in "xyz"):
            xyz = np.array([doc.attr_number(ref, a, f"marker {label!r} reference") for a in "xyz"])
        markers[mid] = MarkerRecord(label, xyz)
        order.append(mid)
    frames = chunk.find("frames")
    if frames is not None:
        for fm in frames.iter("marker"):
            mid = fm.get("marker_id")
            if mid not in markers:
                raise doc.error(f"projection of unknown marker id {mid!r}", fm)
            for loc in fm.findall("location"):
                if loc.get("valid", "1") in ("0", "false"):
                    continue
                cid = loc.get("camera_id")
                img = labels.get(cid, f"camera {cid}")
                x = doc.attr_number(loc, "x", f"marker {markers[mid].label!r} location")
                y = doc.attr_number(loc, "y", f"marker {markers[mid].label!r} location")
                markers[mid].projections[img] = (x - PIXEL_SHIFT, y - PIXEL_SHIFT)
    ref = chunk.find("reference")
    wkt = ref.text.strip() if ref is not None and (ref.text or "").strip() else None
    return MetashapeMarkers([markers[k] for k in order], wkt, str(path))


def markers_from_observations(observations: Iterable, references: Optional[Mapping[str, np.ndarray]] = None
                              ) -> list[MarkerRecord]:
    """MarkerRecords from gcp_list-like observations (objects with ``name, image, im_x, im_y`` and an
    optional ``geo``): one marker per name, references from ``references`` or from ``geo``."""
    out: dict[str, MarkerRecord] = {}
    for o in observations:
        name = o.name
        if name is None:
            raise ValueError("every observation needs a GCP name to become a marker")
        ref = (references or {}).get(name, getattr(o, "geo", None))
        m = out.setdefault(name, MarkerRecord(name, ref))
        m.projections[o.image] = (float(o.im_x), float(o.im_y))
    return list(out.values())
