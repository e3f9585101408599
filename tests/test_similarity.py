"""geometry.similarity: closed-form Umeyama/Horn similarity, weights, degeneracy results."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from geometry.similarity import degeneracy_reason, fit_similarity, fit_similarity_batch
from geometry.transforms import Sim3


def random_sim(rng, scale=None) -> Sim3:
    s = float(np.exp(rng.uniform(np.log(0.1), np.log(30)))) if scale is None else scale
    return Sim3(s, Rotation.random(random_state=rng).as_matrix(), rng.normal(0, 50, 3))


def assert_proper_rotation(R):
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert abs(np.linalg.det(R) - 1.0) < 1e-12


def test_exact_recovery_without_noise():
    rng = np.random.default_rng(0)
    truth = random_sim(rng)
    src = rng.normal(0, 5, (10, 3))
    fit = fit_similarity(src, truth(src))
    assert fit and fit.reason == ""
    assert abs(fit.sim.scale / truth.scale - 1) < 1e-12
    np.testing.assert_allclose(fit.sim.R, truth.R, atol=1e-12)
    np.testing.assert_allclose(fit.sim.t, truth.t, atol=1e-9)
    assert fit.rms < 1e-9
    assert_proper_rotation(fit.sim.R)


def test_tiny_analytic_case():
    # unit right triangle, scaled by 2, rotated 90 degrees about z, shifted by (1, 2, 3)
    src = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0.0]])
    dst = np.array([[1, 2, 3], [1, 4, 3], [-1, 2, 3.0]])
    fit = fit_similarity(src, dst)
    assert fit.sim.scale == pytest.approx(2.0, abs=1e-14)
    np.testing.assert_allclose(fit.sim.R, [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-14)
    np.testing.assert_allclose(fit.sim.t, [1, 2, 3], atol=1e-14)


def test_invariants_and_inverse_roundtrip():
    rng = np.random.default_rng(1)
    for _ in range(5):
        truth = random_sim(rng)
        src = rng.normal(0, 3, (8, 3))
        fit = fit_similarity(src, truth(src) + rng.normal(0, 0.01, (8, 3)))
        assert_proper_rotation(fit.sim.R)
        x = rng.normal(0, 100, (20, 3))
        np.testing.assert_allclose(fit.sim.inverse()(fit.sim(x)), x, atol=1e-9)


def test_noisy_residual_and_scale_error_bounded_both_sides():
    """rms ≈ σ·sqrt(3 − 7/n) and std(ŝ/s − 1) ≈ σ / (s·sqrt(Σ|x − x̄|²)) (first-order Umeyama)."""
    rng = np.random.default_rng(2)
    sigma, n = 0.01, 20
    src = rng.uniform(-5, 5, (n, 3))
    spread = np.sqrt(((src - src.mean(0)) ** 2).sum())
    truth = Sim3(2.0, Rotation.random(random_state=rng).as_matrix(), [100.0, -20, 5])
    rel_errs, rms = [], []
    for _ in range(300):
        fit = fit_similarity(src, truth(src) + rng.normal(0, sigma, (n, 3)))
        rel_errs.append(fit.sim.scale / truth.scale - 1)
        rms.append(fit.rms)
    predicted_scale_std = sigma / (truth.scale * spread)
    assert 0.8 * predicted_scale_std < np.std(rel_errs) < 1.2 * predicted_scale_std
    assert abs(np.mean(rel_errs)) < 4 * predicted_scale_std / np.sqrt(300)
    expected_rms = sigma * np.sqrt(3 - 7 / n)
    assert 0.9 * expected_rms < np.sqrt(np.mean(np.square(rms))) < 1.1 * expected_rms


def test_no_reflection_for_mirrored_data():
    rng = np.random.default_rng(3)
    src = rng.normal(0, 1, (6, 3))
    dst = src * [-1, 1, 1]  # a mirror image: no proper similarity fits it
    fit = fit_similarity(src, dst)
    assert fit
    assert_proper_rotation(fit.sim.R)
    assert fit.rms > 0.1


def test_symmetric_scale_inverts_exactly():
    rng = np.random.default_rng(4)
    truth = random_sim(rng)
    src = rng.normal(0, 2, (12, 3))
    dst = truth(src) + rng.normal(0, 0.05, (12, 3))
    fwd = fit_similarity(src, dst, scale_method="symmetric").sim
    bwd = fit_similarity(dst, src, scale_method="symmetric").sim
    assert fwd.scale * bwd.scale == pytest.approx(1.0, abs=1e-12)
    np.testing.assert_allclose((fwd @ bwd).matrix, np.eye(4), atol=1e-9)
    # Umeyama's scale is not symmetric with noise
    u = fit_similarity(src, dst).sim.scale * fit_similarity(dst, src).sim.scale
    assert u < 1.0 - 1e-6


def test_weights_zero_out_an_outlier():
    rng = np.random.default_rng(5)
    truth = random_sim(rng)
    src = rng.normal(0, 2, (7, 3))
    dst = truth(src)
    dst[3] += [5.0, 0, 0]
    w = np.ones(7)
    w[3] = 0
    fit = fit_similarity(src, dst, w)
    assert abs(fit.sim.scale / truth.scale - 1) < 1e-12
    assert fit.residuals[3] == pytest.approx(5.0, rel=1e-9)
    assert fit.rms < 1e-9  # weighted rms ignores the zero-weight point
    unweighted = fit_similarity(src, dst)
    assert unweighted.rms > 0.5


@pytest.mark.parametrize("points, word", [
    ([[0, 0, 0], [1, 0, 0]], "at least 3"),
    ([[0, 0, 0], [1, 1, 1], [2, 2, 2], [5, 5, 5]], "collinear"),
    ([[1, 2, 3]] * 4, "coincident"),
    ([[0, 0, 0], [1, 0, 0], [0, np.nan, 0]], "NaN"),
])
def test_degenerate_data_is_a_result_not_an_exception(points, word):
    pts = np.asarray(points, float)
    fit = fit_similarity(pts, pts * 2)
    assert not fit and fit.sim is None
    assert word in fit.reason
    assert word in (degeneracy_reason(pts) or "at least 3")


def test_near_collinear_within_noise_is_collinear():
    pts = np.array([[0, 0, 0], [1, 0, 0], [2, 0.001, 0], [3, 0, 0]])
    assert degeneracy_reason(pts, tol=0.0) == ""
    assert "collinear" in degeneracy_reason(pts, tol=0.01)


def test_bad_shapes_raise():
    with pytest.raises(ValueError):
        fit_similarity(np.zeros((4, 2)), np.zeros((4, 2)))
    with pytest.raises(ValueError):
        fit_similarity(np.zeros((4, 3)), np.zeros((5, 3)))


def test_large_coordinates_stay_exact_in_float64():
    """UTM-sized coordinates: the centring keeps sub-micrometre accuracy."""
    rng = np.random.default_rng(6)
    src = rng.uniform(-50, 50, (10, 3))
    truth = Sim3(0.5, Rotation.random(random_state=rng).as_matrix(), [512345.678, 5781234.567, 87.6])
    fit = fit_similarity(src, truth(src))
    assert np.abs(fit.sim(src) - truth(src)).max() < 1e-6


def test_batch_agrees_with_single_fits():
    rng = np.random.default_rng(7)
    src = rng.normal(0, 1, (50, 3, 3))
    dst = np.stack([random_sim(rng)(s) + rng.normal(0, 0.01, (3, 3)) for s in src])
    s, R, t = fit_similarity_batch(src, dst)
    for h in range(0, 50, 7):
        f = fit_similarity(src[h], dst[h]).sim
        assert s[h] == pytest.approx(f.scale, rel=1e-10)
        np.testing.assert_allclose(R[h], f.R, atol=1e-10)
        np.testing.assert_allclose(t[h], f.t, atol=1e-8)
    assert np.allclose(np.linalg.det(R), 1.0)
