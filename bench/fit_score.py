"""Fit the classical detector's marker score: gradient-boosted trees over its verification features.

Runs the classical detector with the score disabled (every verified candidate kept) on generated
images with *train*-split backgrounds only, labels each verified candidate by the true markers
(cpdetect.evaluate.tolerance_px), fits a ``HistGradientBoostingClassifier`` (depth 7, 300 trees,
learning rate 0.05, 40 samples per leaf) and writes it to data/marker_score.json (read by
cpdetect.classical.marker_score). With ``--check``, the same is done on those folders without
fitting, and markers found / false candidates kept at several cuts are printed for the fitted trees
and for the score currently shipped.

    # the shipped data/marker_score.json (stop 83, 2026-12-07): over SCORE_FEATURES and the marker
    # area (PATCH_FEATURES, cpdetect.classical), 6,900 images, 80,938 verified candidates (13,408 on
    # markers); the trees before it (2026-11-26, SCORE_FEATURES alone, 68,428 candidates of the
    # detector then) are data/marker_score_base.json, which hma's classical pass keeps; the first
    # 600 images of train606 are those of the trees before those (seed 606, 600 images, with fit11
    # and sc707: depth 5, 100 trees, learning rate 0.1, 20 per leaf; kept as
    # data/marker_score_hma.json, the scores the hma models were fitted on)
    cpdetect synth images --out train606 --n 6000 --seed 606 --split train
    cpdetect synth images --out fit11 --n 300 --seed 11 --split train
    cpdetect synth images --out sc707 --n 600 --seed 707 --split train
    cpdetect synth images --out dev505 --n 200 --seed 505 --split train   # dev sets, not fitted on
    cpdetect synth images --out dev808 --n 300 --seed 808 --split train
    cpdetect synth images --out dev909 --n 300 --seed 909 --split train
    .venv/bin/python bench/fit_score.py --data train606 --data fit11 --data sc707 \
        --check dev505 --check dev808 --check dev909 --cache rows

``--workers N`` shares each folder's images among N processes: the same rows in the same order, so
the same trees (60 images: 14 s with two workers against 21 s with one, start-up and fit included;
alone, the 6,900 images' rows take about 30 minutes at 3.7 images a second).

The rows are those of candidates that the tests whose measurements these trees weigh too let
through (``strict_tests``: sectors not uniform; on the outer ring inverted surroundings, the checker
continuing, sectors not solid to the outline). Since 2026-11-27 the detector no longer rejects on
those tests and leaves them to these trees: on the train-split dev sets dev808 / dev909 / dev1111 /
dev1212, +4 / +3 / +6 / +4 markers, false ones 1 / 6 / 10 / 13 -> 2 / 5 / 10 / 13. Trees refitted on
rows without the outer-ring tests (161,861 candidates of the same 6,900 images) did worse in the
detector: +3 / -2 / +5 / +3 markers, false ones 4 / 4 / 8 / 18.

Tried on 2026-11-26, not kept: two more features saying whether the four checker lines run on past
the outline as edges (tile grout, a tag's bit grid and checkerboards carry them on; a marker's lines end at
its outline), the grey step across each line at 1.15-1.6 outline distances over the contrast, mean
and least over the lines. On their own they separate poorly (markers: median 0.07, 95th percentile
0.41-0.44 for the mean; the false markers of the detector 0.02-0.66). Refitted with them on the same
6,900 images, the dev sets' candidates at the cut 0.65 kept 378 / 565 / 536 markers with 6 / 2 / 9
false candidates, against 378 / 564 / 538 with 7 / 1 / 10 without them: no gain.

Tried on 2026-11-27, not kept: twice the images. The same three folders plus a fresh one
(`--seed 2525 --split train`, 6,000 images): 12,900 images, 148,741 verified candidates (24,980 on
markers). Checked on ten train-split dev sets none of them were fitted on (dev808, dev909, dev1111,
dev1212 and seeds 1313, 1414, 1515, 1616, 1818, 1919; 3,200 images, 6,893 markers):

- candidates kept at the cut 0.65: shipped 6,024 markers / 81 false candidates; refitted 6,028 / 74;
  refitted with depth 8 and 400 trees 6,038 / 79;
- the detector's markers found / false: shipped 6,279 / 65; refitted 6,268 / 64; depth 8 6,277 / 61.
  The gain among the candidates does not survive the detector's later steps.

Tried on 2026-12-07 (stop 82, rule 48), not kept: a blur feature, log(edge blur sigma / outline
radius) (cpdetect.centre_reach.edge_blur_px on the finest image the verifier samples), for the
small blurred markers the trees drop (their mid grey share, ring agreement and level spread look
like a texture saddle's). Rows of the detector as it was then, for the same 6,900 images: 80,938
candidates (13,408 on markers). In 5-fold cross-validation by image on a fresh train-split set
(seed 50300, 1,500 images) it kept +18 / +20 / +19 of 2,895 markers at equal false candidates; on
dev505 / dev808 / dev909 at the cut 0.65: shipped 1,485 / 19, refitted without it 1,482 / 20, with it
1,491 / 22 (with ``early_stopping=False``; scikit-learn's automatic early stopping, on over 10,000
rows, made such a refit depend on ``random_state`` by 2-6 markers, so SETTINGS (below) reproduce
the shipped file only with it left on). In the detector, fresh test-split 640 x 480 50400 / 50500 /
50600 and 1920 x 1080 50700: 4,556 -> 4,561 of 4,953 markers found (+0.1 %, the rule asked +0.3 %),
false markers 27 -> 22; on 45 MP 50800 1 -> 4 false (soft blobs of 53-180 px radius scored 0.70-0.77:
a ratio to the radius calls a large soft shape sharp), 1.4-4.6 % more time at 640 x 480.

Stop 83 (2026-12-07), the shipped trees: the marker area itself as features (PATCH_FEATURES: 12
rings from 0.15 to 2.2 outline radii x 24 angles from the first dark sector, grey over the
contrast). Cross-validated on 2,700 train-split images (seeds 50300, 51400, 51500; 30,781
candidates) +96 of 5,285 markers at equal false candidates, and at the cut 0.65 39 false
candidates against 71. Refitted on the same 6,900 images: dev505 / dev808 / dev909 at 0.65,
shipped 1,485 / 19, refitted 1,503 / 13. In the detector (fresh test-split sets, rules 50 and 51 in
cpdetect.classical's comment on PATCH_FEATURES) the markers found rose by only 0.15-0.17 %, as the
gains among candidates did before, but false markers fell by a quarter (64 -> 47 over ten sets).
"""
from __future__ import annotations

import argparse
import json
import math
import pickle
import sys
from pathlib import Path

import numpy as np
from train_split import train_split_dataset

OUT = Path(__file__).resolve().parent.parent / "data" / "marker_score.json"
SETTINGS = dict(max_depth=7, max_iter=300, learning_rate=0.05, min_samples_leaf=40, random_state=0)


def verified_rows(folders: list[str], cache: str | None = None, workers: int = 1) -> list[dict]:
    """Score features of every verified candidate (min_score 0), with ``label`` (on a true marker),
    ``key`` (image and marker index, or None), the reported ``type`` and ``radius``, ``typein`` (what
    decides the type: centre, checker lines, boundary points by sector; None for an outline from the
    checker lines) and, on a marker, its ``true_type``. ``cache``: a folder keeping each dataset's
    rows (``<name>.pkl``; delete it after changing the detector), shared with bench/fit_type.py.
    ``workers``: processes the images are shared among (the rows are the same, in the same order)."""
    rows: list[dict] = []
    for folder in folders:
        path = Path(cache) / f"{Path(folder).resolve().name}.pkl" if cache else None
        if path is not None and path.is_file():
            with open(path, "rb") as f:
                got = pickle.load(f)
            if got.get("folder") == str(Path(folder).resolve()):
                rows += got["rows"]
                continue
        got = _verified_rows_of(folder, workers)
        if path is not None:
            # written whole or not at all: a run stopped half-way must not leave a cache that loads
            path.parent.mkdir(parents=True, exist_ok=True)
            tmp = path.with_suffix(".tmp")
            with open(tmp, "wb") as f:
                pickle.dump({"folder": str(Path(folder).resolve()), "rows": got}, f)
            tmp.replace(path)
        rows += got
    return rows


def _dataset(folder: str):
    if not (Path(folder) / "markers.json").is_file():
        raise SystemExit(f"{folder}: no markers.json (make it with cpdetect synth images)")
    return train_split_dataset(folder, 0, 0, "cpdetect_fit_")  # checks that its backgrounds are train-split


def _verified_rows_of(folder: str, workers: int = 1) -> list[dict]:
    """:func:`verified_rows` of one folder, its images in ``workers`` processes (in chunks of
    consecutive images, a few per process, joined in order)."""
    n = len(_dataset(folder).images)
    if workers <= 1 or n < 2:
        return _rows_of_images((folder, 0, n, True))
    from cpdetect.executors import make_executor

    cuts = np.linspace(0, n, min(n, 4 * workers) + 1).round().astype(int)
    chunks = [(folder, int(a), int(b), False) for a, b in zip(cuts[:-1], cuts[1:]) if b > a]
    rows: list[dict] = []
    with make_executor(workers=workers) as ex:
        for (_, _, done, _), got in zip(chunks, ex.imap(_rows_of_images, chunks)):
            rows += got
            print(f"\r{folder}: {done}/{n} rows {len(rows)}", end="", file=sys.stderr)
    print(file=sys.stderr)
    return rows


def _rows_of_images(job: tuple[str, int, int, bool]) -> list[dict]:
    """The rows of images [lo, hi) of a folder: ``job`` = (folder, lo, hi, print progress)."""
    import cv2

    import cpdetect.classical as C
    from cpdetect.evaluate import tolerance_px

    folder, lo, hi, progress = job
    rows, cur, typein = [], [""], [None]
    orig, orig_types = C._Verifier.verify, C._type_of

    def spy(self, *a):
        typein[0] = None
        # rows of candidates that the tests the score weighs too let through, as the shipped trees
        # were fitted (see the module doc: the detector leaves those tests to the score)
        self.strict_tests = True
        self.reads_patch = True  # every feature a refit may read, whatever trees are shipped
        r = orig(self, *a)
        if not isinstance(r, str):
            rows.append(dict(self.last_features, x=r.x, y=r.y, file=cur[0], type=r.type, radius=r.radius,
                             typein=typein[0]))
        return r

    def types_spy(x, y, bounds, widths, pts_by_sector, radius, feats, fallback, trees, other=None,
                  probabilities=None):
        # ``other``: the other polarity's fit, kept as the type trees read it (marker_type.type_features)
        typein[0] = dict(x=x, y=y, bounds=np.array(bounds), widths=np.array(widths),
                         pts_by_sector={k: np.array(v) for k, v in pts_by_sector.items()},
                         other=None if other is None else dict(
                             pts_by_sector={k: np.array(v) for k, v in other["pts_by_sector"].items()},
                             radius=float(other["radius"]), e_rel=float(other["e_rel"])))
        # the rows' type is the residual rule's, whatever type trees are shipped (or none yet)
        return orig_types(x, y, bounds, widths, pts_by_sector, radius, feats, fallback, False,
                          probabilities=probabilities)

    # the score must not decide which candidates are verified: with every score 1 and no bar for
    # outlines from the checker lines, the rows are the same whatever score is shipped
    saved = C._Verifier.verify, C.marker_score, C.LINE_FRAME_MIN_SCORE, C._type_of
    C._Verifier.verify, C.marker_score, C.LINE_FRAME_MIN_SCORE, C._type_of = spy, (lambda feats, name=None: 1.0), 0.0, types_spy
    try:
        det = C.ClassicalDetector(min_score=0.0, colour_min_score=0.0, early_score_cut=0.0)
        ds = _dataset(folder)
        for k in range(lo, hi):
            item = ds.images[k]
            cur[0] = f"{folder}/{item.file}"
            n0 = len(rows)
            det.detect(cv2.imread(str(ds.image_path(item)), cv2.IMREAD_GRAYSCALE))
            for r in rows[n0:]:
                hit = [i for i, t in enumerate(item.markers)
                       if math.hypot(t.x - r["x"], t.y - r["y"]) <= tolerance_px(t.radius_px)]
                r["label"], r["key"] = int(bool(hit)), (cur[0], hit[0]) if hit else None
                if hit:
                    r["true_type"] = item.markers[hit[0]].type
            if progress:
                print(f"\r{folder}: {k + 1}/{hi} rows {len(rows)}", end="", file=sys.stderr)
        if progress:
            print(file=sys.stderr)
    finally:
        C._Verifier.verify, C.marker_score, C.LINE_FRAME_MIN_SCORE, C._type_of = saved
    return rows


def kept(rows: list[dict], p: np.ndarray, cut: float) -> tuple[int, int]:
    """(markers with a candidate scored >= cut, false candidates scored >= cut)."""
    found = {tuple(r["key"]) for r, s in zip(rows, p) if r["label"] and s >= cut}
    return len(found), int(sum(1 for r, s in zip(rows, p) if not r["label"] and s >= cut))


def _at_least_one(text: str) -> int:
    n = int(text)
    if n < 1:
        raise argparse.ArgumentTypeError(f"must be 1 or more, got {n}")
    return n


def fit_arguments(description: str, out: Path) -> argparse.ArgumentParser:
    """The command line of the fitting scripts on verified candidates (this one and bench/fit_type.py)."""
    ap = argparse.ArgumentParser(description=description)
    ap.add_argument("--data", action="append", required=True, help="train-split dataset folder (repeatable)")
    ap.add_argument("--check", action="append", default=[], help="train-split folder to compare on (repeatable)")
    ap.add_argument("--cache", help="folder keeping each dataset's rows (shared by bench/fit_score.py and "
                                    "bench/fit_type.py)")
    ap.add_argument("--workers", type=_at_least_one, default=1,
                    help="processes the row collection shares the images among")
    ap.add_argument("--out", default=str(out))
    return ap


def main(argv=None) -> int:
    args = fit_arguments(__doc__.splitlines()[0], OUT).parse_args(argv)
    from sklearn.ensemble import HistGradientBoostingClassifier

    import cpdetect.classical as C
    from cpdetect.fileio import write_json_atomic
    from cpdetect.tree_ensemble import export_tree_ensemble, tree_ensemble_from_dict

    feats = list(C.SCORE_FEATURES + C.PATCH_FEATURES)  # the shipped trees read the marker area too
    check = verified_rows(args.check, args.cache, args.workers) if args.check else []
    Xc = np.array([[r[f] for f in feats] for r in check], float)
    try:  # before anything is written
        model = C.score_model()  # the shipped trees read their own features (without the patch before stop 83)
        shipped = model.probability(np.array([[r[f] for f in model.features] for r in check], float)) if check else None
    except FileNotFoundError:
        shipped = None
    rows = verified_rows(args.data, args.cache, args.workers)
    X = np.array([[r[f] for f in feats] for r in rows], float)
    y = np.array([r["label"] for r in rows])
    clf = HistGradientBoostingClassifier(**SETTINGS).fit(X, y)
    doc = export_tree_ensemble(clf, feats, fitted_on=[str(Path(d).name) for d in args.data],
                               rows=int(len(y)), positives=int(y.sum()), settings=SETTINGS,
                               script="bench/fit_score.py")
    ens = tree_ensemble_from_dict(doc)
    gap = float(np.abs(ens.probability(X) - clf.predict_proba(X)[:, 1]).max())
    print(f"{len(y)} verified candidates, {int(y.sum())} on markers; exported trees vs scikit-learn: {gap:.2e}")
    if gap > 1e-9:
        print("export does not reproduce the classifier", file=sys.stderr)
        return 1
    if check:
        new = ens.probability(Xc)
        n_m = len({tuple(r["key"]) for r in check if r["label"]})
        print(f"check {', '.join(args.check)}: {n_m} markers with a verified candidate, {len(check)} candidates")
        for name, p in (("shipped", shipped), ("fitted", new)):
            if p is None:
                continue
            cuts = (0.35, 0.5, 0.65, 0.75)
            print(f"  {name:8s}", "  ".join(f"cut {c:.2f}: {'%d / %d' % kept(check, p, c)}" for c in cuts))
    write_json_atomic(args.out, doc, indent=None)
    print(f"written {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
