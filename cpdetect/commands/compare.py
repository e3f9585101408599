"""``cpdetect compare``: compare detectors on an annotated dataset or on a site, with a recommendation.

Writes REPORT_DIR/report.html (self-contained), REPORT_DIR/summary.json and REPORT_DIR/summary.md; in
site mode, each detector's georef run goes to REPORT_DIR/runs/<detector>/ (a rerun resumes).
"""
from __future__ import annotations

import sys
from pathlib import Path

from ..errors import UsageError
from .args import seed_arg


def register(sub) -> None:
    p = sub.add_parser(
        "compare", help="compare detectors on a dataset or a site and recommend one",
        description="Compare detectors. On an annotated dataset (a folder with markers.json): instance and "
                    "pixel metrics, centre error, speed, broken down by marker type, size, blur and "
                    "background. On a site (images/, sparse/, gcps.csv, optional mesh.ply and fused.ply): each "
                    "detector through the georef back end, pairings, residuals, agreement, run time. "
                    "Writes report.html (with a review gallery), summary.json and summary.md.")
    p.add_argument("input", type=Path, metavar="SITE_OR_DATASET", help="site folder or dataset folder")
    p.add_argument("--detectors", required=True, help="comma-separated detector names, e.g. classical,hma")
    p.add_argument("--set", action="append", default=[], metavar="DETECTOR.KEY=VALUE",
                   help="a setting of one detector, e.g. classical.min_score=0.4 (repeatable)")
    p.add_argument("--out", type=Path, default=Path("cpdetect-compare"),
                   help="report folder (default ./cpdetect-compare)")
    p.add_argument("--limit", type=int, help="dataset mode: only the first N images")
    g = p.add_argument_group("site mode (defaults: the files of a 'cpdetect synth scene' folder)")
    g.add_argument("--reconstruction", type=Path, help="reconstruction (default SITE/sparse)")
    g.add_argument("--images", type=Path, help="image folder (default SITE/images)")
    g.add_argument("--gcps", type=Path, help="surveyed points CSV (default SITE/gcps.csv)")
    g.add_argument("--mesh", type=Path, help="mesh PLY (default SITE/mesh.ply when present)")
    g.add_argument("--cloud", type=Path, help="dense cloud PLY (default SITE/fused.ply when present)")
    g.add_argument("--no-cloud", action="store_true", help="do not use SITE/fused.ply")
    g.add_argument("--crs", help="CRS of the surveyed points when gcps.csv does not name it")
    g.add_argument("--mode", default="auto", choices=["auto", "cloud", "ray", "triangulate"],
                   help="georef localisation mode (default auto)")
    g.add_argument("--seed", type=seed_arg, default=0)
    g.add_argument("--rejects", type=Path, metavar="REJECTS.json",
                   help="detections marked wrong in an earlier report's review gallery (rejects.json): "
                        "every detector's georef run drops them")
    p.add_argument("--no-gallery", action="store_true", help="leave the crop gallery out of the HTML report")
    p.add_argument("--screenshot", action="store_true",
                   help="also save REPORT_DIR/report.png, rendered by headless chromium")
    p.set_defaults(func=run)


def split_settings(pairs: list[str], names: list[str]) -> dict[str, dict]:
    """``["classical.min_score=0.4"]`` -> ``{"classical": {"min_score": 0.4}}`` (values as JSON when
    they parse); raises UsageError for a pair without a listed detector prefix."""
    from ..detector import parse_settings

    out: dict[str, dict] = {n: {} for n in names}
    for pair in pairs:
        key = pair.partition("=")[0]
        det, dot, rest = key.partition(".")
        if not dot or det not in out or not rest:
            raise UsageError(f"--set {pair!r}: expected DETECTOR.KEY=VALUE with DETECTOR one of "
                             f"{', '.join(names)}")
        out[det].update(parse_settings([pair[len(det) + 1:]]))
    return out


def run(args) -> int:
    from .. import compare as cmp_mod
    from ..compare_report import write_outputs
    from ..detector import check_settings, get_detector
    from ..progress import iter_progress

    names = cmp_mod.parse_detector_names(args.detectors)
    settings = split_settings(args.set, names)
    for n in names:  # a mistyped setting fails before the inputs are even looked at
        check_settings(n, settings[n])
    if not args.input.exists():
        from ..errors import InputError

        raise InputError("site or dataset folder not found", args.input)
    if args.rejects is not None:
        if cmp_mod.is_dataset_folder(args.input):
            raise UsageError("--rejects applies to a site, not to an annotated dataset")
        from ..html_report import read_rejects

        read_rejects(args.rejects)  # a bad file fails before any run
    if cmp_mod.is_dataset_folder(args.input):
        from ..dataset import load_dataset

        dataset = load_dataset(args.input)
        detectors = {n: get_detector(n, **settings[n]) for n in names}
        result = cmp_mod.compare_dataset(dataset, detectors, limit=args.limit, progress=iter_progress())
    else:
        from ..pipeline import GeorefSettings

        inputs = cmp_mod.find_site(args.input, reconstruction=args.reconstruction, images=args.images,
                                   gcps=args.gcps, mesh=args.mesh, cloud=args.cloud, crs=args.crs,
                                   use_cloud=not args.no_cloud)
        for n in names:  # fail on a bad setting or a detector that cannot load before any long run
            get_detector(n, **settings[n])
        result = cmp_mod.compare_site(inputs, names, args.out, settings,
                                      GeorefSettings(mode=args.mode, seed=args.seed), progress=iter_progress(),
                                      rejects=args.rejects)
    paths = write_outputs(result, args.out, gallery=not args.no_gallery)
    rec = result.recommendation
    print(f"recommendation: {rec.choice or 'none'}" + (" (insufficient evidence)" if rec.insufficient else ""))
    for line in rec.reasons:
        print(f"  {line}")
    for p in paths.values():
        print(f"wrote {p}")
    if args.screenshot:
        from ..browser import find_chromium, screenshot

        if find_chromium() is None:
            print("no chromium found: screenshot skipped", file=sys.stderr)
        else:
            print(f"wrote {screenshot(paths['html'], Path(args.out) / 'report.png')}")
    return 0
