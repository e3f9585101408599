"""Choose the ``hma`` detector's ``classical_min_support``: the network's veto on the classical markers
that ``classical_markers`` adds.

On datasets with *train*-split backgrounds only (generated when ``--data`` has none), runs the network
once per image (probability maps cached in DATA/probability_maps, shared with the other fit_hma_*
scripts), the instance step as the detector runs it, and the classical detector; lists every classical
marker the union would add with its network support (mean P(marker) over its classical outline, see
``learned.adapter._network_support``) and whether a true marker lies there (cpdetect.evaluate.
tolerance_px); then, for each cut, the markers kept, true and false. The interval of cuts with the
best marker count (true - false) goes to bench/results/fit_classical_support.json, with the pixel IoU
of the map after the instance step under both rules of clearing rejected blobs: the network's
sureness alone, and the union's (a classical marker must lie on the blob). Nothing is written
into the model folder: the setting's default is chosen by hand from the interval.

    .venv/bin/python bench/fit_classical_support.py --data /work/runs/dev808 --data /work/runs/dev909
"""
from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

from fit_hma_instances import probability_maps
from train_split import train_split_dataset

RESULTS = Path(__file__).parent / "results" / "fit_classical_support.json"


def added_markers(det, classical, ds, maps, pixels: dict) -> list[dict]:
    """Every classical marker the union would add on ``ds``: its support, score, radius and truth.
    ``pixels``: per rule of clearing the map ("network": the network's sureness, "witnessed": the
    union's, a classical marker on the blob), the :class:`cpdetect.evaluate.PixelCounts` of the map
    after the instance step, added to in place (images with a mask only)."""
    from cpdetect.dataset import read_mask
    from cpdetect.evaluate import PixelCounts, tolerance_px
    from cpdetect.types import DetectionResult
    from cpdetect.imageio import read_image
    from learned.adapter import _network_support, _with_classical_markers

    rows = []
    for item, (prob, f) in zip(ds.images, maps):
        path = ds.image_path(item)
        gray = read_image(path, gray=True)
        dets, cleared = det._instances(gray, prob, f)
        theirs = classical.detect(str(path))
        if item.mask:
            truth = read_mask(ds.root / item.mask, gray.shape)
            _, witnessed = det._instances(gray, prob, f, None, theirs.detections)
            h, w = truth.shape
            for rule, m in (("network", cleared), ("witnessed", witnessed)):
                pixels.setdefault(rule, PixelCounts()).add(DetectionResult([], (w, h), m).probability_at(w, h), truth)
        union, _ = _with_classical_markers(dets, cleared, f, theirs)
        tmap = theirs.probability_at(prob.shape[1], prob.shape[0])
        for m in union[len(dets):]:
            dist = min((math.hypot(t.x - m.x, t.y - m.y) / tolerance_px(t.radius_px) for t in item.markers),
                       default=math.inf)
            rows.append({"file": f"{ds.root}/{item.file}", "x": m.x, "y": m.y, "radius_px": m.radius_px,
                         "score": m.score, "true": bool(dist <= 1.0),
                         "support": _network_support(prob, tmap, f, m)})
    return rows


def cut_table(rows: list[dict]) -> list[dict]:
    """Markers kept, true and false, at each cut between consecutive supports (and 0)."""
    sup = sorted({r["support"] for r in rows})
    cuts = [0.0] + [0.5 * (a + b) for a, b in zip(sup, sup[1:])] + ([sup[-1] + 1e-6] if sup else [])
    out = []
    for c in cuts:
        kept = [r for r in rows if r["support"] >= c]
        tp = sum(r["true"] for r in kept)
        out.append({"cut": c, "true": tp, "false": len(kept) - tp})
    return out


def best_interval(rows: list[dict], table: list[dict]) -> dict:
    """The cuts with the largest true - false (ties: fewer false), as [lo, hi): lo the largest support
    they drop, hi the smallest they keep."""
    best = max(table, key=lambda t: (t["true"] - t["false"], -t["false"]))
    dropped = [r["support"] for r in rows if r["support"] < best["cut"]]
    kept = [r["support"] for r in rows if r["support"] >= best["cut"]]
    return {"above": max(dropped, default=0.0), "up_to": min(kept, default=math.inf),
            "true": best["true"], "false": best["false"]}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model-dir", default=None, help="network folder (default: the shipped one)")
    ap.add_argument("--data", action="append", default=None,
                    help="existing dataset with train-split backgrounds (repeatable)")
    ap.add_argument("--n", type=int, default=300)
    ap.add_argument("--seed", type=int, default=808)
    ap.add_argument("--out", default=str(RESULTS))
    args = ap.parse_args(argv)
    for data in args.data or []:
        if not Path(data).is_dir():
            print(f"{data}: no such dataset folder", file=sys.stderr)
            return 2

    from cpdetect.classical import ClassicalDetector
    from learned.adapter import HMADetector, default_model_dir

    model_dir = Path(args.model_dir) if args.model_dir else default_model_dir()
    t0 = time.time()
    det = HMADetector(model_dir=str(model_dir))
    classical = ClassicalDetector(probability_map=True)
    rows, roots, pixel_iou = [], [], {}
    for data in args.data or [None]:
        ds = train_split_dataset(data, args.n, args.seed, "cpdetect_fit_support_")
        roots.append(str(ds.root))
        maps = probability_maps(det, ds, ds.root / "probability_maps")
        pixels: dict = {}
        rows += added_markers(det, classical, ds, maps, pixels)
        pixel_iou[str(ds.root)] = {rule: counts.metrics()["iou"] for rule, counts in pixels.items()}
    table = cut_table(rows)
    best = best_interval(rows, table)
    report = {"model_dir": str(model_dir), "data": roots, "added": len(rows),
              "added_true": sum(r["true"] for r in rows), "best": best, "cuts": table,
              "pixel_iou_after_instances": pixel_iou, "markers": rows, "seconds": time.time() - t0}
    from cpdetect.fileio import write_json_atomic

    write_json_atomic(args.out, report)
    print(f"{len(rows)} classical markers added by the union, {report['added_true']} of them true")
    for root, iou in pixel_iou.items():
        print(f"{root}: pixel IoU of the map after the instance step, blobs cleared by the network's "
              f"sureness {iou.get('network', math.nan):.4f}, unless a classical marker lies on them "
              f"{iou.get('witnessed', math.nan):.4f}")
    print(f"best cut: any in ({best['above']:.4f}, {best['up_to']:.4f}]: {best['true']} true and "
          f"{best['false']} false kept; figures in {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
