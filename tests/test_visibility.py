"""Depth tests: a small square in front of a large back plane, seen by a camera on the axis."""
import numpy as np
import pytest

from geometry.camera import Camera
from geometry.raycast import cast, detection_rays, make_raycasting_scene
from geometry.transforms import Rigid3
from geometry.visibility import mesh_depth_map, visible_points, zbuffer_depth_map

CAM = Camera(640, 480, 500.0, 500.0, 319.5, 239.5)
POSE = Rigid3.identity()  # camera at the origin looking along +z


def _quad(x0, x1, y0, y1, z):
    v = np.array([[x0, y0, z], [x1, y0, z], [x1, y1, z], [x0, y1, z]], float)
    return v, np.array([[0, 1, 2], [0, 2, 3]])


def _scene():
    v1, t1 = _quad(-1, 1, -1, 1, 5.0)        # occluder, 2 x 2 at depth 5
    v2, t2 = _quad(-10, 10, -10, 10, 10.0)   # back plane at depth 10
    return make_raycasting_scene(vertices=np.vstack([v1, v2]), triangles=np.vstack([t1, t2 + 4]))


def _grid(half, z, step):
    g = np.arange(-half + step / 2, half, step)
    x, y = np.meshgrid(g, g)
    return np.column_stack([x.ravel(), y.ravel(), np.full(x.size, z)])


def _truth_visible(P):
    """Back-plane points are hidden iff their ray passes through the occluder (|x|, |y| < 1 at z = 5)."""
    at5 = P[:, :2] * (5.0 / P[:, 2:3])
    hidden = (P[:, 2] > 5.5) & (np.abs(at5) < 1.0).all(axis=1)
    return ~hidden


def test_mesh_depth_map_is_exact_on_fronto_parallel_planes():
    dm = mesh_depth_map(_scene(), CAM, POSE, max_side=320)
    assert dm.depth.shape == (240, 320) and dm.scale == pytest.approx(0.5)
    # centre pixel sees the occluder, a corner the back plane (3.8 units off-axis at depth 10 is inside)
    assert dm.lookup(np.array([[319.5, 239.5]]))[0] == pytest.approx(5.0, abs=1e-4)
    assert dm.lookup(np.array([[10.0, 10.0]]))[0] == pytest.approx(10.0, abs=1e-3)
    assert np.isinf(dm.lookup(np.array([[-50.0, 10.0]]))[0])  # outside the map


@pytest.mark.parametrize("kind", ["mesh", "zbuffer"])
def test_occluded_points_are_not_visible(kind):
    front = _grid(1.0, 5.0, 0.02)
    back = _grid(3.0, 10.0, 0.02)
    P = np.vstack([front, back])
    if kind == "mesh":
        dm = mesh_depth_map(_scene(), CAM, POSE, max_side=320)
    else:
        dm = zbuffer_depth_map(P, CAM, POSE, max_side=320, fill_px=1)
    vis = visible_points(P, CAM, POSE, dm, rel_tol=0.02)
    truth = _truth_visible(P)
    # all front points visible; back points hidden exactly where the occluder covers them, except a
    # thin band at the occluder's silhouette whose width is one or two depth-map cells
    assert vis.visible[: len(front)].all()
    disagree = vis.visible != truth
    band = np.abs(np.abs(P[:, :2] * (5.0 / P[:, 2:3])).max(axis=1) - 1.0) < 0.05
    assert not (disagree & ~band).any()
    assert disagree.sum() <= 0.2 * band.sum()
    # without a depth map every back point in the frustum counts as visible (the frustum test only)
    assert visible_points(P, CAM, POSE).visible.sum() > vis.visible.sum() + 0.8 * (~truth).sum()


def test_points_behind_camera_and_outside_image_are_not_visible():
    P = np.array([[0, 0, -5.0], [100, 0, 5.0], [0.1, 0.1, 5.0]])
    vis = visible_points(P, CAM, POSE)
    assert vis.visible.tolist() == [False, False, True]


def test_ray_cast_hits_the_nearest_surface():
    scene = _scene()
    pose = Rigid3(np.eye(3), np.array([0.2, -0.1, 0.0]))  # camera centre at (-0.2, 0.1, 0)
    uv_front = CAM.project(pose(np.array([[0.3, 0.4, 5.0]])))[0]
    uv_back = CAM.project(pose(np.array([[4.0, -3.0, 10.0]])))[0]
    o, d = detection_rays(CAM, pose, np.vstack([uv_front, uv_back]))
    hits = cast(scene, o, d)
    assert hits.hit.all()
    np.testing.assert_allclose(hits.points, [[0.3, 0.4, 5.0], [4.0, -3.0, 10.0]], atol=1e-4)
    np.testing.assert_allclose(np.abs(hits.normals[:, 2]), 1.0, atol=1e-6)
    miss = cast(scene, np.zeros((1, 3)), np.array([[0.0, 0.0, -1.0]]))
    assert not miss.hit[0] and np.isnan(miss.points).all()
