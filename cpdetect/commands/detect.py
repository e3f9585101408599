"""``cpdetect detect IMAGES_OR_DIR... --detector NAME --out detections.json``: find markers in photos."""
from __future__ import annotations


def register(sub) -> None:
    p = sub.add_parser("detect", help="find markers in images and write detections.json",
                       description="Run a detector on images (files and/or folders) and write "
                                   "cpdetect.detections/1 JSON. Resumable: finished images are kept in "
                                   "OUT.parts/ and skipped when the same command is run again.")
    p.add_argument("inputs", nargs="+", metavar="IMAGES_OR_DIR", help="image files or folders of images")
    p.add_argument("--detector", default="classical", help="registered detector name (default: classical)")
    p.add_argument("--out", required=True, help="output JSON file")
    p.add_argument("--set", dest="settings", action="append", default=[], metavar="KEY=VALUE",
                   help="detector setting (repeatable); values are read as JSON when they parse")
    p.add_argument("--workers", type=int, default=1, help="worker processes (results identical to serial)")
    p.add_argument("--scheduler", metavar="ADDRESS",
                   help="run on a Dask cluster (pip install 'cpdetect[dask]'), e.g. tcp://host:8786; every "
                        "worker must see the images at the same path (shared storage). Overrides --workers")
    p.add_argument("--skip-bad", action="store_true",
                   help="record unreadable images as errors and go on (default: stop at the first)")
    p.set_defaults(func=run)


def run(args) -> int:
    import logging

    from ..batch import collect_jobs, detect_batch
    from ..detector import get_detector, parse_settings
    from ..errors import UsageError
    from ..progress import counter

    if args.workers < 1:
        raise UsageError("--workers must be >= 1")
    settings = parse_settings(args.settings)
    get_detector(args.detector, **settings)  # fail early on an unknown detector, setting or its type
    jobs = collect_jobs(args.inputs)
    with counter(len(jobs), unit="img") as update:
        doc = detect_batch(jobs, args.detector, settings, args.out, workers=args.workers, skip_bad=args.skip_bad,
                           progress=update, scheduler=args.scheduler or None)
    n_det = sum(len(im.get("detections", [])) for im in doc["images"])
    n_bad = sum(1 for im in doc["images"] if "error" in im)
    logging.getLogger("cpdetect").info("%d images, %d detections%s -> %s", len(doc["images"]), n_det,
                                       f", {n_bad} unreadable" if n_bad else "", args.out)
    return 0

