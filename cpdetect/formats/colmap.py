"""COLMAP sparse models (text or binary) <-> :class:`geometry.scene.Scene`, through pycolmap.

Conventions (see docs/formats.md, "COLMAP model"):

* Poses: COLMAP stores ``cam_from_world`` (world -> camera, Hamilton quaternion ``QW QX QY QZ`` + ``T``),
  the same direction as ``ImageRecord.cam_from_world``; pycolmap's ``Rotation3d.quat`` is ``[x, y, z, w]``,
  so we hand pycolmap rotation matrices and never quaternions.
* Pixels: COLMAP puts the centre of the top-left pixel at (0.5, 0.5); cpdetect (OpenCV) at (0, 0).
  ``cx_colmap = cx_opencv + 0.5`` and ``cy_colmap = cy_opencv + 0.5``; focal lengths and distortion are
  unchanged (the OPENCV model's k1, k2, p1, p2 and FULL_OPENCV's k3 are OpenCV's).
* Rigs and frames (COLMAP >= 3.12 / pycolmap 4): each camera gets a trivial rig (rig_id = camera_id) and
  each image a trivial frame (frame_id = image_id) that carries its pose.

Only the model's cameras, registered images and 3D point positions/colours go into the Scene; tracks and
2D keypoints are not kept (``apply_sim3_to_colmap`` works on the full model and keeps them).
"""
from __future__ import annotations

import logging
import math
import os
import shutil
import tempfile
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator, Optional

import numpy as np

from geometry.camera import Camera
from geometry.scene import ImageRecord, Scene
from geometry.transforms import Rigid3, Sim3

from ..errors import InputError
from ..fileio import cannot_write

log = logging.getLogger(__name__)

#: Shift from the OpenCV pixel convention to COLMAP's: x_colmap = x_opencv + PIXEL_SHIFT.
PIXEL_SHIFT = 0.5

MODEL_PARTS = ("cameras", "images", "points3D", "rigs", "frames")
MODEL_FILES = tuple(f"{p}{ext}" for p in MODEL_PARTS for ext in (".txt", ".bin")) + ("project.ini",)
READ_MODELS = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV", "FULL_OPENCV")


def _pycolmap():
    import pycolmap

    return pycolmap


# ----------------------------------------------------------------------------------------------------
# Locating a model


def find_colmap_model(folder: str | os.PathLike) -> Path:
    """The folder holding a COLMAP model's files: ``folder`` itself, ``folder/sparse`` or
    ``folder/sparse/0`` (the first that holds ``cameras``), checked for the three required files.

    Raises :class:`InputError` naming the missing file (e.g. ``.../images.txt``).
    """
    folder = Path(folder)
    if not folder.exists():
        raise InputError("COLMAP model folder not found", folder)
    if not folder.is_dir():
        raise InputError("expected a COLMAP model folder, found a file", folder)
    for cand in (folder, folder / "sparse", folder / "sparse" / "0"):
        if _has_part(cand, "cameras") or _has_part(cand, "images"):
            break
    else:
        raise InputError("no COLMAP model here (no cameras.txt/.bin in it, in sparse/ or in sparse/0)",
                         folder)
    binary = _has_part(cand, "cameras", ".bin") or _has_part(cand, "images", ".bin")
    ext = ".bin" if binary else ".txt"
    for part in ("cameras", "images", "points3D"):
        if not _has_part(cand, part, ext):
            raise InputError(f"COLMAP model is missing {part}{ext}", cand / f"{part}{ext}")
    return cand


def _has_part(folder: Path, part: str, ext: Optional[str] = None) -> bool:
    exts = (ext,) if ext else (".txt", ".bin")
    return any((folder / f"{part}{e}").is_file() for e in exts)


def is_colmap_model(folder: str | os.PathLike) -> bool:
    """True if ``folder`` (or its sparse/ or sparse/0) looks like a COLMAP model."""
    folder = Path(folder)
    return folder.is_dir() and any(_has_part(c, "cameras") for c in
                                   (folder, folder / "sparse", folder / "sparse" / "0"))


def _load_reconstruction(model: Path):
    """pycolmap.Reconstruction of a located model folder; every failure becomes an InputError."""
    pycolmap = _pycolmap()
    binary = _has_part(model, "cameras", ".bin") or _has_part(model, "images", ".bin")
    if binary:
        _check_binary_layout(model)
    rec = pycolmap.Reconstruction()
    try:
        if binary:
            rec.read_binary(model)
        else:
            rec.read_text(model)
    except (ValueError, RuntimeError, IndexError, MemoryError, OSError) as exc:
        where, line = (model, None) if binary else _locate_text_error(model)
        msg = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise InputError(f"cannot read COLMAP {'binary' if binary else 'text'} model ({msg})",
                         where, line) from None
    return rec, binary


def _param_counts() -> dict[int, int]:
    """{COLMAP camera model id: number of parameters}, asked from pycolmap."""
    pycolmap = _pycolmap()
    out = {}
    for name, mid in pycolmap.CameraModelId.__members__.items():
        if name != "INVALID":
            out[int(mid)] = len(pycolmap.Camera.create_from_model_id(1, mid, 1.0, 1, 1).params)
    return out


def _check_binary_layout(model: Path) -> None:
    """Walk the record sizes of cameras.bin, images.bin and points3D.bin before pycolmap reads them.

    pycolmap reads past the end of a truncated file (stale values, or a crash of the interpreter on a
    huge track length), so the files' structure is checked first: counts and lengths only, following
    COLMAP's little-endian layouts (doc/format.rst); pycolmap still does the reading.
    """
    import struct

    def walk(name: str, record) -> None:
        path = model / name
        data = path.read_bytes()
        try:
            (n,) = struct.unpack_from("<Q", data, 0)
            pos = 8
            for _ in range(n):
                pos = record(data, pos)
                if pos > len(data):
                    raise struct.error
        except (struct.error, KeyError, ValueError):
            raise InputError("truncated or corrupt COLMAP binary file", path) from None
        if pos != len(data):
            raise InputError(f"corrupt COLMAP binary file ({len(data) - pos} unexpected bytes at the end)",
                             path)

    counts = _param_counts()

    def camera(data: bytes, pos: int) -> int:
        (model_id,) = struct.unpack_from("<i", data, pos + 4)
        return pos + 24 + 8 * counts[model_id]

    def image(data: bytes, pos: int) -> int:
        end = data.index(b"\0", pos + 64)
        (n2d,) = struct.unpack_from("<Q", data, end + 1)
        return end + 9 + 24 * n2d

    def point(data: bytes, pos: int) -> int:
        (track,) = struct.unpack_from("<Q", data, pos + 43)
        return pos + 51 + 8 * track

    walk("cameras.bin", camera)
    walk("images.bin", image)
    walk("points3D.bin", point)


def _locate_text_error(model: Path) -> tuple[Path, Optional[int]]:
    """Best effort after pycolmap rejected a text model: the first line with too few or non-numeric
    fields, or a camera line whose parameter count does not fit its model. Only used to name file and
    line in the error; pycolmap does the reading."""
    pycolmap = _pycolmap()
    counts = _param_counts()
    n_params = {name: counts[int(mid)] for name, mid in pycolmap.CameraModelId.__members__.items()
                if name != "INVALID"}
    specs = {  # file: test of one data line's fields (k: index of the data line)
        "cameras.txt": lambda f, k: (len(f) >= 5 and _all_num(f[:1] + f[2:])
                                     and len(f) - 4 == n_params.get(f[1], -1)),
        "images.txt": lambda f, k: (k % 2 == 1) or (len(f) >= 10 and _all_num(f[:9])),
        "points3D.txt": lambda f, k: len(f) >= 8 and _all_num(f),
    }
    for name, ok in specs.items():
        path = model / name
        try:
            lines = path.read_text(encoding="utf-8", errors="replace").splitlines()
        except OSError:
            continue
        k = 0
        for lineno, raw in enumerate(lines, 1):
            s = raw.strip()
            if name != "images.txt" and (not s or s.startswith("#")):
                continue
            if name == "images.txt" and s.startswith("#"):
                continue
            fields = s.split()
            if name == "images.txt" and k % 2 == 0 and not s:
                continue
            if not ok(fields, k):
                return path, lineno
            k += 1
    return model, None


def _all_num(fields) -> bool:
    try:
        return all(math.isfinite(float(v)) for v in fields)
    except ValueError:
        return False


def _text_line(model: Path, name: str, first_field: str) -> Optional[int]:
    """1-based line of ``name`` whose first field is ``first_field`` (text models), else None."""
    path = model / name
    if not path.is_file():
        return None
    with open(path, encoding="utf-8", errors="replace") as fh:
        for lineno, raw in enumerate(fh, 1):
            f = raw.split()
            if f and f[0] == first_field and not raw.lstrip().startswith("#"):
                return lineno
    return None


# ----------------------------------------------------------------------------------------------------
# Cameras


def camera_from_colmap(model_name: str, width: int, height: int, params) -> Camera:
    """Our Camera (OpenCV pixel convention) from a COLMAP model name and parameter list.

    Raises ``ValueError`` for models we do not read or parameters that do not fit them (callers add the
    file and camera id).
    """
    p = [float(v) for v in params]
    if not all(math.isfinite(v) for v in p):
        raise ValueError("parameters are not finite")
    n_expected = {"SIMPLE_PINHOLE": 3, "PINHOLE": 4, "SIMPLE_RADIAL": 4, "RADIAL": 5, "OPENCV": 8,
                  "FULL_OPENCV": 12}
    if model_name not in n_expected:
        raise ValueError(f"camera model {model_name} is not supported (supported: {', '.join(READ_MODELS)})")
    if len(p) != n_expected[model_name]:
        raise ValueError(f"{model_name} needs {n_expected[model_name]} parameters, got {len(p)}")
    if model_name in ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL"):
        fx = fy = p[0]
        cx, cy = p[1], p[2]
        ks = p[3:]
        dist = (ks[0] if ks else 0.0, ks[1] if len(ks) > 1 else 0.0, 0.0, 0.0, 0.0)
    else:
        fx, fy, cx, cy = p[:4]
        if model_name == "PINHOLE":
            dist = (0.0,) * 5
        elif model_name == "OPENCV":
            dist = (p[4], p[5], p[6], p[7], 0.0)
        else:  # FULL_OPENCV: k1 k2 p1 p2 k3 k4 k5 k6 (k4..k6: rational denominator)
            if any(v != 0.0 for v in p[9:12]):
                raise ValueError("FULL_OPENCV with rational terms k4..k6 != 0 is not supported")
            dist = (p[4], p[5], p[6], p[7], p[8])
    return Camera(int(width), int(height), fx, fy, cx - PIXEL_SHIFT, cy - PIXEL_SHIFT, dist)


def camera_to_colmap(cam: Camera) -> tuple[str, list[float]]:
    """(COLMAP model name, parameters in COLMAP's pixel convention) for one of our cameras:
    PINHOLE without distortion, OPENCV when k3 == 0, FULL_OPENCV otherwise."""
    cx, cy = cam.cx + PIXEL_SHIFT, cam.cy + PIXEL_SHIFT
    k1, k2, p1, p2, k3 = cam.dist
    if not cam.has_distortion:
        return "PINHOLE", [cam.fx, cam.fy, cx, cy]
    if k3 == 0.0:
        return "OPENCV", [cam.fx, cam.fy, cx, cy, k1, k2, p1, p2]
    return "FULL_OPENCV", [cam.fx, cam.fy, cx, cy, k1, k2, p1, p2, k3, 0.0, 0.0, 0.0]


# ----------------------------------------------------------------------------------------------------
# Reading


def read_colmap(folder: str | os.PathLike) -> Scene:
    """Read a COLMAP model (text or binary; ``folder``, ``folder/sparse`` or ``folder/sparse/0``).

    Returns a Scene with cameras (keyed by COLMAP camera id, OpenCV pixel convention), registered
    images (keyed by name, ``cam_from_world`` in the model frame), points (n, 3) float64 and colors
    (n, 3) uint8 (None if the model has no points). ``meta`` holds ``format="colmap"``, ``source``,
    ``colmap_binary`` and ``colmap_image_ids`` ({name: image_id}) for faithful write-back.
    Raises :class:`InputError` naming the file (and line, for text models) on any problem.
    """
    model = find_colmap_model(folder)
    rec, binary = _load_reconstruction(model)
    cam_file = model / ("cameras.bin" if binary else "cameras.txt")
    img_file = model / ("images.bin" if binary else "images.txt")
    cameras: dict[int, Camera] = {}
    for cam_id, c in rec.cameras.items():
        try:
            cameras[int(cam_id)] = camera_from_colmap(c.model.name, c.width, c.height, list(c.params))
        except ValueError as exc:
            line = None if binary else _text_line(model, "cameras.txt", str(cam_id))
            raise InputError(f"camera {cam_id}: {exc}", cam_file, line) from None
    images: dict[str, ImageRecord] = {}
    ids: dict[str, int] = {}
    skipped = 0
    for img_id in sorted(rec.images.keys()):
        im = rec.images[img_id]
        if not im.has_pose:
            skipped += 1
            continue
        line = None if binary else _text_line(model, "images.txt", str(img_id))
        if im.camera_id not in cameras:
            raise InputError(f"image {im.name!r} uses camera {im.camera_id}, which is not in the model",
                             img_file, line)
        if im.name in images:
            raise InputError(f"image name {im.name!r} appears twice", img_file, line)
        pose = im.cam_from_world()
        pose = pose() if callable(pose) else pose  # older pycolmap exposed a property
        M = np.asarray(pose.matrix(), float)
        try:
            rigid = Rigid3(M[:3, :3], M[:3, 3])
        except ValueError as exc:
            raise InputError(f"image {im.name!r}: bad pose ({exc})", img_file, line) from None
        images[im.name] = ImageRecord(im.name, int(im.camera_id), rigid)
        ids[im.name] = int(img_id)
    if skipped:
        log.info("%s: %d unregistered images skipped", model, skipped)
    points = colors = None
    if rec.num_points3D():
        items = sorted(rec.points3D.items(), key=lambda kv: kv[0])
        pids = [k for k, _ in items]
        points = np.empty((len(items), 3), np.float64)
        colors = np.empty((len(items), 3), np.uint8)
        for i, (_, p) in enumerate(items):
            points[i] = p.xyz
            colors[i] = p.color
        if not np.all(np.isfinite(points)):
            bad = pids[int(np.flatnonzero(~np.isfinite(points).all(axis=1))[0])]
            line = None if binary else _text_line(model, "points3D.txt", str(bad))
            raise InputError(f"3D point {bad} has non-finite coordinates",
                             model / ("points3D.bin" if binary else "points3D.txt"), line)
    meta = {"format": "colmap", "source": str(model), "colmap_binary": binary, "colmap_image_ids": ids}
    return Scene(cameras=cameras, images=images, points=points, colors=colors, meta=meta)


# ----------------------------------------------------------------------------------------------------
# Writing


@contextmanager
def atomic_folder(path: str | os.PathLike) -> Iterator[Path]:
    """Yield an empty temporary folder beside ``path``; on success it replaces ``path``.

    ``path`` may be absent, empty, or hold only COLMAP model files (a previous model); anything else
    raises :class:`InputError` before writing, so no user file is deleted. The old folder is renamed
    aside, the new one renamed in, then the old one removed: a reader sees the old or the new model,
    never a mixture. A write that raises leaves ``path`` untouched.
    """
    path = Path(path)
    if path.exists():
        if not path.is_dir():
            raise InputError("exists and is not a folder", path)
        others = sorted(p.name for p in path.iterdir() if p.name not in MODEL_FILES)
        if others:
            raise InputError(f"folder holds other files ({', '.join(others[:3])}); choose a new or "
                             "empty output folder", path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.", suffix=".part", dir=path.parent))
    except OSError as exc:
        raise cannot_write(exc, path) from None
    try:
        yield tmp
        old = None
        if path.exists():
            old = Path(tempfile.mkdtemp(prefix=f".{path.name}.", suffix=".old", dir=path.parent))
            os.replace(path, old / "model")
        os.replace(tmp, path)
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def scene_to_reconstruction(scene: Scene, points3d=None):
    """A pycolmap.Reconstruction of a Scene (trivial rigs and frames; points with empty tracks).

    ``points3d``: None (use ``scene.points``/``scene.colors``), an (n, 3) array, or a tuple
    ``(xyz (n, 3), rgb (n, 3) uint8 or None)``.
    """
    pycolmap = _pycolmap()
    rec = pycolmap.Reconstruction()
    for cam_id, cam in scene.cameras.items():
        model, params = camera_to_colmap(cam)
        c = pycolmap.Camera(model=model, width=int(cam.width), height=int(cam.height),
                            params=params, camera_id=int(cam_id))
        rec.add_camera_with_trivial_rig(c)
    wanted = dict(scene.meta.get("colmap_image_ids") or {})
    used = {v for k, v in wanted.items() if k in scene.images}
    if len(used) != len([k for k in wanted if k in scene.images]):
        wanted, used = {}, set()
    next_id = 1
    for name, rec_img in scene.images.items():
        if rec_img.camera_id not in scene.cameras:
            raise ValueError(f"image {name!r} uses camera {rec_img.camera_id}, which the scene lacks")
        img_id = wanted.get(name)
        if img_id is None:
            while next_id in used:
                next_id += 1
            img_id = next_id
            used.add(img_id)
        img = pycolmap.Image(name=name, camera_id=int(rec_img.camera_id), image_id=int(img_id))
        pose = pycolmap.Rigid3d(pycolmap.Rotation3d(rec_img.cam_from_world.R), rec_img.cam_from_world.t)
        rec.add_image_with_trivial_frame(img, pose)
    xyz, rgb = _points_arg(scene, points3d)
    if xyz is not None:
        track = pycolmap.Track()
        for i in range(len(xyz)):
            rec.add_point3D(xyz[i], track, rgb[i])
    return rec


def _points_arg(scene: Scene, points3d):
    if points3d is None:
        xyz, rgb = scene.points, scene.colors
    elif isinstance(points3d, tuple):
        xyz, rgb = points3d
    else:
        xyz, rgb = points3d, None
    if xyz is None:
        return None, None
    xyz = np.asarray(xyz, np.float64).reshape(-1, 3)
    if not np.all(np.isfinite(xyz)):
        raise ValueError("points3d has non-finite coordinates")
    if rgb is None:
        rgb = np.full((len(xyz), 3), 128, np.uint8)
    rgb = np.asarray(rgb)
    if rgb.shape != xyz.shape:
        raise ValueError(f"colors must have shape {xyz.shape}, got {rgb.shape}")
    return xyz, rgb.astype(np.uint8)


def write_colmap(scene: Scene, folder: str | os.PathLike, binary: bool = False, points3d=None) -> Path:
    """Write ``scene`` as a COLMAP model (``binary``: .bin files, else .txt) into ``folder``, atomically.

    Cameras are written as PINHOLE / OPENCV / FULL_OPENCV (see :func:`camera_to_colmap`) with the
    principal point shifted to COLMAP's pixel convention (+0.5). Image ids come from
    ``scene.meta["colmap_image_ids"]`` when present, else 1, 2, ... in the scene's order.
    ``points3d``: see :func:`scene_to_reconstruction`; points get empty tracks. Returns ``folder``.
    """
    rec = scene_to_reconstruction(scene, points3d)
    return write_reconstruction(rec, folder, binary)


def write_reconstruction(rec, folder: str | os.PathLike, binary: bool = False) -> Path:
    """Write a pycolmap.Reconstruction into ``folder`` atomically (temporary folder + rename)."""
    folder = Path(folder)
    with atomic_folder(folder) as tmp:
        try:
            (rec.write_binary if binary else rec.write_text)(tmp)
        except (ValueError, RuntimeError, OSError) as exc:
            raise InputError(f"cannot write COLMAP model: {exc}", folder) from None
    return folder


def sim3_to_pycolmap(sim: Sim3):
    """pycolmap.Sim3d equal to our Sim3 (x_new = s R x_old + t)."""
    pycolmap = _pycolmap()
    return pycolmap.Sim3d(float(sim.scale), pycolmap.Rotation3d(np.asarray(sim.R, float)),
                          np.asarray(sim.t, float))


def apply_sim3_to_colmap(folder_in: str | os.PathLike, sim: Sim3, folder_out: str | os.PathLike,
                         binary: Optional[bool] = None) -> Path:
    """Write the COLMAP model of ``folder_in`` transformed by ``sim`` (new_from_old, e.g.
    ``world_from_model``) into ``folder_out``: points x' = s R x + t, camera centres likewise, camera
    orientations rotated by R; intrinsics, tracks and keypoints are unchanged.

    ``binary``: output format; None keeps the input's. Written atomically. Returns ``folder_out``.
    """
    model = find_colmap_model(folder_in)
    if Path(folder_out).resolve() == model.resolve():
        raise InputError("output folder is the input model; choose another folder", folder_out)
    rec, was_binary = _load_reconstruction(model)
    rec.transform(sim3_to_pycolmap(sim))
    return write_reconstruction(rec, folder_out, was_binary if binary is None else binary)
