"""Region mutual information loss (Zhao et al., NeurIPS 2019) with its BCE part, as HMA trains it.

hma.md section 2. For each class, the R x R (R = 3, d = 9) neighbourhoods of the one-hot label map Y
and of the sigmoid probability map P are treated as d-dimensional samples; minimising
0.5 * log det(Sigma_Y|P) with Sigma_Y|P = S_yy - S_yp (S_pp + a I)^-1 S_yp^T maximises a lower
bound of I(Y; P). Covariances are not divided by the number of samples (a constant), a = 5e-4 is
added to S_pp and to Sigma_Y|P, and all of this runs in float64. A batch whose Cholesky factorisation
fails anyway counts its RMI part as zero (the BCE part still trains) and is counted in ``stats``.

Shapes: logits (N, K, H, W) float; labels (N, H, W) int64 with classes 0..K-1; any value >= K
(e.g. 255) is ignored. Every class channel is an independent binary (sigmoid) map, as upstream.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import torch
import torch.nn.functional as F

POS_ALPHA = 5e-4
CLIP_MIN = 1e-6


@dataclass
class RMIStats:
    """Counters a training loop may log: batches whose Cholesky failed (RMI part dropped)."""

    calls: int = 0
    cholesky_failures: int = 0
    extra: dict = field(default_factory=dict)


def one_hot_valid(labels: torch.Tensor, num_classes: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(one-hot (N, K, H, W) float zeroed on ignored pixels, valid mask (N, 1, H, W) float)."""
    if labels.dim() != 3:
        raise ValueError(f"labels must be (N, H, W), got {tuple(labels.shape)}")
    valid = (labels >= 0) & (labels < num_classes)
    safe = torch.where(valid, labels, torch.zeros_like(labels))
    onehot = F.one_hot(safe.long(), num_classes).permute(0, 3, 1, 2).to(torch.float32)
    v = valid.unsqueeze(1).to(torch.float32)
    return onehot * v, v


def bce_part(logits: torch.Tensor, onehot: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """Sigmoid BCE summed over classes and valid pixels, divided by (valid pixels + 1)."""
    w = valid.expand_as(logits)
    total = F.binary_cross_entropy_with_logits(logits, onehot, weight=w, reduction="sum")
    return total / (valid.sum() + 1.0)


def region_vectors(x: torch.Tensor, radius: int = 3) -> torch.Tensor:
    """(N, K, H, W) -> (N, K, radius^2, M): every valid radius x radius window as a column."""
    n, k, h, w = x.shape
    cols = F.unfold(x, kernel_size=radius)                # (N, K*r*r, M), channel-major
    return cols.view(n, k, radius * radius, -1)


def log_det_conditional(y: torch.Tensor, p: torch.Tensor, alpha: float = POS_ALPHA
                        ) -> tuple[torch.Tensor, torch.Tensor]:
    """log det(S_yy - S_yp (S_pp + aI)^-1 S_yp^T + aI) per (n, k), in float64, and Cholesky info.

    y, p: (N, K, d, M) region vectors. Returns (logdet (N, K) float64, info (N, K) int; 0 = success).
    """
    y = y.double()
    p = p.double()
    y = y - y.mean(dim=3, keepdim=True)
    p = p - p.mean(dim=3, keepdim=True)
    d = y.shape[2]
    eye = torch.eye(d, dtype=torch.float64, device=y.device)
    s_yy = y @ y.transpose(-1, -2)
    s_pp = p @ p.transpose(-1, -2)
    s_yp = y @ p.transpose(-1, -2)
    # S_yp (S_pp + aI)^-1 S_yp^T through a solve (no explicit inverse)
    sol = torch.linalg.solve(s_pp + alpha * eye, s_yp.transpose(-1, -2))
    cond = s_yy - s_yp @ sol
    cond = 0.5 * (cond + cond.transpose(-1, -2)) + alpha * eye
    chol, info = torch.linalg.cholesky_ex(cond)
    diag = torch.diagonal(chol, dim1=-2, dim2=-1)
    logdet = 2.0 * torch.log(diag.clamp_min(0.0) + 1e-8).sum(-1)
    return logdet, info


def _pool_batch(v: torch.Tensor) -> torch.Tensor:
    """(N, K, d, M) -> (1, K, d, N * M): the regions of every image of the batch as one sample set."""
    n, k, d, m = v.shape
    return v.permute(1, 2, 0, 3).reshape(1, k, d, n * m)


def rmi_term(probs: torch.Tensor, onehot: torch.Tensor, radius: int = 3, pool: int = 4,
             alpha: float = POS_ALPHA, pooled_batch: bool = False) -> tuple[torch.Tensor, bool]:
    """The RMI part: sum over classes of the batch mean of 0.5 * logdet / d (float64 -> float32).

    probs, onehot: (N, K, H, W), already masked. Both are average-pooled (kernel = stride = pool,
    padding pool // 2) first. Returns (value, ok); ok is False when a Cholesky failed and the value
    is then a zero that keeps the graph.
    """
    if pool > 1:
        probs = F.avg_pool2d(probs, kernel_size=pool, stride=pool, padding=pool // 2)
        onehot = F.avg_pool2d(onehot, kernel_size=pool, stride=pool, padding=pool // 2)
    if probs.shape[2] < radius or probs.shape[3] < radius:
        return probs.sum() * 0.0, True
    y = region_vectors(onehot, radius)
    p = region_vectors(probs, radius)
    if pooled_batch:
        y, p = _pool_batch(y), _pool_batch(p)
    logdet, info = log_det_conditional(y, p, alpha)
    if bool((info != 0).any()) or not bool(torch.isfinite(logdet).all()):
        return probs.sum() * 0.0, False
    d = radius * radius
    value = (0.5 * logdet / d).mean(dim=0).sum()
    return value.to(probs.dtype), True


def rmi_loss(logits: torch.Tensor, labels: torch.Tensor, do_rmi: bool = True, lam: float = 0.5,
             radius: int = 3, pool: int = 4, stats: RMIStats | None = None,
             pooled_batch: bool = False) -> torch.Tensor:
    """lam * BCE + (1 - lam) * RMI (do_rmi) or the BCE part alone; a scalar float32 tensor.

    pooled_batch: estimate the covariances once over the regions of the whole batch instead of per
    image (upstream). Markers cover a few percent of a crop; per image, a crop with a handful of marker
    pixels has a near-singular conditional covariance whose log-det gradient (of order 1 / alpha)
    drowns the signal, and training on our synthetic sets learned nothing in 400 iterations. Pooled
    over the batch the estimate is stable and the network learns as fast as with BCE alone.
    """
    k = logits.shape[1]
    if labels.shape[-2:] != logits.shape[-2:]:
        raise ValueError(f"labels {tuple(labels.shape)} and logits {tuple(logits.shape)} differ in size")
    onehot, valid = one_hot_valid(labels, k)
    logits = logits.float()
    bce = bce_part(logits, onehot, valid)
    if not do_rmi:
        return bce
    probs = torch.sigmoid(logits) * valid + CLIP_MIN
    rmi, ok = rmi_term(probs, onehot, radius, pool, pooled_batch=pooled_batch)
    if stats is not None:
        stats.calls += 1
        stats.cholesky_failures += int(not ok)
    return lam * bce + (1.0 - lam) * rmi


@dataclass(frozen=True)
class HMALossWeights:
    """main: RMI + BCE on fused logits; aux: BCE on fused OCR aux logits; scale: BCE on each scale.

    rmi_scope: "batch" (covariances over the whole batch, our default, see :func:`rmi_loss`) or
    "image" (per image, as upstream).
    """

    aux: float = 0.4
    scale: float = 0.05
    lam: float = 0.5
    rmi_scope: str = "batch"

    def __post_init__(self) -> None:
        if self.rmi_scope not in ("batch", "image"):
            raise ValueError(f"rmi_scope must be 'batch' or 'image', got {self.rmi_scope!r}")


def hma_loss(out: dict[str, torch.Tensor], labels: torch.Tensor, weights: HMALossWeights = HMALossWeights(),
             stats: RMIStats | None = None) -> tuple[torch.Tensor, dict[str, float]]:
    """Total two-scale HMA loss from :meth:`HMAModel.two_scale_forward` output and (N, H, W) labels."""
    main = rmi_loss(out["pred"], labels, True, weights.lam, stats=stats,
                    pooled_batch=weights.rmi_scope == "batch")
    aux = rmi_loss(out["aux"], labels, False)
    total = main + weights.aux * aux
    parts = {"main": float(main.detach()), "aux": float(aux.detach())}
    if weights.scale > 0:
        s = rmi_loss(out["pred_lo"], labels, False) + rmi_loss(out["pred_hi"], labels, False)
        total = total + weights.scale * s
        parts["scales"] = float(s.detach())
    parts["total"] = float(total.detach())
    return total, parts


__all__ = ["rmi_loss", "rmi_term", "hma_loss", "HMALossWeights", "RMIStats", "log_det_conditional",
           "region_vectors", "one_hot_valid", "POS_ALPHA"]
