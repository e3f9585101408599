"""The narrow OCR head (``ocr_kernel``, ``aux_mid``) and the carrying over of trained weights to it
(learned/narrow.py)."""
from __future__ import annotations

import json

import pytest

torch = pytest.importorskip("torch")

from learned.hma import HMAConfig, build_model, preset, save_model  # noqa: E402
from learned.narrow import main as narrow_main  # noqa: E402
from learned.narrow import narrow_ocr_state  # noqa: E402

torch.set_num_threads(1)


def _trained_like(name: str = "test_micro", seed: int = 0, **changes):
    """A random model with random batch-norm statistics and affine parameters (as a trained one has)."""
    torch.manual_seed(seed)
    m = build_model(preset(name, **changes))
    with torch.no_grad():
        for mod in m.modules():
            if isinstance(mod, torch.nn.BatchNorm2d):
                mod.weight.uniform_(0.5, 1.5)
                mod.bias.uniform_(-0.3, 0.3)
                mod.running_mean.uniform_(-0.2, 0.2)
                mod.running_var.uniform_(0.5, 2.0)
    return m.eval()


def test_the_narrow_options_shape_the_ocr_head_and_round_trip_through_the_config():
    wide = build_model("test_micro")
    narrow = build_model(preset("test_micro", ocr_kernel=1, aux_mid=3))
    c_hl = wide.backbone.out_channels
    assert wide.ocr.conv3x3_ocr[0].kernel_size == (3, 3)
    assert tuple(wide.ocr.aux_head[0].weight.shape[:2]) == (c_hl, c_hl)  # the paper's: C_hl -> C_hl
    assert narrow.ocr.conv3x3_ocr[0].kernel_size == (1, 1)
    assert tuple(narrow.ocr.aux_head[0].weight.shape[:2]) == (3, c_hl)
    assert tuple(narrow.ocr.aux_head[3].weight.shape[:2]) == (2, 3)
    cfg = narrow.config
    assert HMAConfig.from_dict(json.loads(json.dumps(cfg.to_dict()))) == cfg
    # a config written before the options existed is the paper's head
    old = {k: v for k, v in wide.config.to_dict().items() if k not in ("ocr_kernel", "aux_mid")}
    assert HMAConfig.from_dict(old) == wide.config
    # the same spatial size out of both
    x = torch.rand(1, 1, 64, 96)
    with torch.no_grad():
        assert wide.eval()(x).shape == narrow.eval()(x).shape == (1, 2, 64, 96)


@pytest.mark.parametrize("bad", [dict(ocr_kernel=5), dict(ocr_kernel=0), dict(aux_mid=0), dict(aux_mid=2.5)])
def test_bad_narrow_options_are_refused(bad):
    with pytest.raises(ValueError):
        preset("test_micro", **bad)


def test_the_lite_preset_narrows_only_the_two_costly_layers():
    from learned.narrow import narrow_config

    tiny, lite = preset("w16_tiny"), preset("w16_lite")
    differ = {k for k, v in tiny.to_dict().items() if lite.to_dict()[k] != v}
    assert differ == {"ocr_kernel", "aux_mid", "name"}
    assert (lite.ocr_kernel, lite.aux_mid) == (1, 64)
    # narrowing the shipped shape gives the preset, by name too
    assert narrow_config(preset("w16_tiny", num_classes=2), 1, 64) == preset("w16_lite", num_classes=2)


def test_the_summed_kernel_equals_the_3x3_reduction_on_locally_constant_features():
    src = _trained_like()
    dst_cfg = src.config.replace(ocr_kernel=1)
    dst = build_model(dst_cfg).eval()
    dst.load_state_dict(narrow_ocr_state(src.state_dict(), src.config, dst_cfg), strict=True)
    c_hl = src.backbone.out_channels
    feats = torch.randn(1, c_hl, 1, 1).expand(1, c_hl, 9, 11).contiguous()  # constant over space
    with torch.no_grad():
        a = src.ocr.conv3x3_ocr(feats)
        b = dst.ocr.conv3x3_ocr(feats)
    # away from the zero padding the two agree to rounding; at the border they must not (the 3x3
    # kernel sees the padding there), which shows the comparison is not vacuous
    assert torch.allclose(a[..., 1:-1, 1:-1], b[..., 1:-1, 1:-1], atol=1e-5)
    assert not torch.allclose(a[..., 0, :], b[..., 0, :], atol=1e-3)
    # with the full auxiliary width the aux head is carried over unchanged
    with torch.no_grad():
        assert torch.equal(src.ocr.aux_head(feats), dst.ocr.aux_head(feats))


def test_the_narrow_aux_head_keeps_the_units_that_weigh_most():
    src = _trained_like()
    state = src.state_dict()
    hidden = state["ocr.aux_head.0.weight"].shape[0]
    assert hidden >= 6
    strong = [1, hidden - 2]
    w_out = state["ocr.aux_head.3.weight"]
    w_out.mul_(0.01)
    w_out[:, strong] = 5.0  # these two units make the output
    dst_cfg = src.config.replace(aux_mid=2)
    narrowed = narrow_ocr_state(state, src.config, dst_cfg)
    dst = build_model(dst_cfg).eval()
    dst.load_state_dict(narrowed, strict=True)
    assert torch.equal(narrowed["ocr.aux_head.0.weight"], state["ocr.aux_head.0.weight"][strong])
    assert torch.equal(narrowed["ocr.aux_head.1.running_var"], state["ocr.aux_head.1.running_var"][strong])
    # so the narrow head's output is the wide one's less the weak units' small share
    src.load_state_dict(state)
    feats = torch.randn(2, src.backbone.out_channels, 5, 7)
    with torch.no_grad():
        wide_out, narrow_out = src.ocr.aux_head(feats), dst.ocr.aux_head(feats)
    assert (narrow_out - wide_out).abs().max() < 0.05 * wide_out.abs().max()
    # every tensor outside the two layers is the trained one
    same = [k for k in state if not k.startswith(("ocr.conv3x3_ocr.0.weight", "ocr.aux_head."))]
    assert all(torch.equal(narrowed[k], state[k]) for k in same)


def test_narrowing_refuses_other_changes_and_a_wider_head():
    src = _trained_like()
    with pytest.raises(ValueError, match="ocr_mid"):
        narrow_ocr_state(src.state_dict(), src.config, src.config.replace(ocr_kernel=1, ocr_mid=4))
    with pytest.raises(ValueError, match="wider"):
        narrow_ocr_state(src.state_dict(), src.config, src.config.replace(aux_mid=10_000))


def test_the_narrow_command_writes_a_model_folder(tmp_path, capsys):
    from learned.hma import load_model

    src = _trained_like()
    save_model(src, tmp_path / "m")
    out = tmp_path / "narrow"
    assert narrow_main([str(tmp_path / "m"), str(out), "--aux-mid", "3"]) == 0
    m = load_model(out)
    assert (m.config.ocr_kernel, m.config.aux_mid, m.config.name) == (1, 3, "test_micro_narrow")
    assert torch.equal(m.state_dict()["backbone.stem.0.weight"], src.state_dict()["backbone.stem.0.weight"])
    # bad input: one line naming the file, exit 2, nothing written
    assert narrow_main([str(tmp_path / "nothing"), str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "nothing" in err[0]
    assert narrow_main([str(tmp_path / "m"), str(tmp_path / "y"), "--aux-mid", "100000"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "wider" in err[0]
    (tmp_path / "file").write_text("x")
    assert narrow_main([str(tmp_path / "m"), str(tmp_path / "file" / "z"), "--aux-mid", "3"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "is a file" in err[0]
    assert not (tmp_path / "x").exists() and not (tmp_path / "y").exists()


def test_distillation_loss_is_flat_where_the_student_matches_the_teacher():
    from learned.train import distillation_loss

    teacher = _trained_like(seed=1)
    student = _trained_like(seed=1)
    other = _trained_like(seed=2)
    x = torch.rand(2, 1, 64, 64)
    with torch.no_grad():
        taught = teacher.two_scale_forward(x)
    same = distillation_loss(student.two_scale_forward(x), taught, 0.4)
    same.backward()
    grads = [p.grad.abs().max() for p in student.parameters() if p.grad is not None]
    assert grads and max(grads) < 1e-6  # soft cross-entropy: d/dlogits = p_student - p_teacher = 0
    # another network pays more than the teacher's own entropy, and is pulled towards it
    apart = distillation_loss(other.two_scale_forward(x), taught, 0.4)
    assert apart.item() > same.item() + 1e-3
    apart.backward()
    assert max(p.grad.abs().max() for p in other.parameters() if p.grad is not None) > 1e-4


def test_a_distilled_run_logs_its_term_and_a_missing_teacher_is_refused_before_anything_is_written(tmp_path):
    from dataclasses import replace

    from cpdetect.errors import InputError
    from learned.train import train
    from test_learned_model import _cfg, _tiny_samples

    teacher = save_model(_trained_like(), tmp_path / "teacher")
    assert narrow_main([str(teacher), str(tmp_path / "narrow"), "--aux-mid", "3"]) == 0
    s = _tiny_samples()
    cfg = _cfg(tmp_path / "kd", epochs=1, model="from-init", init=str(tmp_path / "narrow"), freeze_backbone=True,
               distill=str(teacher), distill_weight=2.0)
    train(cfg, samples=s[:2], val_samples=s[2:], progress=False)
    logged = [json.loads(line) for line in (tmp_path / "kd" / "train_log.jsonl").read_text().splitlines()]
    terms = [r["last_distill"] for r in logged if "last_distill" in r]
    assert terms and all(t > 0 for t in terms)
    with pytest.raises(InputError, match="checkpoint not found"):
        train(replace(cfg, out=str(tmp_path / "kd2"), distill=str(tmp_path / "none")), samples=s[:2],
              val_samples=s[2:], progress=False)
    assert not (tmp_path / "kd2").exists()
