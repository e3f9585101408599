"""Plots of the detector comparison, as PNG bytes (matplotlib, Agg backend: no display needed).

* :func:`pr_curves`: instance precision-recall (from detection scores) and pixel precision-recall (from
  the 1000-bin probability histograms of :class:`cpdetect.evaluate.PixelCounts`), one line per detector.
* :func:`centre_error_histograms`: distribution of centre errors (pixels), one step line per detector.
* :func:`residual_top_view`: surveyed points seen from above (local frame: x east, y north, metres) with
  each detector's residual vectors, exaggerated by a stated factor, and the points it did not pair.
"""
from __future__ import annotations

from typing import Mapping, Optional, Sequence

import numpy as np

from .html_report import figure_png

_COLOURS = ("#0969da", "#cf222e", "#1a7f37", "#8250df", "#bf8700", "#57606a")


def _plt():
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    return plt


def colour(k: int) -> str:
    return _COLOURS[k % len(_COLOURS)]


def pixel_pr(pos: np.ndarray, neg: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(precision, recall) of the pixel classifier at every histogram threshold, from the top bin down.

    pos / neg: counts of marker / background pixels per probability bin (bin k holds p in
    [k/B, (k+1)/B)). Thresholds where nothing is predicted positive are left out. Empty arrays when
    there is no marker pixel.
    """
    pos = np.asarray(pos, float)
    neg = np.asarray(neg, float)
    total = pos.sum()
    if total <= 0:
        return np.zeros(0), np.zeros(0)
    tp = np.cumsum(pos[::-1])
    fp = np.cumsum(neg[::-1])
    keep = (tp + fp) > 0
    return (tp / np.maximum(tp + fp, 1.0))[keep], (tp / total)[keep]


def pr_curves(instance: Mapping[str, dict], pixel: Mapping[str, Optional[tuple[np.ndarray, np.ndarray]]],
              dpi: int = 90) -> bytes:
    """PNG of two panels: instance PR (``instance[name]`` with ``precision``, ``recall``, ``ap``) and
    pixel PR (``pixel[name] = (pos, neg)`` histograms, or None when the detector gives no map)."""
    plt = _plt()
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(9, 3.6))
    for k, (name, pr) in enumerate(instance.items()):
        if pr["recall"]:
            ap = pr.get("ap")
            label = f"{name} (AP {ap:.3f})" if ap is not None and np.isfinite(ap) else name
            a1.step(pr["recall"], pr["precision"], where="post", color=colour(k), label=label)
    a1.set_title("markers (instance)")
    drew = False
    for k, (name, counts) in enumerate(pixel.items()):
        if counts is None:
            continue
        p, r = pixel_pr(*counts)
        if p.size:
            a2.step(r, p, where="post", color=colour(k), label=name)
            drew = True
    a2.set_title("pixels")
    if not drew:
        a2.text(0.5, 0.5, "no probability maps", ha="center", va="center", transform=a2.transAxes)
    for a in (a1, a2):
        a.set_xlim(0, 1.01)
        a.set_ylim(0, 1.01)
        a.set_xlabel("recall")
        a.set_ylabel("precision")
        a.grid(alpha=0.3)
        if a.get_legend_handles_labels()[0]:
            a.legend(fontsize=8, loc="lower left")
    fig.tight_layout()
    return figure_png(fig, dpi)


def centre_error_histograms(errors: Mapping[str, Sequence[float]], unit: str = "px",
                            title: str = "centre error", dpi: int = 90) -> bytes:
    """PNG of one step histogram per detector on shared bins (0 to the 99th percentile of all values)."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(5, 3.4))
    allv = np.concatenate([np.asarray(v, float) for v in errors.values()] or [np.zeros(0)])
    allv = allv[np.isfinite(allv)]
    if allv.size:
        hi = max(float(np.percentile(allv, 99)), 1e-6)
        bins = np.linspace(0.0, hi, 25)
        for k, (name, v) in enumerate(errors.items()):
            v = np.asarray(v, float)
            v = np.clip(v[np.isfinite(v)], 0.0, hi)
            if v.size:
                ax.hist(v, bins=bins, histtype="step", lw=1.6, color=colour(k),
                        label=f"{name} (n={v.size}, median {np.median(v):.2f} {unit})")
        ax.legend(fontsize=8)
    else:
        ax.text(0.5, 0.5, "no matched markers", ha="center", va="center", transform=ax.transAxes)
    ax.set_xlabel(f"{title} ({unit})")
    ax.set_ylabel("count")
    ax.set_title(title)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    return figure_png(fig, dpi)


def residual_top_view(names: Sequence[str], surveyed_xy: np.ndarray,
                      residuals: Mapping[str, Mapping[str, Sequence[float]]], dpi: int = 90) -> bytes:
    """PNG of the site from above with residual vectors.

    names / surveyed_xy: surveyed points and their (x, y) in the local frame (metres, (n, 2)).
    residuals: detector -> {surveyed name: residual (dx, dy, ...) in metres}; points a detector did not
    pair are marked with a cross of its colour. Vectors are scaled so the largest is a tenth of the
    site's extent; the factor is in the title.
    """
    plt = _plt()
    xy = np.asarray(surveyed_xy, float).reshape(-1, 2)
    fig, ax = plt.subplots(figsize=(6, 5))
    ax.scatter(xy[:, 0], xy[:, 1], s=30, c="#1d2125", marker="o", zorder=3, label="surveyed")
    for n, (x, y) in zip(names, xy):
        ax.annotate(n, (x, y), textcoords="offset points", xytext=(4, 4), fontsize=7)
    extent = float(np.ptp(xy, axis=0).max()) if len(xy) > 1 else 1.0
    extent = extent if extent > 0 else 1.0
    longest = max([float(np.hypot(*np.asarray(r, float)[:2])) for res in residuals.values() for r in res.values()]
                  + [0.0])
    scale = 0.1 * extent / longest if longest > 0 else 1.0
    index = {n: k for k, n in enumerate(names)}
    for k, (det, res) in enumerate(residuals.items()):
        c = colour(k)
        pts = [(index[n], np.asarray(r, float)[:2]) for n, r in res.items() if n in index]
        if pts:
            idx = np.array([i for i, _ in pts])
            d = np.array([v for _, v in pts])
            ax.quiver(xy[idx, 0], xy[idx, 1], d[:, 0] * scale, d[:, 1] * scale, angles="xy", scale_units="xy",
                      scale=1.0, color=c, width=0.005, label=det, zorder=4)
        else:
            ax.plot([], [], color=c, label=det)
        missing = [index[n] for n in names if n not in res]
        if missing:
            ax.scatter(xy[missing, 0], xy[missing, 1], s=140, marker="x", c=c, lw=2, zorder=5,
                       label=f"{det}: not paired")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("east / x (m)")
    ax.set_ylabel("north / y (m)")
    ax.set_title(f"residuals from above (vectors x{scale:.0f})")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="best")
    fig.tight_layout()
    return figure_png(fig, dpi)


__all__ = ["pixel_pr", "pr_curves", "centre_error_histograms", "residual_top_view", "colour"]
