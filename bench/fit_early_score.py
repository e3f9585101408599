"""Fit the classical detector's early score: trees that say, from the core and the rough sector
boundaries alone, whether the full verification will score at least EARLY_TARGET_SCORE.

Runs the detector (early score off, every other setting its default, file input as ``cpdetect eval``
reads it) on generated images with *train*-split backgrounds only, records for every verification
that reaches the early score its EARLY_FEATURES and the outcome of the whole verification (its
score, or the reason it failed: a failure counts as under the target), fits a
``HistGradientBoostingClassifier`` to "score >= EARLY_TARGET_SCORE" and writes it to
data/early_score.json (read by cpdetect.classical.early_score). No truth is needed: the trees learn
the detector's own verdict, so what a cut costs is measured on the detector's own outcomes.

With ``--check`` folders (train-split, not fitted on), prints for each cut in CUTS the share of
their verifications the early score would stop, and how many of those stopped would have scored at
least the target and at least ``min_score`` (0.65: a marker kept, unless a later test drops it).
The cut itself (``ClassicalSettings.early_score_cut``) is then chosen with the detector's own
figures (``cpdetect eval --set early_score_cut=...``).

    cpdetect synth images --out tr41100 --n 3000 --size 640x480 --split train --seed 41100
    cpdetect synth images --out tr41300 --n 40 --size 8192x5460 --radius-min 32 --split train --seed 41300
    cpdetect synth images --out dev41200 --n 600 --size 640x480 --split train --seed 41200
    cpdetect synth images --out dev41400 --n 16 --size 8192x5460 --radius-min 32 --split train --seed 41400
    # the shipped data/early_score.json (stop 74): the first 700 images of tr41100 and all of tr41300
    # (23,794 verifications, 2,231 scoring >= 0.2); refitting from the same rows gives the same trees
    .venv/bin/python bench/fit_early_score.py --data tr41100:700 --data tr41300 --check dev41200:300 \
        --check dev41400 --cache rows
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
from train_split import train_split_dataset

OUT = Path(__file__).resolve().parent.parent / "data" / "early_score.json"
RESULTS = Path(__file__).parent / "results" / "fit_early_score.json"
SETTINGS = dict(max_depth=5, max_iter=120, learning_rate=0.1, min_samples_leaf=40, random_state=0)
CUTS = (0.005, 0.01, 0.02, 0.03, 0.05, 0.1)


def early_rows(folder: str, limit: int | None = None, cache: str | None = None) -> list[dict]:
    """One row per verification of the detector on the folder's images (the first ``limit``) that
    reached the early score: its EARLY_FEATURES, ``score`` (of the whole verification; -1 where it
    failed) and ``file``. ``cache``: a folder keeping each folder's rows (``<name>-<limit>.json``;
    delete it after changing the detector)."""
    from cpdetect.fileio import write_json_atomic

    path = Path(cache) / f"{Path(folder).resolve().name}-{limit or 'all'}.json" if cache else None
    if path is not None and path.is_file():
        got = json.loads(path.read_text())
        if got.get("folder") == str(Path(folder).resolve()):
            return [{k: float("nan") if v is None else v for k, v in r.items()} for r in got["rows"]]
    rows = _early_rows_of(folder, limit)
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        # NaN (a polarity without a boundary) as null: JSON has no NaN
        plain = [{k: None if isinstance(v, float) and v != v else v for k, v in r.items()} for r in rows]
        write_json_atomic(path, {"folder": str(Path(folder).resolve()), "rows": plain}, indent=None)
    return rows


def _early_rows_of(folder: str, limit: int | None) -> list[dict]:
    import cpdetect.classical as C

    if not (Path(folder) / "markers.json").is_file():
        raise SystemExit(f"{folder}: no markers.json (make it with cpdetect synth images)")

    rows: list[dict] = []
    cur = [""]
    orig = C._Verifier.verify

    def spy(self, *a):
        self.early_inputs = None
        r = orig(self, *a)
        early = self.last_early()
        if early is not None:
            rows.append(dict(early, score=-1.0 if isinstance(r, str) else float(r.score), file=cur[0]))
        return r

    C._Verifier.verify = spy
    try:
        det = C.ClassicalDetector(early_score_cut=0.0)
        ds = train_split_dataset(folder, 0, 0, "cpdetect_fit_early_")  # refuses other splits' backgrounds
        images = ds.images[:limit] if limit else ds.images
        for k, item in enumerate(images):
            cur[0] = f"{folder}/{item.file}"
            det.detect(ds.image_path(item))
            print(f"\r{folder}: {k + 1}/{len(images)} rows {len(rows)}", end="", file=sys.stderr)
        print(file=sys.stderr)
    finally:
        C._Verifier.verify = orig
    return rows


def cut_table(p: np.ndarray, score: np.ndarray, min_score: float) -> list[dict]:
    """Per cut: share of verifications stopped, and of those stopped, how many reached the target
    and ``min_score``."""
    from cpdetect.classical import EARLY_TARGET_SCORE

    out = []
    for c in CUTS:
        stop = p < c
        out.append({"cut": c, "stopped": float(stop.mean()) if len(p) else 0.0,
                    "stopped_over_target": int((stop & (score >= EARLY_TARGET_SCORE)).sum()),
                    "stopped_over_min_score": int((stop & (score >= min_score)).sum()),
                    "over_target": int((score >= EARLY_TARGET_SCORE).sum()),
                    "over_min_score": int((score >= min_score).sum())})
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", action="append", required=True, help="train-split dataset folder (repeatable)")
    ap.add_argument("--check", action="append", default=[], help="train-split folder to check on (repeatable)")
    ap.add_argument("--limit", type=int, default=None, help="the first this many images of each folder (a folder "
                                                             "given as FOLDER:N: its first N)")
    ap.add_argument("--cache", help="folder keeping each folder's rows")
    ap.add_argument("--out", default=str(OUT))
    ap.add_argument("--results", default=str(RESULTS))
    args = ap.parse_args(argv)
    from sklearn.ensemble import HistGradientBoostingClassifier

    import cpdetect.classical as C
    from cpdetect.fileio import write_json_atomic
    from cpdetect.tree_ensemble import export_tree_ensemble, tree_ensemble_from_dict

    feats = list(C.EARLY_FEATURES)
    min_score = C.ClassicalSettings().min_score
    def rows_of(spec: str) -> list[dict]:
        folder, _, n = spec.rpartition(":")
        if not (folder and n.isdigit()):  # a plain folder (whose name may hold a colon)
            folder, n = spec, ""
        return early_rows(folder, int(n) if n else args.limit, args.cache)

    rows = [r for d in args.data for r in rows_of(d)]
    check = {d: rows_of(d) for d in args.check}
    X = np.array([[r[f] for f in feats] for r in rows], float)
    score = np.array([r["score"] for r in rows])
    y = score >= C.EARLY_TARGET_SCORE
    clf = HistGradientBoostingClassifier(**SETTINGS).fit(X, y)
    doc = export_tree_ensemble(clf, feats, fitted_on=[Path(d).name for d in args.data], rows=int(len(y)),
                               positives=int(y.sum()), target_score=C.EARLY_TARGET_SCORE, settings=SETTINGS,
                               script="bench/fit_early_score.py")
    ens = tree_ensemble_from_dict(doc)
    gap = float(np.abs(ens.probability(X) - clf.predict_proba(X)[:, 1]).max())
    print(f"{len(y)} verifications, {int(y.sum())} scoring >= {C.EARLY_TARGET_SCORE}; exported trees vs "
          f"scikit-learn: {gap:.2e}")
    if gap > 1e-9:
        print("export does not reproduce the classifier", file=sys.stderr)
        return 1
    figures = {"fitted_on": args.data, "limit": args.limit, "rows": int(len(y)), "positives": int(y.sum()), "settings": SETTINGS,
               "check": {}}
    for name, crow in check.items():
        Xc = np.array([[r[f] for f in feats] for r in crow], float).reshape(-1, len(feats))
        sc = np.array([r["score"] for r in crow])
        table = cut_table(ens.probability(Xc) if len(crow) else np.zeros(0), sc, min_score)
        figures["check"][name] = {"rows": len(crow), "per_cut": table}
        print(f"check {name}: {len(crow)} verifications, {table[0]['over_target']} >= target, "
              f"{table[0]['over_min_score']} >= min_score")
        for t in table:
            print(f"  cut {t['cut']:.3f}: stops {t['stopped']:.3f}; of those {t['stopped_over_target']} over the "
                  f"target, {t['stopped_over_min_score']} over min_score")
    write_json_atomic(args.out, doc, indent=None)
    write_json_atomic(args.results, figures)
    print(f"written {args.out} and {args.results}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
