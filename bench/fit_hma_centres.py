"""Fit the ``hma`` detector's centre ranker (learned/centre_choice.py) for one network.

Runs the network on generated images with *train*-split backgrounds (``--data``, one or more
folders, or ``--n`` images generated with ``--seed``; probability maps cached as for
bench/fit_hma_instances.py), refines every centre candidate of every blob as the detector does
(the centroid and up to ``rank_seeds`` X-corner seeds), and labels a candidate 1 when it lies within
the evaluation tolerance (cpdetect.evaluate.tolerance_px) of a true marker's centre. Blobs where no
candidate is right teach nothing about choosing and are left out. The logistic model is written as
``centre_rank.json`` into the model folder; figures (how often the ranker's choice and the rules'
choice are right, fitted on one half of the images and counted on the other) go to
bench/results/fit_hma_centres.json. Refit the instance model afterwards (its centre features follow
the choice): ``bench/fit_hma_instances.py --features all``.

    .venv/bin/python bench/fit_hma_centres.py --data /tmp/dev808 --data /tmp/dev909
"""
from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np
from fit_hma_instances import finish, probability_maps
from train_split import train_split_dataset

RESULTS = Path(__file__).parent / "results" / "fit_hma_centres.json"


def candidate_table(det, ds, maps) -> tuple[list[dict], list[int], list[int], list[int]]:
    """Features and labels of every candidate on blobs where one is right; per candidate its blob
    number, and per blob whether the rules' centre is right."""
    from cpdetect.evaluate import tolerance_px
    from cpdetect.imageio import read_image

    rows, labels, blob_of, rules_right = [], [], [], []
    for item, (prob, f) in zip(ds.images, maps):
        gray = read_image(ds.image_path(item), gray=True)
        blobs, _ = det.candidates(gray, prob, f, loose=True)

        def right(x, y):
            return any(math.hypot(t.x - x, t.y - y) <= tolerance_px(t.radius_px) for t in item.markers)

        for b in blobs:
            good = [int(right(c.x, c.y)) for c, _, _ in b.options]
            if not any(good):
                continue
            rules_right.append(int(b.centre is not None and right(b.centre.x, b.centre.y)))
            for (_, feats, _), g in zip(b.options, good):
                rows.append(feats)
                labels.append(g)
                blob_of.append(len(rules_right) - 1)
    return rows, labels, blob_of, rules_right


def held_out(rows, labels, blob_of, rules_right) -> dict:
    """Fit on the even blobs, count right choices on the odd ones (ranker against rules)."""
    from learned.centre_choice import fit_centre_ranker

    b = np.asarray(blob_of)
    y = np.asarray(labels)
    train = b % 2 == 0
    model = fit_centre_ranker([rows[i] for i in np.flatnonzero(train)], y[train])
    best: dict[int, tuple[float, int]] = {}
    for i in np.flatnonzero(~train):
        p = model.probability(rows[i])
        if b[i] not in best or p > best[b[i]][0]:
            best[b[i]] = (p, int(y[i]))
    odd = sorted(best)
    return {"blobs": len(odd), "ranker_right": int(sum(best[k][1] for k in odd)),
            "rules_right": int(sum(rules_right[k] for k in odd))}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model-dir", default=None, help="network folder (default: the shipped one)")
    ap.add_argument("--data", action="append", default=None, help="dataset with train-split backgrounds (repeatable)")
    ap.add_argument("--n", type=int, default=400)
    ap.add_argument("--seed", type=int, default=12)
    ap.add_argument("--out", default=str(RESULTS))
    ap.add_argument("--dry-run", action="store_true", help="fit and report, but do not write the model file")
    ap.add_argument("--seed-pool", type=int, default=None,
                    help="the detector's seed_pool setting (default: the detector's default)")
    args = ap.parse_args(argv)

    from learned.adapter import HMADetector, default_model_dir
    from learned.centre_choice import fit_centre_ranker

    model_dir = Path(args.model_dir) if args.model_dir else default_model_dir()
    t0 = time.time()
    # the seeds the candidates are drawn from, as the detector will draw them (the shipped models of
    # stop 25 were fitted before the seed pool existed: --seed-pool 0 draws them that way)
    if args.seed_pool is not None and args.seed_pool < 0:
        ap.error(f"--seed-pool must be >= 0, got {args.seed_pool}")
    pool = {} if args.seed_pool is None else {"seed_pool": args.seed_pool}
    det = HMADetector(model_dir=str(model_dir), centre_ranker="none", **pool)
    det.collect_options = True
    rows, labels, blob_of, rules_right, roots = [], [], [], [], []
    for data in args.data or [None]:
        ds = train_split_dataset(data, args.n, args.seed, "cpdetect_fit_centres_")
        roots.append(str(ds.root))
        maps = probability_maps(det, ds, ds.root / "probability_maps")
        r, y, b, rr = candidate_table(det, ds, maps)
        b = [k + len(rules_right) for k in b]
        rows += r
        labels += y
        blob_of += b
        rules_right += rr
    check = held_out(rows, labels, blob_of, rules_right)
    model = fit_centre_ranker(rows, labels, fitted={
        "data": {"roots": roots, "split": "train"}, "network": str(model_dir), "date": time.strftime("%Y-%m-%d"),
        "command": "bench/fit_hma_centres.py " + " ".join(argv if argv is not None else sys.argv[1:])})
    if not args.dry_run:
        model.save(model_dir)
    report = {"model_dir": str(model_dir), "data": roots, "blobs": len(rules_right), "candidates": len(labels),
              "positives": int(np.sum(labels)), "held_out": check,
              "weights": dict(zip(model.features, model.weights)), "seconds": time.time() - t0,
              "written": not args.dry_run}
    finish(report, args.out, [
        f"{len(rules_right)} blobs with a right candidate, {len(labels)} candidates; held out: ranker right on "
        f"{check['ranker_right']} of {check['blobs']} blobs, rules on {check['rules_right']}"],
        None if args.dry_run else model_dir / model.FILE)
    return 0


if __name__ == "__main__":
    sys.exit(main())
