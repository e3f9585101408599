"""Compare detectors, so a user can pick one per site with evidence (``cpdetect compare``).

Two modes, both pure functions returning dataclasses (writing files is :mod:`cpdetect.compare_report`):

* **Dataset** (an annotated marker dataset, :mod:`cpdetect.dataset`): every detector runs on every image;
  per detector the instance metrics of :mod:`cpdetect.evaluate` (same matching rule), the centre error,
  the pixel IoU/F1/AP (detectors that give probability maps), an instance precision-recall curve from
  the detection scores, the speed, and breakdowns by marker type, size band (equal-area radius, pixels),
  blur band (the truth's ``blur_px``, pixels) and background category (the image's ``category``).
* **Site** (reconstruction + images + surveyed points): every detector goes through the same 3D back
  end (:func:`cpdetect.pipeline.run_georef`, one output folder per detector); per detector the markers
  found, the pairings with surveyed points, the residuals (metres, local frame of the surveyed points),
  the run time; across detectors, which surveyed markers each paired, how far their estimates of one
  marker lie apart, and the images where they found different markers.

Each mode ends with a :class:`Recommendation` whose reasons are spelt out, and which says when the
evidence does not decide. Site ranking: completeness of the pairings first, then residual RMS, then
speed. Dataset ranking: instance F1, then median centre error, then speed.
"""
from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Mapping, Optional, Sequence

import numpy as np

from .errors import InputError, UsageError
from .evaluate import PixelCounts, _json_safe, score_image, summarize

log = logging.getLogger(__name__)

# (low, high, label): low <= value < high
SIZE_BANDS: tuple[tuple[float, float, str], ...] = (
    (0.0, 12.0, "<12 px"), (12.0, 24.0, "12-24 px"), (24.0, 48.0, "24-48 px"), (48.0, math.inf, ">=48 px"))
BLUR_BANDS: tuple[tuple[float, float, str], ...] = (
    (0.0, 0.5, "sharp (<0.5 px)"), (0.5, 2.0, "0.5-2 px"), (2.0, 4.0, "2-4 px"), (4.0, math.inf, ">=4 px"))
BREAKDOWNS = ("type", "size", "blur", "background")
UNKNOWN = "unknown"

# a residual RMS is "comparable" to another when within this ratio or this many metres
RMS_REL_MARGIN = 0.2
RMS_ABS_MARGIN_M = 0.001
# median centre errors (pixels) within RMS_REL_MARGIN or this many pixels count as equal
CENTRE_ABS_MARGIN_PX = 0.05
# one detector is "faster" when its time is below this fraction of the other's and shorter by at least
# SPEED_ABS_MARGIN_S seconds over the whole run (timings of a few milliseconds are noise)
SPEED_MARGIN = 0.8
SPEED_ABS_MARGIN_S = 0.5


def faster(seconds: float, other_seconds: float) -> bool:
    """True when ``seconds`` is clearly less than ``other_seconds`` (see :data:`SPEED_MARGIN`)."""
    return seconds < SPEED_MARGIN * other_seconds and other_seconds - seconds >= SPEED_ABS_MARGIN_S

Progress = Callable[..., Any]


def _no_progress(it, **kw):
    return it


def band_of(value: Optional[float], bands: Sequence[tuple[float, float, str]]) -> str:
    """Label of the band holding ``value`` (``low <= value < high``); ``"unknown"`` for None/NaN."""
    if value is None:
        return UNKNOWN
    v = float(value)
    if not math.isfinite(v):
        return UNKNOWN
    for low, high, label in bands:
        if low <= v < high:
            return label
    return bands[0][2] if v < bands[0][0] else bands[-1][2]


def parse_detector_names(text: str | Sequence[str]) -> list[str]:
    """``"classical,hma"`` -> ``["classical", "hma"]``, each checked against the detector registry.

    Raises :class:`UsageError` (one line) for an empty list, a repeated name or an unknown name (the
    message lists the valid ones).
    """
    from .detector import resolve_factory

    parts = text.split(",") if isinstance(text, str) else list(text)
    names = [p.strip() for p in parts if p.strip()]
    if not names:
        raise UsageError("--detectors needs at least one detector name, e.g. classical,hma")
    seen = set()
    for n in names:
        if n in seen:
            raise UsageError(f"detector {n!r} is listed twice in --detectors")
        seen.add(n)
        resolve_factory(n)  # raises UsageError listing the valid names
    return names


@dataclass
class Recommendation:
    """The detector to use (``choice``, None when nothing qualifies), why (``reasons``, one sentence
    each, the first about the choice), and whether the evidence is too thin to rely on
    (``insufficient``, with the reason among ``reasons``)."""

    choice: Optional[str]
    reasons: list[str]
    insufficient: bool = False

    def to_dict(self) -> dict:
        return {"choice": self.choice, "reasons": list(self.reasons), "insufficient": self.insufficient}


# ----------------------------------------------------------------------------------------------------
# Dataset mode


@dataclass
class DatasetDetectorResult:
    """One detector on a dataset.

    summary: :func:`cpdetect.evaluate.summarize` of all images (JSON-safe: NaN as None) plus
        ``instance_ap``. records: per-image records of :func:`cpdetect.evaluate.score_image`.
    pixel: pixel counts over the set (None when the detector gives no probability map).
    instance_pr: ``{"precision": [...], "recall": [...], "score": [...], "ap": float}``, one point per
        detection in decreasing score (recall relative to all true markers).
    breakdown: dimension (``type``, ``size``, ``blur``, ``background``) -> band label -> stats (see
        :func:`breakdown`).
    """

    name: str
    summary: dict
    records: list[dict]
    pixel: Optional[PixelCounts]
    instance_pr: dict
    breakdown: dict


@dataclass
class DatasetComparison:
    """Every detector on one dataset; ``agreement`` says which true markers each found (see
    :func:`dataset_agreement`)."""

    root: Path
    n_images: int
    n_markers: int
    detectors: list[DatasetDetectorResult]
    agreement: dict
    recommendation: Recommendation
    mode: str = "dataset"


def instance_pr(records: Sequence[dict], n_markers: Optional[int] = None) -> dict:
    """Instance precision-recall from the scores of matched (true positive) and unmatched (false
    positive) detections of ``records``; recall is relative to ``n_markers`` (default: all true markers
    of the records). AP is the step-wise area (as for pixels); NaN when there is no true marker."""
    total = sum(r["markers"] for r in records) if n_markers is None else int(n_markers)
    scored = [(float(m["score"]), 1) for r in records for m in r["matches"]]
    scored += [(float(f["score"]), 0) for r in records for f in r["false_positives"]]
    scored.sort(key=lambda s: -s[0])
    if not scored:
        return {"precision": [], "recall": [], "score": [], "ap": float("nan") if total == 0 else 0.0}
    score = np.array([s for s, _ in scored])
    hit = np.array([h for _, h in scored], float)
    tp = np.cumsum(hit)
    precision = tp / np.arange(1, len(hit) + 1)
    if total == 0:
        return {"precision": precision.tolist(), "recall": [float("nan")] * len(hit), "score": score.tolist(),
                "ap": float("nan")}
    recall = tp / total
    ap = float(np.sum(np.diff(np.concatenate([[0.0], recall])) * precision))
    return {"precision": precision.tolist(), "recall": recall.tolist(), "score": score.tolist(), "ap": ap}


def _marker_blur(m: dict, rec: dict) -> Optional[float]:
    v = m.get("blur_px", rec.get("blur_px"))
    return None if v is None or isinstance(v, bool) else float(v)


def _band_labels(dim: str, m: dict, rec: dict) -> str:
    if dim == "type":
        return str(m["type"])
    if dim == "size":
        return band_of(m["radius_px"], SIZE_BANDS)
    if dim == "blur":
        return band_of(_marker_blur(m, rec), BLUR_BANDS)
    return str(rec.get("category") or rec.get("background") or UNKNOWN)


def _band_order(dim: str, labels: set[str]) -> list[str]:
    if dim == "type":
        from .types import MARKER_TYPES

        fixed = list(MARKER_TYPES)
    elif dim == "size":
        fixed = [b[2] for b in SIZE_BANDS]
    elif dim == "blur":
        fixed = [b[2] for b in BLUR_BANDS]
    else:
        fixed = []
    return [b for b in fixed if b in labels] + sorted(labels - set(fixed) - {UNKNOWN}) + \
        ([UNKNOWN] if UNKNOWN in labels else [])


def breakdown(records: Sequence[dict]) -> dict:
    """Per-band marker statistics of evaluation ``records``.

    Returns ``{dim: {band: stats}}`` for dim in ``type``, ``size`` (true equal-area radius, pixels,
    :data:`SIZE_BANDS`), ``blur`` (the marker's ``blur_px``, else the image's; :data:`BLUR_BANDS`) and
    ``background`` (the image's ``category``). stats: ``markers``, ``tp``, ``fn``, ``recall``,
    ``centre_error_median_px``, ``centre_error_p95_px``; for ``background``, which is a property of whole
    images, also ``images``, ``fp``, ``precision`` and ``f1``. Bands keep a fixed order; NaN where undefined.
    """
    out: dict = {}
    for dim in BREAKDOWNS:
        acc: dict[str, dict] = {}
        for rec in records:
            for m, found in [(m, True) for m in rec["matches"]] + [(m, False) for m in rec["missed"]]:
                a = acc.setdefault(_band_labels(dim, m, rec), {"tp": 0, "fn": 0, "dist": []})
                if found:
                    a["tp"] += 1
                    a["dist"].append(float(m["distance"]))
                else:
                    a["fn"] += 1
            if dim == "background":
                a = acc.setdefault(_band_labels(dim, {}, rec), {"tp": 0, "fn": 0, "dist": []})
                a["fp"] = a.get("fp", 0) + int(rec["fp"])
                a["images"] = a.get("images", 0) + 1
        table = {}
        for label in _band_order(dim, set(acc)):
            a = acc[label]
            n = a["tp"] + a["fn"]
            d = np.array(a["dist"], float)
            stats = {"markers": n, "tp": a["tp"], "fn": a["fn"],
                     "recall": a["tp"] / n if n else float("nan"),
                     "centre_error_median_px": float(np.median(d)) if d.size else float("nan"),
                     "centre_error_p95_px": float(np.percentile(d, 95)) if d.size else float("nan")}
            if dim == "background":
                fp = a.get("fp", 0)
                stats.update(images=a.get("images", 0), fp=fp,
                             precision=a["tp"] / (a["tp"] + fp) if a["tp"] + fp else float("nan"),
                             f1=2 * a["tp"] / (2 * a["tp"] + fp + a["fn"]) if a["tp"] + fp + a["fn"] else float("nan"))
            table[label] = stats
        out[dim] = table
    return out


def dataset_agreement(results: Sequence[DatasetDetectorResult]) -> dict:
    """Which true markers each detector found.

    Returns ``{"found_by_all", "found_by_none", "only": {name: count found by this detector alone},
    "disagreements": [{"file", "truth", "x", "y", "radius_px", "type", "found_by": [...],
    "missed_by": [...], "detections": {name: [x, y]}}]}`` (one entry per true marker that some but not
    all detectors found, in image order).
    """
    names = [r.name for r in results]
    if not results:
        return {"found_by_all": 0, "found_by_none": 0, "only": {}, "disagreements": []}
    all_found = none_found = 0
    only = {n: 0 for n in names}
    disagreements = []
    for recs in zip(*(r.records for r in results)):
        file = recs[0]["file"]
        found: dict[int, dict[str, list]] = {}
        truths: dict[int, dict] = {}
        for name, rec in zip(names, recs):
            for m in rec["matches"]:
                found.setdefault(m["truth"], {})[name] = m
                truths.setdefault(m["truth"], m)
            for m in rec["missed"]:
                truths.setdefault(m["truth"], m)
        for j in sorted(truths):
            by = found.get(j, {})
            if len(by) == len(names):
                all_found += 1
            elif not by:
                none_found += 1
            else:
                if len(by) == 1:
                    only[next(iter(by))] += 1
                t = next(m for rec in recs for m in rec["missed"] if m["truth"] == j)
                tx, ty = float(t["x"]), float(t["y"])
                dets = {n: [float(tx + m["dx"]), float(ty + m["dy"])] for n, m in by.items()}
                disagreements.append({"file": file, "truth": j, "x": float(tx), "y": float(ty),
                                      "radius_px": float(t["radius_px"]), "type": t["type"],
                                      "found_by": [n for n in names if n in by],
                                      "missed_by": [n for n in names if n not in by], "detections": dets})
    return {"found_by_all": all_found, "found_by_none": none_found, "only": only, "disagreements": disagreements}


def _f1_margin(f1: float, n: int) -> float:
    """Two standard errors of an F1 near ``f1`` measured on ``n`` markers (binomial approximation)."""
    if n <= 0 or not math.isfinite(f1):
        return math.inf
    p = min(max(f1, 1.0 / (n + 2)), 1.0 - 1.0 / (n + 2))
    return 2.0 * math.sqrt(p * (1.0 - p) / n)


def _fmt(v: Any, spec: str = ".3f", unit: str = "") -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "n/a"
    return format(v, spec) + unit


def recommend_dataset(results: Sequence[DatasetDetectorResult]) -> Recommendation:
    """Instance F1 first: detectors within two standard errors of the best F1 count as tied; among
    them, the lowest median centre error (others within 20 % or 0.05 px count as tied); among those,
    the fastest when it is clearly faster than each other (:func:`faster`, on the whole run), else
    the best F1. The evidence is insufficient with fewer than 30
    true markers, one detector only, or when nothing separates the chosen detector from the runner-up."""
    if not results:
        return Recommendation(None, ["no detector was compared"], True)
    n = results[0].summary["markers"]

    def f1(r):
        v = r.summary["f1"]
        return -1.0 if v is None else float(v)

    def err(r):
        v = r.summary["centre_error_px"]["median"]
        return math.inf if v is None else float(v)

    def spmp(r):
        v = r.summary["seconds_per_megapixel"]
        return math.inf if v is None else float(v)

    def secs(r):
        return float(r.summary.get("seconds") or 0.0)

    def describe(r):
        s = r.summary
        return (f"{r.name}: F1 {_fmt(s['f1'])} (recall {_fmt(s['recall'])}, precision {_fmt(s['precision'])}), "
                f"median centre error {_fmt(s['centre_error_px']['median'], '.2f', ' px')}, "
                f"{_fmt(s['seconds_per_megapixel'], '.2f', ' s/MP')}")

    def err_tied(a, b):
        return abs(err(a) - err(b)) <= max(CENTRE_ABS_MARGIN_PX, RMS_REL_MARGIN * min(err(a), err(b)))

    margin = _f1_margin(max(f1(r) for r in results), n)
    top = max(f1(r) for r in results)
    tied = [r for r in results if top - f1(r) <= margin]
    emin = min(tied, key=err)
    tied = [r for r in tied if err_tied(r, emin)]
    tied.sort(key=lambda r: (-f1(r), err(r)))
    quick = min(tied, key=secs)
    best = quick if all(faster(secs(quick), secs(r)) for r in tied if r is not quick) else tied[0]
    others = sorted((r for r in results if r is not best), key=lambda r: (-f1(r), err(r), spmp(r)))
    lines = [describe(best)]
    notes = []
    if n < 30:
        notes.append(f"insufficient evidence: only {n} true markers in the dataset (use 30 or more)")
    decided = False
    for other in others:
        part = describe(other)
        if f1(best) - f1(other) > margin:
            part += f"; F1 lower by {f1(best) - f1(other):.3f} (more than two standard errors, {margin:.3f})"
            runner_decided = True
        elif not err_tied(best, other) and err(other) > err(best):
            part += f"; F1 comparable (within {margin:.3f}), centre error larger"
            runner_decided = True
        elif faster(secs(best), secs(other)):
            part += f"; F1 and centre error comparable, {spmp(other) / spmp(best):.1f}x slower"
            runner_decided = True
        else:
            part += "; F1, centre error and speed comparable"
            runner_decided = False
        if other is others[0]:
            decided = runner_decided
            if faster(secs(best), secs(other)):
                lines[0] += f", {spmp(other) / spmp(best):.1f}x faster than {other.name}"
        lines.append(part)
    if not others:
        notes.append("insufficient evidence: only one detector was compared")
    elif not decided:
        notes.append(f"insufficient evidence: {best.name} and {others[0].name} are not separated by F1, "
                     "centre error or speed on this dataset")
    return Recommendation(best.name, lines + notes, bool(notes))


def compare_dataset(dataset, detectors: Mapping[str, Any], limit: Optional[int] = None,
                    progress: Progress = _no_progress) -> DatasetComparison:
    """Run each detector (name -> object with ``detect``) on each image of ``dataset``
    (:class:`cpdetect.dataset.Dataset`, or a folder to load) and compare them.

    Each image is decoded once (:func:`cpdetect.imageio.read_image`, BGR uint8) and given to every
    detector; only ``detect`` is timed. Raises :class:`InputError` naming the file for unreadable data,
    ValueError when a detector reports a wrong image size.
    """
    from .dataset import Dataset, load_dataset, read_mask
    from .imageio import read_image

    if not isinstance(dataset, Dataset):
        dataset = load_dataset(dataset)
    items = dataset.images if limit is None else dataset.images[:max(int(limit), 0)]
    names = list(detectors)
    records: dict[str, list] = {n: [] for n in names}
    pixels: dict[str, PixelCounts] = {n: PixelCounts() for n in names}
    for item in progress(items, desc="images", unit="image"):
        path = dataset.image_path(item)
        image = read_image(path)
        h, w = image.shape[:2]
        truth_mask = None
        for name in names:
            t0 = time.perf_counter()
            result = detectors[name].detect(image)
            seconds = time.perf_counter() - t0
            if tuple(result.image_size) != (w, h):
                raise ValueError(f"detector {name!r} reported image size {result.image_size} for a {w}x{h} "
                                 f"image ({path})")
            if result.probability is not None and item.mask is not None:
                if truth_mask is None:
                    truth_mask = read_mask(dataset.mask_path(item), shape=(h, w))
                pixels[name].add(result.probability_at(w, h), truth_mask)
            records[name].append(score_image(item.file, w, h, seconds, result.detections, item.markers,
                                              item.meta))
    results = []
    for name in names:
        recs = records[name]
        px = pixels[name] if pixels[name].images else None
        summary = summarize(recs, px, detector=name)
        pr = instance_pr(recs)
        summary["instance_ap"] = pr["ap"]
        results.append(DatasetDetectorResult(name, _json_safe(summary), _json_safe(recs), px, pr,
                                             _json_safe(breakdown(recs))))
    agreement = dataset_agreement(results)
    return DatasetComparison(Path(dataset.root), len(items), sum(len(i.markers) for i in items), results,
                             agreement, recommend_dataset(results))


# ----------------------------------------------------------------------------------------------------
# Site mode


@dataclass(frozen=True)
class SiteInputs:
    """The files of a site: ``reconstruction`` (any format cpdetect reads), ``images`` folder,
    ``gcps`` (surveyed points CSV), optional ``mesh`` / ``cloud`` (PLY, model frame) and ``crs`` of the
    surveyed points when the CSV does not name it."""

    root: Path
    reconstruction: Path
    images: Path
    gcps: Path
    mesh: Optional[Path] = None
    cloud: Optional[Path] = None
    crs: Optional[str] = None


def is_dataset_folder(path: str | Path) -> bool:
    """True when ``path`` is a marker dataset (has ``markers.json``)."""
    from .dataset import MARKERS_JSON

    return (Path(path) / MARKERS_JSON).is_file()


def find_site(folder: str | Path, reconstruction: Optional[Path] = None, images: Optional[Path] = None,
              gcps: Optional[Path] = None, mesh: Optional[Path] = None, cloud: Optional[Path] = None,
              crs: Optional[str] = None, use_cloud: bool = True) -> SiteInputs:
    """The inputs of a site folder laid out as ``cpdetect synth scene`` writes it (``images/``,
    ``sparse/``, ``gcps.csv``, optional ``mesh.ply``, ``fused.ply``); any of them may be given
    explicitly instead. Raises a one-line :class:`InputError` naming what is missing."""
    root = Path(folder)
    if not root.exists():
        raise InputError("site or dataset folder not found", root)
    if not root.is_dir():
        raise InputError("expected a site folder (images/, sparse/, gcps.csv) or a dataset folder "
                         "(markers.json), found a file", root)
    images = Path(images) if images is not None else root / "images"
    if not images.is_dir():
        raise InputError("site has no images folder (expected SITE/images/, or pass --images)", images)
    if not any(p.is_file() for p in images.iterdir()):
        raise InputError("the site's images folder is empty", images)
    if reconstruction is None:
        reconstruction = next((p for p in (root / "sparse" / "0", root / "sparse", root / "reconstruction.json")
                               if p.exists() and (p.is_file() or any(p.glob("cameras.*")))), None)
        if reconstruction is None:
            raise InputError("site has no reconstruction (expected SITE/sparse/ with a COLMAP model, or pass "
                             "--reconstruction)", root)
    elif not Path(reconstruction).exists():
        raise InputError("reconstruction not found", reconstruction)
    gcps = Path(gcps) if gcps is not None else root / "gcps.csv"
    if not gcps.is_file():
        raise InputError("site has no surveyed points (expected SITE/gcps.csv, or pass --gcps)", gcps)
    if mesh is None and (root / "mesh.ply").is_file():
        mesh = root / "mesh.ply"
    if cloud is None and use_cloud and (root / "fused.ply").is_file():
        cloud = root / "fused.ply"
    for p, what in ((mesh, "mesh"), (cloud, "point cloud")):
        if p is not None and not Path(p).is_file():
            raise InputError(f"{what} not found", p)
    return SiteInputs(root, Path(reconstruction), images, gcps, None if mesh is None else Path(mesh),
                      None if cloud is None else Path(cloud), crs)


@dataclass
class SiteDetectorResult:
    """One detector through the georef back end.

    report: the run's ``report.json`` (format ``cpdetect.georef-report/1``). detections: image name ->
    list of detection dicts (the run's ``detections.json``; OpenCV pixels). seconds_total: wall time of
    the run in this call (small when the run resumed from its stage files); seconds_detect: time the
    detector spent on all images when they were detected (None if unknown). out_dir: the run's folder.
    """

    name: str
    report: dict
    detections: dict
    seconds_total: float
    seconds_detect: Optional[float]
    out_dir: Path

    @property
    def seconds(self) -> float:
        """The time used to compare speeds: detection time when known, else the whole run."""
        return self.seconds_detect if self.seconds_detect is not None else self.seconds_total

    @property
    def ok(self) -> bool:
        return self.report.get("status") in ("ok", "ambiguous")

    @property
    def paired(self) -> dict[str, dict]:
        """surveyed name -> marker entry of the report (only for a successful registration)."""
        if not self.ok:
            return {}
        return {m["surveyed_name"]: m for m in self.report["markers"] if m.get("surveyed_name")}

    @property
    def rms_m(self) -> Optional[float]:
        return self.report.get("rms_m") if self.ok and self.paired else None


@dataclass
class SiteComparison:
    """Every detector on one site.

    surveyed_names / surveyed_local: the surveyed points and their coordinates (m, 3) in the local
    metric frame the residuals are expressed in (x east, y north, z up for a geographic/projected CRS).
    markers: one entry per surveyed point, see :func:`site_agreement`. images: one entry per image.
    """

    inputs: SiteInputs
    surveyed_names: list[str]
    surveyed_local: np.ndarray
    detectors: list[SiteDetectorResult]
    markers: list[dict]
    images: list[dict]
    recommendation: Recommendation
    mode: str = "site"


def _detect_seconds(out_dir: Path) -> Optional[float]:
    """Sum of the per-image detection times the georef detect stage recorded (None if unavailable)."""
    from .fileio import read_json

    path = out_dir / "stages" / "detect.json"
    try:
        data = read_json(path, "stage file")["data"]
        return float(sum(float(v.get("seconds", 0.0)) for v in data.values()))
    except (InputError, KeyError, TypeError, AttributeError, ValueError):
        return None


def run_site_detector(inputs: SiteInputs, name: str, out_dir: Path, settings: Optional[dict] = None,
                      georef_settings: Any = None, progress: Progress = _no_progress,
                      rejects: Optional[Path] = None) -> SiteDetectorResult:
    """Georeference the site with detector ``name`` (resuming from ``out_dir`` when it holds an earlier
    run with the same inputs and settings) and collect what the comparison needs. ``rejects``: a
    reviewer's ``rejects.json`` (from an earlier report's gallery), honoured by the georef run.

    An :class:`InputError` raised by the back end once the detections are known (a later stage failed)
    becomes a ``failed`` report with that reason; one raised before (the site's files) propagates.
    """
    from dataclasses import replace

    from .pipeline import GeorefInputs, GeorefSettings, run_georef

    base = georef_settings if georef_settings is not None else GeorefSettings()
    gs = replace(base, detector=name, detector_settings=dict(settings or {}))
    gi = GeorefInputs(reconstruction=inputs.reconstruction, images=inputs.images, gcps=inputs.gcps,
                      out=Path(out_dir), crs=inputs.crs, cloud=inputs.cloud, mesh=inputs.mesh, rejects=rejects)
    t0 = time.perf_counter()
    detected: dict = {}
    try:
        report = run_georef(gi, gs, progress=progress, on_detections=detected.update)
    except UsageError:
        raise
    except InputError as exc:
        # once the detections are known, a failure is this detector's result, not a problem of the
        # site's files: record it and let the comparison go on
        if not detected:
            raise
        log.warning("detector %s: georef failed: %s", name, exc)
        report = {"status": "failed", "reason": exc.message, "detector": name, "mode": None, "n_markers": 0,
                  "n_paired": 0, "rms_m": None, "markers": [], "unpaired_surveyed": []}
    seconds = time.perf_counter() - t0
    detections = {name: list(d["detections"]) for name, d in sorted(detected.items())}
    return SiteDetectorResult(name, report, detections, seconds, _detect_seconds(Path(out_dir)), Path(out_dir))


def _union_observations(results: Sequence[SiteDetectorResult]) -> dict[tuple[str, str], list[tuple[float, float]]]:
    obs: dict[tuple[str, str], list[tuple[float, float]]] = {}
    for r in results:
        for name, m in r.paired.items():
            for o in m["observations"]:
                obs.setdefault((name, o["image"]), []).append((float(o["x"]), float(o["y"])))
    return obs


def assign_detections(detections: Sequence[Mapping], observations: Mapping[str, Sequence[tuple[float, float]]]
                      ) -> tuple[dict[str, int], list[int]]:
    """Assign one image's detections to surveyed markers.

    observations: surveyed name -> pixel positions (x, y) of that marker in this image (the georef
    observations of any detector). A detection belongs to the nearest marker whose observation lies
    within ``max(3 px, 0.5 * radius_px)`` of it. Returns ``({name: index of the nearest assigned
    detection}, [indices of detections assigned to no marker])``.
    """
    best: dict[str, tuple[float, int]] = {}
    free = []
    for k, d in enumerate(detections):
        tol = max(3.0, 0.5 * float(d.get("radius_px", 0.0)))
        hit, hit_d = None, math.inf
        for name, pts in observations.items():
            for (x, y) in pts:
                dist = math.hypot(float(d["x"]) - x, float(d["y"]) - y)
                if dist <= tol and dist < hit_d:
                    hit, hit_d = name, dist
        if hit is None:
            free.append(k)
        elif hit not in best or hit_d < best[hit][0]:
            best[hit] = (hit_d, k)
    return {n: k for n, (_, k) in best.items()}, free


def site_agreement(results: Sequence[SiteDetectorResult], surveyed_names: Sequence[str]
                   ) -> tuple[list[dict], list[dict]]:
    """Agreement between detectors on a site.

    Returns ``(markers, images)``. markers: per surveyed name ``{"name", "paired_by": [detectors],
    "residual_mm": {det: |residual| mm}, "n_views": {det: inlier views}, "spread_mm": largest distance
    between two detectors' estimates of the marker (local frame, mm; None with fewer than two)}``.
    images: per image ``{"image", "found": {det: [surveyed names detected here]}, "other": {det: number
    of detections near no paired marker}, "disagree": bool}``; a marker counts as detected in an image
    when a raw detection lies near its georef observation there (:func:`assign_detections`; observations
    of all detectors are pooled, so a marker one detector missed everywhere still counts against it).
    """
    markers = []
    for s in surveyed_names:
        by = [r for r in results if s in r.paired]
        res = {r.name: (None if r.paired[s]["residual_m"] is None
                        else 1000.0 * float(np.linalg.norm(r.paired[s]["residual_m"]))) for r in by}
        pts = [np.asarray(r.paired[s].get("local_point"), float) for r in by if r.paired[s].get("local_point")]
        spread = None
        if len(pts) >= 2:
            spread = 1000.0 * max(float(np.linalg.norm(a - b)) for i, a in enumerate(pts) for b in pts[i + 1:])
        markers.append({"name": s, "paired_by": [r.name for r in by], "residual_mm": res,
                        "n_views": {r.name: int(r.paired[s]["n_views"]) for r in by}, "spread_mm": spread})
    obs = _union_observations(results)
    image_names = sorted({n for r in results for n in r.detections})
    images = []
    for image in image_names:
        here = {name: pts for (name, im), pts in obs.items() if im == image}
        found, other = {}, {}
        for r in results:
            assigned, free = assign_detections(r.detections.get(image, []), here)
            found[r.name] = sorted(assigned)
            other[r.name] = len(free)
        sets = {tuple(v) for v in found.values()}
        images.append({"image": image, "found": found, "other": other, "disagree": len(sets) > 1})
    return markers, images


def recommend_site(results: Sequence[SiteDetectorResult], n_surveyed: int) -> Recommendation:
    """Completeness of the pairings first, then residual RMS, then speed (see the module docstring).

    Among the detectors with the most pairings (a clean ``ok`` status preferred over ``ambiguous``),
    those whose RMS is within 20 % or 1 mm of the lowest count as tied; the fastest of them is chosen
    when it is clearly faster than each other (:func:`faster`: under 80 % of the other's time and at
    least half a second less), else the lowest RMS. The
    evidence is insufficient when no detector georeferenced the site, when the choice pairs fewer than
    4 surveyed points (residuals of a 7-parameter fit on 3 points say little), when only one detector
    ran, or when nothing separates the choice from the runner-up.
    """
    if not results:
        return Recommendation(None, ["no detector was compared"], True)

    def rms(r: SiteDetectorResult) -> float:
        return r.rms_m if r.rms_m is not None else math.inf

    def rms_tied(a: float, b: float) -> bool:
        return abs(a - b) <= max(RMS_ABS_MARGIN_M, RMS_REL_MARGIN * max(a, b))

    usable = [r for r in results if r.ok and r.paired]
    if not usable:
        lines = ["insufficient evidence: no detector georeferenced the site"]
        for r in results:
            lines.append(f"{r.name}: {r.report.get('status')} ({r.report.get('reason') or 'no reason given'}), "
                         f"{r.report.get('n_markers', 0)} markers found")
        return Recommendation(None, lines, True)
    n_best = max(len(r.paired) for r in usable)
    top = [r for r in usable if len(r.paired) == n_best]
    top = [r for r in top if r.report.get("status") == "ok"] or top
    rmin = min(rms(r) for r in top)
    tied = sorted((r for r in top if rms_tied(rms(r), rmin)), key=rms)
    quick = min(tied, key=lambda r: r.seconds)
    best = quick if all(faster(quick.seconds, r.seconds) for r in tied if r is not quick) else tied[0]
    others = sorted((r for r in results if r is not best),
                    key=lambda r: (-len(r.paired), r.report.get("status") != "ok", rms(r), r.seconds))
    what = (f"all {n_surveyed} surveyed markers paired" if n_best == n_surveyed
            else f"{n_best} of {n_surveyed} surveyed markers paired")
    head = f"{best.name}: {what}, residual RMS {1000 * best.rms_m:.1f} mm"
    if best.report.get("status") == "ambiguous":
        head += " (pairing ambiguous)"
    lines = [head]
    notes = []
    decided = False
    for other in others:
        n_o = len(other.paired)
        if not other.ok:
            part = (f"{other.name}: {other.report.get('status')} ({other.report.get('reason') or 'no reason'}), "
                    f"{other.report.get('n_markers', 0)} markers found")
            runner_decided = True
        else:
            if set(other.paired) == set(best.paired):
                part = f"{other.name} found the same {n_o}"
            else:
                missed = sorted(set(best.paired) - set(other.paired))
                extra = sorted(set(other.paired) - set(best.paired))
                notes_o = ([f"missed {', '.join(missed)}"] if missed else []) + \
                    ([f"also paired {', '.join(extra)}"] if extra else [])
                part = f"{other.name} paired {n_o} of {n_surveyed} ({'; '.join(notes_o)})"
            part += f", residual RMS {1000 * other.rms_m:.1f} mm"
            if n_o < n_best:
                part += "; fewer pairings"
                runner_decided = True
            elif other.report.get("status") != "ok" and best.report.get("status") == "ok":
                part += "; pairing ambiguous"
                runner_decided = True
            elif not rms_tied(rms(other), rms(best)) and rms(other) > rms(best):
                part += "; larger residuals"
                runner_decided = True
            elif faster(best.seconds, other.seconds):
                part += f"; residuals comparable, {other.seconds / best.seconds:.1f}x slower"
                runner_decided = True
            else:
                part += "; residuals and speed comparable"
                runner_decided = False
        if other is others[0]:
            decided = runner_decided
            if faster(best.seconds, other.seconds):
                lines[0] += f", {other.seconds / best.seconds:.1f}x faster than {other.name}"
        lines.append(part)
    unpaired_by_all = sorted(set(n for r in results for n in r.report.get("unpaired_surveyed", []))
                             - set(n for r in results for n in r.paired))
    if unpaired_by_all:
        lines.append(f"no detector paired {', '.join(unpaired_by_all)} (not visible in enough images, or "
                     "not detected)")
    if n_best < 4:
        notes.append(f"insufficient evidence: only {n_best} surveyed points paired; residuals of a "
                     "7-parameter fit on so few points say little")
    if not others:
        notes.append("insufficient evidence: only one detector was compared")
    elif not decided:
        notes.append(f"insufficient evidence: {best.name} and {others[0].name} do equally well on this site")
    return Recommendation(best.name, lines + notes, bool(notes))


def compare_site(inputs: SiteInputs, names: Sequence[str], work_dir: str | Path,
                 settings: Optional[Mapping[str, dict]] = None, georef_settings: Any = None,
                 progress: Progress = _no_progress, rejects: Optional[Path] = None) -> SiteComparison:
    """Run every detector of ``names`` through the georef back end (``work_dir/runs/<name>/``, resumable)
    and compare them. ``settings``: detector name -> its settings. ``rejects``: a reviewer's
    ``rejects.json``, passed on to every detector's run (a reject names an image and a pixel, whichever
    detector found it)."""
    from .pipeline import load_surveyed

    surveyed = load_surveyed(Path(inputs.gcps), inputs.crs)
    results = []
    for name in names:
        log.info("site %s: detector %s", inputs.root, name)
        results.append(run_site_detector(inputs, name, Path(work_dir) / "runs" / name,
                                         (settings or {}).get(name), georef_settings, progress, rejects))
    markers, images = site_agreement(results, surveyed.names)
    rec = recommend_site(results, len(surveyed.names))
    return SiteComparison(inputs, list(surveyed.names), np.asarray(surveyed.local, float), results, markers,
                          images, rec)


__all__ = ["SIZE_BANDS", "BLUR_BANDS", "BREAKDOWNS", "band_of", "parse_detector_names", "Recommendation",
           "DatasetDetectorResult", "DatasetComparison", "instance_pr", "breakdown", "dataset_agreement",
           "recommend_dataset", "compare_dataset", "SiteInputs", "is_dataset_folder", "find_site",
           "SiteDetectorResult", "SiteComparison", "run_site_detector", "assign_detections", "site_agreement",
           "recommend_site", "compare_site", "faster"]
