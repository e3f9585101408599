"""Synthetic pier site: geometry, renderer conventions, written files and their agreement with the truth."""
import csv
import json
import math

import numpy as np
import pytest

from cpdetect.cli import main
from cpdetect.synth_render import box_edge_coverage, fit_xcorner, subpixel_pattern
from cpdetect.synth_scene import FORMAT, SiteSettings, _perturb_pose, build_site, write_site
from cpdetect.synth_site_geometry import (build_pier, chamfered_rectangle, min_signature_gap,
                                          offset_convex)
from geometry.camera import Camera
from geometry.transforms import Rigid3, Sim3

pycolmap = pytest.importorskip("pycolmap")
o3d = pytest.importorskip("open3d")

SMALL = dict(n_images=12, width=480, height=320, markers=6, unsurveyed_markers=1, missing_markers=1,
             hidden_surveyed=1, cloud_spacing=0.02)


@pytest.fixture(scope="module")
def site_dir(tmp_path_factory):
    """A small site with every knob used once, noise on, distortion on."""
    out = tmp_path_factory.mktemp("site") / "s"
    write_site(out, SiteSettings(seed=5, **SMALL))
    return out


@pytest.fixture(scope="module", params=[False, True], ids=["pinhole", "distortion"])
def clean_dir(tmp_path_factory, request):
    """A small site without noise, with and without lens distortion (for exact projection checks)."""
    out = tmp_path_factory.mktemp("clean") / "s"
    settings = SiteSettings(seed=3, n_images=8, width=640, height=427, markers=4, noise=False,
                            distortion=request.param, cloud_spacing=0.03)
    write_site(out, settings)
    return out, settings


def _truth(folder):
    return json.loads((folder / "truth.json").read_text())


def _gcps(folder):
    with open(folder / "gcps.csv", newline="") as fh:
        return {r["name"]: np.array([float(r["x"]), float(r["y"]), float(r["z"])]) for r in csv.DictReader(fh)}


# ------------------------------------------------------------------------------------------ geometry

def test_offset_polygon_keeps_every_edge_at_the_distance():
    poly = chamfered_rectangle(3.0, 1.6, 0.3)
    off = offset_convex(poly, 0.2)
    for i in range(len(poly)):
        p, q = poly[i], poly[(i + 1) % len(poly)]
        e = (q - p) / np.linalg.norm(q - p)
        n = np.array([e[1], -e[0]])
        assert np.dot(off[i] - p, n) == pytest.approx(0.2, abs=1e-12)
        assert np.dot(off[(i + 1) % len(poly)] - p, n) == pytest.approx(0.2, abs=1e-12)


def test_pier_mesh_is_closed_and_its_faces_are_planar():
    mesh = build_pier(np.random.default_rng(1))
    m = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(mesh.vertices),
                                  o3d.utility.Vector3iVector(mesh.triangles))
    assert m.is_watertight() and m.is_orientable()
    assert 8 <= mesh.height <= 12 and len(mesh.faces) == 19  # 8 plinth + 8 shaft sides, step, 2 caps
    tri = mesh.vertices[mesh.triangles]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    volume = np.einsum("ij,ij->", tri[:, 0], n) / 6.0  # outward winding gives a positive volume
    assert 25 < volume < 70
    for k, face in enumerate(mesh.faces):
        sel = mesh.tri_face == k
        d = (mesh.vertices[mesh.triangles[sel]].reshape(-1, 3) - face.origin) @ face.normal
        assert np.abs(d).max() < 1e-9
        nn = n[sel] / np.linalg.norm(n[sel], axis=1, keepdims=True)
        assert np.allclose(nn, face.normal, atol=1e-9)  # winding agrees with the outward normal
        assert np.allclose(np.cross(face.e_v, face.e_u), face.normal)  # u x v points into the pier


def test_signature_gap_detects_symmetric_layouts():
    square = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0.0]])
    assert min_signature_gap(square) == pytest.approx(0.0, abs=1e-12)
    bent = square + np.array([[0, 0, 0], [0.3, 0, 0], [0, 0.1, 0], [0, 0, 0.0]])
    assert min_signature_gap(bent) > 0.05


# ------------------------------------------------------------------------------------- the renderer

def test_renderer_puts_the_aiming_point_on_the_projected_pixel():
    """A frontal marker whose centre projects exactly onto pixel (100, 80) renders point-symmetric
    about that pixel, with the pixel itself half dark, half bright; half a pixel off it does not."""
    site = build_site(SiteSettings(seed=3, n_images=8, markers=3, width=320, height=213, noise=False,
                                   distortion=False))
    m = next(mk for mk in site.markers if mk.spec.type == "square")
    R = np.stack([m.axis_u, m.axis_v, -m.normal])
    pose = Rigid3(R, -R @ (m.center + 1.0 * m.normal))
    for cx, expect_symmetric in ((100.0, True), (100.5, False)):
        cam = Camera(200, 160, 400.0, 400.0, cx, 80.0)
        img = site.renderer.render(cam, pose, supersample=8).mean(axis=2)
        patch = img[80 - 15:80 + 16, 100 - 15:100 + 16]
        asym = np.abs(patch - patch[::-1, ::-1]).max()
        if expect_symmetric:
            assert asym < 1e-5
            dark, bright = img[70, 90], img[70, 110]
            assert abs(dark - bright) > 0.3
            assert img[80, 100] == pytest.approx(0.5 * (dark + bright), abs=1e-3)
        else:
            assert asym > 0.1


def test_subpixel_pattern_is_centred_and_rook_like():
    for n in (1, 16, 36, 64):
        p = subpixel_pattern(n)
        assert p.shape == (n, 2) and np.abs(p).max() < 0.5
        assert np.allclose(p.mean(axis=0), 0.0, atol=1e-12)
        if n > 1:  # every sample has its own x and its own y
            assert len(np.unique(np.round(p[:, 0], 9))) == n and len(np.unique(np.round(p[:, 1], 9))) == n


@pytest.mark.parametrize("theta", [0.0, 0.2, 0.9, math.pi / 2, 2.5])
def test_box_edge_coverage_is_the_exact_pixel_area(theta):
    g = (np.arange(600) + 0.5) / 600 - 0.5
    U, V = np.meshgrid(g, g)
    s = np.linspace(-1.1, 1.1, 23)
    brute = [np.mean(U * math.sin(theta) - V * math.cos(theta) > -si) for si in s]
    assert np.abs(box_edge_coverage(s, theta) - brute).max() < 2e-3
    assert box_edge_coverage(np.array([0.0]), theta)[0] == pytest.approx(0.5)


@pytest.mark.parametrize("distortion", [False, True])
def test_fit_xcorner_recovers_a_rendered_centre_under_perspective(distortion):
    site = build_site(SiteSettings(seed=3, n_images=8, markers=3, width=320, height=213, noise=False,
                                   distortion=distortion))
    m = next(mk for mk in site.markers if mk.spec.type == "diagonal")
    from cpdetect.synth_cameras import look_pose

    eye = m.center + 0.9 * m.normal + 0.5 * m.axis_u - 0.3 * m.axis_v  # about 35 degrees oblique
    pose = look_pose(eye, m.center - eye + 0.05 * m.axis_u, roll_rad=0.3)
    cam = site.camera.__class__(400, 300, 380.0, 380.0, 201.3, 148.2, site.camera.dist)
    uv, _ = cam.project(pose(m.center[None]))
    img = site.renderer.render(cam, pose).mean(axis=2)
    got = fit_xcorner(img, uv[0] + [0.7, -0.5], radius=12)
    assert np.hypot(*(got - uv[0])) < 0.02


# --------------------------------------------------------------------------------- the written site

def test_site_files_and_truth_schema(site_dir):
    names = {p.name for p in site_dir.iterdir()}
    assert {"images", "sparse", "fused.ply", "mesh.ply", "gcps.csv", "truth.json"} <= names
    assert not [p for p in site_dir.parent.iterdir() if p.name.startswith(".")]  # no temp folders left
    truth = _truth(site_dir)
    assert truth["format"] == FORMAT and truth["crs"] == "EPSG:25832"
    assert len(list((site_dir / "images").glob("*.jpg"))) == 12 == len(truth["images"])
    roles = [m["role"] for m in truth["markers"]]
    assert sorted(roles) == sorted(["regular"] * 6 + ["unsurveyed", "missing", "hidden"])
    regular = [m for m in truth["markers"] if m["role"] == "regular"]
    assert {m["type"] for m in regular} == {"square", "circle", "diagonal"}
    assert all(0.10 <= m["size_m"] <= 0.30 for m in truth["markers"])
    w2m = Sim3.from_dict(truth["world_from_model"])
    assert 0.5 <= w2m.scale <= 3.0
    assert 400_000 < w2m.t[0] < 500_000 and 5_000_000 < w2m.t[1] < 6_000_000


def test_visibility_roles_and_gcps(site_dir):
    truth = _truth(site_dir)
    gcps = _gcps(site_dir)
    by_role = {}
    for m in truth["markers"]:
        by_role.setdefault(m["role"], []).append(m)
        assert (m["name"] in gcps) == m["surveyed"]
    for m in by_role["regular"] + by_role["unsurveyed"]:
        assert len(m["visible_in"]) >= 3
    assert by_role["hidden"][0]["visible_in"] == [] and by_role["missing"][0]["visible_in"] == []
    seen = {mk["name"] for im in truth["images"] for mk in im["markers"]}
    assert by_role["missing"][0]["name"] not in seen and by_role["unsurveyed"][0]["name"] in seen
    w, h = truth["camera"]["width"], truth["camera"]["height"]
    for im in truth["images"]:
        for mk in im["markers"]:
            assert -0.5 <= mk["x"] <= w - 0.5 and -0.5 <= mk["y"] <= h - 0.5 and mk["radius_px"] > 3


def test_gcps_are_world_from_model_of_the_centres_plus_survey_noise(site_dir):
    truth = _truth(site_dir)
    gcps = _gcps(site_dir)
    w2m = Sim3.from_dict(truth["world_from_model"])
    res = []
    for m in truth["markers"]:
        world = w2m(np.array(m["center_model"]))
        assert np.allclose(world, m["center_world"], atol=1e-6)
        if m["surveyed"]:
            res.append(gcps[m["name"]] - world)
    res = np.array(res)
    assert len(res) == 8
    sigma = np.sqrt(np.mean(res ** 2))  # 24 residuals of sigma 3 mm (0.1 mm rounding)
    assert 0.0015 < sigma < 0.0045
    assert np.abs(res).max() < 0.015


def test_layout_is_asymmetric(site_dir):
    truth = _truth(site_dir)
    world = np.array([m["center_world"] for m in truth["markers"]])
    assert min_signature_gap(world) >= 0.05
    surveyed = np.array([m["center_world"] for m in truth["markers"] if m["surveyed"]])
    assert min_signature_gap(surveyed) >= 0.05


def test_mesh_and_cloud_agree_with_the_markers(site_dir):
    truth = _truth(site_dir)
    scale = truth["model_units_per_metre"]
    mesh = o3d.io.read_triangle_mesh(str(site_dir / "mesh.ply"))
    assert mesh.is_watertight()
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
    centers = np.array([m["center_model"] for m in truth["markers"]], np.float32)
    d = scene.compute_distance(o3d.core.Tensor(centers)).numpy() / scale
    assert d.max() < 1e-4  # markers lie on the mesh (float32 distance query)
    pc = o3d.io.read_point_cloud(str(site_dir / "fused.ply"))
    assert pc.has_normals() and pc.has_colors() and len(pc.points) > 10_000
    pts = np.asarray(pc.points, np.float32)
    dist = scene.compute_distance(o3d.core.Tensor(pts)).numpy() / scale
    # 1.5 mm noise along the normal plus 0.3 % outliers: a dense reconstruction's spread, not exact
    assert 0.0006 < np.median(dist) < 0.0020
    assert np.mean(dist > 0.02) < 0.005
    # the printed markers are in the cloud's colours: dark ink near every visible centre
    col = np.asarray(pc.colors)
    for m in truth["markers"]:
        if m["role"] == "regular":
            near = np.linalg.norm(pts - np.array(m["center_model"]), axis=1) < 0.4 * m["size_m"] * scale
            assert near.sum() > 5 and col[near].mean(axis=1).min() < 0.15


def test_projection_through_written_colmap_model_hits_rendered_centres(clean_dir):
    """Truth model points -> written COLMAP model read back by pycolmap -> pixels, against the
    centres measured on the rendered images (no noise; with and without lens distortion)."""
    folder, settings = clean_dir
    truth = _truth(folder)
    rec = pycolmap.Reconstruction()
    rec.read_text(str(folder / "sparse"))
    by_name = {im.name: im for im in rec.images.values()}
    site = build_site(settings)
    poses = dict(site.poses)
    centers = {m["name"]: np.array(m["center_model"]) for m in truth["markers"]}
    errors = []
    for im in truth["images"]:
        usable = [mk for mk in im["markers"] if mk["radius_px"] >= 15 and mk["view_angle_deg"] <= 60]
        if not usable:
            continue
        img = site.renderer.render(site.camera, poses[im["name"]]).mean(axis=2)
        for mk in usable:
            uv = np.asarray(by_name[im["name"]].project_point(centers[mk["name"]])) - 0.5  # COLMAP -> OpenCV
            assert np.hypot(uv[0] - mk["x"], uv[1] - mk["y"]) < 1e-6
            rad = 0.35 * mk["radius_px"]
            if not (rad + 2 < uv[0] < settings.width - rad - 3 and rad + 2 < uv[1] < settings.height - rad - 3):
                continue
            errors.append(np.hypot(*(fit_xcorner(img, uv + [0.8, -0.6], rad) - uv)))
    errors = np.array(errors)
    assert len(errors) >= 5
    assert np.median(errors) < 0.01 and errors.max() < 0.05


def test_same_seed_same_site_other_seed_other_site(tmp_path):
    kw = dict(n_images=6, width=96, height=64, markers=3, cloud_spacing=0.05)
    for name, seed in (("a", 11), ("b", 11), ("c", 12)):
        write_site(tmp_path / name, SiteSettings(seed=seed, **kw))
    a, b, c = tmp_path / "a", tmp_path / "b", tmp_path / "c"
    for rel in ("truth.json", "gcps.csv", "images/IMG_0003.jpg", "fused.ply", "sparse/images.txt"):
        assert (a / rel).read_bytes() == (b / rel).read_bytes(), rel
    assert (a / "gcps.csv").read_bytes() != (c / "gcps.csv").read_bytes()


def test_pose_noise_moves_camera_centres_by_sigma():
    rng = np.random.default_rng(0)
    pose = Rigid3(np.eye(3), [0.2, -0.1, 3.0])
    scale = 1.7  # model units per metre
    d = np.array([_perturb_pose(pose, 0.01, scale, rng).center - pose.center for _ in range(3000)])
    assert 0.0095 < d.std() / scale < 0.0105 and abs(d.mean()) / scale < 0.001
    assert _perturb_pose(pose, 0.0, scale, rng) is pose


# ------------------------------------------------------------------------------------------------ CLI

def test_cli_reports_one_line_for_an_unwritable_out(tmp_path, capsys):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    code = main(["synth", "scene", "--out", str(blocker / "site"), "--images", "2", "--size", "64x48"])
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1 and str(blocker / "site") in err


def test_cli_refuses_a_non_empty_out_and_bad_sizes(tmp_path, capsys):
    (tmp_path / "keep.txt").write_text("mine")
    assert main(["synth", "scene", "--out", str(tmp_path), "--images", "2", "--size", "64x48"]) == 2
    assert "not empty" in capsys.readouterr().err
    assert (tmp_path / "keep.txt").read_text() == "mine"
    assert main(["synth", "scene", "--out", str(tmp_path / "n"), "--size", "big"]) == 2
    assert "WIDTHxHEIGHT" in capsys.readouterr().err
    assert main(["synth", "scene", "--out", str(tmp_path / "n"), "--markers", "2"]) == 2
    assert not (tmp_path / "n").exists()


def test_cli_writes_a_site(tmp_path):
    out = tmp_path / "cli"
    code = main(["-q", "synth", "scene", "--out", str(out), "--seed", "2", "--images", "6", "--size", "96x64",
                 "--markers", "3", "--no-noise", "--no-distortion", "--cloud-spacing", "0.05"])
    assert code == 0
    truth = _truth(out)
    assert truth["settings"]["noise"] is False and truth["camera"]["dist_k1_k2_p1_p2_k3"] == [0.0] * 5
    assert math.isclose(truth["settings"]["survey_sigma"], 0.003)
