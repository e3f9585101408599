"""Honour a reviewer's rejects: drop the detections that a person marked wrong in the comparison
report's review gallery (``rejects.json``, format ``cpdetect.rejects/1``, read by
:func:`cpdetect.html_report.read_rejects`).

A reject names an image (its name as in the reconstruction / ``detections.json``) and the pixel where
the rejected detection was (OpenCV convention). Every detection of that image whose centre lies within
``tol_px`` of the reject's point is removed. The tolerance absorbs the small shift between a raw
detection and the refined observation the gallery may show; it should stay below the spacing of two
distinct markers in one image (a few pixels is typical).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Mapping, Sequence

DEFAULT_TOL_PX = 3.0


@dataclass
class RejectsApplied:
    """What :func:`apply_rejects` did.

    detections: the filtered mapping, same shape as the input (image name -> list of detections, or
        image name -> record dict whose ``"detections"`` list was filtered; input order kept).
    removed: one ``{"id", "image", "x", "y", "reject_x", "reject_y", "distance_px"}`` per removed
        detection (its pixel position and the reject that removed it).
    unmatched: rejects that removed nothing (image not present, or no detection within ``tol_px``).
    """

    detections: dict
    removed: list[dict] = field(default_factory=list)
    unmatched: list[dict] = field(default_factory=list)


def _xy(det: Any) -> tuple[float, float]:
    if isinstance(det, Mapping):
        return float(det["x"]), float(det["y"])
    return float(det.x), float(det.y)


def apply_rejects(detections_by_image: Mapping[str, Any], rejects: Sequence[Mapping[str, Any]],
                  tol_px: float = DEFAULT_TOL_PX) -> RejectsApplied:
    """Remove every detection within ``tol_px`` pixels of a reject in the same image.

    detections_by_image: image name -> list of detections (:class:`~cpdetect.types.MarkerDetection`
        or dicts with ``x``, ``y``), or image name -> record dict with a ``"detections"`` list (the
        georef pipeline's per-image records); the input is not modified.
    rejects: dicts with ``image``, ``x``, ``y`` (and ``id``), as :func:`~cpdetect.html_report.read_rejects`
        returns them.
    tol_px: match radius in pixels (> 0).

    Returns a :class:`RejectsApplied`. Raises ValueError for a non-positive or non-finite ``tol_px``.
    """
    tol = float(tol_px)
    if not (math.isfinite(tol) and tol > 0):
        raise ValueError(f"tol_px must be a positive number, got {tol_px!r}")
    by_image: dict[str, list[Mapping[str, Any]]] = {}
    for r in rejects:
        by_image.setdefault(str(r["image"]), []).append(r)
    used = set()
    removed: list[dict] = []
    out: dict = {}
    for name, value in detections_by_image.items():
        is_record = isinstance(value, Mapping)
        dets = list(value["detections"]) if is_record else list(value)
        here = by_image.get(name, [])
        keep = []
        for det in dets:
            x, y = _xy(det)
            hit = None
            best = tol
            for r in here:
                d = math.hypot(x - float(r["x"]), y - float(r["y"]))
                if d <= best:
                    hit, best = r, d
            if hit is None:
                keep.append(det)
                continue
            used.add(id(hit))
            removed.append({"id": str(hit.get("id", "")), "image": name, "x": x, "y": y,
                            "reject_x": float(hit["x"]), "reject_y": float(hit["y"]), "distance_px": best})
        out[name] = {**value, "detections": keep} if is_record else keep
    unmatched = [dict(r) for r in rejects if id(r) not in used]
    return RejectsApplied(out, removed, unmatched)


def is_rejected(image: str, x: float, y: float, rejects: Sequence[Mapping[str, Any]],
                tol_px: float = DEFAULT_TOL_PX) -> bool:
    """True when a reject of ``image`` lies within ``tol_px`` of pixel (x, y).

    For the observations georef adds after detection: its refine stage projects each marker into every
    image that sees it and measures the centre there even without a detection, so a rerun must test
    those observations too, or a rejected measurement comes back by projection.
    """
    return any(str(r["image"]) == image and math.hypot(float(x) - float(r["x"]), float(y) - float(r["y"])) <= tol_px
               for r in rejects)


__all__ = ["apply_rejects", "is_rejected", "RejectsApplied", "DEFAULT_TOL_PX"]
