"""bench/hma_bench.py's per-layer profile of the shipped network through OpenCV's DNN."""
from __future__ import annotations

import numpy as np

from bench_loader import load_bench


def test_layer_profile_groups_every_layer_by_part():
    from learned.adapter import default_model_dir
    from learned.infer import OpenCVBackend

    hma_bench = load_bench("hma_bench")
    backend = OpenCVBackend(default_model_dir() / "model.onnx")
    x = np.random.default_rng(0).random((96, 128), dtype=np.float32)
    prof = hma_bench.layer_profile(backend, x, top=5)
    assert prof["input"] == [96, 128]
    assert prof["total_ms"] > 0
    share = prof["share"]
    assert set(share) <= {"backbone", "ocr", "cls_head", "attn_head", "other"}
    # every part of the graph is named as learned.export names it: the backbone and OCR head hold most layers
    assert share["backbone"] > 0.05 and share["ocr"] > 0.05
    assert abs(sum(share.values()) - 1.0) < 0.01
    assert len(prof["slowest_ms"]) == 5
    times = list(prof["slowest_ms"].values())
    assert times == sorted(times, reverse=True) and times[0] > 0
