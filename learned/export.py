"""ONNX export of the HMA trunk for torch-free inference (OpenCV DNN).

The exported graph is the single-scale trunk: ``input`` (1, C, H, W) float32 in [0, 1] (H, W any
multiples of 32; :mod:`learned.infer` pads to that) -> ``trunk`` (1, K + 1, H, W): the K class logits
then the attention map in (0, 1), all at the input size. The hierarchical multi-scale fusion runs
outside the graph, in numpy (:func:`learned.infer.fuse_scales`), identically for both backends:
OpenCV 5.0's DNN engine rejects a graph that rescales its own 1-channel input (``C0 <= 1`` in
``toLayout``), and fusing outside keeps one fusion code for torch and OpenCV.
"""
from __future__ import annotations

import os
from pathlib import Path

import torch
from torch import nn

from .digests import record_digest
from .hma import CONFIG_FILE, HMAModel

OPSET = 17


class TrunkNet(nn.Module):
    """Wraps an :class:`HMAModel`: image (N, C, H, W) in [0, 1] -> cat[class logits, attention] (N, K+1, H, W)."""

    def __init__(self, model: HMAModel):
        super().__init__()
        self.model = model

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        cls, _aux, attn = self.model._fwd(x)
        return torch.cat([cls, attn], dim=1)


def export_onnx(model: HMAModel, path: str | os.PathLike, sample_size: tuple[int, int] = (256, 320)) -> Path:
    """Write the trunk to ``path`` atomically (dynamic height and width); returns the path."""
    import warnings

    from cpdetect.fileio import atomic_path

    model = model.eval().to("cpu").to(memory_format=torch.contiguous_format)
    net = TrunkNet(model).eval()
    h, w = sample_size
    x = torch.rand(1, model.config.backbone.in_channels, h, w)
    path = Path(path)
    with atomic_path(path) as tmp, torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore")  # tracer warnings about shape-dependent Python values
        torch.onnx.export(net, (x,), str(tmp), input_names=["input"], output_names=["trunk"],
                          opset_version=OPSET, dynamic_axes={"input": {2: "height", 3: "width"},
                                                             "trunk": {2: "height", 3: "width"}},
                          dynamo=False)
    model.eval()
    if (path.parent / CONFIG_FILE).exists():  # into a model folder: its digest beside the others
        record_digest(path)
    return path



def check_parity(model: HMAModel, onnx_path: str | os.PathLike,
                 sizes: tuple[tuple[int, int], ...] = ((256, 320), (352, 224)), seed: int = 0) -> float:
    """Largest |P_torch - P_opencv| of P(marker) over test images of the given (h, w) sizes: smooth
    random backgrounds with rendered markers of the three types, so that P spans [0, 1]."""
    import cv2
    import numpy as np

    from cpdetect.markers import MARKER_TYPES, MarkerSpec, frontal_homography, render_marker

    from .infer import OpenCVBackend, TorchBackend, fuse_scales, marker_probability_np

    rng = np.random.default_rng(seed)
    tb, ob = TorchBackend(model), OpenCVBackend(onnx_path)
    worst = 0.0
    for h, w in sizes:
        small = rng.random((h // 8 + 2, w // 8 + 2)).astype(np.float32)
        x = np.clip(cv2.resize(small, (w, h), interpolation=cv2.INTER_CUBIC), 0, 1) * 0.5 + 0.25
        for t in MARKER_TYPES:
            spec = MarkerSpec(t, 1.0)
            c = (rng.uniform(0.2, 0.8) * w, rng.uniform(0.2, 0.8) * h)
            H = frontal_homography(c, rng.uniform(10, 30), rng.uniform(0, 3), spec)
            render_marker(spec, H, x.shape).composite(x, 0.1, 0.9)
        for scales in ((1.0,), (0.5, 1.0)):
            pt = marker_probability_np(fuse_scales(tb, x, scales))
            po = marker_probability_np(fuse_scales(ob, x, scales))
            worst = max(worst, float(np.abs(pt - po).max()))
    return worst


__all__ = ["export_onnx", "TrunkNet", "check_parity", "OPSET"]
