"""Centre refinement where it is hard: markers partly covered by an occluder or near the image border.

On a generated set with *train*-split backgrounds (the set the refinement's window choice was made
on; ``--data`` reuses one), the classical detector runs on every image that has a covered marker or
one whose centre lies within the fitting window (+4 px) of the border, and every call it makes to
:func:`cpdetect.refine.refine_center_coarse_to_fine` (its gray centre) is recorded with its seed and
allowed shift. Each recorded call near a true marker is then replayed, from the same seed, by
- ``auto`` (what the detector runs: the default method, symmetry on the full window and on smaller
  ones when that is uncertain, on a reduced window first where the shift exceeds 16 px);
- ``symmetry_full_window`` (the point-symmetry fit on the full window only);
- ``cv2.cornerSubPix`` with the window adapted to the marker (peer);
and the error against the true centre is summarised for the covered markers and for the others.
Then ``--tip-n`` analytic markers, each with an occluder's tip beside its (visible) centre, are
refined from seeds up to 3 px off by ``auto``, the symmetry fit alone, the Hough lines alone and
``cv2.cornerSubPix`` (:func:`occluder_tip_study`).

Writes bench/results/refine_bench.json and prints a summary.

    .venv/bin/python bench/refine_bench.py --n 400 --seed 11      # ~ 5 minutes on 2 cores
"""
from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np
from train_split import train_split_dataset

RESULTS = Path(__file__).parent / "results" / "refine_bench.json"


def _stats(errors: list[float]) -> dict:
    """detect_bench's error summary of the finite errors, with the failures and the count over 0.5 px."""
    from detect_bench import _stats as summary

    a = np.asarray([e for e in errors if np.isfinite(e)], float)
    return dict(summary(a), failed=int(len(errors) - a.size), **{"over_0.5px": int((a > 0.5).sum())})


def hard(marker, width: int, height: int) -> bool:
    from cpdetect.refine import default_window

    if marker.extra.get("occluded_frac", 0.0) > 0:
        return True
    edge = min(marker.x + 0.5, marker.y + 0.5, width - 0.5 - marker.x, height - 0.5 - marker.y)
    return edge < default_window(marker.radius_px) + 4


def record_calls(ds) -> list[dict]:
    """The detector's centre refinements near true markers on the images with hard markers."""
    import cv2

    import cpdetect.classical as classical

    calls: list[tuple] = []
    real = classical.refine_center_coarse_to_fine

    def spy(gray, x, y, radius, method="auto", *, max_shift_px):
        calls.append((x, y, radius, max_shift_px))
        return real(gray, x, y, radius, method=method, max_shift_px=max_shift_px)

    det = classical.ClassicalDetector()
    rows = []
    classical.refine_center_coarse_to_fine = spy
    try:
        for item in ds.images:
            gray = cv2.imread(str(ds.image_path(item)), cv2.IMREAD_GRAYSCALE)
            h, w = gray.shape
            if not any(hard(m, w, h) for m in item.markers):
                continue
            calls.clear()
            det.detect(gray)
            for x, y, radius, shift in calls:
                for m in item.markers:
                    if math.hypot(x - m.x, y - m.y) < max(3.0, 0.3 * m.radius_px):
                        rows.append({"file": item.file, "x": x, "y": y, "radius": radius, "max_shift": shift,
                                     "tx": m.x, "ty": m.y, "covered": m.extra.get("occluded_frac", 0.0) > 0})
    finally:
        classical.refine_center_coarse_to_fine = real
    return rows


def replay(ds, rows: list[dict]) -> dict:
    import cv2

    from cpdetect.refine import default_window, refine_center, refine_center_coarse_to_fine

    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 100, 1e-4)
    errors = {k: {"covered": [], "other": []} for k in ("auto", "symmetry_full_window", "cornerSubPix_adaptive")}
    images: dict[str, np.ndarray] = {}
    for r in rows:
        if r["file"] not in images:
            images[r["file"]] = cv2.imread(str(ds.root / r["file"]), cv2.IMREAD_GRAYSCALE)
        g = images[r["file"]]
        group = "covered" if r["covered"] else "other"
        for key, fit in (("auto", refine_center_coarse_to_fine), ("symmetry_full_window", None)):
            if fit is None:
                res = refine_center(g, r["x"], r["y"], r["radius"], method="symmetry", max_shift_px=r["max_shift"])
            else:
                res = fit(g, r["x"], r["y"], r["radius"], max_shift_px=r["max_shift"])
            errors[key][group].append(math.hypot(res.x - r["tx"], res.y - r["ty"]) if res.ok else math.nan)
        win = int(round(default_window(r["radius"])))
        p = cv2.cornerSubPix(g, np.array([[[r["x"], r["y"]]]], np.float32), (win, win), (-1, -1), crit)
        errors["cornerSubPix_adaptive"][group].append(float(math.hypot(p[0, 0, 0] - r["tx"], p[0, 0, 1] - r["ty"])))
    return {k: {"all": _stats(v["covered"] + v["other"]), "covered": _stats(v["covered"]), "other": _stats(v["other"])}
            for k, v in errors.items()}


def _tip_case(rng: np.random.Generator, marker_type: str):
    """One analytic marker (radius 10-35 px, tilt 0-50 degrees, dark 40, bright 210 on 120) with a
    wedge-shaped occluder of random grey whose tip lies 1.5 px to 0.6 radii from the centre (the
    centre itself visible), blurred 0.3-1.2 px, noise 2; returns (image, true centre, radius, seed
    within 3 px per axis)."""
    import cv2

    from cpdetect.markers import MarkerSpec, plane_homography, projected_center, projected_radius, render_marker

    rad = rng.uniform(10, 35)
    centre = (80 + rng.uniform(-0.5, 0.5), 80 + rng.uniform(-0.5, 0.5))
    f = 900.0
    K = np.array([[f, 0, centre[0]], [0, f, centre[1]], [0, 0, 1.0]])
    axis = rng.uniform(0, np.pi)
    tilt = np.radians(rng.uniform(0, 50))
    R = cv2.Rodrigues(np.array([np.cos(axis), np.sin(axis), 0.0]) * tilt)[0] @ \
        cv2.Rodrigues(np.array([0.0, 0.0, rng.uniform(0, np.pi)]))[0]
    spec = MarkerSpec(marker_type, size_m=1.0)
    H = plane_homography(K, R, np.array([0.0, 0.0, f * 0.5 / rad]))
    img = np.full((160, 160), 120.0, np.float32)
    render_marker(spec, H, img.shape).composite(img, 40.0, 210.0)
    c, r = projected_center(H), projected_radius(spec, H)
    a, d0, spread = rng.uniform(0, 2 * np.pi), rng.uniform(1.5, 0.6 * rad), rng.uniform(0.3, 1.2)
    u = lambda t: np.array([np.cos(t), np.sin(t)])  # noqa: E731
    tip = c + d0 * u(a)
    wedge = np.array([tip, tip + 2 * rad * u(a - spread), tip + 2.5 * rad * u(a), tip + 2 * rad * u(a + spread)])
    cv2.fillPoly(img, [np.round(wedge * 16).astype(np.int32)], float(rng.uniform(20, 230)), cv2.LINE_AA, 4)
    img = cv2.GaussianBlur(img, (0, 0), rng.uniform(0.3, 1.2)) + rng.normal(0, 2.0, img.shape).astype(np.float32)
    return np.clip(img, 0, 255).astype(np.float32), c, r, c + rng.uniform(-3, 3, 2)


def occluder_tip_study(n: int, seed: int) -> dict:
    """:func:`_tip_case` markers (the three types in turn), each refined from its seed with the
    shift the detector allows (0.3 radius, at least 2 px) by ``auto``, the symmetry fit alone, the
    Hough lines alone and ``cv2.cornerSubPix`` (adaptive window, peer)."""
    import cv2

    from cpdetect.refine import default_window, refine_center

    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 100, 1e-4)
    rng = np.random.default_rng(seed)
    errors: dict[str, list[float]] = {k: [] for k in ("auto", "symmetry", "hough", "cornerSubPix_adaptive")}
    for i in range(n):
        img, c, r, s = _tip_case(rng, ("square", "circle", "diagonal")[i % 3])
        shift = max(2.0, 0.3 * r)
        for key in ("auto", "symmetry", "hough"):
            res = refine_center(img, s[0], s[1], r, method=key, max_shift_px=shift)
            errors[key].append(math.hypot(res.x - c[0], res.y - c[1]) if res.ok else math.nan)
        win = int(round(default_window(r)))
        p = cv2.cornerSubPix(img, np.array([[s]], np.float32), (win, win), (-1, -1), crit)
        errors["cornerSubPix_adaptive"].append(float(math.hypot(p[0, 0, 0] - c[0], p[0, 0, 1] - c[1])))
    return {k: _stats(v) for k, v in errors.items()}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=400)
    ap.add_argument("--seed", type=int, default=11)
    ap.add_argument("--data", help="reuse (or generate into) this train-split dataset folder")
    ap.add_argument("--out", default=str(RESULTS))
    ap.add_argument("--tip-n", type=int, default=480, help="analytic markers with an occluder's tip beside the centre")
    args = ap.parse_args(argv)
    ds = train_split_dataset(args.data, args.n, args.seed, "cpdetect_refine_bench_")
    rows = record_calls(ds)
    result = {"dataset": str(ds.root), "images": len(ds.images), "calls": len(rows), "methods": replay(ds, rows),
              "occluder_tip": {"markers": args.tip_n, "seed": args.seed,
                               "methods": occluder_tip_study(args.tip_n, args.seed)}}
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_suffix(".tmp")
    tmp.write_text(json.dumps(result, indent=1))
    tmp.replace(out)
    print(f"{len(rows)} refinement calls of the classical detector near covered or border markers "
          f"({len(ds.images)} images)")
    for k, v in result["methods"].items():
        line = "  ".join(f"{g} n {s['n']} mean {s.get('mean', math.nan):.3f} p95 {s.get('p95', math.nan):.3f} "
                         f">0.5px {s.get('over_0.5px', 0)} failed {s['failed']}" for g, s in v.items())
        print(f"{k:22s} {line}")
    print(f"{args.tip_n} analytic markers with an occluder's tip beside the centre:")
    for k, st in result["occluder_tip"]["methods"].items():
        print(f"{k:22s} mean {st.get('mean', math.nan):.3f} median {st.get('median', math.nan):.3f} "
              f"p95 {st.get('p95', math.nan):.3f} >0.5px {st.get('over_0.5px', 0)} failed {st['failed']}")
    print(f"written {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
