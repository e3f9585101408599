"""Fit the ``hma`` detector's instance model (learned/instances.py) for one network.

Generates images with *train*-split backgrounds only (or reuses ``--data``), runs the network once per
image (probability maps cached in ``--cache`` so a refit is cheap), collects every blob's features
with its best centre, labels it by the true markers (cpdetect.evaluate.tolerance_px: 1 when the centre
matches a marker no earlier blob matched), fits the logistic model and writes ``instance_score.json``
into the model folder. Figures (counts, the chosen threshold, 5-fold cross-validated marker-level
F1 against the rules alone) go to bench/results/fit_hma_instances.json.

    .venv/bin/python bench/fit_hma_instances.py --n 400 --seed 11 --cache /tmp/fit11_maps
"""
from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np
from train_split import train_split_dataset

RESULTS = Path(__file__).parent / "results" / "fit_hma_instances.json"


def map_cache(det, folder: Path) -> Path:
    """``folder``/<key>: the maps of one network and pass settings, so that a refit for another
    network never reads the maps of the one before (the key hashes model.pt and the settings)."""
    import hashlib

    s = det.settings
    h = hashlib.sha256((Path(det.model_dir) / "model.pt").read_bytes())
    h.update(repr((s.scales, s.small_scales, s.max_side, s.tile, s.overlap)).encode())
    return folder / h.hexdigest()[:12]


def probability_maps(det, ds, cache: Path) -> list[tuple[np.ndarray, float]]:
    """The network's probability maps of every image of ``ds``, kept in ``cache`` (see :func:`map_cache`)."""
    from cpdetect.imageio import read_image

    cache = map_cache(det, cache)
    cache.mkdir(parents=True, exist_ok=True)
    out = []
    for k, item in enumerate(ds.images):
        f = cache / (Path(item.file).stem + ".npz")
        if not f.exists():
            pm = det.probability(read_image(ds.image_path(item), gray=True))
            tmp = f.with_suffix(".tmp.npz")
            np.savez_compressed(tmp, prob=pm.prob.astype(np.float16), factor=pm.factor)
            tmp.replace(f)
        z = np.load(f)
        out.append((z["prob"].astype(np.float32), float(z["factor"])))
        if (k + 1) % 50 == 0 or k + 1 == len(ds.images):
            print(f"probability maps {k + 1}/{len(ds.images)}", file=sys.stderr)
    return out


def blob_table(det, ds, maps) -> tuple[list[dict], list[int], list[str], int, list[int]]:
    """Features, labels and image of every blob with a centre; the number of true markers; and
    which blobs the rules alone keep (1) for the comparison."""
    from cpdetect.evaluate import tolerance_px
    from cpdetect.imageio import read_image

    rows, labels, groups, rules = [], [], [], []
    n_markers = 0
    for k, (item, (prob, f)) in enumerate(zip(ds.images, maps)):
        gray = read_image(ds.image_path(item), gray=True)
        blobs, _ = det.candidates(gray, prob, f, loose=True)
        n_markers += len(item.markers)
        taken = set()
        for b in sorted((b for b in blobs if b.features is not None), key=lambda b: -b.mean_p):
            c = b.centre
            best = None
            for j, t in enumerate(item.markers):
                d = math.hypot(t.x - c.x, t.y - c.y)
                if j not in taken and d <= tolerance_px(t.radius_px) and (best is None or d < best[0]):
                    best = (d, j)
            if best is not None:
                taken.add(best[1])
            rows.append(b.features)
            labels.append(int(best is not None))
            groups.append(item.file)
            rules.append(int(c.kind in ("verified", "centroid")))
        if (k + 1) % 100 == 0 or k + 1 == len(ds.images):
            print(f"blobs of {k + 1}/{len(ds.images)} images: {len(rows)}", file=sys.stderr)
    return rows, labels, groups, n_markers, rules


def cross_validated(rows, labels, groups, n_markers, rules, features, folds: int = 5) -> dict:
    """Marker-level F1 of the rules and of the model (fitted on the other folds, each fold's own
    threshold taken from its training part), over the same blobs."""
    from learned.instances import fit_instance_model

    y = np.asarray(labels)
    g = np.asarray(groups)
    files = np.unique(g)
    rng = np.random.default_rng(0)
    fold_of = dict(zip(rng.permutation(files), np.arange(len(files)) % folds))
    fold = np.array([fold_of[x] for x in g])
    keep = np.zeros(len(y), bool)
    for i in range(folds):
        tr, te = fold != i, fold == i
        pos_tr = int(np.sum(y[tr]))
        # markers to find in the training part, in proportion to its share of the positives
        m_tr = max(int(round(n_markers * pos_tr / max(int(y.sum()), 1))), pos_tr)
        model = fit_instance_model([rows[j] for j in np.flatnonzero(tr)], y[tr], m_tr, features=features)
        keep[te] = [model.probability(rows[j]) >= model.threshold for j in np.flatnonzero(te)]

    def f1(k):
        tp = int(np.sum(k & (y == 1)))
        fp = int(np.sum(k & (y == 0)))
        return {"tp": tp, "fp": fp, "fn": n_markers - tp, "f1": 2 * tp / max(2 * tp + fp + n_markers - tp, 1)}

    return {"rules": f1(np.asarray(rules, bool)), "model": f1(keep)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model-dir", default=None, help="network folder (default: the shipped one)")
    ap.add_argument("--data", action="append", default=None,
                    help="existing dataset with train-split backgrounds (repeatable)")
    ap.add_argument("--n", type=int, default=400)
    ap.add_argument("--seed", type=int, default=11)
    ap.add_argument("--cache", default=None, help="folder for the probability maps (reused when present; "
                                                  "default: DATA/probability_maps; one --data only)")
    ap.add_argument("--out", default=str(RESULTS))
    ap.add_argument("--dry-run", action="store_true", help="fit and report, but do not write the model file")
    ap.add_argument("--seed-pool", type=int, default=None,
                    help="the detector's seed_pool setting (default: the detector's default)")
    ap.add_argument("--features", choices=("base", "all"), default="base",
                    help="base: the twelve features of learned.instances.INSTANCE_FEATURES; all: with the "
                         "symmetry features of the chosen centre (learned.centre_choice)")
    args = ap.parse_args(argv)

    from learned.adapter import HMADetector, default_model_dir
    from learned.centre_choice import load_centre_ranker
    from learned.instances import INSTANCE_FEATURES, SYMMETRY_FEATURES, fit_instance_model

    model_dir = Path(args.model_dir) if args.model_dir else default_model_dir()
    if args.cache and len(args.data or []) > 1:
        ap.error("--cache needs a single --data (each dataset keeps its maps in DATA/probability_maps)")
    t0 = time.time()
    # the seeds the candidates are drawn from, as the detector will draw them (the shipped models of
    # stop 25 were fitted before the seed pool existed: --seed-pool 0 draws them that way)
    if args.seed_pool is not None and args.seed_pool < 0:
        ap.error(f"--seed-pool must be >= 0, got {args.seed_pool}")
    pool = {} if args.seed_pool is None else {"seed_pool": args.seed_pool}
    det = HMADetector(model_dir=str(model_dir), instance_model="none", **pool)
    # the blobs' centres as the detector will choose them: by the centre ranker when there is one
    det.centre_ranker = load_centre_ranker(model_dir)
    features = INSTANCE_FEATURES + (SYMMETRY_FEATURES if args.features == "all" else ())
    rows, labels, groups, rules, roots = [], [], [], [], []
    n_markers = n_images = 0
    for data in args.data or [None]:
        ds = train_split_dataset(data, args.n, args.seed, "cpdetect_fit_hma_")
        roots.append(str(ds.root))
        n_images += len(ds.images)
        maps = probability_maps(det, ds, Path(args.cache) if args.cache else ds.root / "probability_maps")
        r, y, g, n, ru = blob_table(det, ds, maps)
        rows += r
        labels += y
        groups += [f"{ds.root}/{x}" for x in g]
        n_markers += n
        rules += ru
    cv = cross_validated(rows, labels, groups, n_markers, rules, features)
    model = fit_instance_model(rows, labels, n_markers, fitted={
        "data": {"roots": roots, "images": n_images, "split": "train"},
        "network": str(model_dir), "date": time.strftime("%Y-%m-%d"),
        "command": "bench/fit_hma_instances.py " + " ".join(argv if argv is not None else sys.argv[1:]),
        "centre_ranker": det.centre_ranker is not None}, features=features)
    if not args.dry_run:
        model.save(model_dir)
    report = {"model_dir": str(model_dir), "images": n_images, "markers": n_markers, "blobs": len(labels),
              "positives": int(np.sum(labels)), "threshold": model.threshold, "cross_validated": cv,
              "weights": dict(zip(model.features, model.weights)), "seconds": time.time() - t0,
              "written": not args.dry_run}
    r, m = cv["rules"], cv["model"]
    finish(report, args.out, [
        f"{n_images} images, {n_markers} markers, {len(labels)} blobs with a centre ({int(np.sum(labels))} "
        f"on a marker); threshold {model.threshold}",
        f"5-fold marker-level F1: rules {r['f1']:.4f} (tp {r['tp']} fp {r['fp']}), "
        f"model {m['f1']:.4f} (tp {m['tp']} fp {m['fp']})"], None if args.dry_run else model_dir / model.FILE)
    return 0


def finish(report: dict, out: str, lines: list[str], written: Path | None) -> None:
    """Write the figures to ``out`` and print ``lines`` and what was written."""
    from cpdetect.fileio import write_json_atomic

    write_json_atomic(out, report)
    for line in lines:
        print(line)
    print(("dry run: nothing written" if written is None else f"written {written}") + f"; figures in {out}")


if __name__ == "__main__":
    sys.exit(main())
