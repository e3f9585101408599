"""Scale benchmark: batch detection serial vs process pool vs Dask, peak memory, 45 MP inputs, and the
cost of the correspondence-free registration against the number of surveyed points. Writes JSON.

    .venv/bin/python bench/scale_bench.py [--sizes 10,100,1000] [--size 160x120] [--workers 2]
        [--big 4] [--reg-sizes 5,10,20,50,100,200] [--reg-layouts 5] [--out bench/results/scale_bench.json]

Run it on a tree nobody is editing (e.g. ``git archive HEAD | tar -x -C /tmp/snap``): the child
processes import the detector at different moments, and an edit in between shows as ``identical: false``.

* **Detection throughput**: N generated images (``--size``, small so that N = 1,000 stays affordable:
  a smoothed-noise background and one to three rotated 2x2 markers of 8-30 px half-side), run through
  :func:`cpdetect.batch.detect_batch` with the classical detector, in three configurations: ``serial``
  (this process), ``pool`` (``--workers`` local processes) and ``dask`` (a ``distributed.LocalCluster``
  of ``--workers`` single-threaded worker processes; its start-up time is reported apart). Each
  configuration runs in a fresh child process; the parent samples the resident memory (RSS) of the
  child and all its descendants every 20 ms and reports the peak of their sum (``peak_tree_rss_mb``)
  and the child's own peak (``ru_maxrss``, ``main_maxrss_mb``). ``identical`` says the output equals the serial one
  (timings aside). Images per second count the detection run only (no interpreter start).
* **45 MP**: ``--big`` JPEGs of 8192 x 5464 px (a synthetic marker image from
  :mod:`cpdetect.synth_images`, upscaled, with fresh noise), serial and pool: seconds per image and
  peak memory, against what holding the decoded images would cost.
* **Registration**: :func:`geometry.registration.register_points` on ``--reg-layouts`` random layouts
  per number M of surveyed points (uniform in 100 x 100 x 20 m; 80 % of them detected with 1 cm noise,
  plus 20 % false detections; random similarity to the model frame): median wall time of the best of
  3 calls per layout, share of layouts paired exactly right, and the log-log slope of time against M.

The machine's CPU count and load average are recorded: on a shared machine the figures are noisy and
a pool cannot beat serial by more than the free cores allow.
"""
from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import json  # noqa: E402
import platform  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


# ---------------------------------------------------------------------------------------------------
# Inputs


def make_images(folder: Path, n: int, size: tuple[int, int], seed: int) -> Path:
    """``n`` gray JPEGs of ``size`` (w, h): smoothed noise and 1-3 rotated 2x2 checker markers."""
    import cv2

    folder.mkdir(parents=True, exist_ok=True)
    w, h = size
    for i in range(n):
        rng = np.random.default_rng([seed, i])
        bg = cv2.GaussianBlur(rng.normal(0, 1, (h, w)).astype(np.float32), (0, 0), 6)
        img = 120 + 25 * bg / (bg.std() + 1e-6)
        for _ in range(int(rng.integers(1, 4))):
            r = rng.uniform(8, min(30, 0.2 * min(w, h)))
            cx, cy = rng.uniform(r + 2, w - r - 2), rng.uniform(r + 2, h - r - 2)
            a = rng.uniform(0, np.pi / 2)
            u, v = np.array([np.cos(a), np.sin(a)]), np.array([-np.sin(a), np.cos(a)])
            c = np.array([cx, cy])
            dark, bright = rng.uniform(10, 60), rng.uniform(190, 245)
            for k, (su, sv) in enumerate(((1, 1), (-1, 1), (-1, -1), (1, -1))):
                quad = np.array([c, c + su * r * u, c + su * r * u + sv * r * v, c + sv * r * v])
                cv2.fillConvexPoly(img, np.round(quad * 16).astype(np.int32), dark if k % 2 == 0 else bright,
                                   lineType=cv2.LINE_AA, shift=4)
        img = cv2.GaussianBlur(img, (0, 0), 0.7) + rng.normal(0, 2.0, (h, w))
        cv2.imwrite(str(folder / f"{i:05d}.jpg"), np.clip(img, 0, 255).astype(np.uint8),
                    [cv2.IMWRITE_JPEG_QUALITY, 92])
    return folder


def make_big_images(folder: Path, n: int, seed: int, size=(8192, 5464)) -> Path:
    """``n`` 45 MP JPEGs: synthetic marker photographs upscaled to ``size`` with fresh noise."""
    import cv2

    from cpdetect.synth_images import SynthImageOptions, write_synth_images

    small = folder / "small"
    write_synth_images(small, n, seed, SynthImageOptions(width=1024, height=683, empty_prob=0.0))
    for i, f in enumerate(sorted((small / "images").glob("*.jpg"))):
        rng = np.random.default_rng([seed, i])
        img = cv2.resize(cv2.imread(str(f)), size, interpolation=cv2.INTER_CUBIC).astype(np.float32)
        img += rng.normal(0, 3.0, img.shape).astype(np.float32)
        cv2.imwrite(str(folder / f"big{i:03d}.jpg"), np.clip(img, 0, 255).astype(np.uint8),
                    [cv2.IMWRITE_JPEG_QUALITY, 90])
        del img
    return folder


# ---------------------------------------------------------------------------------------------------
# One configuration, in a child process


def child(args) -> None:
    import resource

    from cpdetect.batch import collect_jobs, detect_batch

    jobs = collect_jobs([args.images])
    res: dict = {"n": len(jobs), "config": args.child}
    cluster = client = None
    if args.child == "dask":
        import distributed

        t = time.perf_counter()
        cluster = distributed.LocalCluster(n_workers=args.workers, threads_per_worker=1, processes=True,
                                           dashboard_address=None, silence_logs=40)
        client = distributed.Client(cluster)
        res["cluster_start_s"] = round(time.perf_counter() - t, 3)
    t = time.perf_counter()
    c0 = time.process_time()
    doc = detect_batch(jobs, "classical", {}, args.result, workers=args.workers if args.child == "pool" else 1,
                       scheduler=client)
    res["seconds"] = round(time.perf_counter() - t, 3)
    res["main_cpu_s"] = round(time.process_time() - c0, 3)
    res["detector_seconds_sum"] = round(sum(im.get("seconds", 0.0) for im in doc["images"]), 3)
    res["detections"] = sum(len(im.get("detections", [])) for im in doc["images"])
    if client is not None:
        client.close()
        cluster.close()
    res["main_maxrss_mb"] = round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1)
    print(json.dumps(res), flush=True)


def run_config(config: str, images: Path, workers: int, result: Path) -> dict:
    """Run one configuration in a child process, sampling the RSS of its process tree."""
    import psutil

    cmd = [sys.executable, __file__, "--child", config, "--images", str(images), "--workers", str(workers),
           "--result", str(result)]
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    peak = 0
    ps = psutil.Process(proc.pid)
    while proc.poll() is None:
        try:
            procs = [ps, *ps.children(recursive=True)]
            total = 0
            for p in procs:
                try:
                    total += p.memory_info().rss
                except psutil.Error:
                    pass
            peak = max(peak, total)
        except psutil.Error:
            pass
        time.sleep(0.02)
    out, err = proc.communicate()
    if proc.returncode != 0:
        raise RuntimeError(f"{config} failed ({proc.returncode}): {err[-2000:]}")
    res = json.loads(out.strip().splitlines()[-1])
    res["process_wall_s"] = round(time.perf_counter() - t0, 3)
    res["peak_tree_rss_mb"] = round(peak / 2 ** 20, 1)
    res["images_per_s"] = round(res["n"] / res["seconds"], 2) if res["seconds"] > 0 else None
    return res


def _without_timing(path: Path) -> dict:
    doc = json.loads(path.read_text())
    for im in doc["images"]:
        im.pop("seconds", None)
    return doc


def bench_detection(tmp: Path, sizes, size, workers, configs=("serial", "pool", "dask")) -> list[dict]:
    rows = []
    for n in sizes:
        images = make_images(tmp / f"n{n}", n, size, seed=n)
        ref = None
        for config in configs:
            result = tmp / f"n{n}-{config}.json"
            r = run_config(config, images, workers, result)
            r.update({"image_size": list(size), "workers": 1 if config == "serial" else workers})
            doc = _without_timing(result)
            ref = doc if ref is None else ref
            r["identical"] = doc == ref
            print(f"detect N={n} {config}: {r['images_per_s']} img/s, peak {r['peak_tree_rss_mb']} MB", flush=True)
            rows.append(r)
    return rows


def bench_big(tmp: Path, n: int, workers: int) -> list[dict]:
    # made in a child process: the children that measure memory are forked from this one, and on Linux
    # a forked child's ru_maxrss starts from its parent's resident size
    subprocess.run([sys.executable, __file__, "--make-big", str(n), "--images", str(tmp / "big")], check=True)
    images = tmp / "big"
    (tmp / "big" / "small").rename(tmp / "big-small")
    rows = []
    for config in ("serial", "pool"):
        r = run_config(config, images, workers, tmp / f"big-{config}.json")
        r.update({"image_size": [8192, 5464], "megapixels": round(8192 * 5464 / 1e6, 1),
                  "workers": 1 if config == "serial" else workers,
                  "seconds_per_image": round(r["seconds"] / r["n"], 3),
                  "decoded_bgr_mb_per_image": round(8192 * 5464 * 3 / 2 ** 20, 1),
                  "decoded_gray_mb_per_image": round(8192 * 5464 / 2 ** 20, 1)})
        print(f"45 MP {config}: {r['seconds_per_image']} s/img, peak {r['peak_tree_rss_mb']} MB", flush=True)
        rows.append(r)
    return rows


def bench_registration(sizes, layouts: int) -> list[dict]:
    from geometry.registration import register_points, simulate_detections

    rows = []
    for m in sizes:
        times, right = [], 0
        for k in range(layouts):
            rng = np.random.default_rng([m, k])
            sur = rng.uniform([0, 0, 0], [100, 100, 20], (m, 3))
            sim = simulate_detections(sur, rng, n_seen=max(3, round(0.8 * m)), n_false=round(0.2 * m),
                                      noise=0.01)
            best = np.inf
            for _ in range(3):
                t = time.perf_counter()
                res = register_points(sim.detected, sim.surveyed, rng=np.random.default_rng(0))
                best = min(best, time.perf_counter() - t)
            times.append(best)
            truth = sim.true_pairing()
            got = {p.detected: p.surveyed for p in res.pairs}
            right += int(res.status == "ok" and got == truth)
        rows.append({"surveyed": m, "detected": max(3, round(0.8 * m)) + round(0.2 * m),
                     "median_s": round(float(np.median(times)), 4), "max_s": round(float(np.max(times)), 4),
                     "exactly_right": f"{right}/{layouts}"})
        print(f"register M={m}: median {rows[-1]['median_s']} s, right {right}/{layouts}", flush=True)
    return rows


def loglog_slope(xs, ys) -> float:
    return round(float(np.polyfit(np.log(xs), np.log(ys), 1)[0]), 2)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="10,100,1000")
    ap.add_argument("--size", default="160x120")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--big", type=int, default=4, help="number of 45 MP images (0: skip)")
    ap.add_argument("--reg-sizes", default="5,10,20,50,100,200")
    ap.add_argument("--reg-layouts", type=int, default=5)
    ap.add_argument("--skip-detection", action="store_true")
    ap.add_argument("--out", default=str(ROOT / "bench" / "results" / "scale_bench.json"))
    ap.add_argument("--label", default="", help="free text stored in the JSON (e.g. the commit benchmarked)")
    # child mode
    ap.add_argument("--child", choices=("serial", "pool", "dask"), help=argparse.SUPPRESS)
    ap.add_argument("--images", help=argparse.SUPPRESS)
    ap.add_argument("--result", help=argparse.SUPPRESS)
    ap.add_argument("--make-big", type=int, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.make_big:
        make_big_images(Path(args.images), args.make_big, seed=7)
        return
    if args.child:
        child(args)
        return
    w, h = (int(v) for v in args.size.split("x"))
    doc: dict = {"machine": {"platform": platform.platform(), "python": platform.python_version(),
                             "cpus": os.cpu_count(), "loadavg_start": list(os.getloadavg())},
                 "settings": vars(args)}
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="cpdetect-scale-") as tmp:
        tmp = Path(tmp)
        if not args.skip_detection:
            rows = bench_detection(tmp, [int(s) for s in args.sizes.split(",")], (w, h), args.workers)
            doc["detection"] = rows
            summary = {}
            for cfg in ("serial", "pool", "dask"):
                sub = [r for r in rows if r["config"] == cfg]
                summary[cfg] = {"images_per_s": {r["n"]: r["images_per_s"] for r in sub},
                                "peak_tree_rss_mb": {r["n"]: r["peak_tree_rss_mb"] for r in sub},
                                "seconds_vs_n_loglog_slope": loglog_slope([r["n"] for r in sub],
                                                                          [r["seconds"] for r in sub])}
            doc["detection_summary"] = summary
            doc["all_identical_to_serial"] = all(r["identical"] for r in rows)
        if args.big > 0:
            doc["big_45mp"] = bench_big(tmp, args.big, args.workers)
    reg = bench_registration([int(s) for s in args.reg_sizes.split(",")], args.reg_layouts)
    doc["registration"] = reg
    doc["registration_loglog_slope"] = loglog_slope([r["surveyed"] for r in reg], [r["median_s"] for r in reg])
    doc["machine"]["loadavg_end"] = list(os.getloadavg())
    doc["total_seconds"] = round(time.perf_counter() - t0, 1)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(doc, indent=1) + "\n")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
