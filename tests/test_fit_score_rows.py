"""bench/fit_score.py's row collection (what the shipped score and type trees are fitted on) runs
through the detector as it is now: its spies must keep up with the functions they wrap."""
from __future__ import annotations

import importlib
import sys

from bench_loader import BENCH

import cpdetect.classical as C
from cpdetect.synth_images import SynthImageOptions, write_synth_images


def _rows(rows):
    """The rows as comparable tuples (the type inputs' arrays left out; NaN, a patch ring outside the
    image, as a string so that it equals itself)."""
    return [tuple((k, "nan" if v != v else v) for k, v in sorted(r.items()) if k != "typein") for r in rows]


def test_fit_score_collects_rows_with_every_score_feature(tmp_path):
    # imported by name (not executed afresh): the worker processes find its functions the same way
    if str(BENCH) not in sys.path:
        sys.path.insert(0, str(BENCH))
    fit_score = importlib.import_module("fit_score")
    opts = SynthImageOptions(split="train", width=320, height=240, markers=(2, 3), empty_prob=0.0)
    write_synth_images(tmp_path / "train", 4, 7, opts, workers=1)
    rows = fit_score._verified_rows_of(str(tmp_path / "train"))
    assert sum(r["label"] for r in rows) >= 4  # most of the 8-12 markers have a verified candidate
    # shared among processes, the same rows in the same order
    assert _rows(fit_score._verified_rows_of(str(tmp_path / "train"), workers=2)) == _rows(rows)
    for r in rows:
        assert set(C.SCORE_FEATURES) <= set(r) and set(C.PATCH_FEATURES) <= set(r)  # what the shipped trees read
        if r["label"]:
            # what bench/fit_type.py reads: the true type and the inputs of the type decision
            assert r["true_type"] in ("circle", "diagonal", "square") and "typein" in r
    # on markers the patch's ring at 0.3 radii shows dark sectors (near 0) and bright ones (near 1)
    rings = [[r[f"patch_1_{j}"] for j in range(C.PATCH_ANGLES)] for r in rows if r["label"]]
    shows = [min(v) < 0.25 and max(v) > 0.75 for v in rings if all(x == x for x in v)]
    assert len(shows) >= 4 and sum(shows) >= 0.8 * len(shows)
    # the spies are taken out again
    assert C._Verifier.verify.__name__ == "verify" and C._type_of.__name__ == "_type_of"
    assert C.marker_score.__name__ == "marker_score"
