"""Training loop for the HMA marker segmenter: two-scale training, RMI loss, SGD or AdamW with poly decay.

Output folder layout (``out``)::

    config.json, model.pt   the best model so far (by validation IoU; the latest when there is no
                            validation), loadable with :func:`learned.hma.load_model`
    checkpoint.pt           the latest training state (model, optimiser, iteration, RNG, best) for resume
    train_log.jsonl         one JSON line per logged interval and per validation
    train_args.json         the arguments of the run

Randomness: crops are drawn from generator seeds (seed, epoch, index) and torch is seeded from
``seed``, so two runs with the same arguments (and thread count) give the same weights. ``resume``
continues from ``checkpoint.pt`` at the saved iteration.
"""
from __future__ import annotations

import contextlib
import json
import logging
import math
import os
import signal
import sys
import threading
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable, Sequence

import numpy as np
import torch

from .data import AugmentConfig, CropDataset, Sample, samples_from_dataset, split_samples
from .devices import resolve_device
from .hma import (HMAModel, build_model, load_matching, load_torch_file, marker_probability, preset, read_config,
                  save_model)
from .rmi import HMALossWeights, RMIStats, hma_loss

log = logging.getLogger(__name__)

CHECKPOINT = "checkpoint.pt"
LOG_FILE = "train_log.jsonl"


@dataclass(frozen=True)
class TrainConfig:
    """Arguments of a training run (all saved to ``train_args.json``).

    epochs x iters_per_epoch iterations of ``batch`` crops of ``crop`` pixels. optimizer: "sgd"
    (upstream HMA: momentum, weight decay) or "adamw" (converges in far fewer iterations, which is what
    a CPU budget allows). lr: base rate (None = 0.01 for SGD, 0.001 for AdamW), decayed per iteration
    as (1 - it / total) ** poly. rmi_scope: covariances of the RMI term over the batch or per image
    (:class:`learned.rmi.HMALossWeights`). val_frac: fraction of the images held out
    (ignored when ``val_data`` is given); val_crops: fixed validation crops. checkpoint_minutes: time
    between checkpoints inside an epoch. distill: a trained model folder (or checkpoint) whose
    two-scale outputs the network also learns to reproduce (knowledge distillation: cross-entropy of
    the fused and the auxiliary predictions against the teacher's probabilities, weighed 1 and 0.4 like
    the label terms, all times ``distill_weight``), as when a narrower network
    (:mod:`learned.narrow`) takes over from a wider one. workers: processes that draw the crops (0 = the training
    process itself); the batches, and so the weights, are the same for any number. channels_last:
    train in the channels-last memory format where that is safe, i.e. on the CPU only
    (:func:`use_channels_last`).
    """

    data: str
    out: str
    val_data: str | None = None
    model: str = "w16_tiny"
    init: str | None = None
    freeze_backbone: bool = False
    distill: str | None = None
    distill_weight: float = 1.0
    epochs: int = 30
    iters_per_epoch: int = 200
    batch: int = 8
    crop: int = 256
    optimizer: str = "sgd"
    rmi_scope: str = "batch"
    lr: float | None = None
    momentum: float = 0.9
    weight_decay: float = 1e-4
    poly: float = 1.0
    val_frac: float = 0.05
    val_crops: int = 64
    val_scales: tuple[float, ...] = (0.5, 1.0)
    seed: int = 0
    device: str = "auto"
    threads: int = 2
    workers: int = 0
    checkpoint_minutes: float = 5.0
    log_every: int = 20
    channels_last: bool = True
    augment: AugmentConfig = field(default_factory=AugmentConfig)


@dataclass
class TrainResult:
    out: Path
    iterations: int
    best_iou: float | None
    last_val: dict | None
    seconds: float
    interrupted: bool = False  # stopped by SIGINT/SIGTERM; the checkpoint holds ``iterations``


OPTIMIZERS = ("sgd", "adamw")


def base_learning_rate(cfg: TrainConfig) -> float:
    if cfg.lr is not None:
        return float(cfg.lr)
    return 0.01 if cfg.optimizer == "sgd" else 1e-3


def make_optimizer(params: list[torch.nn.Parameter], cfg: TrainConfig) -> torch.optim.Optimizer:
    """SGD with momentum (upstream) or AdamW; weight decay cfg.weight_decay in both."""
    lr = base_learning_rate(cfg)
    if cfg.optimizer == "sgd":
        return torch.optim.SGD(params, lr=lr, momentum=cfg.momentum, weight_decay=cfg.weight_decay)
    if cfg.optimizer == "adamw":
        return torch.optim.AdamW(params, lr=lr, weight_decay=cfg.weight_decay)
    raise ValueError(f"unknown optimizer {cfg.optimizer!r}; valid: {', '.join(OPTIMIZERS)}")


def use_channels_last(cfg: TrainConfig, device: torch.device) -> bool:
    """Whether to train in the channels-last memory format: only on the CPU, where it is faster.

    On CUDA (an H100, torch 2.11+cu130, 2026-11-26; bench/train_step_parity.py: a fixed batch of 32
    crops, the shipped network, dropout and TF32 off) one step's gradient in channels-last was 19 % off
    the CPU's (cosine 0.989, the classifier's bias gradient 89 % off), and 15 steps on one batch went
    from loss 2.28 to 1.67 instead of 1.27; in the default format the gradient was within 2.3e-4 of the
    CPU's and the 15 steps agreed within 2e-3. The likely reason the GPU fine-tuning of stop 27 lost.
    """
    return bool(cfg.channels_last) and device.type == "cpu"


def read_state(path: str | os.PathLike) -> tuple[dict[str, torch.Tensor], dict | None]:
    """State dict (and config dict when known) from a model folder, a checkpoint.pt or a bare state dict."""
    from cpdetect.errors import InputError

    p = Path(path)
    if p.is_dir():
        cfg = read_config(p).to_dict()
        p = p / "model.pt"
    else:
        cfg = None
    if not p.exists():
        raise InputError("checkpoint not found", p)
    obj = load_torch_file(p, "checkpoint")
    if isinstance(obj, dict) and "model" in obj and isinstance(obj["model"], dict):
        cfg = obj.get("config", cfg)
        obj = obj["model"]
    if not isinstance(obj, dict) or not all(isinstance(v, torch.Tensor) for v in obj.values()):
        raise InputError("not a state dict or cpdetect checkpoint", p)
    return obj, cfg


_CHECKPOINT_KEYS = ("model", "optimizer", "iteration", "config", "torch_rng")


def _read_checkpoint(path: Path) -> dict:
    """A training checkpoint of :func:`_save_checkpoint` for ``--resume``; InputError naming the file
    when it is damaged or is something else."""
    from cpdetect.errors import InputError

    obj = load_torch_file(path, "checkpoint")
    if not isinstance(obj, dict) or any(k not in obj for k in _CHECKPOINT_KEYS):
        raise InputError("not a cpdetect training checkpoint (it lacks "
                         + ", ".join(k for k in _CHECKPOINT_KEYS if not isinstance(obj, dict) or k not in obj)
                         + ")", path)
    return obj


def init_from(model: HMAModel, path: str | os.PathLike) -> tuple[list[str], list[str]]:
    """Transfer learning: load every layer of ``path`` whose name and shape match; log the rest."""
    state, _ = read_state(path)
    loaded, skipped = load_matching(model, state)
    log.info("init from %s: %d tensors loaded, %d re-initialised", path, len(loaded), len(skipped))
    if skipped:
        log.info("re-initialised (absent or other shape): %s", ", ".join(skipped))
    unused = sorted(set(state) - set(loaded))
    if unused:
        log.info("checkpoint tensors not used: %s", ", ".join(unused))
    return loaded, skipped


def load_teacher(path: str | os.PathLike, device: torch.device, channels_last: bool) -> HMAModel:
    """The network of a model folder or checkpoint (``--distill``), frozen, in eval mode."""
    from cpdetect.errors import InputError

    state, cfg = read_state(path)
    if cfg is None:
        raise InputError("--distill needs a model folder or checkpoint that carries its config", path)
    teacher = build_model(cfg)
    try:
        teacher.load_state_dict(state)
    except RuntimeError as exc:
        raise InputError(f"weights do not fit their config: {str(exc).splitlines()[0]}", path) from None
    teacher.to(device).eval()
    if channels_last:
        teacher = teacher.to(memory_format=torch.channels_last)
    for p in teacher.parameters():
        p.requires_grad_(False)
    return teacher


def distillation_loss(student: dict[str, torch.Tensor], teacher: dict[str, torch.Tensor],
                      aux_weight: float) -> torch.Tensor:
    """Cross-entropy of the student's fused and auxiliary logits (``two_scale_forward`` outputs,
    (N, K, H, W)) against the teacher's class probabilities, the auxiliary term times ``aux_weight``.
    Least (the teacher's own entropy, with a zero gradient) where the student gives the teacher's
    probabilities."""
    def soft_ce(logits: torch.Tensor, target_logits: torch.Tensor) -> torch.Tensor:
        return torch.nn.functional.cross_entropy(logits, torch.softmax(target_logits, dim=1))

    return soft_ce(student["pred"], teacher["pred"]) + aux_weight * soft_ce(student["aux"], teacher["aux"])


def set_bn_eval(module: torch.nn.Module) -> None:
    for m in module.modules():
        if isinstance(m, torch.nn.modules.batchnorm._BatchNorm):
            m.eval()


@torch.no_grad()
def evaluate(model: HMAModel, batches: Sequence[tuple[torch.Tensor, torch.Tensor]], scales: Sequence[float],
             device: torch.device, threshold: float = 0.5) -> dict:
    """Pixel IoU / precision / recall / F1 of the marker class accumulated over all batches."""
    was_training = model.training
    model.eval()
    tp = fp = fn = 0
    for x, y in batches:
        logits = model.nscale_forward(x.to(device), scales)
        p = marker_probability(logits)[:, 0].cpu()
        valid = y != 255
        pred = (p >= threshold) & valid
        gt = (y == 1) & valid
        tp += int((pred & gt).sum())
        fp += int((pred & ~gt).sum())
        fn += int((~pred & gt).sum())
    model.train(was_training)
    iou = tp / max(tp + fp + fn, 1)
    prec = tp / max(tp + fp, 1)
    rec = tp / max(tp + fn, 1)
    f1 = 2 * tp / max(2 * tp + fp + fn, 1)
    return {"iou": iou, "precision": prec, "recall": rec, "f1": f1, "tp": tp, "fp": fp, "fn": fn}


def _collate(items: list[tuple[torch.Tensor, torch.Tensor]]) -> tuple[torch.Tensor, torch.Tensor]:
    return torch.stack([a for a, _ in items]), torch.stack([b for _, b in items])


class _RunCrops:
    """The crops of a whole run as one sequence: item ``g`` is crop ``g % batch`` of iteration
    ``g // batch``, i.e. item ``(it % iters_per_epoch) * batch + g % batch`` of epoch
    ``it // iters_per_epoch``, exactly what the serial loop draws."""

    def __init__(self, crops: CropDataset, iters_per_epoch: int, batch: int):
        self.crops, self.iters_per_epoch, self.batch = crops, iters_per_epoch, batch

    def __getitem__(self, g: int):
        it, j = divmod(int(g), self.batch)
        epoch, b = divmod(it, self.iters_per_epoch)
        return self.crops.draw(epoch, b * self.batch + j)

    def collate(self, gs: list[int]):
        """The batch of items ``gs``; in a worker, a bad image comes back as a :class:`_CropError`
        (the loader would re-raise it wrapped in the worker's traceback, not as one line)."""
        from cpdetect.errors import CpdetectError

        try:
            return _collate([self[g] for g in gs])
        except CpdetectError as exc:
            return _CropError(type(exc).__name__, exc.message, exc.path, exc.line, exc.exit_code)


@dataclass(frozen=True)
class _CropError:
    """A :class:`cpdetect.errors.CpdetectError` raised in a crop worker, carried to the training process."""

    kind: str
    message: str
    path: str | None
    line: int | None
    exit_code: int

    def error(self) -> Exception:
        from cpdetect import errors

        cls = getattr(errors, self.kind, errors.CpdetectError)
        return cls(self.message, self.path, self.line, self.exit_code)


def _quiet_worker(_: int) -> None:
    # each worker draws whole crops; nested thread pools would only fight over the cores
    import cv2

    torch.set_num_threads(1)
    cv2.setNumThreads(1)


def batch_stream(crops: CropDataset, iters_per_epoch: int, batch: int, start: int, stop: int, workers: int = 0,
                 pin_memory: bool = False):
    """Batches (x, y) of iterations ``start`` .. ``stop - 1``, drawn in ``workers`` processes (0 = here).

    The same batches for any ``workers``: crop j of iteration it is item ``(it % iters_per_epoch) * batch + j``
    of epoch ``it // iters_per_epoch`` of ``crops``.
    """
    run = _RunCrops(crops, iters_per_epoch, batch)
    if workers <= 0:
        for it in range(start, stop):
            yield _collate([run[it * batch + j] for j in range(batch)])
        return
    loader = torch.utils.data.DataLoader(
        range(start * batch, stop * batch), batch_size=batch, shuffle=False, num_workers=workers,
        collate_fn=run.collate, worker_init_fn=_quiet_worker, pin_memory=pin_memory, prefetch_factor=4,
        # its own generator: the loader's worker seeds must not draw on torch's global one (dropout)
        generator=torch.Generator(),
        # fresh interpreters: a fork of a process whose OpenMP / OpenCV pools have run can deadlock
        multiprocessing_context="spawn")
    for batch in loader:
        if isinstance(batch, _CropError):
            raise batch.error()
        yield batch


def _append_log(path: Path, record: dict) -> None:
    with open(path, "a", encoding="utf-8") as fh:
        fh.write(json.dumps(record) + "\n")


def _save_checkpoint(path: Path, model: HMAModel, opt: torch.optim.Optimizer, it: int, best: float | None,
                     cfg: TrainConfig) -> None:
    from cpdetect.fileio import atomic_path

    state = {"model": model.state_dict(), "optimizer": opt.state_dict(), "iteration": it, "best_iou": best,
             "config": model.config.to_dict(), "torch_rng": torch.get_rng_state(),
             "train_config": _jsonable(cfg)}
    with atomic_path(path) as tmp:
        torch.save(state, tmp)


def _jsonable(cfg: TrainConfig) -> dict:
    d = asdict(cfg)
    d["augment"] = asdict(cfg.augment)
    return json.loads(json.dumps(d, default=list))


def train(cfg: TrainConfig, resume: bool = False, samples: list[Sample] | None = None,
          val_samples: list[Sample] | None = None, progress: bool = True,
          on_iteration: Callable[[int, dict], None] | None = None) -> TrainResult:
    """Train (or resume) a model into ``cfg.out``; ``samples`` overrides reading ``cfg.data``."""
    from cpdetect.errors import InputError, UsageError
    from cpdetect.fileio import cannot_write, write_json_atomic

    t_start = time.time()
    torch.set_num_threads(max(1, int(cfg.threads)))
    device = resolve_device(cfg.device)  # a device this torch cannot use is a UsageError
    out = Path(cfg.out)
    if out.exists() and not out.is_dir():
        raise UsageError(f"{out}: --out must be a folder, this is a file")
    ckpt_path = out / CHECKPOINT
    # batch normalisation in training needs two values per channel or more; the coarsest map of the
    # half-scale pass (stride 32) has ceil(crop / 64) pixels a side: 1 at a 64 px crop
    if cfg.batch * math.ceil(cfg.crop / 64) ** 2 < 2:
        raise UsageError(f"--batch {cfg.batch} with --crop {cfg.crop}: the half-scale pass's coarsest map is 1 pixel, "
                         "too few for batch normalisation; use --batch 2 or more, or --crop 96 or more")

    if samples is None:
        samples = samples_from_dataset(cfg.data)
        if not samples:
            raise UsageError(f"dataset {cfg.data} has no images with masks")
        if cfg.val_data:
            val_samples = samples_from_dataset(cfg.val_data)
        else:
            samples, val_samples = split_samples(samples, cfg.val_frac, cfg.seed)
    if not resume and ckpt_path.exists():
        # hours of CPU live in that checkpoint: never start over it silently
        raise UsageError(f"{out} already holds a training run ({CHECKPOINT}); continue it with --resume, "
                         f"or choose another --out")
    aug = cfg.augment if cfg.augment.crop == cfg.crop else AugmentConfig(**{**asdict(cfg.augment), "crop": cfg.crop})
    train_ds = CropDataset(samples, aug, cfg.iters_per_epoch * cfg.batch, cfg.seed)
    val_batches: list[tuple[torch.Tensor, torch.Tensor]] = []
    if val_samples:
        vds = CropDataset(val_samples, AugmentConfig(**{**asdict(aug), "blur_prob": 0.5}), cfg.val_crops,
                          cfg.seed + 7919)
        items = [vds[i] for i in range(len(vds))]
        val_batches = [_collate(items[i:i + cfg.batch]) for i in range(0, len(items), cfg.batch)]

    # model
    torch.manual_seed(cfg.seed)
    checkpoint = None
    if resume:
        if not ckpt_path.exists():
            raise UsageError(f"--resume: no {CHECKPOINT} in {out}")
        checkpoint = _read_checkpoint(ckpt_path)
        started = checkpoint.get("train_config")
        for name in ("optimizer", "freeze_backbone"):
            # the optimizer's saved state only loads into the same optimizer over the same parameters
            was = started.get(name) if isinstance(started, dict) else None
            if was is not None and was != getattr(cfg, name):
                flag = "--" + name.replace("_", "-")
                raise UsageError(f"--resume: the run in {out} was started with {flag} {was}, this one has "
                                 f"{getattr(cfg, name)}; resume with the same setting")
        try:
            model = build_model(checkpoint["config"])
        except (TypeError, ValueError, KeyError) as exc:
            raise InputError(f"checkpoint's model config is invalid: {exc}", ckpt_path) from None
    elif cfg.init and cfg.model == "from-init":
        _, init_cfg = read_state(cfg.init)
        if init_cfg is None:
            raise UsageError("--model from-init needs a model folder or checkpoint that carries its config")
        model = build_model({**init_cfg, "num_classes": 2})
    else:
        model = build_model(preset(cfg.model, num_classes=2))
    if cfg.init and not resume:
        init_from(model, cfg.init)
    model.to(device)
    channels_last = use_channels_last(cfg, device)
    if channels_last:
        model = model.to(memory_format=torch.channels_last)
    if cfg.freeze_backbone:
        for p in model.backbone.parameters():
            p.requires_grad_(False)
    teacher = load_teacher(cfg.distill, device, channels_last) if cfg.distill else None
    params = [p for p in model.parameters() if p.requires_grad]
    opt = make_optimizer(params, cfg)
    base_lr = base_learning_rate(cfg)
    it, best = 0, None
    if checkpoint is not None:
        try:
            model.load_state_dict(checkpoint["model"])
            opt.load_state_dict(checkpoint["optimizer"])
            it = int(checkpoint["iteration"])
            best = checkpoint.get("best_iou")
            torch.set_rng_state(checkpoint["torch_rng"])
        except (TypeError, ValueError, RuntimeError, KeyError) as exc:
            # e.g. a checkpoint of another --optimizer or of a frozen backbone resumed without it
            why = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
            raise InputError(f"checkpoint does not fit this run: {why}", ckpt_path) from None
        log.info("resumed from %s at iteration %d (best IoU %s)", ckpt_path, it, best)
    # the folder appears only once the inputs are good (a failed start leaves nothing behind)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise cannot_write(exc, out) from None
    write_json_atomic(out / "train_args.json", _jsonable(cfg))

    total = cfg.epochs * cfg.iters_per_epoch
    weights = HMALossWeights(rmi_scope=cfg.rmi_scope)
    stats = RMIStats()
    log_path = out / LOG_FILE
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=total, initial=it, desc="train", unit="it", file=sys.stderr,
                   mininterval=1.0 if sys.stderr.isatty() else 30.0, dynamic_ncols=True)
    model.train()
    if cfg.freeze_backbone:
        set_bn_eval(model.backbone)
    stop = _StopRequest()
    with stop.installed():
        last_ckpt = time.time()
        last_val = None
        run_loss: list[float] = []
        t_iter = time.time()
        batches = batch_stream(train_ds, cfg.iters_per_epoch, cfg.batch, it, total, cfg.workers,
                               pin_memory=device.type == "cuda")
        while it < total and stop.signum is None:
            epoch = it // cfg.iters_per_epoch
            x, y = next(batches)
            x, y = x.to(device, non_blocking=True), y.to(device, non_blocking=True)
            if channels_last:
                x = x.contiguous(memory_format=torch.channels_last)
            lr = base_lr * (1.0 - it / total) ** cfg.poly
            for g in opt.param_groups:
                g["lr"] = lr
            outd = model(x)
            loss, parts = hma_loss(outd, y, weights, stats)
            if teacher is not None:
                with torch.no_grad():
                    taught = teacher.two_scale_forward(x)
                kd = distillation_loss(outd, taught, weights.aux)
                loss = loss + cfg.distill_weight * kd
                parts["distill"] = float(kd.detach())
                parts["total"] = float(loss.detach())
            if not math.isfinite(parts["total"]):
                raise RuntimeError(f"loss is not finite at iteration {it}: {parts}")
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            it += 1
            run_loss.append(parts["total"])
            if bar is not None:
                bar.update(1)
                bar.set_postfix(loss=f"{parts['total']:.3f}", lr=f"{lr:.4g}", refresh=False)
            if on_iteration is not None:
                on_iteration(it, parts)
            if it % cfg.log_every == 0 or it == total:
                now = time.time()
                _append_log(log_path, {"iteration": it, "epoch": epoch, "lr": lr, "loss": float(np.mean(run_loss)),
                                       **{f"last_{k}": v for k, v in parts.items()},
                                       "cholesky_failures": stats.cholesky_failures,
                                       "s_per_it": (now - t_iter) / max(len(run_loss), 1), "time": now})
                run_loss, t_iter = [], now
            end_of_epoch = it % cfg.iters_per_epoch == 0 or it == total
            if end_of_epoch:
                if val_batches:
                    last_val = evaluate(model, val_batches, cfg.val_scales, device)
                    if cfg.freeze_backbone:
                        set_bn_eval(model.backbone)
                    _append_log(log_path, {"iteration": it, "epoch": epoch, "val": last_val, "time": time.time()})
                    log.info("iteration %d: validation IoU %.4f F1 %.4f", it, last_val["iou"], last_val["f1"])
                    if best is None or last_val["iou"] > best:
                        best = last_val["iou"]
                        save_model(model, out, extra={"iteration": it, "val": last_val})
                else:
                    save_model(model, out, extra={"iteration": it})
            if end_of_epoch or time.time() - last_ckpt > 60.0 * cfg.checkpoint_minutes:
                _save_checkpoint(ckpt_path, model, opt, it, best, cfg)
                last_ckpt = time.time()
        batches.close()  # ends the worker processes, if any
    if bar is not None:
        bar.close()
    if stop.signum is not None:
        _save_checkpoint(ckpt_path, model, opt, it, best, cfg)
        log.warning("stopped by signal %d at iteration %d; checkpoint written to %s (continue with --resume)",
                    stop.signum, it, ckpt_path)
        return TrainResult(out, it, best, last_val, time.time() - t_start, interrupted=True)
    if not (out / "model.pt").exists():
        save_model(model, out, extra={"iteration": it})
    return TrainResult(out, it, best, last_val, time.time() - t_start)


class _StopRequest:
    """SIGINT / SIGTERM during training ask the loop to stop after the current iteration, so that the
    checkpoint is written at that iteration instead of losing up to ``checkpoint_minutes`` of work (a
    killed job, a closed terminal, Ctrl-C); a second signal stops at once. Handlers are installed only
    in the main thread and restored afterwards."""

    def __init__(self) -> None:
        self.signum: int | None = None

    def _handle(self, signum, frame) -> None:
        if self.signum is not None:
            # asked twice: stop now, without the checkpoint (the periodic one stays)
            raise KeyboardInterrupt if signum == signal.SIGINT else SystemExit(128 + signum)
        self.signum = signum

    @contextlib.contextmanager
    def installed(self):
        if threading.current_thread() is not threading.main_thread():
            yield self
            return
        old = {sig: signal.signal(sig, self._handle) for sig in (signal.SIGINT, signal.SIGTERM)}
        try:
            yield self
        finally:
            for sig, handler in old.items():
                signal.signal(sig, handler)


__all__ = ["TrainConfig", "TrainResult", "train", "evaluate", "init_from", "read_state", "use_channels_last"]
