"""One entry point for reconstructions: ``read_reconstruction(path) -> Scene`` whatever the format.

Detection (first match wins):

1. a folder holding a COLMAP model directly, in ``sparse/`` or in ``sparse/0`` -> COLMAP (text or binary);
2. a folder holding ``opensfm/reconstruction.json`` (an ODM project) or ``reconstruction.json``
   -> OpenSfM;
3. a COLMAP model file (``cameras.bin``, ``images.txt`` ...) -> its folder as COLMAP;
4. a ``.xml`` file -> Metashape camera export; a ``.json`` file -> OpenSfM reconstruction.

Anything else raises :class:`InputError` naming the path and the accepted layouts.
"""
from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import Optional

from geometry.scene import Scene

from ..errors import InputError, UsageError
from .colmap import MODEL_PARTS, find_colmap_model, is_colmap_model, read_colmap
from .metashape import read_metashape_cameras
from .opensfm import read_opensfm
from .ply import read_ply_points

log = logging.getLogger(__name__)

#: Reconstruction readers by format name: each takes the path :func:`detect_reconstruction_format`
#: returns and gives a Scene.
READERS = {"colmap": read_colmap, "metashape": read_metashape_cameras, "opensfm": read_opensfm}

ACCEPTED = ("a COLMAP model folder (or a folder with sparse/ or sparse/0), an ODM project folder, "
            "an OpenSfM reconstruction.json, or a Metashape camera .xml")


def detect_reconstruction_format(path: str | os.PathLike) -> tuple[str, Path]:
    """(format name in {"colmap", "opensfm", "metashape"}, the path to hand its reader)."""
    path = Path(path)
    if not path.exists():
        raise InputError("reconstruction not found", path)
    if path.is_dir():
        if is_colmap_model(path):
            return "colmap", path
        for cand in (path / "opensfm" / "reconstruction.json", path / "reconstruction.json"):
            if cand.is_file():
                return "opensfm", cand
        raise InputError(f"no reconstruction found in this folder; expected {ACCEPTED}", path)
    if path.stem in MODEL_PARTS and path.suffix in (".txt", ".bin"):
        return "colmap", path.parent
    suffix = path.suffix.lower()
    if suffix == ".xml":
        return "metashape", path
    if suffix == ".json":
        return "opensfm", path
    raise InputError(f"unknown reconstruction format {suffix or '(no extension)'}; expected {ACCEPTED}",
                     path)


def read_reconstruction(path: str | os.PathLike, cloud: Optional[str | os.PathLike] = None,
                        mesh: Optional[str | os.PathLike] = None, fmt: Optional[str] = None) -> Scene:
    """Read any supported reconstruction into a Scene (model frame, OpenCV pixel convention).

    ``fmt``: force a format (a key of :data:`READERS`) instead of detecting it. ``cloud``: an optional
    PLY whose vertices replace ``scene.points`` (and colors/normals when the file has them), e.g. a
    dense cloud in the same model frame. ``mesh``: an optional mesh file path stored as
    ``scene.mesh_path`` (checked to exist). ``scene.meta["format"]`` names the format read.
    """
    if fmt is None:
        fmt, target = detect_reconstruction_format(path)
    elif fmt not in READERS:
        raise UsageError(f"unknown reconstruction format {fmt!r}; valid: {', '.join(sorted(READERS))}")
    else:
        target = Path(path)
        if fmt == "colmap" and target.is_file():
            target = target.parent
        if fmt == "colmap":
            find_colmap_model(target)  # one-line error for a missing folder or file
        elif not target.is_file():
            raise InputError(f"{fmt} reconstruction file not found", target)
    log.info("reading %s as %s", target, fmt)
    scene = READERS[fmt](target)
    if not scene.images:
        raise InputError("the reconstruction has no registered (posed) images", target)
    if cloud is not None:
        pts = read_ply_points(cloud)
        scene.points, scene.colors, scene.normals = pts.xyz, pts.rgb, pts.normals
        scene.meta["cloud_path"] = str(cloud)
    if mesh is not None:
        if not Path(mesh).is_file():
            raise InputError("mesh file not found", mesh)
        scene.mesh_path = str(mesh)
    return scene
