"""``cpdetect eval DIR --detector NAME``: score a detector on a marker dataset (docs/formats.md)."""
from __future__ import annotations

import logging

log = logging.getLogger(__name__)


def register(sub) -> None:
    p = sub.add_parser("eval", aliases=["evaluate"], help="score a detector on a marker image dataset",
                       description="Run a detector on DIR/images and compare with DIR/markers.json: "
                                   "marker precision/recall/F1, centre error, and pixel IoU/F1/AP when the "
                                   "detector gives a probability map.")
    p.add_argument("dataset", metavar="DIR", help="dataset folder (images/, masks/, markers.json)")
    p.add_argument("--detector", required=True, help="registered detector name (e.g. classical, hma)")
    p.add_argument("--set", dest="settings", action="append", default=[], metavar="KEY=VALUE",
                   help="detector setting (repeatable); values are read as JSON when they parse")
    p.add_argument("--out", help="write the metrics (with per-image records) to this JSON file")
    p.add_argument("--limit", type=int, help="only the first N images")
    p.add_argument("--from-array", action="store_true",
                   help="decode each image first and time only the detector on the array, also for a "
                        "detector that reads files itself (the classical one; by default it gets the "
                        "path, as in `cpdetect detect`, and its time includes the decode)")
    p.set_defaults(func=run)


def run(args) -> int:
    from ..dataset import load_dataset
    from ..detector import get_detector, parse_settings
    from ..errors import UsageError
    from ..evaluate import evaluate, format_table
    from ..fileio import write_json_atomic
    from ..progress import counter

    if args.limit is not None and args.limit < 1:
        raise UsageError("--limit must be >= 1")
    dataset = load_dataset(args.dataset)
    detector = get_detector(args.detector, **parse_settings(args.settings))
    n = len(dataset.images) if args.limit is None else min(args.limit, len(dataset.images))
    with counter(n, unit="img") as update:
        metrics = evaluate(dataset, detector, limit=args.limit, progress=update,
                           from_file=False if args.from_array else None)
    metrics["detector"] = args.detector
    metrics["settings"] = parse_settings(args.settings)
    print(format_table(metrics))
    if args.out:
        write_json_atomic(args.out, metrics)
        log.info("metrics written to %s", args.out)
    return 0
