"""``cpdetect train --data DIR --out MODELDIR``: train the learned (HMA) marker segmenter."""
from __future__ import annotations

import logging

from .args import seed_arg

log = logging.getLogger(__name__)


def register(sub) -> None:
    p = sub.add_parser("train", help="train the learned marker detector (HMA over HRNet-OCR, RMI loss)",
                       description="Train the 'hma' detector's network on a marker dataset (the layout "
                                   "'cpdetect synth images' writes, or your own annotated photos with "
                                   "masks). MODELDIR receives config.json + model.pt (best by validation "
                                   "IoU), checkpoint.pt (for --resume) and train_log.jsonl. CPU by "
                                   "default, CUDA when present. Ctrl-C or SIGTERM stops after the "
                                   "current iteration with a checkpoint at it (exit status 130).")
    p.add_argument("--data", required=True, help="training dataset folder (markers.json, images/, masks/)")
    p.add_argument("--out", required=True, help="model folder to write")
    p.add_argument("--val-data", help="validation dataset folder (default: hold out --val-frac of --data)")
    p.add_argument("--val-frac", type=float, default=0.05, help="share of --data held out (default 0.05)")
    p.add_argument("--model", default="w16_tiny",
                   help="architecture preset: w16_tiny, w16_lite (w16_tiny with a narrow OCR head, "
                        "see python -m learned.narrow), w18s1_lite, or from-init to take --init's config "
                        "(default w16_tiny)")
    p.add_argument("--init", help="checkpoint (model folder, checkpoint.pt or state dict) to start from; "
                                  "layers that match are loaded, the others re-initialised and listed")
    p.add_argument("--freeze-backbone", action="store_true", help="train only the OCR and the heads")
    p.add_argument("--distill", metavar="TEACHER",
                   help="a trained model folder (or checkpoint) whose outputs the network also learns to "
                        "reproduce (knowledge distillation), e.g. the wider network a --model w16_lite run "
                        "takes over from")
    p.add_argument("--distill-weight", type=float, default=1.0,
                   help="weight of the distillation terms against the label terms (default 1)")
    p.add_argument("--epochs", type=int, default=30, help="epochs (default 30)")
    p.add_argument("--iters-per-epoch", type=int, default=200, help="iterations per epoch (default 200)")
    p.add_argument("--batch", type=int, default=8, help="crops per iteration (default 8)")
    p.add_argument("--crop", type=int, default=256, help="crop side in pixels (default 256)")
    p.add_argument("--optimizer", choices=("sgd", "adamw"), default="sgd",
                   help="sgd (upstream HMA recipe) or adamw (fewer iterations to converge; default sgd)")
    p.add_argument("--rmi-scope", choices=("batch", "image"), default="batch",
                   help="RMI covariances over the whole batch (default; stable when markers are small) or "
                        "per image (upstream)")
    p.add_argument("--lr", type=float, default=None,
                   help="base learning rate, poly decay (default 0.01 for sgd, 0.001 for adamw)")
    p.add_argument("--small-marker-bias", type=float, default=0.0, metavar="B",
                   help="draw the crops' markers with probability ~ radius ** -B, to train more on small "
                        "markers (default 0: every marker alike)")
    p.add_argument("--seed", type=seed_arg, default=0, help="random seed (default 0)")
    p.add_argument("--device", default="auto", help="auto (CUDA when present), cpu, cuda, cuda:1 ...")
    p.add_argument("--threads", type=int, default=2, help="CPU threads (default 2)")
    p.add_argument("--workers", type=int, default=0,
                   help="processes that draw the augmented crops (default 0: the training process); "
                        "the same batches for any number, so the same weights")
    p.add_argument("--checkpoint-minutes", type=float, default=5.0, help="minutes between checkpoints")
    p.add_argument("--resume", action="store_true", help="continue from MODELDIR/checkpoint.pt")
    p.set_defaults(func=run)


def run(args) -> int:
    from ..errors import UsageError

    try:
        from learned.data import AugmentConfig
        from learned.train import TrainConfig, train
    except ModuleNotFoundError as exc:
        if exc.name == "torch":
            raise UsageError("'cpdetect train' needs PyTorch: pip install 'cpdetect[learned]'") from None
        raise
    for name in ("epochs", "iters_per_epoch", "batch", "crop", "threads"):
        if getattr(args, name) < 1:
            raise UsageError(f"--{name.replace('_', '-')} must be >= 1")
    if args.workers < 0:
        raise UsageError("--workers must be >= 0")
    if args.lr is not None and not args.lr > 0:
        raise UsageError("--lr must be positive")
    if not args.checkpoint_minutes >= 0:
        raise UsageError("--checkpoint-minutes must be >= 0 (0: at every iteration)")
    if not 0 <= args.val_frac < 1:
        raise UsageError("--val-frac must be in [0, 1)")
    if args.crop % 32:
        raise UsageError("--crop must be a multiple of 32")
    if not 0 <= args.small_marker_bias <= 4:
        raise UsageError("--small-marker-bias must be in [0, 4]")
    if not args.distill_weight > 0:
        raise UsageError("--distill-weight must be positive")
    if args.model == "from-init" and not args.init:
        raise UsageError("--model from-init needs --init")
    cfg = TrainConfig(data=args.data, out=args.out, val_data=args.val_data, model=args.model, init=args.init,
                      freeze_backbone=args.freeze_backbone, distill=args.distill,
                      distill_weight=args.distill_weight, epochs=args.epochs,
                      iters_per_epoch=args.iters_per_epoch, batch=args.batch, crop=args.crop, optimizer=args.optimizer, rmi_scope=args.rmi_scope, lr=args.lr,
                      val_frac=args.val_frac, seed=args.seed, device=args.device, threads=args.threads,
                      workers=args.workers, checkpoint_minutes=args.checkpoint_minutes,
                      augment=AugmentConfig(small_marker_bias=args.small_marker_bias))
    try:
        res = train(cfg, resume=args.resume)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    best = "n/a" if res.best_iou is None else f"{res.best_iou:.4f}"
    if res.interrupted:
        log.error("interrupted at iteration %d (best validation IoU %s); continue with the same command and "
                  "--resume", res.iterations, best)
        return 130
    log.info("trained %d iterations in %.0f s; best validation IoU %s; model in %s", res.iterations,
             res.seconds, best, res.out)
    return 0
