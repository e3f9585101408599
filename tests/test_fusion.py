"""Cloud colorization and clustering on analytic scenes: planes, known markers, known weights."""
import numpy as np
import pytest

from geometry.camera import Camera
from geometry.clustering import cluster_points, dbscan_params, point_spacing
from geometry.fusion import FusionView, fuse_scores, sample_bilinear, view_weights
from geometry.raycast import make_raycasting_scene
from geometry.transforms import Rigid3
from geometry.visibility import mesh_depth_map

CAM = Camera(400, 300, 400.0, 400.0, 199.5, 149.5)


def look_at(center, target, up=(0.0, -1.0, 0.0)) -> Rigid3:
    """cam_from_world of a camera at ``center`` looking at ``target`` (y down)."""
    z = np.asarray(target, float) - center
    z /= np.linalg.norm(z)
    x = np.cross(up, z)
    if np.linalg.norm(x) < 1e-9:
        x = np.cross((1.0, 0.0, 0.0), z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    return Rigid3(R, -R @ np.asarray(center, float))


def test_sample_bilinear_matches_a_linear_ramp_at_any_map_resolution():
    W, H = 400, 300
    # a ramp defined on full-image pixel coordinates, stored at quarter resolution (cv2.resize centres)
    w, h = 100, 75
    xs = (np.arange(w) + 0.5) * (W / w) - 0.5
    ys = (np.arange(h) + 0.5) * (H / h) - 0.5
    ramp = (0.001 * xs[None, :] + 0.002 * ys[:, None]).astype(np.float32)
    uv = np.array([[10.3, 20.7], [200.0, 150.0], [390.1, 280.9]])
    np.testing.assert_allclose(sample_bilinear(ramp, uv, (W, H)), 0.001 * uv[:, 0] + 0.002 * uv[:, 1],
                               atol=1e-5)


def test_weight_is_pixel_footprint_of_unit_area():
    P = np.array([[0.0, 0.0, 4.0], [0.0, 0.0, 8.0], [0.0, 0.0, 4.0]])
    n = np.array([[0.0, 0.0, -1.0], [0.0, 0.0, 1.0], [0.0, np.sin(1.2), -np.cos(1.2)]])
    w = view_weights(P, CAM, n, min_cos=0.2)
    np.testing.assert_allclose(w, [400 * 400 / 16, 400 * 400 / 64, 400 * 400 / 16 * np.cos(1.2)])
    assert view_weights(P[2:], CAM, n[2:], min_cos=0.5)[0] == 0.0  # grazing view dropped


def test_fused_score_is_the_weighted_mean_of_view_probabilities():
    P = np.array([[0.0, 0.0, 0.0], [0.5, 0.2, 0.0]])
    normals = np.array([[0.0, 0.0, 1.0]] * 2)
    near = look_at(np.array([0.0, 0.0, -3.0]), np.zeros(3))
    far = look_at(np.array([4.0, 0.0, -6.0]), np.zeros(3))
    views = [FusionView(CAM, near, np.full((30, 40), 0.9, np.float32)),
             FusionView(CAM, far, np.full((30, 40), 0.1, np.float32))]
    res = fuse_scores(P, views, normals)
    w1 = view_weights(near(P), CAM, normals @ near.R.T, 0.2)
    w2 = view_weights(far(P), CAM, normals @ far.R.T, 0.2)
    np.testing.assert_allclose(res.score, (0.9 * w1 + 0.1 * w2) / (w1 + w2), rtol=1e-5)
    assert (res.score > 0.5).all()  # the closer, more frontal view dominates
    np.testing.assert_array_equal(res.n_views, [2, 2])


def _render_marker_probability(cam, pose, centre, radius, shape=(75, 100)):
    """Probability 1 inside the projection of a disc of ``radius`` around ``centre`` on z = 0."""
    h, w = shape
    xs = (np.arange(w) + 0.5) * (cam.width / w) - 0.5
    ys = (np.arange(h) + 0.5) * (cam.height / h) - 0.5
    ang = np.linspace(0, 2 * np.pi, 64, endpoint=False)
    rim = centre + radius * np.column_stack([np.cos(ang), np.sin(ang), np.zeros_like(ang)])
    uv = cam.project(pose(rim))[0]
    c = cam.project(pose(centre[None]))[0][0]
    rpx = np.linalg.norm(uv - c, axis=1).mean()
    X, Y = np.meshgrid(xs, ys)
    return ((X - c[0]) ** 2 + (Y - c[1]) ** 2 <= rpx ** 2).astype(np.float32)


def test_colorize_and_cluster_recovers_markers_and_ignores_occluded_points():
    rng = np.random.default_rng(3)
    # ground plane z = 0 (normal +z towards the cameras at z < 0 ... cameras look down +z from z = -6)
    g = np.arange(-3, 3, 0.03)
    X, Y = np.meshgrid(g, g)
    ground = np.column_stack([X.ravel(), Y.ravel(), np.zeros(X.size)])
    ground[:, :2] += rng.uniform(-0.005, 0.005, (len(ground), 2))
    markers = np.array([[-1.5, -1.0, 0.0], [1.2, 0.8, 0.0], [0.3, -1.8, 0.0]])
    # a roof (plane z = -1.5 over x in [-2.5, -0.5], y in [-2, 0]) hides marker 0 from every camera
    roof_v = np.array([[-2.5, -2.0, -1.5], [-0.5, -2.0, -1.5], [-0.5, 0.0, -1.5], [-2.5, 0.0, -1.5]])
    ground_v = np.array([[-4, -4, 0.0], [4, -4, 0], [4, 4, 0], [-4, 4, 0]])
    tri = np.array([[0, 1, 2], [0, 2, 3]])
    rc = make_raycasting_scene(vertices=np.vstack([roof_v, ground_v]), triangles=np.vstack([tri, tri + 4]))
    views = []
    hidden = np.ones(len(ground), bool)
    for cx, cy in [(-1, -1), (1, -1), (-1, 1), (1, 1), (0, 0)]:
        pose = look_at(np.array([cx, cy, -6.0]), np.array([0.3 * cx, 0.3 * cy, 0.0]))
        prob = np.zeros((75, 100), np.float32)
        for m in markers[1:]:  # the detector sees the two unoccluded markers only ...
            prob = np.maximum(prob, _render_marker_probability(CAM, pose, m, 0.15))
        # ... and "sees" marker 0 through the roof: a false response that only the depth test removes
        prob = np.maximum(prob, _render_marker_probability(CAM, pose, markers[0], 0.15))
        views.append(FusionView(CAM, pose, prob, mesh_depth_map(rc, CAM, pose, max_side=200)))
        # analytic shadow of the roof seen from this camera, shrunk by 0.05 to stay off its edges
        at_roof = np.array([cx, cy]) + 0.75 * (ground[:, :2] - [cx, cy])
        hidden &= ((at_roof[:, 0] > -2.45) & (at_roof[:, 0] < -0.55) & (at_roof[:, 1] > -1.95)
                   & (at_roof[:, 1] < -0.05))
    normals = np.tile([0.0, 0.0, -1.0], (len(ground), 1))
    res = fuse_scores(ground, views, normals)
    assert hidden.sum() > 500 and np.linalg.norm(ground[hidden, :2] - markers[0, :2], axis=1).min() < 0.02
    assert res.n_views[hidden].max() == 0 and res.score[hidden].max() == 0.0

    # the sparse path (candidates lifted from the marked pixels with the depth maps) agrees
    from geometry.fusion import fuse_scores_sparse

    sparse = fuse_scores_sparse(ground, views, normals)
    marked = res.score > 0
    assert marked.sum() > 200
    np.testing.assert_allclose(sparse.score[marked], res.score[marked], rtol=1e-9)
    assert not (sparse.score[~marked] > 0).any()
    assert (sparse.weight == 0).sum() > 0.8 * len(ground)  # most of the cloud was never touched

    spacing = point_spacing(ground, rng=np.random.default_rng(0))
    assert 0.02 < spacing < 0.035
    params = dbscan_params(spacing, marker_size=0.3)
    clusters = cluster_points(ground, res.score, params, threshold=0.5)
    assert len(clusters) == 2
    found = np.array(sorted((c.centroid for c in clusters), key=lambda c: c[0]))
    # centroids of a sampled disc: within a fraction of the point spacing of the truth
    np.testing.assert_allclose(found, markers[[2, 1]][np.argsort(markers[[2, 1]][:, 0])], atol=0.02)
    assert all(0.1 < c.extent < 0.25 for c in clusters)


def test_dbscan_params_scale_with_the_scene():
    a = dbscan_params(0.01, 0.3)
    b = dbscan_params(10.0, 300.0)  # the same scene in millimetres
    assert b.eps == pytest.approx(1000 * a.eps) and b.min_samples == a.min_samples
    with pytest.raises(ValueError):
        dbscan_params(0.0, 0.3)


def test_block_culling_gives_the_same_scores_as_projecting_every_point():
    from geometry.visibility import visible_points, zbuffer_depth_map

    rng = np.random.default_rng(4)
    P = np.column_stack([rng.uniform(-20, 20, 30000), rng.uniform(-20, 20, 30000), rng.normal(0, 0.3, 30000)])
    N = np.tile([0.0, 0.0, -1.0], (len(P), 1))
    cam = Camera(400, 300, 300.0, 300.0, 201.0, 148.0, dist=(-0.1, 0.02, 0.001, 0.0, 0.0))
    views = []
    for k in range(6):
        c = np.array([rng.uniform(-15, 15), rng.uniform(-15, 15), -8.0])
        pose = look_at(c, c + [rng.uniform(-4, 4), rng.uniform(-4, 4), 8.0])
        views.append(FusionView(cam, pose, rng.uniform(0, 1, (30, 40)).astype(np.float32),
                                zbuffer_depth_map(P, cam, pose, max_side=100)))
    res = fuse_scores(P, views, N, abs_tol=0.05)
    num, den, nv = np.zeros(len(P)), np.zeros(len(P)), np.zeros(len(P), int)
    for v in views:
        vis = visible_points(P, v.camera, v.cam_from_world, v.depth_map, rel_tol=0.02, abs_tol=0.05)
        i = np.flatnonzero(vis.visible)
        w = view_weights(v.cam_from_world(P[i]), cam, N[i] @ v.cam_from_world.R.T, 0.2)
        num[i] += w * sample_bilinear(v.probability, vis.uv[i], (cam.width, cam.height))
        den[i] += w
        nv[i] += w > 0
    assert 0.05 * len(P) < (nv > 0).sum() < 0.9 * len(P)  # the views see part of the cloud only
    np.testing.assert_array_equal(res.n_views, nv)
    np.testing.assert_allclose(res.weight, den, rtol=1e-9)
    np.testing.assert_allclose(res.score, np.divide(num, den, out=np.zeros_like(num), where=den > 0), atol=1e-6)
