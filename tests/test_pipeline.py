"""End to end: `cpdetect georef` on a small synthetic site pairs every marker correctly, with residuals
bounded from both sides by the injected survey noise and the triangulation's own uncertainty.

The detector is replaced by the site's true marker projections with injected noise (0.7 px), missed
detections (20 %) and false detections (2 per image), written as a ``cpdetect.detections/1`` file:
this tests the 3D back end on its own, whatever the state of the detectors.
"""
import json
import math
import os

import numpy as np
import pytest

from cpdetect.cli import main
from cpdetect.georef_demo import transform_error_at_markers
from cpdetect.synth_scene import SiteSettings, write_site

SURVEY_SIGMA = 0.003  # metres per axis, injected into gcps.csv
DET_SIGMA = 0.7       # pixels, injected into the detections


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    root = tmp_path_factory.mktemp("georef")
    settings = SiteSettings(seed=1, n_images=16, markers=6, width=768, height=512, cloud_spacing=0.015,
                            supersample=3, survey_sigma=SURVEY_SIGMA)
    write_site(root / "site", settings)
    truth = json.loads((root / "site" / "truth.json").read_text())
    rng = np.random.default_rng(11)
    W, H = truth["camera"]["width"], truth["camera"]["height"]
    images = []
    for im in truth["images"]:
        dets = [{"x": m["x"] + rng.normal(0, DET_SIGMA), "y": m["y"] + rng.normal(0, DET_SIGMA), "score": 0.9,
                 "type": m["type"], "radius_px": m["radius_px"], "sigma_px": DET_SIGMA}
                for m in im["markers"] if rng.random() >= 0.2]
        dets += [{"x": rng.uniform(0, W - 1), "y": rng.uniform(0, H - 1), "score": 0.6, "type": "square",
                  "radius_px": rng.uniform(10, 40), "sigma_px": 1.0} for _ in range(2)]
        images.append({"file": im["name"], "width": W, "height": H, "detections": dets})
    (root / "dets.json").write_text(json.dumps({"format": "cpdetect.detections/1", "detector": "truth+noise",
                                                "images": images}))
    return root, truth


def _georef(root, out, *extra):
    s = root / "site"
    return main(["-q", "georef", "--reconstruction", str(s / "sparse"), "--images", str(s / "images"),
                 "--gcps", str(s / "gcps.csv"), "--crs", "EPSG:25832", "--mesh", str(s / "mesh.ply"),
                 "--detections", str(root / "dets.json"), "--out", str(out), *extra])


def test_georef_pairs_every_marker_and_residuals_match_the_noise(site, capsys):
    root, truth = site
    out = root / "out"
    assert _georef(root, out) == 0
    printed = capsys.readouterr().out
    assert "status: ok" in printed and "residual RMS" in printed
    report = json.loads((out / "report.json").read_text())
    assert report["status"] == "ok" and report["mode"] == "ray"
    true_c = {m["name"]: np.array(m["center_model"]) for m in truth["markers"]}
    upm = truth["model_units_per_metre"]
    seen = {m["name"] for m in truth["markers"] if len(m["visible_in"]) >= 3 and m["surveyed"]}
    paired = {m["surveyed_name"]: m for m in report["markers"] if m["surveyed_name"]}
    # every surveyed marker seen by three images or more is paired, and every pairing is right
    assert set(paired) == seen and len(seen) == 6
    for name, m in paired.items():
        d = {n: np.linalg.norm(c - m["model_point"]) for n, c in true_c.items()}
        assert min(d, key=d.get) == name
        # triangulated from the images: within a millimetre of the truth (the renders are sharp)
        assert d[name] / upm < 1e-3
    # residual RMS against the surveyed points: the survey noise dominates; expected
    # sqrt(3 sigma^2 (n - 7/3) / n) for a 7-parameter fit on n points, plus the triangulation error
    n = len(paired)
    tri_var = np.mean([np.trace(np.array(m["covariance_model"])) for m in paired.values()]) / upm ** 2
    floor = np.sqrt((3 * SURVEY_SIGMA ** 2 + tri_var) * (n - 7 / 3) / n)
    assert 0.4 * floor < report["rms_m"] < 2.0 * floor
    # the transform: scale and position of the model agree with the truth
    assert report["crs_from_model"]["scale"] == pytest.approx(truth["world_from_model"]["scale"], rel=5e-3)
    err = transform_error_at_markers(report["crs_from_model"], truth)
    assert 0.1 * SURVEY_SIGMA < err.mean() < 3 * SURVEY_SIGMA
    # exports
    gcp_lines = (out / "gcp_list.txt").read_text().splitlines()
    assert gcp_lines[0] == "EPSG:25832" and len(gcp_lines) - 1 == sum(m["n_views"] for m in paired.values())
    assert "<marker" in (out / "markers.xml").read_text()
    dets = json.loads((out / "detections.json").read_text())
    assert dets["format"] == "cpdetect.detections/1" and len(dets["images"]) == 16


def test_rerun_resumes_and_a_changed_setting_reruns_only_later_stages(site):
    root, truth = site
    out = root / "out_resume"
    assert _georef(root, out) == 0
    first = json.loads((out / "report.json").read_text())
    assert set(first["stages"]["ran"]) == {"localize", "refine", "triangulate", "register"}
    assert _georef(root, out) == 0
    again = json.loads((out / "report.json").read_text())
    assert again["stages"]["ran"] == [] and again["markers"] == first["markers"]
    # the bundle adjustment changes the triangulate stage: localize and refine are reused
    assert _georef(root, out, "--adjust") == 0
    changed = json.loads((out / "report.json").read_text())
    assert changed["stages"]["skipped"] == ["localize", "refine"]
    assert changed["stages"]["ran"] == ["triangulate", "register"]
    assert changed["stages"]["adjusted"]["success"] and changed["stages"]["adjusted"]["n_images"] >= 10
    assert [m["surveyed_name"] for m in changed["markers"]] == [m["surveyed_name"] for m in first["markers"]]
    # true poses: adjusting them moves the markers by less than half the survey noise (about 1 mm:
    # the pose priors hold the datum only to within their sigmas)
    upm = truth["model_units_per_metre"]
    moved = [np.linalg.norm(np.subtract(a["model_point"], b["model_point"])) / upm
             for a, b in zip(changed["markers"], first["markers"])]
    assert max(moved) < 0.5 * SURVEY_SIGMA


def test_bad_inputs_are_one_line_errors_naming_the_file(site, capsys, tmp_path):
    root, _ = site
    s = root / "site"
    missing = tmp_path / "nope.csv"
    rc = main(["georef", "--reconstruction", str(s / "sparse"), "--images", str(s / "images"), "--gcps",
               str(missing), "--mesh", str(s / "mesh.ply"), "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and str(missing) in err[0]
    bad = tmp_path / "dets.json"
    bad.write_text(json.dumps({"format": "something/1", "images": []}))
    rc = main(["georef", "--reconstruction", str(s / "sparse"), "--images", str(s / "images"), "--gcps",
               str(s / "gcps.csv"), "--crs", "EPSG:25832", "--mesh", str(s / "mesh.ply"), "--detections",
               str(bad), "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and str(bad) in err[0] and "cpdetect.detections/1" in err[0]


def test_without_mesh_or_cloud_markers_are_triangulated_from_detection_pairs(site):
    root, truth = site
    s = root / "site"
    out = root / "out_tri"
    rc = main(["-q", "georef", "--reconstruction", str(s / "sparse"), "--images", str(s / "images"),
               "--gcps", str(s / "gcps.csv"), "--crs", "EPSG:25832", "--detections", str(root / "dets.json"),
               "--out", str(out)])
    report = json.loads((out / "report.json").read_text())
    assert rc == 0 and report["mode"] == "triangulate"
    true_c = {m["name"]: np.array(m["center_model"]) for m in truth["markers"]}
    paired = [m for m in report["markers"] if m["surveyed_name"]]
    assert len(paired) == 6  # GCP02 is detected in only two images here: one ray pair suffices
    for m in paired:
        d = {n: np.linalg.norm(c - m["model_point"]) for n, c in true_c.items()}
        assert min(d, key=d.get) == m["surveyed_name"]
    assert 0.001 < report["rms_m"] < 0.012


def test_cloud_mode_colorizes_the_dense_cloud_with_probability_maps(site, monkeypatch):
    """A stand-in detector that knows the truth (keyed by the image's pixels) gives detections and
    probability maps (discs of the markers' apparent radius, quarter resolution); --mode cloud must
    find every marker by colorizing fused.ply alone."""
    import hashlib

    from cpdetect import detector as registry
    from cpdetect.imageio import read_image
    from cpdetect.types import DetectionResult, MarkerDetection

    root, truth = site
    s = root / "site"
    by_pixels = {}
    for im in truth["images"]:
        img = read_image(s / "images" / im["name"])
        by_pixels[hashlib.sha1(img.tobytes()).hexdigest()] = im["markers"]

    class TruthDetector:
        name = "truth"

        def detect(self, image):
            markers = by_pixels[hashlib.sha1(image.tobytes()).hexdigest()]
            h, w = image.shape[:2]
            yy, xx = np.mgrid[0:h // 4, 0:w // 4]
            prob = np.zeros((h // 4, w // 4), np.float32)
            dets = []
            for m in markers:
                cx, cy = (m["x"] + 0.5) / 4 - 0.5, (m["y"] + 0.5) / 4 - 0.5
                prob[(xx - cx) ** 2 + (yy - cy) ** 2 <= (m["radius_px"] / 4) ** 2] = 1.0
                dets.append(MarkerDetection(m["x"], m["y"], 0.9, m["type"], m["radius_px"], 0.5))
            return DetectionResult(dets, (w, h), probability=prob)

    monkeypatch.setitem(registry._REGISTERED, "truth", TruthDetector)
    out = root / "out_cloud"
    rc = main(["-q", "georef", "--reconstruction", str(s / "sparse"), "--images", str(s / "images"),
               "--gcps", str(s / "gcps.csv"), "--crs", "EPSG:25832", "--cloud", str(s / "fused.ply"),
               "--mesh", str(s / "mesh.ply"), "--detector", "truth", "--mode", "cloud", "--out", str(out)])
    report = json.loads((out / "report.json").read_text())
    assert rc == 0 and report["mode"] == "cloud" and report["detector"] == "truth"
    assert len(list((out / "stages" / "prob").glob("*.npy"))) == 16
    true_c = {m["name"]: np.array(m["center_model"]) for m in truth["markers"]}
    paired = [m for m in report["markers"] if m["surveyed_name"]]
    assert len(paired) == 6 and report["n_markers"] == 6
    for m in paired:
        d = {n: np.linalg.norm(c - m["model_point"]) for n, c in true_c.items()}
        assert min(d, key=d.get) == m["surveyed_name"]


@pytest.mark.parametrize("size, cause", [((512, 768), "turned by 90 degrees"), ((1536, 1024), "scaled copy"),
                                         ((700, 512), "not the image")])
def test_detections_of_another_image_size_are_refused(site, tmp_path, capsys, size, cause):
    # detections measured on rotated or resized copies cannot be pixels of the reconstruction's cameras
    root, truth = site
    s = root / "site"
    doc = json.loads((root / "dets.json").read_text())
    doc["images"][3]["width"], doc["images"][3]["height"] = size
    dets = tmp_path / "dets.json"
    dets.write_text(json.dumps(doc))
    rc = main(["-q", "georef", "--reconstruction", str(s / "sparse"), "--images", str(s / "images"),
               "--gcps", str(s / "gcps.csv"), "--crs", "EPSG:25832", "--mesh", str(s / "mesh.ply"),
               "--detections", str(dets), "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and str(dets) in err[0]
    assert f"is {size[0]}x{size[1]} but its camera in the reconstruction is 768x512" in err[0] and cause in err[0]
    assert not (tmp_path / "o").exists()


def test_no_detections_gives_a_failed_report_not_a_crash(site, tmp_path):
    root, truth = site
    s = root / "site"
    empty = tmp_path / "none.json"
    empty.write_text(json.dumps({"format": "cpdetect.detections/1", "detector": "none", "images": [
        {"file": im["name"], "width": 768, "height": 512, "detections": []} for im in truth["images"]]}))
    rc = main(["-q", "georef", "--reconstruction", str(s / "sparse"), "--images", str(s / "images"),
               "--gcps", str(s / "gcps.csv"), "--crs", "EPSG:25832", "--mesh", str(s / "mesh.ply"),
               "--detections", str(empty), "--out", str(tmp_path / "o")])
    report = json.loads((tmp_path / "o" / "report.json").read_text())
    assert rc == 1 and report["status"] == "failed" and report["n_markers"] == 0
    assert "no detection" in report["reason"]
    assert not (tmp_path / "o" / "gcp_list.txt").exists()


class _TruthFileDetector:
    """A stand-in detector, importable by worker processes: the true marker projections of a synthetic
    site (``truth``: its truth.json, images looked up by their pixels) and a probability map of discs at
    quarter resolution."""

    name = "truthfile"

    def __init__(self, truth: str):
        import hashlib

        from cpdetect.imageio import read_image

        with open(truth) as fh:
            doc = json.load(fh)
        folder = os.path.join(os.path.dirname(truth), "images")
        self.by_pixels = {hashlib.sha1(read_image(os.path.join(folder, im["name"])).tobytes()).hexdigest():
                          im["markers"] for im in doc["images"]}

    def detect(self, image):
        import hashlib

        from cpdetect.types import DetectionResult, MarkerDetection

        markers = self.by_pixels[hashlib.sha1(image.tobytes()).hexdigest()]
        h, w = image.shape[:2]
        yy, xx = np.mgrid[0:h // 4, 0:w // 4]
        prob = np.zeros((h // 4, w // 4), np.float32)
        for m in markers:
            prob[(xx - m["x"] / 4) ** 2 + (yy - m["y"] / 4) ** 2 <= (m["radius_px"] / 4) ** 2] = 1.0
        dets = [MarkerDetection(m["x"], m["y"], 0.9, m["type"], m["radius_px"], 0.5) for m in markers]
        return DetectionResult(dets, (w, h), probability=prob)


def test_detect_stage_on_worker_processes_gives_the_serial_results(site, monkeypatch):
    from cpdetect import detector as registry

    root, truth = site
    s = root / "site"
    monkeypatch.setitem(registry._REGISTERED, "truthfile", _TruthFileDetector)

    def georef(out, *extra):
        return main(["-q", "georef", "--reconstruction", str(s / "sparse"), "--images", str(s / "images"),
                     "--gcps", str(s / "gcps.csv"), "--crs", "EPSG:25832", "--mesh", str(s / "mesh.ply"),
                     "--detector", "truthfile", "--set", f"truth={s / 'truth.json'}", "--out", str(out), *extra])

    serial, pooled = root / "out_serial", root / "out_workers"
    assert georef(serial) == 0 and georef(pooled, "--workers", "2") == 0

    def detect_stage(out):
        data = json.loads((out / "stages" / "detect.json").read_text())["data"]
        return {n: {k: v for k, v in d.items() if k != "seconds"} for n, d in data.items()}

    a, b = detect_stage(serial), detect_stage(pooled)
    assert list(a) == list(b) == sorted(im["name"] for im in truth["images"]) and a == b
    assert sum(len(d["detections"]) for d in a.values()) > 16
    for d in a.values():
        assert (serial / "stages" / d["probability"]).read_bytes() == (pooled / "stages" / d["probability"]).read_bytes()
    ra, rb = (json.loads((o / "report.json").read_text()) for o in (serial, pooled))
    assert ra["status"] == "ok" and ra["markers"] == rb["markers"]
    # where the detection ran is not part of any stage key: a serial rerun resumes the pooled run
    assert georef(pooled) == 0
    assert json.loads((pooled / "report.json").read_text())["stages"]["ran"] == []


def test_georef_workers_must_be_positive_and_lambdas_cannot_go_to_workers(site, monkeypatch, capsys):
    from cpdetect import detector as registry

    root, _ = site
    s = root / "site"
    base = ["georef", "--reconstruction", str(s / "sparse"), "--images", str(s / "images"), "--gcps",
            str(s / "gcps.csv"), "--crs", "EPSG:25832", "--out", str(root / "out_bad_workers")]
    assert main(base + ["--workers", "0"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--workers" in err[0]
    monkeypatch.setitem(registry._REGISTERED, "local", lambda: None)
    assert main(base + ["--detector", "local", "--workers", "2"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "'local' cannot run in worker processes" in err[0]


@pytest.mark.parametrize("where", ["register", "export"])
def test_a_run_that_fails_late_leaves_no_outputs_and_a_rerun_resumes(site, monkeypatch, capsys, where):
    """A failure in a later stage (or while the outputs are written) leaves none of this run's outputs
    and keeps the previous run's intact; the stage files stay and the rerun resumes from them."""
    import cpdetect.pipeline as pipeline
    from cpdetect.errors import InputError

    root, _ = site
    out = root / f"out_fail_{where}"
    outputs = ("report.json", "detections.json", "gcp_list.txt", "markers.xml")

    def boom(*a, **kw):
        raise InputError("simulated failure", "somewhere.bin")

    target = "stage_register" if where == "register" else "write_metashape_markers"
    module = pipeline if where == "register" else __import__("cpdetect.formats.metashape", fromlist=["x"])
    with monkeypatch.context() as m:
        m.setattr(module, target, boom)
        assert _georef(root, out) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "simulated failure" in err[0]
    left = sorted(p.relative_to(out).as_posix() for p in out.rglob("*") if p.is_file())
    assert not any(name in left for name in outputs), left
    assert all(p.startswith("stages/") for p in left), left  # no staging leftovers either
    assert _georef(root, out) == 0
    report = json.loads((out / "report.json").read_text())
    assert all((out / name).is_file() for name in outputs)
    assert report["stages"]["ran"] == (["register"] if where == "register" else [])
    # a failing rerun keeps the complete outputs of the run before, byte for byte
    before = {name: (out / name).read_bytes() for name in outputs}
    with monkeypatch.context() as m:
        m.setattr(module, target, boom)
        assert _georef(root, out, "--noise", "0.03") == 2
    capsys.readouterr()
    assert {name: (out / name).read_bytes() for name in outputs} == before


def test_rejects_from_the_review_gallery_remove_a_marker_and_its_projected_views(site, capsys):
    """Rejecting every observation of one marker (as the review gallery writes them) removes it (its
    detections are dropped before fusion); rejecting a third of the views of another keeps that marker but
    without those views: georef, which projects each marker into every image that sees it and measures
    it there, must not bring a rejected measurement back. The other markers keep their pairings."""
    root, truth = site
    assert _georef(root, root / "out") == 0  # resumes the first test's run when it ran
    base = json.loads((root / "out" / "report.json").read_text())
    victim = next(m for m in base["markers"] if m["surveyed_name"] == "GCP03")
    rejects = [{"id": victim["id"], "image": o["image"], "x": o["x"], "y": o["y"]} for o in victim["observations"]]
    thinned = max((m for m in base["markers"] if m["surveyed_name"] not in (None, "GCP03")),
                  key=lambda m: m["n_views"])
    inliers = [o for o in thinned["observations"] if o["inlier"]]
    half = inliers[::3]  # a third of its views: it keeps enough to be triangulated
    assert len(half) >= 2 and len(inliers) - len(half) >= 4
    rejects += [{"id": thinned["id"], "image": o["image"], "x": o["x"], "y": o["y"]} for o in half]
    path = root / "rejects.json"
    path.write_text(json.dumps({"format": "cpdetect.rejects/1", "rejects": rejects}))
    out = root / "out_rejects"
    capsys.readouterr()
    assert _georef(root, out, "--rejects", str(path)) == 0
    assert "rejects: " in capsys.readouterr().out
    report = json.loads((out / "report.json").read_text())
    assert report["status"] == "ok" and "GCP03" in report["unpaired_surveyed"]
    assert sorted(m["surveyed_name"] for m in report["markers"] if m["surveyed_name"]) == \
        sorted(m["surveyed_name"] for m in base["markers"] if m["surveyed_name"] and m["surveyed_name"] != "GCP03")
    # no marker is left where GCP03 was, and no observation sits on a reject
    r = victim["model_point"]
    assert all(np.linalg.norm(np.subtract(m["model_point"], r)) > 0.1 for m in report["markers"])
    assert not any(o["image"] == j["image"] and math.hypot(o["x"] - j["x"], o["y"] - j["y"]) <= 3.0
                   for m in report["markers"] for o in m["observations"] for j in rejects)
    kept = next(m for m in report["markers"] if m["surveyed_name"] == thinned["surveyed_name"])
    assert {o["image"] for o in kept["observations"]}.isdisjoint({o["image"] for o in half})
    assert kept["n_views"] >= thinned["n_views"] - len(half) - 1
    summary = report["rejects"]
    assert summary["n_rejects"] == len(rejects) and summary["removed_detections"] >= 3
    assert summary["removed_observations"] >= 1  # measured by projection where a detection was dropped
    # the detections the back end used (detections.json) lack the rejected ones
    used = json.loads((out / "detections.json").read_text())["images"]
    near = [d for im in used for d in im["detections"] for j in rejects
            if im["file"] == j["image"] and math.hypot(d["x"] - j["x"], d["y"] - j["y"]) <= 3.0]
    assert near == []


@pytest.mark.parametrize("content, words", [
    ('{"rejects": [', "not valid JSON"),
    ('{"format": "cpdetect.rejects/1"}', "needs a 'rejects' list"),
    ('{"rejects": [{"id": "M001", "image": "a.jpg", "x": 10}]}', "rejects[0] needs id, image, x, y"),
])
def test_a_bad_rejects_file_is_a_one_line_error_naming_it(site, tmp_path, capsys, content, words):
    root, _ = site
    path = tmp_path / "rejects.json"
    path.write_text(content)
    out = tmp_path / "o"
    assert _georef(root, out, "--rejects", str(path)) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(path) in err[0] and words in err[0], err
    assert not out.exists()


def test_settings_name_the_valid_refinement_methods():
    from cpdetect.errors import UsageError
    from cpdetect.pipeline import GeorefSettings

    assert GeorefSettings(refine_method="model").refine_method == "model"
    with pytest.raises(UsageError, match="unknown refine_method 'bogus'; valid: auto, symmetry"):
        GeorefSettings(refine_method="bogus")
