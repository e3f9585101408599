"""Hierarchical multi-scale attention (Tao et al., 2020) over HRNet-OCR: the model, its config and files.

One shared trunk ``_fwd`` (HRNet -> OCR -> semantic head + attention head) runs at several scales of
the same image; the attention predicted at the lower of two scales weights its logits against the
higher scale's (hma.md sections 1.4-1.5):

    fused = up(a_lo * p_lo) + (1 - up(a_lo)) * p_hi          (on logits)

Training always uses the two scales {0.5, 1.0}; inference takes any list of scales containing 1.0 and
fuses recursively from the highest scale down. Shapes: input (N, C, H, W) float32 with values in
[0, 1] (normalised inside the model); logits (N, K, H, W); attention (N, 1, H, W) in (0, 1).

Files: a model directory holds ``config.json`` (the constructor arguments, see :class:`HMAConfig`) and
``model.pt`` (the state dict). :func:`load_model` rebuilds the model from the directory alone.
"""
from __future__ import annotations

import json
import os
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Sequence

import torch
import torch.nn.functional as F
from torch import nn

from .digests import check_digest, record_digest
from .hrnet import HRNet, HRNetConfig, bn, resize_to
from .ocr import OCRHead

FORMAT = "cpdetect-hma"
FORMAT_VERSION = 1
WEIGHTS_FILE = "model.pt"
CONFIG_FILE = "config.json"


@dataclass(frozen=True)
class HMAConfig:
    """Everything needed to rebuild the network.

    num_classes: K output channels (2 = background, marker). backbone: HRNet widths and depths.
    ocr_mid / ocr_key: OCR channel widths. ocr_kernel: the kernel of the OCR head's reducing
    convolution (3, the paper's; 1 for a CPU budget). aux_mid: the OCR auxiliary head's hidden width
    (None = the backbone's output width, the paper's). head_bot: bottleneck of the semantic and attention heads.
    seg_head: "conv3" = 3x3-BN-ReLU, 3x3-BN-ReLU, 1x1 (the paper's semantic head, issue 6) or
    "linear" = one 1x1 conv (upstream MscaleOCR). mean / std: normalisation of the [0, 1] input.
    train_scales: the two scales of training (low, high). name: a label (the preset it came from).
    """

    num_classes: int = 2
    backbone: HRNetConfig = field(default_factory=HRNetConfig)
    ocr_mid: int = 128
    ocr_key: int = 64
    ocr_kernel: int = 3
    aux_mid: int | None = None
    head_bot: int = 64
    seg_head: str = "conv3"
    dropout: float = 0.05
    mean: float = 0.5
    std: float = 0.25
    train_scales: tuple[float, float] = (0.5, 1.0)
    name: str = "custom"

    def __post_init__(self) -> None:
        if self.num_classes < 1:
            raise ValueError("num_classes must be >= 1")
        if self.seg_head not in ("conv3", "linear"):
            raise ValueError(f"seg_head must be 'conv3' or 'linear', got {self.seg_head!r}")
        if self.ocr_kernel not in (1, 3):
            raise ValueError(f"ocr_kernel must be 1 or 3, got {self.ocr_kernel!r}")
        if self.aux_mid is not None and not (isinstance(self.aux_mid, int) and self.aux_mid >= 1):
            raise ValueError(f"aux_mid must be a positive integer (or None), got {self.aux_mid!r}")
        if not self.std > 0:
            raise ValueError("std must be positive")
        lo, hi = self.train_scales
        if not 0 < lo < hi:
            raise ValueError("train_scales must be (low, high) with 0 < low < high")

    def to_dict(self) -> dict:
        d = asdict(self)
        d["backbone"] = self.backbone.to_dict()
        d["train_scales"] = list(self.train_scales)
        return {"format": FORMAT, "version": FORMAT_VERSION, **d}

    @classmethod
    def from_dict(cls, d: dict) -> "HMAConfig":
        d = dict(d)
        fmt, version = d.pop("format", FORMAT), d.pop("version", FORMAT_VERSION)
        if fmt != FORMAT or int(version) > FORMAT_VERSION:
            raise ValueError(f"not a {FORMAT} v<={FORMAT_VERSION} config (format {fmt!r}, version {version})")
        bb = dict(d.pop("backbone", {}))
        for k in ("widths", "modules"):
            if k in bb:
                bb[k] = tuple(bb[k])
        if "train_scales" in d:
            d["train_scales"] = tuple(float(s) for s in d["train_scales"])
        known = set(cls.__dataclass_fields__)
        unknown = sorted(set(d) - known)
        if unknown:
            raise ValueError(f"unknown config keys {unknown}")
        return cls(backbone=HRNetConfig(**bb), **d)

    def replace(self, **changes) -> "HMAConfig":
        from dataclasses import replace

        return replace(self, **changes)


# stem 32, stage1 1x16 -> 64, 1 block per branch; OCR 64/32; heads 32
_W16_TINY = HMAConfig(backbone=HRNetConfig(stem_width=32, stage1_blocks=1, stage1_planes=16,
                                           widths=(16, 32, 64, 128), modules=(1, 1, 1), blocks=1),
                      ocr_mid=64, ocr_key=32, head_bot=32, name="w16_tiny")

PRESETS: dict[str, HMAConfig] = {
    # HRNet-W18-Small-v1 widths, one module per stage, 2 BasicBlocks; OCR 128/64; heads 64 (hma.md 4.2)
    "w18s1_lite": HMAConfig(backbone=HRNetConfig(stem_width=64, stage1_blocks=1, stage1_planes=32,
                                                 widths=(16, 32, 64, 128), modules=(1, 1, 1), blocks=2),
                            ocr_mid=128, ocr_key=64, head_bot=64, name="w18s1_lite"),
    "w16_tiny": _W16_TINY,
    # w16_tiny with the OCR head's two costliest layers narrowed for the CPU: a 1x1 reduction and
    # a 64-wide auxiliary head
    "w16_lite": _W16_TINY.replace(ocr_kernel=1, aux_mid=64, name="w16_lite"),
    # for contract tests: a few thousand parameters
    "test_micro": HMAConfig(backbone=HRNetConfig(stem_width=8, stage1_blocks=1, stage1_planes=4,
                                                 widths=(4, 8, 8, 8), modules=(1, 1, 1), blocks=1),
                            ocr_mid=8, ocr_key=4, head_bot=4, name="test_micro"),
}


def preset(name: str, **changes) -> HMAConfig:
    if name not in PRESETS:
        raise ValueError(f"unknown model preset {name!r}; valid: {', '.join(sorted(PRESETS))}")
    return PRESETS[name].replace(**changes) if changes else PRESETS[name]


def _head(cin: int, bot: int, cout: int, final_bias: bool) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(cin, bot, 3, padding=1, bias=False), bn(bot), nn.ReLU(),
                         nn.Conv2d(bot, bot, 3, padding=1, bias=False), bn(bot), nn.ReLU(),
                         nn.Conv2d(bot, cout, 1, bias=final_bias))


def resize_scale(x: torch.Tensor, s: float) -> torch.Tensor:
    """Image rescaling by factor ``s`` (bilinear, align_corners=False); identity for s == 1."""
    if s == 1.0:
        return x
    return F.interpolate(x, scale_factor=s, mode="bilinear", align_corners=False, recompute_scale_factor=True)


class HMAModel(nn.Module):
    """HRNet-OCR trunk with a semantic head and an attention head, fused by hierarchical attention.

    ``forward(x)`` in training mode returns the two-scale dict (see :meth:`two_scale_forward`); in
    eval mode it returns fused logits over ``self.scales`` (default (1.0,)).
    """

    def __init__(self, config: HMAConfig):
        super().__init__()
        self.config = config
        self.scales: tuple[float, ...] = (1.0,)
        self.backbone = HRNet(config.backbone)
        self.ocr = OCRHead(self.backbone.out_channels, config.num_classes, config.ocr_mid, config.ocr_key,
                           config.dropout, config.ocr_kernel, config.aux_mid)
        if config.seg_head == "conv3":
            self.cls_head = _head(config.ocr_mid, config.head_bot, config.num_classes, final_bias=True)
        else:
            self.cls_head = nn.Conv2d(config.ocr_mid, config.num_classes, 1, bias=True)
        self.attn_head = _head(config.ocr_mid, config.head_bot, 1, final_bias=False)
        self.register_buffer("_mean", torch.tensor(float(config.mean)), persistent=False)
        self.register_buffer("_std", torch.tensor(float(config.std)), persistent=False)
        init_weights(self)
        # output layers keep PyTorch's default (small) init, as upstream's decoders: Kaiming fan_out on
        # a 1- or K-channel 1x1 conv gives logits of std ~3-7 and a saturated attention at the start
        for conv in self.output_layers():
            conv.reset_parameters()

    def output_layers(self) -> list[nn.Conv2d]:
        """The final 1x1 convolutions of the semantic, auxiliary and attention heads."""
        return [self.cls_head if isinstance(self.cls_head, nn.Conv2d) else self.cls_head[-1],
                self.ocr.aux_head[-1], self.attn_head[-1]]

    # ------------------------------------------------------------------ trunk
    def _fwd(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """One scale: (cls logits, aux logits, attention) all at x's size."""
        feats = self.backbone((x - self._mean) / self._std)
        aux, ocr_feats = self.ocr(feats)
        cls = self.cls_head(ocr_feats)
        attn = torch.sigmoid(self.attn_head(ocr_feats))
        return resize_to(cls, x), resize_to(aux, x), resize_to(attn, x)

    # ------------------------------------------------------------------ training
    def two_scale_forward(self, x: torch.Tensor) -> dict[str, torch.Tensor]:
        """Training forward at (low, high) = config.train_scales relative to x (high is normally 1.0).

        Returns logits ``pred`` / ``aux`` (fused), ``pred_lo`` / ``pred_hi`` (single scales, at x's
        size) and ``attn`` (the low scale's attention, at the low scale's size).
        """
        lo, hi = self.config.train_scales
        x_hi = resize_scale(x, hi)
        p_lo, aux_lo, a = self._fwd(resize_scale(x, lo))
        p_hi, aux_hi, _ = self._fwd(x_hi)
        a_up = resize_to(a, p_hi)
        pred = resize_to(a * p_lo, p_hi) + (1 - a_up) * p_hi
        aux = resize_to(a * aux_lo, p_hi) + (1 - a_up) * aux_hi
        out = {"pred": pred, "aux": aux, "pred_lo": resize_to(p_lo, p_hi), "pred_hi": p_hi, "attn": a}
        if hi != 1.0:
            out = {k: (resize_to(v, x) if k != "attn" else v) for k, v in out.items()}
        return out

    # ------------------------------------------------------------------ inference
    def nscale_forward(self, x: torch.Tensor, scales: Sequence[float], with_aux: bool = False):
        """Recursive hierarchical fusion over ``scales`` (must contain 1.0); fused logits at x's size.

        From the highest scale down: the first prediction is taken as is; a scale s >= 1 combines
        a_s * p_s + (1 - a_s) * down(pred); a scale s < 1 combines up(a_s * p_s) + (1 - up(a_s)) * pred.
        """
        scales = sorted({float(s) for s in scales}, reverse=True)
        if 1.0 not in scales:
            raise ValueError(f"the scales {scales} must include 1.0 (the output resolution)")
        pred = aux = None
        for s in scales:
            p, ax, a = self._fwd(resize_scale(x, s))
            if pred is None:
                pred, aux = p, ax
            elif s >= 1.0:
                pred, aux = resize_to(pred, p), resize_to(aux, p)
                pred = a * p + (1 - a) * pred
                aux = a * ax + (1 - a) * aux
            else:
                a_up = resize_to(a, pred)
                pred = resize_to(a * p, pred) + (1 - a_up) * pred
                aux = resize_to(a * ax, aux) + (1 - a_up) * aux
        return (pred, aux) if with_aux else pred

    def forward(self, x: torch.Tensor, scales: Sequence[float] | None = None):
        if self.training and scales is None:
            return self.two_scale_forward(x)
        return self.nscale_forward(x, self.scales if scales is None else scales)


def marker_probability(logits: torch.Tensor) -> torch.Tensor:
    """P(marker) (N, 1, H, W) from logits (N, K, H, W): softmax channel 1 (K >= 2), sigmoid if K == 1."""
    if logits.shape[1] == 1:
        return torch.sigmoid(logits)
    return torch.softmax(logits, dim=1)[:, 1:2]


def init_weights(model: nn.Module) -> None:
    """Kaiming-normal convolutions (fan_out, ReLU), BN weight 1 / bias 0 (no pretrained backbone)."""
    for m in model.modules():
        if isinstance(m, nn.Conv2d):
            nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu")
            if m.bias is not None:
                nn.init.zeros_(m.bias)
        elif isinstance(m, (nn.BatchNorm2d, nn.BatchNorm1d)):
            nn.init.ones_(m.weight)
            nn.init.zeros_(m.bias)


def build_model(config: HMAConfig | dict | str) -> HMAModel:
    """A fresh (Kaiming-initialised) model from a config, a config dict or a preset name."""
    if isinstance(config, str):
        config = preset(config)
    elif isinstance(config, dict):
        config = HMAConfig.from_dict(config)
    return HMAModel(config)


def count_parameters(model: nn.Module) -> int:
    return int(sum(p.numel() for p in model.parameters()))


def save_model(model: HMAModel, directory: str | os.PathLike, extra: dict | None = None) -> Path:
    """Write ``config.json`` and ``model.pt`` (float32 state dict) into ``directory`` atomically."""
    from cpdetect.fileio import atomic_path, write_json_atomic

    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    cfg = model.config.to_dict()
    if extra:
        cfg["extra"] = extra
    state = {k: v.detach().cpu().contiguous() for k, v in model.state_dict().items()}
    with atomic_path(d / WEIGHTS_FILE) as tmp:
        torch.save(state, tmp)
    record_digest(d / WEIGHTS_FILE)
    write_json_atomic(d / CONFIG_FILE, cfg)
    return d


def read_config(directory: str | os.PathLike) -> HMAConfig:
    """The :class:`HMAConfig` stored in ``directory/config.json`` (InputError naming the file if bad)."""
    from cpdetect.errors import InputError
    from cpdetect.fileio import read_json

    path = Path(directory) / CONFIG_FILE
    d = read_json(path, "model config")
    if not isinstance(d, dict):
        raise InputError("model config must be a JSON object", path)
    d.pop("extra", None)
    try:
        return HMAConfig.from_dict(d)
    except (TypeError, ValueError) as exc:
        raise InputError(f"invalid model config: {exc}", path) from None


def _first_sentence(exc: BaseException) -> str:
    """The first sentence of an exception's message (torch appends paragraphs of advice), or its type."""
    text = str(exc).strip().splitlines()[0] if str(exc).strip() else ""
    return text.split(". ")[0].rstrip(".") or type(exc).__name__


def load_torch_file(path: str | os.PathLike, what: str, map_location: str | torch.device = "cpu"):
    """``torch.load`` of a file a user gave (weights, a checkpoint) with ``weights_only``: tensors and
    plain values only, never arbitrary pickled objects, which could run code on loading. Every
    failure is one :class:`cpdetect.errors.InputError` naming the file and, in words, what is wrong
    with it (torch's own message for a damaged file can be a bare number)."""
    import pickle

    from cpdetect.errors import InputError

    p = Path(path)
    try:
        with open(p, "rb") as fh:
            head = fh.read(4)
    except OSError as exc:
        raise InputError(f"cannot read {what}: {exc.strerror or exc}", p) from None
    if not head:
        raise InputError(f"cannot read {what}: empty file", p)
    # the format torch.save writes is a zip archive; the legacy one a pickle (protocol 2+: 0x80)
    zipped, legacy = head == b"PK\x03\x04", head[:1] == b"\x80"
    try:
        return torch.load(p, map_location=map_location, weights_only=True)
    except pickle.UnpicklingError as exc:
        # torch says "weights only" for any file its restricted unpickler stops on, a text file too
        if (zipped or legacy) and "weights only" in str(exc).lower():
            raise InputError(f"cannot read {what}: it holds Python objects besides tensors and plain values, "
                             "which cpdetect does not load (they could run code)", p) from None
        why = _first_sentence(exc)
    except Exception as exc:  # noqa: BLE001 - torch raises many kinds for a damaged file
        why = _first_sentence(exc)
    if zipped:
        raise InputError(f"cannot read {what}: damaged or truncated PyTorch file ({why})", p)
    if legacy:
        raise InputError(f"cannot read {what}: damaged or truncated PyTorch file (legacy format; {why})", p)
    raise InputError(f"cannot read {what}: not a PyTorch file", p)


def load_model(directory: str | os.PathLike, map_location: str | torch.device = "cpu") -> HMAModel:
    """Rebuild the model from ``directory`` (config.json + model.pt), in eval mode."""
    from cpdetect.errors import InputError

    d = Path(directory)
    if not d.is_dir():
        raise InputError("model directory not found", d)
    model = HMAModel(read_config(d))
    wpath = d / WEIGHTS_FILE
    if not wpath.exists():
        raise InputError("model weights not found", wpath)
    check_digest(wpath)
    state = load_torch_file(wpath, "model weights", map_location)
    if not isinstance(state, dict) or not all(isinstance(v, torch.Tensor) for v in state.values()):
        raise InputError("not a state dict (a dict of tensors, as save_model writes)", wpath)
    try:
        model.load_state_dict(state)
    except RuntimeError as exc:
        # torch's first line only names the model class; the next says which tensors differ
        lines = [ln.strip() for ln in str(exc).splitlines() if ln.strip()]
        detail = lines[1] if len(lines) > 1 else lines[0] if lines else ""
        if len(detail) > 160:
            detail = detail[:157] + "..."
        raise InputError(f"weights do not match config.json: {detail}", wpath) from None
    return model.eval()


def load_matching(model: nn.Module, state: dict[str, torch.Tensor]) -> tuple[list[str], list[str]]:
    """Copy every tensor of ``state`` whose name and shape match ``model`` (transfer learning).

    Returns (loaded names, names of the model left at their initialisation: missing in ``state`` or
    of another shape, e.g. a head with another number of classes).
    """
    own = model.state_dict()
    loaded, skipped = [], []
    for name, tensor in own.items():
        src = state.get(name)
        if src is not None and tuple(src.shape) == tuple(tensor.shape):
            with torch.no_grad():
                tensor.copy_(src)
            loaded.append(name)
        else:
            skipped.append(name)
    return loaded, skipped


def config_json(config: HMAConfig) -> str:
    return json.dumps(config.to_dict(), indent=1)


__all__ = ["HMAConfig", "HMAModel", "PRESETS", "preset", "build_model", "save_model", "load_model", "load_torch_file", "read_config",
           "load_matching", "marker_probability", "count_parameters", "init_weights"]
