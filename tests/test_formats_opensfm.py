"""OpenSfM reconstruction.json: round trip, normalised intrinsics, angle-axis poses, ENU reference."""
from __future__ import annotations

import json

import numpy as np
import pytest
from pyproj import Transformer
from scipy.spatial.transform import Rotation

from cpdetect.errors import InputError
from cpdetect.formats.opensfm import (camera_from_opensfm, camera_to_opensfm, ecef_from_enu, read_opensfm,
                                      write_opensfm)
from cpdetect.formats.reconstruction import read_reconstruction
from geometry.camera import Camera
from geometry.scene import ImageRecord, Scene
from geometry.transforms import Rigid3


def make_scene(rng) -> Scene:
    cams = {1: Camera(5472, 3648, 3650.0, 3650.0, 2735.5, 1823.5, (-0.01, 0.02, 0.0, 0.0, 0.0)),
            2: Camera(4000, 3000, 3000.0, 3010.0, 2001.7, 1497.2, (0.03, -0.01, 0.001, -0.0005, 0.002))}
    images = {f"DJI_{i:04d}.JPG": ImageRecord(f"DJI_{i:04d}.JPG", 1 + i % 2,
                                              Rigid3(Rotation.from_rotvec(rng.normal(size=3)).as_matrix(),
                                                     rng.normal(size=3) * 50)) for i in range(4)}
    pts = rng.normal(size=(15, 3)) * 20
    cols = rng.integers(0, 256, (15, 3)).astype(np.uint8)
    return Scene(cams, images, pts, cols,
                 meta={"reference_lla": {"latitude": 46.84, "longitude": -91.99, "altitude": 198.5}})


def test_round_trip(tmp_path):
    scene = make_scene(np.random.default_rng(0))
    p = write_opensfm(scene, tmp_path / "reconstruction.json")
    back = read_opensfm(p)
    for name, rec in scene.images.items():
        np.testing.assert_allclose(back.images[name].cam_from_world.matrix, rec.cam_from_world.matrix,
                                   atol=1e-12, rtol=0)
        assert back.images[name].camera_id == rec.camera_id
    for k, cam in scene.cameras.items():
        b = back.cameras[k]
        np.testing.assert_allclose([b.fx, b.fy, b.cx, b.cy], [cam.fx, cam.fy, cam.cx, cam.cy], atol=1e-9)
        np.testing.assert_allclose(b.dist, cam.dist, atol=1e-15)
    np.testing.assert_array_equal(back.points, scene.points)
    np.testing.assert_array_equal(back.colors, scene.colors)
    assert back.meta["reference_lla"] == scene.meta["reference_lla"]
    data = json.loads(p.read_text())
    kinds = {v["projection_type"] for v in data[0]["cameras"].values()}
    assert kinds == {"perspective", "brown"}
    # Writing the read scene keeps the camera keys.
    again = read_opensfm(write_opensfm(back, tmp_path / "r2.json"))
    assert again.meta["opensfm_camera_ids"] == back.meta["opensfm_camera_ids"]


def opensfm_project(cam_obj: dict, X: np.ndarray) -> np.ndarray:
    """OpenSfM's brown projection then ``denormalized_image_coordinates``, written out independently."""
    w, h = cam_obj["width"], cam_obj["height"]
    size = max(w, h)
    x, y = X[:, 0] / X[:, 2], X[:, 1] / X[:, 2]
    r2 = x * x + y * y
    rad = 1 + r2 * (cam_obj["k1"] + r2 * (cam_obj["k2"] + r2 * cam_obj["k3"]))
    xd = x * rad + 2 * cam_obj["p1"] * x * y + cam_obj["p2"] * (r2 + 2 * x * x)
    yd = y * rad + 2 * cam_obj["p2"] * x * y + cam_obj["p1"] * (r2 + 2 * y * y)
    xn = cam_obj["focal_x"] * xd + cam_obj["c_x"]
    yn = cam_obj["focal_y"] * yd + cam_obj["c_y"]
    return np.stack([xn * size - 0.5 + w / 2.0, yn * size - 0.5 + h / 2.0], axis=1)


def test_normalised_intrinsics_and_pixel_convention():
    obj = {"projection_type": "brown", "width": 4000, "height": 3000, "focal_x": 0.75, "focal_y": 0.76,
           "c_x": 0.01, "c_y": -0.02, "k1": -0.1, "k2": 0.03, "p1": 0.001, "p2": -0.002, "k3": 0.004}
    cam = camera_from_opensfm(obj)
    assert (cam.fx, cam.fy) == (3000.0, 3040.0)
    assert (cam.cx, cam.cy) == (0.01 * 4000 + 1999.5, -0.02 * 4000 + 1499.5)
    X = np.array([[0.3, -0.2, 2.0], [-0.4, 0.35, 1.5], [0.0, 0.0, 1.0]])
    uv, _ = cam.project(X)
    np.testing.assert_allclose(opensfm_project(obj, X), uv, atol=1e-9)  # same pixels, no shift
    persp = camera_from_opensfm({"projection_type": "perspective", "width": 100, "height": 50,
                                 "focal": 0.9, "k1": 0.1})
    assert (persp.fx, persp.cx, persp.cy, persp.dist[0]) == (90.0, 49.5, 24.5, 0.1)
    assert camera_to_opensfm(persp)["projection_type"] == "perspective"
    radial = camera_from_opensfm({"projection_type": "simple_radial", "width": 100, "height": 50,
                                  "focal_x": 0.9, "focal_y": 0.9, "c_x": 0.0, "c_y": 0.0, "k1": 0.2})
    assert radial.dist == (0.2, 0.0, 0.0, 0.0, 0.0)


def test_ecef_from_enu():
    lat, lon, alt = 46.84, -91.99, 198.5
    T = ecef_from_enu(lat, lon, alt)
    to_ecef = Transformer.from_crs("EPSG:4979", "EPSG:4978", always_xy=True)
    np.testing.assert_allclose(T([0.0, 0.0, 0.0]), to_ecef.transform(lon, lat, alt), atol=1e-6)
    # 100 m up is 100 m more ellipsoidal height; 100 m north raises latitude by ~0.0009 degrees.
    np.testing.assert_allclose(T([0.0, 0.0, 100.0]), to_ecef.transform(lon, lat, alt + 100.0), atol=1e-6)
    to_lla = Transformer.from_crs("EPSG:4978", "EPSG:4979", always_xy=True)
    lo, la, h = to_lla.transform(*T([0.0, 100.0, 0.0]))
    assert 0.0008 < la - lat < 0.00095 and abs(lo - lon) < 1e-9 and 0.0 < h - alt < 0.01
    lo, la, h = to_lla.transform(*T([100.0, 0.0, 0.0]))
    assert lo > lon and abs(la - lat) < 1e-6


def test_bad_files(tmp_path):
    p = tmp_path / "reconstruction.json"
    p.write_text('[{"cameras": {},\n "shots": {')
    with pytest.raises(InputError, match="not valid JSON") as ei:
        read_opensfm(p)
    assert ei.value.line == 2
    p.write_text(json.dumps([{"cameras": {"c": {"projection_type": "fisheye", "width": 10, "height": 10,
                                                "focal": 1.0}}, "shots": {}}]))
    with pytest.raises(InputError, match="camera 'c'.*fisheye"):
        read_opensfm(p)
    p.write_text('[{"cameras": {"c": {"projection_type": "perspective", "width": 10, "height": 10, '
                 '"focal": 1.0}}, "shots": {"a.jpg": {"camera": "c", "rotation": [0, NaN, 0], '
                 '"translation": [0, 0, 0]}}}]')
    with pytest.raises(InputError, match=r"shots\['a.jpg'\].rotation\[1\] is not finite"):
        read_opensfm(p)
    p.write_text('[{"cameras": {}, "shots": {"a.jpg": {"camera": "x", "rotation": [0, 0, 0]}}}]')
    with pytest.raises(InputError, match="camera 'x'"):
        read_opensfm(p)
    p.write_text('{"type": "FeatureCollection"}')
    with pytest.raises(InputError, match="not an OpenSfM"):
        read_opensfm(p)


def test_read_reconstruction_detects_odm_project(tmp_path):
    scene = make_scene(np.random.default_rng(3))
    write_opensfm(scene, tmp_path / "odm" / "opensfm" / "reconstruction.json")
    got = read_reconstruction(tmp_path / "odm")
    assert got.meta["format"] == "opensfm" and list(got.images) == list(scene.images)
    assert read_reconstruction(tmp_path / "odm" / "opensfm" / "reconstruction.json").meta["format"] == "opensfm"
    write_opensfm(Scene(scene.cameras, {}), tmp_path / "empty.json")
    with pytest.raises(InputError, match="no registered"):
        read_reconstruction(tmp_path / "empty.json")


def test_same_pixels_through_every_format(tmp_path):
    """A 3D point projects to the same OpenCV pixel after a trip through COLMAP (text and binary),
    Metashape and OpenSfM: every pixel-convention and distortion conversion is consistent."""
    from cpdetect.formats.colmap import read_colmap, write_colmap
    from cpdetect.formats.metashape import read_metashape_cameras, write_metashape_cameras

    rng = np.random.default_rng(9)
    scene = make_scene(rng)
    for rec in scene.images.values():  # cameras 60 m from the origin, looking at it
        z = -rng.normal(size=3)
        z /= np.linalg.norm(z)
        x = np.cross([0.0, 0.0, 1.0], z)
        x /= np.linalg.norm(x)
        R = np.stack([x, np.cross(z, x), z])
        rec.cam_from_world = Rigid3(R, -R @ (-60.0 * z))
    X = rng.normal(size=(30, 3)) * 5
    trips = {
        "colmap-text": lambda: read_colmap(write_colmap(scene, tmp_path / "ct")),
        "colmap-bin": lambda: read_colmap(write_colmap(scene, tmp_path / "cb", binary=True)),
        "metashape": lambda: read_metashape_cameras(write_metashape_cameras(scene, tmp_path / "m.xml")),
        "opensfm": lambda: read_opensfm(write_opensfm(scene, tmp_path / "o.json")),
    }
    for fmt, trip in trips.items():
        back = trip()
        for name in scene.images:
            uv0, ok0 = scene.project(name, X)
            uv1, ok1 = back.project(name, X)
            assert ok0.sum() >= 10, fmt
            np.testing.assert_array_equal(ok1, ok0)
            np.testing.assert_allclose(uv1, uv0, atol=1e-8, err_msg=fmt)
