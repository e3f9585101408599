"""``cpdetect georef``: detect, localize, refine, triangulate, register and export (see cpdetect.pipeline)."""
from __future__ import annotations

import sys
from pathlib import Path

from .args import seed_arg


def register(sub) -> None:
    p = sub.add_parser("georef", help="georeference a reconstruction from the markers in its photos",
                       description="From per-image detections to surveyed, georeferenced control points, "
                                   "without being told which marker is which. Stages write files into "
                                   "OUT/stages/ and a rerun resumes.")
    p.add_argument("--reconstruction", required=True, type=Path,
                   help="COLMAP model folder (or another format cpdetect reads)")
    p.add_argument("--images", required=True, type=Path, help="folder of the reconstruction's images")
    p.add_argument("--gcps", required=True, type=Path, help="surveyed points (gcps.csv)")
    p.add_argument("--crs", help="CRS of the surveyed points when gcps.csv does not name it, e.g. EPSG:25832")
    p.add_argument("--cloud", type=Path, help="dense point cloud (PLY) in the model frame, for the cloud mode")
    p.add_argument("--mesh", type=Path, help="triangle mesh (PLY) in the model frame: depth tests, ray mode")
    p.add_argument("--detector", default="classical", help="detector name (default: classical)")
    p.add_argument("--detections", type=Path,
                   help="use these detections (cpdetect.detections/1, e.g. from 'cpdetect detect') instead of "
                        "running the detector")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="detector setting (repeatable)")
    p.add_argument("--rejects", type=Path, metavar="REJECTS.json",
                   help="detections a reviewer marked wrong in the review gallery of 'cpdetect compare' "
                        "(rejects.json): they are dropped, and so are observations measured within 3 px of one")
    p.add_argument("--workers", type=int, default=1,
                   help="worker processes of the detect stage (results identical to serial)")
    p.add_argument("--scheduler", metavar="ADDRESS",
                   help="run the detect stage on a Dask cluster (pip install 'cpdetect[dask]'), e.g. "
                        "tcp://host:8786; every worker must see the images at the same path. Overrides --workers")
    p.add_argument("--mode", default="auto", choices=["auto", "cloud", "ray", "triangulate"],
                   help="how markers are first placed in 3D: cloud colorization + DBSCAN, ray casting of "
                        "detections onto the mesh, or triangulation of detection pairs (default auto: cloud "
                        "when --cloud is given and the detector gives probability maps, plus ray when --mesh "
                        "is given, else triangulate)")
    p.add_argument("--adjust", action="store_true", help="also bundle-adjust poses (with priors) and markers")
    p.add_argument("--loss", default="huber", choices=["huber", "cauchy", "soft_l1", "linear"])
    p.add_argument("--noise", type=float, default=0.02,
                   help="per-axis survey + detection noise assumed by the registration, metres (default 0.02)")
    p.add_argument("--seed", type=seed_arg, default=0, help="seed of every random choice (default 0)")
    p.add_argument("--out", required=True, type=Path, help="output folder")
    p.set_defaults(func=run)


def run(args) -> int:
    from ..detector import check_settings, parse_settings
    from ..errors import UsageError
    from ..pipeline import GeorefInputs, GeorefSettings, run_georef
    from ..progress import iter_progress

    if args.workers < 1:
        raise UsageError("--workers must be >= 1")
    detector_settings = parse_settings(args.set)
    if args.detections is None:  # the detector is built late: a mistyped --set must fail before any work
        check_settings(args.detector, detector_settings)
    settings = GeorefSettings(detector=args.detector, detector_settings=detector_settings,
                              mode=args.mode, adjust=args.adjust, loss=args.loss,
                              registration_noise_m=args.noise, seed=args.seed)
    inputs = GeorefInputs(reconstruction=args.reconstruction, images=args.images, gcps=args.gcps, out=args.out,
                          crs=args.crs, cloud=args.cloud, mesh=args.mesh,
                          detections=args.detections, rejects=args.rejects)
    report = run_georef(inputs, settings, progress=iter_progress(), workers=args.workers,
                        scheduler=args.scheduler or None)
    print_summary(report, sys.stdout)
    return 0 if report["status"] == "ok" else 1


def print_summary(report: dict, fh) -> None:
    print(f"status: {report['status']}" + (f" ({report['reason']})" if report.get("reason") else ""), file=fh)
    print(f"markers: {report['n_markers']} found, {report['n_paired']} paired with "
          f"{report['n_surveyed']} surveyed points (mode {report['mode']}, detector {report['detector']})", file=fh)
    for m in report["markers"]:
        res = m["residual_m"]
        r = "" if res is None else f"  residual {1000 * sum(v * v for v in res) ** 0.5:.1f} mm"
        print(f"  {m['id']} -> {m['surveyed_name'] or '(none)':12s} views {m['n_views']:3d}  "
              f"reprojection rms {m['rms_px'] if m['rms_px'] is not None else float('nan'):.2f} px{r}", file=fh)
    if report["world_from_model"]:
        w = report["world_from_model"]
        print(f"world_from_model: scale {w['scale']:.6f}, translation "
              f"{', '.join(f'{v:.3f}' for v in w['translation'])}", file=fh)
    if report.get("rejects"):
        r = report["rejects"]
        print(f"rejects: {r['n_rejects']} from {r['file']}: {r['removed_detections']} detections and "
              f"{r['removed_observations']} measured views dropped", file=fh)
    if report.get("rms_m") is not None:
        print(f"residual RMS: {1000 * report['rms_m']:.1f} mm", file=fh)
