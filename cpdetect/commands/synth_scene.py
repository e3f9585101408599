"""``cpdetect synth scene``: render a synthetic bridge-pier survey site with known truth."""
from __future__ import annotations

import argparse
import logging
import re

from ..errors import UsageError
from .args import seed_arg

log = logging.getLogger(__name__)


def _size(text: str) -> tuple[int, int]:
    m = re.fullmatch(r"\s*(\d+)\s*[xX]\s*(\d+)\s*", text)
    if not m:
        raise UsageError(f"--size must look like WIDTHxHEIGHT (e.g. 1024x683), got {text!r}")
    return int(m.group(1)), int(m.group(2))


def register(kinds) -> None:
    p = kinds.add_parser(
        "scene", help="a synthetic bridge-pier site: images, COLMAP model, dense cloud, mesh, GCPs, truth",
        description="Render a drone survey of a synthetic bridge-pier segment with checkerboard markers and "
                    "write images/, sparse/ (COLMAP text, model frame), fused.ply, mesh.ply, gcps.csv "
                    "(surveyed centres in the CRS) and truth.json (written last). See docs/formats.md, "
                    "'Synthetic sites'.")
    p.add_argument("--out", required=True, help="output folder (created; must be new or empty unless "
                                                "--overwrite)")
    p.add_argument("--seed", type=seed_arg, default=0, help="random seed; a seed always gives the same site")
    p.add_argument("--images", type=int, default=48, help="number of images (default 48)")
    p.add_argument("--size", default="1024x683", help="image size WIDTHxHEIGHT (default 1024x683; "
                                                      "8192x5460 is the paper's camera)")
    p.add_argument("--markers", type=int, default=9, help="printed and surveyed markers (default 9, >= 3)")
    p.add_argument("--missing-markers", type=int, default=0,
                   help="surveyed points (in gcps.csv) whose marker was never printed")
    p.add_argument("--unsurveyed-markers", type=int, default=0,
                   help="extra printed markers that are not in gcps.csv")
    p.add_argument("--hidden-surveyed", type=int, default=0,
                   help="surveyed, printed markers placed where no camera sees them")
    p.add_argument("--noise", action=argparse.BooleanOptionalAction, default=True,
                   help="photometric effects and cloud noise (--no-noise: clean images, exact cloud)")
    p.add_argument("--distortion", action=argparse.BooleanOptionalAction, default=True,
                   help="lens distortion (--no-distortion)")
    p.add_argument("--pose-noise", type=float, default=0.0,
                   help="sigma in metres of the camera centres written to sparse/ (rotation sigma "
                        "pose-noise/2 m radians); default 0: true poses")
    p.add_argument("--survey-sigma", type=float, default=0.003, help="GCP survey noise sigma per axis (m)")
    p.add_argument("--cloud-spacing", type=float, default=0.008, help="dense cloud point spacing (m)")
    p.add_argument("--supersample", type=int, default=6, help="sub-samples per axis at edges (default 6)")
    p.add_argument("--backgrounds", choices=("all", "train", "test"), default="all",
                   help="background split used for textures")
    p.add_argument("--overwrite", action="store_true", help="replace an existing non-empty --out folder")
    p.set_defaults(func=run)


def run(args) -> int:
    from ..synth_scene import SiteSettings, write_site

    width, height = _size(args.size)
    settings = SiteSettings(seed=args.seed, n_images=args.images, width=width, height=height,
                            markers=args.markers, unsurveyed_markers=args.unsurveyed_markers,
                            missing_markers=args.missing_markers, hidden_surveyed=args.hidden_surveyed,
                            noise=args.noise, distortion=args.distortion, pose_noise=args.pose_noise,
                            survey_sigma=args.survey_sigma, cloud_spacing=args.cloud_spacing,
                            supersample=args.supersample, backgrounds=args.backgrounds)
    settings.check()
    from ..progress import counter

    with counter(settings.n_images, unit="img", desc="rendering") as update:
        report = write_site(args.out, settings, overwrite=args.overwrite, progress=update)
    secs = report.seconds
    log.info("wrote %s: %d images, %d dense points, marker views %s; %.1f s (build %.1f, render %.1f, "
             "cloud/mesh/sparse %.1f)", report.out_dir, report.n_images, report.n_cloud_points,
             report.visible_counts, sum(secs.values()), secs.get("build", 0), secs.get("render", 0),
             secs.get("cloud_mesh_sparse", 0))
    return 0
