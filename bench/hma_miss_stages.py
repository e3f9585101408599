"""Why the ``hma`` detector missed markers: each miss of a ``cpdetect eval`` run put to the stage that lost it.

Reads the metrics JSON of ``cpdetect eval DIR --detector hma --out F`` (its per-image records name the
dataset and every missed true marker), runs the network again on each image with a miss and, for each
missed marker, follows what the detector's default settings decide about the blob under its true
centre (:meth:`learned.adapter.HMADetector.candidates`):

- ``no blob``: P(marker) under the threshold at the true centre;
- ``blob too small`` / ``blob mean P low`` / ``no point-symmetric seed``: the blob is dropped before
  its centre is looked for (the last: an unsure blob, see ``unsure_min_symmetry``);
- ``no centre``: no seed on the blob refines to an acceptable X-corner;
- ``centre on another corner``: the blob's centre lies beyond the match tolerance of the true one;
- ``instance model``: the instance model's P is under its cut (and no classical marker confirms it;
  the classical markers are given as seeds where the detector's settings give them);
- ``not point-symmetric`` / ``centre reach``: the checks after the instance model;
- ``kept``: the blob yields a marker there (another blob's marker took it, or it was merged).

Writes the misses with their stage, the network's P at the centre, the blob's figures and the truth's
fields (radius, occlusion, blur, contrast, centre hidden) as JSON, and prints the counts. Costs one
network pass per image with a miss (the mirror image's map is not needed: the markers come from the
image's own map).

    .venv/bin/python bench/hma_miss_stages.py EVAL_JSON [--out bench/results/hma_miss_stages.json] [--threads 2]
"""
from __future__ import annotations

import math
import sys
from collections import Counter
from pathlib import Path

RESULTS = Path(__file__).parent / "results" / "hma_miss_stages.json"
TRUTH_FIELDS = ("radius_px", "type", "centre_hidden", "occluded_frac", "blur_px", "contrast")


def stage_of(det, gray, blobs, labels, f: float, truth) -> dict:
    """The stage that lost the true marker ``truth`` (a missed record: x, y, radius_px), with what
    the detector saw of it."""
    from cpdetect.centre_reach import centre_reach
    from cpdetect.evaluate import tolerance_px
    from learned.adapter import _map_pixel

    s = det.settings
    col, row = _map_pixel(truth["x"], truth["y"], f, labels.shape)
    out = {"p_centre": None, "stage": "no blob"}
    label = int(labels[row, col])
    if label == 0:
        return out
    b = next(b for b in blobs if b.label == label)
    out.update(blob_radius_px=b.radius, blob_mean_p=b.mean_p)
    if b.radius < s.min_radius_px:
        return {**out, "stage": "blob too small"}
    if b.hopeless:
        return {**out, "stage": b.hopeless}  # the detector's own words for why it dropped the blob
    c = b.centre
    if c is None:
        return {**out, "stage": "no centre"}
    d = math.hypot(c.x - truth["x"], c.y - truth["y"])
    out.update(centre_offset_px=d, centre_kind=c.kind, centre_sigma_px=c.sigma)
    if d > tolerance_px(truth["radius_px"]):
        return {**out, "stage": "centre on another corner"}
    model = det.instance_model
    if model is not None:
        p = model.probability(b.features)
        cut = s.instance_threshold if s.instance_threshold is not None else model.threshold
        out["instance_p"] = p
        if p < cut and not c.classical:
            return {**out, "stage": "instance model"}
        if det.centre_ranker is not None and c.kind != "verified" and not c.classical \
                and c.sym180 < s.min_sym180_unverified:
            return {**out, "stage": "not point-symmetric"}
    if s.min_centre_reach > 0:
        reach = centre_reach(gray, c.x, c.y, b.radius) if c.reach is None else c.reach
        if reach < s.min_centre_reach:
            return {**out, "stage": "centre reach"}
    return {**out, "stage": "kept"}


def main(argv=None) -> int:
    from eval_misses import arguments, images_with_misses, read_eval

    ap = arguments(__doc__, "hma", RESULTS)
    ap.add_argument("--threads", type=int, default=2, help="network threads")
    args = ap.parse_args(argv)

    from cpdetect.errors import InputError
    from cpdetect.fileio import write_json_atomic
    from cpdetect.imageio import read_image
    from learned.adapter import HMADetector, _map_pixel

    got = read_eval(args.eval_json, "hma")
    if got is None:
        return 2
    ev, ds = got
    det = HMADetector(threads=args.threads)
    rows = []
    try:
        for rec, item in images_with_misses(ev, ds):
            gray = read_image(ds.image_path(item), gray=True)
            pm = det.probability(gray)
            # the classical markers the detector would give the blobs as seeds (large_classical_seeds)
            seeds = det.seeds_of(det._classical(ds.image_path(item), False).detections) \
                if det.takes_classical_seeds(gray.shape[1], gray.shape[0]) else None
            blobs, labels = det.candidates(gray, pm.prob, pm.factor, seeds=seeds)
            for m in rec["missed"]:
                row = {"file": rec["file"], "x": m["x"], "y": m["y"], **{k: m.get(k) for k in TRUTH_FIELDS}}
                row.update(stage_of(det, gray, blobs, labels, pm.factor, m))
                col, r = _map_pixel(m["x"], m["y"], pm.factor, pm.prob.shape)
                row["p_centre"] = float(pm.prob[r, col])
                rows.append(row)
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    counts = Counter(r["stage"] for r in rows)
    hidden = Counter(r["stage"] for r in rows if r.get("centre_hidden"))
    report = {"eval": str(args.eval_json), "dataset": ev["dataset"], "missed": len(rows),
              "stages": {k: {"missed": n, "centre_hidden": hidden.get(k, 0)} for k, n in counts.most_common()},
              "misses": rows}
    write_json_atomic(args.out, report)
    print(f"{len(rows)} missed markers ({sum(hidden.values())} with the centre hidden by an occluder)")
    for k, n in counts.most_common():
        print(f"  {k:26s} {n:4d}   centre hidden {hidden.get(k, 0)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
