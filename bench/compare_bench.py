"""Benchmark of ``cpdetect compare``: the detectors that load, on a synthetic marker dataset and on a
synthetic site, with the figures the comparison reports and the time it takes to write the report.

Usage: python bench/compare_bench.py OUT.json [--detectors classical,hma] [--work /tmp/compare_bench]
       [--n 30] [--images 24] [--size 1024x683] [--seed 0]

Detectors that cannot be built (e.g. hma without trained weights) are listed under "skipped" with the
reason. Figures: dataset mode F1, recall, precision, instance AP, median centre error, s/MP per detector;
site mode markers paired, residual RMS, detection seconds; the recommendation of each mode; report sizes.
"""
from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", type=Path)
    ap.add_argument("--detectors", default="classical,hma")
    ap.add_argument("--work", type=Path, default=Path("/tmp/compare_bench"))
    ap.add_argument("--n", type=int, default=30, help="dataset images")
    ap.add_argument("--images", type=int, default=24, help="site images")
    ap.add_argument("--size", default="1024x683", help="site image size")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()

    from cpdetect.cli import main as cli
    from cpdetect.compare import compare_dataset, compare_site, find_site
    from cpdetect.compare_report import summary_dict, write_outputs
    from cpdetect.detector import get_detector
    from cpdetect.errors import CpdetectError

    names, skipped = [], {}
    for n in [s.strip() for s in args.detectors.split(",") if s.strip()]:
        try:
            get_detector(n)
            names.append(n)
        except CpdetectError as exc:
            skipped[n] = str(exc)
    result = {"machine": platform.platform(), "detectors": names, "skipped": skipped,
              "settings": {k: str(v) for k, v in vars(args).items()}}
    work = args.work
    ds, site = work / "dataset", work / "site"
    if not (ds / "markers.json").is_file():
        cli(["-q", "synth", "images", "--out", str(ds), "--n", str(args.n), "--seed", str(args.seed),
             "--split", "test"])
    if not (site / "truth.json").is_file():
        cli(["-q", "synth", "scene", "--out", str(site), "--seed", str(args.seed), "--images", str(args.images),
             "--size", args.size, "--overwrite"])

    t0 = time.perf_counter()
    cmp = compare_dataset(ds, {n: get_detector(n) for n in names})
    t1 = time.perf_counter()
    paths = write_outputs(cmp, work / "report_dataset")
    t2 = time.perf_counter()
    s = summary_dict(cmp)
    result["dataset"] = {
        "images": cmp.n_images, "markers": cmp.n_markers, "seconds_compare": round(t1 - t0, 2),
        "seconds_report": round(t2 - t1, 2), "report_bytes": paths["html"].stat().st_size,
        "recommendation": s["recommendation"],
        "results": {n: {k: r[k] for k in ("f1", "recall", "precision", "instance_ap", "centre_error_px",
                                          "seconds_per_megapixel", "pixel")}
                    for n, r in s["results"].items()}}

    t0 = time.perf_counter()
    cmp = compare_site(find_site(site), names, work / "report_site")
    t1 = time.perf_counter()
    paths = write_outputs(cmp, work / "report_site")
    t2 = time.perf_counter()
    s = summary_dict(cmp)
    result["site"] = {
        "images": args.images, "size": args.size, "surveyed": s["n_surveyed"], "seconds_compare": round(t1 - t0, 2),
        "seconds_report": round(t2 - t1, 2), "report_bytes": paths["html"].stat().st_size,
        "recommendation": s["recommendation"],
        "results": {n: {k: r[k] for k in ("status", "mode", "n_markers", "n_paired", "rms_m", "seconds_detect")}
                    for n, r in s["results"].items()},
        "images_disagreeing": len(s["images_disagreeing"])}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1) + "\n")
    print(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
