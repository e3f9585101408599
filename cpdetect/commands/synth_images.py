"""``cpdetect synth images --out DIR --n N --seed S``: synthetic marker images with exact truth."""
from __future__ import annotations

import logging
import time

from .args import seed_arg

log = logging.getLogger(__name__)


def register(kinds) -> None:
    p = kinds.add_parser("images", help="markers rendered onto real photographs, with masks and truth",
                         description="Render markers of all three types onto real photographs "
                                     "(dataset layout: docs/formats.md). Deterministic for a seed; "
                                     "image i depends only on (seed, i).")
    p.add_argument("--out", required=True, help="output dataset folder (images/, masks/, markers.json)")
    p.add_argument("--n", type=int, default=100, help="number of images (default 100)")
    p.add_argument("--seed", type=seed_arg, default=0, help="random seed (default 0)")
    p.add_argument("--size", default="640x480", help="image size WxH in pixels (default 640x480)")
    p.add_argument("--split", choices=("train", "test", "all"), default="all",
                   help="which backgrounds to use: the held-out 'test' ~20%% per category, the rest "
                        "('train'), or all (default)")
    p.add_argument("--format", choices=("jpg", "png"), default="jpg", help="image format (default jpg)")
    p.add_argument("--markers", default="1-4", help="markers per non-empty image, MIN-MAX (default 1-4)")
    p.add_argument("--empty-prob", type=float, default=0.15, help="share of images without markers")
    p.add_argument("--confusers", default="0-4", help="confusers per image, MIN-MAX (default 0-4)")
    p.add_argument("--tilt-max", type=float, default=60.0, help="largest tilt in degrees (default 60)")
    p.add_argument("--radius-min", type=float, default=8.0, help="smallest marker radius, px (default 8)")
    p.add_argument("--workers", type=int, default=1, help="parallel processes (same files as serial)")
    p.set_defaults(func=run)


def _range(text: str, what: str) -> tuple[int, int]:
    from ..errors import UsageError

    lo, sep, hi = text.partition("-")
    try:
        a, b = (int(lo), int(hi)) if sep else (int(lo), int(lo))
    except ValueError:
        raise UsageError(f"--{what} must be MIN-MAX (e.g. 1-4), got {text!r}") from None
    if not 0 <= a <= b:
        raise UsageError(f"--{what} must be MIN-MAX with 0 <= MIN <= MAX, got {text!r}")
    return a, b


def run(args) -> int:
    from ..errors import UsageError
    from ..synth_images import SynthImageOptions, write_synth_images

    try:
        w, h = (int(v) for v in args.size.lower().split("x"))
    except ValueError:
        raise UsageError(f"--size must be WxH, e.g. 640x480, got {args.size!r}") from None
    if args.n < 0:
        raise UsageError("--n must be >= 0")
    if args.workers < 1:
        raise UsageError("--workers must be >= 1")
    try:
        opt = SynthImageOptions(width=w, height=h, split=args.split, image_format=args.format,
                                markers=_range(args.markers, "markers"), empty_prob=args.empty_prob,
                                confusers=_range(args.confusers, "confusers"), tilt_max_deg=args.tilt_max,
                                radius_min_px=args.radius_min)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    from ..progress import counter

    t0 = time.perf_counter()
    with counter(args.n, unit="img") as update:
        path = write_synth_images(args.out, args.n, args.seed, opt, workers=args.workers, progress=update)
    dt = time.perf_counter() - t0
    log.info("wrote %d images to %s in %.1f s (%.1f images/s); truth in %s", args.n, args.out, dt,
             args.n / dt if dt > 0 else float("inf"), path)
    return 0
