"""Pixel figures of the ``hma`` detector's returned map with and without ``mirror_map``, in one run.

For every image of a dataset (``cpdetect synth images`` output or any dataset in our contract) the
detector runs once as ``cpdetect eval`` runs it but with ``mirror_map="never"``; the network is
then run on the image mirrored left to right, and the map ``mirror_map="small"`` would return is
made from the two (:func:`learned.mirror_map.mirrored_mean`, :func:`learned.mirror_map.keep_blobs_of`),
so both are scored against the same masks at the threshold of :class:`cpdetect.evaluate.PixelCounts`.
The markers are the same either way (they come from the image's own map): their figures (instance
F1, recall, centre error, type, as :func:`cpdetect.evaluate.summarize` gives them) are reported
once. Costs two network passes per image (about 8 s per 640 x 480 image with two runs at once on a
2-core CPU).

    .venv/bin/python bench/mirror_map_eval.py DATASET [--limit N] [--out bench/results/mirror_map_eval.json]
"""
from __future__ import annotations

import sys
from pathlib import Path

from dataset_bench import fmt, load_dataset_or_none, parse_args

RESULTS = Path(__file__).parent / "results" / "mirror_map_eval.json"


def _figures(c) -> dict:
    """``PixelCounts.metrics()`` with the pixel counts beside them (NaN, where undefined, made None
    by the caller)."""
    return {**c.metrics(), "tp": c.tp, "fp": c.fp, "fn": c.fn}


def main(argv=None) -> int:
    args = parse_args(__doc__, RESULTS, argv)

    from cpdetect.dataset import read_mask
    from cpdetect.detector import as_gray_uint8, get_detector
    from cpdetect.errors import InputError
    from cpdetect.evaluate import PixelCounts, _json_safe, score_image, summarize
    from cpdetect.fileio import write_json_atomic
    from cpdetect.imageio import read_image
    from cpdetect.types import DetectionResult
    from learned.mirror_map import keep_blobs_of, mirrored_mean

    ds = load_dataset_or_none(args.dataset)
    if ds is None:
        return 2
    det = get_detector("hma", threads=args.threads, mirror_map="never")
    network = det.probability
    last = {}

    def probability(gray, **kw):  # the detector's own pass, kept for the mirror step
        last["pm"] = network(gray, **kw)
        return last["pm"]

    det.probability = probability
    items = ds.images if args.limit is None else ds.images[:max(args.limit, 0)]
    counts = {"never": PixelCounts(), "small": PixelCounts()}
    records = []
    try:
        for k, item in enumerate(items):
            image = read_image(ds.image_path(item))
            h, w = image.shape[:2]
            res = det.detect(image)
            records.append(score_image(item.file, w, h, 0.0, res.detections, item.markers, item.meta))
            if item.mask is None or "pm" not in last:
                continue
            pm = last.pop("pm")
            mean = mirrored_mean(as_gray_uint8(image), pm.prob, lambda g: network(g).prob)
            mirrored = keep_blobs_of(mean, res.probability, det.settings.threshold)
            truth = read_mask(ds.mask_path(item), shape=(h, w))
            for name, prob in (("never", res.probability), ("small", mirrored)):
                at = DetectionResult(detections=res.detections, image_size=(w, h), probability=prob, seconds=0.0)
                counts[name].add(at.probability_at(w, h), truth)
            if (k + 1) % 50 == 0:
                print(f"{k + 1}/{len(items)}", {n: fmt(c.metrics()["iou"]) for n, c in counts.items()},
                      file=sys.stderr, flush=True)
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    figures = _json_safe({n: _figures(c) for n, c in counts.items()})
    iou = [figures[n]["iou"] for n in ("never", "small")]
    markers = summarize(records, detector="hma")
    instances = {k: markers[k] for k in ("markers", "tp", "fp", "fn", "precision", "recall", "f1",
                                         "centre_error_px", "type_accuracy", "centre_visible")}
    report = {"dataset": str(ds.root), "images": len(items), "mirror_map": figures,
              "iou_change": None if None in iou else iou[1] - iou[0], "instances": _json_safe(instances)}
    write_json_atomic(args.out, report)
    for n, f in figures.items():
        print(f"mirror_map={n:5s}  pixel IoU {fmt(f['iou'])}  pixel F1 {fmt(f['f1'])}  "
              f"false px {f['fp']}  missed px {f['fn']}")
    i, c = report["instances"], report["instances"]["centre_error_px"]
    print(f"markers (either way): found {i['tp']} of {i['markers']}, false {i['fp']}, instance F1 {fmt(i['f1'])}, "
          f"centre mean {fmt(c['mean'])} px, p95 {fmt(c['p95'])}, type {fmt(i['type_accuracy'])}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
