"""A trained network's weights carried over to a narrower OCR head, as the start of a fine-tuning.

The OCR head's reducing convolution and its auxiliary head's hidden layer are most of a small
network's cost at 1/4 resolution (bench/hma_bench.py, ``network_layers``). A network with a 1x1
reduction (``ocr_kernel`` 1) and a narrower auxiliary head (``aux_mid``) starts better from the
trained one's weights than from random ones:

- the 1x1 reduction gets the sum of the 3x3 kernel's taps, which is what the 3x3 convolution does
  where the features are locally constant;
- the auxiliary head keeps the ``aux_mid`` hidden units that weigh most in its output (the norm of
  their output weights times their batch-norm scale and shift), with their weights.

Every other tensor is copied as it is. The result is a model folder (config.json, model.pt), which
``cpdetect train --init OUTDIR --model from-init [--distill MODELDIR]`` then fine-tunes
(learned/weights/default/TRAINING.md).

    python -m learned.narrow MODELDIR OUTDIR [--aux-mid 64] [--ocr-kernel 1]
"""
from __future__ import annotations

import argparse
import sys

import torch

from .hma import HMAConfig


def narrow_ocr_state(state: dict[str, torch.Tensor], src: HMAConfig, dst: HMAConfig) -> dict[str, torch.Tensor]:
    """``state`` (a network of config ``src``) with its OCR reduction and auxiliary head made to fit
    ``dst``, which may differ from ``src`` in ``ocr_kernel`` and ``aux_mid`` only."""
    if src.replace(ocr_kernel=dst.ocr_kernel, aux_mid=dst.aux_mid, name=dst.name) != dst:
        a, b = src.to_dict(), dst.to_dict()
        diff = sorted(k for k in a if k not in ("ocr_kernel", "aux_mid", "name") and a[k] != b.get(k))
        raise ValueError(f"the configs differ beyond ocr_kernel and aux_mid: {', '.join(diff)}")
    out = dict(state)
    key = "ocr.conv3x3_ocr.0.weight"
    w = state[key]
    if w.shape[-1] != dst.ocr_kernel:
        if dst.ocr_kernel != 1:
            raise ValueError(f"can only narrow the reduction to 1x1, not {w.shape[-1]} -> {dst.ocr_kernel}")
        out[key] = w.sum(dim=(2, 3), keepdim=True)
    hidden = state["ocr.aux_head.0.weight"].shape[0]
    want = hidden if dst.aux_mid is None else dst.aux_mid
    if want > hidden:
        raise ValueError(f"aux_mid {want} is wider than the trained head's {hidden}")
    if want < hidden:
        gamma, beta = state["ocr.aux_head.1.weight"], state["ocr.aux_head.1.bias"]
        var = state["ocr.aux_head.1.running_var"]
        w_out = state["ocr.aux_head.3.weight"].flatten(1)  # (K, hidden)
        weight = w_out.norm(dim=0) * (gamma.abs() / torch.sqrt(var + 1e-5) + beta.clamp(min=0))
        keep = torch.sort(torch.argsort(weight, descending=True)[:want]).values
        out["ocr.aux_head.0.weight"] = state["ocr.aux_head.0.weight"][keep]
        for name in ("weight", "bias", "running_mean", "running_var"):
            out[f"ocr.aux_head.1.{name}"] = state[f"ocr.aux_head.1.{name}"][keep]
        out["ocr.aux_head.3.weight"] = state["ocr.aux_head.3.weight"][:, keep]
    return out


def narrow_config(src: HMAConfig, ocr_kernel: int, aux_mid: int | None) -> HMAConfig:
    """``src`` with the given OCR head, named after the preset it then equals (w16_tiny -> w16_lite),
    else ``<name>_narrow``."""
    from .hma import PRESETS

    dst = src.replace(ocr_kernel=ocr_kernel, aux_mid=aux_mid)
    for name, p in PRESETS.items():
        if p.replace(name=dst.name, num_classes=dst.num_classes) == dst:
            return dst.replace(name=name)
    return dst.replace(name=f"{src.name}_narrow")


def main(argv: list[str] | None = None) -> int:
    from cpdetect.errors import CpdetectError
    from cpdetect.fileio import cannot_write

    from .hma import build_model, read_config, save_model
    from .train import read_state

    ap = argparse.ArgumentParser(prog="python -m learned.narrow", description=__doc__.split("\n\n")[0])
    ap.add_argument("model_dir", help="trained model folder (config.json, model.pt)")
    ap.add_argument("out", help="model folder to write (config.json, model.pt), for cpdetect train --init")
    ap.add_argument("--ocr-kernel", type=int, default=1, choices=(1, 3))
    ap.add_argument("--aux-mid", type=int, default=64)
    a = ap.parse_args(argv)
    try:
        src = read_config(a.model_dir)
        state, _ = read_state(a.model_dir)
        dst = narrow_config(src, a.ocr_kernel, a.aux_mid)
        model = build_model(dst)
        model.load_state_dict(narrow_ocr_state(state, src, dst))
        save_model(model, a.out)
    except CpdetectError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except (ValueError, KeyError, RuntimeError) as exc:  # a state that does not fit its own config
        print(f"error: {a.model_dir}: {str(exc).splitlines()[0]}", file=sys.stderr)
        return 2
    except OSError as exc:
        print(f"error: {cannot_write(exc, a.out)}", file=sys.stderr)
        return 2
    print(f"wrote {a.out}: ocr_kernel {dst.ocr_kernel}, aux_mid {dst.aux_mid}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
