"""One training step of the ``hma`` network on every device and memory format, against the CPU's.

Why: a fine-tuning on a lent H100 (stop 27) got worse where the same run on the CPU did not. This
draws one fixed batch of augmented crops (``--data``, ``--batch``, ``--seed``), takes the network
of ``--model-dir`` with dropout off (batch norm in training mode, TF32 off), and computes the loss,
the gradient and one AdamW update on the CPU in the default (NCHW) format as the reference, then
on the CPU in channels-last and on CUDA (when present) in both formats. Then ``--steps`` AdamW
steps on that one batch on each device and format: the loss curves show whether a gradient error
matters. Figures go to bench/results/train_step_parity.json (or ``--out``).

Seen 2026-11-26 on an H100 (torch 2.11+cu130), 32 crops of train-split images: CUDA channels-last
gradient 19 % off (cosine 0.989) and 15 steps ending at loss 1.67 against 1.27; CUDA NCHW within
2.3e-4, CPU channels-last within 6.6e-4 (float reordering). So ``cpdetect train`` uses channels-last
on the CPU only (learned.train.use_channels_last).

    .venv/bin/python bench/train_step_parity.py --data DIR [--model-dir learned/weights/default]
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

RESULTS = Path(__file__).parent / "results" / "train_step_parity.json"


def _variants(torch) -> list[tuple[str, bool]]:
    out = [("cpu", False), ("cpu", True)]
    if torch.cuda.is_available():
        out += [("cuda", False), ("cuda", True)]
    return out


def _model(torch, model_dir: str, device: str, channels_last: bool):
    from learned.hma import load_model

    m = load_model(model_dir)
    for mod in m.modules():
        if isinstance(mod, (torch.nn.Dropout, torch.nn.Dropout2d)):
            mod.p = 0.0
    m.to(device)
    if channels_last:
        m = m.to(memory_format=torch.channels_last)
    m.train()
    return m


def _optimizer(torch, model):
    from learned.train import TrainConfig, make_optimizer

    return make_optimizer(list(model.parameters()), TrainConfig(data="", out="", optimizer="adamw", lr=4e-4))


def _inputs(torch, x, y, device: str, channels_last: bool):
    xd, yd = x.to(device), y.to(device)
    if channels_last:
        xd = xd.contiguous(memory_format=torch.channels_last)
    return xd, yd


def one_step(torch, model_dir: str, device: str, channels_last: bool, x, y) -> dict:
    """Loss parts, gradients and one AdamW update (float32, on the CPU) of one step."""
    from learned.rmi import HMALossWeights, hma_loss

    m = _model(torch, model_dir, device, channels_last)
    xd, yd = _inputs(torch, x, y, device, channels_last)
    loss, parts = hma_loss(m(xd), yd, HMALossWeights(rmi_scope="batch"))
    loss.backward()
    grads = {k: p.grad.detach().float().cpu().clone() for k, p in m.named_parameters()}
    before = {k: p.detach().float().cpu().clone() for k, p in m.named_parameters()}
    _optimizer(torch, m).step()
    update = {k: p.detach().float().cpu() - before[k] for k, p in m.named_parameters()}
    return {"parts": parts, "grads": grads, "update": update}


def curve(torch, model_dir: str, device: str, channels_last: bool, x, y, steps: int) -> list[float]:
    """The loss at each of ``steps`` AdamW steps on the one batch."""
    from learned.rmi import HMALossWeights, hma_loss

    m = _model(torch, model_dir, device, channels_last)
    opt = _optimizer(torch, m)
    xd, yd = _inputs(torch, x, y, device, channels_last)
    losses = []
    for _ in range(steps):
        loss, parts = hma_loss(m(xd), yd, HMALossWeights(rmi_scope="batch"))
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        losses.append(round(parts["total"], 5))
    return losses


def compare(torch, got: dict, ref: dict) -> dict:
    """Relative differences of the whole gradient and update, their cosine, and the worst tensors."""
    names = sorted(ref["grads"])

    def flat(d):
        return torch.cat([d[k].flatten() for k in names]).double()

    g, gr = flat(got["grads"]), flat(ref["grads"])
    u, ur = flat(got["update"]), flat(ref["update"])
    scale = float(gr.norm()) / len(names) ** 0.5
    # tensors whose reference gradient is noise (a conv bias before batch norm) are not ranked
    per = sorted(((float((got["grads"][k] - ref["grads"][k]).norm() / ref["grads"][k].norm()), k)
                  for k in names if float(ref["grads"][k].norm()) > 1e-3 * scale), reverse=True)
    return {"loss": got["parts"]["total"], "ref_loss": ref["parts"]["total"],
            "grad_rel": float((g - gr).norm() / gr.norm()), "grad_cos": float(g @ gr / (g.norm() * gr.norm())),
            "grad_norm": float(g.norm()), "ref_grad_norm": float(gr.norm()),
            "update_rel": float((u - ur).norm() / ur.norm()), "worst_tensors": per[:6]}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", required=True, help="dataset folder (images/, masks/, markers.json)")
    ap.add_argument("--model-dir", default=None, help="model folder (default: the shipped weights)")
    ap.add_argument("--batch", type=int, default=32)
    ap.add_argument("--seed", type=int, default=8)
    ap.add_argument("--steps", type=int, default=15)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--out", default=str(RESULTS))
    args = ap.parse_args(argv)

    import torch

    from cpdetect.errors import CpdetectError
    from learned.adapter import default_model_dir
    from learned.data import AugmentConfig, CropDataset, samples_from_dataset
    from learned.hma import load_model
    from learned.train import _collate

    torch.backends.cudnn.allow_tf32 = False
    torch.backends.cuda.matmul.allow_tf32 = False
    torch.set_num_threads(args.threads)
    model_dir = args.model_dir or str(default_model_dir())
    try:
        samples = samples_from_dataset(args.data)
        load_model(model_dir)
    except CpdetectError as exc:
        print(f"train_step_parity: {exc}", file=sys.stderr)
        return 2
    if not samples:
        print(f"train_step_parity: {args.data}: no images with masks", file=sys.stderr)
        return 2
    crops = CropDataset(samples, AugmentConfig(), args.batch, args.seed)
    x, y = _collate([crops[i] for i in range(args.batch)])  # the batch as training stacks it

    ref = one_step(torch, model_dir, "cpu", False, x, y)
    rows = []
    for device, cl in _variants(torch):
        t0 = time.perf_counter()
        row = {"device": device, "channels_last": cl,
               **compare(torch, one_step(torch, model_dir, device, cl, x, y), ref)}
        row["curve"] = curve(torch, model_dir, device, cl, x, y, args.steps)
        row["seconds"] = round(time.perf_counter() - t0, 2)
        rows.append(row)
        print(f"{device:4s} channels_last={cl!s:5s} grad rel {row['grad_rel']:.2e} cos {row['grad_cos']:.6f} "
              f"update rel {row['update_rel']:.2e}; loss after {args.steps} steps {row['curve'][-1]:.4f}",
              flush=True)
    from cpdetect.fileio import write_json_atomic

    write_json_atomic(Path(args.out), {
        "torch": str(torch.__version__), "cuda_device": torch.cuda.get_device_name() if torch.cuda.is_available() else None,
        "data": str(args.data), "model_dir": model_dir, "batch": args.batch, "seed": args.seed,
        "steps": args.steps, "reference": "cpu, NCHW", "rows": rows})
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
