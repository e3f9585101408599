"""The ``hma`` detector: instance extraction, marker type by shape, settings, the torch-free path,
and the detector contract with the shipped weights."""
from __future__ import annotations

import math
import subprocess
import sys
import textwrap

import cv2
import numpy as np
import pytest

from cpdetect import get_detector
from cpdetect.errors import InputError, UsageError
from cpdetect.markers import MarkerSpec, frontal_homography, render_marker
from learned.adapter import HMADetector, checker_phase_type, classify_shape, shipped_weights_present
from detector_contract import DetectorContract, marker_image


class OracleBackend:
    """Stands in for the network: logits +-8 from a known marker mask (at the processing size)."""

    name = "oracle"

    def __init__(self, mask: np.ndarray):
        self.mask = mask.astype(np.float32)

    def trunk(self, x: np.ndarray):
        m = cv2.resize(self.mask, (x.shape[1], x.shape[0]), interpolation=cv2.INTER_LINEAR)
        logit = 16.0 * (m - 0.5)
        return np.stack([np.zeros_like(logit), logit]), np.full(x.shape, 0.5, np.float32)


class SoftBackend(OracleBackend):
    """Stands in for the network with a given P(marker) map (the mask's values, not 0 / 1)."""

    def trunk(self, x: np.ndarray):
        m = cv2.resize(self.mask, (x.shape[1], x.shape[0]), interpolation=cv2.INTER_NEAREST)
        logit = np.log(np.clip(m, 1e-4, 1 - 1e-4) / np.clip(1 - m, 1e-4, 1))
        return np.stack([np.zeros_like(logit), logit]), np.full(x.shape, 0.5, np.float32)


def rendered(marker_type: str, center=(128.0, 128.0), radius=24.0, angle=0.3, shape=(256, 256)):
    """(uint8 gray image, pattern mask) of one frontal marker on a mid-grey textured background."""
    img = cv2.cvtColor(marker_image(center, radius, angle, marker_type, shape, seed=2), cv2.COLOR_BGR2GRAY)
    spec = MarkerSpec(marker_type, size_m=1.0)
    H = frontal_homography(center, radius, angle, spec)
    rm = render_marker(spec, H, shape)
    mask = np.zeros(shape, np.float32)
    mask[rm.y0:rm.y0 + rm.dark.shape[0], rm.x0:rm.x0 + rm.dark.shape[1]] = rm.pattern
    return img, (mask >= 0.5).astype(np.uint8), H


def test_shape_of_a_disk_is_a_circle_and_of_a_square_a_quad():
    disk = np.zeros((80, 80), np.uint8)
    cv2.circle(disk, (40, 40), 25, 1, -1)
    assert classify_shape(disk)[0] == "circle"
    sq = np.zeros((80, 80), np.uint8)
    pts = cv2.boxPoints(((40.0, 40.0), (40.0, 40.0), 20.0)).astype(np.int32)
    cv2.fillPoly(sq, [pts], 1)
    kind, quad = classify_shape(sq)
    assert kind == "quad" and quad.shape == (4, 2)
    # the fitted corners are the square's corners within a pixel
    d = np.min(np.linalg.norm(quad[:, None] - pts[None].astype(np.float32), axis=2), axis=1)
    assert d.max() < 1.5


@pytest.mark.parametrize("marker_type", ["square", "diagonal"])
@pytest.mark.parametrize("angle", [0.0, 0.3, 1.2])
def test_checker_phase_separates_square_from_diagonal(marker_type, angle):
    img, mask, H = rendered(marker_type, angle=angle)
    kind, quad = classify_shape(mask)
    assert kind == "quad"
    assert checker_phase_type(img, 128.0, 128.0, 24.0 * 2 / np.sqrt(np.pi), quad) == marker_type


@pytest.mark.parametrize("marker_type", ["square", "diagonal"])
def test_checker_phase_reads_a_window_so_images_of_any_width_work(marker_type):
    # the rings were sampled from a float copy of the whole image: 180 MB on a 45 MP photograph, and
    # cv2.remap refuses images of 32767 pixels a side or more
    img, mask, _ = rendered(marker_type, angle=0.3)
    _, quad = classify_shape(mask)
    wide = np.full((256, 40000), 128, np.uint8)
    wide[:, 39000:39256] = img
    assert checker_phase_type(wide, 39128.0, 128.0, 24.0 * 2 / np.sqrt(np.pi), quad + [39000.0, 0.0]) == marker_type


@pytest.mark.skipif(not shipped_weights_present(), reason="shipped hma weights not present")
@pytest.mark.parametrize("shape", [(30000, 9), (9, 30000), (4097, 2)])
def test_strips_that_downscale_to_one_pixel_give_no_detection(shape):
    # downscaled to max_side 2048, a 30000 x 9 strip is 1 pixel wide and its half-scale pass was 0
    # pixels: "internal error" from cv2.resize before
    strip = np.random.default_rng(0).integers(0, 256, shape).astype(np.uint8)
    res = get_detector("hma", backend="opencv").detect(strip)
    assert res.detections == [] and res.image_size == (shape[1], shape[0])


@pytest.mark.parametrize("marker_type", ["square", "circle", "diagonal"])
def test_instances_from_an_oracle_probability_map(marker_type):
    center = (121.3, 133.6)
    img, mask, _ = rendered(marker_type, center=center, radius=26.0, angle=0.5)
    det = HMADetector.with_backend(OracleBackend(mask))
    res = det.detect(img)
    assert len(res.detections) == 1
    m = res.detections[0]
    assert m.type == marker_type
    # refined on the image: far better than the pixel grid, but not exact (noise + rendering)
    err = float(np.hypot(m.x - center[0], m.y - center[1]))
    assert err < 0.15
    # equal-area radius of the pattern mask
    true_r = np.sqrt(mask.sum() / np.pi)
    assert abs(m.radius_px - true_r) < 0.03 * true_r + 0.5
    assert 0.9 < m.score <= 1.0 and 0 < m.sigma_px < 1.0
    assert res.probability.shape == img.shape and res.probability.dtype == np.float32
    # without refinement the centre is the probability-weighted centroid: close but coarser
    raw = HMADetector.with_backend(OracleBackend(mask), refine="none").detect(img).detections[0]
    assert 0.0 < np.hypot(raw.x - center[0], raw.y - center[1]) < 2.0


def test_downscaled_processing_maps_back_to_image_pixels():
    center = (301.7, 222.2)
    img, mask, _ = rendered("square", center=center, radius=40.0, angle=0.2, shape=(480, 640))
    det = HMADetector.with_backend(OracleBackend(mask), max_side=320, refine="none")
    res = det.detect(img)
    assert res.probability.shape == (240, 320)
    assert abs(res.extras["probability_factor"] - 0.5) < 1e-9
    m = res.detections[0]
    assert np.hypot(m.x - center[0], m.y - center[1]) < 1.5
    assert abs(m.radius_px - np.sqrt(mask.sum() / np.pi)) < 2.0


def test_small_blobs_and_empty_maps_give_nothing():
    img = np.full((120, 160), 128, np.uint8)
    blob = np.zeros(img.shape, np.uint8)
    blob[50:52, 60:62] = 1  # equal-area radius ~1.1 px < min_radius_px
    assert HMADetector.with_backend(OracleBackend(blob)).detect(img).detections == []
    assert HMADetector.with_backend(OracleBackend(blob * 0)).detect(img).detections == []


def test_blobs_without_a_marker_are_cleared_unless_the_network_is_sure():
    img, mask, _ = rendered("square", center=(80.0, 128.0), radius=22.0, angle=0.4)
    # two blobs on plain background: one the network is unsure of (P 0.7), one it is sure of (P 0.97)
    soft = mask.astype(np.float32)
    soft[100:150, 170:220] = 0.7
    soft[30:60, 180:210] = 0.97

    # the image's own map (this stand-in network does not mirror with its input, so the mean with
    # its mirror image's map would mix the blobs with their mirror images'; tests/test_mirror_map.py)
    res = HMADetector.with_backend(SoftBackend(soft), scales=(1.0,), mirror_map="never").detect(img)
    assert len(res.detections) == 1 and res.detections[0].type == "square"
    p = res.probability
    assert p[110:140, 180:210].max() == 0.0  # unsure and no marker: cleared
    assert np.allclose(p[35:55, 185:205], 0.97, atol=1e-3)  # sure: kept for the pixel metrics
    assert p[mask > 0].mean() > 0.95  # the marker's own blob is untouched
    raw = HMADetector.with_backend(SoftBackend(soft), scales=(1.0,), clear_rejected_below=0.0,
                                   mirror_map="never").detect(img).probability
    assert np.allclose(raw[110:140, 180:210], 0.7, atol=1e-3)


def test_images_seen_downscaled_clear_blobs_up_to_their_own_cut():
    img, mask, _ = rendered("square", center=(80.0, 128.0), radius=22.0, angle=0.4)
    soft = mask.astype(np.float32)
    soft[30:60, 180:210] = 0.93  # no marker, the network fairly sure of it

    def sure_blob(max_side, **cuts):
        det = HMADetector.with_backend(SoftBackend(soft), scales=(1.0,), small_scales=None, mirror_map="never",
                                       max_side=max_side, **cuts)
        res = det.detect(img)
        assert len(res.detections) == 1 and res.detections[0].type == "square"
        f = res.extras["probability_factor"]
        return float(res.probability[int(45 * f), int(195 * f)])

    # by default the one cut holds everywhere; the large-image cut changes the images seen
    # downscaled (longest side over max_side) only
    assert abs(sure_blob(512) - 0.93) < 2e-3 and abs(sure_blob(128) - 0.93) < 2e-3
    assert abs(sure_blob(512, large_clear_rejected_below=0.97) - 0.93) < 2e-3
    assert sure_blob(128, large_clear_rejected_below=0.97) == 0.0
    assert abs(sure_blob(128, large_clear_rejected_below=0.9) - 0.93) < 2e-3
    assert sure_blob(512, clear_rejected_below=0.97, large_clear_rejected_below=0.9) == 0.0
    with pytest.raises(ValueError, match="large_clear_rejected_below"):
        HMADetector.with_backend(SoftBackend(soft), large_clear_rejected_below=1.2)


def test_blobs_the_network_is_far_from_sure_of_are_dropped_unrefined_with_an_instance_model(monkeypatch):
    import learned.adapter as adapter
    from learned.instances import INSTANCE_FEATURES, InstanceModel

    img, mask, _ = rendered("square", center=(121.3, 133.6), radius=26.0, angle=0.5)
    unsure = mask.astype(np.float32) * 0.58  # a real marker, but the network unsure of it

    n = len(INSTANCE_FEATURES)
    keep_all = InstanceModel(mean=(0.0,) * n, std=(1.0,) * n, weights=(0.0,) * n, bias=5.0, threshold=0.5)
    refined = []
    real = adapter.HMADetector._refined_centre
    monkeypatch.setattr(adapter.HMADetector, "_refined_centre",
                        lambda self, *a, **k: refined.append(1) or real(self, *a, **k))
    gated = HMADetector.with_backend(SoftBackend(unsure), keep_all, scales=(1.0,)).detect(img)
    assert gated.detections == [] and refined == []
    assert gated.probability.max() < 0.5  # unsure and dropped: its blob cleared like any rejected one
    # the same blob refined and judged when the gate is off, or without an instance model
    for det in (HMADetector.with_backend(SoftBackend(unsure), keep_all, scales=(1.0,), min_blob_mean_p=0.0),
                HMADetector.with_backend(SoftBackend(unsure), None, scales=(1.0,))):
        found = det.detect(img).detections
        assert len(found) == 1 and np.hypot(found[0].x - 121.3, found[0].y - 133.6) < 0.15
    assert refined


def test_small_images_get_the_extra_scale_within_max_side():
    det = HMADetector.with_backend(OracleBackend(np.zeros((4, 4))))
    assert det.scales_for(640, 480) == (0.5, 1.0, 1.5, 2.0)
    assert det.scales_for(1024, 700) == (0.5, 1.0, 1.5, 2.0)
    assert det.scales_for(1025, 700) == (0.5, 1.0)
    assert det.scales_for(8192, 5460) == (0.5, 1.0)
    off = HMADetector.with_backend(OracleBackend(np.zeros((4, 4))), small_scales=None)
    assert off.scales_for(640, 480) == (0.5, 1.0)
    img, mask, _ = rendered("circle", center=(100.3, 90.8), radius=20.0)
    res = HMADetector.with_backend(OracleBackend(mask)).detect(img)
    assert res.extras["scales"] == [0.5, 1.0, 1.5, 2.0]
    assert len(res.detections) == 1 and abs(res.detections[0].x - 100.3) < 0.15


def test_settings_are_checked():
    with pytest.raises(UsageError, match="bogus"):
        get_detector("hma", bogus=1)
    with pytest.raises(UsageError, match="1.0"):
        get_detector("hma", scales=[0.5, 2.0])
    with pytest.raises(UsageError, match="backend"):
        get_detector("hma", backend="tensorflow")
    with pytest.raises(ValueError):
        HMADetector.with_backend(OracleBackend(np.zeros((4, 4))), threshold=1.5)
    with pytest.raises(UsageError, match="small_scales"):
        get_detector("hma", small_scales=[2.0])
    # a pass at scale 50 asked 19 GB for one 1024-px tile ("internal error: Insufficient memory")
    for key in ("scales", "small_scales"):
        with pytest.raises(UsageError, match=rf"{key} must be in \(0, 4\]"):
            get_detector("hma", **{key: [1.0, 50.0]})
    assert get_detector("hma", scales=[0.25, 1.0, 4.0]).settings.scales == (0.25, 1.0, 4.0)
    with pytest.raises(ValueError, match="clear_rejected_below"):
        HMADetector.with_backend(OracleBackend(np.zeros((4, 4))), clear_rejected_below=1.5)
    with pytest.raises(ValueError, match="colour_min_mean_p"):
        HMADetector.with_backend(OracleBackend(np.zeros((4, 4))), colour_min_mean_p=-0.1)
    with pytest.raises(ValueError, match="max_sigma_verified_px"):
        HMADetector.with_backend(OracleBackend(np.zeros((4, 4))), max_sigma_verified_px=0.0)
    with pytest.raises(UsageError, match="outline_window"):
        get_detector("hma", outline_window=-1.0)
    with pytest.raises(UsageError, match="refine method 'bogus'"):
        get_detector("hma", refine="bogus")
    assert HMADetector.with_backend(OracleBackend(np.zeros((4, 4))), refine="model").settings.refine == "model"


def test_rejects_non_images():
    det = HMADetector.with_backend(OracleBackend(np.zeros((8, 8))))
    with pytest.raises(ValueError):
        det.detect(np.zeros((10, 10, 3), np.float64))
    with pytest.raises(ValueError):
        det.detect(np.zeros((10, 10, 5), np.uint8))


@pytest.fixture(scope="module")
def micro_model_dir(tmp_path_factory):
    """A tiny random model folder with config.json, model.pt and model.onnx."""
    torch = pytest.importorskip("torch")
    pytest.importorskip("onnx")
    from learned.export import export_onnx
    from learned.hma import build_model, save_model

    torch.manual_seed(0)
    m = build_model("test_micro")
    m.train()
    with torch.no_grad():  # realistic BN statistics
        for mod in m.modules():
            if isinstance(mod, torch.nn.modules.batchnorm._BatchNorm):
                mod.momentum = None
        m(torch.rand(4, 1, 96, 128))
    m.eval()
    d = save_model(m, tmp_path_factory.mktemp("micro"))
    export_onnx(m, d / "model.onnx")
    return d


def test_torch_and_opencv_backends_agree_through_the_detector(micro_model_dir):
    img = marker_image(angle=0.3)
    a = get_detector("hma", model_dir=str(micro_model_dir), backend="torch", scales=[0.5, 1.0]).detect(img)
    b = get_detector("hma", model_dir=str(micro_model_dir), backend="opencv", scales=[0.5, 1.0]).detect(img)
    assert a.extras["backend"] == "torch" and b.extras["backend"] == "opencv"
    assert np.abs(a.probability - b.probability).max() < 1e-3
    assert a.probability.std() > 1e-4


def test_auto_backend_is_opencv_on_the_cpu_where_the_onnx_export_is(micro_model_dir, tmp_path):
    import cv2

    assert get_detector("hma", model_dir=str(micro_model_dir)).backend.name == "opencv"
    only_pt = tmp_path / "pt_only"
    only_pt.mkdir()
    for name in ("config.json", "model.pt"):
        (only_pt / name).write_bytes((micro_model_dir / name).read_bytes())
    assert get_detector("hma", model_dir=str(only_pt)).backend.name == "torch"
    # a set thread count holds while the network runs and is given back after it
    det = get_detector("hma", model_dir=str(micro_model_dir), threads=1)
    net, seen = det.backend.net, []

    class Watched:  # cv2.dnn.Net's methods are read-only: watch it from outside
        def setInput(self, x):
            net.setInput(x)

        def forward(self):
            seen.append(cv2.getNumThreads())
            return net.forward()

    det.backend.net = Watched()
    before = cv2.getNumThreads()
    cv2.setNumThreads(2)
    try:
        det.detect(marker_image(angle=0.3))
        assert seen and set(seen) == {1}
        assert cv2.getNumThreads() == 2
    finally:
        cv2.setNumThreads(before)
    with pytest.raises(UsageError, match="threads"):
        get_detector("hma", model_dir=str(micro_model_dir), threads=0)
    with pytest.raises(InputError, match="model folder not found"):
        get_detector("hma", model_dir=str(tmp_path / "nowhere"))


def test_detector_runs_without_torch(micro_model_dir, tmp_path):
    only_onnx = tmp_path / "onnx_only"
    only_onnx.mkdir()
    for name in ("config.json", "model.onnx"):
        (only_onnx / name).write_bytes((micro_model_dir / name).read_bytes())
    code = textwrap.dedent(f"""
        import sys
        sys.modules["torch"] = None  # any import of torch now fails
        import numpy as np
        from cpdetect import get_detector
        det = get_detector("hma", model_dir={str(only_onnx)!r})
        r = det.detect(np.full((96, 128), 128, np.uint8))
        assert r.extras["backend"] == "opencv", r.extras
        assert r.probability.shape == (96, 128)
        try:
            get_detector("hma", model_dir={str(only_onnx)!r}, backend="torch")
        except Exception as exc:
            print("torch backend refused:", type(exc).__name__)
        print("ok")
    """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert "ok" in out.stdout and "torch backend refused: UsageError" in out.stdout


@pytest.mark.skipif(not shipped_weights_present(), reason="the shipped hma weights (learned/weights/default) are absent")
class TestHMAContract(DetectorContract):
    detector_name = "hma"
    settings = {"backend": "opencv"}


@pytest.mark.skipif(not shipped_weights_present("lite"), reason="the shipped lite hma weights (learned/weights/lite) are absent")
class TestHMALiteContract(DetectorContract):
    detector_name = "hma"
    settings = {"backend": "opencv", "network": "lite"}


def test_the_lite_network_is_its_own_folder_with_its_digests_and_a_narrow_head():
    from cpdetect.errors import UsageError
    from learned.adapter import SHIPPED_NETWORKS, default_model_dir
    from learned.digests import check_digest, read_digests
    from learned.hma import read_config

    lite = default_model_dir("lite")
    assert lite == SHIPPED_NETWORKS["lite"] != default_model_dir()
    assert set(read_digests(lite)) == {"model.pt", "model.onnx"}
    for name in ("model.pt", "model.onnx"):
        check_digest(lite / name)
    cfg = read_config(lite)
    assert (cfg.ocr_kernel, cfg.aux_mid, cfg.name) == (1, 64, "w16_lite")
    assert read_config(default_model_dir()).ocr_kernel == 3
    assert HMADetector(network="lite", backend="opencv").model_dir == lite
    # model_dir wins over network
    assert HMADetector(network="lite", model_dir=str(default_model_dir()), backend="opencv").model_dir == \
        default_model_dir()
    with pytest.raises((ValueError, UsageError), match="network must be one of default, lite"):
        get_detector("hma", network="huge")


@pytest.mark.skipif(not shipped_weights_present("lite"), reason="the shipped lite hma weights (learned/weights/lite) are absent")
def test_large_network_takes_the_images_seen_downscaled_only():
    from cpdetect.errors import UsageError

    rng = np.random.default_rng(5)
    small = rng.integers(0, 255, (96, 160), dtype=np.uint8)
    large = cv2.resize(small, (1200, 720), interpolation=cv2.INTER_LINEAR)  # over max_side=512 below
    both = HMADetector(large_network="lite", backend="opencv", max_side=512, small_scales=None, scales=(1.0,))
    plain = HMADetector(backend="opencv", max_side=512, small_scales=None, scales=(1.0,))
    lite = HMADetector(network="lite", backend="opencv", max_side=512, small_scales=None, scales=(1.0,))
    assert both.backend_for(160, 96) is both.backend and both.backend_for(1200, 720) is both.large_backend
    np.testing.assert_array_equal(both.probability(small).prob, plain.probability(small).prob)
    np.testing.assert_array_equal(both.probability(large).prob, lite.probability(large).prob)
    assert not np.array_equal(both.probability(large).prob, plain.probability(large).prob)
    assert both.detect(large).extras["network"] == "lite" and both.detect(small).extras["network"] == "default"
    assert plain.detect(large).extras["network"] == "default"
    # the same network twice opens one backend; no max_side means no image is seen downscaled
    same = HMADetector(large_network="default", backend="opencv")
    assert same.large_backend is None
    own = HMADetector(large_network="lite", model_dir=str(both.model_dir), backend="opencv")
    assert own.large_backend is None and own.detect(large).extras["network"] == "model_dir"
    unbounded = HMADetector(large_network="lite", backend="opencv", max_side=None)
    assert unbounded.backend_for(8192, 5460) is unbounded.backend
    with pytest.raises((ValueError, UsageError), match="large_network must be one of default, lite, got 'huge'"):
        get_detector("hma", large_network="huge")


def test_dedupe_keeps_one_detection_per_x_corner():
    from cpdetect.types import MarkerDetection
    from learned.adapter import dedupe

    big = MarkerDetection(50.0, 50.0, 0.7, "square", 20.0, 0.1)
    frag = MarkerDetection(50.4, 49.8, 0.9, "square", 6.0, 0.1)
    other = MarkerDetection(80.0, 50.0, 0.8, "circle", 10.0, 0.1)
    assert dedupe([frag, big, other]) == [big, other]
    assert len(dedupe([big, MarkerDetection(60.0, 50.0, 0.9, "square", 20.0, 0.1)])) == 2


def test_blobs_without_an_x_corner_are_dropped():
    # a dark disc on grey: the oracle says "marker", refinement finds no X-corner
    img = np.full((128, 128), 128, np.uint8)
    cv2.circle(img, (64, 64), 20, 30, -1)
    mask = np.zeros(img.shape, np.uint8)
    cv2.circle(mask, (64, 64), 20, 1, -1)
    assert HMADetector.with_backend(OracleBackend(mask)).detect(img).detections == []
    kept = HMADetector.with_backend(OracleBackend(mask), drop_unrefined=False).detect(img).detections
    assert len(kept) == 1 and abs(kept[0].x - 64) < 0.5 and abs(kept[0].y - 64) < 0.5


def blurred_noisy_marker():
    """(image, mask) of a square marker under heavy blur and noise: refinement finds its X-corner,
    but with a large sigma."""
    img, mask, _ = rendered("square", center=(128.0, 128.0), radius=26.0, angle=0.3)
    rng = np.random.default_rng(3)
    blurred = cv2.GaussianBlur(img.astype(np.float32), (0, 0), 6.0)
    return np.clip(blurred + rng.normal(0, 12.0, img.shape), 0, 255).astype(np.uint8), mask


def test_uncertain_refinements_are_dropped():
    noisy, mask = blurred_noisy_marker()
    # the bounds apply to the refinement's sigma; the model fit polishes kept centres after that,
    # and would report a smaller sigma than the one the bounds saw
    loose = HMADetector.with_backend(OracleBackend(mask), max_sigma_px=100.0, model_fit=False).detect(noisy).detections
    assert len(loose) == 1
    sigma = loose[0].sigma_px
    assert sigma > 0.05
    polished = HMADetector.with_backend(OracleBackend(mask), max_sigma_px=100.0).detect(noisy).detections
    assert len(polished) == 1 and polished[0].sigma_px <= sigma
    strict = HMADetector.with_backend(OracleBackend(mask), max_sigma_px=0.5 * sigma,
                                      max_sigma_verified_px=0.5 * sigma).detect(noisy).detections
    assert strict == []
    # where the marker model confirms the centre, a looser bound applies
    confirmed = HMADetector.with_backend(OracleBackend(mask), max_sigma_px=0.5 * sigma,
                                         max_sigma_verified_px=2.0 * sigma, model_fit=False).detect(noisy).detections
    # (its type is not asked for: a blur of a quarter of the radius rounds the square's corners into
    # an outline that fits a circle better, and the classical model now types by the outline's shape)
    assert len(confirmed) == 1 and confirmed[0].type in ("square", "circle")
    assert abs(confirmed[0].x - loose[0].x) < 1e-9 and abs(confirmed[0].y - loose[0].y) < 1e-9
    with pytest.raises(ValueError, match="max_sigma_px"):
        HMADetector.with_backend(OracleBackend(mask), max_sigma_px=0.0)


@pytest.mark.parametrize("marker_type", ["square", "circle", "diagonal"])
def test_centre_found_when_the_blob_centroid_is_far_off(marker_type):
    # the oracle blob covers the marker plus a long strip beside it (as a merged neighbour or a
    # perspective-stretched segment would): its centroid lies ~ a radius off the X-corner, beyond
    # the refinement's reach from there; the X-corner seeds still find the centre and the type
    center = (111.4, 128.7)
    img, mask, _ = rendered(marker_type, center=center, radius=26.0, angle=0.4)
    blob = mask.copy()
    blob[105:152, 130:240] = 1
    m = HMADetector.with_backend(OracleBackend(blob)).detect(img).detections
    assert len(m) == 1
    assert np.hypot(m[0].x - center[0], m[0].y - center[1]) < 0.15
    assert m[0].type == marker_type
    # only the centroid as seed (the former behaviour): nothing sharp there
    assert HMADetector.with_backend(OracleBackend(blob), max_seeds=0).detect(img).detections == []
    with pytest.raises(ValueError, match="type_by"):
        HMADetector.with_backend(OracleBackend(blob), type_by="colour")


@pytest.mark.skipif(not shipped_weights_present(), reason="the shipped hma weights (learned/weights/default) are absent")
def test_opencv_trunk_on_a_side_under_64_pixels():
    # OpenCV 5.0's DNN gave logits of 3.4e38 for a 32 x 96 input of the shipped network (and once a
    # segmentation fault further on); the backends pad every input to at least 64 x 64
    from learned.adapter import DEFAULT_MODEL_DIR
    from learned.infer import open_backend, torch_available

    x = np.random.default_rng(0).random((32, 96)).astype(np.float32)
    logits, attention = open_backend(DEFAULT_MODEL_DIR, "opencv").trunk(x)
    assert logits.shape == (2, 32, 96) and attention.shape == (32, 96)
    assert np.isfinite(logits).all() and np.abs(logits).max() < 100
    if torch_available() and (DEFAULT_MODEL_DIR / "model.pt").exists():
        ref, ref_att = open_backend(DEFAULT_MODEL_DIR, "torch").trunk(x)
        assert np.abs(logits - ref).max() < 1e-3 and np.abs(attention - ref_att).max() < 1e-3


def _one_sure_blob(monkeypatch, centre) -> None:
    """The detector's candidates become one blob over the whole map (mean P 0.95, radius 26 px) with
    this centre."""
    import learned.adapter as adapter

    def one_blob(self, gray, prob, f, seeds=None, loose=False):
        labels = (prob >= 0.5).astype(np.int32)
        blob = adapter.BlobCandidate(1, (0, 0, prob.shape[1], prob.shape[0]), 26.0, 0.95, (128.0, 128.0), centre)
        return [blob], labels

    monkeypatch.setattr(adapter.HMADetector, "candidates", one_blob)


@pytest.mark.parametrize("kind", ["seed", "verified", "centroid"])
def test_images_seen_downscaled_can_drop_centres_only_an_x_corner_seed_gave(monkeypatch, kind):
    # on 45 MP sets most refined X-corner seeds that the marker model does not verify were checkerboard
    # and shadow corners (stop 58); the setting drops those on the images the network sees downscaled
    import learned.adapter as adapter

    img, mask, _ = rendered("square", center=(128.0, 128.0), radius=26.0, angle=0.3)
    _one_sure_blob(monkeypatch, adapter._Centre(128.0, 128.0, 0.05, kind, type="square", sym180=0.9, reach=1.0))

    def found(max_side, drop):
        det = HMADetector.with_backend(OracleBackend(mask), None, scales=(1.0,), small_scales=None, mirror_map="never",
                                       max_side=max_side, large_drop_unverified_seeds=drop)
        return len(det.detect(img).detections)

    assert found(512, False) == found(512, True) == found(128, False) == 1  # not downscaled, or off
    assert found(128, True) == (0 if kind == "seed" else 1)
    assert HMADetector.with_backend(OracleBackend(mask)).settings.large_drop_unverified_seeds  # since stop 58


@pytest.mark.parametrize("reach,sym180", [(0.9, 0.5), (1.2, 0.5), (1.2, 0.95)])
def test_images_seen_downscaled_keep_seed_centres_that_reach_in(monkeypatch, reach, sym180):
    # large_spare_reach: a seed-only centre whose X-corner is at least as strong near the centre as on
    # the ring of half the blob's radius (a covered marker), and which is not point-symmetric (a
    # checkerboard's corner is), is kept where large_drop_unverified_seeds would drop it
    import learned.adapter as adapter

    img, mask, _ = rendered("square", center=(128.0, 128.0), radius=26.0, angle=0.3)
    _one_sure_blob(monkeypatch, adapter._Centre(128.0, 128.0, 0.05, "seed", type="square", sym180=sym180,
                                                reach=reach))

    def found(max_side, spare):
        det = HMADetector.with_backend(OracleBackend(mask), None, scales=(1.0,), small_scales=None, mirror_map="never",
                                       max_side=max_side, large_classical_veto=False, large_spare_reach=spare)
        return len(det.detect(img).detections)

    assert found(512, None) == found(512, 1.0) == 1  # not downscaled: not dropped at all
    assert found(128, None) == 0  # dropped, whatever the reach, with the setting off
    assert found(128, 1.0) == int(reach >= 1.0 and sym180 < 0.9)
    with pytest.raises(ValueError, match="large_spare_reach"):
        HMADetector.with_backend(OracleBackend(mask), large_spare_reach=0.0)
    with pytest.raises(ValueError, match="large_spare_max_sym180"):
        HMADetector.with_backend(OracleBackend(mask), large_spare_max_sym180=1.5)


def test_a_cover_across_half_the_radius_makes_the_x_corner_reach_over_one():
    # the measure large_spare_reach reads: with the blob's radius (the visible part's equal-area
    # radius), an occluder that crosses the ring of half that radius weakens the body's X-corner
    # there and not near the centre; uncovered, the ratio stays under 1 (blur only lowers it)
    from cpdetect.centre_reach import centre_reach
    from cpdetect.markers import render_frontal

    for mtype in ("square", "circle", "diagonal"):
        img = render_frontal(mtype, 200, 40.0, angle_rad=0.3, dark=30.0, bright=220.0, background=120.0)
        on = np.abs(img - 120.0) > 1.0
        whole = math.sqrt(on.sum() / math.pi)
        assert 0.85 < centre_reach(img.astype(np.uint8), 99.5, 99.5, whole) < 1.0
        covered = img.copy()
        covered[:, 112:] = 90.0  # from 12.5 px right of the centre on
        visible = math.sqrt((on & (np.arange(200)[None, :] < 112)).sum() / math.pi)
        assert 1.1 < centre_reach(covered.astype(np.uint8), 99.5, 99.5, visible) < 1.6


def _kept_in_map(img, mask, max_side, **settings) -> bool:
    """Whether the one sure blob (``_one_sure_blob``) stays in the returned map; min_radius_px over the
    blob's radius, so that it yields no marker whatever its centre."""
    det = HMADetector.with_backend(OracleBackend(mask), None, scales=(1.0,), small_scales=None, mirror_map="never",
                                   max_side=max_side, min_radius_px=40.0, **settings)
    res = det.detect(img)
    assert res.detections == []
    return float(res.probability.max()) >= 0.5


@pytest.mark.parametrize("kind,classical", [("seed", False), ("seed", True), ("verified", False), ("centroid", False)])
def test_images_seen_downscaled_can_clear_sure_blobs_around_unconfirmed_seeds(monkeypatch, kind, classical):
    # a blob the network is sure of stays in the map when it yields no marker, unless, on an image the
    # network sees downscaled and with the setting on, its centre is a seed nothing confirmed
    import learned.adapter as adapter

    img, mask, _ = rendered("square", center=(128.0, 128.0), radius=26.0, angle=0.3)
    _one_sure_blob(monkeypatch, adapter._Centre(128.0, 128.0, 0.05, kind, type="square", sym180=0.9, reach=1.0,
                                                classical=classical))

    def kept_in_map(max_side, clear):
        return _kept_in_map(img, mask, max_side, large_clear_unverified_seeds=clear)

    assert kept_in_map(512, False) and kept_in_map(512, True) and kept_in_map(128, False)  # not downscaled, or off
    assert kept_in_map(128, True) == (kind != "seed" or classical)
    assert HMADetector.with_backend(OracleBackend(mask)).settings.large_clear_unverified_seeds  # since stop 59


@pytest.mark.parametrize("flat", [True, False])
def test_images_seen_downscaled_can_clear_sure_blobs_of_one_tone(monkeypatch, flat):
    # a sure blob that yields no marker stays in the map, unless, on an image the network sees downscaled
    # and with large_clear_flat_below set, its inside shows one grey tone (a plain panel, no marker paint)
    import learned.adapter as adapter

    img, mask, _ = rendered("square", center=(128.0, 128.0), radius=26.0, angle=0.3)
    if flat:  # the same blob over a plain panel with sensor noise
        rng = np.random.default_rng(3)
        img = np.clip(50.0 + rng.normal(0.0, 3.0, img.shape), 0, 255).astype(np.uint8)
    _one_sure_blob(monkeypatch, adapter._Centre(128.0, 128.0, 0.05, "centroid", type="square", sym180=0.9, reach=1.0))

    def kept_in_map(max_side, below):
        return _kept_in_map(img, mask, max_side, large_clear_flat_below=below)

    assert kept_in_map(512, 3.0) and kept_in_map(128, 0.0)  # not downscaled, or off
    assert kept_in_map(128, 3.0) == (not flat)
    assert HMADetector.with_backend(OracleBackend(mask)).settings.large_clear_flat_below == 3.0  # since stop 61


def test_large_clear_flat_below_is_grey_levels():
    with pytest.raises(ValueError, match="large_clear_flat_below"):
        HMADetector.with_backend(OracleBackend(np.zeros((8, 8), np.uint8)), large_clear_flat_below=-1.0)


def _one_seed_blob(monkeypatch, at: tuple[float, float] = (128.02, 127.98)) -> list:
    """HMADetector.candidates replaced by one sure blob whose centre is a refined seed at ``at``,
    confirmed when a classical seed lies near it; returns the list that collects the seeds it was given."""
    import learned.adapter as adapter

    given = []

    def one_blob(self, gray, prob, f, seeds=None, loose=False):
        given.append(seeds)
        centre = adapter._Centre(at[0], at[1], 0.05, "seed", type="square", sym180=0.9, reach=1.0)
        if seeds:
            centre = adapter._with_classical(centre, seeds, 26.0)
        labels = (prob >= 0.5).astype(np.int32)
        return [adapter.BlobCandidate(1, (0, 0, prob.shape[1], prob.shape[0]), 26.0, 0.95, (128.0, 128.0), centre)], labels

    monkeypatch.setattr(adapter.HMADetector, "candidates", one_blob)
    return given


@pytest.mark.parametrize("max_side,on,kept", [(512, True, 1), (128, False, 0), (128, True, 1)])
def test_images_seen_downscaled_can_take_classical_markers_as_seeds(monkeypatch, max_side, on, kept):
    # a centre only a seed gave is dropped on a downscaled image (large_drop_unverified_seeds) unless
    # the classical detector, given the image, found a marker there too
    img, mask, _ = rendered("square", center=(128.0, 128.0), radius=26.0, angle=0.3)
    given = _one_seed_blob(monkeypatch)
    det = HMADetector.with_backend(OracleBackend(mask), None, scales=(1.0,), small_scales=None, mirror_map="never",
                                   max_side=max_side, large_classical_veto=False, large_classical_seeds=on)
    res = det.detect(img)
    assert len(res.detections) == kept and (res.probability.max() >= 0.5) == bool(kept)
    if max_side == 128 and on:  # the classical marker of the rendered one, within 0.1 px
        assert len(given[0]) == 1 and math.hypot(given[0][0].x - 128.0, given[0][0].y - 128.0) < 0.1
    else:
        assert given[0] is None  # the classical detector is not asked (nothing else needs it here)
    assert HMADetector.with_backend(OracleBackend(mask)).settings.large_classical_seeds  # the default since stop 65


def test_classical_seeds_can_be_limited_to_sure_classical_markers(monkeypatch):
    # classical_seed_min_score: a classical marker scored under it is no seed, so it confirms nothing
    from cpdetect.classical import BASE_SCORE_FILE, ClassicalDetector

    img, mask, _ = rendered("square", center=(128.0, 128.0), radius=26.0, angle=0.3)
    # hma's classical pass scores with the trees of before stop 83
    score = ClassicalDetector(score_trees=BASE_SCORE_FILE).detect(img).detections[0].score
    given = _one_seed_blob(monkeypatch)

    def found(min_score):
        det = HMADetector.with_backend(OracleBackend(mask), None, scales=(1.0,), small_scales=None,
                                       mirror_map="never", max_side=128, large_classical_veto=False,
                                       large_classical_seeds=True, classical_seed_min_score=min_score)
        return len(det.detect(img).detections)

    assert 0.5 < score < 1.0
    assert found(score) == 1 and len(given[-1]) == 1  # at its score: a seed, the blob kept
    assert found(min(1.0, score + 1e-6)) == 0 and given[-1] == []  # above it: no seed, the blob dropped
    assert HMADetector.with_backend(OracleBackend(mask)).settings.classical_seed_min_score == 0.99  # since stop 65
    with pytest.raises(ValueError, match="classical_seed_min_score"):
        HMADetector.with_backend(OracleBackend(mask), classical_seed_min_score=1.5)


@pytest.mark.parametrize("max_side,offset,confirm_above,kept", [
    (128, 0.0, 0.0, 1),      # a classical marker under the seeds' cut confirms the seed centre
    (128, 1.4, 0.0, 1),      # within 1.5 px
    (128, 1.7, 0.0, 0),      # not farther
    (128, 0.0, 1e-6, 0),     # scored under large_seed_confirm_min_score: no say
    (128, 0.0, None, 0),     # the setting off
    (512, 0.0, None, 1),     # an image seen whole: no seed-only centre is dropped
])
def test_a_classical_marker_under_the_seed_cut_can_confirm_a_seed_centre(monkeypatch, max_side, offset,
                                                                         confirm_above, kept):
    # large_seed_confirm_min_score (rule 25, stop 67): on 45 MP set 36100 a marker of radius 400 px whose
    # seed centre the classical detector confirmed at score 0.968, under the seeds' cut, was dropped as a
    # centre nothing confirmed; the confirmation spares it that rule and nothing else
    from cpdetect.classical import BASE_SCORE_FILE, ClassicalDetector

    img, mask, _ = rendered("square", center=(128.0, 128.0), radius=26.0, angle=0.3)
    found_at = ClassicalDetector(score_trees=BASE_SCORE_FILE).detect(img).detections[0]  # hma's classical pass
    given = _one_seed_blob(monkeypatch, at=(found_at.x + offset, found_at.y))
    det = HMADetector.with_backend(
        OracleBackend(mask), None, scales=(1.0,), small_scales=None, mirror_map="never", max_side=max_side,
        large_classical_veto=False, large_classical_seeds=True, classical_seed_min_score=1.0,
        large_seed_confirm_min_score=None if confirm_above is None else min(1.0, found_at.score + confirm_above))
    res = det.detect(img)
    assert 0.5 < found_at.score < 1.0
    assert given[-1] in ([], None)  # never a seed: scored under classical_seed_min_score
    assert len(res.detections) == kept and (res.probability.max() >= 0.5) == bool(kept)


def test_large_seed_confirm_min_score_is_a_score_or_off():
    mask = np.zeros((8, 8), np.uint8)
    assert HMADetector.with_backend(OracleBackend(mask)).settings.large_seed_confirm_min_score is None
    with pytest.raises(ValueError, match="large_seed_confirm_min_score"):
        HMADetector.with_backend(OracleBackend(mask), large_seed_confirm_min_score=1.2)


@pytest.mark.parametrize("on", [False, True])
def test_a_blob_can_take_the_classical_centre_its_own_choice_missed(monkeypatch, on):
    # the blob's refinement gives a centre 12 px off (as one whose window runs off the frame can); the
    # classical detector found the marker on the blob
    import learned.adapter as adapter

    img, mask, _ = rendered("square", center=(128.0, 128.0), radius=26.0, angle=0.3)
    off = adapter._Centre(140.0, 128.0, 0.05, "seed", type="square", sym180=0.9, reach=1.0)
    monkeypatch.setattr(adapter.HMADetector, "_refined_centre", lambda self, *a, **k: off)  # no ranker here
    det = HMADetector.with_backend(OracleBackend(mask), None, scales=(1.0,), small_scales=None, mirror_map="never",
                                   max_side=128, large_classical_veto=False, large_drop_unverified_seeds=False,
                                   large_classical_seeds=True, classical_centres=on)
    res = det.detect(img)
    at_centre = [d for d in res.detections if math.hypot(d.x - 128.0, d.y - 128.0) < 1.0]
    assert len(res.detections) == 1 and len(at_centre) == int(on)
    if on:
        assert math.hypot(at_centre[0].x - 128.0, at_centre[0].y - 128.0) < 0.1 and at_centre[0].type == "square"
    assert not HMADetector.with_backend(OracleBackend(mask)).settings.classical_centres  # opt-in (stop 60)


def test_the_classical_centre_prefers_an_option_it_confirms():
    from cpdetect.types import MarkerDetection
    from learned.adapter import _Centre, _classical_centre

    gray = np.zeros((64, 64), np.uint8)
    found = [MarkerDetection(30.0, 30.0, 0.9, "circle", 20.0, 0.02)]
    near = _Centre(30.4, 30.0, 0.1, "seed", type="square")
    far = _Centre(40.0, 30.0, 0.1, "verified", type="square")
    c = _classical_centre(gray, [(far, {}, 0.9), (near, {}, 0.2)], found, 20.0)
    assert (c.x, c.y, c.kind, c.type, c.classical) == (30.4, 30.0, "seed", "square", True)  # within 1.5 px
    c = _classical_centre(gray, [(far, {}, 0.9)], found, 20.0)
    assert (c.x, c.y, c.kind, c.type, c.model_score, c.classical) == (30.0, 30.0, "verified", "circle", 0.9, True)
    assert c.sigma == pytest.approx(0.02) and _classical_centre(gray, None, found, 20.0).x == 30.0


def test_classical_veto_needs_a_rejection_at_the_centre_and_no_classical_marker():
    from cpdetect.classical import TAG_FIELD
    from cpdetect.types import MarkerDetection
    from learned.adapter import ClassicalVeto

    trace = [{"x": 100.0, "y": 100.0, "stage": "score"}, {"x": 300.0, "y": 300.0, "stage": "prefilter"},
             {"x": 500.0, "y": 500.0, "stage": "single saddle"}, {"x": 700.0, "y": 700.0, "stage": "verify: " + TAG_FIELD},
             {"x": 900.0, "y": 900.0, "stage": "verify: outline degenerate"}]
    veto = ClassicalVeto.from_trace(trace, [MarkerDetection(505.0, 500.0, 0.9, "square", 30.0, 0.1)])
    assert veto.says_no(102.0, 100.0, 30.0) and veto.says_no(700.0, 707.0, 30.0)
    assert not veto.says_no(100.0, 109.0, 30.0) and veto.says_no(100.0, 109.0, 100.0)  # max(8 px, 0.1 radius)
    assert not veto.says_no(300.0, 300.0, 30.0) and not veto.says_no(900.0, 900.0, 30.0)  # no judgement there
    assert not veto.says_no(500.0, 500.0, 30.0)  # the classical detector kept a marker within half the radius
    assert not ClassicalVeto.from_trace([], []).says_no(100.0, 100.0, 30.0)


def test_images_seen_downscaled_take_the_classical_detectors_veto(monkeypatch):
    # the real classical scan, told to reject every centre's grey, leaves a "centre grey" row at the marker
    import learned.adapter as adapter
    from cpdetect.classical import ClassicalDetector

    img, mask, _ = rendered("square", center=(128.0, 128.0), radius=26.0, angle=0.3)
    plain = adapter.HMADetector._classical
    strict = {"on": False}

    def classical(self, image, with_map, trace=None):
        if strict["on"]:
            return ClassicalDetector(max_centre_offset=1e-6).detect(image, trace=trace)
        return plain(self, image, with_map, trace)

    monkeypatch.setattr(adapter.HMADetector, "_classical", classical)

    def detect(max_side, veto, reject):
        strict["on"] = reject
        det = HMADetector.with_backend(OracleBackend(mask), None, scales=(1.0,), small_scales=None, mirror_map="never",
                                       max_side=max_side, large_classical_veto=veto)
        return det.detect(img)

    for max_side, veto, reject in [(128, False, True), (512, True, True), (128, True, False)]:
        res = detect(max_side, veto, reject)
        assert len(res.detections) == 1 and res.probability.max() >= 0.5
    res = detect(128, True, True)
    assert res.detections == [] and res.probability.max() < 0.5  # dropped, its blob cleared
    assert HMADetector.with_backend(OracleBackend(mask)).settings.large_classical_veto  # since stop 59


@pytest.mark.parametrize("reach,sym180", [(0.9, 0.5), (1.2, 0.5), (1.2, 0.95)])
def test_a_centre_that_reaches_in_outweighs_the_classical_veto(monkeypatch, reach, sym180):
    # the real classical scan, told to reject every centre's grey, vetoes the marker unless its centre
    # reaches in and is not point-symmetric (large_spare_reach, large_spare_max_sym180)
    import learned.adapter as adapter
    from cpdetect.classical import ClassicalDetector

    img, mask, _ = rendered("square", center=(128.0, 128.0), radius=26.0, angle=0.3)
    monkeypatch.setattr(adapter.HMADetector, "_classical",
                        lambda self, image, with_map, trace=None: ClassicalDetector(max_centre_offset=1e-6).detect(
                            image, trace=trace))
    _one_sure_blob(monkeypatch, adapter._Centre(128.0, 128.0, 0.05, "verified", type="square", sym180=sym180,
                                                reach=reach))

    def found(spare):
        det = HMADetector.with_backend(OracleBackend(mask), None, scales=(1.0,), small_scales=None, mirror_map="never",
                                       max_side=128, large_spare_reach=spare)
        return len(det.detect(img).detections)

    assert found(None) == 0 and found(1.0) == int(reach >= 1.0 and sym180 < 0.9)


def test_the_veto_stages_are_stages_the_classical_scan_names():
    # the classical trace's stages are checked against the miss-stages bench's list in its own tests
    from bench_loader import load_bench
    from learned.adapter import CLASSICAL_VETO_STAGES

    known = set(load_bench("classical_miss_stages").ORDER)
    assert {st.split(":")[0] for st in CLASSICAL_VETO_STAGES} <= known
    assert "prefilter" not in CLASSICAL_VETO_STAGES and "kept" not in CLASSICAL_VETO_STAGES
