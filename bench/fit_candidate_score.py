"""Fit the classical detector's candidate score (the prefilter's logistic model, CANDIDATE_FEATURES).

Generates images with *train*-split backgrounds only (or reuses ``--data``), runs the detector's
candidate stage (X-corner candidates and the prefilter's fixed tests) on each, labels every candidate
that passes those tests by whether it lies on a true marker (cpdetect.evaluate.tolerance_px), fits a
logistic regression (positives weighted 20x: a lost marker costs more than a wasted verification) and
prints the constants to paste into cpdetect/classical.py (_CAND_MEAN, _CAND_STD, _CAND_W, _CAND_B).
A marker shows as several candidates (pyramid levels, neighbouring pixels) and needs only one, so the
cut is judged per marker: for each cut in CUTS, the share of markers whose best candidate is kept
and the share of the other candidates kept (the verifications left to do); CANDIDATE_SCORE_CUT is
then chosen with the detector's own figures at those cuts (recall, false markers, time). Writes its
figures to bench/results/fit_candidate_score.json.

    .venv/bin/python bench/fit_candidate_score.py --n 400 --seed 11

Tried on 2026-11-26, not kept: gradient-boosted trees (depth 6, 200 trees) instead of the logistic
model, fitted on 1.33M candidates of 6,900 train-split images. On the dev sets dev505 / dev808 /
dev909, at as many markers kept, they keep 25-30 % fewer other candidates, but the detector found
394 / 585 / 549 markers with 5 / 1 / 6 false ones at a cut of 0.05, against 394 / 583 / 549 with 4 /
1 / 6: no more markers verified, for more verifications.
"""
from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np
from train_split import train_split_dataset

RESULTS = Path(__file__).parent / "results" / "fit_candidate_score.json"


CUTS = (0.01, 0.02, 0.05, 0.1, 0.2, 0.3, 0.5)


def candidate_table(ds) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Features (n, F) of the candidates that pass the fixed tests, whether each lies on a marker,
    and which marker (a running index over the dataset; -1 off markers)."""
    import cv2

    from cpdetect.classical import CANDIDATE_FEATURES, ClassicalDetector, _search_levels, _Verifier
    from cpdetect.evaluate import tolerance_px
    from cpdetect.xcorner import find_candidates

    det = ClassicalDetector(min_candidate_score=0.0)
    s = det.settings
    X, y, ids = [], [], []
    n_markers = 0
    for i, item in enumerate(ds.images):
        gray = cv2.imread(str(ds.image_path(item)), cv2.IMREAD_GRAYSCALE)
        h, w = gray.shape
        k = det._search_factor(w, h)
        _, pyramid, levels = _search_levels(gray, k)
        cands = find_candidates(pyramid, 0.6 * s.min_contrast, s.max_candidates_per_level)
        if not cands:
            continue
        ver = _Verifier(levels, s, (w, h))
        xy = np.array([[(c.x + 0.5) * k - 0.5, (c.y + 0.5) * k - 0.5] for c in cands])
        scale = np.array([k * 2.0 ** c.level for c in cands])
        passed, feats = ver.prefilter_features(xy, np.maximum(1.5, 1.5 * scale),
                                               chat=np.array([c.contrast for c in cands]),
                                               level=np.array([c.level for c in cands], float))
        if not passed.any():
            continue
        # the features are those of the candidates that passed the fixed tests, in order
        fx = np.stack([feats[f] for f in CANDIDATE_FEATURES], 1)
        for px, py in xy[passed]:
            near = [j for j, t in enumerate(item.markers)
                    if math.hypot(t.x - px, t.y - py) <= tolerance_px(t.radius_px)]
            y.append(bool(near))
            ids.append(n_markers + near[0] if near else -1)
        n_markers += len(item.markers)
        X.append(fx)
        if (i + 1) % 100 == 0 or i + 1 == len(ds.images):
            print(f"candidates of {i + 1}/{len(ds.images)} images: {sum(len(a) for a in X)}", file=sys.stderr)
    return np.concatenate(X), np.asarray(y, bool), np.asarray(ids)


def marker_keep(p: np.ndarray, y: np.ndarray, ids: np.ndarray, cut: float) -> tuple[float, float]:
    """(share of the markers with a candidate whose best candidate scores >= cut, share of the
    candidates off markers kept)."""
    best: dict[int, float] = {}
    for m, v in zip(ids[y], p[y]):
        best[int(m)] = max(best.get(int(m), 0.0), float(v))
    kept = float(np.mean([v >= cut for v in best.values()])) if best else 1.0
    return kept, float(np.mean(p[~y] >= cut))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=400)
    ap.add_argument("--seed", type=int, default=11)
    ap.add_argument("--data", default=None, help="existing dataset with train-split backgrounds")
    ap.add_argument("--keep", type=float, default=0.995, help="share of the candidates on markers to report the cut for")
    ap.add_argument("--out", default=str(RESULTS))
    args = ap.parse_args(argv)
    from sklearn.linear_model import LogisticRegression

    from cpdetect.classical import CANDIDATE_FEATURES
    from cpdetect.fileio import write_json_atomic

    ds = train_split_dataset(args.data, args.n, args.seed, "cpdetect_fit_cand_")
    root = ds.root
    X, y, ids = candidate_table(ds)
    mean, std = X.mean(0), X.std(0) + 1e-9
    clf = LogisticRegression(C=1.0, max_iter=5000, class_weight={0: 1.0, 1: 20.0}).fit((X - mean) / std, y)
    p = clf.predict_proba((X - mean) / std)[:, 1]
    cut = float(np.quantile(p[y], 1.0 - args.keep))
    kept_off = float(np.mean(p[~y] >= cut))
    fmt = lambda a: "np.array([" + ", ".join(f"{v:.5g}" for v in a) + "])"  # noqa: E731
    print(f"{len(y)} candidates ({int(y.sum())} on markers); cut {cut:.4g} keeps {args.keep:.3f} of those on markers "
          f"and {kept_off:.3f} of the others")
    print("_CAND_MEAN =", fmt(mean))
    print("_CAND_STD =", fmt(std))
    print("_CAND_W =", fmt(clf.coef_[0]))
    print("_CAND_B =", f"{clf.intercept_[0]:.5g}")
    print("per marker (each needs one candidate):")
    table = []
    for c in CUTS:
        mk, off = marker_keep(p, y, ids, c)
        table.append({"cut": c, "markers_kept": mk, "others_kept": off})
        print(f"cut {c:.2f}: markers kept {mk:.4f}, other candidates kept {off:.3f}")
    write_json_atomic(args.out, {"data": str(root), "images": len(ds.images), "candidates": int(len(y)),
                                 "on_markers": int(y.sum()), "keep": args.keep, "cut": cut,
                                 "others_kept": kept_off, "per_marker": table, "features": list(CANDIDATE_FEATURES),
                                 "mean": mean.tolist(), "std": std.tolist(), "weights": clf.coef_[0].tolist(),
                                 "bias": float(clf.intercept_[0])})
    return 0


if __name__ == "__main__":
    sys.exit(main())
