"""bench/fit_score.py's row collection (what the shipped score and type trees are fitted on) runs
through the detector as it is now: its spies must keep up with the functions they wrap."""
from __future__ import annotations

from bench_loader import load_bench

import cpdetect.classical as C
from cpdetect.synth_images import SynthImageOptions, write_synth_images


def test_fit_score_collects_rows_with_every_score_feature(tmp_path):
    fit_score = load_bench("fit_score")
    opts = SynthImageOptions(split="train", width=320, height=240, markers=(2, 3), empty_prob=0.0)
    write_synth_images(tmp_path / "train", 3, 7, opts, workers=1)
    rows = fit_score._verified_rows_of(str(tmp_path / "train"))
    assert sum(r["label"] for r in rows) >= 3  # most of the 6-9 markers have a verified candidate
    for r in rows:
        assert set(C.SCORE_FEATURES) <= set(r)
        if r["label"]:
            # what bench/fit_type.py reads: the true type and the inputs of the type decision
            assert r["true_type"] in ("circle", "diagonal", "square") and "typein" in r
    # the spies are taken out again
    assert C._Verifier.verify.__name__ == "verify" and C._type_of.__name__ == "_type_of"
    assert C.marker_score.__name__ == "marker_score"
