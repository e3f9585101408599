"""Contract tests of the HMA network with a tiny random model (no trained weights needed)."""
from __future__ import annotations

import json
import os

import numpy as np
import pytest

torch = pytest.importorskip("torch")
cv2 = pytest.importorskip("cv2")

from cpdetect.errors import InputError  # noqa: E402
torch.set_num_threads(1)  # the shared CI machine: one thread is faster than two oversubscribed

from learned.hma import (HMAConfig, build_model, count_parameters, load_matching, load_model,  # noqa: E402
                         marker_probability, preset, save_model)


_CALIBRATED: dict = {}


def calibrated(name: str = "test_micro", seed: int = 0, **changes):
    """A fresh copy of :func:`_calibrated` (cached)."""
    import copy

    key = (name, seed, tuple(sorted(changes.items())))
    if key not in _CALIBRATED:
        _CALIBRATED[key] = _calibrated(name, seed, **changes)
    return copy.deepcopy(_CALIBRATED[key])


def _calibrated(name: str = "test_micro", seed: int = 0, **changes):
    """A random model whose BatchNorm statistics are measured on smooth random images, so that its
    activations have realistic magnitudes in eval mode (raw Kaiming init + unit BN stats explode)."""
    torch.manual_seed(seed)
    m = build_model(preset(name, **changes))
    for mod in m.modules():
        if isinstance(mod, torch.nn.modules.batchnorm._BatchNorm):
            mod.momentum = None  # cumulative average
    m.train()
    with torch.no_grad():
        for _ in range(3):
            m(smooth_images(4, 128, 160, seed=seed + _))
    for mod in m.modules():
        if isinstance(mod, torch.nn.modules.batchnorm._BatchNorm):
            mod.momentum = 0.1
    return m.eval()


def smooth_images(n: int, h: int, w: int, seed: int = 0) -> torch.Tensor:
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        small = rng.random((h // 8 + 2, w // 8 + 2)).astype(np.float32)
        out.append(np.clip(cv2.resize(small, (w, h), interpolation=cv2.INTER_CUBIC), 0, 1))
    return torch.from_numpy(np.stack(out)[:, None])


def test_presets_have_the_documented_sizes():
    # hma.md 4.1: w18s1_lite ~2.0 M parameters, w16_tiny ~1.1 M (our semantic head is the paper's 3x3-3x3-1x1)
    lite = count_parameters(build_model("w18s1_lite"))
    tiny = count_parameters(build_model("w16_tiny"))
    assert 1.8e6 < lite < 2.4e6
    assert 1.0e6 < tiny < 1.3e6
    assert count_parameters(build_model("test_micro")) < 30_000


def test_forward_backward_two_scale_training():
    torch.manual_seed(0)
    m = build_model("test_micro").train()
    x = smooth_images(2, 64, 96)
    out = m(x)
    assert set(out) == {"pred", "aux", "pred_lo", "pred_hi", "attn"}
    for k in ("pred", "aux", "pred_lo", "pred_hi"):
        assert out[k].shape == (2, 2, 64, 96)
    assert out["attn"].shape == (2, 1, 32, 48)
    a = out["attn"].detach()
    assert 0.0 < float(a.min()) and float(a.max()) < 1.0
    from learned.rmi import hma_loss

    labels = torch.zeros(2, 64, 96, dtype=torch.int64)
    labels[:, 20:40, 30:60] = 1
    loss, _ = hma_loss(out, labels)
    loss.backward()
    no_grad = [n for n, p in m.named_parameters() if p.grad is None or not torch.isfinite(p.grad).all()]
    assert no_grad == []
    # every head takes part: attention, semantic, aux and the backbone stem get non-zero gradients
    for name in ("attn_head.0.weight", "cls_head.6.weight", "ocr.aux_head.3.weight", "backbone.stem.0.weight"):
        assert float(dict(m.named_parameters())[name].grad.abs().sum()) > 0


@pytest.mark.parametrize("hw", [(37, 53), (64, 64), (96, 130)])
def test_arbitrary_input_size_in_eval(hw):
    m = calibrated()
    x = smooth_images(1, *hw)
    with torch.no_grad():
        for scales in ((1.0,), (0.5, 1.0), (0.5, 1.0, 2.0)):
            y = m(x, scales=scales)
            assert y.shape == (1, 2) + hw
            assert bool(torch.isfinite(y).all())


def test_nscale_at_half_and_one_equals_two_scale_forward():
    m = calibrated()
    x = smooth_images(2, 96, 128, seed=3)
    with torch.no_grad():
        two = m.two_scale_forward(x)
        n = m.nscale_forward(x, (1.0, 0.5))
        n_aux = m.nscale_forward(x, (0.5, 1.0), with_aux=True)[1]
    assert float((two["pred"] - n).abs().max()) < 1e-5
    assert float((two["aux"] - n_aux).abs().max()) < 1e-5
    # the fusion is not trivial: it differs from the 1.0 scale alone
    assert float((n - two["pred_hi"]).abs().max()) > 1e-3


def test_nscale_requires_the_unit_scale():
    m = calibrated()
    with pytest.raises(ValueError):
        m.nscale_forward(smooth_images(1, 32, 32), (0.5, 2.0))


def test_three_scale_fusion_follows_the_recursion():
    m = calibrated()
    x = smooth_images(1, 64, 96, seed=4)
    from learned.hma import resize_scale
    from learned.hrnet import resize_to

    with torch.no_grad():
        got = m.nscale_forward(x, (0.5, 1.0, 2.0))
        p2, _, _ = m._fwd(resize_scale(x, 2.0))
        p1, _, a1 = m._fwd(x)
        p05, _, a05 = m._fwd(resize_scale(x, 0.5))
        mid = a1 * p1 + (1 - a1) * resize_to(p2, p1)
        want = resize_to(a05 * p05, p1) + (1 - resize_to(a05, p1)) * mid
    assert float((got - want).abs().max()) < 1e-5


def test_save_load_round_trip(tmp_path):
    m = calibrated()
    d = save_model(m, tmp_path / "model")
    cfg = json.loads((d / "config.json").read_text())
    assert cfg["format"] == "cpdetect-hma" and cfg["num_classes"] == 2 and cfg["name"] == "test_micro"
    m2 = load_model(d)
    assert m2.config == m.config
    x = smooth_images(1, 64, 80, seed=5)
    with torch.no_grad():
        assert torch.equal(m(x), m2(x))


def test_load_errors_name_the_file(tmp_path):
    with pytest.raises(InputError, match="not found"):
        load_model(tmp_path / "nothing")
    d = save_model(calibrated(), tmp_path / "m")
    (d / "model.pt").write_bytes(b"garbage")
    with pytest.raises(InputError, match="model.pt"):
        load_model(d)
    other = save_model(build_model(preset("test_micro", num_classes=3)), tmp_path / "k3")
    (other / "config.json").write_text((d / "config.json").read_text())
    with pytest.raises(InputError, match="do not match"):
        load_model(other)
    (d / "config.json").write_text('{"format": "cpdetect-hma", "version": 1, "bogus": 1}')
    with pytest.raises(InputError, match="bogus"):
        load_model(d)


class _RunsCodeWhenUnpickled:
    """Pickles as a call of os.mkdir: loading it with plain pickle would create ``path``."""

    def __init__(self, path):
        self.path = str(path)

    def __reduce__(self):
        return (os.mkdir, (self.path,))


def test_damaged_or_unsafe_weight_files_are_refused_in_words(tmp_path):
    from learned.hma import load_torch_file
    from learned.train import read_state

    d = save_model(calibrated(), tmp_path / "m")
    (d / "SHA256SUMS").unlink()  # a folder without digests: torch reads each file, and we say why not
    good = (d / "model.pt").read_bytes()
    cases = [(b"", "empty file"), (b"junk\n", "not a PyTorch file"),
             (b'{"format": "cpdetect.model/1"}\n', "not a PyTorch file"),
             (good[: len(good) // 2], "damaged or truncated PyTorch file")]
    for data, why in cases:
        (d / "model.pt").write_bytes(data)
        with pytest.raises(InputError, match=why) as exc:
            load_model(d)
        assert "model.pt" in str(exc.value) and "\n" not in str(exc.value)
    # a pickled object that runs code on loading is refused, and its code never runs
    marker = tmp_path / "code_ran"
    torch.save({"w": _RunsCodeWhenUnpickled(marker)}, tmp_path / "unsafe.pt")
    for load in (lambda p: load_torch_file(p, "checkpoint"), read_state):
        with pytest.raises(InputError, match="could run code"):
            load(tmp_path / "unsafe.pt")
    assert not marker.exists()
    # weights that are not a state dict
    torch.save([torch.zeros(2)], d / "model.pt")
    with pytest.raises(InputError, match="not a state dict"):
        load_model(d)


def _flip_a_weight_byte(path, tensor):
    """Change one byte inside ``tensor``'s stored bytes in ``path`` (the file still loads)."""
    data = bytearray(path.read_bytes())
    at = bytes(data).find(tensor.detach().contiguous().numpy().tobytes())
    assert at > 0
    data[at + 5] ^= 0xFF
    path.write_bytes(bytes(data))


def test_weight_digests_catch_a_changed_byte_in_torch_and_onnx_files(tmp_path):
    from learned.digests import file_sha256, read_digests
    from learned.export import export_onnx
    from learned.infer import OpenCVBackend

    m = calibrated()
    d = save_model(m, tmp_path / "m")
    assert read_digests(d) == {"model.pt": file_sha256(d / "model.pt")}
    onnx = export_onnx(m, d / "model.onnx")  # into the model folder: recorded beside model.pt
    assert set(read_digests(d)) == {"model.pt", "model.onnx"}
    OpenCVBackend(onnx)
    big = max(m.state_dict().values(), key=lambda t: t.numel())
    _flip_a_weight_byte(d / "model.pt", big)
    with pytest.raises(InputError, match="model.pt: damaged: its SHA-256 is not the one in SHA256SUMS"):
        load_model(d)
    data = bytearray(onnx.read_bytes())
    data[len(data) // 2] ^= 0xFF
    onnx.write_bytes(bytes(data))
    with pytest.raises(InputError, match="model.onnx: damaged"):
        OpenCVBackend(onnx)
    # a file without a line is not checked: the changed model.pt loads once its line is gone
    (d / "SHA256SUMS").write_text(f"{read_digests(d)['model.onnx']}  model.onnx\n")
    assert load_model(d).config == m.config
    # an export outside a model folder leaves no digest file behind
    export_onnx(m, tmp_path / "loose.onnx")
    assert not (tmp_path / "SHA256SUMS").exists()
    (d / "SHA256SUMS").write_text("not a digest line\n")
    with pytest.raises(InputError, match="SHA256SUMS: line 1 is not"):
        load_model(d)
    # without digests, a file OpenCV cannot parse is named in OpenCV's words, without its source paths
    (d / "SHA256SUMS").unlink()
    onnx.write_bytes(b"junk")
    with pytest.raises(InputError, match=r"model.onnx: OpenCV cannot load the ONNX model: Failed to parse ONNX model$"):
        OpenCVBackend(onnx)
    onnx.write_bytes(b"")
    with pytest.raises(InputError, match="model.onnx: empty file"):
        OpenCVBackend(onnx)


def test_the_shipped_weights_match_their_digests():
    from learned.adapter import default_model_dir
    from learned.digests import check_digest, read_digests

    d = default_model_dir()
    assert set(read_digests(d)) == {"model.pt", "model.onnx"}
    for name in ("model.pt", "model.onnx"):
        check_digest(d / name)


def test_config_round_trips_through_dict():
    c = preset("w18s1_lite")
    assert HMAConfig.from_dict(json.loads(json.dumps(c.to_dict()))) == c
    with pytest.raises(ValueError):
        HMAConfig(seg_head="deeplab")


def test_transfer_learning_loads_matching_layers_only():
    src = calibrated(num_classes=5)
    dst = build_model("test_micro")
    before = {k: v.clone() for k, v in dst.state_dict().items()}
    loaded, skipped = load_matching(dst, src.state_dict())
    # only the class-count dependent tensors differ: final convs of the semantic and aux heads
    assert sorted(skipped) == ["cls_head.6.bias", "cls_head.6.weight", "ocr.aux_head.3.bias", "ocr.aux_head.3.weight"]
    assert len(loaded) == len(before) - 4
    sd = dst.state_dict()
    assert torch.equal(sd["backbone.stem.0.weight"], src.state_dict()["backbone.stem.0.weight"])
    assert torch.equal(sd["cls_head.6.weight"], before["cls_head.6.weight"])


def test_marker_probability_is_softmax_channel_one():
    logits = torch.tensor([[[[0.0]], [[np.log(3.0)]]]], dtype=torch.float32)
    assert abs(float(marker_probability(logits)) - 0.75) < 1e-6


# ---------------------------------------------------------------------------------------- inference


def test_numpy_fusion_equals_the_model_fusion():
    from learned.infer import TorchBackend, fuse_scales, marker_probability_np

    m = calibrated()
    x = smooth_images(1, 128, 192, seed=6)
    tb = TorchBackend(m)
    for scales in ((1.0,), (0.5, 1.0), (0.5, 1.0, 2.0)):
        got = marker_probability_np(fuse_scales(tb, x[0, 0].numpy(), scales))
        with torch.no_grad():
            want = marker_probability(m.nscale_forward(x, scales))[0, 0].numpy()
        assert np.abs(got - want).max() < 1e-4, scales


def test_one_lower_step_equals_fusing_the_lower_scale_with_the_others():
    from learned.infer import TorchBackend, fuse_lower, fuse_scales

    m = calibrated()
    x = smooth_images(1, 128, 192, seed=7)[0, 0].numpy()
    tb = TorchBackend(m)
    for above, low in (((0.5, 1.0), 0.25), ((1.0,), 0.5), ((0.5, 1.0, 2.0), 0.25)):
        want = fuse_scales(tb, x, above + (low,))
        got = fuse_lower(tb, x, fuse_scales(tb, x, above), low)
        assert got.shape == want.shape
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-6)
        # and the lower pass changes the fusion (the step is not a no-op)
        assert np.abs(got - fuse_scales(tb, x, above)).max() > 1e-3


def test_onnx_through_opencv_matches_torch_at_two_sizes(tmp_path):
    pytest.importorskip("onnx")
    from learned.export import export_onnx
    from learned.infer import OpenCVBackend, TorchBackend, fuse_scales, marker_probability_np

    m = calibrated("test_micro", seed=1)
    path = export_onnx(m, tmp_path / "m.onnx")
    tb, ob = TorchBackend(m), OpenCVBackend(path)
    for hw in ((128, 160), (96, 224)):
        x = smooth_images(1, *hw, seed=hw[0])[0, 0].numpy()
        for scales in ((1.0,), (0.5, 1.0)):
            pt = marker_probability_np(fuse_scales(tb, x, scales))
            po = marker_probability_np(fuse_scales(ob, x, scales))
            assert pt.shape == po.shape == hw
            assert np.abs(pt - po).max() < 1e-3
            assert pt.std() > 1e-4  # not a constant map


def test_fusion_stays_finite_when_a_backend_returns_infinite_logits():
    from learned.infer import fuse_scales, marker_probability_np

    class Saturated:
        name = "saturated"

        def trunk(self, x):
            p = np.zeros((2,) + x.shape, np.float32)
            p[1] = np.inf  # certain marker everywhere
            p[1, 0, 0] = np.nan
            return p, np.zeros(x.shape, np.float32)

    logits = fuse_scales(Saturated(), np.full((32, 48), 0.4, np.float32), (0.5, 1.0, 2.0))
    assert np.isfinite(logits).all()
    prob = marker_probability_np(logits)
    assert prob.shape == (32, 48) and prob[5:, 5:].min() > 0.999


def test_tiles_partition_the_axis():
    from learned.infer import tiles

    for length, tile, overlap in ((100, 200, 10), (1000, 256, 32), (777, 300, 50)):
        ts = tiles(length, tile, overlap)
        keep = [(k0, k1) for _, _, k0, k1 in ts]
        assert keep[0][0] == 0 and keep[-1][1] == length
        assert all(a[1] == b[0] for a, b in zip(keep, keep[1:]))
        for s0, s1, k0, k1 in ts:
            assert 0 <= s0 <= k0 < k1 <= s1 <= length and s1 - s0 <= tile
            assert (k0 - s0 >= overlap or s0 == 0) and (s1 - k1 >= overlap or s1 == length)


class LocalBackend:
    """A stand-in network whose output at a pixel depends only on a 13x13 neighbourhood."""

    name = "local"

    def __init__(self):
        self.calls = []

    def trunk(self, x):
        self.calls.append(x.shape)
        logit = 8.0 * (cv2.GaussianBlur(x, (13, 13), 2.0, borderType=cv2.BORDER_REFLECT_101) - 0.5)
        return np.stack([np.zeros_like(logit), logit]), np.full(x.shape, 0.5, np.float32)


def test_tiled_probability_map_equals_untiled_for_a_local_network():
    from learned.infer import probability_map

    g = (smooth_images(1, 300, 500, seed=8)[0, 0].numpy() * 255).astype(np.uint8)
    be = LocalBackend()
    whole = probability_map(g, be, (1.0,), max_side=None, tile=2048)
    assert be.calls == [(300, 500)]
    be.calls.clear()
    tiled = probability_map(g, be, (1.0,), max_side=None, tile=160, overlap=32)
    assert len(be.calls) > 6 and max(max(c) for c in be.calls) <= 160
    assert whole.prob.shape == tiled.prob.shape == g.shape
    assert np.abs(whole.prob - tiled.prob).max() < 1e-5
    small = probability_map(g, be, (1.0,), max_side=250)
    assert small.prob.shape == (150, 250) and abs(small.factor - 0.5) < 1e-9


def test_real_network_tiles_stay_close_to_the_whole_image():
    from learned.infer import TorchBackend, probability_map

    m = calibrated("test_micro", seed=2)
    g = (smooth_images(1, 192, 320, seed=8)[0, 0].numpy() * 255).astype(np.uint8)
    tb = TorchBackend(m)
    whole = probability_map(g, tb, (1.0,), max_side=None, tile=2048)
    tiled = probability_map(g, tb, (1.0,), max_side=None, tile=192, overlap=48)
    # the OCR context is gathered per tile, so a random network differs, but boundedly
    assert 0.0 < np.abs(whole.prob - tiled.prob).mean() < 0.25


# ---------------------------------------------------------------------------------------- training


def _tiny_samples(n: int = 3, seed: int = 0):
    from cpdetect.markers import MarkerSpec, frontal_homography, render_marker
    from learned.data import Sample

    rng = np.random.default_rng(seed)
    out = []
    for i in range(n):
        img = (smooth_images(1, 96, 128, seed=seed + i)[0, 0].numpy() * 120 + 60).astype(np.float32)
        mask = np.zeros(img.shape, np.float32)
        c = (rng.uniform(30, 98), rng.uniform(30, 66))
        spec = MarkerSpec("square", 1.0)
        rm = render_marker(spec, frontal_homography(c, 14.0, rng.uniform(0, 3), spec), img.shape)
        rm.composite(img, 20.0, 235.0)
        mask[rm.y0:rm.y0 + rm.dark.shape[0], rm.x0:rm.x0 + rm.dark.shape[1]] += rm.pattern
        out.append(Sample(None, None, np.array([c]), np.array([14.0]), np.clip(img, 0, 255).astype(np.uint8),
                          (mask >= 0.5).astype(np.uint8)))
    return out


def _cfg(out, **kw):
    from learned.data import AugmentConfig
    from learned.train import TrainConfig

    base = dict(data="", out=str(out), model="test_micro", epochs=2, iters_per_epoch=2, batch=2, crop=64,
                val_crops=4, checkpoint_minutes=0.0, augment=AugmentConfig(crop=64), channels_last=False, threads=1)
    base.update(kw)
    return TrainConfig(**base)


def _weights(d):
    return torch.load(d / "checkpoint.pt", weights_only=False)["model"]


@pytest.mark.parametrize("optimizer", ["sgd", "adamw"])
def test_training_is_deterministic_and_resume_continues_exactly(tmp_path, optimizer):
    from learned.train import train

    s = _tiny_samples()
    r1 = train(_cfg(tmp_path / "a", optimizer=optimizer), samples=s[:2], val_samples=s[2:], progress=False)
    r2 = train(_cfg(tmp_path / "b", optimizer=optimizer), samples=s[:2], val_samples=s[2:], progress=False)
    assert r1.iterations == r2.iterations == 4
    w1, w2 = _weights(tmp_path / "a"), _weights(tmp_path / "b")
    assert all(torch.equal(w1[k], w2[k]) for k in w1)
    # an interrupted run (checkpoint every iteration) resumed == the uninterrupted run

    class Stop(Exception):
        pass

    def stop_at_3(it, parts):
        if it == 3:
            raise Stop

    with pytest.raises(Stop):
        train(_cfg(tmp_path / "c", optimizer=optimizer), samples=s[:2], val_samples=s[2:], progress=False,
              on_iteration=stop_at_3)
    assert torch.load(tmp_path / "c" / "checkpoint.pt", weights_only=False)["iteration"] == 2
    r3 = train(_cfg(tmp_path / "c", optimizer=optimizer), resume=True, samples=s[:2], val_samples=s[2:],
               progress=False)
    assert r3.iterations == 4
    w3 = _weights(tmp_path / "c")
    assert max(float((w1[k].float() - w3[k].float()).abs().max()) for k in w1) < 1e-6
    log = [json.loads(line) for line in (tmp_path / "a" / "train_log.jsonl").read_text().splitlines()]
    assert any("val" in rec for rec in log)
    assert load_model(tmp_path / "a").config.name == "test_micro"


def test_crop_workers_draw_the_serial_batches_and_weights(tmp_path):
    """Crops drawn in worker processes are the serial loop's, batch for batch, across an epoch
    boundary and from a resumed iteration; so a run with workers ends with the same weights."""
    from learned.data import AugmentConfig, CropDataset
    from learned.train import batch_stream, train

    s = _tiny_samples()
    crops = CropDataset(s, AugmentConfig(crop=64), 3 * 2, seed=5)
    serial = list(batch_stream(crops, 3, 2, start=2, stop=7))
    pooled = list(batch_stream(crops, 3, 2, start=2, stop=7, workers=2))
    assert len(serial) == len(pooled) == 5
    for (xa, ya), (xb, yb) in zip(serial, pooled):
        assert torch.equal(xa, xb) and torch.equal(ya, yb)
    # iteration 3 is the first of epoch 1: item 0 of that epoch, not of epoch 0
    crops.set_epoch(1)
    assert torch.equal(serial[1][0][0], crops[0][0])
    assert not torch.equal(serial[1][0][0], crops.draw(0, 0)[0])
    r0 = train(_cfg(tmp_path / "a"), samples=s[:2], val_samples=s[2:], progress=False)
    r2 = train(_cfg(tmp_path / "b", workers=2), samples=s[:2], val_samples=s[2:], progress=False)
    assert r0.iterations == r2.iterations == 4
    w0, w2 = _weights(tmp_path / "a"), _weights(tmp_path / "b")
    assert all(torch.equal(w0[k], w2[k]) for k in w0)
    # a bad image met by a worker is the same one-line error as in the training process
    from learned.data import Sample

    bad = tmp_path / "bad.jpg"
    bad.write_bytes(b"not a jpeg")
    broken = CropDataset([Sample(bad, bad, np.zeros((0, 2)), np.zeros(0))], AugmentConfig(crop=64), 2, seed=5)
    for workers in (0, 2):
        with pytest.raises(InputError) as exc:
            list(batch_stream(broken, 1, 2, start=0, stop=1, workers=workers))
        assert str(exc.value) == f"{bad}: not an image (unrecognised format)"


def test_channels_last_is_used_on_the_cpu_only_and_trains_the_same_weights(tmp_path):
    """Channels-last gave a CUDA gradient 19 % off (bench/train_step_parity.py), so it is a CPU-only
    speed-up; on the CPU it must not change what is learned."""
    from learned.train import train, use_channels_last

    assert use_channels_last(_cfg(tmp_path, channels_last=True), torch.device("cpu"))
    assert not use_channels_last(_cfg(tmp_path, channels_last=True), torch.device("cuda"))
    assert not use_channels_last(_cfg(tmp_path, channels_last=False), torch.device("cpu"))
    # one SGD step (later steps of this tiny random network amplify float reordering chaotically)
    s = _tiny_samples()
    one = dict(optimizer="sgd", epochs=1, iters_per_epoch=1)
    train(_cfg(tmp_path / "a", **one), samples=s[:2], val_samples=s[2:], progress=False)
    train(_cfg(tmp_path / "b", channels_last=True, **one), samples=s[:2], val_samples=s[2:], progress=False)
    wa, wb = _weights(tmp_path / "a"), _weights(tmp_path / "b")
    torch.manual_seed(0)  # the run's seed: its initial weights
    start = build_model(preset("test_micro", num_classes=2)).state_dict()
    moved = max(float((wa[k].float() - start[k].float()).abs().max()) for k in wa if k.endswith("weight"))
    assert moved > 1e-3  # the step did move the weights, by more than the tolerance below
    assert all(torch.allclose(wa[k].float(), wb[k].float(), rtol=1e-4, atol=1e-4) for k in wa)


def test_a_signal_stops_training_with_a_checkpoint_at_that_iteration(tmp_path):
    """SIGTERM (a killed job) mid-epoch: the run returns at once, marked interrupted, with the
    checkpoint at the current iteration (not the last periodic one), and resuming it ends where an
    uninterrupted run ends. The handlers are restored afterwards."""
    import os
    import signal

    from learned.train import train

    s = _tiny_samples()
    ref = train(_cfg(tmp_path / "ref", epochs=2, iters_per_epoch=3), samples=s[:2], val_samples=s[2:],
                progress=False)
    before = signal.getsignal(signal.SIGTERM)

    def term_at_4(it, parts):
        if it == 4:
            os.kill(os.getpid(), signal.SIGTERM)

    cfg = _cfg(tmp_path / "c", epochs=2, iters_per_epoch=3, checkpoint_minutes=60.0)
    r = train(cfg, samples=s[:2], val_samples=s[2:], progress=False, on_iteration=term_at_4)
    assert r.interrupted and r.iterations == 4
    assert signal.getsignal(signal.SIGTERM) is before
    assert torch.load(tmp_path / "c" / "checkpoint.pt", weights_only=False)["iteration"] == 4
    r2 = train(cfg, resume=True, samples=s[:2], val_samples=s[2:], progress=False)
    assert not r2.interrupted and r2.iterations == ref.iterations == 6
    w_ref, w = _weights(tmp_path / "ref"), _weights(tmp_path / "c")
    assert max(float((w_ref[k].float() - w[k].float()).abs().max()) for k in w_ref) < 1e-6


def test_a_second_signal_stops_at_once():
    import signal

    from learned.train import _StopRequest

    stop = _StopRequest()
    stop._handle(signal.SIGINT, None)
    assert stop.signum == signal.SIGINT
    with pytest.raises(KeyboardInterrupt):
        stop._handle(signal.SIGINT, None)
    stop = _StopRequest()
    stop._handle(signal.SIGTERM, None)
    with pytest.raises(SystemExit) as exc:
        stop._handle(signal.SIGTERM, None)
    assert exc.value.code == 128 + signal.SIGTERM


def test_training_from_init_with_other_class_count_and_frozen_backbone(tmp_path):
    from learned.train import train

    src = save_model(calibrated(num_classes=4), tmp_path / "src")
    s = _tiny_samples()
    train(_cfg(tmp_path / "ft", epochs=1, init=str(src), freeze_backbone=True), samples=s[:2],
          val_samples=s[2:], progress=False)
    ft = torch.load(tmp_path / "ft" / "checkpoint.pt", weights_only=False)["model"]
    src_state = torch.load(src / "model.pt", weights_only=True)
    # frozen backbone: its weights and BN statistics are those of the checkpoint
    assert torch.equal(ft["backbone.stem.0.weight"], src_state["backbone.stem.0.weight"])
    assert torch.equal(ft["backbone.stem.1.running_mean"], src_state["backbone.stem.1.running_mean"])
    # the OCR head trained on, the 2-class semantic head was re-initialised with 2 outputs
    assert not torch.equal(ft["ocr.conv3x3_ocr.0.weight"], src_state["ocr.conv3x3_ocr.0.weight"])
    assert ft["cls_head.6.weight"].shape[0] == 2


def test_a_new_run_refuses_to_overwrite_a_checkpoint(tmp_path):
    from cpdetect.errors import UsageError
    from learned.train import train

    s = _tiny_samples()
    train(_cfg(tmp_path / "m", epochs=1), samples=s[:2], val_samples=s[2:], progress=False)
    before = (tmp_path / "m" / "checkpoint.pt").read_bytes()
    with pytest.raises(UsageError, match="already holds a training run.*--resume"):
        train(_cfg(tmp_path / "m", epochs=1), samples=s[:2], val_samples=s[2:], progress=False)
    assert (tmp_path / "m" / "checkpoint.pt").read_bytes() == before


def test_resume_refuses_a_damaged_checkpoint_or_another_optimizer(tmp_path):
    from cpdetect.errors import UsageError
    from learned.train import train

    s = _tiny_samples()
    train(_cfg(tmp_path / "m", epochs=1), samples=s[:2], val_samples=s[2:], progress=False)
    ck = tmp_path / "m" / "checkpoint.pt"
    good = ck.read_bytes()
    with pytest.raises(UsageError, match="started with --optimizer sgd, this one has adamw"):
        train(_cfg(tmp_path / "m", epochs=2, optimizer="adamw"), resume=True, samples=s[:2], val_samples=s[2:],
              progress=False)
    with pytest.raises(UsageError, match="started with --freeze-backbone False"):
        train(_cfg(tmp_path / "m", epochs=2, freeze_backbone=True), resume=True, samples=s[:2],
              val_samples=s[2:], progress=False)
    ck.write_bytes(good[: len(good) // 3])
    with pytest.raises(InputError, match="checkpoint.pt.*damaged or truncated"):
        train(_cfg(tmp_path / "m", epochs=2), resume=True, samples=s[:2], val_samples=s[2:], progress=False)
    torch.save({"model": {}}, ck)
    with pytest.raises(InputError, match="not a cpdetect training checkpoint .*optimizer"):
        train(_cfg(tmp_path / "m", epochs=2), resume=True, samples=s[:2], val_samples=s[2:], progress=False)


def test_a_batch_too_small_for_batch_norm_is_refused_before_anything_is_written(tmp_path):
    from cpdetect.errors import UsageError
    from learned.data import AugmentConfig
    from learned.train import train

    s = _tiny_samples()
    # one 64 px crop: the half-scale pass ends in a 1 x 1 map, and torch's batch norm would fail
    # inside the first iteration
    with pytest.raises(UsageError, match="--batch 2 or more, or --crop 96"):
        train(_cfg(tmp_path / "m", batch=1, crop=64), samples=s[:2], val_samples=s[2:], progress=False)
    assert not (tmp_path / "m").exists()
    res = train(_cfg(tmp_path / "ok", batch=1, crop=96, augment=AugmentConfig(crop=96), epochs=1, iters_per_epoch=1),
                samples=s[:2], val_samples=s[2:], progress=False)
    assert res.iterations == 1


def test_unknown_optimizer_is_refused(tmp_path):
    from learned.train import train

    s = _tiny_samples()
    with pytest.raises(ValueError, match="unknown optimizer 'rmsprop'; valid: sgd, adamw"):
        train(_cfg(tmp_path / "x", optimizer="rmsprop"), samples=s[:2], val_samples=s[2:], progress=False)


def test_augmented_crops_keep_labels_aligned():
    from learned.data import AugmentConfig, augment

    s = _tiny_samples(1, seed=3)[0]
    img, mask = s.load()
    rng = np.random.default_rng(0)
    cfg = AugmentConfig(crop=64, blur_prob=0.0, noise_max=0.0, brightness=0.0, contrast=0.0, gamma=0.0)
    for _ in range(10):
        x, lab = augment(img, mask, s.centers, cfg, rng)
        assert x.shape == lab.shape == (64, 64) and x.dtype == np.float32
        assert set(np.unique(lab)) <= {0, 1, 255}
        inside = lab == 1
        if inside.sum() > 50:  # marker pixels are dark or bright, never the mid-grey background
            v = x[inside]
            assert np.mean((v < 0.25) | (v > 0.75)) > 0.7


def test_small_marker_bias_draws_small_markers_more_often():
    from learned.data import AugmentConfig, augment

    # two markers far apart, 8 and 64 px in radius
    img = np.full((200, 600), 128, np.uint8)
    mask = np.zeros_like(img)
    centers = np.array([[100.0, 100.0], [500.0, 100.0]])
    radii = np.array([8.0, 64.0])
    mask[95:106, 95:106] = 1
    mask[95:106, 495:506] = 1

    # the crop is centred on a marker either way; the small one's half of the image is dark
    def small_count(bias):
        cfg = AugmentConfig(crop=64, marker_frac=1.0, shift_frac=0.0, scale_min=1.0, scale_max=1.0, rotate=False,
                            flip=False, blur_prob=0.0, noise_max=0.0, small_marker_bias=bias)
        rng = np.random.default_rng(1)
        img2 = img.copy()
        img2[:, :300] = 20
        n = 0
        for _ in range(400):
            x, lab = augment(img2, mask, centers, cfg, rng, radii)
            assert lab[31, 31] == 1
            n += x[5, 5] < 0.3
        return n

    n0, n1, n2 = small_count(0.0), small_count(1.0), small_count(2.0)
    # p(small) = 0.5, 8/9 and 64/65 for b = 0, 1, 2 (400 draws: 3-sigma bounds)
    assert 170 <= n0 <= 230
    assert 335 <= n1 <= 376
    assert n2 >= 385


def test_cli_train_resume_export_and_detect(tmp_path, capsys):
    from cpdetect.cli import main

    data = tmp_path / "data"
    assert main(["-q", "synth", "images", "--out", str(data), "--n", "4", "--seed", "3", "--size", "160x128",
                 "--empty-prob", "0"]) == 0
    out = tmp_path / "model"
    args = ["-q", "train", "--data", str(data), "--out", str(out), "--model", "test_micro", "--iters-per-epoch",
            "2", "--batch", "2", "--crop", "64", "--threads", "1", "--val-frac", "0.25"]
    assert main(args + ["--epochs", "1"]) == 0
    assert (out / "model.pt").exists() and (out / "checkpoint.pt").exists()
    assert main(args + ["--epochs", "2", "--resume"]) == 0
    assert torch.load(out / "checkpoint.pt", weights_only=False)["iteration"] == 4
    assert main(["-q", "export-onnx", str(out), str(out / "model.onnx")]) == 0
    from cpdetect import get_detector

    det = get_detector("hma", model_dir=str(out), backend="opencv")
    res = det.detect(np.full((64, 96), 100, np.uint8))
    assert res.probability.shape == (64, 96)
    capsys.readouterr()
    assert main(["train", "--data", str(tmp_path / "missing"), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "missing" in err[0]
    assert main(["train", "--data", str(data), "--out", str(out), "--crop", "100"]) == 2
    capsys.readouterr()
    assert main(["train", "--data", str(data), "--out", str(tmp_path / "w"), "--workers", "-1"]) == 2
    assert "--workers must be >= 0" in capsys.readouterr().err and not (tmp_path / "w").exists()
    assert main(["train", "--data", str(data), "--out", str(tmp_path / "w"), "--small-marker-bias", "-1"]) == 2
    assert "--small-marker-bias must be in [0, 4]" in capsys.readouterr().err and not (tmp_path / "w").exists()
    # bad starts name the problem and leave no folder behind
    capsys.readouterr()
    assert main(["train", "--data", str(data), "--out", str(tmp_path / "new"), "--init", str(tmp_path / "nope")]) == 2
    assert "nope" in capsys.readouterr().err and not (tmp_path / "new").exists()
    (tmp_path / "afile").write_text("x")
    assert main(["train", "--data", str(data), "--out", str(tmp_path / "afile")]) == 2
    assert "must be a folder" in capsys.readouterr().err


def test_a_device_torch_cannot_use_is_a_usage_error(monkeypatch):
    import torch

    from cpdetect.errors import UsageError
    from learned.devices import resolve_device

    assert resolve_device("cpu") == torch.device("cpu")
    with pytest.raises(UsageError, match="unknown device 'cuda:x'"):
        resolve_device("cuda:x")
    # no GPU: a CPU-only build and a CUDA build that sees none say which
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert resolve_device("auto") == torch.device("cpu")
    monkeypatch.setattr(torch.version, "cuda", None)
    with pytest.raises(UsageError, match="'cuda': this torch is built without CUDA"):
        resolve_device("cuda")
    monkeypatch.setattr(torch.version, "cuda", "13.0")
    with pytest.raises(UsageError, match="'cuda:0': no CUDA GPU is visible"):
        resolve_device("cuda:0")
    # one GPU: cuda and cuda:0 resolve, cuda:1 does not
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 1)
    assert resolve_device("auto") == torch.device("cuda")
    assert resolve_device("cuda:0") == torch.device("cuda", 0)
    with pytest.raises(UsageError, match="'cuda:1': this machine has 1 CUDA GPU"):
        resolve_device("cuda:1")


@pytest.mark.skipif(__import__("torch").cuda.is_available(), reason="needs a machine without CUDA")
def test_train_on_a_missing_gpu_stops_with_one_line_and_writes_nothing(tmp_path):
    import subprocess
    import sys

    cli = [sys.executable, "-m", "cpdetect.cli"]
    data, out = tmp_path / "data", tmp_path / "model"
    subprocess.run([*cli, "synth", "images", "--out", str(data), "--n", "2", "--seed", "3"], check=True,
                   capture_output=True, timeout=120)
    r = subprocess.run([*cli, "train", "--data", str(data), "--out", str(out), "--device", "cuda",
                        "--epochs", "1", "--iters-per-epoch", "1", "--batch", "2", "--crop", "64"],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2
    assert len(r.stderr.splitlines()) == 1 and "device 'cuda'" in r.stderr and "Traceback" not in r.stderr
    assert not out.exists()
