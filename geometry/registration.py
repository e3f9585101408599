"""Correspondence-free registration of detected marker points to surveyed points.

Given N detected points in the (arbitrary, unknown-scale) model frame and M surveyed points in a
metric Cartesian frame (metres; use ``geometry.crs.LocalFrame`` for geographic/projected CRSs), find
which detected point is which surveyed point and the 7-parameter similarity ``world_from_model``
(a :class:`~geometry.transforms.Sim3`), with false detections and unseen surveyed points on both sides.

Method (the 3D version of star-tracker "asterism" matching; seed paper §5.2 done better):

1. **Hypotheses** come from a pluggable generator (:class:`TripletIndex` by default,
   :class:`RandomTriplets` for the paper's plain RANSAC baseline). Each hypothesis is an ordered
   pair of triplets (3 detected ↔ 3 surveyed points). ``TripletIndex`` indexes triangles by their
   scale-invariant sorted side ratios (L0/L2, L1/L2), rejects needle-like triangles (L2/L0 > 10),
   triangles whose shortest side or height is small against the tolerance (near-duplicate points,
   near-collinear triplets: the old ODM "optimal triplet" failure), looks detected triangles up with a
   KD-tree within the worst-case invariant error 4·tol/L2, largest (most discriminative) surveyed
   triangles first, and expands vertex orders that are consistent with the side lengths (ties).
2. **One verification core** for every generator: batch Umeyama fits of the triplets, rejection of
   triplets whose own residual exceeds the tolerance, then all detected points are transformed and
   counted as inliers when within ``tol`` of a surveyed point (scipy cKDTree, vectorised).
3. **Early accept** on a statistical test (tetra3): the binomial probability that ≥ k−3 of the other
   N−3 detected points land within ``tol`` of a surveyed point by chance, times the number of
   hypotheses the generator could produce (Bonferroni), below ``accept_alpha``.
4. **Refit → re-assign → refit** (one-to-one nearest neighbours within ``tol``) until the pairing is
   stable; the final similarity is the least-squares (Umeyama) fit on all pairs. With the default
   automatic tolerance, the per-axis noise is re-estimated from the residuals and the tolerance
   adapted (bounded) before the final assignment.
5. **Ambiguity**: probe triangles of the matched detected points are looked up again against *all*
   surveyed triangles; every hypothesis that refines to a pairing that maps some detected point to a
   *different* surveyed point and explains the data almost as well (pairs ≥ best − margin, rms ≤
   factor × best) is an alternative, and the status becomes ``ambiguous``. Alternatives are looked
   for at the best pairing's scale (± 2 % + 4·tol on the probe's longest side): a pairing of about the
   same points at a different scale would need a self-similar layout. Rotationally symmetric
   layouts (a rectangle's corners, the paper's "table") are ambiguous; a layout that is only mirror
   symmetric is not (det R = +1), *except* when it is planar: flipping a plane over is a proper
   rotation, so a planar layout with an in-plane mirror line is ambiguous too (the flipped model would
   be upside down; no "up" prior is used).

Units: ``tolerance`` and all residuals/rms are in surveyed units (metres). Everything is float64 and
both point sets are centred on their centroids before any arithmetic.
"""
from __future__ import annotations

import itertools
import logging
import math
import time
from dataclasses import dataclass, field
from functools import lru_cache
from typing import Iterator, Protocol

import numpy as np
from scipy.spatial import cKDTree
from scipy.special import betainc

from .similarity import degeneracy_reason, fit_similarity, fit_similarity_batch
from .transforms import Sim3

log = logging.getLogger(__name__)

_PERMS = np.array(list(itertools.permutations(range(3))), dtype=np.intp)  # (6, 3)


# ----------------------------------------------------------------------------------------------
# Configuration and results
# ----------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class RegistrationConfig:
    """Settings of :func:`register_points` (units: surveyed units, i.e. metres).

    tolerance: inlier distance between a transformed detected point and its surveyed point; None
      derives it from ``noise`` (``tolerance_sigmas × noise``) and, when ``adapt_tolerance``, adapts it
      to the per-axis noise estimated from the residuals of the best pairing (clamped to
      [0.5, 3] × the initial value).
    noise: assumed per-axis standard deviation of (surveyed − transformed detected), e.g. 1 cm.
    max_side_ratio: needle filter L2/L0 for surveyed triangles (detected ones get 1.25× that).
    min_side_tolerances / min_height_tolerances: an indexed surveyed triangle needs its shortest side
      and its height over the longest side at least this many tolerances (near-duplicate points and
      near-collinear triplets give badly conditioned similarities).
    full_index_limit: up to this many points all C(n, 3) triangles are indexed, above it the
      triangles of each point with pairs of its ``knn`` nearest neighbours.
    accept_alpha: early-accept threshold on the Bonferroni-corrected chance probability.
    final_alpha: the same test on the final pairing against the hypotheses actually tried; a pairing
      that fails it is still accepted when it explains every point of the smaller set (≥ 3 pairs).
    ambiguity_margin: an alternative needs ≥ best_pairs − floor(margin × best_pairs) pairs.
    ambiguity_rms_factor: ... and rms ≤ factor × max(best rms, tolerance / 6).
    ambiguity_probes: number of probe triangles used by the ambiguity search (all of them when the
      matched set is small).
    max_hypotheses: hard cap on hypotheses verified in the main search.
    batch: hypotheses verified per vectorised batch (also capped by batch × N ≤ 250 000 points).
    """

    tolerance: float | None = None
    noise: float = 0.01
    tolerance_sigmas: float = 6.0
    adapt_tolerance: bool = True
    max_side_ratio: float = 10.0
    min_side_tolerances: float = 6.0
    min_height_tolerances: float = 4.0
    full_index_limit: int = 60
    knn: int = 10
    accept_alpha: float = 1e-3
    final_alpha: float = 1e-2
    ambiguity_margin: float = 0.1
    ambiguity_rms_factor: float = 2.0
    ambiguity_probes: int = 6
    max_hypotheses: int = 200_000
    batch: int = 512
    max_refine_iterations: int = 20

    def __post_init__(self) -> None:
        if self.tolerance is not None and not (np.isfinite(self.tolerance) and self.tolerance > 0):
            raise ValueError(f"tolerance must be positive, got {self.tolerance}")
        if not (np.isfinite(self.noise) and self.noise > 0):
            raise ValueError(f"noise must be positive, got {self.noise}")

    @property
    def initial_tolerance(self) -> float:
        return float(self.tolerance) if self.tolerance is not None else self.tolerance_sigmas * self.noise


@dataclass(frozen=True)
class PointPair:
    """Detected point ``detected`` (row index) is surveyed point ``surveyed``; residual in metres."""

    detected: int
    surveyed: int
    residual: float


@dataclass(frozen=True)
class Alternative:
    """A different pairing that explains the data almost as well as the reported one."""

    pairs: tuple[tuple[int, int], ...]
    rms: float
    n_inliers: int
    world_from_model: Sim3


@dataclass
class RegistrationResult:
    """Outcome of :func:`register_points`.

    status: "ok", "ambiguous" (a different pairing explains the data almost as well: see
      ``alternatives``; ``world_from_model``/``pairs`` are the best-scoring one) or "failed" (no
      transform; see ``reason``).
    world_from_model: x_world = s·R·x_model + t (world = the surveyed frame given), or None.
    pairs: matched points with residuals; unmatched_detected / unmatched_surveyed: row indices.
    rms_m: RMS of the pair residuals (metres; nan when failed); sigma_m: per-axis noise estimated
      from them (nan with < 4 pairs); tolerance_m: inlier tolerance finally used.
    hypotheses_tried: hypotheses verified (main search and ambiguity search); generator: its name.
    chance_probability: Bonferroni-corrected probability that the pairing is a coincidence.
    """

    status: str
    world_from_model: Sim3 | None = None
    pairs: list[PointPair] = field(default_factory=list)
    unmatched_detected: list[int] = field(default_factory=list)
    unmatched_surveyed: list[int] = field(default_factory=list)
    rms_m: float = float("nan")
    alternatives: list[Alternative] = field(default_factory=list)
    hypotheses_tried: int = 0
    reason: str = ""
    tolerance_m: float = float("nan")
    sigma_m: float = float("nan")
    chance_probability: float = float("nan")
    generator: str = ""
    seconds: float = 0.0

    @property
    def ok(self) -> bool:
        return self.status == "ok"

    def pairing(self) -> dict[int, int]:
        """{detected row: surveyed row} of the reported pairing."""
        return {p.detected: p.surveyed for p in self.pairs}


# ----------------------------------------------------------------------------------------------
# Triangles
# ----------------------------------------------------------------------------------------------

@lru_cache(maxsize=8)
def _all_triplets(n: int) -> np.ndarray:
    """All C(n, 3) sorted index triplets, (T, 3); cached and read-only."""
    out = np.array(list(itertools.combinations(range(n), 3)), dtype=np.intp).reshape(-1, 3)
    out.flags.writeable = False
    return out


def _candidate_triplets(points: np.ndarray, full_limit: int, knn: int) -> np.ndarray:
    """(T, 3) sorted index triplets: all C(n, 3) up to ``full_limit`` points, else each point with every
    pair of its ``knn`` nearest neighbours (astroalign-style local triangles), deduplicated."""
    n = len(points)
    if n <= full_limit:
        return _all_triplets(n)
    k = min(knn, n - 1)
    _, nbr = cKDTree(points).query(points, k=k + 1)  # column 0 is the point itself
    pairs = np.array(list(itertools.combinations(range(1, k + 1), 2)), dtype=np.intp)
    apex = np.repeat(np.arange(n), len(pairs))[:, None]
    tri = np.concatenate([apex, nbr[:, pairs].reshape(-1, 2)], axis=1)
    tri.sort(axis=1)
    tri = tri[(tri[:, 0] != tri[:, 1]) & (tri[:, 1] != tri[:, 2])]
    return np.unique(tri, axis=0)


def _distance_matrix(points: np.ndarray) -> np.ndarray:
    diff = points[:, None, :] - points[None, :, :]
    return np.sqrt(np.einsum("ijk,ijk->ij", diff, diff))


def _cswap(x, y, i, j):
    """Compare-swap: (min, max) of x, y with their labels."""
    swap = x > y
    return (np.where(swap, y, x), np.where(swap, x, y), np.where(swap, j, i), np.where(swap, i, j))


@dataclass(frozen=True)
class Triangles:
    """Triangles of a point set in canonical vertex order.

    vertices: (T, 3) point indices ordered so that the side opposite vertex i is the i-th shortest;
    sides: (T, 3) those opposite sides L0 ≤ L1 ≤ L2 (point units); inv: (T, 2) (L0/L2, L1/L2);
    height: (T,) height of the triangle over its longest side.
    """

    vertices: np.ndarray
    sides: np.ndarray
    inv: np.ndarray
    height: np.ndarray

    @classmethod
    def build(cls, points: np.ndarray, triplets: np.ndarray, dist: np.ndarray | None = None) -> "Triangles":
        """Triangles of ``points`` (n, 3) for ``triplets`` (T, 3); ``dist``: optional (n, n) distances."""
        if dist is None:
            dist = _distance_matrix(points)
        a, b, c = triplets[:, 0], triplets[:, 1], triplets[:, 2]
        la, lb, lc = dist[b, c], dist[c, a], dist[a, b]  # sides opposite a, b, c
        # sorting network on (side, vertex) so that the side opposite vertex i is the i-th shortest
        la, lb, a, b = _cswap(la, lb, a, b)
        lb, lc, b, c = _cswap(lb, lc, b, c)
        la, lb, a, b = _cswap(la, lb, a, b)
        sides = np.stack([la, lb, lc], axis=1)
        verts = np.stack([a, b, c], axis=1)
        # Kahan's stable Heron formula with lc >= lb >= la
        prod = (lc + (lb + la)) * (la - (lc - lb)) * (la + (lc - lb)) * (lc + (lb - la))
        area = 0.25 * np.sqrt(np.maximum(prod, 0.0))
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = sides[:, :2] / sides[:, 2:3]
            height = 2.0 * area / lc
        return cls(verts, sides, inv, height)

    def select(self, keep: np.ndarray) -> "Triangles":
        return Triangles(self.vertices[keep], self.sides[keep], self.inv[keep], self.height[keep])

    def __len__(self) -> int:
        return len(self.vertices)


def _consistent_orders(s_sides: np.ndarray, d_sides: np.ndarray, tol: float):
    """For (P, 3) surveyed and detected canonical sides: which of the 6 detected vertex orders fit.

    Returns (pair index (Q,), permutation (Q, 3)) with |scale·Ld[π] − Ls| ≤ 3·tol on every side,
    scale = perimeter ratio. A scalene triangle keeps only the identity; near-isosceles ones more.
    """
    dp = d_sides[:, _PERMS]  # (P, 6, 3)
    scale = s_sides.sum(axis=1) / d_sides.sum(axis=1)
    err = np.abs(scale[:, None, None] * dp - s_sides[:, None, :]).max(axis=2)
    pi, qi = np.nonzero(err <= 3.0 * tol)
    return pi, _PERMS[qi]


# ----------------------------------------------------------------------------------------------
# Problem, hypothesis generators
# ----------------------------------------------------------------------------------------------

@dataclass
class Problem:
    """The centred point sets and everything derived from them that generators and the core share.

    model: (N, 3) detected points minus their centroid (model units); world: (M, 3) surveyed points
    minus their centroid (metres); tol: inlier tolerance (metres); world_tree: KD-tree of ``world``.
    """

    model: np.ndarray
    world: np.ndarray
    tol: float
    config: RegistrationConfig
    world_tree: cKDTree
    chance_p: float
    _world_tris: Triangles | None = None
    _world_cache: tuple | None = None

    def _world_candidates(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(candidate triplets (T, 3), their longest sides (T,), distance matrix (M, M)), cached."""
        if self._world_cache is None:
            c = self.config
            trip = _candidate_triplets(self.world, c.full_index_limit, c.knn)
            dist = _distance_matrix(self.world)
            a, b, cc = trip[:, 0], trip[:, 1], trip[:, 2]
            longest = np.maximum(np.maximum(dist[a, b], dist[b, cc]), dist[a, cc])
            self._world_cache = (trip, longest, dist)
        return self._world_cache

    @property
    def world_longest_sides(self) -> np.ndarray:
        """(T,) longest side of every candidate surveyed triplet (metres)."""
        return self._world_candidates()[1]

    @property
    def n_world_candidates(self) -> int:
        return len(self._world_candidates()[0])

    def world_triangles_of(self, idx: np.ndarray) -> Triangles:
        """Usable surveyed triangles among candidate triplets ``idx`` (shape and size filters at the
        initial tolerance), in the order of ``idx``."""
        trip, _, dist = self._world_candidates()
        c = self.config
        tris = Triangles.build(self.world, trip[idx], dist)
        keep = ((tris.sides[:, 0] >= c.min_side_tolerances * self.tol)
                & (tris.sides[:, 2] <= c.max_side_ratio * tris.sides[:, 0])
                & (tris.height >= c.min_height_tolerances * self.tol))
        return tris.select(keep)

    def world_triangles(self) -> Triangles:
        """All usable surveyed triangles (cached)."""
        if self._world_tris is None:
            self._world_tris = self.world_triangles_of(np.arange(self.n_world_candidates))
        return self._world_tris

    def model_index(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Detected triangles for lookup: (triplets (T, 3), invariants (T, 2), model distance matrix),
        after the scale-free needle filter, sorted by the first invariant. Vertex order is resolved
        later, only for the candidates (``Triangles.build``)."""
        c = self.config
        trip = _candidate_triplets(self.model, c.full_index_limit, c.knn)
        dist = _distance_matrix(self.model)
        a, b, cc = trip[:, 0], trip[:, 1], trip[:, 2]
        la, lb, lc = dist[b, cc], dist[cc, a], dist[a, b]
        l0 = np.minimum(np.minimum(la, lb), lc)
        l2 = np.maximum(np.maximum(la, lb), lc)
        keep = (l2 <= 1.25 * c.max_side_ratio * l0) & (l0 > 0)
        l0, l2 = l0[keep], l2[keep]
        l1 = la[keep] + lb[keep] + lc[keep] - l0 - l2
        inv = np.stack([l0 / l2, l1 / l2], axis=1)
        order = np.argsort(inv[:, 0], kind="stable")
        return trip[keep][order], inv[order], dist


class HypothesisGenerator(Protocol):
    """Yields batches of hypotheses, each an (h, 2, 3) int array: [:, 0] detected rows, [:, 1] the
    surveyed rows they are paired with (same order). ``bound(problem)`` is the number of hypotheses
    the generator could produce (used for the Bonferroni correction)."""

    name: str

    def bound(self, problem: Problem) -> float: ...

    def batches(self, problem: Problem, rng: np.random.Generator) -> Iterator[np.ndarray]: ...


@dataclass(frozen=True)
class TripletIndex:
    """Triangles of the surveyed points indexed by side ratios, matched to detected triangles.

    Surveyed triangles are processed largest first (smallest invariant error → fewest candidates);
    ``chunk`` surveyed triangles are looked up per step.
    """

    chunk: int = 64
    first: int = 1024
    name: str = "triplet-index"

    def bound(self, problem: Problem) -> float:
        return float(max(1, problem.n_world_candidates) * max(1, math.comb(len(problem.model), 3)))

    def batches(self, problem: Problem, rng: np.random.Generator) -> Iterator[np.ndarray]:
        mtrip, minv, mdist = problem.model_index()
        if len(mtrip) == 0:
            return
        # 1D index on the first invariant (sorted), filtered on the second: a box query in
        # (L0/L2, L1/L2) with a per-surveyed-triangle half-width 4·tol/L2 (worst-case invariant error)
        inv0, inv1 = minv[:, 0], minv[:, 1]
        tol = problem.tol
        for sel in _largest_first(problem.world_longest_sides, self.first, self.chunk):
            wt = problem.world_triangles_of(sel)  # built lazily, largest first
            if len(wt) == 0:
                continue
            q = wt.inv
            r = 4.0 * tol / wt.sides[:, 2]
            lo = np.searchsorted(inv0, q[:, 0] - r, side="left")
            n = np.searchsorted(inv0, q[:, 0] + r, side="right") - lo
            total = int(n.sum())
            if total == 0:
                continue
            si = np.repeat(np.arange(len(q)), n)
            di = lo[si] + np.arange(total) - np.repeat(np.cumsum(n) - n, n)
            keep = np.abs(inv1[di] - q[si, 1]) <= r[si]
            if not keep.any():
                continue
            si, di = si[keep], di[keep]
            mt = Triangles.build(problem.model, mtrip[di], mdist)  # one row per candidate pair
            yield from _expand(wt, mt, si, np.arange(len(di)), tol, problem.config.batch)


def _largest_first(values: np.ndarray, first: int, chunk: int) -> Iterator[np.ndarray]:
    """Chunks of indices of ``values`` in descending order. Only the ``first`` largest are sorted up
    front (argpartition); the rest is sorted when a search gets that far (rarely: early accept)."""
    n = len(values)
    if n <= first:
        parts = [np.argsort(-values, kind="stable")]
    else:
        top = np.argpartition(-values, first - 1)
        head = top[:first]
        parts = [head[np.argsort(-values[head], kind="stable")], top[first:]]
    for k, part in enumerate(parts):
        if k == 1:
            part = part[np.argsort(-values[part], kind="stable")]
        for start in range(0, len(part), chunk):
            yield part[start:start + chunk]


def _expand(wt: Triangles, mt: Triangles, si: np.ndarray, di: np.ndarray, tol: float,
            batch: int) -> Iterator[np.ndarray]:
    pi, perm = _consistent_orders(wt.sides[si], mt.sides[di], tol)
    if len(pi) == 0:
        return
    det = np.take_along_axis(mt.vertices[di[pi]], perm, axis=1)
    hyp = np.stack([det, wt.vertices[si[pi]]], axis=1)
    for b in range(0, len(hyp), batch):
        yield hyp[b:b + batch]


@dataclass(frozen=True)
class RandomTriplets:
    """The seed paper's plain RANSAC: uniformly random ordered triplets on both sides."""

    batch: int = 4096
    name: str = "random-triplets"

    def bound(self, problem: Problem) -> float:
        n, m = len(problem.model), len(problem.world)
        return float(math.comb(n, 3) * m * (m - 1) * (m - 2))

    def batches(self, problem: Problem, rng: np.random.Generator) -> Iterator[np.ndarray]:
        n, m = len(problem.model), len(problem.world)
        while True:
            det = np.argsort(rng.random((self.batch, n)), axis=1)[:, :3]
            sur = np.argsort(rng.random((self.batch, m)), axis=1)[:, :3]
            yield np.stack([det, sur], axis=1)


# ----------------------------------------------------------------------------------------------
# Verification / refinement core
# ----------------------------------------------------------------------------------------------

@dataclass
class _Scored:
    count: int
    cost: float
    scale: float
    R: np.ndarray
    t: np.ndarray

    def sim(self) -> Sim3:
        return Sim3(self.scale, self.R, self.t)


def _verify(problem: Problem, hyp: np.ndarray) -> tuple[np.ndarray, np.ndarray, tuple]:
    """Score a batch of hypotheses: inlier counts (h,), MSAC costs (h,), and the fits (s, R, t)."""
    src = problem.model[hyp[:, 0]]
    dst = problem.world[hyp[:, 1]]
    s, R, t = fit_similarity_batch(src, dst)
    tol = problem.tol
    ok = np.isfinite(s) & (s > 0)
    ok &= np.all(np.isfinite(R), axis=(1, 2)) & np.all(np.isfinite(t), axis=1)
    count = np.zeros(len(hyp), dtype=np.intp)
    cost = np.full(len(hyp), np.inf)
    if ok.any():
        idx = np.nonzero(ok)[0]
        fit = s[idx, None, None] * np.einsum("hij,hkj->hki", R[idx], src[idx]) + t[idx, None, :]
        sample_ok = np.linalg.norm(fit - dst[idx], axis=2).max(axis=1) <= tol
        idx = idx[sample_ok]
    else:
        idx = np.zeros(0, dtype=np.intp)
    if len(idx):
        x = s[idx, None, None] * np.einsum("hij,nj->hni", R[idx], problem.model) + t[idx, None, :]
        d, _ = problem.world_tree.query(x.reshape(-1, 3), distance_upper_bound=tol)
        d = d.reshape(len(idx), -1)
        inl = np.isfinite(d)
        count[idx] = inl.sum(axis=1)
        cost[idx] = np.where(inl, d * d, tol * tol).sum(axis=1)
    return count, cost, (s, R, t)


def _chance_probability(problem: Problem, count: int, n_tests: float) -> float:
    """Bonferroni-corrected P(≥ count − 3 of the other N − 3 detected points hit a surveyed point)."""
    n = len(problem.model) - 3
    k = count - 3
    if k <= 0:
        return 1.0
    if n <= 0 or k > n:
        return 1.0 if k > n else 0.0
    tail = float(betainc(k, n - k + 1, problem.chance_p))
    return min(1.0, tail * max(1.0, n_tests))


@dataclass
class _Pairing:
    sim: Sim3
    det: np.ndarray
    sur: np.ndarray
    res: np.ndarray

    @property
    def n(self) -> int:
        return len(self.det)

    @property
    def rms(self) -> float:
        return float(np.sqrt(np.mean(self.res**2))) if len(self.res) else float("nan")

    def key(self) -> frozenset:
        return frozenset(zip(self.det.tolist(), self.sur.tolist()))


def _assign(problem: Problem, sim: Sim3, tol: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pairs (detected rows, surveyed rows, distances): each detected point with its nearest surveyed
    point within ``tol``; a surveyed point claimed by several keeps only the closest (one-to-one)."""
    x = sim(problem.model)
    d, j = problem.world_tree.query(x, distance_upper_bound=tol)
    i = np.nonzero(np.isfinite(d))[0]
    if len(i) == 0:
        return i, i, np.zeros(0)
    j, d = j[i], d[i]
    order = np.lexsort((d, j))  # by surveyed point, closest first
    first = np.ones(len(order), dtype=bool)
    first[1:] = j[order][1:] != j[order][:-1]
    keep = np.sort(order[first])
    return i[keep], j[keep], d[keep]


def _refine(problem: Problem, sim: Sim3, tol: float, max_iter: int) -> tuple[_Pairing | None, str]:
    """Re-assign → refit until the pairing is stable; the last fit is least squares on all pairs."""
    prev = None
    for _ in range(max_iter):
        det, sur, _ = _assign(problem, sim, tol)
        if len(det) < 3:
            return None, f"only {len(det)} pairs within the tolerance"
        key = (det.tobytes(), sur.tobytes())
        if key == prev:
            break
        fit = fit_similarity(problem.model[det], problem.world[sur])
        if not fit:
            return None, f"matched points are degenerate: {fit.reason}"
        sim, prev = fit.sim, key
    res = np.linalg.norm(problem.world[sur] - sim(problem.model[det]), axis=1)
    return _Pairing(sim, det, sur, res), ""


def _sigma_from(p: _Pairing) -> float:
    dof = 3 * p.n - 7
    return float(np.sqrt(np.sum(p.res**2) / dof)) if dof > 0 else float("nan")


# ----------------------------------------------------------------------------------------------
# Ambiguity search
# ----------------------------------------------------------------------------------------------

def _probe_triangles(problem: Problem, best: _Pairing, rng: np.random.Generator, n_probes: int) -> np.ndarray:
    """Well-shaped triangles (detected rows, in canonical order) among the matched points."""
    c = problem.config
    k = best.n
    if k <= 12:
        trip = _all_triplets(k)
    else:
        trip = np.sort(np.argsort(rng.random((40 * n_probes, k)), axis=1)[:, :3], axis=1)
        trip = np.unique(trip, axis=0)
    wtri = Triangles.build(problem.world[best.sur], trip)  # shapes measured in metres
    keep = ((wtri.sides[:, 0] >= c.min_side_tolerances * problem.tol)
            & (wtri.sides[:, 2] <= c.max_side_ratio * wtri.sides[:, 0])
            & (wtri.height >= c.min_height_tolerances * problem.tol))
    trip = trip[keep]
    if len(trip) == 0:
        return trip
    if k > 12 or len(trip) > 4 * n_probes:
        # greedily prefer large triangles with vertices not used yet
        order = np.argsort(-wtri.height[keep])
        chosen, used = [], set()
        for o in order:
            v = set(trip[o].tolist())
            if not (v & used) or len(chosen) * 3 >= k:
                chosen.append(o)
                used |= v
            if len(chosen) >= n_probes:
                break
        trip = trip[chosen]
    return best.det[trip]


def _alternatives(problem: Problem, best: _Pairing, rng: np.random.Generator,
                  tried: list[int]) -> list[_Pairing]:
    """Refined pairings reachable from probe triangles (may include the best pairing itself)."""
    c = problem.config
    probes = _probe_triangles(problem, best, rng, c.ambiguity_probes)
    if len(probes) == 0:
        return []
    ptris = Triangles.build(problem.model, probes)
    # An alternative that explains about the same detected points almost as well has the same scale to
    # within noise (a 2 % different scale would move points by 2 % of the site's extent): only surveyed
    # triangles whose longest side matches a probe's (in metres) within 4·tol + 2 % are candidates.
    metric = best.sim.scale * ptris.sides[:, 2]  # (P,)
    slack = 4.0 * problem.tol + 0.02 * metric
    longest = problem.world_longest_sides
    band = np.zeros(len(longest), dtype=bool)
    for m, sl in zip(metric, slack):
        band |= np.abs(longest - m) <= sl
    wt = problem.world_triangles_of(np.nonzero(band)[0])
    if len(wt) == 0:
        return []
    found: dict[frozenset, _Pairing] = {}
    min_count = best.n - math.floor(c.ambiguity_margin * best.n)
    partner = np.full(len(problem.model), -1)
    partner[best.det] = best.sur
    radius = 4.0 * problem.tol / (best.sim.scale * ptris.sides[:, 2])  # (P,)
    near = np.abs(wt.inv[:, 0, None] - ptris.inv[None, :, 0]) <= radius
    si, di = np.nonzero(near)
    keep = ((np.abs(wt.inv[si, 1] - ptris.inv[di, 1]) <= radius[di])
            & (np.abs(wt.sides[si, 2] - metric[di]) <= slack[di]))
    si, di = si[keep], di[keep]
    if len(si):
        for hyp in _expand(wt, ptris, si, di, problem.tol, c.batch):
            tried[0] += len(hyp)
            # the best pairing's own triangle refines back to it: skip it
            hyp = hyp[~np.all(partner[hyp[:, 0]] == hyp[:, 1], axis=1)]
            if len(hyp) == 0:
                continue
            count, _, (s, R, t) = _verify(problem, hyp)
            for h in np.nonzero(count >= min_count)[0]:
                pairing, _ = _refine(problem, Sim3(s[h], R[h], t[h]), problem.tol, c.max_refine_iterations)
                if pairing is not None and pairing.n >= min_count:
                    found.setdefault(pairing.key(), pairing)
    return list(found.values())


def _conflicts(a: _Pairing, b: _Pairing) -> bool:
    """True when some detected point is paired with different surveyed points in ``a`` and ``b``."""
    ma = dict(zip(a.det.tolist(), a.sur.tolist()))
    return any(ma.get(d, s) != s for d, s in zip(b.det.tolist(), b.sur.tolist()))


# ----------------------------------------------------------------------------------------------
# Entry points
# ----------------------------------------------------------------------------------------------

def _failed(reason: str, t0: float, tried: int = 0, gen: str = "", tol: float = float("nan")) -> RegistrationResult:
    return RegistrationResult("failed", reason=reason, hypotheses_tried=tried, generator=gen, tolerance_m=tol,
                              seconds=time.perf_counter() - t0)


def _chance_p(world: np.ndarray, tol: float) -> float:
    """Probability that a random point in the surveyed region lands within ``tol`` of a surveyed point.

    The region is the box of the surveyed points' principal extents, each at least 2·tol (planar
    and linear sites therefore get an area or length density: conservative)."""
    sv_axes = np.linalg.svd(world - world.mean(axis=0), full_matrices=False)[2]
    proj = world @ sv_axes.T
    ext = np.maximum(proj.max(axis=0) - proj.min(axis=0), 2.0 * tol)
    return float(min(1.0, len(world) * (4.0 / 3.0) * math.pi * tol**3 / np.prod(ext)))


def register_points(detected, surveyed, *, rng: np.random.Generator,
                    config: RegistrationConfig = RegistrationConfig(),
                    generator: HypothesisGenerator | None = None) -> RegistrationResult:
    """Find the pairing and ``world_from_model`` between detected and surveyed points.

    detected: (N, 3) marker points in the model frame (any scale); surveyed: (M, 3) surveyed points
    in a metric Cartesian frame (metres, e.g. ``LocalFrame`` coordinates); rng: numpy Generator (used
    by random generators and probe selection); generator: hypothesis generator (default
    :class:`TripletIndex`). Degenerate inputs (< 3 points, coincident, collinear, non-finite) give a
    ``failed`` result with a reason; wrongly shaped arrays raise ``ValueError``.
    """
    t0 = time.perf_counter()
    gen = generator if generator is not None else TripletIndex()
    det = np.asarray(detected, dtype=np.float64)
    sur = np.asarray(surveyed, dtype=np.float64)
    for name, a in (("detected", det), ("surveyed", sur)):
        if a.ndim != 2 or a.shape[1] != 3:
            raise ValueError(f"{name} points must be an (n, 3) array, got shape {a.shape}")
    c = config
    tol = c.initial_tolerance
    if len(det) < 3 or len(sur) < 3:
        return _failed(f"need at least 3 detected and 3 surveyed points, got {len(det)} and {len(sur)}",
                       t0, gen=gen.name, tol=tol)
    for name, a, noise in (("detected", det, 0.0), ("surveyed", sur, tol)):
        reason = degeneracy_reason(a, noise)
        if reason:
            return _failed(f"{name} {reason}", t0, gen=gen.name, tol=tol)
    world_c = sur.mean(axis=0)
    model_c = det.mean(axis=0)
    world = sur - world_c
    model = det - model_c
    problem = Problem(model, world, tol, c, cKDTree(world), _chance_p(world, tol))

    # --- main search --------------------------------------------------------------------------
    bound = gen.bound(problem)
    tried = 0
    best: _Scored | None = None
    accepted = False
    max_batch_points = 250_000
    for hyp in gen.batches(problem, rng):
        step = max(1, max_batch_points // max(1, len(model)))
        for b in range(0, len(hyp), step):
            sub = hyp[b:b + step]
            count, cost, (s, R, t) = _verify(problem, sub)
            tried += len(sub)
            h = int(np.lexsort((cost, -count))[0])
            if count[h] >= 3 and (best is None or (count[h], -cost[h]) > (best.count, -best.cost)):
                best = _Scored(int(count[h]), float(cost[h]), float(s[h]), R[h].copy(), t[h].copy())
            if best is not None and _chance_probability(problem, best.count, bound) < c.accept_alpha:
                accepted = True
                break
        if accepted or tried >= c.max_hypotheses:
            break
    if best is None:
        if len(problem.world_triangles()) == 0:
            return _failed("no usable surveyed triangle: the surveyed points are nearly collinear or closer "
                           f"than {c.min_side_tolerances:g} tolerances ({c.min_side_tolerances * tol:.3g} m) "
                           "to each other", t0, tried, gen.name, tol)
        return _failed("no consistent pairing: no pair of triangles matches within the tolerance",
                       t0, tried, gen.name, tol)

    # --- refine, adapt the tolerance ------------------------------------------------------------
    pairing, why = _refine(problem, best.sim(), tol, c.max_refine_iterations)
    if pairing is None:
        return _failed(f"no consistent pairing: {why}", t0, tried, gen.name, tol)
    if c.tolerance is None and c.adapt_tolerance and pairing.n >= 6:
        tol0 = tol
        for _ in range(3):
            sigma = _sigma_from(pairing)
            new_tol = float(np.clip(c.tolerance_sigmas * sigma, 0.5 * tol0, 3.0 * tol0))
            if abs(new_tol - tol) <= 0.05 * tol:
                break
            tol = new_tol
            p2, _ = _refine(problem, pairing.sim, tol, c.max_refine_iterations)
            if p2 is None:
                break
            pairing = p2
        problem.tol = tol
        problem.chance_p = _chance_p(world, tol)
    prob = _chance_probability(problem, pairing.n, tried)
    smaller = min(len(model), len(world))
    if not (prob < c.final_alpha or pairing.n >= smaller):
        return _failed(f"no consistent pairing: the best one has {pairing.n} pairs, which chance explains "
                       f"(p = {prob:.2g})", t0, tried, gen.name, tol)

    # --- ambiguity ------------------------------------------------------------------------------
    counter = [0]
    alts: list[_Pairing] = []
    for _ in range(3):  # a probe may find a better pairing (e.g. a shifted grid): restart from it
        cands = _alternatives(problem, pairing, rng, counter)
        better = [p for p in cands if (p.n, -p.rms) > (pairing.n, -pairing.rms + 1e-12) and _conflicts(p, pairing)]
        if better:
            pairing = max(better, key=lambda p: (p.n, -p.rms))
            continue
        alts = cands
        break
    tried += counter[0]
    min_count = pairing.n - math.floor(c.ambiguity_margin * pairing.n)
    rms_cap = c.ambiguity_rms_factor * max(pairing.rms, tol / 6.0)
    alternatives = [p for p in alts if _conflicts(p, pairing) and p.n >= min_count and p.rms <= rms_cap]
    alternatives.sort(key=lambda p: (-p.n, p.rms))

    # --- result ---------------------------------------------------------------------------------
    to_world = Sim3(1.0, np.eye(3), world_c)
    from_model = Sim3(1.0, np.eye(3), -model_c)

    def outer(sim: Sim3) -> Sim3:
        return to_world @ sim @ from_model

    reasons = []
    status = "ok"
    if alternatives:
        status = "ambiguous"
        reasons.append(f"{len(alternatives)} different pairing(s) explain the data almost as well "
                       "(symmetric layout?)")
    dup = problem.world_tree.query_pairs(2.0 * tol)
    used = set(pairing.sur.tolist())
    close = sorted((a, b) for a, b in dup if a in used or b in used)
    if close:
        status = "ambiguous"
        reasons.append("surveyed points closer than two tolerances cannot be told apart: "
                       + ", ".join(f"{a}/{b}" for a, b in close[:5]))
    if pairing.n == 3:
        reasons.append("only 3 pairs: nothing checks the transform")
    order = np.argsort(pairing.det)
    pairs = [PointPair(int(pairing.det[i]), int(pairing.sur[i]), float(pairing.res[i])) for i in order]
    result = RegistrationResult(
        status=status,
        world_from_model=outer(pairing.sim),
        pairs=pairs,
        unmatched_detected=sorted(set(range(len(model))) - set(pairing.det.tolist())),
        unmatched_surveyed=sorted(set(range(len(world))) - used),
        rms_m=pairing.rms,
        alternatives=[Alternative(tuple(sorted(zip(p.det.tolist(), p.sur.tolist()))), p.rms, p.n, outer(p.sim))
                      for p in alternatives],
        hypotheses_tried=tried,
        reason="; ".join(reasons),
        tolerance_m=tol,
        sigma_m=_sigma_from(pairing),
        chance_probability=prob,
        generator=gen.name,
        seconds=time.perf_counter() - t0,
    )
    log.debug("registration %s: %d pairs, rms %.4g m, %d hypotheses, %.1f ms", status, pairing.n,
              pairing.rms, tried, 1e3 * result.seconds)
    return result


def plain_ransac(detected, surveyed, *, rng: np.random.Generator,
                 config: RegistrationConfig = RegistrationConfig(), max_hypotheses: int = 200_000) -> RegistrationResult:
    """The seed paper's method (§5.2): random triplets on both sides, same verification/refit core.

    Only for comparison (bench/register_bench.py): it needs ~1/(P(3 true detections) · M³) hypotheses.
    """
    from dataclasses import replace

    return register_points(detected, surveyed, rng=rng, config=replace(config, max_hypotheses=max_hypotheses),
                           generator=RandomTriplets())


# ----------------------------------------------------------------------------------------------
# Synthetic problems (tests, bench, demo)
# ----------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class SyntheticRegistration:
    """A registration problem with known truth.

    detected: (N, 3) model-frame points; surveyed: (M, 3) observed surveyed points (metres);
    truth: the true world_from_model; labels: (N,) surveyed row of each detected point, −1 for a false
    detection; surveyed_true: (M, 3) noise-free surveyed points.
    """

    detected: np.ndarray
    surveyed: np.ndarray
    truth: Sim3
    labels: np.ndarray
    surveyed_true: np.ndarray

    def true_pairing(self) -> dict[int, int]:
        return {i: int(j) for i, j in enumerate(self.labels) if j >= 0}


def simulate_detections(surveyed_true, rng: np.random.Generator, *, n_seen: int | None = None,
                        n_false: int = 0, noise: float = 0.01, survey_noise: float = 0.0,
                        scale_range: tuple[float, float] = (0.1, 30.0), false_box=None,
                        seen: np.ndarray | None = None) -> SyntheticRegistration:
    """Detections of a surveyed layout in a random model frame.

    surveyed_true: (M, 3) true surveyed points (metres). ``n_seen`` random ones (or rows ``seen``) are
    detected with per-axis Gaussian noise ``noise`` (metres, before the change of frame); ``n_false``
    false detections are drawn uniformly in ``false_box`` ((2, 3) min/max corners; default the
    surveyed bounding box); the observed surveyed points get ``survey_noise``. The model frame is a
    random similarity: log-uniform scale in ``scale_range`` (model units per metre), uniform random
    rotation, translation of the order of the site. Detected rows are shuffled.
    """
    from scipy.spatial.transform import Rotation

    sur = np.asarray(surveyed_true, dtype=np.float64)
    m = len(sur)
    if seen is None:
        seen = rng.choice(m, m if n_seen is None else n_seen, replace=False)
    seen = np.asarray(seen, dtype=np.intp)
    box = np.array([sur.min(axis=0), sur.max(axis=0)]) if false_box is None else np.asarray(false_box, float)
    world_pts = np.vstack([sur[seen] + rng.normal(0.0, noise, (len(seen), 3)),
                           rng.uniform(box[0], box[1], (n_false, 3))])
    labels = np.concatenate([seen, np.full(n_false, -1)])
    perm = rng.permutation(len(world_pts))
    world_pts, labels = world_pts[perm], labels[perm]
    lo, hi = np.log(scale_range[0]), np.log(scale_range[1])
    model_from_world = Sim3(float(np.exp(rng.uniform(lo, hi))), Rotation.random(random_state=rng).as_matrix(),
                            rng.normal(0.0, 1.0, 3) * max(1.0, float(np.ptp(sur, axis=0).max())))
    observed = sur + rng.normal(0.0, survey_noise, sur.shape) if survey_noise > 0 else sur.copy()
    return SyntheticRegistration(model_from_world(world_pts), observed, model_from_world.inverse(), labels, sur)
