"""Markers of the ``hma`` detector with and without ``colour_centres``, in one run.

For every image of a dataset (``cpdetect synth images`` output or any dataset in our contract) the
detector runs once as ``cpdetect eval --detector hma`` runs it (on the BGR image), with
``colour_centres=true``: the markers of the gray image, then those found on the paint image (max of
the channels) on the blobs the network is sure of that hold none of them
(:meth:`learned.adapter.HMADetector._colour_instances`). The markers and the returned map before that
step are what ``colour_centres=never`` reports (the step off), so both are scored from the same run,
against the same truth: instance F1, recall, false markers, centre error and type
(:func:`cpdetect.evaluate.summarize`), and pixel IoU / F1 of the returned maps. Costs what ``cpdetect
eval`` costs, and the instance stage on the paint image for those blobs.

    .venv/bin/python bench/colour_centres_eval.py DATASET [--limit N] [--threads 2] [--out F]
"""
from __future__ import annotations

import sys
from pathlib import Path

from dataset_bench import fmt, load_dataset_or_none, parse_args

RESULTS = Path(__file__).parent / "results" / "colour_centres_eval.json"
KEYS = ("markers", "tp", "fp", "fn", "precision", "recall", "f1", "centre_error_px", "type_accuracy",
        "centre_visible")


def main(argv=None) -> int:
    args = parse_args(__doc__, RESULTS, argv)

    from cpdetect.dataset import read_mask
    from cpdetect.detector import get_detector
    from cpdetect.errors import InputError
    from cpdetect.evaluate import PixelCounts, _json_safe, score_image, summarize
    from cpdetect.fileio import write_json_atomic
    from cpdetect.imageio import read_image
    from cpdetect.types import DetectionResult

    ds = load_dataset_or_none(args.dataset)
    if ds is None:
        return 2
    det = get_detector("hma", threads=args.threads, colour_centres=True)
    step = det._colour_instances
    before = {}

    def colour_instances(paint, network, f, dets, prob, *rest):  # what the step off would have returned
        before["dets"], before["prob"] = list(dets), prob
        return step(paint, network, f, dets, prob, *rest)

    det._colour_instances = colour_instances
    # the returned map keeps the blobs of the mirrored mean that the map after the instances keeps:
    # the default's is that rule applied to the map before the colour step
    import learned.adapter as adapter

    keep_blobs_of = adapter.keep_blobs_of

    def keep_blobs(mean, kept, threshold):
        before["mean"] = mean
        return keep_blobs_of(mean, kept, threshold)

    adapter.keep_blobs_of = keep_blobs
    items = ds.images if args.limit is None else ds.images[:max(args.limit, 0)]
    names = ("off", "on")
    counts = {n: PixelCounts() for n in names}
    records = {n: [] for n in names}
    added = []
    try:
        for k, item in enumerate(items):
            image = read_image(ds.image_path(item))
            h, w = image.shape[:2]
            before.clear()
            res = det.detect(image)
            off = (before.get("dets", res.detections), before.get("prob", res.probability))
            if "prob" in before and "mean" in before:
                off = (off[0], keep_blobs_of(before["mean"], before["prob"], det.settings.threshold))
            new = [d for d in res.detections if all(d is not o for o in off[0])]
            for d in new:
                added.append({"file": item.file, **d.to_dict()})
            for name, (dets, prob) in (("off", off), ("on", (res.detections, res.probability))):
                records[name].append(score_image(item.file, w, h, res.seconds, dets, item.markers, item.meta))
                if item.mask is not None and prob is not None:
                    at = DetectionResult(detections=dets, image_size=(w, h), probability=prob, seconds=0.0)
                    counts[name].add(at.probability_at(w, h), read_mask(ds.mask_path(item), shape=(h, w)))
            if (k + 1) % 50 == 0:
                print(f"{k + 1}/{len(items)} added {len(added)}", file=sys.stderr, flush=True)
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    report = {"dataset": str(ds.root), "images": len(items), "added": added}
    for n in names:
        s = summarize(records[n], counts[n], detector="hma")
        report[n] = _json_safe({**{key: s[key] for key in KEYS}, "pixel": s["pixel"],
                                "seconds_per_megapixel": s["seconds_per_megapixel"]})
    write_json_atomic(args.out, report)
    for n in names:
        i = report[n]
        px = i["pixel"] or {}
        print(f"colour_centres={n:3s} found {i['tp']} of {i['markers']}, false {i['fp']}, instance F1 "
              f"{fmt(i['f1'])}, centre mean {fmt(i['centre_error_px']['mean'])} px, p95 "
              f"{fmt(i['centre_error_px']['p95'])}, type {fmt(i['type_accuracy'])}, pixel IoU "
              f"{fmt(px.get('iou'))}, F1 {fmt(px.get('f1'))}")
    print(f"seconds per megapixel (with the step) {fmt(report['on']['seconds_per_megapixel'])}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
