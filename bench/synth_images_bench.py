"""Speed and content figures of the synthetic marker image generator; writes a JSON of figures.

    .venv/bin/python bench/synth_images_bench.py [--n 100] [--size 640x480]
        [--out bench/results/synth_images_bench.json]

Measures, single-threaded (OpenCV and BLAS on one thread): images per second for generation alone
(``generate_image``) and for generation plus encoding and atomic writes (``write_synth_images``,
``--workers 1``), the bytes per image on disk, and the content: markers per image, share of empty
images, radius / tilt / occlusion / blur distributions, marker types and confuser kinds.
Wall-clock on a shared machine: treat the speeds as lower bounds.
"""
from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import collections  # noqa: E402
import json  # noqa: E402
import platform  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from cpdetect.backgrounds import BackgroundLibrary, list_backgrounds  # noqa: E402
from cpdetect.fileio import write_json_atomic  # noqa: E402
from cpdetect.synth_images import SynthImageOptions, generate_image, write_synth_images  # noqa: E402


def _q(a) -> dict:
    a = np.asarray(a, float)
    if a.size == 0:
        return {}
    return {"min": float(a.min()), "p5": float(np.percentile(a, 5)), "median": float(np.median(a)),
            "p95": float(np.percentile(a, 95)), "max": float(a.max()), "mean": float(a.mean())}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=100)
    ap.add_argument("--size", default="640x480")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default="bench/results/synth_images_bench.json")
    args = ap.parse_args()
    cv2.setNumThreads(1)
    w, h = (int(v) for v in args.size.split("x"))
    opt = SynthImageOptions(width=w, height=h)
    lib = BackgroundLibrary(list_backgrounds())
    generate_image(0, args.seed, opt, lib)  # warm the background cache
    for i in range(len(lib)):
        lib.image(i)

    t0 = time.perf_counter()
    samples = [generate_image(i, args.seed, opt, lib) for i in range(args.n)]
    t_gen = time.perf_counter() - t0
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        write_synth_images(tmp, args.n, args.seed, opt, workers=1)
        t_write = time.perf_counter() - t0
        img_bytes = [p.stat().st_size for p in Path(tmp, "images").iterdir()]
        mask_bytes = [p.stat().st_size for p in Path(tmp, "masks").iterdir()]
        json_bytes = Path(tmp, "markers.json").stat().st_size

    markers = [m for s in samples for m in s.markers]
    figures = {
        "machine": {"python": platform.python_version(), "cpu": platform.processor() or platform.machine(),
                    "opencv_threads": cv2.getNumThreads()},
        "n": args.n, "size": [w, h], "seed": args.seed,
        "generate_images_per_s": args.n / t_gen,
        "generate_and_write_images_per_s": args.n / t_write,
        "bytes_per_image": float(np.mean(img_bytes)), "bytes_per_mask": float(np.mean(mask_bytes)),
        "markers_json_bytes": json_bytes,
        "markers_per_image": _q([len(s.markers) for s in samples]),
        "empty_image_share": float(np.mean([len(s.markers) == 0 for s in samples])),
        "radius_px": _q([m.radius_px for m in markers]),
        "tilt_deg": _q([m.extra["tilt_deg"] for m in markers]),
        "occluded_share": float(np.mean([m.extra["occluded_frac"] > 0 for m in markers])) if markers else None,
        "blurred_image_share": float(np.mean([s.meta["blur_px"] > 0 for s in samples])),
        "types": dict(collections.Counter(m.type for m in markers)),
        "confusers": dict(collections.Counter(c["kind"] for s in samples for c in s.meta["confusers"])),
        "categories": dict(collections.Counter(s.meta["category"] for s in samples)),
        "mask_marker_pixel_share": float(np.mean([np.mean(s.mask > 0) for s in samples])),
    }
    write_json_atomic(args.out, figures)
    print(json.dumps({k: v for k, v in figures.items() if "per_s" in k or "bytes" in k}, indent=1))


if __name__ == "__main__":
    main()
