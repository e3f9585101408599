"""Evaluation: greedy matching on hand-made cases, pixel metrics against scikit-learn, oracle detectors."""
import hashlib
import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest
from sklearn.metrics import average_precision_score

import cpdetect.detector as registry
from cpdetect.cli import main
from cpdetect.dataset import TrueMarker, load_dataset, read_mask
from cpdetect.evaluate import PixelCounts, evaluate, match_detections, score_image, summarize, tolerance_px
from cpdetect.imageio import read_image
from cpdetect.synth_images import SynthImageOptions, write_synth_images
from cpdetect.types import DetectionResult, MarkerDetection


def det(x, y, score=0.9, type="square", r=8.0):
    return MarkerDetection(x, y, score, type, r, 0.5)


def tru(x, y, r=8.0, type="square"):
    return TrueMarker(x, y, type, r)


def test_tolerance_rule():
    assert tolerance_px(4.0) == 3.0 and tolerance_px(12.0) == 3.0 and tolerance_px(40.0) == 10.0


def test_distance_threshold_small_and_large_markers():
    pairs, fp, fn = match_detections([det(12.9, 10), det(104, 100)], [tru(10, 10, 8), tru(100, 100, 8)])
    assert [(p.det, p.truth) for p in pairs] == [(0, 0)] and fp == [1] and fn == [1]
    assert math.isclose(pairs[0].distance, 2.9)
    pairs, fp, fn = match_detections([det(109.9, 100), det(10, 20.1)], [tru(100, 100, 40), tru(10, 10, 40)])
    assert [(p.det, p.truth) for p in pairs] == [(0, 0)] and fp == [1] and fn == [1]


def test_greedy_by_score_not_by_list_order():
    truths = [tru(0, 0), tru(4, 0)]
    # low-score detection listed first would take B (nearest) if order were by list; by score the
    # confident detection takes B and the other still reaches A
    dets = [det(2.2, 0, score=0.5), det(3.9, 0, score=0.9)]
    pairs, fp, fn = match_detections(dets, truths)
    assert [(p.det, p.truth) for p in pairs] == [(1, 1), (0, 0)] and fp == [] and fn == []


def test_a_closer_but_weaker_detection_does_not_steal():
    pairs, fp, fn = match_detections([det(2, 0, 0.9), det(0.5, 0, 0.3)], [tru(0, 0)])
    assert [(p.det, p.truth, p.distance) for p in pairs] == [(0, 0, 2.0)] and fp == [1] and fn == []


def test_each_truth_matched_once_and_empty_sides():
    pairs, fp, fn = match_detections([det(0, 0, 0.9), det(0.1, 0, 0.8), det(0.2, 0, 0.7)], [tru(0, 0)])
    assert len(pairs) == 1 and fp == [1, 2] and fn == []
    assert match_detections([], [tru(0, 0), tru(5, 5)]) == ([], [], [0, 1])
    assert match_detections([det(1, 1)], []) == ([], [0], [])


def test_markers_with_a_hidden_centre_are_left_out_of_the_centre_visible_recall():
    hidden = TrueMarker(100, 100, "square", 8.0, extra={"centre_hidden": True})
    truths = [tru(0, 0), tru(50, 0), TrueMarker(0, 50, "circle", 8.0, extra={"centre_hidden": False}), hidden,
              TrueMarker(200, 0, "square", 8.0, extra={"centre_hidden": True})]
    # found: the first, the third and the first hidden one; missed: the second and the other hidden
    rec = score_image("a.png", 300, 300, 0.1, [det(0.5, 0), det(0, 50.5), det(100, 101), det(250, 250)], truths)
    s = summarize([rec])
    assert (s["tp"], s["fp"], s["fn"]) == (3, 1, 2)
    cv = s["centre_visible"]
    assert (cv["markers"], cv["tp"], cv["fn"], cv["hidden"]) == (3, 2, 1, 2)
    assert math.isclose(cv["recall"], 2 / 3)
    assert math.isclose(cv["f1"], 2 * 2 / (2 * 2 + 1 + 1))  # the false one counts; the hidden found one does not
    # the hidden marker found 1 px off is left out of the centre error too
    assert math.isclose(s["centre_error_px"]["mean"], (0.5 + 0.5 + 1.0) / 3)
    assert math.isclose(cv["centre_error_px"]["mean"], 0.5)


def test_pixel_iou_f1_exact_on_hand_case():
    p = np.array([[0.9, 0.6, 0.2], [0.5, 0.49, 0.0]], np.float32)
    t = np.array([[1, 0, 1], [1, 0, 0]], bool)
    c = PixelCounts()
    c.add(p, t)
    # predicted (p >= 0.5): (0,0) (0,1) (1,0) -> TP 2 ((0,0), (1,0)), FP 1 ((0,1)), FN 1 ((0,2))
    m = c.metrics()
    assert (c.tp, c.fp, c.fn) == (2, 1, 1)
    assert m["iou"] == pytest.approx(0.5) and m["f1"] == pytest.approx(4 / 6)
    # AP by hand, thresholds from the top: 0.9 (P 1, R 1/3), 0.6 (P 1/2), 0.5 (P 2/3, R 2/3),
    # 0.49 (P 1/2), 0.2 (P 3/5, R 1): recall steps of 1/3 at precisions 1, 2/3, 3/5
    assert m["ap"] == pytest.approx(1 / 3 * 1 + 1 / 3 * 2 / 3 + 1 / 3 * 3 / 5)
    assert m["ap"] == pytest.approx(average_precision_score(t.ravel(), p.ravel()))


def test_pixel_ap_matches_sklearn_on_random_data():
    rng = np.random.default_rng(4)
    t = rng.random((400, 500)) < 0.1
    logit = rng.normal(0, 1, t.shape) + 1.6 * t
    p = (1 / (1 + np.exp(-logit))).astype(np.float32)
    c = PixelCounts()
    c.add(p[:200], t[:200])  # accumulated over two "images"
    c.add(p[200:], t[200:])
    exact = average_precision_score(t.ravel(), p.ravel())
    assert 0.3 < exact < 0.8  # a non-trivial curve
    assert abs(c.metrics()["ap"] - exact) < 5e-3
    pred = p >= 0.5
    tp, fp, fn = (pred & t).sum(), (pred & ~t).sum(), (~pred & t).sum()
    assert c.metrics()["iou"] == pytest.approx(tp / (tp + fp + fn))


def test_pixel_metrics_without_positives_are_nan():
    c = PixelCounts()
    c.add(np.zeros((5, 5), np.float32), np.zeros((5, 5), bool))
    m = c.metrics()
    assert math.isnan(m["ap"]) and math.isnan(m["iou"]) and math.isnan(m["f1"])


# ------------------------------------------------------------------------------ oracle detectors

@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    root = tmp_path_factory.mktemp("synth")
    write_synth_images(root, 6, 11, SynthImageOptions(width=320, height=240, radius_min_px=8))
    return load_dataset(root)


def _oracle_factory(ds):
    """A detector that returns the truth (looked up by image content), offset by ``offset`` px in x,
    with a probability map equal to the mask (scaled by ``p``)."""
    table = {}
    for item in ds.images:
        img = read_image(ds.image_path(item))
        table[hashlib.sha1(img.tobytes()).hexdigest()] = item

    class Oracle:
        name = "oracle"

        def __init__(self, offset: float = 0.0, p: float = 0.9, with_map: bool = True):
            self.offset, self.p, self.with_map = offset, p, with_map

        def detect(self, image):
            item = table[hashlib.sha1(np.ascontiguousarray(image).tobytes()).hexdigest()]
            h, w = image.shape[:2]
            dets = [MarkerDetection(m.x + self.offset, m.y, 0.9, m.type, m.radius_px, 0.3) for m in item.markers]
            prob = None
            if self.with_map:
                prob = read_mask(ds.mask_path(item)).astype(np.float32) * np.float32(self.p)
            return DetectionResult(dets, (w, h), probability=prob)

    return Oracle


def test_oracle_scores_perfectly(dataset, monkeypatch, tmp_path, capsys):
    monkeypatch.setitem(registry._REGISTERED, "oracle", _oracle_factory(dataset))
    out = tmp_path / "m.json"
    assert main(["eval", str(dataset.root), "--detector", "oracle", "--out", str(out)]) == 0
    table = capsys.readouterr().out
    assert "precision 1.000" in table and "recall 1.000" in table
    m = json.loads(out.read_text())
    for key in ("detector", "images", "markers", "tp", "fp", "fn", "precision", "recall", "f1",
                "centre_error_px", "pixel", "seconds_per_megapixel", "type_accuracy"):
        assert key in m
    assert m["detector"] == "oracle" and m["images"] == 6 and m["markers"] == dataset.n_markers > 0
    assert (m["tp"], m["fp"], m["fn"]) == (dataset.n_markers, 0, 0)
    assert m["precision"] == m["recall"] == m["f1"] == m["type_accuracy"] == 1.0
    assert m["centre_error_px"]["mean"] < 1e-9 and m["centre_error_px"]["p95"] < 1e-9
    assert m["pixel"]["iou"] == 1.0 and m["pixel"]["f1"] == 1.0 and m["pixel"]["ap"] == pytest.approx(1.0)
    assert m["seconds_per_megapixel"] > 0
    rec = m["per_image"][0]
    assert {"file", "tp", "fp", "fn", "matches", "missed", "false_positives", "background"} <= set(rec)
    assert all("tilt_deg" in x and "blur_px" in x for r in m["per_image"] for x in r["matches"])


def test_offset_oracle_has_the_known_error(dataset):
    m = evaluate(dataset, _oracle_factory(dataset)(offset=0.7, with_map=False))
    e = m["centre_error_px"]
    assert abs(e["mean"] - 0.7) < 1e-9 and abs(e["median"] - 0.7) < 1e-9
    assert m["pixel"] is None and m["recall"] == 1.0
    # beyond the tolerance every small marker is lost: 3.5 px > max(3, 0.25 r) when r < 14
    m = evaluate(dataset, _oracle_factory(dataset)(offset=3.5, with_map=False))
    small = sum(1 for im in dataset.images for t in im.markers if t.radius_px < 14)
    large = sum(1 for im in dataset.images for t in im.markers if t.radius_px >= 14)
    assert m["fn"] == small and m["tp"] == large and m["fp"] == small


def test_a_detector_that_reads_files_gets_the_path_as_in_detect(dataset, monkeypatch, tmp_path):
    oracle = _oracle_factory(dataset)

    class FileOracle(oracle):
        accepts_path = True
        seen: list = []

        def detect(self, image):
            FileOracle.seen.append("path" if isinstance(image, (str, Path)) else type(image).__name__)
            return super().detect(read_image(image) if isinstance(image, (str, Path)) else image)

    m = evaluate(dataset, FileOracle(with_map=False))
    assert m["input"] == "file" and set(FileOracle.seen) == {"path"} and len(FileOracle.seen) == 6
    assert m["recall"] == 1.0 and all(r["width"] == 320 and r["height"] == 240 for r in m["per_image"])
    FileOracle.seen.clear()
    m = evaluate(dataset, FileOracle(with_map=False), from_file=False)
    assert m["input"] == "array" and set(FileOracle.seen) == {"ndarray"} and m["recall"] == 1.0
    assert evaluate(dataset, oracle(with_map=False), limit=1)["input"] == "array"
    with pytest.raises(ValueError, match="takes decoded images, not paths"):
        evaluate(dataset, oracle(with_map=False), from_file=True)
    # the CLI's --from-array
    monkeypatch.setitem(registry._REGISTERED, "file-oracle", FileOracle)
    out = tmp_path / "m.json"
    FileOracle.seen.clear()
    assert main(["eval", str(dataset.root), "--detector", "file-oracle", "--limit", "2", "--from-array",
                 "--out", str(out)]) == 0
    assert json.loads(out.read_text())["input"] == "array" and FileOracle.seen == ["ndarray", "ndarray"]
    # an unreadable image is named, whichever input the detector gets
    bad = tmp_path / "bad"
    shutil.copytree(dataset.root, bad)
    first = sorted((bad / "images").iterdir())[0]
    first.write_bytes(b"not a jpeg at all")
    from cpdetect.errors import InputError
    for ff in (True, False):
        with pytest.raises(InputError, match=first.name):
            evaluate(load_dataset(bad), FileOracle(with_map=False), from_file=ff)


def test_limit_and_json_safety(dataset):
    m = evaluate(dataset, _oracle_factory(dataset)(p=0.3), limit=2)
    assert m["images"] == 2 and len(m["per_image"]) == 2
    # p = 0.3 everywhere on markers: nothing reaches 0.5, so IoU = 0 but AP is still perfect
    assert m["pixel"]["iou"] == 0.0 and m["pixel"]["ap"] == pytest.approx(1.0)
    json.dumps(m, allow_nan=False)


def test_demo_generates_and_evaluates_skipping_broken_detectors(tmp_path, monkeypatch, capsys):
    class Nothing:
        name = "nothing"

        def detect(self, image):
            return DetectionResult([], (image.shape[1], image.shape[0]))

    def broken():
        raise RuntimeError("no weights\nsecond line")

    monkeypatch.setitem(registry._REGISTERED, "nothing", Nothing)
    class Crashes:
        name = "crashes"

        def detect(self, image):
            raise IndexError("bug inside the detector")

    monkeypatch.setitem(registry._REGISTERED, "broken", broken)
    monkeypatch.setitem(registry._REGISTERED, "crashes", Crashes)
    rc = main(["-q", "demo", "--workdir", str(tmp_path), "--n", "3", "--detectors", "nothing", "broken", "crashes"])
    out = capsys.readouterr().out
    assert rc == 0
    assert "crashes" in out and "IndexError: bug inside the detector" in out
    assert "broken" in out and "skipped" in out and "no weights" in out and "second line" not in out
    m = json.loads((tmp_path / "metrics-nothing.json").read_text())
    assert m["images"] == 3 and m["tp"] == 0 and m["fn"] == m["markers"]
    assert m["recall"] == (0.0 if m["markers"] else None) and m["precision"] is None
    assert load_dataset(tmp_path / "images-set").images[0].file == "images/000000.jpg"


def test_low_resolution_probability_map_is_resampled(dataset):
    Oracle = _oracle_factory(dataset)

    class HalfRes(Oracle):
        def detect(self, image):
            res = super().detect(image)
            p = res.probability[::2, ::2].copy()  # a map at half the image size
            return DetectionResult(res.detections, res.image_size, probability=p)

    m = evaluate(dataset, HalfRes(p=1.0))
    px = m["pixel"]
    assert px["images"] == 6
    assert 0.8 < px["iou"] < 0.98 and 0.88 < px["f1"] < 0.99 and 0.95 < px["ap"] < 1.0


def test_recall_by_groups_markers(dataset):
    from cpdetect.evaluate import recall_by

    m = evaluate(dataset, _oracle_factory(dataset)(offset=3.5, with_map=False))
    by_size = recall_by(m["per_image"], "radius_px", edges=[0, 14, 1e9])
    assert [g["group"] for g in by_size] == [[0.0, 14.0], [14.0, 1e9]]
    small, large = by_size
    assert small["recall"] == 0.0 and large["recall"] == 1.0
    assert small["markers"] + large["markers"] == dataset.n_markers
    assert abs(large["centre_error_px_median"] - 3.5) < 1e-9
    by_type = recall_by(m["per_image"], "type")
    assert sum(g["markers"] for g in by_type) == dataset.n_markers
    by_cat = recall_by(m["per_image"], "category")
    assert sum(g["markers"] for g in by_cat) == dataset.n_markers
