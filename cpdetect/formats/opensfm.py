"""OpenSfM / ODM ``reconstruction.json`` <-> :class:`geometry.scene.Scene`.

Conventions (docs/formats.md, "OpenSfM reconstruction.json"; OpenSfM ``io.py``, ``geometry.rst``):

* The file is a JSON list of reconstructions; we read one (the first by default: OpenSfM sorts them
  largest first).
* Shot poses are world -> camera: ``rotation`` is an angle-axis vector (radians), ``translation`` a
  3-vector, so ``cam_from_world = (Rotation.from_rotvec(rotation), translation)``.
* Camera intrinsics are *normalised*: lengths divided by ``size = max(width, height)``, principal
  point measured from the image centre. OpenSfM pixels put the centre of the top-left pixel at (0, 0)
  (``features.denormalized_image_coordinates``: ``x = xn * size - 0.5 + w / 2``), so in OpenCV pixels
  ``fx = focal_x * size``, ``cx = c_x * size + (w - 1) / 2`` (likewise y).
* Projection types read: ``perspective`` (focal, k1, k2; centred principal point), ``brown`` (focal_x,
  focal_y, c_x, c_y, k1, k2, p1, p2, k3 in OpenCV's order and meaning), ``radial`` (k1, k2) and
  ``simple_radial`` (k1). Fisheye and spherical models are not pinhole: an error names the camera.
* World frame: topocentric ENU (x east, y north, z up) around ``reference_lla`` when present; we keep
  it as ``meta["reference_lla"]`` and add ``meta["ecef_from_model"]`` (a Sim3 with scale 1).
"""
from __future__ import annotations

import logging
import math
import os
from pathlib import Path
from typing import Any, Optional

import numpy as np
from scipy.spatial.transform import Rotation

from geometry.camera import Camera
from geometry.scene import ImageRecord, Scene
from geometry.transforms import Rigid3, Sim3

from ..errors import InputError
from ..fileio import read_json, write_json_atomic

log = logging.getLogger(__name__)

PINHOLE_TYPES = ("perspective", "brown", "radial", "simple_radial")


def _num(path: Path, where: str, v: Any) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise InputError(f"{where} is not a number: {v!r}", path)
    f = float(v)
    if not math.isfinite(f):
        raise InputError(f"{where} is not finite", path)
    return f


def _vec(path: Path, where: str, v: Any, n: int = 3) -> np.ndarray:
    if not isinstance(v, list) or len(v) != n:
        raise InputError(f"{where} must be a list of {n} numbers", path)
    return np.array([_num(path, f"{where}[{i}]", x) for i, x in enumerate(v)])


def camera_from_opensfm(obj: dict, path: Path = Path("?"), key: str = "?") -> Camera:
    """Our Camera (OpenCV pixels) from one entry of ``cameras`` (see module docstring)."""
    where = f"cameras[{key!r}]"
    if not isinstance(obj, dict):
        raise InputError(f"{where} is not an object", path)
    pt = obj.get("projection_type", "perspective")
    if pt not in PINHOLE_TYPES:
        raise InputError(f"camera {key!r}: projection_type {pt!r} is not supported "
                         f"(supported: {', '.join(PINHOLE_TYPES)})", path)
    w = int(_num(path, f"{where}.width", obj.get("width")))
    h = int(_num(path, f"{where}.height", obj.get("height")))
    if w <= 0 or h <= 0:
        raise InputError(f"camera {key!r}: width and height must be positive", path)
    size = float(max(w, h))

    def get(name: str, default: Optional[float] = 0.0) -> float:
        if name not in obj:
            if default is None:
                raise InputError(f"camera {key!r} ({pt}) has no {name}", path)
            return default
        return _num(path, f"{where}.{name}", obj[name])

    if pt == "perspective":
        fx = fy = get("focal", None)
        c_x = c_y = 0.0
        dist = (get("k1"), get("k2"), 0.0, 0.0, 0.0)
    else:
        fx, fy = get("focal_x", None), get("focal_y", None)
        c_x, c_y = get("c_x"), get("c_y")
        if pt == "brown":
            dist = (get("k1"), get("k2"), get("p1"), get("p2"), get("k3"))
        elif pt == "radial":
            dist = (get("k1"), get("k2"), 0.0, 0.0, 0.0)
        else:
            dist = (get("k1"), 0.0, 0.0, 0.0, 0.0)
    try:
        return Camera(w, h, fx * size, fy * size, c_x * size + (w - 1) / 2.0, c_y * size + (h - 1) / 2.0,
                      dist)
    except ValueError as exc:
        raise InputError(f"camera {key!r}: {exc}", path) from None


def camera_to_opensfm(cam: Camera) -> dict:
    """OpenSfM camera object: ``perspective`` when it fits exactly (fx == fy, centred principal point,
    radial k1, k2 only), else ``brown``."""
    size = float(max(cam.width, cam.height))
    k1, k2, p1, p2, k3 = cam.dist
    c_x = (cam.cx - (cam.width - 1) / 2.0) / size
    c_y = (cam.cy - (cam.height - 1) / 2.0) / size
    base = {"width": int(cam.width), "height": int(cam.height)}
    if cam.fx == cam.fy and c_x == 0.0 and c_y == 0.0 and p1 == p2 == k3 == 0.0:
        return {"projection_type": "perspective", **base, "focal": cam.fx / size, "k1": k1, "k2": k2}
    return {"projection_type": "brown", **base, "focal_x": cam.fx / size, "focal_y": cam.fy / size,
            "c_x": c_x, "c_y": c_y, "k1": k1, "k2": k2, "p1": p1, "p2": p2, "k3": k3}


def ecef_from_enu(latitude: float, longitude: float, altitude: float) -> Sim3:
    """The rigid transform (as a Sim3 with scale 1) from the topocentric ENU frame at a WGS84
    latitude/longitude (degrees) and ellipsoidal altitude (m) to ECEF (EPSG:4978), metres."""
    from pyproj import Transformer

    to_ecef = Transformer.from_crs("EPSG:4979", "EPSG:4978", always_xy=True)
    origin = np.array(to_ecef.transform(longitude, latitude, altitude))
    lat, lon = math.radians(latitude), math.radians(longitude)
    east = [-math.sin(lon), math.cos(lon), 0.0]
    north = [-math.sin(lat) * math.cos(lon), -math.sin(lat) * math.sin(lon), math.cos(lat)]
    up = [math.cos(lat) * math.cos(lon), math.cos(lat) * math.sin(lon), math.sin(lat)]
    return Sim3(1.0, np.column_stack([east, north, up]), origin)


def read_opensfm(path: str | os.PathLike, index: int = 0) -> Scene:
    """Read reconstruction number ``index`` of an OpenSfM ``reconstruction.json``.

    cameras keyed 1, 2, ... in file order (``meta["opensfm_camera_ids"]`` maps them back to the
    file's camera keys); images keyed by shot name; points (n, 3) float64 and colors (n, 3) uint8
    from ``points``; ``meta["reference_lla"]`` and ``meta["ecef_from_model"]`` when the file has a
    reference. Raises :class:`InputError` naming the file (and JSON line for syntax errors).
    """
    path = Path(path)
    data = read_json(path, "OpenSfM reconstruction.json")
    if isinstance(data, dict) and "shots" in data:
        data = [data]
    if not isinstance(data, list) or not data or not all(isinstance(r, dict) for r in data):
        raise InputError("not an OpenSfM reconstruction file (expected a list of reconstructions)", path)
    if not 0 <= index < len(data):
        raise InputError(f"reconstruction {index} requested, the file has {len(data)}", path)
    if len(data) > 1:
        log.info("%s: %d reconstructions, reading number %d", path, len(data), index)
    rec = data[index]
    cams_obj, shots_obj = rec.get("cameras"), rec.get("shots")
    if not isinstance(cams_obj, dict) or not isinstance(shots_obj, dict):
        raise InputError(f"reconstruction {index} has no 'cameras' or 'shots' object", path)
    cameras: dict[int, Camera] = {}
    keys: dict[str, int] = {}
    for i, (key, obj) in enumerate(cams_obj.items(), 1):
        cameras[i] = camera_from_opensfm(obj, path, key)
        keys[key] = i
    images: dict[str, ImageRecord] = {}
    for name, shot in shots_obj.items():
        where = f"shots[{name!r}]"
        if not isinstance(shot, dict):
            raise InputError(f"{where} is not an object", path)
        cam_key = shot.get("camera")
        if cam_key not in keys:
            raise InputError(f"{where} uses camera {cam_key!r}, which is not in 'cameras'", path)
        rv = _vec(path, f"{where}.rotation", shot.get("rotation"))
        t = _vec(path, f"{where}.translation", shot.get("translation", [0.0, 0.0, 0.0]))
        images[name] = ImageRecord(name, keys[cam_key], Rigid3(Rotation.from_rotvec(rv).as_matrix(), t))
    points = colors = None
    pts_obj = rec.get("points") or {}
    if not isinstance(pts_obj, dict):
        raise InputError("'points' is not an object", path)
    if pts_obj:
        pts, cols = [], []
        for pid, p in pts_obj.items():
            if not isinstance(p, dict):
                raise InputError(f"points[{pid!r}] is not an object", path)
            pts.append(_vec(path, f"points[{pid!r}].coordinates", p.get("coordinates")))
            c = p.get("color", [128, 128, 128])
            cols.append(_vec(path, f"points[{pid!r}].color", c))
        points = np.array(pts, np.float64).reshape(-1, 3)
        colors = np.clip(np.rint(np.array(cols)), 0, 255).astype(np.uint8).reshape(-1, 3)
    meta: dict = {"format": "opensfm", "source": str(path), "opensfm_camera_ids": {v: k for k, v in keys.items()}}
    lla = rec.get("reference_lla")
    if lla is not None:
        if not isinstance(lla, dict):
            raise InputError("reference_lla is not an object", path)
        ref = {k: _num(path, f"reference_lla.{k}", lla.get(k)) for k in ("latitude", "longitude", "altitude")}
        meta["reference_lla"] = ref
        meta["ecef_from_model"] = ecef_from_enu(ref["latitude"], ref["longitude"], ref["altitude"])
    return Scene(cameras=cameras, images=images, points=points, colors=colors, meta=meta)


def scene_to_opensfm(scene: Scene) -> list[dict]:
    """The JSON object (a one-element list) of a Scene (see :func:`write_opensfm`)."""
    ids = scene.meta.get("opensfm_camera_ids") or {}
    keys = {cid: str(ids.get(cid, f"cpdetect camera {cid}")) for cid in scene.cameras}
    if len(set(keys.values())) != len(keys):
        keys = {cid: f"cpdetect camera {cid}" for cid in scene.cameras}
    cams = {keys[cid]: camera_to_opensfm(cam) for cid, cam in scene.cameras.items()}
    shots = {}
    for name, rec in scene.images.items():
        if rec.camera_id not in scene.cameras:
            raise ValueError(f"image {name!r} uses camera {rec.camera_id}, which the scene lacks")
        shots[name] = {"camera": keys[rec.camera_id],
                       "rotation": Rotation.from_matrix(rec.cam_from_world.R).as_rotvec().tolist(),
                       "translation": rec.cam_from_world.t.tolist()}
    out: dict[str, Any] = {"cameras": cams, "shots": shots}
    if scene.points is not None:
        pts = np.asarray(scene.points, np.float64).reshape(-1, 3)
        cols = (np.asarray(scene.colors).reshape(-1, 3) if scene.colors is not None
                else np.full((len(pts), 3), 128))
        out["points"] = {str(i): {"coordinates": pts[i].tolist(), "color": [int(c) for c in cols[i]]}
                         for i in range(len(pts))}
    else:
        out["points"] = {}
    if scene.meta.get("reference_lla"):
        out["reference_lla"] = {k: float(scene.meta["reference_lla"][k])
                                for k in ("latitude", "longitude", "altitude")}
    return [out]


def write_opensfm(scene: Scene, path: str | os.PathLike) -> Path:
    """Write a Scene as an OpenSfM reconstruction.json (one reconstruction), atomically.

    Shots carry angle-axis world -> camera poses; cameras are written as ``perspective`` when exact,
    else ``brown``, in normalised units; ``meta["reference_lla"]`` is kept.
    """
    write_json_atomic(path, scene_to_opensfm(scene), indent=1)
    return Path(path)
