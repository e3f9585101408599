"""``cpdetect georef``: from photographs and a reconstruction to surveyed, georeferenced markers.

Stages (each writes ``OUTDIR/stages/<name>.json`` with a format version and a key, the hash of its
inputs, settings and the key of the stage before it; a rerun skips every stage whose file has the
same key, so an interrupted run resumes and a changed setting recomputes only from where it matters):

1. ``detect``     run the detector on every registered image (one cached file per image in
                  ``stages/detect/``; probability maps, reduced, in ``stages/prob/``).
2. ``localize``   first 3D estimates of the markers, model frame, by one of three modes:
                  ``cloud``: colorize the dense cloud with the probability maps (depth-tested against
                  the mesh or a point z-buffer, :mod:`geometry.fusion`) and DBSCAN the marker points;
                  ``ray``: cast every detection onto the mesh and cluster the hits;
                  ``triangulate``: intersect detection rays of image pairs and cluster the midpoints
                  (no mesh or cloud needed). ``auto``: cloud and ray candidates pooled when the
                  inputs allow them, else triangulate.
3. ``refine``     project every candidate into every image that sees it (depth test), drop views
                  where the marker is too small or too oblique, and refine the centre there
                  (:func:`cpdetect.refine.refine_center_painted`: on the gray image, and where that
                  fit is uncertain also on the max of the colour channels, for markers painted red
                  on black), seeded by a detection near the projection.
4. ``triangulate`` robust multi-view triangulation of each candidate (Huber/Cauchy), merge of
                  candidates on the same X-corner, a second refinement in every view from the
                  triangulated point and a final triangulation; markers the detector found in too few
                  of their views are dropped; optionally a pose + marker bundle adjustment;
                  per-marker reprojection RMS, covariance and a quality score for ranking.
5. ``register``   correspondence-free registration of the markers to the surveyed points
                  (:func:`geometry.registration.register_points`) in a local metric frame; when it
                  fails with every marker, retried with the best-ranked ones.
6. export         ``report.json``, ``gcp_list.txt`` (ODM), ``markers.xml`` (Metashape) and
                  ``detections.json`` (format ``cpdetect.detections/1``), written together at the end:
                  a run that fails leaves no output of its own (only stage files, for the rerun).

Frames: the reconstruction's frame is the *model* frame; surveyed points are converted to a local
Cartesian frame (metres) for registration; ``world_from_model`` in the report maps model points into
that local frame, and the report also gives each marker in the surveyed CRS.
"""
from __future__ import annotations

import hashlib
import json
import functools
import logging
import math
import re
import threading
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Callable, Optional

import numpy as np

from .errors import InputError, UsageError
from .fileio import atomic_path, read_json, staged_outputs, write_json_atomic

log = logging.getLogger(__name__)

STAGE_FORMAT = "cpdetect.georef-stage/1"
# bumped whenever what a stage computes changes, so that stale stage files are recomputed
ALGORITHM_VERSION = 11
REPORT_FORMAT = "cpdetect.georef-report/1"
DETECTIONS_FORMAT = "cpdetect.detections/1"
MODES = ("auto", "cloud", "ray", "triangulate")


@dataclass(frozen=True)
class GeorefSettings:
    """Settings of a georef run (each stage's key holds the fields it uses, see ``_STAGE_FIELDS``).

    detector / detector_settings: the detector and its settings (see :mod:`cpdetect.detector`).
    mode: "auto", "cloud", "ray" or "triangulate" (see the module docstring).
    min_score: detections below this score are ignored (ray and triangulate modes, refinement seeds).
    cloud_threshold: fused score above which a cloud point is a marker point.
    prob_max_side: longest side (pixels) at which probability maps are kept for the cloud mode.
    depth_max_side: longest side of the per-image depth maps used for the visibility tests.
    min_radius_px: views where the marker's apparent radius is smaller are not used.
    max_obliquity_deg: views seeing the marker plane more obliquely than this are not used.
    refine_method: method of :func:`cpdetect.refine.refine_center`.
    sigma_floor_px: smallest pixel sigma used as a weight (refinement sigmas can be optimistic, and
        pose errors of the reconstruction add to them).
    loss / f_scale / outlier_sigma: robust triangulation (see :func:`geometry.triangulate.triangulate`).
    outlier_radius_fraction: an observation is an outlier only when it is also off by more than this
        fraction of the marker's apparent radius (tolerates pose errors of the reconstruction: closer
        than that, the refinement still sat on the marker's own X-corner).
    min_views: markers with fewer inlier views are dropped.
    min_detected_fraction: markers the detector found in fewer of their usable views are dropped.
    adjust: run the pose + marker bundle adjustment after triangulation; pose priors
        ``prior_rot_deg`` (degrees) and ``prior_pos`` (model units; None: 0.4 marker radii).
    registration_noise_m: per-axis noise assumed by the registration (surveyed + detection), metres.
    seed: seed of every random choice (registration probes).
    """

    detector: str = "classical"
    detector_settings: dict = field(default_factory=dict)
    mode: str = "auto"
    min_score: float = 0.3
    cloud_threshold: float = 0.3
    prob_max_side: int = 384
    depth_max_side: int = 480
    min_radius_px: float = 5.0
    max_obliquity_deg: float = 75.0
    refine_method: str = "auto"
    sigma_floor_px: float = 0.3
    loss: str = "huber"
    f_scale: float = 2.0
    outlier_sigma: float = 6.0
    outlier_radius_fraction: float = 0.25
    min_views: int = 3
    min_detected_fraction: float = 0.3
    adjust: bool = False
    prior_rot_deg: float = 0.05
    prior_pos: Optional[float] = None
    registration_noise_m: float = 0.02
    seed: int = 0

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise UsageError(f"unknown mode {self.mode!r}; valid: {', '.join(MODES)}")
        if self.loss not in ("huber", "cauchy", "soft_l1", "linear"):
            raise UsageError(f"unknown loss {self.loss!r}; valid: huber, cauchy, soft_l1, linear")
        if self.min_views < 2:
            raise UsageError("min_views must be at least 2")
        from .refine import METHODS

        if self.refine_method not in METHODS:
            raise UsageError(f"unknown refine_method {self.refine_method!r}; valid: {', '.join(METHODS)}")


@dataclass(frozen=True)
class GeorefInputs:
    """Paths of a georef run. crs: the surveyed points' CRS when gcps.csv does not say it. rejects: the
    detections a reviewer marked wrong in the comparison report's gallery (``rejects.json``)."""

    reconstruction: Path
    images: Path
    gcps: Path
    out: Path
    crs: Optional[str] = None
    cloud: Optional[Path] = None
    mesh: Optional[Path] = None
    detections: Optional[Path] = None  # a cpdetect.detections/1 file to use instead of running the detector
    rejects: Optional[Path] = None  # a cpdetect.rejects/1 file from the review gallery (see run_georef)


# ----------------------------------------------------------------------------------------------------
# Stage bookkeeping

# the settings each stage depends on (a stage's key holds these and the key of the stage before it)
_STAGE_FIELDS = {
    "localize": ("mode", "min_score", "cloud_threshold", "prob_max_side", "depth_max_side", "seed"),
    "refine": ("min_score", "depth_max_side", "min_radius_px", "max_obliquity_deg", "refine_method"),
    "triangulate": ("min_score", "depth_max_side", "min_radius_px", "max_obliquity_deg", "refine_method",
                    "sigma_floor_px", "loss", "f_scale", "outlier_sigma", "outlier_radius_fraction", "min_views", "min_detected_fraction",
                    "adjust", "prior_rot_deg", "prior_pos", "seed"),
    "register": ("registration_noise_m", "seed"),
}


def _stage_settings(settings: "GeorefSettings", stage: str) -> dict:
    return {k: getattr(settings, k) for k in _STAGE_FIELDS[stage]}



def _hash(obj: Any) -> str:
    return hashlib.sha256(json.dumps(obj, sort_keys=True, default=str).encode()).hexdigest()[:24]


def _file_key(path: Optional[Path]) -> Any:
    """Cheap identity of a file or folder: (relative name, size, mtime) of each file."""
    if path is None:
        return None
    p = Path(path)
    if p.is_dir():
        return [(str(f.relative_to(p)), f.stat().st_size, f.stat().st_mtime_ns)
                for f in sorted(p.rglob("*")) if f.is_file()]
    if not p.exists():
        return None
    st = p.stat()
    return (p.name, st.st_size, st.st_mtime_ns)


class StageStore:
    """Stage files under ``OUTDIR/stages``: reuse a stage whose key matches, else compute it."""

    def __init__(self, out: Path):
        self.dir = Path(out) / "stages"
        self.ran: list[str] = []
        self.skipped: list[str] = []

    def run(self, name: str, key_parts: Any, compute: Callable[[], Any]) -> tuple[Any, str]:
        key = _hash([STAGE_FORMAT, ALGORITHM_VERSION, name, key_parts])
        path = self.dir / f"{name}.json"
        if path.exists():
            try:
                doc = read_json(path, "stage file")
            except InputError:
                doc = None
            if isinstance(doc, dict) and doc.get("format") == STAGE_FORMAT and doc.get("key") == key:
                log.info("stage %s: up to date (%s), skipped", name, path)
                self.skipped.append(name)
                return doc["data"], key
        t0 = time.perf_counter()
        data = _finite(compute())
        write_json_atomic(path, {"format": STAGE_FORMAT, "stage": name, "key": key,
                                 "seconds": round(time.perf_counter() - t0, 3), "data": data})
        log.info("stage %s: done in %.1f s", name, time.perf_counter() - t0)
        self.ran.append(name)
        return data, key


def _safe_name(image_name: str) -> str:
    return re.sub(r"[^A-Za-z0-9._-]", "_", image_name) + "-" + hashlib.sha1(image_name.encode()).hexdigest()[:8]


# ----------------------------------------------------------------------------------------------------
# Inputs


def load_scene(path: Path):
    """The reconstruction as a :class:`geometry.scene.Scene` (any format cpdetect reads)."""
    try:
        from .formats.reconstruction import read_reconstruction
    except ModuleNotFoundError as exc:
        if exc.name != "cpdetect.formats.reconstruction":
            raise
        from .formats.colmap import read_colmap as read_reconstruction
    scene = read_reconstruction(path)
    if not scene.images:
        raise InputError("the reconstruction has no registered images", path)
    return scene


def _image_paths(scene, images_dir: Path) -> dict[str, Path]:
    if not Path(images_dir).is_dir():
        raise InputError("image folder not found", images_dir)
    found = {}
    for name in sorted(scene.images):
        p = Path(images_dir) / name
        if p.is_file():
            found[name] = p
    if not found:
        raise InputError(f"none of the {len(scene.images)} images of the reconstruction is in this folder "
                         f"(e.g. {sorted(scene.images)[0]!r})", images_dir)
    missing = len(scene.images) - len(found)
    if missing:
        log.warning("%d registered images are not in %s; they are ignored", missing, images_dir)
    return found


def _load_cloud(path: Path) -> tuple[np.ndarray, Optional[np.ndarray]]:
    import open3d as o3d

    if not Path(path).is_file():
        raise InputError("point cloud not found", path)
    pc = o3d.io.read_point_cloud(str(path))
    pts = np.asarray(pc.points, dtype=np.float64)
    if len(pts) == 0:
        raise InputError("no points in the cloud (unreadable or empty)", path)
    if not np.all(np.isfinite(pts)):
        raise InputError("the cloud has non-finite coordinates", path)
    normals = np.asarray(pc.normals, dtype=np.float64) if pc.has_normals() else None
    return pts, normals


def _load_mesh_scene(path: Optional[Path]):
    if path is None:
        return None
    from geometry.raycast import load_mesh, make_raycasting_scene

    if not Path(path).is_file():
        raise InputError("mesh not found", path)
    try:
        return make_raycasting_scene(load_mesh(path))
    except ValueError as exc:
        raise InputError(str(exc).split(": ", 1)[-1], path) from None


def _estimate_normals(points: np.ndarray, radius: float) -> np.ndarray:
    import open3d as o3d

    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    pc.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=radius, max_nn=30))
    return np.asarray(pc.normals)


# ----------------------------------------------------------------------------------------------------
# Stage 1: detect


class _DetectImage:
    """The per-image task of the detect stage: ``task((name, path)) -> {"data": record, "probability":
    float16 array or None}`` (the map already reduced to ``prob_max_side``), or ``{"fatal": message}``
    for a :class:`~cpdetect.errors.CpdetectError` (so that every executor stops with the one-line message).

    The same task runs in this process (serial) and in worker processes or on Dask workers, so the results
    are identical whatever the executor (but for the ``seconds`` timings). It carries the detector's
    factory (pickled by reference: a module-level class or function) and settings, not a built
    detector: in this process the detector is built once per run, in a worker once per process and
    thread (:func:`_worker_detector`).
    """

    def __init__(self, name: str, factory: Callable, settings: dict, prob_max_side: int):
        self.name, self.factory, self.settings = name, factory, dict(settings)
        self.prob_max_side = int(prob_max_side)
        self._detector = None

    def __getstate__(self) -> dict:
        return dict(self.__dict__, _detector=None, _remote=True)

    def detector(self):
        if self._detector is None:
            if getattr(self, "_remote", False):
                self._detector = _worker_detector(self.name, self.factory, self.settings)
            else:
                self._detector = _build_detector(self.name, self.factory, self.settings)
        return self._detector

    def __call__(self, item: tuple[str, str]) -> dict:
        from .errors import CpdetectError
        from .imageio import read_image

        name, path = item
        try:
            img = read_image(path)
            t0 = time.perf_counter()
            res = self.detector().detect(img)
            seconds = time.perf_counter() - t0
        except CpdetectError as exc:
            return {"fatal": str(exc), "usage": isinstance(exc, UsageError)}
        h, w = img.shape[:2]
        prob = None
        if res.probability is not None:
            import cv2

            prob = np.asarray(res.probability, np.float32)
            s = min(1.0, self.prob_max_side / max(prob.shape))
            if s < 1.0:
                prob = cv2.resize(prob, (max(1, round(prob.shape[1] * s)), max(1, round(prob.shape[0] * s))),
                                  interpolation=cv2.INTER_AREA)
            prob = prob.astype(np.float16)
        data = {"width": int(w), "height": int(h), "seconds": round(seconds, 3),
                "detections": [d.to_dict() for d in res.detections]}
        return {"name": name, "data": data, "probability": prob}


# detectors built in a worker process or thread, by (factory, settings): built once per worker, not once
# per image; thread-local because a Dask worker may run tasks in several threads
_WORKER = threading.local()


def _worker_detector(name: str, factory: Callable, settings: dict):
    cache = getattr(_WORKER, "detectors", None)
    if cache is None:
        cache = _WORKER.detectors = {}
    key = (getattr(factory, "__module__", ""), getattr(factory, "__qualname__", repr(factory)),
           json.dumps(settings, sort_keys=True, default=str))
    if key not in cache:
        cache[key] = _build_detector(name, factory, settings)
    return cache[key]


def _build_detector(name: str, factory: Callable, settings: dict):
    """``factory(**settings)`` with :func:`cpdetect.detector.get_detector`'s one-line errors."""
    try:
        return factory(**settings)
    except (TypeError, ValueError) as exc:
        raise UsageError(f"detector {name!r}: {exc}") from None


def stage_detect(store: StageStore, scene, image_paths: dict[str, Path], settings: GeorefSettings,
                 progress: Callable = lambda it, **kw: it, workers: int = 1, scheduler: Any = None
                 ) -> tuple[dict, str]:
    """Detections per image: {name: {"width", "height", "detections": [...], "probability": file|None}}.

    Images whose cached record (``stages/detect/``) matches are not detected again; the others run on
    ``workers`` local processes, or a Dask cluster when ``scheduler`` (an address or a
    ``distributed.Client``; every worker must see the images at the same path) is given, else in this
    process; the records are identical whichever runs them (but for the timings).
    """
    from .detector import check_settings, resolve_factory
    from .executors import SerialExecutor, make_executor

    det_key = [settings.detector, settings.detector_settings, settings.prob_max_side, _detector_code_key(settings.detector)]
    per_image: dict[str, dict] = {}
    keys, todo = {}, []
    for name, path in image_paths.items():
        key = keys[name] = _hash([STAGE_FORMAT, "detect-image", det_key, name, _file_key(path)])
        cache = store.dir / "detect" / f"{_safe_name(name)}.json"
        if cache.exists():
            try:
                doc = read_json(cache)
                if doc.get("key") == key:
                    per_image[name] = doc["data"]
                    continue
            except (InputError, AttributeError, KeyError):
                pass
        todo.append((name, str(Path(path).resolve())))
    if todo:
        check_settings(settings.detector, settings.detector_settings)
        task = _DetectImage(settings.detector, resolve_factory(settings.detector), settings.detector_settings,
                            settings.prob_max_side)
        ex = make_executor(workers if len(todo) > 1 else 1, scheduler)
        try:
            if not isinstance(ex, SerialExecutor):
                _check_picklable(task, settings.detector)
            for rec in progress(ex.imap(task, todo), desc="detect", unit="image", total=len(todo)):
                if "fatal" in rec:  # the message names the image file
                    raise (UsageError if rec["usage"] else InputError)(rec["fatal"])
                name, data = rec["name"], rec["data"]
                data["probability"] = None
                if rec["probability"] is not None:
                    data["probability"] = f"prob/{_safe_name(name)}.npy"
                    with atomic_path(store.dir / data["probability"]) as tmp:
                        with open(tmp, "wb") as fh:
                            np.save(fh, rec["probability"])
                write_json_atomic(store.dir / "detect" / f"{_safe_name(name)}.json",
                                  {"format": STAGE_FORMAT, "key": keys[name], "data": data})
                per_image[name] = data
        finally:
            ex.close()
    per_image = {name: per_image[name] for name in image_paths}  # the images' order, however they ran
    return store.run("detect", [keys[n] for n in image_paths], lambda: per_image)


def _check_picklable(task: _DetectImage, name: str) -> None:
    """Worker processes get the detector's factory by reference: a lambda or a local class cannot go."""
    import pickle

    try:
        pickle.dumps(task)
    except Exception as exc:  # pickle raises several types (PicklingError, AttributeError, TypeError)
        raise UsageError(f"detector {name!r} cannot run in worker processes (its factory cannot be "
                         f"pickled: {type(exc).__name__}); run with --workers 1") from None


def load_detections_json(path: Path, image_paths: dict[str, Path]) -> dict:
    """Per-image detections from a ``cpdetect.detections/1`` file (e.g. written by ``cpdetect detect``).

    Entries are matched to the reconstruction's image names exactly, or else by path suffix (the file
    may name ``photos/IMG_1.jpg`` for the image ``IMG_1.jpg``); entries with an ``error`` (images the
    detector could not read) count as images without detections; images it lacks have none.
    """
    from .types import MarkerDetection

    doc = read_json(path, "detections file")
    if not isinstance(doc, dict) or doc.get("format") != DETECTIONS_FORMAT:
        raise InputError(f"not a {DETECTIONS_FORMAT} file (format {doc.get('format') if isinstance(doc, dict) else None!r})",
                         path)
    names = set(image_paths)
    per_image = {}
    for k, im in enumerate(doc.get("images", [])):
        try:
            name = str(im["file"]).replace("\\", "/")
            if name not in names:
                match = [n for n in names if name.endswith("/" + n)]
                name = match[0] if len(match) == 1 else name
            if "error" in im or "fatal" in im:
                log.warning("%s: no detections for %s (%s)", path, name, im.get("error") or im.get("fatal"))
                continue
            dets = [MarkerDetection.from_dict(d).to_dict() for d in im["detections"]]
            per_image[name] = {"width": int(im["width"]), "height": int(im["height"]), "detections": dets,
                               "probability": None, "seconds": float(im.get("seconds", 0.0))}
        except (KeyError, TypeError, ValueError) as exc:
            raise InputError(f"image entry {k}: {type(exc).__name__}: {exc}", path) from None
    if per_image and not set(per_image) & names:
        raise InputError(f"no image of the reconstruction is named in it (e.g. {sorted(per_image)[0]!r})", path)
    return {n: per_image.get(n, {"width": 0, "height": 0, "detections": [], "probability": None, "seconds": 0.0})
            for n in image_paths}


def _detector_code_key(name: str) -> Any:
    """Identity of the detector's code (its module file's size and time), so that cached detections
    are recomputed when the detector changes."""
    import inspect

    from .detector import resolve_factory

    try:
        return _file_key(Path(inspect.getfile(resolve_factory(name))))
    except Exception:  # unknown name (get_detector reports it) or a built-in without a file
        return None


def write_detections_json(path: Path, detector: str, per_image: dict) -> None:
    """OUTDIR/detections.json in the ``cpdetect.detections/1`` format."""
    images = [{"file": name, "width": d["width"], "height": d["height"], "detections": d["detections"]}
              for name, d in sorted(per_image.items())]
    write_json_atomic(path, {"format": DETECTIONS_FORMAT, "detector": detector, "images": images})


# ----------------------------------------------------------------------------------------------------
# Stage 2: localize


def _pose_cam(scene, name):
    rec = scene.images[name]
    return scene.cameras[rec.camera_id], rec.cam_from_world


class _NothingFound(Exception):
    """A localization mode found no candidate; the run goes on and reports ``failed`` with the reason."""


def _marker_radius_from_depths(scene, per_image, depth_of: Callable) -> float:
    """Median equal-area marker radius (model units) from detections' radius_px and depth."""
    radii = []
    for name, d in per_image.items():
        dets = d["detections"]
        if not dets:
            continue
        cam, pose = _pose_cam(scene, name)
        uv = np.array([[x["x"], x["y"]] for x in dets])
        z = depth_of(name, uv)
        r = np.array([x["radius_px"] for x in dets]) * z / cam.fx
        radii.extend(r[np.isfinite(r) & (r > 0)].tolist())
    if not radii:
        raise _NothingFound("no detection could be placed in 3D (no detections, or none on the model)")
    return float(np.median(radii))


def _localize_cloud(scene, per_image, settings, cloud, normals, mesh_rc, prob_dir: Path, progress) -> dict:
    from geometry.clustering import cluster_points, dbscan_params, point_spacing
    from geometry.fusion import FusionView, fuse_scores_sparse
    from geometry.visibility import mesh_depth_map, zbuffer_depth_map

    rng = np.random.default_rng(settings.seed)
    spacing = point_spacing(cloud, rng=rng)
    depth_maps = {}

    def depth_map(name):
        if name not in depth_maps:
            cam, pose = _pose_cam(scene, name)
            if mesh_rc is not None:
                depth_maps[name] = mesh_depth_map(mesh_rc, cam, pose, settings.depth_max_side)
            else:
                # cells about 1.5 point spacings wide at the median depth of the cloud
                z = np.median(pose(cloud[:: max(1, len(cloud) // 20000)])[:, 2])
                side = int(np.clip(max(cam.width, cam.height) * 1.0 / (1.5 * spacing * cam.fx / z), 64,
                                   settings.depth_max_side))
                depth_maps[name] = zbuffer_depth_map(cloud, cam, pose, side, fill_px=1)
        return depth_maps[name]

    names = [n for n in per_image if per_image[n]["probability"]]
    radius = _marker_radius_from_depths(scene, {n: per_image[n] for n in names},
                                        lambda n, uv: depth_map(n).lookup(uv))
    marker_size = 2.0 * radius
    if normals is None:
        normals = _estimate_normals(cloud, max(3 * spacing, 0.3 * radius))

    views = []
    for n in progress(names, desc="colorize", unit="image"):
        cam, pose = _pose_cam(scene, n)
        prob = np.load(prob_dir / per_image[n]["probability"]).astype(np.float32)
        views.append(FusionView(cam, pose, prob, depth_map(n)))
    # only the points near marked pixels can score above zero: fuse those (same scores, far less work)
    fused = fuse_scores_sparse(cloud, views, normals, rel_tol=0.02, abs_tol=0.25 * radius)
    params = dbscan_params(spacing, marker_size)
    clusters = cluster_points(cloud, fused.score, params, threshold=settings.cloud_threshold)
    cands = []
    for c in clusters:
        nrm = _pca_normal(cloud[c.members])
        # a square of side s has extent s / sqrt(2) and equal-area radius s / sqrt(pi)
        r = float(np.clip(0.8 * c.extent, 0.5 * radius, 3.0 * radius))
        cands.append({"center_model": c.centroid.tolist(), "support": c.n_points, "score": c.mean_score,
                      "radius_model": r, "normal_model": nrm.tolist() if nrm is not None else None})
    return {"mode": "cloud", "radius_model": radius, "spacing_model": spacing,
            "dbscan": asdict(params), "n_marker_points": int((fused.score >= settings.cloud_threshold).sum()),
            "candidates": cands}


def _pca_normal(P: np.ndarray) -> Optional[np.ndarray]:
    if len(P) < 5:
        return None
    w, v = np.linalg.eigh(np.cov((P - P.mean(0)).T))
    return v[:, 0] if w[0] < 0.2 * w[1] else None


def _localize_ray(scene, per_image, settings, mesh_rc) -> dict:
    from geometry.clustering import cluster_centres
    from geometry.raycast import cast, detection_rays

    hits, weights, radii, normals = [], [], [], []
    for name, d in per_image.items():
        dets = [x for x in d["detections"] if x["score"] >= settings.min_score]
        if not dets:
            continue
        cam, pose = _pose_cam(scene, name)
        o, v = detection_rays(cam, pose, np.array([[x["x"], x["y"]] for x in dets]))
        h = cast(mesh_rc, o, v)
        for k in np.flatnonzero(h.hit):
            z = h.t[k] * (pose.R @ v[k])[2]
            hits.append(h.points[k])
            weights.append(dets[k]["score"])
            radii.append(dets[k]["radius_px"] * z / cam.fx)
            normals.append(h.normals[k])
    if not hits:
        raise _NothingFound("no detection ray hit the mesh (no detections, or the mesh is not in the "
                         "reconstruction's frame)")
    hits, weights, normals, radii = np.array(hits), np.array(weights), np.array(normals), np.array(radii)
    radius = float(np.median(radii))
    centres, labels = cluster_centres(hits, eps=0.5 * radius, min_samples=2, weights=weights)
    cands = []
    for k, c in enumerate(centres):
        m = labels == k
        nrm = normals[m].mean(0)
        cands.append({"center_model": np.median(hits[m], axis=0).tolist(), "support": int(m.sum()),
                      "score": float(weights[m].mean()), "radius_model": float(np.median(radii[m])),
                      "normal_model": (nrm / max(np.linalg.norm(nrm), 1e-12)).tolist()})
    return {"mode": "ray", "radius_model": radius, "n_hits": int(len(hits)), "candidates": cands}


def _localize_triangulate(scene, per_image, settings) -> dict:
    """Intersect detection rays of image pairs with nearby centres (each image with its 12 nearest);
    cluster the midpoints of pairs that nearly meet, at a depth consistent with both apparent sizes."""
    from geometry.clustering import cluster_centres
    from geometry.raycast import detection_rays

    rays = []  # (image index, origin, dir, radius_px, fx)
    names = [n for n in per_image if per_image[n]["detections"]]
    centers = np.array([scene.images[n].center for n in names]).reshape(-1, 3)
    for i, name in enumerate(names):
        dets = [x for x in per_image[name]["detections"] if x["score"] >= settings.min_score]
        if not dets:
            continue
        cam, pose = _pose_cam(scene, name)
        o, v = detection_rays(cam, pose, np.array([[x["x"], x["y"]] for x in dets]))
        for k, x in enumerate(dets):
            rays.append((i, o[k], v[k], x["radius_px"], cam.fx))
    if len(rays) < 2:
        raise _NothingFound("too few detections to triangulate markers")
    img = np.array([r[0] for r in rays])
    O = np.array([r[1] for r in rays])
    V = np.array([r[2] for r in rays])
    rpx = np.array([r[3] for r in rays])
    fx = np.array([r[4] for r in rays])
    # pairs of rays from different images among each image's nearest neighbours (camera centres)
    from scipy.spatial import cKDTree

    k_nn = min(len(names), 13)
    _, nn = cKDTree(centers).query(centers, k=k_nn)
    near = np.zeros((len(names), len(names)), bool)
    near[np.repeat(np.arange(len(names)), k_nn), np.asarray(nn).reshape(-1)] = True
    near |= near.T
    a_idx, b_idx = np.triu_indices(len(rays), 1)
    keep = (img[a_idx] != img[b_idx]) & near[img[a_idx], img[b_idx]]
    a_idx, b_idx = a_idx[keep], b_idx[keep]
    # closest points of the two rays
    w0 = O[a_idx] - O[b_idx]
    a = np.einsum("ij,ij->i", V[a_idx], V[b_idx])
    d = np.einsum("ij,ij->i", V[a_idx], w0)
    e = np.einsum("ij,ij->i", V[b_idx], w0)
    den = 1 - a * a
    ok = den > np.sin(np.radians(2.0)) ** 2
    s = np.where(ok, (a * e - d) / np.where(ok, den, 1), 0)
    t = np.where(ok, (e - a * d) / np.where(ok, den, 1), 0)
    ok &= (s > 0) & (t > 0)
    pa = O[a_idx] + s[:, None] * V[a_idx]
    pb = O[b_idx] + t[:, None] * V[b_idx]
    gap = np.linalg.norm(pa - pb, axis=1)
    ra = rpx[a_idx] * s / fx[a_idx]
    rb = rpx[b_idx] * t / fx[b_idx]
    r_est = 0.5 * (ra + rb)
    # apparent sizes shrink with obliquity (equal-area radius ~ sqrt(cos)): allow a factor 2
    ok &= (gap < 0.5 * r_est) & (np.maximum(ra, rb) < 2.0 * np.minimum(ra, rb))
    if not ok.any():
        raise _NothingFound("no two detections in different images agree on a 3D position")
    mids = 0.5 * (pa[ok] + pb[ok])
    radius = float(np.median(r_est[ok]))
    # a marker detected in two images only gives one pair: every midpoint may found a candidate (false
    # ones are dropped after refinement by the views and detection-fraction tests)
    centres, labels = cluster_centres(mids, eps=0.5 * radius, min_samples=1)
    r_ok = r_est[ok]
    cands = [{"center_model": np.median(mids[labels == k], axis=0).tolist(), "support": int((labels == k).sum()),
              "score": 1.0, "radius_model": float(np.median(r_ok[labels == k])), "normal_model": None}
             for k in range(len(centres))]
    return {"mode": "triangulate", "radius_model": radius, "n_pairs": int(ok.sum()), "candidates": cands}


def stage_localize(store, scene, per_image, settings, inputs: GeorefInputs, prev_key: str, progress):
    """First 3D marker estimates. Mode ``auto``: the cloud colorization when a cloud and probability
    maps are available, *plus* the ray casting of detections when a mesh is (their candidates are
    pooled; duplicates merge after triangulation), else triangulation of detection pairs."""
    has_prob = any(d["probability"] for d in per_image.values())
    mode = settings.mode
    if mode == "auto":
        parts = (["cloud"] if (inputs.cloud and has_prob) else []) + (["ray"] if inputs.mesh else [])
        mode = "+".join(parts) or "triangulate"
    if "cloud" in mode.split("+") and not inputs.cloud:
        raise UsageError("mode 'cloud' needs --cloud")
    if "cloud" in mode.split("+") and not has_prob:
        raise UsageError(f"mode 'cloud' needs probability maps; detector {settings.detector!r} gives none")
    if "ray" in mode.split("+") and not inputs.mesh:
        raise UsageError("mode 'ray' needs --mesh")
    key = [prev_key, mode, _file_key(inputs.cloud) if "cloud" in mode else None, _file_key(inputs.mesh),
           _stage_settings(settings, "localize")]

    def compute():
        mesh_rc = _load_mesh_scene(inputs.mesh)
        results = []
        for part in mode.split("+"):
            try:
                if part == "cloud":
                    cloud, normals = _load_cloud(inputs.cloud)
                    res = _localize_cloud(scene, per_image, settings, cloud, normals, mesh_rc, store.dir, progress)
                elif part == "ray":
                    res = _localize_ray(scene, per_image, settings, mesh_rc)
                else:
                    res = _localize_triangulate(scene, per_image, settings)
            except _NothingFound as exc:
                log.warning("localize (%s): %s", part, exc)
                res = {"mode": part, "radius_model": None, "candidates": [], "reason": str(exc)}
            for c in res["candidates"]:
                c["source"] = part
            results.append(res)
        radii = [r["radius_model"] for r in results if r["radius_model"] is not None]
        out = {"mode": mode, "radius_model": radii[0] if radii else None,
               "candidates": [c for r in results for c in r["candidates"]],
               "details": {r["mode"]: {k: v for k, v in r.items() if k != "candidates"} for r in results}}
        return out

    return store.run("localize", key, compute)


# ----------------------------------------------------------------------------------------------------
# Stage 3: refine in every view


class _ViewContext:
    """Per-image depth maps (mesh, else cloud z-buffer, else none) and gray images, cached per pass."""

    def __init__(self, scene, image_paths, settings, inputs, rejects=()):
        self.scene, self.paths, self.settings = scene, image_paths, settings
        self.rejects = list(rejects)  # reviewer's rejects: observations there are not used
        self.mesh_rc = _load_mesh_scene(inputs.mesh)
        self.cloud = None
        if self.mesh_rc is None and inputs.cloud:
            self.cloud, _ = _load_cloud(inputs.cloud)
        self._depth = {}

    def depth_map(self, name):
        from geometry.visibility import mesh_depth_map, zbuffer_depth_map

        if name not in self._depth:
            cam, pose = _pose_cam(self.scene, name)
            if self.mesh_rc is not None:
                self._depth[name] = mesh_depth_map(self.mesh_rc, cam, pose, self.settings.depth_max_side)
            elif self.cloud is not None:
                self._depth[name] = zbuffer_depth_map(self.cloud, cam, pose, min(self.settings.depth_max_side, 320))
            else:
                self._depth[name] = None
        return self._depth[name]


def refine_views(ctx: _ViewContext, points: np.ndarray, normals: list, radii: np.ndarray, per_image: dict,
                 gate: float, progress: Callable) -> tuple[list[list[dict]], list[dict], dict]:
    """Project markers (k, 3, model frame) into every image that sees them and refine the centre there.

    A view is used when the marker is visible (depth test), its apparent radius is at least
    ``min_radius_px`` and it is seen at most ``max_obliquity_deg`` off its normal (when known). The
    refinement is seeded at the nearest detection within ``gate`` x the apparent radius of the
    projected point, else at the projected point. ``radii``: (k,) equal-area marker radii, model units.
    Returns per marker the observations, per marker counts {"usable", "detected", "refined",
    "radius_model" (median of the seeding detections' radii, model units, or None)}, and the
    rejection counts by reason. A refined centre within the tolerance of one of ``ctx.rejects`` (a
    reviewer's rejects) is dropped, so that a rejected measurement does not come back by projection.
    """
    from geometry.visibility import visible_points

    from .imageio import paint_image, read_image
    from .refine import refine_center_painted
    from .rejects import is_rejected

    settings = ctx.settings
    obs: list[list[dict]] = [[] for _ in points]
    counts = [{"usable": 0, "detected": 0, "refined": 0} for _ in points]
    det_radii: list[list[float]] = [[] for _ in points]
    radii = np.asarray(radii, float).reshape(len(points))
    rejected: dict[str, int] = {}
    if len(points) == 0:
        return obs, counts, rejected
    cos_max = math.cos(math.radians(settings.max_obliquity_deg))
    for name in progress(list(ctx.paths), desc="refine", unit="image"):
        cam, pose = _pose_cam(ctx.scene, name)
        vis = visible_points(points, cam, pose, ctx.depth_map(name), rel_tol=0.02, abs_tol=0.5 * radii,
                             border_px=2.0)
        dets = [d for d in per_image.get(name, {}).get("detections", []) if d["score"] >= settings.min_score]
        det_xy = np.array([[d["x"], d["y"]] for d in dets]).reshape(-1, 2)
        todo = []
        for j in np.flatnonzero(vis.visible):
            view = pose.center - points[j]
            cos = 1.0 if normals[j] is None else abs(float(normals[j] @ view)) / np.linalg.norm(view)
            r_px = cam.fx * radii[j] / vis.depth[j] * math.sqrt(max(cos, 1e-3))
            if cos < cos_max:
                rejected["oblique"] = rejected.get("oblique", 0) + 1
            elif r_px < settings.min_radius_px:
                rejected["small"] = rejected.get("small", 0) + 1
            else:
                todo.append((j, r_px, cos))
        if not todo:
            continue
        gray = read_image(ctx.paths[name], gray=True)
        # decoded in colour only if a gray fit is uncertain (markers painted red on black)
        paint = functools.cache(lambda path=ctx.paths[name]: paint_image(read_image(path)))
        for j, r_px, cos in todo:
            u, v = vis.uv[j]
            seed, seeded_by, det_radius = (float(u), float(v)), "projection", None
            if len(det_xy):
                dd = np.hypot(det_xy[:, 0] - u, det_xy[:, 1] - v)
                k = int(dd.argmin())
                if dd[k] <= gate * r_px:
                    seed, seeded_by = (float(det_xy[k, 0]), float(det_xy[k, 1])), "detection"
                    det_radius = dets[k]["radius_px"] * vis.depth[j] / cam.fx / math.sqrt(max(cos, 1e-3))
            res = refine_center_painted(gray, paint, seed[0], seed[1], float(r_px), method=settings.refine_method)
            if res.ok and ctx.rejects and is_rejected(name, res.x, res.y, ctx.rejects):
                # a reviewer rejected this measurement: the view is not used (nor counted usable, so
                # the marker's detected fraction is taken over the views that remain)
                rejected["reviewer"] = rejected.get("reviewer", 0) + 1
                continue
            counts[j]["usable"] += 1
            if det_radius is not None:
                counts[j]["detected"] += 1
                det_radii[j].append(det_radius)
            if not res.ok:
                rejected["refine failed"] = rejected.get("refine failed", 0) + 1
                continue
            counts[j]["refined"] += 1
            obs[j].append({"image": name, "x": float(res.x), "y": float(res.y), "sigma_px": float(res.sigma_px),
                           "method": res.method, "seed": seeded_by, "radius_px": float(r_px),
                           "cos_incidence": float(cos), "predicted": [float(u), float(v)]})
    for j in range(len(points)):
        counts[j]["radius_model"] = float(np.median(det_radii[j])) if det_radii[j] else None
    return obs, counts, rejected


def stage_refine(store, ctx_factory, localized, per_image, settings, prev_key, progress):
    """Pass 1: refine every candidate in every view, seeded by detections near its projection."""
    key = [prev_key, _stage_settings(settings, "refine")]

    def compute():
        cands = localized["candidates"]
        C = np.array([c["center_model"] for c in cands]).reshape(-1, 3)
        N = [None if c["normal_model"] is None else np.asarray(c["normal_model"], float) for c in cands]
        R = np.array([c["radius_model"] for c in cands])
        obs, counts, rejected = refine_views(ctx_factory(), C, N, R, per_image, gate=1.5, progress=progress)
        markers = [{"candidate": j, "center_model": cands[j]["center_model"], "normal_model": cands[j]["normal_model"],
                    "radius_model": counts[j]["radius_model"] or cands[j]["radius_model"],
                    "observations": obs[j], "counts": counts[j]} for j in range(len(cands))]
        return {"markers": markers, "rejected": rejected}

    return store.run("refine", key, compute)


# ----------------------------------------------------------------------------------------------------
# Stage 4: triangulate, refine again from the triangulated points, triangulate (and adjust)


def _triangulate_markers(scene, markers, settings, dropped):
    from geometry.triangulate import Observation, triangulate

    out = []
    for m in markers:
        obs = [Observation(*_pose_cam(scene, o["image"]), np.array([o["x"], o["y"]]),
                           max(o["sigma_px"], settings.sigma_floor_px), o["image"])
               for o in m["observations"]]
        res = triangulate(obs, loss=settings.loss, f_scale=settings.f_scale,
                          outlier_sigma=settings.outlier_sigma, rng=np.random.default_rng(settings.seed),
                          outlier_px=[settings.outlier_radius_fraction * o["radius_px"] for o in m["observations"]])
        if not res.ok or res.n_inliers < settings.min_views:
            dropped.append({"candidate": m["candidate"], "reason": res.reason or
                            f"{res.n_inliers} inlier views < {settings.min_views}"})
            continue
        out.append({"candidate": m["candidate"], "model_point": res.point.tolist(), "rms_px": res.rms_px,
                    "covariance_model": res.covariance.tolist(), "max_angle_deg": res.max_angle_deg,
                    "normal_model": m.get("normal_model"), "counts": m.get("counts"),
                    "radius_model": m["radius_model"],
                    "observations": [dict(o, inlier=bool(res.inliers[k]),
                                          residual_px=np.linalg.norm(res.residuals_px[k]).item())
                                     for k, o in enumerate(m["observations"])]})
    return out


def stage_triangulate(store, ctx_factory, scene, refined, localized, per_image, settings, prev_key, progress):
    key = [prev_key, _stage_settings(settings, "triangulate")]

    def compute():
        dropped: list[dict] = []
        first = _merge_duplicates(_triangulate_markers(scene, refined["markers"], settings, dropped), dropped)
        # pass 2: the triangulated points project to within a pixel or so: refine in every view again
        P = np.array([m["model_point"] for m in first]).reshape(-1, 3)
        N = [None if m["normal_model"] is None else np.asarray(m["normal_model"], float) for m in first]
        R = np.array([m["radius_model"] for m in first])
        obs, counts, rejected = refine_views(ctx_factory(), P, N, R, per_image, gate=0.5, progress=progress)
        second = [{"candidate": m["candidate"], "normal_model": m["normal_model"], "observations": obs[j],
                   "counts": counts[j], "radius_model": counts[j]["radius_model"] or m["radius_model"]}
                  for j, m in enumerate(first)]
        out = _merge_duplicates(_triangulate_markers(scene, second, settings, dropped), dropped)
        out = [m for m in out if _enough_support(m, settings, dropped)]
        for m in out:
            m["quality"] = marker_quality(m, settings)
        adjusted = None
        if settings.adjust and out:
            adjusted = _adjust(scene, out, settings)
        return {"markers": out, "dropped": dropped, "adjusted": adjusted, "rejected_views": rejected}

    return store.run("triangulate", key, compute)


def marker_quality(m: dict, settings: GeorefSettings) -> float:
    """How much a triangulated marker looks like a real marker (higher is better), for ranking:
    (fraction of its usable views where the detector found it) x min(1, inlier views / 5) /
    max(median refinement sigma of its inlier views, 0.05 px). Markers give a crisp X-corner that
    the detector recognises in most views; X-corners of the scenery refine less sharply and are
    recognised rarely."""
    c = m["counts"]
    inl = [o for o in m["observations"] if o["inlier"]]
    frac = c["detected"] / max(c["usable"], 1)
    sig = float(np.median([o["sigma_px"] for o in inl])) if inl else 1.0
    return float(frac * min(1.0, len(inl) / 5.0) / max(sig, 0.05))


def _enough_support(m, settings, dropped) -> bool:
    """A marker must have been *detected* (not only refined) in at least two views and in at least
    ``min_detected_fraction`` of the views where it is usable: X-corners of the scenery refine as
    well as markers do, but the detector (which checks the whole pattern) fires on them rarely."""
    c = m["counts"]
    frac = c["detected"] / max(c["usable"], 1)
    if c["detected"] >= 2 and frac >= settings.min_detected_fraction:
        return True
    dropped.append({"candidate": m["candidate"],
                    "reason": f"detected in {c['detected']} of {c['usable']} usable views"})
    return False


def _merge_duplicates(markers, dropped):
    """Candidates that triangulate to the same point (within a quarter of the smaller marker radius:
    they refined onto the same X-corner) are one marker: keep the one with the best quality (or, before
    qualities exist, the most inlier views). A nearby but distinct X-corner is *not* merged away."""
    def rank(m):
        return m.get("quality", sum(o["inlier"] for o in m["observations"]))

    order = sorted(range(len(markers)), key=lambda k: -rank(markers[k]))
    kept = []
    for k in order:
        p = np.asarray(markers[k]["model_point"])
        r = markers[k]["radius_model"]
        if any(np.linalg.norm(p - np.asarray(markers[q]["model_point"])) < 0.25 * min(r, markers[q]["radius_model"])
               for q in kept):
            dropped.append({"candidate": markers[k]["candidate"], "reason": "duplicate of another candidate"})
            continue
        kept.append(k)
    return [markers[k] for k in sorted(kept)]

def _adjust(scene, markers, settings):
    from geometry.adjust import MarkerObservation, bundle_adjust

    obs = [MarkerObservation(j, o["image"], np.array([o["x"], o["y"]]), max(o["sigma_px"], settings.sigma_floor_px))
           for j, m in enumerate(markers) for o in m["observations"] if o["inlier"]]
    names = {o.image for o in obs}
    poses = {n: scene.images[n].cam_from_world for n in names}
    cams = {n: scene.camera_of(n) for n in names}
    radius = float(np.median([m["radius_model"] for m in markers]))
    prior_pos = settings.prior_pos if settings.prior_pos is not None else 0.4 * radius
    res = bundle_adjust(np.array([m["model_point"] for m in markers]), obs, poses, cams,
                        sigma_rot_rad=math.radians(settings.prior_rot_deg), sigma_pos=prior_pos,
                        loss=settings.loss, f_scale=max(settings.f_scale, 3.0))
    for j, m in enumerate(markers):
        m["model_point_triangulated"] = m["model_point"]
        m["model_point"] = res.points[j].tolist()
        m["rms_px"] = float(res.rms_px[j])
        m["covariance_model"] = res.covariance[j].tolist()
    return {"success": res.success, "message": res.message, "s0": res.s0, "n_evaluations": res.n_evaluations,
            "n_images": len(names)}


# ----------------------------------------------------------------------------------------------------
# Stage 5: register


@dataclass
class Surveyed:
    """Surveyed points: names, coordinates in their CRS (m, 3), local metric coordinates (m, 3)."""

    names: list[str]
    xyz: np.ndarray
    local: np.ndarray
    crs: Optional[str]
    frame: Any = None  # geometry.crs.LocalFrame or None


def load_surveyed(path: Path, crs: Optional[str]) -> Surveyed:
    """Read gcps.csv and express the points in a local Cartesian frame (metres).

    ``crs``: the CRS of the coordinates when the file does not name one (None: plain Cartesian metres).
    """
    from geometry.crs import CRSInputError, LocalFrame, crs_from_user

    if crs is not None:
        # a bad --crs is the option's fault, not the file's: check it before reading the file, even
        # when the file names its own CRS (which then wins)
        try:
            option_crs = crs_from_user(crs)
        except CRSInputError as exc:
            raise UsageError(f"--crs: {exc}") from None
    names, xyz, file_crs = _read_points(Path(path))
    crs_text = file_crs or crs
    try:
        user_crs = None if crs_text is None else (crs_from_user(file_crs) if file_crs else option_crs)
    except CRSInputError as exc:
        raise InputError(f"the CRS it names: {exc}", path) from None
    try:
        frame = LocalFrame.from_points(xyz, user_crs)
        local = frame.to_local(xyz)
    except CRSInputError as exc:
        where = "from the file" if file_crs else f"given by --crs {crs!r}"
        raise InputError(f"{exc} (CRS {where})", path) from None
    return Surveyed(names, xyz, np.asarray(local, float), None if crs_text is None else str(crs_text), frame)


def _read_points(path: Path) -> tuple[list[str], np.ndarray, Optional[str]]:
    """(names, xyz (m, 3), crs named by the file or None) of a surveyed-points CSV."""
    from .formats.points_csv import read_points_csv

    pts = read_points_csv(path, min_points=3, what="surveyed points")
    return list(pts.names), np.asarray(pts.xyz, float).reshape(-1, 3), getattr(pts, "crs", None)


def stage_register(store, triangulated, surveyed: Surveyed, settings, prev_key, gcps_key):
    """Register the markers to the surveyed points. When that fails with every marker (false markers
    can outnumber the real ones and let chance explain any pairing), it is retried with the best
    markers by :func:`marker_quality`: the best 3M, 2M, 1.5M and M for M surveyed points."""
    key = [prev_key, gcps_key, surveyed.crs, _stage_settings(settings, "register")]

    def compute():
        from geometry.registration import RegistrationConfig, register_points

        markers = triangulated["markers"]
        det = np.array([m["model_point"] for m in markers]).reshape(-1, 3)
        cfg = RegistrationConfig(noise=settings.registration_noise_m)
        order = np.argsort([-m.get("quality", 0.0) for m in markers], kind="stable")
        M = len(surveyed.names)
        sizes = [len(markers)] + sorted({int(math.ceil(f * M)) for f in (3, 2, 1.5, 1)
                                         if 3 <= math.ceil(f * M) < len(markers)}, reverse=True)
        attempts = []
        for n in sizes:
            subset = np.sort(order[:n])
            res = register_points(det[subset], surveyed.local, rng=np.random.default_rng(settings.seed), config=cfg)
            attempts.append({"markers": int(n), "status": res.status, "reason": res.reason,
                             "pairs": len(res.pairs), "rms_m": res.rms_m})
            if res.status == "ok":
                break
        return {"status": res.status, "reason": res.reason, "attempts": attempts,
                "world_from_model": None if res.world_from_model is None else res.world_from_model.to_dict(),
                "pairs": [{"detected": int(subset[p.detected]), "surveyed": p.surveyed, "residual_m": p.residual}
                          for p in res.pairs],
                "rms_m": res.rms_m, "sigma_m": res.sigma_m, "tolerance_m": res.tolerance_m,
                "hypotheses_tried": res.hypotheses_tried, "chance_probability": res.chance_probability,
                "n_alternatives": len(res.alternatives), "seconds": res.seconds}

    return store.run("register", key, compute)


# ----------------------------------------------------------------------------------------------------
# Export


def _finite(x):
    """JSON-safe: NaN/inf -> None, recursively."""
    if isinstance(x, float):
        return x if math.isfinite(x) else None
    if isinstance(x, dict):
        return {k: _finite(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_finite(v) for v in x]
    return x


def build_report(settings, inputs, localized, triangulated, registered, surveyed: Surveyed, stages) -> dict:
    from geometry.transforms import Sim3

    wfm = None if registered["world_from_model"] is None else Sim3.from_dict(registered["world_from_model"])
    pair_of = {p["detected"]: p for p in registered["pairs"]}
    markers = []
    for k, m in enumerate(triangulated["markers"]):
        entry = {"id": f"M{k + 1:03d}", "model_point": m["model_point"], "rms_px": m["rms_px"],
                 "quality": m.get("quality"),
                 "covariance_model": m["covariance_model"],
                 "n_views": sum(o["inlier"] for o in m["observations"]),
                 "observations": [{"image": o["image"], "x": o["x"], "y": o["y"], "sigma_px": o["sigma_px"],
                                   "inlier": o["inlier"], "residual_px": o["residual_px"]}
                                  for o in m["observations"]],
                 "surveyed_name": None, "residual_m": None}
        if wfm is not None:
            local = wfm(np.asarray(m["model_point"]))
            entry["local_point"] = local.tolist()
            if surveyed.frame is not None:
                entry["crs_point"] = np.asarray(surveyed.frame.from_local(local[None])).reshape(3).tolist()
        if k in pair_of and registered["status"] in ("ok", "ambiguous"):
            s = pair_of[k]["surveyed"]
            entry["surveyed_name"] = surveyed.names[s]
            entry["residual_m"] = (wfm(np.asarray(m["model_point"])) - surveyed.local[s]).tolist()
        markers.append(entry)
    paired = [m for m in markers if m["surveyed_name"] is not None]
    crs_from_model = _crs_from_model(wfm, triangulated["markers"], surveyed)
    status = registered["status"] if registered["status"] != "ok" else ("ok" if len(paired) >= 3 else "failed")
    reason = registered.get("reason", "")
    if not localized["candidates"]:
        reason = "; ".join(d["reason"] for d in localized.get("details", {}).values() if d.get("reason")) or reason
    report = {
        "format": REPORT_FORMAT, "status": status, "reason": reason,
        "detector": settings.detector if inputs.detections is None else f"detections from {Path(inputs.detections).name}",
        "mode": localized["mode"], "crs": surveyed.crs,
        "local_frame": None if surveyed.frame is None else _frame_dict(surveyed.frame),
        "world_from_model": registered["world_from_model"],
        "world_frame": "local Cartesian frame of the surveyed points (metres; see local_frame)",
        "crs_from_model": crs_from_model,
        "rms_m": registered["rms_m"], "n_markers": len(markers), "n_paired": len(paired),
        "n_surveyed": len(surveyed.names),
        "unpaired_surveyed": sorted(set(surveyed.names) - {m["surveyed_name"] for m in paired}),
        "markers": markers, "settings": asdict(settings),
        "inputs": {k: (None if v is None else str(v)) for k, v in asdict(inputs).items()},
        "stages": stages,
    }
    return _finite(report)


def _crs_from_model(wfm, markers, surveyed: Surveyed) -> Optional[dict]:
    """The similarity from the model frame straight to the surveyed CRS' coordinates, fitted on the
    markers (exact for a Cartesian CRS; for a projected CRS it absorbs the map projection's scale and
    convergence over the site, ``fit_rms_m`` says how well)."""
    if wfm is None or surveyed.frame is None or len(markers) < 3:
        return None
    from geometry.similarity import fit_similarity

    model = np.array([m["model_point"] for m in markers])
    crs_pts = np.asarray(surveyed.frame.from_local(wfm(model)))
    offset = np.round(crs_pts.mean(0))
    fit = fit_similarity(model, crs_pts - offset)
    if not fit:
        return None
    from geometry.transforms import Sim3

    sim = Sim3(fit.sim.scale, fit.sim.R, fit.sim.t + offset)
    return dict(sim.to_dict(), fit_rms_m=float(fit.rms), crs=surveyed.crs)


def _frame_dict(frame) -> dict:
    for attr in ("to_dict",):
        if hasattr(frame, attr):
            return getattr(frame, attr)()
    return {"repr": repr(frame)}


OUTPUTS = ("report.json", "detections.json", "gcp_list.txt", "markers.xml")


def export(report: dict, out: Path, surveyed: Surveyed, scene) -> None:
    """report.json, gcp_list.txt (ODM) and markers.xml (Metashape) in ``out`` (the last two only for
    a registration with pairs; :func:`run_georef` writes into a staging folder and moves them at once)."""
    out = Path(out)
    write_json_atomic(out / "report.json", report)
    paired = [m for m in report["markers"] if m["surveyed_name"] is not None]
    if not paired or report["status"] not in ("ok", "ambiguous"):
        return
    idx = {n: k for k, n in enumerate(surveyed.names)}
    if surveyed.crs is not None:
        from .formats.odm import GcpObservation, write_gcp_list

        obs = [GcpObservation(surveyed.xyz[idx[m["surveyed_name"]]], o["x"], o["y"], o["image"],
                              m["surveyed_name"])
               for m in paired for o in m["observations"] if o["inlier"]]
        write_gcp_list(out / "gcp_list.txt", surveyed.crs, obs)
    from .formats.metashape import MarkerRecord, write_metashape_markers

    records = []
    for m in report["markers"]:
        ref = None if m["surveyed_name"] is None else surveyed.xyz[idx[m["surveyed_name"]]]
        label = m["surveyed_name"] or m["id"]
        records.append(MarkerRecord(label, ref, {o["image"]: (o["x"], o["y"])
                                                 for o in m["observations"] if o["inlier"]}))
    write_metashape_markers(out / "markers.xml", records, scene=scene, crs=surveyed.crs)


# ----------------------------------------------------------------------------------------------------
# The whole run


def run_georef(inputs: GeorefInputs, settings: GeorefSettings = GeorefSettings(),
               progress: Callable = lambda it, **kw: it, workers: int = 1, scheduler: Any = None,
               on_detections: Optional[Callable[[dict], None]] = None) -> dict:
    """Run (or resume) every stage and export; returns the report (also in ``inputs.out/report.json``).

    The outputs (:data:`OUTPUTS`) are written together at the end: a run that fails leaves those of
    the previous run, if any, untouched and none of its own (its stage files stay, for a rerun to
    resume; an output folder it created and left empty is removed).

    ``workers`` / ``scheduler``: where the detect stage runs (see :func:`stage_detect`; the results do
    not depend on it, so neither do the stage keys). ``on_detections``: called with the per-image
    records (``{name: {"width", "height", "detections", ...}}``) once the detections are known, before
    the later stages (the comparison keeps them when a later stage fails).
    """
    out = Path(inputs.out)
    created = [d for d in (out, *out.parents) if not d.exists()]  # deepest first
    try:
        return _run_georef(inputs, settings, progress, workers, scheduler, on_detections)
    except BaseException:
        for d in created:  # only folders this run made and left empty
            try:
                d.rmdir()
            except OSError:
                break
        raise


def _check_image_sizes(scene, per_image: dict, source: Path) -> None:
    """Detections are pixel positions in the camera model of their image, so every image detected
    must have its camera's size; a one-line :class:`InputError` naming ``source`` (the detections
    file or the image folder) and the first image that differs, with the likely cause, otherwise."""
    for name, rec in per_image.items():
        w, h = int(rec.get("width") or 0), int(rec.get("height") or 0)
        if not (w and h):  # an image without a record
            continue
        cam = scene.cameras[scene.images[name].camera_id]
        if (w, h) == (cam.width, cam.height):
            continue
        if (w, h) == (cam.height, cam.width):
            why = ("turned by 90 degrees: cpdetect reads images as stored, with no EXIF orientation applied; "
                   "were these images rotated after the reconstruction, or detected by another tool?")
        elif abs(w * cam.height - h * cam.width) <= max(w, h, cam.width, cam.height):
            why = "a scaled copy? detect on the images the reconstruction was made from"
        else:
            why = "not the image the reconstruction was made from?"
        raise InputError(f"image {name!r} is {w}x{h} but its camera in the reconstruction is "
                         f"{cam.width}x{cam.height} ({why})", source)


def _apply_rejects(per_image: dict, rejects: list[dict], path: Path) -> tuple[dict, dict]:
    """Drop the detections a reviewer rejected (:func:`cpdetect.rejects.apply_rejects`); returns the
    filtered records and the report's ``rejects`` summary."""
    from .rejects import apply_rejects

    applied = apply_rejects(per_image, rejects)
    log.info("rejects (%s): %d rejects removed %d detections", path, len(rejects), len(applied.removed))
    if applied.unmatched:
        # normal for rejects of observations that georef measured by projection, not detected
        log.info("rejects (%s): %d match no detection (e.g. %s at %.1f, %.1f)", path, len(applied.unmatched),
                 applied.unmatched[0]["image"], applied.unmatched[0]["x"], applied.unmatched[0]["y"])
    return applied.detections, {"file": str(path), "n_rejects": len(rejects),
                                "removed_detections": len(applied.removed),
                                "unmatched_by_detections": len(applied.unmatched)}


def _run_georef(inputs, settings, progress, workers, scheduler, on_detections) -> dict:
    t0 = time.perf_counter()
    out = Path(inputs.out)
    store = StageStore(out)
    if not Path(inputs.gcps).is_file():
        raise InputError("surveyed points file not found", inputs.gcps)
    for p, what in ((inputs.cloud, "point cloud"), (inputs.mesh, "mesh")):
        if p is not None and not Path(p).is_file():
            raise InputError(f"{what} not found", p)
    rejects = None
    if inputs.rejects is not None:
        from .html_report import read_rejects

        rejects = read_rejects(Path(inputs.rejects))
    scene = load_scene(Path(inputs.reconstruction))
    surveyed = load_surveyed(Path(inputs.gcps), inputs.crs)
    image_paths = _image_paths(scene, Path(inputs.images))
    recon_key = _file_key(Path(inputs.reconstruction))

    if inputs.detections is not None:
        per_image = load_detections_json(Path(inputs.detections), image_paths)
        k1 = _hash(["detections-file", _file_key(Path(inputs.detections)),
                    [(n, _file_key(p)) for n, p in image_paths.items()]])  # refine reads the images
    else:
        per_image, k1 = stage_detect(store, scene, image_paths, settings, progress, workers, scheduler)
    _check_image_sizes(scene, per_image, Path(inputs.detections if inputs.detections is not None else inputs.images))
    k1 = _hash([k1, recon_key])
    rejects_summary = None
    if rejects is not None:
        per_image, rejects_summary = _apply_rejects(per_image, rejects, inputs.rejects)
        # the rejects (not the file's name or time) decide every later stage
        k1 = _hash([k1, sorted((r["image"], r["x"], r["y"]) for r in rejects)])
    if on_detections is not None:
        on_detections(per_image)
    localized, k2 = stage_localize(store, scene, per_image, settings, inputs, k1, progress)
    ctx_cache: list = []

    def ctx_factory():
        if not ctx_cache:
            ctx_cache.append(_ViewContext(scene, image_paths, settings, inputs, rejects or ()))
        return ctx_cache[0]

    k2b = _hash([k2, _file_key(inputs.mesh), _file_key(inputs.cloud)])
    refined, k3 = stage_refine(store, ctx_factory, localized, per_image, settings, k2b, progress)
    triangulated, k4 = stage_triangulate(store, ctx_factory, scene, refined, localized, per_image, settings, k3,
                                         progress)
    registered, _ = stage_register(store, triangulated, surveyed, settings, k4,
                                   _hash(Path(inputs.gcps).read_bytes().hex()))
    stages = {"ran": store.ran, "skipped": store.skipped, "seconds": round(time.perf_counter() - t0, 2),
              "candidates": len(localized["candidates"]), "refine_rejected": refined["rejected"],
              "dropped": triangulated["dropped"], "adjusted": triangulated["adjusted"],
              "registration_attempts": registered.get("attempts")}
    report = build_report(settings, inputs, localized, triangulated, registered, surveyed, stages)
    if rejects_summary is not None:
        # views dropped in the last refinement pass, the one the reported observations come from
        rejects_summary["removed_observations"] = triangulated["rejected_views"].get("reviewer", 0)
    report["rejects"] = rejects_summary
    with staged_outputs(out, stale=OUTPUTS) as staging:
        write_detections_json(staging / "detections.json", settings.detector, per_image)
        export(report, staging, surveyed, scene)
    return report
