"""Benchmark of the learned ``hma`` detector's deployment path (shipped weights by default).

1. ONNX vs PyTorch: largest |P_torch - P_opencv| (learned.export.check_parity) at two input sizes,
   scales (1.0,) and (0.5, 1.0).
2. A 45 MP gray image (8256 x 5504: a generated test-split image upscaled, so it holds markers):
   median wall time of ``probability_map`` (downscale to max_side, OpenCV DNN) and of the full
   ``detect`` (instances and refinement on the full-resolution image), for the OpenCV backend; peak
   RSS of a fresh subprocess that reads the image and runs one detection.
3. Model files: parameters, model.pt / model.onnx sizes.

Writes bench/results/hma_bench.json and prints it.

    .venv/bin/python bench/hma_bench.py [--model-dir DIR] [--repeats 3]
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

RESULTS = Path(__file__).parent / "results" / "hma_bench.json"


def big_image(seed: int = 5) -> np.ndarray:
    import tempfile

    import cv2

    from cpdetect.synth_images import SynthImageOptions, write_synth_images

    with tempfile.TemporaryDirectory() as tmp:
        opt = SynthImageOptions(width=2064, height=1376, split="test", markers=(3, 5), empty_prob=0.0)
        write_synth_images(tmp, 1, seed, opt)
        img = cv2.imread(str(next(Path(tmp, "images").iterdir())), cv2.IMREAD_GRAYSCALE)
    return cv2.resize(img, (8256, 5504), interpolation=cv2.INTER_CUBIC)


def peak_rss_mb(model_dir: str, path: str) -> float:
    """Peak RSS (MB) of a fresh process that decodes the 45 MP gray image and detects on it once."""
    code = (
        "import resource, cv2, numpy as np\n"
        "from cpdetect import get_detector\n"
        f"d = get_detector('hma', model_dir={model_dir!r}, backend='opencv')\n"
        f"img = cv2.imread({path!r}, cv2.IMREAD_GRAYSCALE)\n"
        "d.detect(img)\n"
        "print(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    return float(out.stdout.strip().splitlines()[-1])


def main() -> int:
    import cv2

    from learned.adapter import default_model_dir
    from learned.infer import OpenCVBackend, probability_map

    ap = argparse.ArgumentParser()
    ap.add_argument("--model-dir", default=str(default_model_dir()))
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
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
    img = big_image()
    res["image"] = {"width": img.shape[1], "height": img.shape[0]}
    ob = OpenCVBackend(d / "model.onnx")
    from cpdetect import get_detector

    det = get_detector("hma", model_dir=str(d), backend="opencv")
    tp, td = [], []
    for _ in range(args.repeats):
        t = time.perf_counter()
        probability_map(img, ob, (1.0,), max_side=2048, tile=2048)
        tp.append(time.perf_counter() - t)
        t = time.perf_counter()
        r = det.detect(img)
        td.append(time.perf_counter() - t)
    res["probability_map_s_median"] = float(np.median(tp))
    res["detect_s_median"] = float(np.median(td))
    res["detections_45mp"] = len(r.detections)
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        p = str(Path(tmp) / "big.png")
        cv2.imwrite(p, img)
        res["detect_process_peak_rss_MB"] = peak_rss_mb(str(d), p)
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text(json.dumps(res, indent=1) + "\n")
    print(json.dumps(res, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
