"""bench/classical_miss_stages.py and the classical scan's trace: the stage named is the detector's own decision."""
from __future__ import annotations

import json
import math

from bench_loader import load_bench
from cpdetect.classical import ClassicalDetector
from detector_contract import marker_image

stages = load_bench("classical_miss_stages")

CENTRE = (131.3, 122.6)


def _traced(**settings):
    img = marker_image(center=CENTRE, radius=26.0, angle=0.4, marker_type="circle")
    trace: list[dict] = []
    res = ClassicalDetector(**settings).detect(img, trace=trace)
    return res, trace, stages.stage_of(trace, {"x": CENTRE[0], "y": CENTRE[1], "radius_px": 26.0})


def test_the_trace_changes_nothing_and_names_the_marker_kept():
    img = marker_image(center=CENTRE, radius=26.0, angle=0.4, marker_type="circle")
    plain = ClassicalDetector().detect(img).detections
    res, trace, got = _traced()
    assert [(d.x, d.y, d.type, d.score) for d in res.detections] == [(d.x, d.y, d.type, d.score) for d in plain]
    assert len(plain) == 1 and math.hypot(plain[0].x - CENTRE[0], plain[0].y - CENTRE[1]) < 0.1
    assert got["stage"] == "kept" and got["best_score"] > 0.9
    kept = [t for t in trace if t["stage"] == "kept"]
    assert len(kept) == 1 and kept[0]["type"] == "circle" and abs(kept[0]["radius_px"] / 26.0 - 1) < 0.15
    # every candidate of the scan is accounted for, and only known stages appear
    assert {t["stage"].split(":")[0] for t in trace} <= set(stages.ORDER)
    assert all(t["pass"] in ("gray", "colour") for t in trace)


def test_a_marker_scored_under_the_cut_is_named_score():
    # held markers off: with the cut at 1 every candidate of 0.2 or more would be held and added
    res, _, got = _traced(min_score=1.0, held_score=None)
    assert res.detections == []
    assert got["stage"] == "score" and 0.9 < got["best_score"] < 1.0


def test_a_marker_dropped_by_the_centre_grey_test_is_named_so():
    # a cut far under any real marker's offset (noise alone moves it by 0.01-0.03)
    res, _, got = _traced(max_centre_offset=1e-6)
    assert res.detections == []
    assert got["stage"] == "centre grey"


def test_stage_of_takes_the_furthest_stage_and_the_commonest_reason():
    truth = {"x": 100.0, "y": 50.0, "radius_px": 20.0}  # near: within 7 px
    t = [{"x": 101.0, "y": 50.0, "stage": "prefilter: weak four-sector pattern"},
         {"x": 99.0, "y": 52.0, "stage": "verify: no four-sector pattern"},
         {"x": 100.5, "y": 49.0, "stage": "verify: outline degenerate"},
         {"x": 100.0, "y": 48.0, "stage": "verify: outline degenerate"},
         {"x": 130.0, "y": 50.0, "stage": "kept", "score": 0.99}]  # another marker's
    assert stages.stage_of(t, truth) == {"stage": "verify: outline degenerate", "candidates": 4, "best_score": None}
    t.append({"x": 103.0, "y": 55.0, "stage": "score", "score": 0.4})
    assert stages.stage_of(t, truth)["stage"] == "score"
    assert stages.stage_of(t[-2:-1], truth) == {"stage": "no candidate", "candidates": 0}
    # stopped at the prefilter only: its commonest reason
    pre = [{"x": 100.0, "y": 50.0 + d, "stage": "prefilter: " + r}
           for d, r in ((0, "candidate score"), (1, "not four sectors"), (2, "candidate score"), (40, "not four sectors"))]
    assert stages.stage_of(pre, truth) == {"stage": "prefilter: candidate score", "candidates": 3, "best_score": None}


def test_bad_metrics_files_get_one_line_and_exit_2(tmp_path, capsys):
    assert stages.main([str(tmp_path / "none.json"), "--out", str(tmp_path / "o.json")]) == 2
    hma = tmp_path / "hma.json"
    hma.write_text(json.dumps({"detector": "hma", "per_image": [], "dataset": str(tmp_path)}))
    assert stages.main([str(hma), "--out", str(tmp_path / "o.json")]) == 2
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"detector": "classical", "per_image": [], "dataset": str(tmp_path),
                               "settings": {"min_score": 7}}))
    assert stages.main([str(bad), "--out", str(tmp_path / "o.json")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 3 and all(line.startswith("error: ") for line in err)
    assert not (tmp_path / "o.json").exists()


def test_a_run_on_an_evaluated_set(tmp_path):
    from cpdetect.dataset import load_dataset
    from cpdetect.evaluate import evaluate
    from cpdetect.synth_images import SynthImageOptions, write_synth_images

    write_synth_images(tmp_path / "set", 2, 7, SynthImageOptions(split="train"))
    det = ClassicalDetector(min_score=1.0, held_score=None)  # everything verified scores under the cut, none held
    ev = evaluate(load_dataset(tmp_path / "set"), det)
    assert ev["tp"] == 0 and ev["markers"] > 0
    ev["settings"] = {"min_score": 1.0}
    (tmp_path / "ev.json").write_text(json.dumps(ev))
    out = tmp_path / "stages.json"
    assert stages.main([str(tmp_path / "ev.json"), "--out", str(out)]) == 0
    rep = json.loads(out.read_text())
    assert rep["missed"] == ev["markers"]
    assert sum(v["missed"] for v in rep["stages"].values()) == rep["missed"]
    assert "kept" not in rep["stages"] and rep["stages"]["score"]["missed"] >= 1
    # a metrics file of before stop 68 (no "input": decoded arrays) is rerun on the arrays, the same here
    assert ev.pop("input") == "file"
    (tmp_path / "ev.json").write_text(json.dumps(ev))
    assert stages.main([str(tmp_path / "ev.json"), "--out", str(out)]) == 0
    assert json.loads(out.read_text())["stages"] == rep["stages"]


def test_candidates_past_the_verification_cap_are_named_unverified():
    img = marker_image(center=CENTRE, radius=26.0, angle=0.4, marker_type="circle")
    full: list[dict] = []
    ClassicalDetector(colour_pass=False).detect(img, trace=full)
    capped: list[dict] = []
    res = ClassicalDetector(colour_pass=False, max_verified=1).detect(img, trace=capped)
    # the same candidates either way; all but the first that passed the prefilter go unverified
    assert len(capped) == len(full)
    passed = [t for t in full if not t["stage"].startswith("prefilter")]
    assert len(passed) >= 2
    assert sum(t["stage"] == "unverified" for t in capped) == len(passed) - 1
    assert res.extras["unverified"] == len(passed) - 1


def test_every_stage_the_scan_names_is_ranked():
    # the tag tests (tag_lattice is on by default) and the opt-in ones end a candidate's scan too:
    # a miss beside such a candidate is put to that stage, not lost to an unknown one
    truth = {"x": 100.0, "y": 50.0, "radius_px": 20.0}
    for stage in ("tag grid", "tag lattice", "edges run on", "held"):
        t = [{"x": 101.0, "y": 50.0, "stage": stage, "score": 0.9},
             {"x": 99.0, "y": 51.0, "stage": "single saddle", "score": 0.95}]
        assert stages.stage_of(t, truth)["stage"] == stage
    order = list(stages.ORDER)
    assert order.index("edges run on") < order.index("tag lattice") < order.index("tag grid") \
        < order.index("score after refinement")


def test_a_marker_keeps_its_stage_under_the_edges_test_at_its_least_cut():
    # a marker's edges end at its outline: even at the least cut (1 edge) it is kept, its trace
    # row counting 0 edges
    res, trace, got = _traced(max_edges_running_on=1)
    assert len(res.detections) == 1 and got["stage"] == "kept"
    assert [t["edges"] for t in trace if t["stage"] == "kept"] == [0]
