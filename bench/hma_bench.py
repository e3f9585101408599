"""Benchmark of the learned ``hma`` detector's deployment path (shipped weights by default).

1. ONNX vs PyTorch: largest |P_torch - P_opencv| (learned.export.check_parity) at two input sizes,
   scales (1.0,) and (0.5, 1.0).
2. The two 45 MP JPEGs of bench/detect_bench.py (8192 x 5460, six markers of radius 24 to 400 px with
   known centres; one on a test-split background upscaled 8x, one on a mosaic of test-split
   backgrounds at their own resolution), for the OpenCV backend: median wall time of
   ``probability_map`` (downscale to max_side, OpenCV DNN) and of the full ``detect`` (instances and
   refinement on the full-resolution image) on the decoded gray image, markers found (centre within
   max(3, 0.25 radius) px), false detections and centre errors; peak RSS of a fresh subprocess that
   reads the image and runs one detection. Also: the network's time inside each ``detect`` call
   and the time after it (instances, refinement), and OpenCV's own per-layer times of one scale-1
   network pass on the processing-size image (``cv2.dnn.Net.getPerfProfile``): the slowest layers
   and each part's share (backbone, OCR head, class and attention heads), which says where a
   lighter network would save.
3. Model files: parameters, model.pt / model.onnx sizes.

Writes bench/results/hma_bench.json and prints it.

    .venv/bin/python bench/hma_bench.py [--model-dir DIR] [--repeats 3]
"""
from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

RESULTS = Path(__file__).parent / "results" / "hma_bench.json"


_MEM_CHILD = r"""
import cv2
from cpdetect import get_detector
d = get_detector("hma", model_dir=sys.argv[1], backend="opencv")
base = hwm()
img = cv2.imread(sys.argv[2], cv2.IMREAD_GRAYSCALE)
d.detect(img)
print(base, hwm())
"""


def peak_rss_mb(model_dir: str, path: str) -> dict:
    """Peak RSS (MB) of a fresh process that decodes the 45 MP gray image and detects on it once, and
    its increase over the process with the detector loaded."""
    from detect_bench import MEM_PRELUDE

    out = subprocess.run([sys.executable, "-c", MEM_PRELUDE + _MEM_CHILD, model_dir, path], capture_output=True,
                         text=True, check=True)
    base, peak = (int(v) for v in out.stdout.split())
    return {"peak_rss_mb": peak / 1024, "increase_mb": (peak - base) / 1024}


def layer_profile(backend, x: np.ndarray, top: int = 8) -> dict:
    """OpenCV's per-layer times (ms) of one network pass of ``backend`` (an OpenCVBackend) on ``x``
    (h, w) float32: the ``top`` slowest layers and the share of each part of the network, by the
    first component of the layer names of learned.export's graph (backbone, ocr, cls_head,
    attn_head; the rest, such as resizes and concatenations between them, as "other")."""
    import cv2

    backend.trunk(x)
    total, per = backend.net.getPerfProfile()
    ms = np.asarray(per, float).ravel() * 1000.0 / cv2.getTickFrequency()
    # one time per layer, in the order of getLayerNames (layer ids 1..n)
    names = list(backend.net.getLayerNames())[:len(ms)]
    parts: dict[str, float] = {}
    for name, t in zip(names, ms):
        head = name.strip("/").split("/")[0]
        key = head if head in ("backbone", "ocr", "cls_head", "attn_head") else "other"
        parts[key] = parts.get(key, 0.0) + float(t)
    layer_sum = float(ms.sum()) or 1.0
    order = np.argsort(-ms)[:top]
    return {"input": list(x.shape), "total_ms": float(total) * 1000.0 / cv2.getTickFrequency(),
            "share": {k: round(v / layer_sum, 3) for k, v in sorted(parts.items(), key=lambda kv: -kv[1])},
            "slowest_ms": {names[i]: round(float(ms[i]), 1) for i in order}}


def main() -> int:
    from learned.adapter import default_model_dir

    ap = argparse.ArgumentParser()
    ap.add_argument("--model-dir", default=str(default_model_dir()))
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--seed", type=int, default=2024, help="seed of the 45 MP images (detect_bench's default)")
    args = ap.parse_args()
    from cpdetect.errors import InputError, UsageError

    if args.repeats < 1:
        print(f"error: --repeats must be >= 1, got {args.repeats}", file=sys.stderr)
        return 2
    try:
        return run(args)
    except (InputError, UsageError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except subprocess.CalledProcessError as exc:
        last = (exc.stderr or "").strip().splitlines()[-1:] or [f"exit status {exc.returncode}"]
        print(f"error: the peak-memory child process failed: {last[0]}", file=sys.stderr)
        return 2


def run(args: argparse.Namespace) -> int:
    import cv2

    from cpdetect.fileio import write_json_atomic
    from learned.infer import OpenCVBackend, probability_map, processing_image

    d = Path(args.model_dir)
    res: dict = {"model_dir": str(d), "cv2": cv2.__version__}
    try:
        from learned.export import check_parity
        from learned.hma import count_parameters, load_model

        model = load_model(d)
        res["parameters"] = count_parameters(model)
        res["parity_max_abs_diff"] = check_parity(model, d / "model.onnx")
    except ModuleNotFoundError:
        res["parity_max_abs_diff"] = None
    for name in ("model.pt", "model.onnx"):
        if (d / name).exists():
            res[f"{name}_MB"] = (d / name).stat().st_size / 1e6
    ob = OpenCVBackend(d / "model.onnx")
    from cpdetect import get_detector
    from detect_bench import make_45mp

    det = get_detector("hma", model_dir=str(d), backend="opencv")
    # the network's share of each detect call, timed inside that call
    net_seconds: list[float] = []
    probability = det.probability

    def timed_probability(gray, **kw):
        t = time.perf_counter()
        out = probability(gray, **kw)
        net_seconds.append(time.perf_counter() - t)
        return out

    det.probability = timed_probability
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        for key, texture in (("jpeg_45mp", False), ("jpeg_45mp_texture", True)):
            path = Path(tmp) / f"{key}.jpg"
            truth = make_45mp(path, args.seed, texture)
            img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
            tp, td, tn = [], [], []
            for _ in range(args.repeats):
                t = time.perf_counter()
                probability_map(img, ob, (0.5, 1.0), max_side=2048, tile=2048)
                tp.append(time.perf_counter() - t)
                net_seconds.clear()
                t = time.perf_counter()
                r = det.detect(img)
                td.append(time.perf_counter() - t)
                tn.append(sum(net_seconds))
            errors, per_marker = [], []
            for t in truth:
                dist = [math.hypot(m.x - t["x"], m.y - t["y"]) for m in r.detections]
                hit = bool(dist) and min(dist) <= max(3.0, 0.25 * t["radius_px"])
                if hit:
                    errors.append(min(dist))
                per_marker.append({"type": t["type"], "radius_px": round(t["radius_px"], 1),
                                   "centre_error_px": round(min(dist), 4) if hit else None})
            res[key] = {"width": img.shape[1], "height": img.shape[0], "markers": len(truth),
                        "found": len(errors), "false_markers": len(r.detections) - len(errors),
                        "centre_error_px_mean": float(np.mean(errors)) if errors else None,
                        "per_marker": per_marker,
                        "probability_map_s_median": float(np.median(tp)),
                        "detect_s_median": float(np.median(td)),
                        "detect_network_s_median": float(np.median(tn)),
                        "after_network_s_median": float(np.median(np.subtract(td, tn))),
                        "detect_process_memory": peak_rss_mb(str(d), str(path))}
            if key == "jpeg_45mp":
                small = processing_image(img, det.settings.max_side)  # what the detector's network sees
                res["network_layers"] = layer_profile(ob, small.astype(np.float32) / 255.0)
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    write_json_atomic(RESULTS, res, indent=1)
    print(json.dumps(res, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
