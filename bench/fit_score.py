"""Fit the classical detector's marker score (a logistic model over its verification features).

Generates images with *train*-split backgrounds only, runs the classical detector with the score
disabled (every verified candidate kept), labels each verified candidate by the true markers
(cpdetect.evaluate.tolerance_px), fits a logistic regression, and prints the constants to paste into
cpdetect/classical.py (_SCORE_MEAN, _SCORE_STD, _SCORE_W, _SCORE_B). Writes the feature table to
bench/results/score_features.json.

    .venv/bin/python bench/fit_score.py --n 150 --seed 11
"""
from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np
from train_split import train_split_dataset


def main(argv=None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, default=150)
    ap.add_argument("--seed", type=int, default=11)
    ap.add_argument("--data", default=None, help="existing train-split dataset folder")
    args = ap.parse_args(argv)
    import cv2
    from sklearn.linear_model import LogisticRegression

    import cpdetect.classical as C
    from cpdetect.evaluate import tolerance_px

    ds = train_split_dataset(args.data, args.n, args.seed, "cpdetect_fit_")
    rows = []
    orig = C._Verifier.verify

    def spy(self, *a):
        r = orig(self, *a)
        if not isinstance(r, str):
            rows.append(dict(self.last_features, x=r.x, y=r.y, file=cur[0]))
        return r

    C._Verifier.verify = spy
    det = C.ClassicalDetector(min_score=0.0)
    cur = [""]
    for k, item in enumerate(ds.images):
        cur[0] = item.file
        n0 = len(rows)
        det.detect(cv2.imread(str(ds.image_path(item)), cv2.IMREAD_GRAYSCALE))
        for r in rows[n0:]:
            d = [math.hypot(t.x - r["x"], t.y - r["y"]) <= tolerance_px(t.radius_px) for t in item.markers]
            r["label"] = int(any(d))
        print(f"\r{k + 1}/{len(ds.images)} rows {len(rows)}", end="", file=sys.stderr)
    print(file=sys.stderr)
    C._Verifier.verify = orig
    X = np.array([[r[f] for f in C.SCORE_FEATURES] for r in rows], float)
    y = np.array([r["label"] for r in rows])
    mean, std = X.mean(0), X.std(0) + 1e-9
    clf = LogisticRegression(C=1.0, class_weight={0: 3.0, 1: 1.0}, max_iter=2000).fit((X - mean) / std, y)
    p = clf.predict_proba((X - mean) / std)[:, 1]
    for t in (0.3, 0.5, 0.7):
        print(f"threshold {t}: kept positives {np.mean(p[y == 1] >= t):.3f}, kept negatives {np.sum(p[y == 0] >= t)} "
              f"of {np.sum(y == 0)}")
    fmt = lambda a: "np.array([" + ", ".join(f"{v:.5g}" for v in a) + "])"
    print("_SCORE_MEAN =", fmt(mean))
    print("_SCORE_STD =", fmt(std))
    print("_SCORE_W =", fmt(clf.coef_[0]))
    print("_SCORE_B =", f"{clf.intercept_[0]:.5g}")
    out = Path(__file__).parent / "results" / "score_features.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"features": list(C.SCORE_FEATURES), "rows": rows}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
