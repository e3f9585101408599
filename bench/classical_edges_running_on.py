"""How many sector edges of the ``classical`` detector's markers run on past their outlines, true and false.

Reads the metrics JSON of ``cpdetect eval DIR --detector classical --out F``, runs the detector again
on every image with the same settings and input plus ``max_edges_running_on=5`` (measured, never
dropped: :func:`cpdetect.checker_lines.edges_running_on`), and counts the gray-pass markers kept by
the number of their edges running on (0-4), split into true markers and false ones. A kept marker is
false where the evaluation has a false marker within max(3 px, 0.3 radius) of its candidate.
This is how the setting's cut (4) was chosen on stop 79's seen sets (46000, 46200-47100: 9,419 true,
67 false; four edges: 0 true, 4 false). Writes the counts and every marker with 3 or 4 edges.

    .venv/bin/python bench/classical_edges_running_on.py EVAL_JSON [--out bench/results/classical_edges_running_on.json]
"""
from __future__ import annotations

import math
import sys
from pathlib import Path

RESULTS = Path(__file__).parent / "results" / "classical_edges_running_on.json"


def is_false(row: dict, false_markers: list[dict]) -> bool:
    """Whether the trace ``row`` (a kept candidate) lies on one of the evaluation's false markers."""
    return any(math.hypot(f["x"] - row["x"], f["y"] - row["y"]) < max(3.0, 0.3 * f["radius_px"]) for f in false_markers)


def main(argv=None) -> int:
    from eval_misses import arguments, read_eval

    args = arguments(__doc__, "classical", RESULTS).parse_args(argv)

    from cpdetect.classical import ClassicalDetector
    from cpdetect.errors import InputError
    from cpdetect.fileio import write_json_atomic
    from cpdetect.imageio import read_image

    got = read_eval(args.eval_json, "classical")
    if got is None:
        return 2
    ev, ds = got
    try:
        det = ClassicalDetector(**{**(ev.get("settings") or {}), "max_edges_running_on": 5})
    except (InputError, ValueError, TypeError) as exc:
        print(f"error: {args.eval_json}: {exc}", file=sys.stderr)
        return 2
    items = {it.file: it for it in ds.images}
    counts = {"true": [0] * 5, "false": [0] * 5}
    listed = []
    try:
        for rec in ev["per_image"]:
            item = items.get(rec["file"])
            if item is None:
                raise InputError("not in the dataset the metrics name", Path(ev["dataset"]) / rec["file"])
            trace: list[dict] = []
            path = ds.image_path(item)
            det.detect(read_image(path) if ev.get("input", "array") == "array" else path, trace=trace)
            for t in trace:
                if t["stage"] != "kept" or t["pass"] != "gray":
                    continue
                false = is_false(t, rec["false_positives"])
                counts["false" if false else "true"][t["edges"]] += 1
                if t["edges"] >= 3:
                    listed.append({"file": rec["file"], "x": t["x"], "y": t["y"], "radius_px": t["radius_px"],
                                   "type": t["type"], "score": t["score"], "edges": t["edges"], "false": false})
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    report = {"eval": str(args.eval_json), "dataset": ev["dataset"], "settings": ev.get("settings") or {},
              "kept_by_edges_running_on": counts, "three_or_four": listed}
    write_json_atomic(args.out, report)
    for k in ("true", "false"):
        print(f"{k:5s} markers kept, by edges running on 0-4: {counts[k]}")
    for r in listed:
        print(f"  {r['file']} ({r['x']:.0f}, {r['y']:.0f}) {r['type']} {r['radius_px']:.0f} px: {r['edges']} edges"
              f"{', false' if r['false'] else ''}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
