"""The georeferencing part of ``cpdetect demo``: a synthetic site, ``georef`` on it, and a check
of the result against the site's truth (pairing, transform, residuals).

A marker found by georef is *the* truth marker nearest to its model point when that one is within a
tenth of its size (markers are triangulated to well under a millimetre on the synthetic sites); a
pairing is correct when georef's surveyed name is that marker's name.
"""
from __future__ import annotations

import json
import logging
from dataclasses import asdict
from pathlib import Path
from typing import Callable, Optional

import numpy as np

log = logging.getLogger(__name__)


def demo_site_settings(seed: int = 0, n_images: int = 32):
    """The demo's site: a pier corner with 6 markers, ``n_images`` photos of 1024 x 683 pixels."""
    from .synth_scene import SiteSettings

    return SiteSettings(seed=seed, n_images=n_images, markers=6, width=1024, height=683, cloud_spacing=0.012,
                        supersample=4)


def make_site(folder: Path, settings) -> Path:
    """Write the site into ``folder`` unless the same settings are already there (a rerun reuses it)."""
    from .synth_scene import write_site

    truth = folder / "truth.json"
    if truth.is_file():
        try:
            if json.loads(truth.read_text())["settings"] == json.loads(json.dumps(asdict(settings))):
                log.info("demo: reusing the site in %s", folder)
                return folder
        except (KeyError, ValueError):
            pass
    log.info("demo: rendering a synthetic site (%d images) in %s", settings.n_images, folder)
    write_site(folder, settings, overwrite=True)
    return folder


def compare_with_truth(report: dict, truth: dict) -> dict:
    """Pairing and residuals of a georef report against the site's truth."""
    names = [m["name"] for m in truth["markers"]]
    centres = np.array([m["center_model"] for m in truth["markers"]])
    upm = float(truth["model_units_per_metre"])
    size = {m["name"]: m["size_m"] * upm for m in truth["markers"]}
    rows, correct, wrong = [], 0, 0
    found = set()
    for m in report["markers"]:
        d = np.linalg.norm(centres - np.asarray(m["model_point"]), axis=1)
        k = int(d.argmin())
        true_name = names[k] if d[k] < 0.1 * size[names[k]] else None
        if true_name:
            found.add(true_name)
        ok = m["surveyed_name"] is not None and m["surveyed_name"] == true_name
        correct += ok
        wrong += m["surveyed_name"] is not None and not ok
        rows.append({"id": m["id"], "is": true_name, "paired_with": m["surveyed_name"], "correct": ok,
                     "error_to_truth_m": float(d[k] / upm) if true_name else None,
                     "residual_m": None if m["residual_m"] is None else float(np.linalg.norm(m["residual_m"]))})
    surveyed_seen = sorted(m["name"] for m in truth["markers"] if m["surveyed"] and m["printed"]
                           and len(m["visible_in"]) >= 2)
    return {"rows": rows, "correct": correct, "wrong": wrong, "surveyed_visible": surveyed_seen,
            "missed": sorted(set(surveyed_seen) - {r["paired_with"] for r in rows if r["correct"]}),
            "all_paired": set(surveyed_seen) <= {r["paired_with"] for r in rows if r["correct"]} and wrong == 0}


def transform_error_at_markers(crs_from_model: dict, truth: dict) -> np.ndarray:
    """|T(c) - T_true(c)| (metres) at every true marker centre c (model frame) for a report's
    ``crs_from_model`` T."""
    from geometry.transforms import Sim3

    c = np.array([m["center_model"] for m in truth["markers"]])
    est = Sim3.from_dict(crs_from_model)
    tru = Sim3.from_dict(truth["world_from_model"])
    return np.linalg.norm(est(c) - tru(c), axis=1)


def run_site_demo(workdir: Path, seed: int = 0, detector: str = "classical", n_images: int = 32,
                  print_fn: Callable[[str], None] = print, progress: Optional[Callable] = None) -> dict:
    """Render a site in ``workdir/site``, georeference it into ``workdir/georef`` and print the pairing,
    the transform and the residuals against the truth. Returns the comparison (also written to
    ``workdir/georef-vs-truth.json``)."""
    from .fileio import write_json_atomic
    from .pipeline import GeorefInputs, GeorefSettings, run_georef

    workdir = Path(workdir)
    site = make_site(workdir / "site", demo_site_settings(seed, n_images))
    inputs = GeorefInputs(reconstruction=site / "sparse", images=site / "images", gcps=site / "gcps.csv",
                          out=workdir / "georef", crs="EPSG:25832", cloud=site / "fused.ply", mesh=site / "mesh.ply")
    report = run_georef(inputs, GeorefSettings(detector=detector, seed=seed),
                        progress=progress or (lambda it, **kw: it))
    truth = json.loads((site / "truth.json").read_text())
    cmp = compare_with_truth(report, truth)
    print_fn(f"georef on a synthetic site ({n_images} images, {len(truth['markers'])} markers; detector "
             f"{detector}, mode {report['mode']}): status {report['status']}")
    others = [r for r in cmp["rows"] if r["is"] is None and r["paired_with"] is None]
    for r in cmp["rows"]:
        if r in others:
            continue
        verdict = "correct" if r["correct"] else ("WRONG" if r["paired_with"] else "not paired")
        res = "" if r["residual_m"] is None else f"  residual {1000 * r['residual_m']:.1f} mm"
        err = "" if r["error_to_truth_m"] is None else f"  3D error {1000 * r['error_to_truth_m']:.2f} mm"
        print_fn(f"  {r['id']} is {r['is'] or 'no marker'} -> paired with {r['paired_with'] or '-'}: "
                 f"{verdict}{res}{err}")
    if others:
        print_fn(f"  ({len(others)} more points found that are no marker of the site, e.g. X-corners of its "
                 f"textures; none of them paired)")
    cfm = report.get("crs_from_model")
    if cfm:
        err = transform_error_at_markers(cfm, truth)
        print_fn(f"  transform model -> {truth['crs']}: scale {cfm['scale']:.6f} (truth "
                 f"{truth['world_from_model']['scale']:.6f}); at the markers it is off from the true transform "
                 f"by {1000 * err.mean():.1f} mm on average ({1000 * err.max():.1f} mm at most)")
    if report.get("rms_m") is not None:
        print_fn(f"  residual RMS {1000 * report['rms_m']:.1f} mm "
                 f"(survey noise {1000 * truth['settings']['survey_sigma']:.1f} mm per axis)")
    print_fn(f"  {cmp['correct']} of {len(cmp['surveyed_visible'])} visible surveyed markers paired correctly, "
             f"{cmp['wrong']} wrong" + (f"; missed: {', '.join(cmp['missed'])}" if cmp["missed"] else "")
             + ("  -> ALL MARKERS PAIRED CORRECTLY" if cmp["all_paired"] else ""))
    write_json_atomic(workdir / "georef-vs-truth.json", cmp)
    return cmp
