"""Benchmark of ``cpdetect synth scene``: run time of the default site, time of one 8192 x 5460 image,
and how well the written COLMAP model projects the true marker centres onto the rendered ones.

Usage: python bench/synth_scene_bench.py OUT.json [--work /tmp/synth_bench] [--skip-big]

Projection error: for every marker seen at <= 60 degrees from its normal with a projected radius >= 15 px,
the true model-frame centre is projected through the written sparse/ model (read back with pycolmap,
shifted from COLMAP's pixel convention by -0.5) and compared with the X-corner measured on the
rendered image by :func:`cpdetect.synth_render.fit_xcorner` (on the float render, and on the JPEG).
"""
from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

import cv2
import numpy as np


def projection_errors(folder: Path, settings, max_angle: float = 60.0, min_radius: float = 15.0) -> dict:
    import pycolmap

    from cpdetect.synth_render import fit_xcorner
    from cpdetect.synth_scene import build_site

    truth = json.loads((folder / "truth.json").read_text())
    rec = pycolmap.Reconstruction()
    rec.read_text(str(folder / "sparse"))
    by_name = {im.name: im for im in rec.images.values()}
    site = build_site(settings)
    poses = dict(site.poses)
    centers = {m["name"]: np.array(m["center_model"]) for m in truth["markers"]}
    out = {"float": [], "jpeg": [], "all_angles_float": []}
    w, h = settings.width, settings.height
    for im in truth["images"]:
        marks = [mk for mk in im["markers"] if mk["radius_px"] >= min_radius]
        if not marks:
            continue
        img = site.renderer.render(site.camera, poses[im["name"]]).mean(axis=2)
        jpg = cv2.imread(str(folder / "images" / im["name"]), cv2.IMREAD_COLOR)[..., ::-1].mean(axis=2) / 255.0
        for mk in marks:
            uv = np.asarray(by_name[im["name"]].project_point(centers[mk["name"]])) - 0.5
            rad = 0.35 * mk["radius_px"]
            if not (rad + 2 < uv[0] < w - rad - 3 and rad + 2 < uv[1] < h - rad - 3):
                continue
            e_float = float(np.hypot(*(fit_xcorner(img, uv + [0.8, -0.6], rad) - uv)))
            out["all_angles_float"].append(e_float)
            if mk["view_angle_deg"] <= max_angle:
                out["float"].append(e_float)
                out["jpeg"].append(float(np.hypot(*(fit_xcorner(jpg, uv + [0.8, -0.6], rad) - uv))))

    def summary(v):
        v = np.asarray(v)
        return {"n": int(len(v)), "median_px": float(np.median(v)), "p90_px": float(np.percentile(v, 90)),
                "max_px": float(v.max())} if len(v) else {"n": 0}

    return {k: summary(v) for k, v in out.items()}


def main() -> None:
    from cpdetect.synth_scene import SiteSettings, build_site, write_site

    ap = argparse.ArgumentParser()
    ap.add_argument("out")
    ap.add_argument("--work", default="/tmp/synth_bench")
    ap.add_argument("--skip-big", action="store_true")
    args = ap.parse_args()
    work = Path(args.work)
    res: dict = {"machine": platform.platform(), "cpu_count": __import__("os").cpu_count()}
    t = time.perf_counter()
    rep = write_site(work / "default", SiteSettings(seed=3), overwrite=True)
    res["default_site"] = {"wall_s": time.perf_counter() - t, "stages_s": rep.seconds, "images": rep.n_images,
                           "dense_points": rep.n_cloud_points, "marker_views": rep.visible_counts}
    for name, dist in (("clean", False), ("clean_distortion", True)):
        st = SiteSettings(seed=3, noise=False, distortion=dist)
        write_site(work / name, st, overwrite=True)
        res[f"projection_{name}"] = projection_errors(work / name, st)
    if not args.skip_big:
        st = SiteSettings(seed=3, width=8192, height=5460, noise=False, distortion=False)
        site = build_site(st)
        name, pose = site.poses[20]
        t = time.perf_counter()
        img = site.renderer.render(site.camera, pose)
        res["one_8192x5460_image_s"] = time.perf_counter() - t
        del img
    Path(args.out).write_text(json.dumps(res, indent=1) + "\n")
    print(json.dumps(res, indent=1))


if __name__ == "__main__":
    main()
