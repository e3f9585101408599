"""Training crops from a marker dataset (cpdetect.dataset contract) with the paper's augmentations.

A sample is one ``crop`` x ``crop`` gray crop (float32 in [0, 1], shape (1, S, S)) and its label map
(int64 (S, S): 0 background, 1 marker, 255 ignore outside the source image). Each crop is produced by
one affine warp of the full image (cv2.warpAffine), composed of:

* a centre: with probability ``marker_frac`` a true marker's aiming point shifted by up to
  ``shift_frac`` of the crop, else a uniform point of the image; with ``small_marker_bias`` b > 0 the
  marker is drawn with probability proportional to radius ** -b (small markers are where the shipped
  network misses most), else uniformly;
* a scale in [scale_min, scale_max] (log-uniform), a rotation in [0, 360) degrees, a horizontal flip;
* photometric: brightness/contrast/gamma jitter, Gaussian blur (sigma in ``blur_sigma``) on
  ``blur_prob`` (80 %) of the samples, Gaussian noise.

Randomness comes from a numpy Generator seeded by (seed, epoch, index), so a run is deterministic for
a seed whatever the loader's worker count.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import cv2
import numpy as np

IGNORE = 255


@dataclass(frozen=True)
class AugmentConfig:
    crop: int = 256
    marker_frac: float = 0.8
    shift_frac: float = 0.35
    scale_min: float = 0.5
    scale_max: float = 2.0
    rotate: bool = True
    flip: bool = True
    blur_prob: float = 0.8
    blur_sigma: tuple[float, float] = (0.15, 1.5)
    brightness: float = 0.25
    contrast: float = 0.25
    gamma: float = 0.25
    noise_max: float = 4.0  # std of additive Gaussian noise, grey levels (uniform in [0, noise_max])
    small_marker_bias: float = 0.0  # b: marker k drawn with p ~ radius_k ** -b (0: uniform)


@dataclass
class Sample:
    """One source image in memory or on disk: gray uint8 (H, W), bool/uint8 mask (H, W), centres (n, 2)."""

    image_path: Path | None
    mask_path: Path | None
    centers: np.ndarray
    radii: np.ndarray
    image: np.ndarray | None = None
    mask: np.ndarray | None = None

    def load(self) -> tuple[np.ndarray, np.ndarray]:
        if self.image is not None and self.mask is not None:
            return self.image, self.mask
        from cpdetect.dataset import read_mask
        from cpdetect.imageio import read_image

        img = read_image(self.image_path, gray=True) if self.image is None else self.image
        if self.mask is not None:
            mask = self.mask
        elif self.mask_path is not None:
            mask = read_mask(self.mask_path, img.shape[:2]).astype(np.uint8)
        else:
            raise ValueError(f"{self.image_path}: no mask, cannot train on it")
        return img, mask


def samples_from_dataset(folder: str | Path) -> list[Sample]:
    """Every image of the dataset at ``folder`` that has a mask (images without masks are skipped)."""
    from cpdetect.dataset import load_dataset

    ds = load_dataset(folder)
    out = []
    for item in ds.images:
        mp = ds.mask_path(item)
        if mp is None:
            continue
        c = np.array([[m.x, m.y] for m in item.markers], float).reshape(-1, 2)
        r = np.array([m.radius_px for m in item.markers], float)
        out.append(Sample(ds.image_path(item), mp, c, r))
    return out


def split_samples(samples: Sequence[Sample], val_frac: float, seed: int) -> tuple[list[Sample], list[Sample]]:
    """Deterministic train/validation split (at least one validation image when val_frac > 0)."""
    n = len(samples)
    idx = np.random.default_rng(seed).permutation(n)
    n_val = 0 if val_frac <= 0 else max(1, int(round(n * val_frac)))
    n_val = min(n_val, n - 1) if n > 1 else 0
    val = [samples[i] for i in sorted(idx[:n_val])]
    train = [samples[i] for i in sorted(idx[n_val:])]
    return train, val


def crop_transform(center: tuple[float, float], scale: float, angle_deg: float, flip: bool, crop: int) -> np.ndarray:
    """2x3 affine from source pixels to crop pixels mapping ``center`` to the crop centre.

    Pixel convention OpenCV (centre of top-left pixel = 0): the crop centre is ((crop-1)/2, (crop-1)/2).
    """
    a = math.radians(angle_deg)
    c, s = math.cos(a) * scale, math.sin(a) * scale
    A = np.array([[c, -s], [s, c]])
    if flip:
        A = A @ np.diag([-1.0, 1.0])
    cc = (crop - 1) / 2.0
    t = np.array([cc, cc]) - A @ np.asarray(center, float)
    return np.hstack([A, t[:, None]])


def augment(image: np.ndarray, mask: np.ndarray, centers: np.ndarray, cfg: AugmentConfig,
            rng: np.random.Generator, radii: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """One augmented crop: (float32 (S, S) in [0, 1], int64 labels (S, S) in {0, 1, 255}).

    ``radii`` (pixels, one per centre) are needed only when ``cfg.small_marker_bias`` > 0.
    """
    h, w = image.shape[:2]
    S = cfg.crop
    scale = math.exp(rng.uniform(math.log(cfg.scale_min), math.log(cfg.scale_max)))
    if len(centers) and rng.random() < cfg.marker_frac:
        if cfg.small_marker_bias > 0 and radii is not None and len(radii) == len(centers):
            w_k = np.maximum(np.asarray(radii, float), 1.0) ** -cfg.small_marker_bias
            cx, cy = centers[rng.choice(len(centers), p=w_k / w_k.sum())]
        else:  # the draw of the unbiased default stays what it was, so old runs replay exactly
            cx, cy = centers[rng.integers(len(centers))]
        span = cfg.shift_frac * S / scale
        cx += rng.uniform(-span, span)
        cy += rng.uniform(-span, span)
    else:
        cx, cy = rng.uniform(0, w - 1), rng.uniform(0, h - 1)
    angle = rng.uniform(0, 360) if cfg.rotate else 0.0
    flip = bool(cfg.flip and rng.random() < 0.5)
    M = crop_transform((cx, cy), scale, angle, flip, S)
    src = image
    if scale < 0.75:  # anti-alias before shrinking
        sigma = 0.5 * math.sqrt(max(1.0 / scale ** 2 - 1.0, 0.0))
        src = cv2.GaussianBlur(image, (0, 0), sigma)
    fill = float(rng.uniform(0, 255))
    img = cv2.warpAffine(src, M, (S, S), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                         borderValue=fill).astype(np.float32)
    lab = cv2.warpAffine(np.where(mask > 0, 1, 0).astype(np.uint8), M, (S, S), flags=cv2.INTER_NEAREST,
                         borderMode=cv2.BORDER_CONSTANT, borderValue=IGNORE)
    # photometric jitter on [0, 1]
    x = img / 255.0
    x = x * (1.0 + rng.uniform(-cfg.contrast, cfg.contrast)) + rng.uniform(-cfg.brightness, cfg.brightness) * 0.5
    x = np.clip(x, 0.0, 1.0)
    g = math.exp(rng.uniform(-cfg.gamma, cfg.gamma))
    x = x ** g
    if rng.random() < cfg.blur_prob:
        x = cv2.GaussianBlur(x, (0, 0), float(rng.uniform(*cfg.blur_sigma)))
    if cfg.noise_max > 0:
        x = x + rng.normal(0.0, rng.uniform(0, cfg.noise_max) / 255.0, x.shape).astype(np.float32)
    x = np.clip(x, 0.0, 1.0).astype(np.float32)
    return x, lab.astype(np.int64)


class CropDataset:
    """Map-style dataset of augmented crops: ``len = samples_per_epoch``; item i of epoch e is drawn
    from generator seed (seed, e, i). Call :meth:`set_epoch` before each epoch."""

    def __init__(self, samples: Sequence[Sample], cfg: AugmentConfig, samples_per_epoch: int, seed: int,
                 cache: bool = False):
        if not samples:
            raise ValueError("no training images")
        self.samples = list(samples)
        self.cfg = cfg
        self.n = int(samples_per_epoch)
        self.seed = int(seed)
        self.epoch = 0
        self.cache = cache
        self._cache: dict[int, tuple[np.ndarray, np.ndarray]] = {}

    def set_epoch(self, epoch: int) -> None:
        self.epoch = int(epoch)

    def __len__(self) -> int:
        return self.n

    def _load(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        if k in self._cache:
            return self._cache[k]
        pair = self.samples[k].load()
        if self.cache:
            self._cache[k] = pair
        return pair

    def __getitem__(self, i: int):
        return self.draw(self.epoch, i)

    def draw(self, epoch: int, i: int):
        """Item ``i`` of epoch ``epoch`` (what ``__getitem__`` gives after ``set_epoch(epoch)``)."""
        import torch

        rng = np.random.default_rng([self.seed, int(epoch), int(i)])
        k = int(rng.integers(len(self.samples)))
        img, mask = self._load(k)
        x, lab = augment(img, mask, self.samples[k].centers, self.cfg, rng, self.samples[k].radii)
        return torch.from_numpy(x[None]), torch.from_numpy(lab)


__all__ = ["AugmentConfig", "Sample", "samples_from_dataset", "split_samples", "augment", "CropDataset",
           "crop_transform", "IGNORE"]
