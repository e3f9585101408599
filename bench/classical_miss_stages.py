"""Why the ``classical`` detector missed markers: each miss of a ``cpdetect eval`` run put to the stage that lost it.

Reads the metrics JSON of ``cpdetect eval DIR --detector classical --out F`` (its per-image records
name the dataset, the settings and every missed true marker), runs the detector again on each image
with a miss, with the same settings and the same input (the file, or the decoded image where the
evaluation's ``input`` says "array"), and records where its scan left
every X-corner candidate (``ClassicalDetector.detect(image, trace=...)``, see
``cpdetect.classical._Scan``). Each missed marker gets the furthest stage reached by a candidate
within max(3 px, 0.35 radius) of its true centre:

- ``no candidate``: no X-corner candidate there (too weak, past the per-level cap, or none);
- ``prefilter: <reason>``: every candidate there was stopped by the prefilter (inner rings, candidate
  score), with the test its candidates failed first most often (``PREFILTER_REASONS`` of
  :mod:`cpdetect.classical`: rings leaving the image, not four sectors, a weak or turning four-sector
  pattern, low contrast, opposite sectors unlike, sectors not uniform, the candidate score);
- ``unverified``: past ``max_verified``;
- ``verify: <reason>``: the marker model does not fit (the most frequent reason among them);
- ``score``: verified, but scored under the cut; ``beside a found marker``: skipped near one;
- ``single saddle``, ``centre reach``, ``centre grey``, ``score after refinement``, ``tag grid``,
  ``tag lattice``, ``edges run on``: the tests after the verification, in the scan's order;
- ``held``: scored under the cut but held aside (``held_score``) and not added;
- ``kept``: a marker was found there, but not matched to this truth (too far off, or matched to
  another).

Writes the misses with their stage, the best score seen, and the truth's fields (radius, occlusion,
centre hidden, blur, contrast, tilt, margin, texture) as JSON, and prints the counts, split by
whether the marker is over 2 % covered and whether its centre is hidden.

    .venv/bin/python bench/classical_miss_stages.py EVAL_JSON [--out bench/results/classical_miss_stages.json]
"""
from __future__ import annotations

import math
import sys
from collections import Counter
from pathlib import Path

from detect_bench import COVERED_FRAC as COVERED  # the occluded share over which a marker counts as covered

RESULTS = Path(__file__).parent / "results" / "classical_miss_stages.json"
TRUTH_FIELDS = ("radius_px", "type", "centre_hidden", "occluded_frac", "blur_px", "contrast", "tilt_deg", "margin",
                "texture")
# furthest first: the order of the scan's tests (cpdetect.classical._Scan.run); "held" is a candidate
# scored under the cut and held aside (``held_score``), added after every pass unless beside a kept marker
ORDER = ("kept", "held", "edges run on", "tag lattice", "tag grid", "mixed-ray fit, centre unsure",
         "score after refinement", "centre grey", "centre reach", "single saddle", "beside a found marker", "score",
         "verify", "unverified", "prefilter")


def near_radius(radius_px: float) -> float:
    """How far (pixels) from a true centre a candidate still counts as that marker's."""
    return max(3.0, 0.35 * float(radius_px))


def stage_of(trace: list[dict], truth: dict) -> dict:
    """The furthest stage the candidates near ``truth`` (x, y, radius_px) reached in ``trace``
    (the dicts of ``ClassicalDetector.detect(..., trace=)``), with their count and best score."""
    near = [t for t in trace if math.hypot(t["x"] - truth["x"], t["y"] - truth["y"]) <= near_radius(truth["radius_px"])]
    if not near:
        return {"stage": "no candidate", "candidates": 0}
    rank = {s: i for i, s in enumerate(ORDER)}
    best = min(rank[t["stage"].split(":")[0]] for t in near)
    stage = ORDER[best]
    if stage in ("verify", "prefilter"):
        stage = Counter(t["stage"] for t in near if t["stage"].startswith(stage)).most_common(1)[0][0]
    scores = [t["score"] for t in near if "score" in t]
    return {"stage": stage, "candidates": len(near), "best_score": max(scores) if scores else None}


def main(argv=None) -> int:
    from eval_misses import arguments, images_with_misses, read_eval

    ap = arguments(__doc__, "classical", RESULTS)
    args = ap.parse_args(argv)

    from cpdetect.classical import ClassicalDetector
    from cpdetect.errors import InputError
    from cpdetect.fileio import write_json_atomic
    from cpdetect.imageio import read_image

    got = read_eval(args.eval_json, "classical")
    if got is None:
        return 2
    ev, ds = got
    try:
        det = ClassicalDetector(**(ev.get("settings") or {}))
    except (InputError, ValueError, TypeError) as exc:
        print(f"error: {args.eval_json}: {exc}", file=sys.stderr)
        return 2
    rows = []
    try:
        for rec, item in images_with_misses(ev, ds):
            trace: list[dict] = []
            # the same input as the evaluation: the file (its reduced decode), or the decoded image
            # where it ran on arrays (as every evaluation before stop 68 did, whose JSON has no "input")
            path = ds.image_path(item)
            det.detect(read_image(path) if ev.get("input", "array") == "array" else path, trace=trace)
            for m in rec["missed"]:
                row = {"file": rec["file"], "x": m["x"], "y": m["y"], **{k: m.get(k) for k in TRUTH_FIELDS}}
                row.update(stage_of(trace, m))
                rows.append(row)
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    counts = Counter(r["stage"] for r in rows)
    covered = Counter(r["stage"] for r in rows if (r.get("occluded_frac") or 0.0) > COVERED)
    hidden = Counter(r["stage"] for r in rows if r.get("centre_hidden"))
    report = {"eval": str(args.eval_json), "dataset": ev["dataset"], "settings": ev.get("settings") or {},
              "missed": len(rows),
              "stages": {k: {"missed": n, "covered": covered.get(k, 0), "centre_hidden": hidden.get(k, 0)}
                         for k, n in counts.most_common()},
              "misses": rows}
    write_json_atomic(args.out, report)
    print(f"{len(rows)} missed markers ({sum(covered.values())} over {COVERED:.0%} covered, "
          f"{sum(hidden.values())} with the centre hidden by an occluder)")
    for k, n in counts.most_common():
        print(f"  {k:44s} {n:4d}   covered {covered.get(k, 0):3d}   centre hidden {hidden.get(k, 0):3d}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
