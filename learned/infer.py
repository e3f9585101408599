"""Probability maps from the HMA network with bounded memory: torch or OpenCV-DNN backends, tiling.

Pipeline for one gray uint8 image (H, W):

1. downscale by ``f = min(1, max_side / max(H, W))`` (cv2.INTER_AREA) to the processing size;
2. cut the processing image into tiles of at most ``tile`` x ``tile`` pixels overlapping by
   ``overlap`` (one tile when it fits);
3. per tile and per scale s: resize (bilinear) to s, pad (reflect) to a multiple of 32 and at least
   64 per side (``SIZE_MIN``), run the
   backend's single-scale trunk -> class logits (K, h, w) and attention (h, w), crop the padding;
4. fuse the scales recursively exactly as :meth:`learned.hma.HMAModel.nscale_forward` does, in numpy
   (one implementation for both backends);
5. P(marker) = softmax(logits)[1], tiles pasted by their central parts.

The result is P(marker) at the processing resolution (float32 (h, w) in [0, 1]) and the factor ``f``
(processing pixels per image pixel). Pixel centres: processing pixel (u, v) is image point
((u + 0.5) / f - 0.5, (v + 0.5) / f - 0.5) (cv2.resize convention).

Backends: ``TorchBackend`` (needs torch) and ``OpenCVBackend`` (cv2.dnn on the exported ONNX trunk;
no torch). ``open_backend(model_dir, "auto")`` picks OpenCV when the folder has ``model.onnx`` and the
device is the CPU: on the 2-core CPU it ran the network on the 45 MP bench image (2048 x 1365 after
downscaling, two scales) in 3.9 s on one thread against torch's 5.3 s, 2.1 s on both cores against
torch's 3.6 s, and with another process busy on the same 2 cores its two threads took 4.0 s where
torch's took 8.5 s (2026-11-25); else torch.
"""
from __future__ import annotations

import importlib.util
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol, Sequence

import cv2
import numpy as np

from .digests import check_digest

SIZE_MULTIPLE = 32
# no side under 64 (the coarsest branch at least 2 pixels): OpenCV 5.0's DNN returned logits of
# 3.4e38 for a 32 x 96 input of the shipped network, and a run through 62 x 188, 46 x 141 and 31 x 94
# (a 31 x 94 image at scales 2, 1.5, 1) ended in a segmentation fault; 64 and more give the torch values
SIZE_MIN = 64
ONNX_FILE = "model.onnx"


class TrunkBackend(Protocol):
    """Runs the network at one scale: x (h, w) float32 in [0, 1] -> (logits (K, h, w), attention (h, w))."""

    name: str

    def trunk(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]: ...


def _pad_to_multiple(x: np.ndarray, m: int = SIZE_MULTIPLE, least: int = SIZE_MIN) -> np.ndarray:
    """``x`` (h, w) padded at the bottom and right to a multiple of ``m`` of at least ``least`` per side."""
    h, w = x.shape
    ph, pw = max((-h) % m, least - h), max((-w) % m, least - w)
    if ph == 0 and pw == 0:
        return x
    mode = cv2.BORDER_REFLECT_101 if min(h, w) > 1 else cv2.BORDER_REPLICATE
    return cv2.copyMakeBorder(x, 0, ph, 0, pw, mode)


class TorchBackend:
    """The PyTorch model (``learned.hma``) on CPU or CUDA."""

    name = "torch"

    def __init__(self, model, device: str = "cpu", threads: int | None = None):
        import torch

        if threads:
            torch.set_num_threads(int(threads))
        from .devices import resolve_device

        self.torch = torch
        self.device = resolve_device(device)
        self.model = model.eval().to(self.device)

    @classmethod
    def from_dir(cls, model_dir: str | os.PathLike, device: str = "cpu", threads: int | None = None) -> "TorchBackend":
        from .hma import load_model

        return cls(load_model(model_dir), device, threads)

    def trunk(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        torch = self.torch
        h, w = x.shape
        xp = _pad_to_multiple(np.ascontiguousarray(x, np.float32))
        with torch.inference_mode():
            t = torch.from_numpy(xp)[None, None].to(self.device)
            cls, _aux, attn = self.model._fwd(t)
            cls = cls[0, :, :h, :w].float().cpu().numpy()
            attn = attn[0, 0, :h, :w].float().cpu().numpy()
        return cls, attn


class OpenCVBackend:
    """The exported ONNX trunk (``export.export_trunk_onnx``) through cv2.dnn; needs no torch."""

    name = "opencv"

    def __init__(self, onnx_path: str | os.PathLike, threads: int | None = None):
        """``threads``: OpenCV threads while the network runs (restored after each pass); None
        leaves OpenCV's own setting (all cores unless the process set otherwise)."""
        from cpdetect.errors import InputError, opencv_words

        p = Path(onnx_path)
        if not p.is_file():
            raise InputError("ONNX model not found", p)
        check_digest(p)
        if p.stat().st_size == 0:
            raise InputError("empty file (not an ONNX model)", p)
        try:
            self.net = cv2.dnn.readNetFromONNX(str(p))
        except cv2.error as exc:
            # its words ("Failed to parse ONNX model: FILE") without the file, named by the error
            why = opencv_words(str(exc).strip().splitlines()[-1]).replace(str(p), "").rstrip(" :")
            raise InputError(f"OpenCV cannot load the ONNX model: {why}", p) from None
        self.path = p
        self.threads = int(threads) if threads else None

    def trunk(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        h, w = x.shape
        xp = _pad_to_multiple(np.ascontiguousarray(x, np.float32))
        self.net.setInput(xp[None, None])
        if not self.threads:
            out = self.net.forward()  # (1, K + 1, H, W): K logits then the attention
        else:
            before = cv2.getNumThreads()
            cv2.setNumThreads(self.threads)
            try:
                out = self.net.forward()
            finally:
                cv2.setNumThreads(before)
        out = np.asarray(out)[0, :, :h, :w]
        return np.ascontiguousarray(out[:-1]), np.ascontiguousarray(out[-1])


def torch_available() -> bool:
    return importlib.util.find_spec("torch") is not None


def open_backend(model_dir: str | os.PathLike, backend: str = "auto", device: str = "cpu",
                 threads: int | None = None) -> TrunkBackend:
    """A backend for the model folder: "torch", "opencv" or "auto" (OpenCV on ``model.onnx`` when
    the folder has one and ``device`` is the CPU, else torch; see the module doc). ``threads``: CPU
    threads of the network, None = 1 for torch (its kernels slow down many times over when another
    process shares the cores) and OpenCV's own setting for OpenCV."""
    from cpdetect.errors import InputError, UsageError

    d = Path(model_dir)
    if backend not in ("auto", "torch", "opencv"):
        raise UsageError(f"unknown backend {backend!r}; valid: auto, torch, opencv")
    if not d.is_dir():
        raise InputError("model folder not found" if not d.exists() else "expected a model folder, found a file", d)
    if backend == "auto":
        on_cpu = str(device).split(":")[0] == "cpu"
        if (d / ONNX_FILE).exists() and on_cpu:
            backend = "opencv"
        else:
            backend = "torch" if (torch_available() and (d / "model.pt").exists()) else "opencv"
    if backend == "torch":
        if not torch_available():
            raise UsageError("backend 'torch' needs PyTorch (pip install 'cpdetect[learned]'); "
                             "use backend='opencv' with an exported model.onnx")
        return TorchBackend.from_dir(d, device, threads or 1)
    onnx = d / ONNX_FILE
    if not onnx.exists():
        raise InputError("no model.onnx in the model folder (run 'cpdetect export-onnx')", d)
    return OpenCVBackend(onnx, threads)


def resize_scale_np(x: np.ndarray, s: float) -> np.ndarray:
    """Bilinear rescale by ``s`` to floor(size * s), like torch interpolate(scale_factor=s,
    recompute_scale_factor=True, align_corners=False) without antialiasing; at least 1 pixel a side
    (a 30000 x 9 strip, downscaled to ``max_side`` 2048, is 1 pixel wide, and its half-scale pass
    would be 0)."""
    if s == 1.0:
        return x
    h, w = x.shape[-2:]
    return resize_to_np(x, (max(1, int(np.floor(h * s))), max(1, int(np.floor(w * s)))))


def resize_to_np(x: np.ndarray, hw: tuple[int, int]) -> np.ndarray:
    """Bilinear (align_corners=False) resize of (h, w) or (C, h, w) float32 to ``hw``."""
    h, w = hw
    if x.shape[-2:] == (h, w):
        return x
    if x.ndim == 2:
        return cv2.resize(x, (w, h), interpolation=cv2.INTER_LINEAR)
    return np.stack([cv2.resize(c, (w, h), interpolation=cv2.INTER_LINEAR) for c in x])


LOGIT_LIMIT = 1e4  # stands in for an infinite logit: far beyond any finite one, and a * p stays finite


def fuse_scales(backend: TrunkBackend, x: np.ndarray, scales: Sequence[float]) -> np.ndarray:
    """Hierarchical multi-scale fusion of class logits over ``scales`` (must contain 1.0), at x's size.

    Identical recursion to :meth:`learned.hma.HMAModel.nscale_forward` (hma.md section 1.5). Logits
    that are not finite become +-LOGIT_LIMIT (a saturated pixel stays saturated; NaN: 0) and the
    attention is clipped to [0, 1]: the OpenCV DNN path returned +inf logits for a barely trained
    network on a 32x48 input (1 run in 5 of a CLI test), and inf times a zero attention weight is NaN,
    which would spread through the resize.
    """
    ss = sorted({float(s) for s in scales}, reverse=True)
    if 1.0 not in ss:
        raise ValueError(f"scales {ss} must include 1.0")
    pred = None
    for s in ss:
        if pred is not None and s < 1.0:
            pred = fuse_lower(backend, x, pred, s)
            continue
        p, a = _trunk_at(backend, x, s)
        if pred is None:
            pred = p
        else:
            pred = resize_to_np(pred, p.shape[-2:])
            pred = a[None] * p + (1.0 - a[None]) * pred
    return pred


def fuse_lower(backend: TrunkBackend, x: np.ndarray, pred: np.ndarray, s: float) -> np.ndarray:
    """One more step of the hierarchical fusion: ``pred``, the class logits fused over scales above
    ``s`` (from :func:`fuse_scales`, at x's size), with a pass at scale ``s`` below them, whose
    attention weighs its own logits. ``fuse_lower(b, x, fuse_scales(b, x, S), s)`` equals
    ``fuse_scales(b, x, S + (s,))`` for ``s`` under every scale of S, without running S's passes again."""
    p, a = _trunk_at(backend, x, s)
    hw = pred.shape[-2:]
    return resize_to_np(a[None] * p, hw) + (1.0 - resize_to_np(a, hw)[None]) * pred


def _trunk_at(backend: TrunkBackend, x: np.ndarray, s: float) -> tuple[np.ndarray, np.ndarray]:
    """The trunk's logits and attention for ``x`` rescaled by ``s``, made finite (see :func:`fuse_scales`)."""
    p, a = backend.trunk(resize_scale_np(x, s))
    if not np.isfinite(p).all():
        p = np.nan_to_num(p, nan=0.0, posinf=LOGIT_LIMIT, neginf=-LOGIT_LIMIT)
    return p, np.clip(np.nan_to_num(a, nan=0.5), 0.0, 1.0)


def marker_probability_np(logits: np.ndarray) -> np.ndarray:
    """P(marker) (h, w) from (K, h, w) logits: softmax channel 1, or sigmoid when K == 1."""
    if logits.shape[0] == 1:
        return 1.0 / (1.0 + np.exp(-logits[0]))
    m = logits.max(axis=0, keepdims=True)
    e = np.exp(logits - m)
    return (e[1] / e.sum(axis=0)).astype(np.float32)


def tiles(length: int, tile: int, overlap: int) -> list[tuple[int, int, int, int]]:
    """1-D tiling: (start, stop, keep_start, keep_stop) covering [0, length); kept parts partition it."""
    if length <= tile:
        return [(0, length, 0, length)]
    step = tile - 2 * overlap
    if step <= 0:
        raise ValueError("tile must exceed 2 * overlap")
    out = []
    keep0 = 0
    while keep0 < length:
        keep1 = min(keep0 + step, length)
        start = max(0, min(keep0 - overlap, length - tile))
        stop = min(length, start + tile)
        out.append((start, stop, keep0, keep1))
        keep0 = keep1
    return out


@dataclass(frozen=True)
class ProbabilityMap:
    """P(marker) at the processing resolution and the factor f (processing px per image px);
    ``lower``: with a ``lower_scale`` asked of :func:`probability_map`, P(marker) fused one scale
    further down (same grid), else None."""

    prob: np.ndarray
    factor: float
    lower: np.ndarray | None = None


def processing_image(gray: np.ndarray, max_side: int | None) -> np.ndarray:
    """``gray`` area-reduced so that its longer side is at most ``max_side`` (None: as it is): the
    image the network sees."""
    h, w = gray.shape[:2]
    if not max_side or max(h, w) <= max_side:
        return gray
    f = max_side / float(max(h, w))
    return cv2.resize(gray, (max(1, int(round(w * f))), max(1, int(round(h * f)))), interpolation=cv2.INTER_AREA)


def probability_map(gray: np.ndarray, backend: TrunkBackend, scales: Sequence[float] = (1.0,),
                    max_side: int | None = 2048, tile: int = 1024, overlap: int = 64,
                    lower_scale: float | None = None) -> ProbabilityMap:
    """P(marker) for a gray uint8 (or float [0, 1]) image, downscaled to ``max_side`` and tiled.
    ``lower_scale`` (under every one of ``scales``): also the map fused with a pass at that scale
    (:func:`fuse_lower`, one more pass per tile), as :attr:`ProbabilityMap.lower`."""
    if gray.ndim != 2:
        raise ValueError(f"expected a gray (H, W) image, got shape {gray.shape}")
    if lower_scale is not None and not 0.0 < lower_scale < min(scales):
        raise ValueError(f"lower_scale must be in (0, {min(scales):g}), got {lower_scale}")
    w = gray.shape[1]
    img = processing_image(gray, max_side)
    x = img.astype(np.float32) / 255.0 if img.dtype == np.uint8 else img.astype(np.float32)
    ph, pw = x.shape
    prob = np.empty((ph, pw), np.float32)
    lower = np.empty((ph, pw), np.float32) if lower_scale is not None else None
    for y0, y1, ky0, ky1 in tiles(ph, tile, overlap):
        for x0, x1, kx0, kx1 in tiles(pw, tile, overlap):
            part = x[y0:y1, x0:x1]
            logits = fuse_scales(backend, part, scales)
            keep = (slice(ky0 - y0, ky1 - y0), slice(kx0 - x0, kx1 - x0))
            prob[ky0:ky1, kx0:kx1] = marker_probability_np(logits)[keep]
            if lower is not None:
                lower[ky0:ky1, kx0:kx1] = marker_probability_np(fuse_lower(backend, part, logits, lower_scale))[keep]
    return ProbabilityMap(np.clip(prob, 0.0, 1.0), pw / float(w),
                          None if lower is None else np.clip(lower, 0.0, 1.0))


__all__ = ["TorchBackend", "OpenCVBackend", "open_backend", "fuse_scales", "fuse_lower", "probability_map", "processing_image",
           "ProbabilityMap",
           "marker_probability_np", "tiles", "resize_scale_np", "resize_to_np", "torch_available"]
