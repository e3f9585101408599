"""Multi-view triangulation: exact on exact data, noise-consistent RMS and covariance, robust to outliers."""
import numpy as np
import pytest

from geometry.camera import Camera
from geometry.transforms import Rigid3
from geometry.triangulate import Observation, dlt, triangulate

CAM = Camera(1200, 900, 1000.0, 1000.0, 599.5, 449.5)
CAM_DIST = Camera(1200, 900, 1000.0, 1010.0, 610.0, 440.0, dist=(-0.12, 0.05, 0.001, -0.0005, 0.0))
X_TRUE = np.array([0.3, -0.2, 0.1])


def look_at(center, target, up=(0.0, 0.0, 1.0)) -> Rigid3:
    z = np.asarray(target, float) - center
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    return Rigid3(R, -R @ np.asarray(center, float))


def ring(n, radius=10.0, height=6.0):
    poses = []
    for a in np.linspace(0, 2 * np.pi, n, endpoint=False):
        c = np.array([radius * np.cos(a), radius * np.sin(a), height])
        poses.append(look_at(c, np.zeros(3)))
    return poses


def observe(X, poses, cam, sigma=0.0, rng=None):
    obs = []
    for k, pose in enumerate(poses):
        uv = cam.project(pose(X[None]))[0][0]
        if sigma > 0:
            uv = uv + rng.normal(0, sigma, 2)
        obs.append(Observation(cam, pose, uv, max(sigma, 0.3), f"im{k}"))
    return obs


@pytest.mark.parametrize("cam", [CAM, CAM_DIST])
def test_exact_observations_give_the_exact_point(cam):
    obs = observe(X_TRUE, ring(6), cam)
    np.testing.assert_allclose(dlt(obs), X_TRUE, atol=1e-9)
    res = triangulate(obs)
    assert res.ok and res.inliers.all()
    np.testing.assert_allclose(res.point, X_TRUE, atol=1e-8)
    assert res.rms_px < 1e-5


def test_noisy_rms_and_error_match_the_injected_noise():
    rng = np.random.default_rng(7)
    sigma = 0.5
    errs, rms, maha = [], [], []
    for _ in range(120):
        obs = observe(X_TRUE, ring(12), CAM, sigma, rng)
        res = triangulate(obs, loss="huber")
        assert res.ok and res.inliers.all()
        d = res.point - X_TRUE
        errs.append(np.linalg.norm(d))
        rms.append(res.rms_px)
        maha.append(d @ np.linalg.solve(res.covariance, d))
    # residual vector length RMS ~ sigma * sqrt(2 (2n - 3) / (2n)) = 0.68 px for n = 12
    assert 0.55 < np.mean(rms) < 0.8
    # 1-sigma ground error at ~11.7 units and f = 1000: about 0.5 * 11.7 / 1000 / sqrt(12 / 2) = 2.4e-3
    assert 1e-3 < np.sqrt(np.mean(np.square(errs))) < 5e-3
    # the covariance is calibrated: E[d^T C^-1 d] = 3
    assert 2.4 < np.mean(maha) < 4.5  # s0^2 is estimated: 3 * F(3, 21) has mean 3.3


@pytest.mark.parametrize("loss", ["huber", "cauchy"])
def test_gross_outliers_are_flagged_and_do_not_pull_the_point(loss):
    rng = np.random.default_rng(1)
    obs = observe(X_TRUE, ring(10), CAM, 0.3, rng)
    bad = [2, 7]
    for k in bad:
        o = obs[k]
        obs[k] = Observation(o.camera, o.cam_from_world, o.uv + np.array([40.0, -25.0]), o.sigma_px, o.image)
    res = triangulate(obs, loss=loss)
    assert res.ok
    assert res.inliers.tolist() == [k not in bad for k in range(10)]
    assert np.linalg.norm(res.point - X_TRUE) < 3e-3
    assert 0.1 < res.rms_px < 0.8
    assert np.linalg.norm(res.residuals_px[bad], axis=1).min() > 20


def test_degenerate_inputs_fail_with_a_reason():
    single = observe(X_TRUE, ring(1), CAM)
    res = triangulate(single)
    assert not res and "fewer than two" in res.reason
    # two views from (almost) the same place: no baseline
    p = look_at(np.array([10.0, 0, 6]), np.zeros(3))
    q = look_at(np.array([10.0, 0.001, 6]), np.zeros(3))
    res = triangulate(observe(X_TRUE, [p, q], CAM))
    assert not res.ok and res.reason
    with pytest.raises(ValueError):
        dlt(single)


def test_bundle_adjustment_pulls_perturbed_poses_towards_the_truth():
    from scipy.spatial.transform import Rotation

    from geometry.adjust import MarkerObservation, bundle_adjust

    rng = np.random.default_rng(5)
    pts = rng.uniform(-2, 2, (8, 3))
    true_poses = {f"im{k}": p for k, p in enumerate(ring(16, radius=12.0))}
    sig_rot, sig_pos, sig_px = 2e-3, 0.03, 0.3
    noisy = {}
    for n, p in true_poses.items():
        R = Rotation.from_rotvec(rng.normal(0, sig_rot, 3)).as_matrix() @ p.R
        C = p.center + rng.normal(0, sig_pos, 3)
        noisy[n] = Rigid3(R, -R @ C)
    cams = {n: CAM for n in true_poses}
    obs, per_point = [], [[] for _ in pts]
    for n, p in true_poses.items():
        uv = CAM.project(p(pts))[0] + rng.normal(0, sig_px, (len(pts), 2))
        for j in range(len(pts)):
            obs.append(MarkerObservation(j, n, uv[j], sig_px))
            per_point[j].append(Observation(CAM, noisy[n], uv[j], 3.0, n))  # pose noise: ~2 px
    start = np.array([triangulate(o).point for o in per_point])
    res = bundle_adjust(start, obs, noisy, cams, sigma_rot_rad=sig_rot, sigma_pos=sig_pos)
    assert res.success
    before = np.sqrt(np.mean([np.sum((CAM.project(noisy[o.image](pts[o.point][None]))[0][0] - o.uv) ** 2)
                              for o in obs]))
    after = float(np.sqrt(np.nanmean(res.rms_px ** 2)))
    assert after < 0.6 * before  # poses absorbed most of their perturbation
    assert 0.5 * sig_px < after < 2.0 * sig_px
    rot_err = lambda poses: np.mean([np.linalg.norm(Rotation.from_matrix(poses[n].R @ true_poses[n].R.T)
                                                    .as_rotvec()) for n in true_poses])
    assert rot_err(res.poses) < 0.7 * rot_err(noisy)
    # the datum is held by the pose priors: markers stay within a few prior sigmas of the truth
    assert np.abs(res.points - pts).max() < 3 * sig_pos
    assert np.all(np.isfinite(res.covariance)) and np.all(np.linalg.eigvalsh(res.covariance) > 0)


def test_pixel_floor_of_the_outlier_threshold_keeps_views_with_pose_errors():
    rng = np.random.default_rng(3)
    obs = observe(X_TRUE, ring(8), CAM, 0.0)
    # every view off by 2..4 px (as from pose errors of the reconstruction), sigma claims 0.3 px
    obs = [Observation(o.camera, o.cam_from_world, o.uv + rng.uniform(2, 4) * np.array([np.cos(a), np.sin(a)]),
                       0.3, o.image) for o, a in zip(obs, rng.uniform(0, 2 * np.pi, 8))]
    strict = triangulate(obs, outlier_sigma=6.0)
    tolerant = triangulate(obs, outlier_sigma=6.0, outlier_px=10.0)
    assert strict.n_inliers < 8
    assert tolerant.ok and tolerant.n_inliers == 8
    assert 2.0 < tolerant.rms_px < 4.0
    assert np.linalg.norm(tolerant.point - X_TRUE) < 0.06  # one view's 3 px is 0.035 units at this range
