"""Object-Contextual Representations (OCR, Yuan et al.) head, plain PyTorch.

hma.md section 1.2: a 3x3 conv reduces the backbone features to ``mid`` channels; an auxiliary head
predicts soft object regions (K logits); SpatialGather pools one ``mid`` vector per class with the
spatial softmax of the aux logits; an object attention block relates every pixel to the K region
vectors (``key`` channels); the result is fused with the pixel features into ``ocr_feats``.

All tensors are NCHW float32 at the backbone's 1/4 resolution.
"""
from __future__ import annotations

import math

import torch
from torch import nn

from .hrnet import bn


def bn_relu_conv1x1(cin: int, cout: int, bias: bool = False) -> list[nn.Module]:
    return [nn.Conv2d(cin, cout, 1, bias=bias), bn(cout), nn.ReLU()]


class SpatialGather(nn.Module):
    """Class-region vectors (no parameters): context[n, :, k, 0] = sum_p softmax_p(aux[n, k]) feats[n, :, p].

    Returns (N, MID, K, 1) so that the object branch uses 1x1 convolutions like the pixel branch.
    """

    def forward(self, feats: torch.Tensor, aux_logits: torch.Tensor) -> torch.Tensor:
        probs = torch.softmax(aux_logits.flatten(2), dim=2)                  # (N, K, HW)
        ctx = torch.matmul(feats.flatten(2), probs.transpose(1, 2))          # (N, MID, K)
        return ctx.unsqueeze(3)


class ObjectAttention(nn.Module):
    """Pixel-to-region attention: softmax over the K regions of query . key / sqrt(key)."""

    def __init__(self, mid: int, key: int):
        super().__init__()
        self.key_channels = key
        self.f_pixel = nn.Sequential(*bn_relu_conv1x1(mid, key), *bn_relu_conv1x1(key, key))
        self.f_object = nn.Sequential(*bn_relu_conv1x1(mid, key), *bn_relu_conv1x1(key, key))
        self.f_down = nn.Sequential(*bn_relu_conv1x1(mid, key))
        self.f_up = nn.Sequential(*bn_relu_conv1x1(key, mid))

    def forward(self, feats: torch.Tensor, context: torch.Tensor) -> torch.Tensor:
        query = self.f_pixel(feats)                                   # (N, KEY, h, w)
        key = self.f_object(context).flatten(2)                       # (N, KEY, K)
        value = self.f_down(context).flatten(2)                       # (N, KEY, K)
        q = query.flatten(2).transpose(1, 2)                          # (N, hw, KEY)
        sim = torch.softmax(torch.matmul(q, key) / math.sqrt(self.key_channels), dim=-1)  # (N, hw, K)
        out = torch.matmul(value, sim.transpose(1, 2))                # (N, KEY, hw)
        out = out.reshape(query.shape)
        return self.f_up(out)


class OCRHead(nn.Module):
    """feats_hl (N, C_hl, h, w) -> (aux logits (N, K, h, w), ocr_feats (N, mid, h, w)).

    ``reduce_kernel``: the kernel of the convolution that reduces the backbone features to ``mid``
    channels (3, the paper's; 1 for a CPU budget). ``aux_mid``: the auxiliary head's hidden width
    (None = ``in_channels``, the paper's). At 1/4 resolution these two layers are most of the head's
    cost on a small backbone: in the shipped w16_tiny network they take half of a 2048 x 1365 pass
    (bench/hma_bench.py, ``network_layers``).
    """

    def __init__(self, in_channels: int, num_classes: int, mid: int = 128, key: int = 64, dropout: float = 0.05,
                 reduce_kernel: int = 3, aux_mid: int | None = None):
        super().__init__()
        if reduce_kernel not in (1, 3):
            raise ValueError(f"reduce_kernel must be 1 or 3, got {reduce_kernel}")
        aux_mid = in_channels if aux_mid is None else int(aux_mid)
        # upstream's name whatever the kernel: checkpoints keep their keys
        self.conv3x3_ocr = nn.Sequential(nn.Conv2d(in_channels, mid, reduce_kernel, padding=reduce_kernel // 2),
                                         bn(mid), nn.ReLU())
        self.aux_head = nn.Sequential(*bn_relu_conv1x1(in_channels, aux_mid),
                                      nn.Conv2d(aux_mid, num_classes, 1, bias=True))
        self.gather = SpatialGather()
        self.attention = ObjectAttention(mid, key)
        self.fuse = nn.Sequential(*bn_relu_conv1x1(2 * mid, mid), nn.Dropout2d(dropout))

    def forward(self, feats_hl: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        feats = self.conv3x3_ocr(feats_hl)
        aux = self.aux_head(feats_hl)
        context = self.gather(feats, aux)
        attended = self.attention(feats, context)
        ocr_feats = self.fuse(torch.cat([attended, feats], dim=1))
        return aux, ocr_feats


__all__ = ["OCRHead", "SpatialGather", "ObjectAttention"]
