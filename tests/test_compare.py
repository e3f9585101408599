"""`cpdetect compare`: dataset and site comparisons, the recommendation and its reasons, the report in a
real headless browser, and rejects.

Site mode runs on a small synthetic site with two test-registered detectors that return the site's true
marker projections plus 0.5 px noise ("oracle"), one of them never reporting GCP05 ("oracle_drop"):
this exercises the comparison through the real georef back end whatever the state of the detectors.
Dataset mode runs the classical detector and a wrapper of it that drops every detection it typed
"square" on a few synthetic images.
"""
import functools
import hashlib
import json
import math
import re

import cv2
import numpy as np
import pytest

import cpdetect
from cpdetect import detector as detector_registry
from cpdetect.browser import dump_dom, find_chromium, screenshot
from cpdetect.cli import main
from cpdetect.compare import (Recommendation, SiteDetectorResult, band_of, breakdown, instance_pr,
                              recommend_site, SIZE_BANDS, BLUR_BANDS)
from cpdetect.evaluate import PixelCounts
from cpdetect.html_report import read_rejects
from cpdetect.imageio import read_image
from cpdetect.plots import pixel_pr
from cpdetect.rejects import apply_rejects, is_rejected
from cpdetect.synth_scene import SiteSettings, write_site
from cpdetect.types import DetectionResult, MarkerDetection

DROPPED = "GCP05"
DET_SIGMA = 0.5
needs_chromium = pytest.mark.skipif(find_chromium() is None, reason="chromium is installed by make setup")


def _key(image) -> str:
    return hashlib.sha1(np.ascontiguousarray(image).tobytes()).hexdigest()


class _Oracle:
    """True marker projections of a synthetic site + Gaussian noise (deterministic per image)."""

    def __init__(self, table, drop=(), name="oracle"):
        self.table, self.drop, self.name = table, set(drop), name

    def detect(self, image):
        im = self.table[_key(image)]
        rng = np.random.default_rng(int(_key(image)[:8], 16))
        dets = [MarkerDetection(m["x"] + rng.normal(0, DET_SIGMA), m["y"] + rng.normal(0, DET_SIGMA), 0.9,
                                m["type"], m["radius_px"], DET_SIGMA)
                for m in im["markers"] if m["name"] not in self.drop]
        return DetectionResult(dets, (image.shape[1], image.shape[0]))


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    root = tmp_path_factory.mktemp("compare")
    write_site(root / "site", SiteSettings(seed=3, n_images=12, width=640, height=427, cloud_spacing=0.015,
                                           supersample=3))
    truth = json.loads((root / "site" / "truth.json").read_text())
    table = {_key(read_image(root / "site" / "images" / im["name"])): im for im in truth["images"]}
    detector_registry.register_detector("oracle", lambda: _Oracle(table))
    detector_registry.register_detector("oracle_drop", lambda: _Oracle(table, [DROPPED], "oracle_drop"))
    out = root / "report"
    rc = main(["-q", "compare", str(root / "site"), "--detectors", "oracle,oracle_drop", "--out", str(out),
               "--no-cloud"])
    yield root, truth, out, rc
    for name in ("oracle", "oracle_drop"):
        detector_registry._REGISTERED.pop(name, None)


def test_site_comparison_shows_the_missed_marker_in_summary_and_recommendation(site):
    root, truth, out, rc = site
    assert rc == 0
    seen = sorted(m["name"] for m in truth["markers"] if len(m["visible_in"]) >= 3)
    assert DROPPED in seen and len(seen) == 9
    s = json.loads((out / "summary.json").read_text())
    assert s["format"] == "cpdetect.compare/1" and s["mode"] == "site" and s["n_surveyed"] == 9
    full, drop = s["results"]["oracle"], s["results"]["oracle_drop"]
    assert full["status"] == drop["status"] == "ok"
    assert full["paired"] == seen
    assert drop["paired"] == [n for n in seen if n != DROPPED] and drop["unpaired_surveyed"] == [DROPPED]
    # residuals: the injected survey noise (3 mm per axis) dominates; 7-parameter fit on 9 points
    floor = math.sqrt(3 * 0.003 ** 2 * (9 - 7 / 3) / 9)
    assert 0.4 * floor < full["rms_m"] < 2.0 * floor
    # the two detectors place the markers they share within a few millimetres of each other
    spreads = {m["name"]: m["spread_mm"] for m in s["markers"]}
    assert spreads[DROPPED] is None
    assert all(0.0 < v < 10.0 for n, v in spreads.items() if n != DROPPED)
    # images where they disagree: exactly those where the full oracle found GCP05, and only by GCP05
    where = [im["image"] for im in s["images_disagreeing"]]
    gcp05_images = {im["name"] for im in truth["images"] if any(m["name"] == DROPPED for m in im["markers"])}
    assert 3 <= len(where) <= len(gcp05_images) and set(where) <= gcp05_images
    for im in s["images_disagreeing"]:
        assert set(im["found"]["oracle"]) - set(im["found"]["oracle_drop"]) == {DROPPED}
        assert set(im["found"]["oracle_drop"]) <= set(im["found"]["oracle"])
    # the recommendation: completeness first, with the reason spelt out
    rec = s["recommendation"]
    assert rec["choice"] == "oracle" and rec["insufficient"] is False
    assert rec["reasons"][0].startswith("oracle: all 9 surveyed markers paired, residual RMS")
    assert any(f"oracle_drop paired 8 of 9 (missed {DROPPED})" in r for r in rec["reasons"])
    md = (out / "summary.md").read_text()
    assert f"(missed {DROPPED})" in md and f"oracle_drop misses {DROPPED}" in md
    # each detector's run is a normal georef output folder
    assert json.loads((out / "runs" / "oracle_drop" / "report.json").read_text())["n_paired"] == 8


def test_a_detector_that_finds_nothing_is_reported_as_failed_not_an_error(site):
    from cpdetect.compare import compare_site, find_site

    root, truth, out, rc = site
    table = detector_registry._REGISTERED["oracle"]().table
    detector_registry.register_detector("nothing", lambda: _Oracle(table, [m["name"] for m in truth["markers"]]))
    try:
        cmp = compare_site(find_site(root / "site", use_cloud=False), ["nothing", "oracle"], out)
    finally:
        detector_registry._REGISTERED.pop("nothing", None)
    nothing, oracle = cmp.detectors
    assert nothing.report["status"] == "failed" and nothing.report["reason"] and not nothing.paired
    assert sum(map(len, nothing.detections.values())) == 0
    assert len(oracle.paired) == 9 and oracle.report["stages"]["ran"] == []  # resumed from the first run
    assert cmp.recommendation.choice == "oracle" and not cmp.recommendation.insufficient
    assert cmp.recommendation.reasons[1].startswith("nothing: failed (")
    assert all(im["disagree"] == bool(im["found"]["oracle"]) for im in cmp.images)


def test_compare_passes_rejects_to_every_georef_run(site, tmp_path, capsys):
    """The gallery's rejects.json given to compare: each detector's run drops them (here every
    observation of GCP03: the oracle no longer pairs it); a bad rejects file fails before any run."""
    root, truth, out, rc = site
    first = json.loads((out / "runs" / "oracle" / "report.json").read_text())
    gcp03 = next(m for m in first["markers"] if m["surveyed_name"] == "GCP03")
    path = tmp_path / "rejects.json"
    path.write_text(json.dumps({"format": "cpdetect.rejects/1", "rejects": [
        {"id": gcp03["id"], "image": o["image"], "x": o["x"], "y": o["y"]} for o in gcp03["observations"]]}))
    again = tmp_path / "report"
    assert main(["-q", "compare", str(root / "site"), "--detectors", "oracle", "--out", str(again), "--no-cloud",
                 "--no-gallery", "--rejects", str(path)]) == 0
    s = json.loads((again / "summary.json").read_text())
    assert s["results"]["oracle"]["unpaired_surveyed"] == ["GCP03"] and len(s["results"]["oracle"]["paired"]) == 8
    run = json.loads((again / "runs" / "oracle" / "report.json").read_text())
    assert run["rejects"]["n_rejects"] == len(gcp03["observations"]) and run["rejects"]["removed_detections"] >= 3
    capsys.readouterr()
    path.write_text('{"rejects": [{"image": "a.jpg"}]}')
    bad_out = tmp_path / "bad"
    assert main(["compare", str(root / "site"), "--detectors", "oracle", "--out", str(bad_out),
                 "--rejects", str(path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(path) in err[0] and "rejects[0] needs id, image, x, y" in err[0]
    assert not bad_out.exists()


@needs_chromium
def test_site_report_opens_in_a_browser_with_plots_gallery_and_summary_table(site, tmp_path):
    root, truth, out, rc = site
    assert rc == 0
    html = (out / "report.html").read_text()
    assert "http://" not in html and "https://" not in html  # self-contained
    dom = dump_dom(out / "report.html")
    body = re.search(r"<body[^>]*>", dom).group(0)
    assert 'data-ready="1"' in body and 'data-broken-images="0"' in body
    n_img = int(re.search(r'data-images="(\d+)"', body).group(1))
    n_crops = dom.count('class="crop"')
    n_plots = dom.count('class="plot"')
    s = json.loads((out / "summary.json").read_text())
    views = sum(min(8, v) for m in s["markers"] for v in m["n_views"].values())
    assert n_plots == 2 and views <= n_crops <= views + 2 * 16 and n_img == n_plots + n_crops
    # the gallery has a reject box per crop, carrying the detection's image and pixel
    assert dom.count('class="reject"') == n_crops and 'data-image="IMG_' in dom
    # a reject ticked in the gallery, saved as rejects.json, removes exactly that detection on a rerun
    tile = re.search(r'detected, score [^<]*</div><label><input type="checkbox" class="reject" data-id="([^"]+)" '
                     r'data-image="([^"]+)" data-x="([^"]+)" data-y="([^"]+)"', dom)
    (tmp_path / "rejects.json").write_text(json.dumps({"format": "cpdetect.rejects/1", "rejects": [
        {"id": tile.group(1), "image": tile.group(2), "x": float(tile.group(3)), "y": float(tile.group(4))}]}))
    det_name = tile.group(1).split(":")[0]
    dets = json.loads((out / "runs" / det_name / "detections.json").read_text())
    by_image = {im["file"]: im["detections"] for im in dets["images"]}
    applied = apply_rejects(by_image, read_rejects(tmp_path / "rejects.json"), tol_px=3.0)
    assert len(applied.removed) == 1 and applied.removed[0]["image"] == tile.group(2)
    assert applied.removed[0]["distance_px"] < 2.0 and not applied.unmatched  # refined vs raw centre
    assert sum(map(len, applied.detections.values())) == sum(map(len, by_image.values())) - 1
    rec = re.search(r'<div class="rec" id="recommendation">(.*?)</div>', dom, re.S).group(1)
    assert f"missed {DROPPED}" in rec
    markers = re.search(r'<table id="markers">(.*?)</table>', dom, re.S).group(1)
    row = re.search(rf"<tr><td>{DROPPED}</td>(.*?)</tr>", markers).group(1)
    assert "not paired" in row
    # a screenshot of the top of the page shows the summary table: a block of equally long horizontal
    # border lines (one above the header, one under it and one under each detector's row)
    png = screenshot(out / "report.html", tmp_path / "shot.png", 1280, 900)
    shot = cv2.imread(str(png))
    assert shot is not None and shot.shape[:2] == (900, 1280)
    border = np.all(np.abs(shot.astype(int) - [222, 215, 208]) <= 6, axis=2)  # #d0d7de in BGR
    runs = {}
    for y in range(shot.shape[0]):
        xs = np.flatnonzero(border[y])
        if xs.size > 300 and xs[-1] - xs[0] + 1 == xs.size:
            runs.setdefault((int(xs[0]), int(xs[-1])), []).append(y)
    tables = [ys for (x0, x1), ys in runs.items() if 500 < x1 - x0 < 1150 and len(ys) == 2 + 2]
    assert len(tables) == 1, f"no summary table in the screenshot: {runs}"
    header_bg = np.all(np.abs(shot.astype(int) - [247, 245, 243]) <= 2, axis=2)  # #f3f5f7
    ys = tables[0]
    assert header_bg[ys[0]:ys[1]].sum() > 1000


@needs_chromium
@pytest.mark.filterwarnings("ignore:Mean of empty slice:RuntimeWarning")
def test_dataset_comparison_breakdowns_and_report(tmp_path):
    from cpdetect.classical import ClassicalDetector

    assert main(["-q", "synth", "images", "--out", str(tmp_path / "ds"), "--n", "4", "--seed", "1",
                 "--split", "test"]) == 0
    inner = ClassicalDetector()

    @functools.lru_cache(maxsize=8)
    def cached(key, image_bytes, shape):
        return inner.detect(np.frombuffer(image_bytes, np.uint8).reshape(shape))

    class NoSquare:
        name = "nosquare"

        def detect(self, image):
            r = cached(_key(image), np.ascontiguousarray(image).tobytes(), image.shape)
            return DetectionResult([d for d in r.detections if d.type != "square"], r.image_size, r.probability)

    class Classical:
        name = "classical_cached"

        def detect(self, image):
            return cached(_key(image), np.ascontiguousarray(image).tobytes(), image.shape)

    for f in sorted((tmp_path / "ds" / "images").iterdir()):  # both detectors then take no time
        image = read_image(f)
        cached(_key(image), np.ascontiguousarray(image).tobytes(), image.shape)
    cpdetect.register_detector("nosquare", NoSquare)
    cpdetect.register_detector("classical_cached", Classical)
    try:
        rc = main(["-q", "compare", str(tmp_path / "ds"), "--detectors", "classical_cached,nosquare",
                   "--out", str(tmp_path / "rep")])
    finally:
        detector_registry._REGISTERED.pop("nosquare", None)
        detector_registry._REGISTERED.pop("classical_cached", None)
    assert rc == 0
    s = json.loads((tmp_path / "rep" / "summary.json").read_text())
    assert s["mode"] == "dataset" and s["n_images"] == 4
    full, drop = s["results"]["classical_cached"], s["results"]["nosquare"]
    squares = full["tp"] - drop["tp"]
    assert squares >= 1 and drop["tp"] >= 1  # the seed gives both kinds of matches
    assert s["agreement"]["only"] == {"classical_cached": squares, "nosquare": 0}
    assert len(s["agreement"]["disagreements"]) == squares
    assert all(d["missed_by"] == ["nosquare"] for d in s["agreement"]["disagreements"])
    # every breakdown partitions the true markers
    for dim in ("type", "size", "blur", "background"):
        bands = full["breakdown"][dim]
        assert sum(b["markers"] for b in bands.values()) == full["markers"] == s["n_markers"]
        assert sum(b["tp"] for b in bands.values()) == full["tp"]
        for label, b in bands.items():
            assert drop["breakdown"][dim][label]["tp"] <= b["tp"]
    assert sum(b["images"] for b in full["breakdown"]["background"].values()) == 4
    # classical gives probability maps: pixel metrics present and identical (same maps)
    assert full["pixel"] is not None and drop["pixel"] == full["pixel"]
    assert 0.0 < full["instance_ap"] <= 1.0 and drop["instance_ap"] < full["instance_ap"]
    assert s["recommendation"]["choice"] == "classical_cached"
    assert s["recommendation"]["insufficient"] is True  # a handful of markers cannot decide
    assert any("only" in r and "true markers" in r for r in s["recommendation"]["reasons"])
    dom = dump_dom(tmp_path / "rep" / "report.html")
    body = re.search(r"<body[^>]*>", dom).group(0)
    assert 'data-ready="1"' in body and 'data-broken-images="0"' in body
    assert dom.count('class="plot"') == 2 and dom.count('class="crop"') == squares
    for dim in ("type", "size", "blur", "background"):
        assert f'<table id="by-{dim}">' in dom
    md = (tmp_path / "rep" / "summary.md").read_text()
    assert "## By size" in md and "| nosquare |" in md


def test_bands_and_instance_pr_on_tiny_inputs():
    assert band_of(11.99, SIZE_BANDS) == "<12 px" and band_of(12.0, SIZE_BANDS) == "12-24 px"
    assert band_of(48.0, SIZE_BANDS) == ">=48 px" and band_of(1e6, SIZE_BANDS) == ">=48 px"
    assert band_of(None, BLUR_BANDS) == "unknown" and band_of(float("nan"), BLUR_BANDS) == "unknown"
    assert band_of(0.0, BLUR_BANDS) == "sharp (<0.5 px)" and band_of(2.0, BLUR_BANDS) == "2-4 px"
    rec = {"markers": 3, "matches": [{"score": 0.9, "distance": 0.5, "type": "square", "radius_px": 10.0,
                                      "blur_px": 0.0},
                                     {"score": 0.5, "distance": 1.5, "type": "circle", "radius_px": 30.0,
                                      "blur_px": 3.0}],
           "missed": [{"type": "square", "radius_px": 60.0, "blur_px": 0.0}],
           "false_positives": [{"score": 0.7}], "fp": 1, "category": "stone"}
    pr = instance_pr([rec])
    np.testing.assert_allclose(pr["precision"], [1.0, 0.5, 2 / 3])
    np.testing.assert_allclose(pr["recall"], [1 / 3, 1 / 3, 2 / 3])
    assert pr["ap"] == pytest.approx(1 / 3 + 1 / 3 * 2 / 3)
    b = breakdown([rec])
    assert b["type"]["square"]["markers"] == 2 and b["type"]["square"]["recall"] == 0.5
    assert list(b["size"]) == ["<12 px", "24-48 px", ">=48 px"]
    assert b["blur"]["2-4 px"]["centre_error_median_px"] == 1.5
    st = b["background"]["stone"]
    assert (st["tp"], st["fp"], st["fn"], st["images"]) == (2, 1, 1, 1) and st["precision"] == 2 / 3


def test_pixel_pr_matches_the_average_precision_of_the_counts():
    rng = np.random.default_rng(5)
    pc = PixelCounts()
    truth = rng.random((60, 80)) < 0.2
    prob = np.clip(np.where(truth, 0.7, 0.3) + rng.normal(0, 0.2, truth.shape), 0, 1).astype(np.float32)
    pc.add(prob, truth)
    p, r = pixel_pr(pc.pos, pc.neg)
    assert np.all(np.diff(r) >= 0) and r[-1] == pytest.approx(1.0)
    ap = np.sum(np.diff(np.concatenate([[0.0], r])) * p)
    assert ap == pytest.approx(pc.average_precision(), abs=1e-12)
    assert 0.5 < ap < 1.0


def _fake(name, paired, rms_mm, seconds, status="ok"):
    markers = [{"surveyed_name": n, "residual_m": [rms_mm / 1000, 0, 0], "n_views": 5, "observations": []}
               for n in paired]
    report = {"status": status, "reason": "" if status == "ok" else "no consistent pairing",
              "markers": markers, "rms_m": rms_mm / 1000 if paired else None, "n_markers": len(paired),
              "unpaired_surveyed": []}
    return SiteDetectorResult(name, report, {}, seconds, seconds, None)


def test_site_recommendation_rules():
    all9 = [f"G{k}" for k in range(1, 10)]
    # completeness first: the slower, noisier detector that pairs every point wins
    rec = recommend_site([_fake("fast", all9[:8], 3.0, 1.0), _fake("slow", all9, 5.0, 6.0)], 9)
    assert rec.choice == "slow" and not rec.insufficient
    assert "all 9 surveyed markers paired" in rec.reasons[0] and "missed G9" in rec.reasons[1]
    # same pairings and comparable residuals: speed decides, and the reason gives the factor
    rec = recommend_site([_fake("hma", all9, 4.2, 6.0), _fake("classical", all9, 4.0, 1.0)], 9)
    assert rec.choice == "classical" and not rec.insufficient
    assert rec.reasons[0] == ("classical: all 9 surveyed markers paired, residual RMS 4.0 mm, "
                              "6.0x faster than hma")
    assert rec.reasons[1].startswith("hma found the same 9")
    # residuals within the margin count as equal even when the slower one is a little better
    rec = recommend_site([_fake("hma", all9, 3.9, 6.0), _fake("classical", all9, 4.2, 1.0)], 9)
    assert rec.choice == "classical" and not rec.insufficient
    assert rec.reasons[1] == "hma found the same 9, residual RMS 3.9 mm; residuals comparable, 6.0x slower"
    # same pairings, clearly smaller residuals win over speed
    rec = recommend_site([_fake("a", all9, 4.0, 1.0), _fake("b", all9, 2.0, 6.0)], 9)
    assert rec.choice == "b" and "larger residuals" in rec.reasons[1]
    # nothing separates them: insufficient evidence, said so
    rec = recommend_site([_fake("a", all9, 4.0, 1.0), _fake("b", all9, 4.1, 1.1)], 9)
    assert rec.insufficient and "do equally well" in rec.reasons[-1]
    # one detector, or too few pairings, or none georeferenced
    assert recommend_site([_fake("a", all9, 4.0, 1.0)], 9).insufficient
    rec = recommend_site([_fake("a", all9[:3], 4.0, 1.0), _fake("b", all9[:2], 4.0, 1.0)], 9)
    assert rec.choice == "a" and rec.insufficient and any("only 3 surveyed points" in r for r in rec.reasons)
    rec = recommend_site([_fake("a", [], 0, 1.0, "failed"), _fake("b", [], 0, 1.0, "failed")], 9)
    assert rec == Recommendation(None, rec.reasons, True) and "no detector georeferenced" in rec.reasons[0]


def test_apply_rejects_removes_only_detections_near_a_reject():
    d = lambda x, y: MarkerDetection(x, y, 0.9, "square", 10.0, 0.5)  # noqa: E731
    dets = {"a.jpg": [d(10, 10), d(12.9, 10), d(13.2, 10), d(100, 100)], "b.jpg": [d(10, 10)]}
    rejects = [{"id": "m1", "image": "a.jpg", "x": 10.0, "y": 10.0},
               {"id": "m2", "image": "c.jpg", "x": 10.0, "y": 10.0}]
    res = apply_rejects(dets, rejects, tol_px=3.0)
    assert [(p.x, p.y) for p in res.detections["a.jpg"]] == [(13.2, 10), (100, 100)]  # 2.9 px in, 3.2 px out
    assert res.detections["b.jpg"] == dets["b.jpg"] and len(dets["a.jpg"]) == 4  # input untouched
    assert [(r["id"], r["x"]) for r in res.removed] == [("m1", 10.0), ("m1", 12.9)]
    assert [r["id"] for r in res.unmatched] == ["m2"]
    # the pipeline's per-image records keep their other keys
    recs = {"a.jpg": {"width": 640, "height": 480, "detections": [p.to_dict() for p in dets["a.jpg"]]}}
    out = apply_rejects(recs, rejects[:1], tol_px=1.0).detections["a.jpg"]
    assert out["width"] == 640 and [p["x"] for p in out["detections"]] == [12.9, 13.2, 100.0]
    with pytest.raises(ValueError, match="tol_px"):
        apply_rejects(dets, rejects, tol_px=0.0)
    assert is_rejected("a.jpg", 12.9, 10.0, rejects) and not is_rejected("a.jpg", 13.2, 10.0, rejects)
    assert not is_rejected("b.jpg", 10.0, 10.0, rejects)


def test_bad_inputs_are_one_line_errors(tmp_path, capsys):
    rc = main(["compare", str(tmp_path), "--detectors", "classical,nosuch", "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and "unknown detector 'nosuch'" in err[0] and "classical" in err[0]
    rc = main(["compare", str(tmp_path), "--detectors", "classical,classical"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and "twice" in err[0]
    site = tmp_path / "site"
    (site / "sparse").mkdir(parents=True)
    (site / "gcps.csv").write_text("name,x,y,z\n")
    rc = main(["compare", str(site), "--detectors", "classical", "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and str(site / "images") in err[0] and "no images folder" in err[0]
    (site / "images").mkdir()
    rc = main(["compare", str(site), "--detectors", "classical", "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and "empty" in err[0]
    rc = main(["compare", str(tmp_path / "missing"), "--detectors", "classical"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and "not found" in err[0]
    rc = main(["compare", str(site), "--detectors", "classical", "--set", "min_score=0.3"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and "DETECTOR.KEY=VALUE" in err[0]
    rc = main(["compare", str(site), "--detectors", "classical", "--set", "classical.min_score=high"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and "min_score" in err[0] and "expected float" in err[0]
    assert not (tmp_path / "o").exists()  # nothing half-written


def _fake_dataset(name, f1, err_px, seconds, n=200):
    from cpdetect.compare import DatasetDetectorResult

    summary = {"markers": n, "f1": f1, "recall": f1, "precision": f1, "centre_error_px": {"median": err_px},
               "seconds_per_megapixel": seconds / 10.0, "seconds": seconds}
    return DatasetDetectorResult(name, summary, [], None, {}, {})


def test_dataset_recommendation_rules():
    from cpdetect.compare import recommend_dataset

    # F1 apart by more than two standard errors (about 0.04 at F1 0.9 on 200 markers) decides
    rec = recommend_dataset([_fake_dataset("a", 0.80, 0.3, 1.0), _fake_dataset("b", 0.90, 0.5, 9.0)])
    assert rec.choice == "b" and not rec.insufficient and "more than two standard errors" in rec.reasons[1]
    # F1 tied: the more precise centres win, then speed
    rec = recommend_dataset([_fake_dataset("a", 0.90, 0.6, 1.0), _fake_dataset("b", 0.91, 0.3, 9.0)])
    assert rec.choice == "b" and "centre error larger" in rec.reasons[1]
    rec = recommend_dataset([_fake_dataset("a", 0.90, 0.30, 1.0), _fake_dataset("b", 0.91, 0.31, 9.0)])
    assert rec.choice == "a" and rec.reasons[0].endswith("9.0x faster than b") and not rec.insufficient
    # nothing separates them, or too few markers
    rec = recommend_dataset([_fake_dataset("a", 0.90, 0.30, 1.0), _fake_dataset("b", 0.91, 0.31, 1.2)])
    assert rec.insufficient and "not separated" in rec.reasons[-1]
    rec = recommend_dataset([_fake_dataset("a", 0.5, 0.3, 1.0, n=10), _fake_dataset("b", 0.9, 0.3, 1.0, n=10)])
    assert rec.choice == "b" and rec.insufficient and any("only 10 true markers" in r for r in rec.reasons)
