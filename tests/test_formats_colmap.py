"""COLMAP model reader/writer: round trips, pixel convention, camera models, bad files, Sim3 export."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from cpdetect.errors import InputError
from cpdetect.formats.colmap import (apply_sim3_to_colmap, camera_from_colmap, camera_to_colmap,
                                     find_colmap_model, read_colmap, write_colmap)
from cpdetect.formats.reconstruction import detect_reconstruction_format, read_reconstruction
from geometry.camera import Camera
from geometry.scene import ImageRecord, Scene
from geometry.transforms import Rigid3, Sim3

pycolmap = pytest.importorskip("pycolmap")


def make_scene(rng: np.random.Generator, n_points: int = 20) -> Scene:
    cams = {
        1: Camera(640, 480, 500.0, 510.0, 319.5, 239.5),
        2: Camera(800, 600, 700.0, 701.0, 400.2, 300.1, (0.1, -0.02, 0.001, 0.002, 0.0)),
        7: Camera(800, 600, 700.0, 700.0, 399.7, 298.9, (0.1, -0.02, 0.001, 0.002, 0.003)),
    }
    images = {}
    for i, (name, cam_id) in enumerate([("a.jpg", 1), ("sub/b.jpg", 2), ("c.JPG", 7), ("d.jpg", 2)]):
        R = Rotation.from_rotvec(rng.normal(size=3)).as_matrix()
        images[name] = ImageRecord(name, cam_id, Rigid3(R, rng.normal(size=3) * 10))
    pts = rng.normal(size=(n_points, 3)) * 30 + np.array([500_000.0, 5_700_000.0, 100.0])
    cols = rng.integers(0, 256, size=(n_points, 3)).astype(np.uint8)
    return Scene(cams, images, points=pts, colors=cols)


def assert_scenes_equal(a: Scene, b: Scene, tol: float = 1e-9) -> None:
    assert set(a.cameras) == set(b.cameras)
    for k, ca in a.cameras.items():
        cb = b.cameras[k]
        assert (ca.width, ca.height) == (cb.width, cb.height)
        np.testing.assert_allclose([ca.fx, ca.fy, ca.cx, ca.cy], [cb.fx, cb.fy, cb.cx, cb.cy], atol=tol, rtol=0)
        np.testing.assert_allclose(ca.dist, cb.dist, atol=1e-15, rtol=0)
    assert list(a.images) == list(b.images)
    for name, ia in a.images.items():
        ib = b.images[name]
        assert ia.camera_id == ib.camera_id
        np.testing.assert_allclose(ia.cam_from_world.matrix, ib.cam_from_world.matrix, atol=tol, rtol=0)


@pytest.mark.parametrize("binary", [False, True])
def test_round_trip_scene_colmap_scene(tmp_path, binary):
    rng = np.random.default_rng(1)
    scene = make_scene(rng)
    out = write_colmap(scene, tmp_path / "model", binary=binary)
    ext = ".bin" if binary else ".txt"
    assert sorted(p.name for p in out.iterdir()) == sorted(
        f"{n}{ext}" for n in ("cameras", "images", "points3D", "rigs", "frames"))
    back = read_colmap(out)
    assert_scenes_equal(scene, back)
    # UTM-sized coordinates survive in float64 (no float32 anywhere on the way).
    np.testing.assert_array_equal(back.points, scene.points)
    np.testing.assert_array_equal(back.colors, scene.colors)
    assert back.meta["colmap_binary"] is binary
    assert back.meta["colmap_image_ids"] == {"a.jpg": 1, "sub/b.jpg": 2, "c.JPG": 3, "d.jpg": 4}
    # Writing the read scene again keeps the image ids.
    back.meta["colmap_image_ids"] = {"a.jpg": 10, "sub/b.jpg": 3, "c.JPG": 11, "d.jpg": 4}
    again = read_colmap(write_colmap(back, tmp_path / "model2", binary=binary))
    assert again.meta["colmap_image_ids"] == back.meta["colmap_image_ids"]


def test_camera_models_chosen_by_distortion(tmp_path):
    scene = make_scene(np.random.default_rng(2))
    write_colmap(scene, tmp_path / "m")
    lines = [l.split() for l in (tmp_path / "m" / "cameras.txt").read_text().splitlines()
             if l and not l.startswith("#")]
    models = {int(f[0]): f[1] for f in lines}
    assert models == {1: "PINHOLE", 2: "OPENCV", 7: "FULL_OPENCV"}
    params = {int(f[0]): [float(v) for v in f[4:]] for f in lines}
    # COLMAP pixel convention: principal point shifted by +0.5 on write.
    assert params[1] == [500.0, 510.0, 320.0, 240.0]
    assert params[7][8] == pytest.approx(0.003) and params[7][9:] == [0.0, 0.0, 0.0]


def test_pixel_convention_projected_point():
    """The same 3D point lands exactly 0.5 px further right and down in COLMAP than in OpenCV."""
    cam = Camera(1000, 750, 900.0, 905.0, 498.3, 371.9, (-0.12, 0.05, 0.0011, -0.0007, 0.01))
    model, params = camera_to_colmap(cam)
    c = pycolmap.Camera(model=model, width=cam.width, height=cam.height, params=params, camera_id=1)
    pts = np.array([[0.1, -0.2, 3.0], [-0.5, 0.3, 2.0], [0.0, 0.0, 1.0]])
    uv_cv, _ = cam.project(pts)
    uv_colmap = np.array([c.img_from_cam(p) for p in pts])
    np.testing.assert_allclose(uv_colmap - uv_cv, 0.5, atol=1e-9)
    # And back: the reader undoes the shift.
    back = camera_from_colmap(model, cam.width, cam.height, params)
    assert back.cx == pytest.approx(cam.cx, abs=1e-12) and back.cy == pytest.approx(cam.cy, abs=1e-12)


def write_text_model(folder: Path, cameras: str, images: str = "", points: str = "") -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "cameras.txt").write_text(cameras)
    (folder / "images.txt").write_text(images)
    (folder / "points3D.txt").write_text(points)
    return folder


def test_reads_simple_models_and_legacy_model_without_rigs(tmp_path):
    cams = ("# comment\n"
            "1 SIMPLE_PINHOLE 100 80 90 50 40\n"
            "2 SIMPLE_RADIAL 100 80 91 50.5 40.5 0.05\n"
            "3 RADIAL 100 80 92 49 39 0.05 -0.01\n")
    # Pose: identity rotation, T = (1, 2, 3); second image rotated 90 degrees about z.
    q = Rotation.from_euler("z", 90, degrees=True).as_quat()  # x y z w
    imgs = ("1 1 0 0 0 1 2 3 1 one.jpg\n\n"
            f"2 {q[3]} {q[0]} {q[1]} {q[2]} 0 0 5 3 two.jpg\n10 20 -1\n")
    pts = "5 1 2 3 255 0 10 0.5\n"
    model = write_text_model(tmp_path / "proj" / "sparse" / "0", cams, imgs, pts)
    assert find_colmap_model(tmp_path / "proj") == model
    s = read_colmap(tmp_path / "proj")
    c1, c2, c3 = s.cameras[1], s.cameras[2], s.cameras[3]
    assert (c1.fx, c1.fy, c1.cx, c1.cy, c1.dist) == (90, 90, 49.5, 39.5, (0, 0, 0, 0, 0))
    assert (c2.cx, c2.cy, c2.dist[0]) == (50.0, 40.0, 0.05)
    assert c3.dist == (0.05, -0.01, 0.0, 0.0, 0.0)
    np.testing.assert_allclose(s.images["one.jpg"].cam_from_world.t, [1, 2, 3])
    np.testing.assert_allclose(s.images["two.jpg"].cam_from_world.R @ [1, 0, 0], [0, 1, 0], atol=1e-12)
    np.testing.assert_array_equal(s.points, [[1, 2, 3]])
    np.testing.assert_array_equal(s.colors, [[255, 0, 10]])


def test_unsupported_model_names_camera_file_and_line(tmp_path):
    model = write_text_model(tmp_path / "m", "# c\n4 OPENCV_FISHEYE 100 80 90 90 50 40 0.1 0 0 0\n",
                             "1 1 0 0 0 0 0 0 4 x.jpg\n\n")
    with pytest.raises(InputError) as ei:
        read_colmap(model)
    msg = str(ei.value)
    assert "camera 4" in msg and "OPENCV_FISHEYE" in msg and msg.startswith(f"{model / 'cameras.txt'}:2:")
    assert "\n" not in msg and ei.value.exit_code != 0


def test_full_opencv_rational_terms_rejected():
    with pytest.raises(ValueError, match="rational"):
        camera_from_colmap("FULL_OPENCV", 10, 10, [5, 5, 5, 5, 0, 0, 0, 0, 0, 0.1, 0, 0])


def test_missing_images_txt(tmp_path):
    scene = make_scene(np.random.default_rng(3))
    out = write_colmap(scene, tmp_path / "m")
    (out / "images.txt").unlink()
    with pytest.raises(InputError) as ei:
        read_colmap(out)
    assert ei.value.path == str(out / "images.txt") and "missing images.txt" in str(ei.value)


@pytest.mark.parametrize("part", ["cameras", "images", "points3D"])
def test_truncated_or_padded_binary_file(tmp_path, part):
    """pycolmap alone reads stale values (or crashes) past the end of a cut file: we must refuse it."""
    out = write_colmap(make_scene(np.random.default_rng(7)), tmp_path / "m", binary=True)
    f = out / f"{part}.bin"
    data = f.read_bytes()
    for cut in (data[:5], data[:len(data) // 2], data[:-8], data[:-1], data + b"\0"):
        f.write_bytes(cut)
        with pytest.raises(InputError, match="corrupt") as ei:
            read_colmap(out)
        assert ei.value.path == str(f) and "\n" not in str(ei.value)
    f.write_bytes(data)
    assert_scenes_equal(read_colmap(out), read_colmap(out))


def test_malformed_line_is_located(tmp_path):
    model = write_text_model(tmp_path / "m", "1 PINHOLE 100 80 90 90 50 40\n",
                             "# h\n1 1 0 0 0 0 0 0 1 a.jpg\n\n2 1 0 0 zero 0 0 0 1 b.jpg\n\n")
    with pytest.raises(InputError) as ei:
        read_colmap(model)
    assert (ei.value.path, ei.value.line) == (str(model / "images.txt"), 4)


def test_wrong_parameter_count_is_located(tmp_path):
    model = write_text_model(tmp_path / "m", "1 PINHOLE 100 80 90 90 50 40\n2 OPENCV 100 80 90 90 50 40\n",
                             "1 1 0 0 0 0 0 0 1 a.jpg\n\n")
    with pytest.raises(InputError) as ei:
        read_colmap(model)
    assert (ei.value.path, ei.value.line) == (str(model / "cameras.txt"), 2)


def test_non_finite_point_rejected(tmp_path):
    model = write_text_model(tmp_path / "m", "1 PINHOLE 100 80 90 90 50 40\n",
                             "1 1 0 0 0 0 0 0 1 a.jpg\n\n", "1 0 0 0 1 1 1 0\n2 nan 0 0 1 1 1 0\n")
    with pytest.raises(InputError) as ei:
        read_colmap(model)
    assert ei.value.path.endswith("points3D.txt")


def test_not_a_model(tmp_path):
    with pytest.raises(InputError, match="no COLMAP model"):
        read_colmap(tmp_path)
    with pytest.raises(InputError, match="not found"):
        read_colmap(tmp_path / "nope")


def test_writer_is_atomic_and_refuses_foreign_files(tmp_path):
    rng = np.random.default_rng(4)
    s1, s2 = make_scene(rng), make_scene(rng)
    out = tmp_path / "m"
    write_colmap(s1, out)
    write_colmap(s2, out, binary=True)  # replaces the previous text model entirely
    assert sorted(p.suffix for p in out.iterdir()) == [".bin"] * 5
    assert_scenes_equal(s2, read_colmap(out))
    assert [p.name for p in tmp_path.iterdir()] == ["m"]  # no temporary folders left behind
    (out / "notes.md").write_text("mine")
    with pytest.raises(InputError, match="other files"):
        write_colmap(s1, out)
    assert (out / "notes.md").read_text() == "mine"
    bad = Scene(s1.cameras, {"x": ImageRecord("x", 99, Rigid3.identity())})
    with pytest.raises(ValueError, match="camera 99"):
        write_colmap(bad, tmp_path / "bad")
    assert not (tmp_path / "bad").exists()


def test_apply_sim3_to_colmap(tmp_path):
    rng = np.random.default_rng(5)
    scene = make_scene(rng)
    scene.points = scene.points - scene.points.mean(axis=0)  # a 30 m cloud round the origin
    for name, rec in scene.images.items():  # cameras 200 m away, looking at the cloud
        z = -rng.normal(size=3)
        z /= np.linalg.norm(z)
        x = np.cross([0.0, 0.0, 1.0], z)
        x /= np.linalg.norm(x)
        R = np.stack([x, np.cross(z, x), z])  # rows: camera axes in world
        rec.cam_from_world = Rigid3(R, -R @ (-200.0 * z))
    src = write_colmap(scene, tmp_path / "in", binary=True)
    sim = Sim3(3.7, Rotation.from_rotvec([0.3, -0.2, 1.1]).as_matrix(), [1e3, -2e3, 50.0])
    out = apply_sim3_to_colmap(src, sim, tmp_path / "aligned")
    res = read_colmap(out)
    assert res.meta["colmap_binary"] is True
    np.testing.assert_allclose(res.points, sim(scene.points), atol=1e-9, rtol=0)
    for name, rec in scene.images.items():
        new = res.images[name]
        np.testing.assert_allclose(new.center, sim(rec.center), atol=1e-9, rtol=0)
        # Projections are unchanged: the model moved, the photos did not.
        uv_old, front_old = scene.cameras[rec.camera_id].project(rec.cam_from_world(scene.points))
        uv_new, front_new = res.cameras[rec.camera_id].project(new.cam_from_world(res.points))
        np.testing.assert_array_equal(front_new, front_old)
        assert front_old.all()
        np.testing.assert_allclose(uv_new[front_old], uv_old[front_old], atol=1e-7, rtol=0)
    with pytest.raises(InputError, match="output folder is the input"):
        apply_sim3_to_colmap(src, sim, src)


def test_read_reconstruction_detects_colmap(tmp_path):
    scene = make_scene(np.random.default_rng(6))
    write_colmap(scene, tmp_path / "proj" / "sparse" / "0", binary=True)
    assert detect_reconstruction_format(tmp_path / "proj") == ("colmap", tmp_path / "proj")
    assert detect_reconstruction_format(tmp_path / "proj" / "sparse" / "0" / "images.bin")[0] == "colmap"
    got = read_reconstruction(tmp_path / "proj")
    assert got.meta["format"] == "colmap"
    assert_scenes_equal(scene, got)
    (tmp_path / "elsewhere").mkdir()
    with pytest.raises(InputError, match="no reconstruction found"):
        read_reconstruction(tmp_path / "elsewhere")
    (tmp_path / "x.obj").write_text("v 0 0 0")
    with pytest.raises(InputError, match="unknown reconstruction format"):
        read_reconstruction(tmp_path / "x.obj")


def test_explicit_points3d_argument(tmp_path):
    scene = make_scene(np.random.default_rng(8))
    xyz = np.array([[1.0, 2.0, 3.0], [-4.0, 5.5, 6.25]])
    got = read_colmap(write_colmap(scene, tmp_path / "a", points3d=xyz))
    np.testing.assert_array_equal(got.points, xyz)
    np.testing.assert_array_equal(got.colors, np.full((2, 3), 128))
    rgb = np.array([[1, 2, 3], [4, 5, 6]], np.uint8)
    got = read_colmap(write_colmap(scene, tmp_path / "b", points3d=(xyz, rgb)))
    np.testing.assert_array_equal(got.colors, rgb)
    with pytest.raises(ValueError, match="non-finite"):
        write_colmap(scene, tmp_path / "c", points3d=np.array([[0.0, np.nan, 1.0]]))
