"""PLY: double-precision point output, similarity applied to clouds and meshes, bad files."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from cpdetect.errors import InputError
from cpdetect.formats.ply import read_ply_points, transform_ply, write_ply_points
from cpdetect.formats.colmap import write_colmap
from cpdetect.formats.reconstruction import read_reconstruction
from geometry.camera import Camera
from geometry.scene import ImageRecord, Scene
from geometry.transforms import Rigid3, Sim3

o3d = pytest.importorskip("open3d")

SIM = Sim3(2.5, Rotation.from_rotvec([0.1, -0.4, 1.2]).as_matrix(), [651_000.0, 5_237_000.0, 120.0])


def test_write_points_keeps_float64_at_utm_magnitudes(tmp_path):
    rng = np.random.default_rng(0)
    xyz = np.array([500_000.0, 5_700_000.0, 100.0]) + rng.uniform(-500, 500, (50, 3))
    xyz += 1e-4 * rng.uniform(size=(50, 3))  # sub-millimetre detail a float32 file would lose
    rgb = rng.integers(0, 256, (50, 3)).astype(np.uint8)
    nrm = rng.normal(size=(50, 3))
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    p = write_ply_points(tmp_path / "c.ply", xyz, rgb, nrm, comments=("test",))
    back = read_ply_points(p)
    np.testing.assert_array_equal(back.xyz, xyz)
    np.testing.assert_array_equal(back.rgb, rgb)
    np.testing.assert_allclose(back.normals, nrm, atol=1e-7)
    assert b"property double x" in p.read_bytes()[:300]
    pc = o3d.io.read_point_cloud(str(p))  # other tools read it the same way
    np.testing.assert_array_equal(np.asarray(pc.points), xyz)
    with pytest.raises(ValueError, match="uint8"):
        write_ply_points(tmp_path / "bad.ply", xyz, rgb.astype(float))
    assert not (tmp_path / "bad.ply").exists()


def test_transform_mesh_written_by_open3d(tmp_path):
    mesh = o3d.geometry.TriangleMesh.create_box(2.0, 3.0, 1.0)
    mesh.compute_vertex_normals()
    mesh.vertex_colors = o3d.utility.Vector3dVector(np.random.default_rng(1).uniform(size=(8, 3)))
    src = tmp_path / "mesh.ply"
    o3d.io.write_triangle_mesh(str(src), mesh, write_ascii=False, write_vertex_normals=True)
    before = read_ply_points(src)
    out = transform_ply(src, SIM, tmp_path / "geo" / "mesh.ply")
    after = read_ply_points(out)
    np.testing.assert_allclose(after.xyz, SIM(before.xyz), atol=1e-9, rtol=0)
    np.testing.assert_array_equal(after.rgb, before.rgb)
    np.testing.assert_allclose(after.normals, before.normals @ SIM.R.T, atol=1e-6)
    m2 = o3d.io.read_triangle_mesh(str(out))
    np.testing.assert_array_equal(np.asarray(m2.triangles), np.asarray(mesh.triangles))
    # Edge lengths scale by s (a similarity), whatever the rotation.
    e0 = np.linalg.norm(before.xyz[1] - before.xyz[0])
    assert np.linalg.norm(after.xyz[1] - after.xyz[0]) == pytest.approx(2.5 * e0, abs=1e-8)  # ulp at 5e6 m is 1e-9


def test_transform_ascii_with_faces_and_extra_properties(tmp_path):
    src = tmp_path / "a.ply"
    src.write_text("ply\nformat ascii 1.0\ncomment hand made\nelement vertex 3\n"
                   "property float x\nproperty float y\nproperty float z\nproperty uchar class\n"
                   "element face 1\nproperty list uchar int vertex_indices\nend_header\n"
                   "0 0 0 2\n1 0 0 2\n0 1 0 7\n3 0 1 2\n")
    out = transform_ply(src, SIM, tmp_path / "b.ply")
    text = out.read_text().splitlines()
    assert "property double x" in text and "property uchar class" in text and text[-1] == "3 0 1 2"
    assert [l.split()[-1] for l in text[-4:-1]] == ["2", "2", "7"]
    back = read_ply_points(out)
    np.testing.assert_allclose(back.xyz, SIM(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0.0]])), atol=1e-9)


def test_transform_big_endian_keeps_format(tmp_path):
    xyz = np.array([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]], ">f4")
    src = tmp_path / "be.ply"
    src.write_bytes(b"ply\nformat binary_big_endian 1.0\nelement vertex 2\nproperty float x\n"
                    b"property float y\nproperty float z\nend_header\n" + xyz.tobytes())
    out = transform_ply(src, SIM, tmp_path / "be2.ply")
    assert b"binary_big_endian" in out.read_bytes()[:60]
    np.testing.assert_allclose(read_ply_points(out).xyz, SIM(xyz.astype(float)), atol=1e-9)


@pytest.mark.parametrize("content, match, line", [
    (b"PK\x03\x04 zip", "not a PLY", 1),
    (b"ply\nformat binary_little_endian 1.0\nelement vertex 10\nproperty double x\nproperty double y\n"
     b"property double z\nend_header\n" + b"\0" * 100, "truncated", None),
    (b"ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\nproperty float z\n"
     b"end_header\n1 2 3\n", "truncated", 9),
    (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nproperty float z\n"
     b"end_header\n1 nan 3\n", "non-finite", None),
    (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\n"
     b"end_header\n1 2\n", "no x, y, z", 3),
    (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nproperty float z\n", "end_header", None),
])
def test_bad_files(tmp_path, content, match, line):
    p = tmp_path / "bad.ply"
    p.write_bytes(content)
    with pytest.raises(InputError, match=match) as ei:
        read_ply_points(p)
    assert ei.value.path == str(p) and ei.value.line == line
    with pytest.raises(InputError):
        transform_ply(p, SIM, tmp_path / "out.ply")
    assert not (tmp_path / "out.ply").exists()


def test_read_reconstruction_with_cloud_and_mesh(tmp_path):
    scene = Scene({1: Camera(100, 80, 90.0, 90.0, 49.5, 39.5)}, {"a.jpg": ImageRecord("a.jpg", 1, Rigid3.identity())})
    write_colmap(scene, tmp_path / "m")
    xyz = np.array([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]])
    cloud = write_ply_points(tmp_path / "dense.ply", xyz, np.array([[1, 2, 3], [4, 5, 6]], np.uint8))
    (tmp_path / "mesh.ply").write_bytes(cloud.read_bytes())
    got = read_reconstruction(tmp_path / "m", cloud=cloud, mesh=tmp_path / "mesh.ply")
    np.testing.assert_array_equal(got.points, xyz)
    np.testing.assert_array_equal(got.colors, [[1, 2, 3], [4, 5, 6]])
    assert got.mesh_path == str(tmp_path / "mesh.ply") and got.normals is None
    with pytest.raises(InputError, match="mesh file not found"):
        read_reconstruction(tmp_path / "m", mesh=tmp_path / "none.ply")
