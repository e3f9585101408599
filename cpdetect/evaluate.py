"""Scoring a detector on a marker dataset (:mod:`cpdetect.dataset`): marker-level matching and
pixel-level metrics, as in the paper's Table 2. JSON layout: docs/formats.md, "Evaluation metrics JSON".

Marker level: a detection matches an unmatched true marker when their distance is at most
``max(3 px, 0.25 * radius_px)`` of that true marker; detections are taken greedily by decreasing score,
each taking the nearest eligible true marker. Unmatched detections are false positives, unmatched true
markers false negatives. Centre error is the distance of each matched pair (pixels).

Pixel level (only when the detector gives a probability map): counts are accumulated over the whole
set, not averaged per image. A pixel is predicted "marker" when p >= 0.5; IoU = TP/(TP+FP+FN),
F1 = 2TP/(2TP+FP+FN). AP is the area under the pixel precision-recall curve, step-wise (no trapezoid),
from two 1000-bin histograms of p (positives, negatives) swept from the top bin down; it is NaN (JSON
null) when the set has no marker pixel.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any, Callable, Sequence

import numpy as np

from .dataset import Dataset, TrueMarker, read_mask
from .types import DetectionResult, MarkerDetection

AP_BINS = 1000
MIN_TOLERANCE_PX = 3.0
TOLERANCE_RADIUS_FRAC = 0.25


def tolerance_px(radius_px: float) -> float:
    """Largest centre distance (pixels) at which a detection matches a true marker of ``radius_px``."""
    return max(MIN_TOLERANCE_PX, TOLERANCE_RADIUS_FRAC * float(radius_px))


@dataclass(frozen=True)
class Match:
    """Detection index ``det`` matched to true-marker index ``truth`` at ``distance`` pixels."""

    det: int
    truth: int
    distance: float


def match_detections(detections: Sequence[MarkerDetection], truths: Sequence[TrueMarker]
                     ) -> tuple[list[Match], list[int], list[int]]:
    """Greedy-by-score matching of ``detections`` to ``truths`` (both with ``x``, ``y`` in pixels).

    Returns ``(pairs, fp_idx, fn_idx)``: matched pairs in the order they were made (decreasing score;
    ties keep the detections' order), indices of unmatched detections (false positives, ascending) and
    of unmatched truths (false negatives, ascending).
    """
    n_t = len(truths)
    taken = np.zeros(n_t, bool)
    if n_t:
        tx = np.array([t.x for t in truths], float)
        ty = np.array([t.y for t in truths], float)
        tol = np.array([tolerance_px(t.radius_px) for t in truths], float)
    order = sorted(range(len(detections)), key=lambda k: (-float(detections[k].score), k))
    pairs: list[Match] = []
    fp: list[int] = []
    for k in order:
        d = detections[k]
        if n_t:
            dist = np.hypot(tx - d.x, ty - d.y)
            ok = (~taken) & (dist <= tol)
            if ok.any():
                j = int(np.flatnonzero(ok)[np.argmin(dist[ok])])
                taken[j] = True
                pairs.append(Match(k, j, float(dist[j])))
                continue
        fp.append(k)
    return pairs, sorted(fp), [j for j in range(n_t) if not taken[j]]


@dataclass
class PixelCounts:
    """Pixel-level counts accumulated over a set of images (see module docstring)."""

    bins: int = AP_BINS
    pos: np.ndarray = field(default=None)  # type: ignore[assignment]
    neg: np.ndarray = field(default=None)  # type: ignore[assignment]
    tp: int = 0
    fp: int = 0
    fn: int = 0
    images: int = 0

    def __post_init__(self) -> None:
        if self.pos is None:
            self.pos = np.zeros(self.bins, np.int64)
        if self.neg is None:
            self.neg = np.zeros(self.bins, np.int64)

    def add(self, probability: np.ndarray, truth: np.ndarray) -> None:
        """Add one image: ``probability`` float (H, W) in [0, 1] and ``truth`` bool (H, W)."""
        p = np.asarray(probability, np.float32)
        t = np.asarray(truth, bool)
        if p.shape != t.shape:
            raise ValueError(f"probability {p.shape} and truth {t.shape} differ in shape")
        p = np.nan_to_num(p, nan=0.0)
        idx = np.clip((p * self.bins).astype(np.int64), 0, self.bins - 1)
        self.pos += np.bincount(idx[t], minlength=self.bins)
        self.neg += np.bincount(idx[~t], minlength=self.bins)
        pred = p >= 0.5
        self.tp += int(np.count_nonzero(pred & t))
        self.fp += int(np.count_nonzero(pred & ~t))
        self.fn += int(np.count_nonzero(~pred & t))
        self.images += 1

    def average_precision(self) -> float:
        """Step-wise area under the precision-recall curve over the histogram thresholds (NaN when
        there is no positive pixel)."""
        total = int(self.pos.sum())
        if total == 0:
            return float("nan")
        tp = np.cumsum(self.pos[::-1]).astype(float)
        fp = np.cumsum(self.neg[::-1]).astype(float)
        precision = tp / np.maximum(tp + fp, 1.0)
        recall = tp / total
        return float(np.sum(np.diff(np.concatenate([[0.0], recall])) * precision))

    def metrics(self) -> dict:
        """{"iou", "f1", "ap", "precision", "recall", "images"}; NaN where undefined (0/0)."""
        return {"iou": _ratio(self.tp, self.tp + self.fp + self.fn),
                "f1": _ratio(2 * self.tp, 2 * self.tp + self.fp + self.fn),
                "ap": self.average_precision(),
                "precision": _ratio(self.tp, self.tp + self.fp),
                "recall": _ratio(self.tp, self.tp + self.fn),
                "images": self.images}


def _ratio(a: float, b: float) -> float:
    return float(a) / float(b) if b else float("nan")


def _json_safe(obj: Any) -> Any:
    """NaN and infinities become None (JSON null); numpy scalars become Python numbers."""
    if isinstance(obj, dict):
        return {k: _json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_json_safe(v) for v in obj]
    if isinstance(obj, (np.floating, float)):
        return float(obj) if math.isfinite(obj) else None
    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, np.bool_):
        return bool(obj)
    return obj


def score_image(file: str, width: int, height: int, seconds: float, detections: Sequence[MarkerDetection],
                 truths: Sequence[TrueMarker], meta: dict | None = None) -> dict:
    """Per-image evaluation record: counts, matched pairs and misses with the truth's extra fields
    (for breakdowns by type, size, tilt, blur, background), and the false positives."""
    pairs, fp, fn = match_detections(detections, truths)
    matches = []
    for m in pairs:
        t, d = truths[m.truth], detections[m.det]
        matches.append({**t.extra, "truth": m.truth, "det": m.det, "distance": m.distance,
                        "dx": float(d.x - t.x), "dy": float(d.y - t.y), "type": t.type, "det_type": d.type,
                        "radius_px": t.radius_px, "det_radius_px": float(d.radius_px),
                        "score": float(d.score), "sigma_px": float(d.sigma_px)})
    missed = [{**truths[j].extra, "truth": j, "x": truths[j].x, "y": truths[j].y, "type": truths[j].type,
               "radius_px": truths[j].radius_px} for j in fn]
    false_pos = [{"det": k, **detections[k].to_dict()} for k in fp]
    rec = {"file": file, "width": int(width), "height": int(height), "seconds": float(seconds),
           "markers": len(truths), "detections": len(detections),
           "tp": len(pairs), "fp": len(fp), "fn": len(fn),
           "matches": matches, "missed": missed, "false_positives": false_pos}
    for key in ("background", "category"):
        if meta and key in meta:
            rec[key] = meta[key]
    return rec


def summarize(records: Sequence[dict], pixel: PixelCounts | None = None, detector: str = "") -> dict:
    """Set-level metrics from per-image records (see docs/formats.md); NaN where undefined.

    Works on any subset of records, so breakdowns (by background, category, ...) reuse it.
    """
    tp = sum(r["tp"] for r in records)
    fp = sum(r["fp"] for r in records)
    fn = sum(r["fn"] for r in records)
    dist = np.array([m["distance"] for r in records for m in r["matches"]], float)
    types_ok = [m["type"] == m["det_type"] for r in records for m in r["matches"]]
    megapixels = sum(r["width"] * r["height"] for r in records) / 1e6
    seconds = sum(r["seconds"] for r in records)
    err = _error_stats(dist)
    return {
        "detector": detector,
        "images": len(records),
        "markers": sum(r["markers"] for r in records),
        "detections": sum(r["detections"] for r in records),
        "tp": tp, "fp": fp, "fn": fn,
        "precision": _ratio(tp, tp + fp),
        "recall": _ratio(tp, tp + fn),
        "f1": _ratio(2 * tp, 2 * tp + fp + fn),
        "centre_error_px": err,
        "type_accuracy": _ratio(sum(types_ok), len(types_ok)),
        "centre_visible": centre_visible_summary(records),
        "pixel": pixel.metrics() if pixel is not None and pixel.images > 0 else None,
        "seconds_per_megapixel": _ratio(seconds, megapixels),
        "seconds": seconds,
    }


def centre_hidden(fields: dict) -> bool:
    """Whether a true marker's fields (``TrueMarker.extra`` or a per-image record's match / miss)
    say an occluder hides its aiming point; markers without the field count as visible."""
    return bool(fields.get("centre_hidden", False))


def centre_visible_summary(records: Sequence[dict]) -> dict:
    """Marker recall and centre error without the markers whose aiming point an occluder hides
    (truth field ``centre_hidden``, written by the generator): nothing in the image locates such a
    marker's centre, so it is left out of both counts here (a detection matched to one was no false
    positive either). ``{"markers", "tp", "fn", "recall", "f1", "hidden", "centre_error_px"}``;
    ``f1`` weighs those markers against every false positive; ``hidden`` counts the markers left out.
    Markers without the field count as visible."""
    dist = np.array([m["distance"] for r in records for m in r["matches"] if not centre_hidden(m)], float)
    missed = sum(1 for r in records for m in r["missed"] if not centre_hidden(m))
    everyone = sum(len(r["matches"]) + len(r["missed"]) for r in records)
    false = sum(len(r["false_positives"]) for r in records)
    tp = int(dist.size)
    return {"markers": tp + missed, "tp": tp, "fn": missed, "recall": _ratio(tp, tp + missed),
            "f1": _ratio(2 * tp, 2 * tp + false + missed),
            "hidden": everyone - tp - missed, "centre_error_px": _error_stats(dist)}


def _error_stats(dist: np.ndarray) -> dict:
    if not dist.size:
        return {"mean": float("nan"), "median": float("nan"), "p95": float("nan")}
    return {"mean": float(dist.mean()), "median": float(np.median(dist)), "p95": float(np.percentile(dist, 95))}


def recall_by(records: Sequence[dict], key: str, edges: Sequence[float] | None = None) -> list[dict]:
    """Marker-level recall grouped by a true marker's field ``key`` (e.g. "type", "radius_px",
    "tilt_deg", "blur_px", "occluded_frac") or an image field ("category", "background").

    Without ``edges`` groups are the distinct values; with ``edges`` (ascending numbers) groups are the
    half-open bins [edges[k], edges[k+1]). Returns ``[{"group", "markers", "tp", "recall",
    "centre_error_px_median"}]``; markers lacking ``key`` are left out.
    """
    groups: dict[Any, list] = {}
    for r in records:
        for found, items in ((True, r["matches"]), (False, r["missed"])):
            for m in items:
                value = m.get(key, r.get(key))
                if value is None:
                    continue
                if edges is not None:
                    k = int(np.searchsorted(np.asarray(edges, float), float(value), side="right")) - 1
                    if k < 0 or k >= len(edges) - 1:
                        continue
                    value = (float(edges[k]), float(edges[k + 1]))
                groups.setdefault(value, []).append((found, m.get("distance")))
    out = []
    for g in sorted(groups, key=lambda v: (str(type(v)), v)):
        items = groups[g]
        tp = sum(1 for f, _ in items if f)
        d = [x for f, x in items if f]
        out.append({"group": list(g) if isinstance(g, tuple) else g, "markers": len(items), "tp": tp,
                    "recall": _ratio(tp, len(items)),
                    "centre_error_px_median": float(np.median(d)) if d else float("nan")})
    return out


def evaluate(dataset: Dataset, detector: Any, limit: int | None = None,
             progress: Callable[[int, int], None] | None = None, from_file: bool | None = None) -> dict:
    """Run ``detector`` on every image of ``dataset`` (the first ``limit`` when given) and score it.

    Returns a JSON-safe dict: the summary keys of :func:`summarize` (NaN written as None) plus
    ``"dataset"`` (its root), ``"input"`` ("file" or "array") and ``"per_image"`` (one
    :func:`score_image` per image). ``from_file``: give the detector the image's path, as ``cpdetect
    detect`` does for a detector with ``accepts_path`` (the classical one decodes a large JPEG at
    reduced size for its search, which finds slightly different candidates than the area-reduced
    array does; only for such a detector); the timing then includes the decode. False: decode with
    :func:`cpdetect.imageio.read_image` (BGR uint8) and time only ``detector.detect``. None (default):
    the path exactly where ``cpdetect detect`` would pass it.
    Raises :class:`~cpdetect.errors.InputError` naming the file for an unreadable image or mask.
    """
    from .imageio import probe_image, read_image

    items = dataset.images if limit is None else dataset.images[:max(int(limit), 0)]
    name = str(getattr(detector, "name", type(detector).__name__))
    reads_files = bool(getattr(detector, "accepts_path", False))
    if from_file is None:
        from_file = reads_files
    elif from_file and not reads_files:
        raise ValueError(f"detector {name!r} takes decoded images, not paths (from_file=True needs accepts_path)")
    pixel = PixelCounts()
    records = []
    for k, item in enumerate(items):
        path = dataset.image_path(item)
        if from_file:
            info = probe_image(path)
            w, h = info.width, info.height
            t0 = time.perf_counter()
            result: DetectionResult = detector.detect(path)
        else:
            image = read_image(path)
            h, w = image.shape[:2]
            t0 = time.perf_counter()
            result = detector.detect(image)
        seconds = time.perf_counter() - t0
        if tuple(result.image_size) != (w, h):
            raise ValueError(f"detector {name!r} reported image size {result.image_size} for a {w}x{h} image")
        if result.probability is not None and item.mask is not None:
            truth = read_mask(dataset.mask_path(item), shape=(h, w))
            pixel.add(result.probability_at(w, h), truth)
        records.append(score_image(item.file, w, h, seconds, result.detections, item.markers, item.meta))
        if progress:
            progress(k + 1, len(items))
    out = summarize(records, pixel, detector=name)
    out["dataset"] = str(dataset.root)
    out["input"] = "file" if from_file else "array"
    out["per_image"] = records
    return _json_safe(out)


def format_table(metrics: dict) -> str:
    """A short human-readable summary of :func:`evaluate`'s result."""
    def f(v, spec=".3f"):
        return "n/a" if v is None or (isinstance(v, float) and not math.isfinite(v)) else format(v, spec)

    e = metrics["centre_error_px"]
    lines = [
        f"detector   {metrics['detector']}   images {metrics['images']}   markers {metrics['markers']}"
        f"   detections {metrics.get('detections', 'n/a')}",
        f"markers    tp {metrics['tp']}   fp {metrics['fp']}   fn {metrics['fn']}   precision "
        f"{f(metrics['precision'])}   recall {f(metrics['recall'])}   f1 {f(metrics['f1'])}",
    ]
    cv = metrics.get("centre_visible")
    if cv and cv.get("hidden"):
        ce = cv["centre_error_px"]
        lines.append(f"           recall {f(cv['recall'])} (f1 {f(cv.get('f1'))}) of the {cv['markers']} markers whose "
                     f"centre is visible ({cv['hidden']} hidden by an occluder); their centre mean {f(ce['mean'])} px, "
                     f"p95 {f(ce['p95'])} px")
    lines += [
        f"centre     mean {f(e['mean'])} px   median {f(e['median'])} px   p95 {f(e['p95'])} px"
        f"   type accuracy {f(metrics.get('type_accuracy'))}",
    ]
    px = metrics.get("pixel")
    if px:
        lines.append(f"pixels     iou {f(px['iou'])}   f1 {f(px['f1'])}   ap {f(px['ap'])}")
    else:
        lines.append("pixels     n/a (the detector gives no probability map)")
    lines.append(f"speed      {f(metrics['seconds_per_megapixel'], '.4f')} s per megapixel")
    return "\n".join(lines)


__all__ = ["Match", "match_detections", "tolerance_px", "PixelCounts", "score_image", "summarize",
           "centre_hidden", "centre_visible_summary", "recall_by",
           "evaluate", "format_table", "AP_BINS"]
