"""A synthetic survey site with known truth: a bridge-pier segment with markers, photographed by a drone.

``build_site(settings)`` makes the site in memory; ``write_site(out_dir, settings)`` renders and writes:

* ``images/IMG_0001.jpg`` ...: the rendered photographs;
* ``sparse/``: a COLMAP text model (cameras, images with the true poses, optionally perturbed by
  ``pose_noise``; points3D: a sample of the dense cloud) in the *model* frame;
* ``fused.ply``: a dense coloured cloud with normals in the model frame, like a dense reconstruction
  (points on the surface seen by two images or more, with noise and a few outliers);
* ``mesh.ply``: the pier's closed triangle mesh in the model frame;
* ``gcps.csv``: ``name,x,y,z`` surveyed marker centres in the projected CRS (default EPSG:25832: x
  easting, y northing, z height, metres) with survey noise;
* ``truth.json`` (written last): markers, their centres in both frames, ``world_from_model``, the true
  poses and each image's projected marker centres (OpenCV pixel convention), and the settings.

Frames. *site*: metric, z up, pier on z = 0 (internal only). *model*: an arbitrary similarity of the
site (1 model unit != 1 m; random rotation and offset), as a reconstruction would have; everything
written except gcps.csv is in the model frame. *world*: the CRS; ``world_from_model`` is a
:class:`~geometry.transforms.Sim3` with scale 0.5-3 and a UTM-magnitude translation.

Every random draw comes from its own stream spawned from ``seed``, so a seed gives identical output
and changing e.g. the image count leaves the pier and markers unchanged.
"""
from __future__ import annotations

import csv
import io
import logging
import math
import os
import shutil
import tempfile
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable, Optional

import cv2
import numpy as np

from geometry.camera import Camera
from geometry.scene import ImageRecord, Scene
from geometry.transforms import Rigid3, Sim3, matrix_to_quat_wxyz

from .errors import InputError, UsageError
from .markers import plane_homography, projected_radius
from .synth_cameras import NetworkSettings, survey_camera, survey_network
from .synth_render import Appearance, ImageEffects, SiteRenderer, apply_effects
from .synth_site_geometry import (PierMesh, PlacedMarker, PlacementRequest, build_pier, place_markers,
                                  sample_surface)

log = logging.getLogger(__name__)

FORMAT = "cpdetect.synth_scene/1"
STREAMS = ("geometry", "appearance", "cameras", "markers", "effects", "cloud", "survey", "poses", "frames")


@dataclass(frozen=True)
class SiteSettings:
    """Everything that defines a synthetic site (all lengths in metres unless stated).

    n_images, width, height: the survey; markers: printed and surveyed markers (>= 3, all three types;
    each seen well by min(3, n_images // 2) images or more); unsurveyed_markers: printed but absent
    from gcps.csv; missing_markers: surveyed but never printed (in gcps.csv, not in any image);
    hidden_surveyed: surveyed and printed where no camera sees them; noise: photometric effects
    (exposure, vignetting, blur, sensor noise, JPEG quality 85-95) and cloud noise; distortion: lens
    distortion; pose_noise: sigma (m) of the camera-centre perturbation in sparse/ (rotation sigma
    pose_noise / 2 m, in radians); survey_sigma: sigma (m, per axis) of gcps.csv; cloud_spacing:
    dense-cloud point spacing; supersample: sub-samples per pixel axis at edges (supersample^2 rays);
    backgrounds: background split for textures ("train", "test", "all"); crs: the CRS label;
    distance: camera-to-shaft distance; jpeg_quality: JPEG quality without noise.
    """

    seed: int = 0
    n_images: int = 48
    width: int = 1024
    height: int = 683
    markers: int = 9
    unsurveyed_markers: int = 0
    missing_markers: int = 0
    hidden_surveyed: int = 0
    noise: bool = True
    distortion: bool = True
    pose_noise: float = 0.0
    survey_sigma: float = 0.003
    cloud_spacing: float = 0.008
    supersample: int = 6
    backgrounds: str = "all"
    crs: str = "EPSG:25832"
    distance: float = 2.0
    jpeg_quality: int = 95

    def check(self) -> None:
        """Raise :class:`UsageError` for settings that cannot be honoured."""
        if self.n_images < 1:
            raise UsageError("--images must be at least 1")
        if not (16 <= self.width <= 20000 and 16 <= self.height <= 20000):
            raise UsageError(f"image size {self.width}x{self.height} out of range (16..20000 px per side)")
        if self.markers < 3:
            raise UsageError("--markers must be at least 3 (one of each type)")
        for name in ("unsurveyed_markers", "missing_markers", "hidden_surveyed"):
            if getattr(self, name) < 0:
                raise UsageError(f"{name.replace('_', '-')} must be >= 0")
        if self.markers + self.unsurveyed_markers + self.missing_markers + self.hidden_surveyed > 40:
            raise UsageError("at most 40 markers in all fit on the surveyed part of the pier")
        if not (self.pose_noise >= 0 and self.survey_sigma >= 0) or not math.isfinite(self.pose_noise + self.survey_sigma):
            raise UsageError("noise sigmas must be finite and >= 0")  # NaN passed "< 0" and broke the JSON
        if not 0.002 <= self.cloud_spacing <= 0.1:
            raise UsageError("--cloud-spacing must be within 0.002..0.1 m")
        if not 1 <= self.supersample <= 16:
            raise UsageError("--supersample must be within 1..16")
        if not 1.0 <= self.distance <= 10.0:
            raise UsageError("--distance must be within 1..10 m")


@dataclass
class Site:
    """A synthetic site in memory (site frame unless a name says otherwise)."""

    settings: SiteSettings
    mesh: PierMesh
    markers: list[PlacedMarker]
    camera: Camera
    poses: list[tuple[str, Rigid3]]  # (image name, cam_from_site)
    model_from_site: Sim3
    world_from_site: Sim3
    appearance: Appearance
    renderer: SiteRenderer
    textures_used: list[str] = field(default_factory=list)

    @property
    def world_from_model(self) -> Sim3:
        return self.world_from_site @ self.model_from_site.inverse()

    def cam_from_model(self, cam_from_site: Rigid3) -> Rigid3:
        """The same camera posed in the model frame (the camera frame rescaled by the model scale,
        which leaves every projection unchanged)."""
        site_from_model = self.model_from_site.inverse()
        a = site_from_model.scale
        t = (cam_from_site.R @ site_from_model.t + cam_from_site.t) / a
        return Rigid3(cam_from_site.R @ site_from_model.R, t)

    def scene(self) -> Scene:
        """The true cameras and poses as a :class:`Scene` in the model frame."""
        images = {name: ImageRecord(name, 1, self.cam_from_model(pose)) for name, pose in self.poses}
        return Scene(cameras={1: self.camera}, images=images, meta={"source": "cpdetect synth scene"})

    def visibility(self, points: np.ndarray, normals: np.ndarray, max_angle_deg: float = 75.0,
                   border_px: float = 0.0) -> np.ndarray:
        """(n_points, n_images) bool: which images see each site point."""
        return np.stack([self.renderer.visible(self.camera, pose, points, normals, max_angle_deg, border_px)
                         for _, pose in self.poses], axis=1)


def _streams(seed: int) -> dict[str, np.random.Generator]:
    seqs = np.random.SeedSequence(int(seed)).spawn(len(STREAMS))
    return {name: np.random.default_rng(s) for name, s in zip(STREAMS, seqs)}


def _random_rotation(rng: np.random.Generator) -> np.ndarray:
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    w, x, y, z = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def _load_textures(split: str, rng: np.random.Generator, n_faces: int, mesh: PierMesh
                   ) -> tuple[Appearance, list[str]]:
    from .backgrounds import BackgroundLibrary, list_backgrounds

    def pick(categories, k, min_side=0):
        try:
            cands = list_backgrounds(split=split, categories=categories)
        except UsageError:  # the split lacks this category: any split will do for ground and sky
            cands = list_backgrounds(split="all", categories=categories)
        big = [b for b in cands if min(_image_size(b.path)) >= min_side] or cands
        idx = rng.choice(len(big), size=min(k, len(big)), replace=False)
        return [big[i] for i in idx]

    walls = pick(("concrete", "plaster"), 3, min_side=400)
    ground = pick(("other",), 1, min_side=400)[0]
    env = pick(("facade",), 1)[0]
    chosen = walls + [ground, env]
    lib = BackgroundLibrary(chosen)
    textures = []
    for i in range(len(chosen)):
        bgr = lib.image(i)
        bgr = bgr[3:-3, 3:-3] if min(bgr.shape[:2]) > 64 else bgr  # JPEG borders would show as seams
        rgb = cv2.cvtColor(np.ascontiguousarray(bgr), cv2.COLOR_BGR2RGB).astype(np.float32) / 255.0
        textures.append(rgb)
    env_img = cv2.GaussianBlur(textures[-1], (0, 0), 3.0)
    textures = textures[:-1]
    # the shaft shares one texture, the plinth another: like two concrete pours
    face_texture = np.zeros(n_faces, np.int64)
    shaft_tex, plinth_tex = int(rng.integers(len(walls))), int(rng.integers(len(walls)))
    for f in mesh.faces:
        face_texture[f.index] = plinth_tex if f.name.startswith("plinth") or f.kind == "step" else shaft_tex
        if f.kind == "cap":
            face_texture[f.index] = shaft_tex
    face_texel = rng.uniform(0.0012, 0.002, n_faces)
    face_offset = rng.uniform(0, 2000, (n_faces, 2))
    face_gain = rng.uniform(0.9, 1.1, n_faces)
    az, el = rng.uniform(0, 2 * math.pi), math.radians(rng.uniform(25, 60))
    sun = np.array([math.cos(az) * math.cos(el), math.sin(az) * math.cos(el), math.sin(el)])
    app = Appearance(textures=textures, face_texture=face_texture, face_texel=face_texel,
                     face_offset=face_offset, face_gain=face_gain, ground_texture=len(walls),
                     ground_texel=float(rng.uniform(0.002, 0.004)), environment=env_img, sun=sun,
                     ambient=float(rng.uniform(0.45, 0.6)), diffuse=0.45)
    return app, [b.file for b in chosen]


def _image_size(path) -> tuple[int, int]:
    from .imageio import probe_image

    info = probe_image(path)
    return (info.width, info.height)


def build_site(settings: SiteSettings) -> Site:
    """Make the pier, its appearance, the camera network, and place the markers (no rendering)."""
    settings.check()
    rng = _streams(settings.seed)
    mesh = build_pier(rng["geometry"])
    g = rng["geometry"]
    # model frame: an arbitrary similarity of the site; world: the CRS (metric, z up)
    model_scale = float(np.exp(g.uniform(np.log(1 / 3.0), np.log(2.0))))
    model_from_site = Sim3(model_scale, _random_rotation(g), g.normal(0.0, 20.0, 3))
    heading = g.uniform(0, 2 * math.pi)
    Rz = np.array([[math.cos(heading), -math.sin(heading), 0], [math.sin(heading), math.cos(heading), 0],
                   [0, 0, 1.0]])
    world_from_site = Sim3(1.0, Rz, [g.uniform(420_000, 480_000), g.uniform(5_300_000, 5_900_000),
                                     g.uniform(100, 500)])
    appearance, used = _load_textures(settings.backgrounds, rng["appearance"], len(mesh.faces), mesh)
    camera = survey_camera(settings.width, settings.height, distortion=settings.distortion)
    corner = int(rng["cameras"].choice([2, 4, 6, 0]))  # a chamfer of the shaft
    poses = survey_network(mesh.footprint, corner, camera, settings.n_images, rng["cameras"],
                           NetworkSettings(distance=settings.distance))
    probe = SiteRenderer(mesh, [], appearance)
    min_views = min(3, max(1, settings.n_images // 2))  # 3 in any real survey; fewer for tiny tests

    def view_count(points, normals):
        border = 0.04 * camera.width
        return sum(probe.visible(camera, pose, points, normals, 60.0, border).astype(np.int32)
                   for _, pose in poses)

    def glimpse_count(points, normals):  # hidden markers: not even at grazing angles or just off-image
        border = -0.15 * camera.width
        return sum(probe.visible(camera, pose, points, normals, 89.0, border).astype(np.int32)
                   for _, pose in poses)

    request = PlacementRequest(regular=settings.markers, unsurveyed=settings.unsurveyed_markers,
                               missing=settings.missing_markers, hidden=settings.hidden_surveyed,
                               min_views=min_views)
    try:
        placed = place_markers(mesh, request, rng["markers"], view_count, glimpse_count=glimpse_count)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    placed = _name_markers(placed, rng["markers"])
    renderer = SiteRenderer(mesh, placed, appearance)
    return Site(settings, mesh, placed, camera, poses, model_from_site, world_from_site, appearance, renderer,
                used)


def _name_markers(placed: list[PlacedMarker], rng: np.random.Generator) -> list[PlacedMarker]:
    """Name surveyed markers GCP01.. and printed, unsurveyed ones U01.., numbered in a random order so
    that a name betrays nothing of the marker's role; returned sorted by name."""
    from dataclasses import replace

    surveyed = [m for m in placed if m.surveyed]
    unsurveyed = [m for m in placed if not m.surveyed]
    out = [replace(surveyed[i], name=f"GCP{k + 1:02d}") for k, i in enumerate(rng.permutation(len(surveyed)))]
    out += [replace(unsurveyed[i], name=f"U{k + 1:02d}") for k, i in enumerate(rng.permutation(len(unsurveyed)))]
    return sorted(out, key=lambda m: m.name)


# ------------------------------------------------------------------------------------------- writing

def _marker_projections(site: Site) -> tuple[dict[str, list[str]], list[dict]]:
    """Which images see each printed marker's centre, and per image the projected centres."""
    printed = [m for m in site.markers if m.printed]
    if not printed:
        return {}, [{"name": n, "markers": []} for n, _ in site.poses]
    centers = np.array([m.center for m in printed])
    normals = np.array([m.normal for m in printed])
    vis = site.visibility(centers, normals, max_angle_deg=80.0)
    visible_in: dict[str, list[str]] = {m.name: [] for m in printed}
    per_image = []
    cam = site.camera
    for j, (name, pose) in enumerate(site.poses):
        entries = []
        uv, _ = cam.project(pose(centers))
        for i, m in enumerate(printed):
            if not vis[i, j]:
                continue
            visible_in[m.name].append(name)
            R_cp = pose.R @ np.column_stack([m.axis_u, m.axis_v, m.normal * -1.0])
            H = plane_homography(cam.K, R_cp, pose(m.center[None])[0])
            outline = m.spec.outline(64, with_margin=False)
            pts = m.center + outline[:, :1] * m.axis_u + outline[:, 1:] * m.axis_v
            ouv, ofront = cam.project(pose(pts))
            to_cam = pose.center - m.center
            angle = math.degrees(math.acos(np.clip(to_cam @ m.normal / np.linalg.norm(to_cam), -1.0, 1.0)))
            entries.append({"name": m.name, "type": m.spec.type, "x": float(uv[i, 0]), "y": float(uv[i, 1]),
                            "radius_px": projected_radius(m.spec, H), "view_angle_deg": angle,
                            "fully_inside": bool(ofront.all() and cam.in_image(ouv).all())})
        per_image.append({"name": name, "markers": entries})
    return visible_in, per_image


def _dense_cloud(site: Site, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Dense cloud in the site frame: points (n, 3), colours (n, 3) uint8 RGB, normals (n, 3): the
    surface seen by two images or more, with noise (and 0.3 % outliers) when ``settings.noise``."""
    s = site.settings
    from scipy.spatial import cKDTree

    face_normals = np.array([f.normal for f in site.mesh.faces])
    # visibility on a coarse 4 cm grid, carried to the fine points by nearest neighbour (cheap, and
    # the coverage boundary of a real dense cloud is ragged anyway)
    coarse, cfidx = sample_surface(site.mesh, max(0.04, s.cloud_spacing), rng)
    counts = site.visibility(coarse, face_normals[cfidx], max_angle_deg=75.0).sum(axis=1)
    pts, fidx = sample_surface(site.mesh, s.cloud_spacing, rng)
    _, nearest = cKDTree(coarse).query(pts)
    keep = counts[nearest] >= min(2, len(site.poses))
    pts, fidx = pts[keep], fidx[keep]
    normals = face_normals[fidx]
    rgb, _ = site.renderer.albedo(fidx.astype(np.int32), pts, -normals)
    rgb = rgb * site.renderer.shading(fidx.astype(np.int32))[:, None]
    if s.noise:
        tangential = rng.normal(0.0, 0.001, pts.shape)
        tangential -= np.einsum("ij,ij->i", tangential, normals)[:, None] * normals
        pts = pts + rng.normal(0.0, 0.0015, (len(pts), 1)) * normals + tangential
        normals = normals + rng.normal(0.0, 0.03, normals.shape)
        normals /= np.linalg.norm(normals, axis=1, keepdims=True)
        n_out = int(0.003 * len(pts))
        if n_out:
            idx = rng.choice(len(pts), n_out, replace=False)
            pts[idx] += rng.normal(0.0, 0.05, (n_out, 3))
        rgb = rgb + rng.normal(0.0, 0.02, rgb.shape).astype(np.float32)
    colors = np.clip(rgb * 255.0 + 0.5, 0, 255).astype(np.uint8)
    return pts, colors, normals


def _write_mesh(path: Path, vertices: np.ndarray, triangles: np.ndarray) -> None:
    import open3d as o3d
    from .fileio import atomic_path

    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(np.asarray(vertices, float)),
                                     o3d.utility.Vector3iVector(np.asarray(triangles, np.int32)))
    mesh.compute_vertex_normals()
    with atomic_path(path) as tmp:
        tmp_ply = tmp.with_suffix(".ply")
        if not o3d.io.write_triangle_mesh(str(tmp_ply), mesh, write_ascii=False):
            raise InputError("cannot write mesh", path)
        os.replace(tmp_ply, tmp)


def _perturb_pose(pose: Rigid3, sigma_m: float, model_scale: float, rng: np.random.Generator) -> Rigid3:
    """Perturb a cam_from_model pose: centre by N(0, sigma_m) per axis (metres, converted to model units
    by ``model_scale`` = model units per metre), rotation by an angle-axis vector N(0, sigma_m / 2)."""
    if sigma_m <= 0:
        return pose
    from scipy.spatial.transform import Rotation

    dR = Rotation.from_rotvec(rng.normal(0.0, sigma_m / 2.0, 3)).as_matrix()
    center = pose.center + rng.normal(0.0, sigma_m, 3) * model_scale
    R = dR @ pose.R
    return Rigid3(R, -R @ center)


@dataclass
class SiteReport:
    """What ``write_site`` made: the output folder, timings (s) and counts."""

    out_dir: Path
    seconds: dict
    n_images: int
    n_cloud_points: int
    visible_counts: dict


def _prepare_out(out_dir: Path, overwrite: bool) -> Path:
    from .fileio import cannot_write

    if out_dir.exists():
        if not out_dir.is_dir():
            raise InputError("exists and is not a folder", out_dir)
        if any(out_dir.iterdir()) and not overwrite:
            raise InputError("output folder exists and is not empty (use --overwrite)", out_dir)
    try:
        out_dir.parent.mkdir(parents=True, exist_ok=True)
        return Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.", suffix=".part", dir=out_dir.parent))
    except OSError as exc:
        raise cannot_write(exc, out_dir) from None


def write_site(out_dir: str | os.PathLike, settings: SiteSettings, overwrite: bool = False,
               progress: Optional[Callable[[int, int], None]] = None) -> SiteReport:
    """Build, render and write a site into ``out_dir`` (see the module docstring).

    The folder is assembled under a temporary name beside ``out_dir`` and renamed into place at the
    end, so a reader never sees a half-written site; an existing non-empty ``out_dir`` is replaced
    only with ``overwrite``. ``progress(done, total)`` is called after each image.
    """
    from .formats.colmap import write_colmap
    from .formats.ply import write_ply_points

    out_dir = Path(out_dir)
    settings.check()
    tmp = _prepare_out(out_dir, overwrite)
    times: dict[str, float] = {}
    try:
        t0 = time.perf_counter()
        site = build_site(settings)
        rng = _streams(settings.seed)
        times["build"] = time.perf_counter() - t0
        # images
        t0 = time.perf_counter()
        (tmp / "images").mkdir()
        eff_rng, frame_rng = rng["effects"], rng["frames"]
        n = len(site.poses)
        ray_cache: dict = {}
        for k, (name, pose) in enumerate(site.poses):
            img = site.renderer.render(site.camera, pose, supersample=settings.supersample, ray_cache=ray_cache)
            effects = ImageEffects.random(eff_rng) if settings.noise else ImageEffects()
            quality = int(eff_rng.integers(85, 96)) if settings.noise else settings.jpeg_quality
            bgr = apply_effects(img, effects, frame_rng)
            ok, buf = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, quality])
            if not ok:
                raise InputError("JPEG encoding failed", tmp / "images" / name)
            (tmp / "images" / name).write_bytes(buf.tobytes())
            del img, bgr
            if progress is not None:
                progress(k + 1, n)
        times["render"] = time.perf_counter() - t0
        # dense cloud, mesh, sparse model
        t0 = time.perf_counter()
        m2s = site.model_from_site
        pts, colors, normals = _dense_cloud(site, rng["cloud"])
        pts_m = m2s.scale * np.einsum("ij,kj->ki", m2s.R, pts) + m2s.t
        normals_m = np.einsum("ij,kj->ki", m2s.R, normals)
        write_ply_points(tmp / "fused.ply", pts_m, colors, normals_m)
        _write_mesh(tmp / "mesh.ply", m2s(site.mesh.vertices), site.mesh.triangles)
        scene = site.scene()
        pose_rng = rng["poses"]
        for rec in scene.images.values():
            rec.cam_from_world = _perturb_pose(rec.cam_from_world, settings.pose_noise, m2s.scale, pose_rng)
        sparse_idx = rng["cloud"].choice(len(pts_m), size=min(3000, len(pts_m)), replace=False)
        write_colmap(scene, tmp / "sparse", points3d=(pts_m[sparse_idx], colors[sparse_idx]))
        times["cloud_mesh_sparse"] = time.perf_counter() - t0
        # survey and truth
        w2m = site.world_from_model
        centers_m = np.array([m2s(m.center[None])[0] for m in site.markers])
        centers_w = w2m(centers_m)
        survey_noise = rng["survey"].normal(0.0, settings.survey_sigma, centers_w.shape)
        surveyed_w = centers_w + survey_noise
        lines = io.StringIO()
        wr = csv.writer(lines, lineterminator="\n")
        wr.writerow(["name", "x", "y", "z"])
        for m, p in sorted(zip(site.markers, surveyed_w), key=lambda mp: mp[0].name):
            if m.surveyed:
                wr.writerow([m.name] + [f"{v:.4f}" for v in p])
        (tmp / "gcps.csv").write_text(lines.getvalue(), encoding="utf-8")
        visible_in, per_image = _marker_projections(site)
        truth = _truth(site, centers_m, centers_w, surveyed_w, visible_in, per_image, scene, len(pts_m))
        from .fileio import write_json_atomic

        write_json_atomic(tmp / "truth.json", truth)
        _replace_folder(tmp, out_dir)
    except OSError as exc:  # disk full, permissions changed under us...
        shutil.rmtree(tmp, ignore_errors=True)
        raise InputError(f"cannot write the site: {exc.strerror or exc}", out_dir) from None
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return SiteReport(out_dir, times, n, len(pts_m), {k: len(v) for k, v in visible_in.items()})


def _replace_folder(tmp: Path, out_dir: Path) -> None:
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp, 0o777 & ~umask)  # mkdtemp made it private
    old = None
    if out_dir.exists():
        old = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.", suffix=".old", dir=out_dir.parent))
        os.replace(out_dir, old / "site")
    os.replace(tmp, out_dir)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


def _truth(site: Site, centers_m, centers_w, surveyed_w, visible_in, per_image, scene: Scene,
           n_cloud: int) -> dict:
    m2s = site.model_from_site
    markers = []
    for i, m in enumerate(site.markers):
        markers.append({
            "name": m.name, "type": m.spec.type, "size_m": m.spec.size_m, "margin_m": m.spec.margin_m,
            "role": m.role, "printed": m.printed, "surveyed": m.surveyed,
            "center_model": centers_m[i].tolist(), "center_world": centers_w[i].tolist(),
            "surveyed_world": surveyed_w[i].tolist() if m.surveyed else None,
            "normal_model": (m2s.R @ m.normal).tolist(),
            "axis_u_model": (m2s.R @ m.axis_u).tolist(), "axis_v_model": (m2s.R @ m.axis_v).tolist(),
            "face": site.mesh.faces[m.face].name, "visible_in": visible_in.get(m.name, []),
        })
    images = []
    for (name, pose), proj in zip(site.poses, per_image):
        true = site.cam_from_model(pose)
        written = scene.images[name].cam_from_world
        images.append({"name": name, "cam_from_model": {"qvec_wxyz": matrix_to_quat_wxyz(true.R).tolist(),
                                                         "tvec": true.t.tolist()},
                       "center_model": true.center.tolist(),
                       "written_center_model": written.center.tolist(), "markers": proj["markers"]})
    cam = site.camera
    return {
        "format": FORMAT, "crs": site.settings.crs,
        "world_from_model": site.world_from_model.to_dict(),
        "model_units_per_metre": m2s.scale,
        "pixel_convention": "opencv (centre of the top-left pixel is (0, 0))",
        "camera": {"width": cam.width, "height": cam.height, "fx": cam.fx, "fy": cam.fy, "cx": cam.cx,
                   "cy": cam.cy, "dist_k1_k2_p1_p2_k3": list(cam.dist)},
        "markers": markers, "images": images,
        "pier": {"height_m": site.mesh.height, "step_height_m": site.mesh.step_height,
                 "faces": len(site.mesh.faces), "triangles": int(len(site.mesh.triangles))},
        "dense_cloud_points": n_cloud, "textures": site.textures_used,
        "settings": asdict(site.settings),
    }


__all__ = ["SiteSettings", "Site", "SiteReport", "build_site", "write_site", "FORMAT"]
