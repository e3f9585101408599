"""Benchmark of correspondence-free registration (geometry.registration); writes a JSON of figures.

    .venv/bin/python bench/register_bench.py [--layouts 200] [--baseline-layouts 50]
        [--baseline-max 1000000] [--out bench/results/register_bench.json]

Cases, all in the same run:

* **asymmetric**: 50 surveyed points uniform in a 100 × 100 × 20 m site; 30 of them detected with
  1 cm per-axis noise, plus 10 false detections uniform in the site; 20 surveyed points unseen;
  surveyed coordinates with 3 mm noise; model frame = random similarity (scale 0.1–30 log-uniform,
  random rotation). Success = status "ok" and exactly the true pairing (every true pair found, no
  false detection paired).
* **asymmetric-planar**: the same on a flat 300 × 300 × 2 m drone site (fewer layouts).
* **symmetric**: rectangles, "tables" (4 top corners + 4 inset leg feet), random C2/C3-symmetric 3D
  layouts (with unseen points and false detections), planar layouts with an in-plane mirror line
  (a flip is a proper rotation), planar grids. Success = status "ambiguous".
* **mirror-3d** (control): non-planar layouts symmetric only under a mirror: must be "ok" and correct.
* **baseline**: the seed paper's plain RANSAC over random triplets (``plain_ransac``: same
  verification/refit core, random hypotheses, capped at ``--baseline-max``) on the first
  ``--baseline-layouts`` asymmetric layouts.

Timings are wall-clock (``perf_counter``) and process CPU time per call, single-threaded BLAS, on a
shared machine: median and p95 are reported, plus the median over layouts of the fastest of
``--repeats`` runs of the same call (the figure least disturbed by other load).
"""
from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import json  # noqa: E402
import platform  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from geometry.registration import (RegistrationConfig, plain_ransac, register_points,  # noqa: E402
                                   simulate_detections)


def rot_z(deg: float) -> np.ndarray:
    a = np.radians(deg)
    return np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1.0]])


def symmetric_layouts(rng: np.random.Generator, n_each: int):
    """(kind, surveyed_true (M, 3), n_seen, n_false) of layouts with a non-trivial proper symmetry."""
    out = []
    for _ in range(n_each):
        a, b = rng.uniform(1.0, 4.0), rng.uniform(1.0, 4.0)
        if abs(a - b) < 0.3:
            b = a + 0.5
        out.append(("rectangle", np.array([[0, 0, 0], [a, 0, 0], [a, b, 0], [0, b, 0]]), 4, 0))
        h, d = rng.uniform(0.6, 1.1), rng.uniform(0.05, 0.25)
        top = np.array([[0, 0, h], [a, 0, h], [a, b, h], [0, b, h]])
        legs = np.array([[d, d, 0], [a - d, d, 0], [a - d, b - d, 0], [d, b - d, 0]])
        out.append(("table", np.vstack([top, legs]), 8, 0))
        for order in (2, 3):
            base = rng.uniform([-20, -20, 0], [20, 20, 15], (5, 3))
            pts = np.vstack([base @ rot_z(360.0 * k / order).T for k in range(order)])
            out.append((f"C{order}-3d", pts, len(pts) - 2, 2))
        half = rng.uniform([2, -20, 0], [20, 20, 0], (5, 3))  # planar, mirror line x = 0
        out.append(("planar-mirror", np.vstack([half, half * [-1, 1, 1]]), 10, 1))
        nx, ny = 3, 4
        g = np.stack(np.meshgrid(np.arange(nx) * rng.uniform(5, 10), np.arange(ny) * rng.uniform(5, 10)), -1)
        out.append(("grid", np.c_[g.reshape(-1, 2), np.zeros(nx * ny)], nx * ny, 0))
    return out


def mirror_layouts(rng: np.random.Generator, n: int):
    out = []
    for _ in range(n):
        half = rng.uniform([2, -20, 0], [20, 20, 15], (5, 3))
        out.append(("mirror-3d", np.vstack([half, half * [-1, 1, 1], [[0, 25, 3]]]), 11, 1))
    return out


def stats(values) -> dict:
    v = np.asarray(values, float)
    if len(v) == 0:
        return {}
    return {"median": float(np.median(v)), "p95": float(np.percentile(v, 95)), "mean": float(v.mean()),
            "max": float(v.max())}


def timed(fn):
    w0, c0 = time.perf_counter(), time.process_time()
    r = fn()
    return r, time.perf_counter() - w0, time.process_time() - c0


def run_asymmetric(layout_seed, n_layouts, site, method, label, repeats=1, **kw):
    """Layouts come from ``layout_seed`` alone, so two methods run with the same seed see the same ones."""
    rng = np.random.default_rng(layout_seed)
    method_rng = np.random.default_rng(layout_seed + 1)
    ok = 0
    wall, cpu, best, hyps, scale_err, rms, fails = [], [], [], [], [], [], []
    for k in range(n_layouts):
        sur = rng.uniform([0, 0, 0], site, (50, 3))
        prob = simulate_detections(sur, rng, n_seen=30, n_false=10, noise=0.01, survey_noise=0.003)
        r, w, c = timed(lambda: method(prob.detected, prob.surveyed, rng=method_rng, **kw))
        wall.append(w)
        cpu.append(c)
        # the same call again with the same rng state: the fastest run is the least disturbed by other load
        again = [timed(lambda: method(prob.detected, prob.surveyed, rng=np.random.default_rng(k), **kw))[1]
                 for _ in range(repeats - 1)]
        best.append(min([w] + again))
        hyps.append(r.hypotheses_tried)
        good = r.status == "ok" and r.pairing() == prob.true_pairing()
        ok += good
        if r.world_from_model is not None:
            scale_err.append(abs(r.world_from_model.scale / prob.truth.scale - 1))
            rms.append(r.rms_m)
        if not good:
            fails.append({"layout": k, "status": r.status, "reason": r.reason, "pairs": len(r.pairs),
                          "correct_pairs": sum(r.pairing().get(i) == j for i, j in prob.true_pairing().items())})
    if n_layouts:
        print(f"{label}: {ok}/{n_layouts} correct, median {1e3 * np.median(wall):.1f} ms "
              f"(CPU {1e3 * np.median(cpu):.1f} ms, best of {repeats}: {1e3 * np.median(best):.1f} ms), "
              f"p95 {1e3 * np.percentile(wall, 95):.1f} ms", flush=True)
    return {"layouts": n_layouts, "correct": ok, "correct_rate": ok / max(1, n_layouts),
            "wall_ms": {k: 1e3 * v for k, v in stats(wall).items()},
            "cpu_ms": {k: 1e3 * v for k, v in stats(cpu).items()},
            "wall_best_of_repeats_ms": {k: 1e3 * v for k, v in stats(best).items()}, "repeats": repeats,
            "hypotheses": stats(hyps), "relative_scale_error": stats(scale_err), "rms_m": stats(rms),
            "failures": fails[:20]}


def run_layouts(rng, layouts, expect):
    results = {}
    for kind, sur, n_seen, n_false in layouts:
        prob = simulate_detections(sur, rng, n_seen=n_seen, n_false=n_false, noise=0.005, survey_noise=0.002,
                                   false_box=np.array([sur.min(0) - 1, sur.max(0) + 1]))
        r, w, _ = timed(lambda: register_points(prob.detected, prob.surveyed, rng=rng))
        good = r.status == expect and (expect != "ok" or r.pairing() == prob.true_pairing())
        d = results.setdefault(kind, {"layouts": 0, "as_expected": 0, "statuses": {}, "wall_ms": [],
                                      "alternatives": []})
        d["layouts"] += 1
        d["as_expected"] += int(good)
        d["statuses"][r.status] = d["statuses"].get(r.status, 0) + 1
        d["wall_ms"].append(1e3 * w)
        d["alternatives"].append(len(r.alternatives))
    for kind, d in results.items():
        d["wall_ms"] = stats(d["wall_ms"])
        d["alternatives"] = stats(d["alternatives"])
        print(f"{kind}: {d['as_expected']}/{d['layouts']} {expect} ({d['statuses']})", flush=True)
    return results


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--layouts", type=int, default=200)
    ap.add_argument("--planar-layouts", type=int, default=50)
    ap.add_argument("--symmetric-each", type=int, default=10)
    ap.add_argument("--baseline-layouts", type=int, default=50)
    ap.add_argument("--baseline-max", type=int, default=1_000_000)
    ap.add_argument("--seed", type=int, default=2026)
    ap.add_argument("--repeats", type=int, default=3, help="timing repeats per layout (index method)")
    ap.add_argument("--out", default=str(ROOT / "bench" / "results" / "register_bench.json"))
    args = ap.parse_args(argv)

    rng = np.random.default_rng(args.seed)
    # warm-up (imports, caches)
    warm = simulate_detections(rng.uniform([0, 0, 0], [100, 100, 20], (50, 3)), rng, n_seen=30, n_false=10)
    register_points(warm.detected, warm.surveyed, rng=rng)

    report = {
        "bench": "register_bench", "seed": args.seed, "when": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "machine": {"platform": platform.platform(), "python": platform.python_version(),
                    "cpu_count": os.cpu_count(), "numpy": np.__version__,
                    "load_avg": os.getloadavg() if hasattr(os, "getloadavg") else None},
        "config": {k: getattr(RegistrationConfig(), k) for k in RegistrationConfig.__dataclass_fields__},
        "setup": {"surveyed": 50, "detected_true": 30, "detected_false": 10, "surveyed_unseen": 20,
                  "noise_m": 0.01, "survey_noise_m": 0.003, "site_m": [100, 100, 20],
                  "scale_range": [0.1, 30]},
    }
    report["asymmetric"] = run_asymmetric(args.seed + 10, args.layouts, [100, 100, 20], register_points,
                                          "triplet index", repeats=args.repeats)
    report["asymmetric_planar"] = run_asymmetric(args.seed + 20, args.planar_layouts, [300, 300, 2],
                                                 register_points, "triplet index, planar site", repeats=args.repeats)
    sym_rng = np.random.default_rng(args.seed + 30)
    report["symmetric"] = run_layouts(sym_rng, symmetric_layouts(sym_rng, args.symmetric_each), "ambiguous")
    report["mirror_3d_control"] = run_layouts(sym_rng, mirror_layouts(sym_rng, args.symmetric_each), "ok")
    # the baseline sees the same layouts as the first ones of the asymmetric case (same seed)
    report["baseline_plain_ransac"] = run_asymmetric(
        args.seed + 10, args.baseline_layouts, [100, 100, 20], plain_ransac, f"plain RANSAC (cap {args.baseline_max})", max_hypotheses=args.baseline_max)
    report["baseline_plain_ransac"]["max_hypotheses"] = args.baseline_max
    report["baseline_plain_ransac"]["note"] = (
        "same layouts as the first asymmetric ones; same verification, statistical early accept and refit core, "
        "random ordered triplets on both sides instead of the index (the paper stops when the mean distance is "
        "below 10 cm, which presumes every point paired; the early-accept test replaces it here)")
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_suffix(".json.part")
    tmp.write_text(json.dumps(report, indent=1) + "\n")
    os.replace(tmp, out)
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
