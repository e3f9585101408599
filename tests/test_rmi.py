"""RMI loss: against a direct numpy computation on small tensors, its floor, masking and stability."""
from __future__ import annotations

import math

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from learned.rmi import POS_ALPHA, HMALossWeights, RMIStats, hma_loss, rmi_loss, rmi_term  # noqa: E402


def direct_rmi(probs: np.ndarray, onehot: np.ndarray, radius: int = 3, alpha: float = POS_ALPHA,
               pooled_batch: bool = False) -> float:
    """sum_k mean_n 0.5 logdet(Syy - Syp (Spp + aI)^-1 Syp^T + aI) / d with explicit window loops;
    pooled_batch: one covariance estimate per class from the windows of all images."""
    n, k, h, w = probs.shape
    d = radius * radius
    total = 0.0
    groups = [list(range(n))] if pooled_batch else [[b] for b in range(n)]
    for c in range(k):
        vals = []
        for group in groups:
            ys, ps = [], []
            for b, i in ((b, i) for b in group for i in range(h - radius + 1)):
                for j in range(w - radius + 1):
                    ys.append(onehot[b, c, i:i + radius, j:j + radius].ravel())
                    ps.append(probs[b, c, i:i + radius, j:j + radius].ravel())
            Y = np.array(ys, np.float64).T  # (d, M)
            P = np.array(ps, np.float64).T
            Y -= Y.mean(1, keepdims=True)
            P -= P.mean(1, keepdims=True)
            syy, spp, syp = Y @ Y.T, P @ P.T, Y @ P.T
            cond = syy - syp @ np.linalg.inv(spp + alpha * np.eye(d)) @ syp.T + alpha * np.eye(d)
            sign, logdet = np.linalg.slogdet(cond)
            assert sign > 0
            vals.append(0.5 * logdet / d)
        total += float(np.mean(vals))
    return total


def direct_bce(logits: np.ndarray, onehot: np.ndarray, valid: np.ndarray) -> float:
    p = 1.0 / (1.0 + np.exp(-logits.astype(np.float64)))
    ll = -(onehot * np.log(p) + (1 - onehot) * np.log(1 - p)) * valid[:, None]
    return float(ll.sum() / (valid.sum() + 1.0))


def _case(seed: int, n=2, k=2, h=11, w=13):
    rng = np.random.default_rng(seed)
    labels = (rng.random((n, h, w)) < 0.35).astype(np.int64)
    labels[:, 2:6, 3:8] = 1
    logits = rng.normal(0, 1.5, (n, k, h, w)).astype(np.float32)
    return labels, logits


def test_rmi_term_matches_direct_computation_without_pooling():
    labels, logits = _case(1)
    onehot = np.eye(2)[labels].transpose(0, 3, 1, 2)
    probs = 1.0 / (1.0 + np.exp(-logits.astype(np.float64))) + 1e-6
    got, ok = rmi_term(torch.from_numpy(probs.astype(np.float32)), torch.from_numpy(onehot.astype(np.float32)), pool=1)
    want = direct_rmi(probs.astype(np.float32).astype(np.float64), onehot)
    assert ok
    assert abs(float(got) - want) <= 1e-4 * max(1.0, abs(want))


@pytest.mark.parametrize("n", [1, 3])
def test_batch_pooled_rmi_matches_direct_computation_over_all_windows(n):
    labels, logits = _case(3, n=n)
    onehot = np.eye(2)[labels].transpose(0, 3, 1, 2)
    probs = (1.0 / (1.0 + np.exp(-logits.astype(np.float64))) + 1e-6).astype(np.float32)
    t_p, t_y = torch.from_numpy(probs), torch.from_numpy(onehot.astype(np.float32))
    got, ok = rmi_term(t_p, t_y, pool=1, pooled_batch=True)
    want = direct_rmi(probs.astype(np.float64), onehot, pooled_batch=True)
    assert ok
    assert abs(float(got) - want) <= 1e-4 * max(1.0, abs(want))
    per_image, _ = rmi_term(t_p, t_y, pool=1)
    if n == 1:  # one image: both scopes are the same estimate
        assert abs(float(per_image) - float(got)) <= 1e-6 * max(1.0, abs(want))
    else:  # pooling mixes images with other statistics: a different (larger) conditional variance
        assert abs(float(per_image) - float(got)) > 1e-3


def test_rmi_loss_matches_direct_bce_and_rmi_with_pooling():
    labels, logits = _case(2, h=24, w=28)
    labels[0, 0, :5] = 255  # ignored pixels
    t_logits = torch.from_numpy(logits)
    got = float(rmi_loss(t_logits, torch.from_numpy(labels), do_rmi=True, lam=0.5))
    valid = (labels < 2).astype(np.float64)
    onehot = np.eye(2)[np.where(labels < 2, labels, 0)].transpose(0, 3, 1, 2) * valid[:, None]
    bce = direct_bce(logits, onehot, valid)
    probs = (1.0 / (1.0 + np.exp(-logits.astype(np.float64)))) * valid[:, None] + 1e-6
    pooled_p = torch.nn.functional.avg_pool2d(torch.from_numpy(probs), 4, 4, padding=2).numpy()
    pooled_y = torch.nn.functional.avg_pool2d(torch.from_numpy(onehot), 4, 4, padding=2).numpy()
    want = 0.5 * bce + 0.5 * direct_rmi(pooled_p, pooled_y)
    assert abs(got - want) <= 1e-4 * max(1.0, abs(want))
    only_bce = float(rmi_loss(t_logits, torch.from_numpy(labels), do_rmi=False))
    assert abs(only_bce - bce) <= 1e-5 * bce


def test_absent_class_gives_the_floor_half_log_alpha_and_no_gradient():
    # a crop without markers: class 1 is constant (0), so Sigma_Y|P = a I and the term is 0.5 ln(a)
    rng = np.random.default_rng(3)
    onehot = torch.zeros(3, 1, 20, 20)
    logits = torch.tensor(rng.normal(0, 2, (3, 1, 20, 20)), dtype=torch.float32, requires_grad=True)
    value, ok = rmi_term(torch.sigmoid(logits) + 1e-6, onehot, pool=1)
    assert ok
    assert abs(float(value.detach()) - 0.5 * math.log(POS_ALPHA)) < 1e-6
    value.backward()
    assert float(logits.grad.abs().max()) < 1e-9


def test_ignored_pixels_do_not_change_the_loss():
    labels, logits = _case(4, h=32, w=32)
    labels[:, :8, :] = 255
    a = torch.from_numpy(logits.copy())
    b = a.clone()
    b[:, :, :8, :] = torch.randn(b[:, :, :8, :].shape) * 5.0
    la = float(rmi_loss(a, torch.from_numpy(labels)))
    lb = float(rmi_loss(b, torch.from_numpy(labels)))
    assert abs(la - lb) < 1e-6


def test_saturated_confident_predictions_stay_finite_in_float32():
    # the float32 Schur complement fails Cholesky here (hma.md 2.3); float64 must not
    labels = torch.zeros(4, 64, 64, dtype=torch.int64)
    labels[:, 16:40, 20:44] = 1
    onehot = torch.nn.functional.one_hot(labels, 2).permute(0, 3, 1, 2).float()
    logits = (onehot * 2 - 1) * 30.0
    stats = RMIStats()
    loss = rmi_loss(logits.requires_grad_(), labels, stats=stats)
    assert bool(torch.isfinite(loss.detach()))
    loss.backward()
    assert stats.calls == 1 and stats.cholesky_failures == 0


def test_better_predictions_have_lower_loss():
    labels, _ = _case(5, h=48, w=48)
    onehot = torch.nn.functional.one_hot(torch.from_numpy(labels), 2).permute(0, 3, 1, 2).float()
    good = (onehot * 2 - 1) * 4.0
    noisy = good + torch.from_numpy(np.random.default_rng(6).normal(0, 4, good.shape).astype(np.float32))
    lab = torch.from_numpy(labels)
    assert float(rmi_loss(good, lab)) < float(rmi_loss(noisy, lab)) - 0.1


@pytest.mark.parametrize("scope", ["batch", "image"])
def test_hma_loss_combines_parts_with_the_recipe_weights(scope):
    labels, logits = _case(7, h=32, w=32)
    lab = torch.from_numpy(labels)
    t = torch.from_numpy(logits)
    out = {"pred": t, "aux": t * 0.5, "pred_lo": t * 2.0, "pred_hi": -t}
    total, parts = hma_loss(out, lab, HMALossWeights(rmi_scope=scope))
    want = (float(rmi_loss(t, lab, pooled_batch=scope == "batch")) + 0.4 * float(rmi_loss(t * 0.5, lab, False))
            + 0.05 * (float(rmi_loss(t * 2.0, lab, False)) + float(rmi_loss(-t, lab, False))))
    assert abs(float(total) - want) < 1e-5 * max(1.0, abs(want))
    assert set(parts) == {"main", "aux", "scales", "total"}


def test_unknown_rmi_scope_is_refused():
    with pytest.raises(ValueError, match="rmi_scope"):
        HMALossWeights(rmi_scope="pixel")


def test_labels_and_logits_must_agree_in_size():
    with pytest.raises(ValueError):
        rmi_loss(torch.zeros(1, 2, 8, 8), torch.zeros(1, 9, 8, dtype=torch.int64))
