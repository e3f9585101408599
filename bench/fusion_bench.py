"""Cloud colorization speed: fuse probability maps of N images into a cloud of P points.

Scene: a wavy terrain heightfield of P points (100 x 100 model units) with normals, and its triangle
mesh; N nadir/oblique cameras (4000 x 3000 pixels, f = 3000) on a grid 40 units above it; per image a
probability map of 384 x 288 with 8 marker-sized blobs. Times: the mesh depth maps (Open3D ray casting, longest
side 480), the fusion itself (geometry.fusion.fuse_scores, numpy, one image at a time), and as a peer
for the projection step alone, OpenCV's cv2.projectPoints on the same points. Also the sparse path
(geometry.fusion.fuse_scores_sparse: marked pixels lifted to 3D through the depth maps, only the cloud
points near them fused), its time and its agreement with the full fusion.

Usage: .venv/bin/python bench/fusion_bench.py [--points 2000000] [--images 100]
Writes bench/results/fusion_bench.json (wall-clock and process CPU seconds: on a shared machine
the wall clock includes waiting for the CPU).
"""
from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

import numpy as np

from geometry.camera import Camera
from geometry.fusion import FusionView, fuse_scores, fuse_scores_sparse
from geometry.raycast import make_raycasting_scene
from geometry.transforms import Rigid3
from geometry.visibility import mesh_depth_map


def terrain(n_points: int, rng):
    side = int(np.sqrt(n_points))
    g = np.linspace(-50, 50, side)
    X, Y = np.meshgrid(g, g)
    Z = 2.0 * np.sin(X / 7.0) * np.cos(Y / 9.0)
    P = np.column_stack([X.ravel(), Y.ravel(), Z.ravel()])
    dzdx = 2.0 / 7.0 * np.cos(X / 7.0) * np.cos(Y / 9.0)
    dzdy = -2.0 / 9.0 * np.sin(X / 7.0) * np.sin(Y / 9.0)
    N = np.column_stack([-dzdx.ravel(), -dzdy.ravel(), np.ones(P.shape[0])])
    N /= np.linalg.norm(N, axis=1, keepdims=True)
    # coarse mesh of the same surface (every 4th grid node)
    s = 4
    gx, gy = g[::s], g[::s]
    MX, MY = np.meshgrid(gx, gy)
    MZ = 2.0 * np.sin(MX / 7.0) * np.cos(MY / 9.0)
    V = np.column_stack([MX.ravel(), MY.ravel(), MZ.ravel()])
    m = len(gx)
    i, j = np.meshgrid(np.arange(m - 1), np.arange(m - 1), indexing="ij")
    a = (i * m + j).ravel()
    T = np.concatenate([np.column_stack([a, a + 1, a + m + 1]), np.column_stack([a, a + m + 1, a + m])])
    return P + rng.normal(0, 0.01, P.shape), N, V, T


def cameras(n: int, rng):
    cam = Camera(4000, 3000, 3000.0, 3000.0, 1999.5, 1499.5, dist=(-0.05, 0.01, 0, 0, 0))
    k = int(np.ceil(np.sqrt(n)))
    out = []
    for idx in range(n):
        cx = -40 + 80 * (idx % k) / max(k - 1, 1)
        cy = -40 + 80 * (idx // k) / max(k - 1, 1)
        C = np.array([cx, cy, 40.0])
        target = np.array([cx + rng.uniform(-10, 10), cy + rng.uniform(-10, 10), 0.0])
        z = target - C
        z /= np.linalg.norm(z)
        x = np.cross(z, [0.0, 1.0, 0.0])
        x /= np.linalg.norm(x)
        y = np.cross(z, x)
        R = np.stack([x, y, z])
        out.append(Rigid3(R, -R @ C))
    return cam, out


def prob_map(rng, h=288, w=384, blobs=8):
    """Marker-like blobs: a 0.3-unit marker seen from 40 units with f = 3000 is ~11 px in radius at
    full resolution, 1-2 px in this 384 x 288 map; radii 1-3 px, and soft edges."""
    yy, xx = np.mgrid[0:h, 0:w]
    p = np.zeros((h, w), np.float32)
    for _ in range(blobs):
        cx, cy, r = rng.uniform(0, w), rng.uniform(0, h), rng.uniform(1, 3)
        d = np.sqrt((xx - cx) ** 2 + (yy - cy) ** 2)
        p = np.maximum(p, np.clip(r + 0.5 - d, 0, 1).astype(np.float32))
    return p


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--points", type=int, default=2_000_000)
    ap.add_argument("--images", type=int, default=100)
    args = ap.parse_args()
    rng = np.random.default_rng(0)
    t0 = time.perf_counter()
    P, N, V, T = terrain(args.points, rng)
    cam, poses = cameras(args.images, rng)
    probs = [prob_map(rng) for _ in poses]
    t_setup = time.perf_counter() - t0

    rc = make_raycasting_scene(vertices=V, triangles=T)
    t0, c0 = time.perf_counter(), time.process_time()
    depth = [mesh_depth_map(rc, cam, pose, max_side=480) for pose in poses]
    t_depth, c_depth = time.perf_counter() - t0, time.process_time() - c0

    views = [FusionView(cam, pose, pr, dm) for pose, pr, dm in zip(poses, probs, depth)]
    t0, c0 = time.perf_counter(), time.process_time()
    res = fuse_scores(P, views, N)
    t_fuse, c_fuse = time.perf_counter() - t0, time.process_time() - c0

    # sparse path: only points near marked pixels (lifted with the depth maps) are fused
    from scipy.spatial import cKDTree

    t0, c0 = time.perf_counter(), time.process_time()
    tree = cKDTree(P)
    t_tree = time.perf_counter() - t0
    sp = fuse_scores_sparse(P, views, N, tree=tree)
    t_sparse, c_sparse = time.perf_counter() - t0, time.process_time() - c0
    marked = res.score > 0
    agree = float(np.max(np.abs(sp.score[marked] - res.score[marked]))) if marked.any() else 0.0
    missed = int((marked & (sp.score == 0)).sum())

    # peer for the projection step: cv2.projectPoints on all points, first 10 images
    import cv2

    k = min(10, len(poses))
    t0 = time.perf_counter()
    for pose in poses[:k]:
        rvec, _ = cv2.Rodrigues(pose.R)
        cv2.projectPoints(P, rvec, pose.t, cam.K, np.array(cam.dist))
    t_cv = (time.perf_counter() - t0) / k
    t0 = time.perf_counter()
    for pose in poses[:k]:
        cam.project(pose(P))
    t_np = (time.perf_counter() - t0) / k

    n_obs = int(res.n_views.sum())
    out = {
        "points": int(len(P)), "images": len(poses), "image_size": [cam.width, cam.height],
        "probability_map_size": [384, 288], "depth_map_max_side": 480, "mesh_triangles": int(len(T)),
        "seconds_setup": round(t_setup, 2),
        "seconds_depth_maps": round(t_depth, 2),
        "seconds_fusion": round(t_fuse, 2),
        "seconds_total": round(t_depth + t_fuse, 2),
        "seconds_fusion_per_image": round(t_fuse / len(poses), 4),
        "cpu_seconds_depth_maps": round(c_depth, 2), "cpu_seconds_fusion": round(c_fuse, 2),
        "visible_point_views": n_obs,
        "sparse": {"seconds": round(t_sparse, 2), "cpu_seconds": round(c_sparse, 2),
                   "seconds_kdtree": round(t_tree, 2), "points_fused": int((sp.weight > 0).sum()),
                   "points_with_score_above_0_exact": int(marked.sum()),
                   "of_those_missed_by_sparse": missed, "max_score_difference": agree},
        "points_seen_by_any_image": int((res.n_views > 0).sum()),
        "projection_seconds_per_image": {"numpy Camera.project (ours)": round(t_np, 4),
                                         "cv2.projectPoints (peer)": round(t_cv, 4)},
        "machine": {"cpus": __import__("os").cpu_count(), "python": platform.python_version(),
                    "note": "shared 2-core machine, other jobs running"},
    }
    path = Path(__file__).parent / "results" / "fusion_bench.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(out, indent=1) + "\n")
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
