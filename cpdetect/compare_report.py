"""Write a detector comparison (:mod:`cpdetect.compare`) as ``report.html`` (self-contained: embedded
PNG plots, no network), ``summary.json`` (format ``cpdetect.compare/1``, for scripts and CI) and
``summary.md``, all atomically. Layout: docs/formats.md, "Comparison report".

The site report's review gallery shows, for each detector and marker, crops of the images with the
centre georef measured there drawn (see :func:`site_gallery`); a reviewer ticks wrong ones and downloads
``rejects.json`` (:func:`cpdetect.rejects.apply_rejects` drops them on a rerun).
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Optional, Union

import numpy as np

from .compare import DatasetComparison, SiteComparison, assign_detections
from .evaluate import _json_safe
from .fileio import write_json_atomic, write_text_atomic
from .html_report import GalleryItem, HtmlReport, crop_with_marker

SUMMARY_FORMAT = "cpdetect.compare/1"
Comparison = Union[DatasetComparison, SiteComparison]


def _f(v: Any, spec: str = ".3f") -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "n/a"
    return format(v, spec)


def _mm(v: Optional[float]) -> str:
    return "n/a" if v is None else f"{1000 * v:.1f}"


# ----------------------------------------------------------------------------------------------------
# summary.json


def summary_dict(cmp: Comparison) -> dict:
    """The JSON summary (see docs/formats.md, "Comparison report"); NaN written as null."""
    if isinstance(cmp, DatasetComparison):
        results = {}
        for r in cmp.detectors:
            s = dict(r.summary)
            s.pop("per_image", None)
            results[r.name] = {**s, "breakdown": r.breakdown}
        ag = cmp.agreement
        doc = {"format": SUMMARY_FORMAT, "mode": "dataset", "input": str(cmp.root),
               "detectors": [r.name for r in cmp.detectors], "recommendation": cmp.recommendation.to_dict(),
               "n_images": cmp.n_images, "n_markers": cmp.n_markers, "results": results,
               "agreement": {"found_by_all": ag["found_by_all"], "found_by_none": ag["found_by_none"],
                             "only": ag["only"], "disagreements": ag["disagreements"]}}
        return _json_safe(doc)
    results = {}
    for r in cmp.detectors:
        rep = r.report
        results[r.name] = {
            "status": rep.get("status"), "reason": rep.get("reason") or "", "mode": rep.get("mode"),
            "n_markers": rep.get("n_markers"), "n_paired": len(r.paired), "paired": sorted(r.paired),
            "unpaired_surveyed": rep.get("unpaired_surveyed", []), "rms_m": r.rms_m,
            "residual_m": {n: m["residual_m"] for n, m in sorted(r.paired.items())},
            "detections": sum(len(v) for v in r.detections.values()),
            "seconds_detect": r.seconds_detect, "seconds_total": r.seconds_total,
            "run_dir": str(r.out_dir)}
    doc = {"format": SUMMARY_FORMAT, "mode": "site", "input": str(cmp.inputs.root),
           "detectors": [r.name for r in cmp.detectors], "recommendation": cmp.recommendation.to_dict(),
           "n_surveyed": len(cmp.surveyed_names), "n_images": len(cmp.images), "results": results,
           "markers": cmp.markers, "images_disagreeing": [im for im in cmp.images if im["disagree"]]}
    return _json_safe(doc)


# ----------------------------------------------------------------------------------------------------
# tables shared by the Markdown and HTML outputs


def summary_table(cmp: Comparison) -> tuple[list[str], list[list[Any]]]:
    """(header, rows) of the one-line-per-detector summary."""
    if isinstance(cmp, DatasetComparison):
        header = ["detector", "markers", "tp", "fp", "fn", "precision", "recall", "F1", "instance AP",
                  "centre err median (px)", "centre err p95 (px)", "pixel IoU", "pixel F1", "pixel AP", "s/MP"]
        rows = []
        for r in cmp.detectors:
            s = r.summary
            px = s.get("pixel") or {}
            e = s["centre_error_px"]
            rows.append([r.name, s["markers"], s["tp"], s["fp"], s["fn"], _f(s["precision"]), _f(s["recall"]),
                         _f(s["f1"]), _f(s.get("instance_ap")), _f(e["median"], ".2f"), _f(e["p95"], ".2f"),
                         _f(px.get("iou")), _f(px.get("f1")), _f(px.get("ap")), _f(s["seconds_per_megapixel"], ".2f")])
        return header, rows
    header = ["detector", "status", "markers found", "paired", "surveyed", "residual RMS (mm)", "detections",
              "detect (s)", "run (s)"]
    rows = []
    for r in cmp.detectors:
        rep = r.report
        rows.append([r.name, rep.get("status"), rep.get("n_markers"), len(r.paired), len(cmp.surveyed_names),
                     _mm(r.rms_m), sum(len(v) for v in r.detections.values()),
                     _f(r.seconds_detect, ".2f"), _f(r.seconds_total, ".2f")])
    return header, rows


def breakdown_table(cmp: DatasetComparison, dim: str) -> tuple[list[str], list[list[Any]]]:
    """(header, rows): per band, markers and each detector's recall and median centre error."""
    bands: list[str] = []
    for r in cmp.detectors:
        for b in r.breakdown.get(dim, {}):
            if b not in bands:
                bands.append(b)
    header = [dim, "markers"]
    for r in cmp.detectors:
        header += [f"{r.name} recall", f"{r.name} err (px)"]
        if dim == "background":
            header.append(f"{r.name} precision")
    rows = []
    for b in bands:
        first = next(r.breakdown[dim][b] for r in cmp.detectors if b in r.breakdown.get(dim, {}))
        row: list[Any] = [b, first["markers"]]
        for r in cmp.detectors:
            st = r.breakdown.get(dim, {}).get(b, {})
            row += [_f(st.get("recall")), _f(st.get("centre_error_median_px"), ".2f")]
            if dim == "background":
                row.append(_f(st.get("precision")))
        rows.append(row)
    return header, rows


def site_marker_table(cmp: SiteComparison) -> tuple[list[str], list[list[Any]]]:
    header = ["surveyed point"] + [f"{r.name} residual (mm)" for r in cmp.detectors] + \
        [f"{r.name} views" for r in cmp.detectors] + ["spread between detectors (mm)"]
    rows = []
    for m in cmp.markers:
        row: list[Any] = [m["name"]]
        row += [_f(m["residual_mm"].get(r.name), ".1f") if r.name in m["paired_by"] else "not paired"
                for r in cmp.detectors]
        row += [m["n_views"].get(r.name, 0) for r in cmp.detectors]
        row.append(_f(m["spread_mm"], ".1f"))
        rows.append(row)
    return header, rows


def site_image_table(cmp: SiteComparison) -> tuple[list[str], list[list[Any]]]:
    header = (["image", "difference"] + [f"{r.name} found" for r in cmp.detectors]
              + [f"{r.name} other detections" for r in cmp.detectors])
    rows = []
    for im in cmp.images:
        if im["disagree"]:
            union = set().union(*(set(v) for v in im["found"].values()))
            diff = "; ".join(f"{r.name} misses {', '.join(sorted(union - set(im['found'][r.name])))}"
                             for r in cmp.detectors if union - set(im["found"][r.name]))
            rows.append([im["image"], diff] + [", ".join(im["found"][r.name]) or "-" for r in cmp.detectors]
                        + [im["other"][r.name] for r in cmp.detectors])
    return header, rows


# ----------------------------------------------------------------------------------------------------
# summary.md


def _md_table(header, rows) -> str:
    esc = lambda v: str(v).replace("|", "\\|")  # noqa: E731
    lines = ["| " + " | ".join(esc(h) for h in header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(esc(v) for v in row) + " |" for row in rows]
    return "\n".join(lines)


def summary_markdown(cmp: Comparison) -> str:
    """A Markdown summary: recommendation, summary table, and the breakdowns or per-marker tables."""
    rec = cmp.recommendation
    src = cmp.root if isinstance(cmp, DatasetComparison) else cmp.inputs.root
    out = [f"# Detector comparison: {src}", "", f"Mode: {cmp.mode}. Detectors: "
           f"{', '.join(r.name for r in cmp.detectors)}.", "", "## Recommendation", ""]
    out.append(f"**{rec.choice or 'none'}**" + (" (insufficient evidence)" if rec.insufficient else ""))
    out += [""] + [f"- {line}" for line in rec.reasons] + ["", "## Summary", "", _md_table(*summary_table(cmp)), ""]
    if isinstance(cmp, DatasetComparison):
        for dim in ("type", "size", "blur", "background"):
            out += [f"## By {dim}", "", _md_table(*breakdown_table(cmp, dim)), ""]
        ag = cmp.agreement
        out += ["## Agreement", "", f"Found by every detector: {ag['found_by_all']}; by none: "
                f"{ag['found_by_none']}; found by one detector alone: "
                + ", ".join(f"{n} {c}" for n, c in ag["only"].items()) + ".", ""]
    else:
        out += ["## Surveyed points", "", _md_table(*site_marker_table(cmp)), ""]
        h, rows = site_image_table(cmp)
        out += ["## Images where the detectors disagree", ""]
        out += [_md_table(h, rows) if rows else "None: every image has the same markers detected by every "
                "detector.", ""]
    return "\n".join(out)


# ----------------------------------------------------------------------------------------------------
# report.html


def _read(path: Path):
    from .imageio import read_image

    return read_image(path)


def site_gallery(cmp: SiteComparison, max_views: int = 8, max_other: int = 16, crop_px: int = 128
                 ) -> dict[str, list[GalleryItem]]:
    """Review crops per detector.

    For each marker of the detector's georef run (paired ones in the surveyed points' order, then the
    unpaired ones), up to ``max_views`` of its inlier observations: the image measurements georef
    exports, with the refined centre drawn; the caption says whether the detector detected the marker in
    that image or georef found it by projecting the marker there. Then up to ``max_other`` raw
    detections that belong to no marker. Item ids are ``detector:marker:image``; x, y the drawn centre
    (OpenCV pixels), which :func:`cpdetect.rejects.apply_rejects` matches within its tolerance.
    """
    wanted: dict[str, list[tuple]] = {r.name: [] for r in cmp.detectors}
    order = {n: i for i, n in enumerate(cmp.surveyed_names)}
    for r in cmp.detectors:
        markers = sorted(r.report.get("markers", []),
                         key=lambda m: (order.get(m.get("surveyed_name"), len(order)), m["id"]))
        labels = {m["id"]: (m["surveyed_name"] if r.ok and m.get("surveyed_name") else f"{m['id']} (unpaired)")
                  for m in markers}
        per_image: dict[str, dict[str, list]] = {}
        for m in markers:
            for o in m["observations"]:
                if o.get("inlier", True):
                    per_image.setdefault(o["image"], {})[m["id"]] = [(float(o["x"]), float(o["y"]))]
        det_of: dict[tuple[str, str], dict] = {}
        other = []
        for image in sorted(set(r.detections) | set(per_image)):
            dets = r.detections.get(image, [])
            assigned, free = assign_detections(dets, per_image.get(image, {}))
            for mid, k in assigned.items():
                det_of[(mid, image)] = dets[k]
            other += [(image, dets[k]) for k in free]
        for m in markers:
            views = [o for o in sorted(m["observations"], key=lambda o: o["image"]) if o.get("inlier", True)]
            radii = [float(det_of[(m["id"], o["image"])]["radius_px"]) for o in views
                     if (m["id"], o["image"]) in det_of]
            default_r = float(np.median(radii)) if radii else 10.0
            for o in views[:max_views]:
                d = det_of.get((m["id"], o["image"]))
                how = f"detected, score {float(d['score']):.2f}" if d else "not detected (projected)"
                wanted[r.name].append((labels[m["id"]], o["image"], float(o["x"]), float(o["y"]),
                                       float(d["radius_px"]) if d else default_r, how))
        for image, d in other[:max_other]:
            wanted[r.name].append(("(no marker)", image, float(d["x"]), float(d["y"]), float(d["radius_px"]),
                                   f"detection, score {float(d['score']):.2f}"))
    by_image: dict[str, list] = {}
    for det, items in wanted.items():
        for k, it in enumerate(items):
            by_image.setdefault(it[1], []).append((det, k))
    crops: dict[tuple[str, int], bytes] = {}
    for image, keys in sorted(by_image.items()):
        arr = _read(cmp.inputs.images / image)
        for det, k in keys:
            _, _, x, y, radius, _ = wanted[det][k]
            crops[(det, k)] = crop_with_marker(arr, x, y, radius, crop_px)
    return {det: [GalleryItem(f"{det}:{label}:{image}", image, x, y, crops[(det, k)], f"{label} · {image} · {how}")
                  for k, (label, image, x, y, _, how) in enumerate(items)]
            for det, items in wanted.items()}


def dataset_gallery(cmp: DatasetComparison, max_items: int = 48, crop_px: int = 128) -> list[GalleryItem]:
    """Crops of the true markers that some detectors found and others missed (centre: the truth)."""
    items = []
    cache: dict[str, Any] = {}
    for dg in cmp.agreement["disagreements"][:max_items]:
        f = dg["file"]
        if f not in cache:
            cache.clear()
            cache[f] = _read(cmp.root / f)
        png = crop_with_marker(cache[f], dg["x"], dg["y"], dg["radius_px"], crop_px)
        cap = (f"{Path(f).name} · {dg['type']} r={dg['radius_px']:.0f}px (true centre) · missed by "
               f"{', '.join(dg['missed_by'])}")
        items.append(GalleryItem(f"{f}#{dg['truth']}", f, dg["x"], dg["y"], png, cap))
    return items


def build_html(cmp: Comparison, gallery: bool = True) -> HtmlReport:
    """The HTML report of a comparison (see the module docstring)."""
    from . import plots

    src = cmp.root if isinstance(cmp, DatasetComparison) else cmp.inputs.root
    rep = HtmlReport(f"cpdetect detector comparison: {Path(src).name}")
    rep.paragraph(f"{cmp.mode} mode, input {src}; detectors {', '.join(r.name for r in cmp.detectors)}.", "note")
    rec = cmp.recommendation
    rep.heading("Recommendation")
    rep.paragraph((f"Use {rec.choice}" if rec.choice else "No detector can be recommended")
                  + (" (insufficient evidence: see below)" if rec.insufficient and rec.choice else ""),
                  "bad" if rec.insufficient or not rec.choice else "good")
    rep.recommendation(rec.reasons)
    rep.heading("Summary")
    rep.table(*summary_table(cmp), table_id="summary")
    if isinstance(cmp, DatasetComparison):
        rep.paragraph(f"{cmp.n_images} images, {cmp.n_markers} true markers. A detection matches a true marker "
                      "within max(3 px, 0.25 radius); pixel metrics need a probability map.", "note")
        rep.heading("Precision-recall")
        rep.figure(plots.pr_curves({r.name: r.instance_pr for r in cmp.detectors},
                                   {r.name: None if r.pixel is None else (r.pixel.pos, r.pixel.neg)
                                    for r in cmp.detectors}), "instance and pixel precision-recall")
        rep.heading("Centre error")
        errs = {r.name: [m["distance"] for rec_ in r.records for m in rec_["matches"]] for r in cmp.detectors}
        rep.figure(plots.centre_error_histograms(errs), "distance of matched detections to the true centre")
        for dim, title in (("type", "By marker type"), ("size", "By marker size (equal-area radius)"),
                           ("blur", "By blur"), ("background", "By background category")):
            rep.heading(title)
            rep.table(*breakdown_table(cmp, dim), table_id=f"by-{dim}")
        ag = cmp.agreement
        rep.heading("Agreement")
        rep.paragraph(f"Found by every detector: {ag['found_by_all']}; by none: {ag['found_by_none']}; found by "
                      "one detector alone: " + ", ".join(f"{n} {c}" for n, c in ag["only"].items()) + ".")
        if gallery and ag["disagreements"]:
            rep.heading("Markers the detectors disagree on", 3)
            rep.gallery(dataset_gallery(cmp), rejectable=False)
        return rep
    rep.heading("Residuals")
    xy = cmp.surveyed_local[:, :2] if len(cmp.surveyed_local) else np.zeros((0, 2))
    res = {r.name: {n: m["residual_m"] for n, m in r.paired.items() if m["residual_m"] is not None}
           for r in cmp.detectors}
    rep.figure(plots.residual_top_view(cmp.surveyed_names, xy, res),
               "residual vectors (registered marker minus surveyed point) on a top view of the site")
    reproj = {r.name: [o["residual_px"] for m in r.paired.values() for o in m["observations"]
                       if o.get("inlier") and o.get("residual_px") is not None] for r in cmp.detectors}
    rep.figure(plots.centre_error_histograms(reproj, title="reprojection residual"),
               "reprojection residuals of the paired markers' observations")
    rep.heading("Surveyed points")
    rep.table(*site_marker_table(cmp), table_id="markers")
    rep.heading("Images where the detectors disagree")
    h, rows = site_image_table(cmp)
    if rows:
        rep.table(h, rows, table_id="disagree")
    else:
        rep.paragraph("None: every image has the same markers detected by every detector.")
    if gallery:
        rep.heading("Review gallery")
        rep.paragraph("Each crop shows one image measurement of a marker as georef exports it (its refined "
                      "centre drawn, up to 8 images per marker), then detections that belong to no marker. "
                      "Tick wrong ones and download rejects.json; a rerun with it (cpdetect georef --rejects, or "
                      "cpdetect compare --rejects) drops them.", "note")
        for det, items in site_gallery(cmp).items():
            rep.heading(det, 3)
            if items:
                rep.gallery(items)
            else:
                rep.paragraph("no detections")
    return rep


def write_outputs(cmp: Comparison, out_dir: str | Path, gallery: bool = True) -> dict[str, Path]:
    """Write ``report.html``, ``summary.json`` and ``summary.md`` into ``out_dir`` (atomically);
    returns their paths."""
    out = Path(out_dir)
    paths = {"html": out / "report.html", "json": out / "summary.json", "md": out / "summary.md"}
    write_json_atomic(paths["json"], summary_dict(cmp))
    write_text_atomic(paths["md"], summary_markdown(cmp))
    build_html(cmp, gallery).write(paths["html"])
    return paths


__all__ = ["SUMMARY_FORMAT", "summary_dict", "summary_markdown", "summary_table", "breakdown_table",
           "site_marker_table", "site_image_table", "site_gallery", "dataset_gallery", "build_html",
           "write_outputs"]
