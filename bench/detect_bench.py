"""Benchmark of the classical detector against its peers, in one run, on the same data.

1. A generated set with *test*-split backgrounds (never used for tuning): ``--n`` images of 640x480
   plus ``--n-large`` of 1600x1200. For each detector: marker recall (also apart for the uncovered
   markers, those over 2 % covered and those whose centre no occluder hides), precision, false
   markers per image, type accuracy, centre error (mean, median, p95, per radius bin, mean dx/dy for
   bias) and throughput. Peers on the same images:
   - chess-corners (``chess_corners``, Rust ChESS and Radon X-corner detectors, default multiscale
     presets): its X-corners matched to the true markers with the same tolerance
     (cpdetect.evaluate.tolerance_px): recall, false corners per image, centre error;
   - ``cv2.cornerSubPix`` seeded at the true centre + U(-1, 1) px: centre error only, with the
     usual fixed 5x5 half-window and with a window adapted to the marker (our default_window);
   - our :func:`cpdetect.refine.refine_center` seeded the same way (isolates refinement).
2. Two 45 MP JPEGs (8192x5460, six markers): ``cv2.imread(GRAYSCALE)`` time vs
   ``ClassicalDetector().detect(path)`` time (medians), and the detector's peak memory (VmHWM of a
   fresh subprocess, minus that after importing the same modules); in the same loop the time with
   ``min_radius_px=16``, whose search is at 1/4 instead of the default's 1/2 (``min_search_radius_px``:
   the default looks for markers from 8 px radius). One has a test background
   upscaled 8x (smooth, so it decodes about three times faster than a camera's JPEG of that size);
   the other a mosaic of test backgrounds at their own resolution (texture at every scale).

Writes bench/results/detect_bench.json and prints a summary.

    .venv/bin/python bench/detect_bench.py            # ~ a few minutes on 2 cores
"""
from __future__ import annotations

import argparse
import math
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

RESULTS = Path(__file__).parent / "results" / "detect_bench.json"


def _stats(d: list[float]) -> dict:
    a = np.asarray(d, float)
    if a.size == 0:
        return {"n": 0}
    return {"n": int(a.size), "mean": float(a.mean()), "median": float(np.median(a)),
            "p95": float(np.percentile(a, 95)), "max": float(a.max())}


def make_sets(root: Path, n: int, n_large: int, seed: int) -> list[Path]:
    from cpdetect.synth_images import SynthImageOptions, write_synth_images

    sets = []
    if n:
        write_synth_images(root / "small", n, seed, SynthImageOptions(split="test"), workers=2)
        sets.append(root / "small")
    if n_large:
        write_synth_images(root / "large", n_large, seed + 1,
                           SynthImageOptions(split="test", width=1600, height=1200), workers=2)
        sets.append(root / "large")
    return sets


COVERED_FRAC = 0.02  # a marker counts as partly covered above this share of its area hidden


def _covered(marker) -> bool:
    return float(marker.extra.get("occluded_frac", 0.0)) > COVERED_FRAC


def _recall_split(found: list[bool], truths: list) -> dict:
    """Recall of the uncovered and of the partly covered markers, and of those whose centre no
    occluder hides (an aiming point under an occluder cannot be measured), with their counts."""
    from cpdetect.evaluate import centre_hidden

    f = np.asarray(found, bool)
    c = np.asarray([_covered(t) for t in truths], bool)
    v = np.asarray([not centre_hidden(t.extra) for t in truths], bool)

    def part(m):
        return {"markers": int(m.sum()), "recall": float(f[m].mean()) if m.any() else None}
    return {"uncovered": part(~c), "covered": part(c), "centre_visible": part(v)}


def bench_classical(datasets, det) -> dict:
    import cv2

    from cpdetect.evaluate import centre_hidden, match_detections

    n_img = n_truth = n_det = tp = type_ok = 0
    errs, dxs, dys, by_bin, mp, secs = [], [], [], {}, 0.0, 0.0
    errs_visible = []  # of markers whose centre no occluder hides
    found, truths = [], []
    for ds in datasets:
        for item in ds.images:
            img = cv2.imread(str(ds.image_path(item)), cv2.IMREAD_COLOR)
            t0 = time.perf_counter()
            res = det.detect(img)
            secs += time.perf_counter() - t0
            mp += img.shape[0] * img.shape[1] / 1e6
            pairs, fp, fn = match_detections(res.detections, item.markers)
            n_img += 1
            n_truth += len(item.markers)
            n_det += len(res.detections)
            tp += len(pairs)
            hit = {m.truth for m in pairs}
            found += [i in hit for i in range(len(item.markers))]
            truths += item.markers
            for m in pairs:
                d, t = res.detections[m.det], item.markers[m.truth]
                errs.append(m.distance)
                if not centre_hidden(t.extra):
                    errs_visible.append(m.distance)
                dxs.append(d.x - t.x)
                dys.append(d.y - t.y)
                type_ok += d.type == t.type
                b = "8-16" if t.radius_px < 16 else "16-32" if t.radius_px < 32 else "32-64" if t.radius_px < 64 else "64+"
                by_bin.setdefault(b, []).append(m.distance)
    return {"images": n_img, "markers": n_truth, "detections": n_det, "recall": tp / max(n_truth, 1),
            "recall_by_cover": _recall_split(found, truths),
            "precision": tp / max(n_det, 1), "false_markers_per_image": (n_det - tp) / max(n_img, 1),
            "type_accuracy": type_ok / max(tp, 1), "centre_error_px": _stats(errs),
            "centre_error_centre_visible_px": _stats(errs_visible),
            "centre_error_by_radius_px": {k: _stats(v) for k, v in sorted(by_bin.items())},
            "bias_px": {"dx_mean": float(np.mean(dxs)) if dxs else None, "dy_mean": float(np.mean(dys)) if dys else None},
            "seconds": secs, "seconds_per_image": secs / max(n_img, 1), "megapixels_per_second": mp / max(secs, 1e-9)}


def bench_chess(datasets, preset: str) -> dict:
    import chess_corners
    import cv2

    from cpdetect.evaluate import tolerance_px

    det = chess_corners.Detector(getattr(chess_corners.DetectorConfig, preset)())
    n_img = n_truth = n_corners = tp = 0
    errs, secs, mp = [], 0.0, 0.0
    found, truths = [], []
    for ds in datasets:
        for item in ds.images:
            g = np.ascontiguousarray(cv2.imread(str(ds.image_path(item)), cv2.IMREAD_GRAYSCALE))
            t0 = time.perf_counter()
            r = det.detect(g)
            secs += time.perf_counter() - t0
            mp += g.size / 1e6
            xy = np.asarray(r.xy, float).reshape(-1, 2)
            n_img += 1
            n_truth += len(item.markers)
            n_corners += len(xy)
            used = np.zeros(len(xy), bool)
            for t in item.markers:  # nearest unused corner within the tolerance
                truths.append(t)
                found.append(False)
                if not len(xy):
                    continue
                d = np.hypot(xy[:, 0] - t.x, xy[:, 1] - t.y)
                d[used] = np.inf
                j = int(np.argmin(d))
                if d[j] <= tolerance_px(t.radius_px):
                    used[j] = True
                    tp += 1
                    found[-1] = True
                    errs.append(float(d[j]))
    return {"preset": preset, "images": n_img, "markers": n_truth, "corners": n_corners, "recall": tp / max(n_truth, 1),
            "recall_by_cover": _recall_split(found, truths),
            "false_corners_per_image": (n_corners - tp) / max(n_img, 1), "centre_error_px": _stats(errs),
            "seconds_per_image": secs / max(n_img, 1), "megapixels_per_second": mp / max(secs, 1e-9)}


def bench_seeded_refiners(datasets, seed: int) -> dict:
    """Centre error of refiners seeded at truth + U(-1, 1) px (markers at least 2 px inside the image)."""
    import cv2

    from cpdetect.refine import default_window, refine_center

    rng = np.random.default_rng(seed)
    out = {"cornerSubPix_win5": [], "cornerSubPix_adaptive": [], "refine_center_auto": [], "refine_center_hough": [],
           "refine_center_saddle": [], "refine_center_model": []}
    dx_auto = []
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 100, 1e-4)
    for ds in datasets:
        for item in ds.images:
            g = cv2.imread(str(ds.image_path(item)), cv2.IMREAD_GRAYSCALE)
            h, w = g.shape
            for t in item.markers:
                if not (8 <= t.x <= w - 9 and 8 <= t.y <= h - 9):
                    continue
                s = np.array([t.x, t.y]) + rng.uniform(-1, 1, 2)
                for key, win in (("cornerSubPix_win5", 5), ("cornerSubPix_adaptive", int(round(default_window(t.radius_px))))):
                    p = s.reshape(1, 1, 2).astype(np.float32)
                    p = cv2.cornerSubPix(g, p, (win, win), (-1, -1), crit)
                    out[key].append(float(np.hypot(p[0, 0, 0] - t.x, p[0, 0, 1] - t.y)))
                for method in ("auto", "hough", "saddle", "model"):
                    r = refine_center(g, s[0], s[1], t.radius_px, method=method)
                    out[f"refine_center_{method}"].append(float(np.hypot(r.x - t.x, r.y - t.y)))
                    if method == "auto":
                        dx_auto.append(r.x - t.x)
    res = {k: _stats(v) for k, v in out.items()}
    res["refine_center_auto"]["dx_mean"] = float(np.mean(dx_auto)) if dx_auto else None
    return res


def _mosaic(W: int, H: int, rng: np.random.Generator) -> np.ndarray:
    """Test-split backgrounds tiled at their own resolution (random flips): real texture at every
    scale, so the JPEG costs what a camera's does to decode."""
    import cv2

    from cpdetect.backgrounds import list_backgrounds

    tiles = [cv2.imread(str(b.path), cv2.IMREAD_COLOR) for b in list_backgrounds("test")]
    img = np.zeros((H, W, 3), np.uint8)
    y = 0
    while y < H:
        x, row_h = 0, 0
        while x < W:
            t = tiles[int(rng.integers(len(tiles)))]
            t = t[:, ::-1] if rng.random() < 0.5 else t
            h, w = min(t.shape[0], H - y), min(t.shape[1], W - x)
            img[y:y + h, x:x + w] = t[:h, :w]
            x += w
            row_h = max(row_h, h)
        y += row_h
    return img


def make_45mp(path: Path, seed: int, texture: bool = False) -> list[dict]:
    """A 8192x5460 JPEG (quality 92) with six markers (radius 24 to 400 px) and sensor noise, on a
    test-split background upscaled 8x (smooth: decodes fast) or, with ``texture``, on a mosaic of
    test-split backgrounds at their own resolution. Returns the markers' truth."""
    import cv2

    from cpdetect.backgrounds import list_backgrounds
    from cpdetect.markers import MarkerSpec, frontal_homography, projected_radius, render_marker

    rng = np.random.default_rng(seed)
    W, H = 8192, 5460
    if texture:
        img = _mosaic(W, H, np.random.default_rng(seed + 2)).astype(np.float32)
    else:
        img = cv2.imread(str(list_backgrounds("test")[0].path), cv2.IMREAD_COLOR)
        img = cv2.resize(img, (W, H), interpolation=cv2.INTER_CUBIC).astype(np.float32)
    truth = []
    for k, (r, mtype) in enumerate([(24, "square"), (60, "circle"), (150, "diagonal"), (400, "square"),
                                    (40, "diagonal"), (90, "circle")]):
        cx, cy = 700 + (k % 3) * 2600 + rng.uniform(0, 600), 900 + (k // 3) * 2600 + rng.uniform(0, 600)
        spec = MarkerSpec(mtype, 1.0, margin_m=0.1)
        Hm = frontal_homography((cx, cy), r, rng.uniform(0, np.pi), spec)
        render_marker(spec, Hm, (H, W), supersample=4).composite(img, 30.0, 220.0, 235.0)
        truth.append({"x": cx, "y": cy, "type": mtype, "radius_px": projected_radius(spec, Hm)})
    img += np.random.default_rng(seed + 1).normal(0, 2.0, img.shape).astype(np.float32)
    cv2.imwrite(str(path), np.clip(img + 0.5, 0, 255).astype(np.uint8), [cv2.IMWRITE_JPEG_QUALITY, 92])
    return truth


# the start of a child process that measures its own peak memory (also used by hma_bench.py)
MEM_PRELUDE = r"""
import sys, time
def hwm():
    # peak resident set (kB) of this process; ru_maxrss would include the parent's peak (fork)
    for line in open("/proc/self/status"):
        if line.startswith("VmHWM:"):
            return int(line.split()[1])
def reset():
    try:
        with open("/proc/self/clear_refs", "w") as fh:
            fh.write("5")  # resets VmHWM to the current RSS (Linux >= 4.0)
    except OSError:
        pass
reset()
"""

_MEM_CHILD = MEM_PRELUDE + r"""
import cv2, numpy as np
from cpdetect.classical import ClassicalDetector
det = ClassicalDetector()
base = hwm()
if sys.argv[2] == "detect":
    res = det.detect(sys.argv[1])
    n = len(res.detections)
else:
    g = cv2.imread(sys.argv[1], cv2.IMREAD_GRAYSCALE)
    n = 0
peak = hwm()
print(base, peak, n)
"""


COARSE_MIN_RADIUS_PX = 16.0  # ClassicalSettings.min_radius_px for the 45 MP search at 1/4


def bench_45mp(tmp: Path, seed: int, repeats: int, texture: bool = False) -> dict:
    import cv2

    from cpdetect.classical import ClassicalDetector

    path = tmp / ("big45_texture.jpg" if texture else "big45.jpg")
    truth = make_45mp(path, seed, texture)
    det = ClassicalDetector()
    # the search of before stop 80 (k = 4 at 45 MP), for markers of 16 px radius and more; the
    # bench JPEGs' smallest marker is 27 px
    coarse = ClassicalDetector(min_radius_px=COARSE_MIN_RADIUS_PX)
    t_read, t_det, t_coarse = [], [], []
    res = res_coarse = None
    for _ in range(repeats):
        t0 = time.perf_counter()
        g = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        t_read.append(time.perf_counter() - t0)
        del g
        t0 = time.perf_counter()
        res = det.detect(str(path))
        t_det.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        res_coarse = coarse.detect(str(path))
        t_coarse.append(time.perf_counter() - t0)

    def found_in(r) -> list[bool]:
        out = []
        for t in truth:
            d = [math.hypot(m.x - t["x"], m.y - t["y"]) for m in r.detections]
            out.append(bool(d) and min(d) <= max(3.0, 0.25 * t["radius_px"]))
        return out

    found, found_coarse = found_in(res), found_in(res_coarse)
    mem = {}
    for mode in ("detect", "imread"):
        out = subprocess.run([sys.executable, "-c", _MEM_CHILD, str(path), mode], capture_output=True, text=True,
                             timeout=600)
        base, peak, _ = (int(v) for v in out.stdout.split())
        mem[mode] = {"peak_rss_mb_after_imports": base / 1024, "peak_rss_mb": peak / 1024,
                     "increase_mb": (peak - base) / 1024}
    return {"background": "mosaic of test-split backgrounds at their own resolution" if texture else
            "one test-split background upscaled 8x", "jpeg_mb": path.stat().st_size / 1e6,
            "width": 8192, "height": 5460, "markers": len(truth), "found": int(sum(found)),
            "false_markers": len(res.detections) - int(sum(found)),
            "imread_gray_seconds_median": float(np.median(t_read)), "detect_seconds_median": float(np.median(t_det)),
            "ratio_detect_to_imread": float(np.median(t_det) / np.median(t_read)),
            "search_factor": res.extras.get("search_factor"), "memory": mem,
            "coarse_search": {"settings": {"min_radius_px": COARSE_MIN_RADIUS_PX},
                              "search_factor": res_coarse.extras.get("search_factor"),
                              "detect_seconds_median": float(np.median(t_coarse)),
                              "ratio_detect_to_imread": float(np.median(t_coarse) / np.median(t_read)),
                              "found": int(sum(found_coarse)),
                              "false_markers": len(res_coarse.detections) - int(sum(found_coarse))}}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=100)
    ap.add_argument("--n-large", type=int, default=4)
    ap.add_argument("--seed", type=int, default=2024)
    ap.add_argument("--data", help="reuse this folder for the generated sets")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--out", default=str(RESULTS))
    ap.add_argument("--skip-45mp", action="store_true")
    args = ap.parse_args(argv)

    from cpdetect.classical import ClassicalDetector
    from cpdetect.dataset import load_dataset
    from cpdetect.fileio import write_json_atomic

    tmp = Path(args.data) if args.data else Path(tempfile.mkdtemp(prefix="cpdetect_bench_"))
    tmp.mkdir(parents=True, exist_ok=True)
    roots = [tmp / "small", tmp / "large"]
    if not all((r / "markers.json").exists() for r in roots):
        make_sets(tmp, args.n, args.n_large, args.seed)
    datasets = [load_dataset(r) for r in roots if (r / "markers.json").exists()]
    t0 = time.time()
    report = {"generated": {"root": str(tmp), "seed": args.seed, "split": "test",
                            "images": {d.root.name: len(d.images) for d in datasets}}}
    print("classical ...", file=sys.stderr)
    report["classical"] = bench_classical(datasets, ClassicalDetector())
    print("chess-corners ...", file=sys.stderr)
    report["chess_corners"] = {p: bench_chess(datasets, p) for p in ("chess_multiscale", "radon_multiscale")}
    print("seeded refiners ...", file=sys.stderr)
    report["seeded_refiners"] = bench_seeded_refiners(datasets, args.seed)
    if not args.skip_45mp:
        print("45 MP ...", file=sys.stderr)
        report["jpeg_45mp"] = bench_45mp(tmp, args.seed, args.repeats)
        report["jpeg_45mp_texture"] = bench_45mp(tmp, args.seed, args.repeats, texture=True)
    report["bench_seconds"] = time.time() - t0
    write_json_atomic(args.out, report)

    c = report["classical"]
    ce = c["centre_error_px"]
    print(f"classical      recall {c['recall']:.3f}  precision {c['precision']:.3f}  false/img "
          f"{c['false_markers_per_image']:.3f}  type acc {c['type_accuracy']:.3f}  centre mean {ce.get('mean', float('nan')):.3f} "
          f"p95 {ce.get('p95', float('nan')):.3f} px  bias ({c['bias_px']['dx_mean']:+.4f}, {c['bias_px']['dy_mean']:+.4f})  "
          f"{c['seconds_per_image']:.2f} s/img")
    def by_cover(v: dict) -> str:
        rc = v["recall_by_cover"]
        return "  ".join(f"{k} {rc[k]['recall']:.3f} of {rc[k]['markers']}" for k in ("uncovered", "covered",
                                                                                  "centre_visible")
                         if rc[k]["recall"] is not None)

    print(f"   recall: {by_cover(c)}")
    cv = c["centre_error_centre_visible_px"]
    print(f"   centre error of the markers whose centre is visible: mean {cv.get('mean', float('nan')):.3f} "
          f"p95 {cv.get('p95', float('nan')):.3f} px")
    for k, v in c["centre_error_by_radius_px"].items():
        print(f"   radius {k:>6} px: n {v['n']:4d}  mean {v['mean']:.3f}  p95 {v['p95']:.3f}")
    for p, v in report["chess_corners"].items():
        e = v["centre_error_px"]
        print(f"chess-corners {p:17s} recall {v['recall']:.3f}  false corners/img {v['false_corners_per_image']:.1f}  "
              f"centre mean {e.get('mean', float('nan')):.3f} p95 {e.get('p95', float('nan')):.3f} px  {v['seconds_per_image']*1000:.1f} ms/img"
              f"\n   recall: {by_cover(v)}")
    for k, v in report["seeded_refiners"].items():
        print(f"seeded {k:24s} mean {v['mean']:.3f}  median {v['median']:.3f}  p95 {v['p95']:.3f} px (n {v['n']})")
    for j in (report[k] for k in ("jpeg_45mp", "jpeg_45mp_texture") if k in report):
        print(f"45 MP JPEG on {j['background']} ({j['jpeg_mb']:.1f} MB):")
        print(f"   imread gray {j['imread_gray_seconds_median']:.3f} s, detect {j['detect_seconds_median']:.3f} s, "
              f"ratio {j['ratio_detect_to_imread']:.2f}; found {j['found']}/{j['markers']}, false {j['false_markers']}; "
              f"peak RSS increase {j['memory']['detect']['increase_mb']:.0f} MB (imread alone "
              f"{j['memory']['imread']['increase_mb']:.0f} MB)")
        c45 = j["coarse_search"]
        print(f"   with min_radius_px={COARSE_MIN_RADIUS_PX:g} (search at 1/{c45['search_factor']} instead of "
              f"1/{j['search_factor']}): detect {c45['detect_seconds_median']:.3f} s, ratio "
              f"{c45['ratio_detect_to_imread']:.2f}; found {c45['found']}/{j['markers']}, false {c45['false_markers']}")
    print(f"written {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
