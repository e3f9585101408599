"""Geometry of the synthetic bridge-pier site: the pier mesh, its planar faces, and marker placement.

Site frame: local metric frame of the synthetic site, metres, z up, the pier standing on z = 0 with its
cross-section roughly centred on the origin. Everything here is in the site frame; the model and world
frames are similarities of it chosen in :mod:`cpdetect.synth_scene`.

The pier is an extruded chamfered rectangle (an octagon in plan) on a wider plinth, so it has a step,
chamfers and corners; it is a closed, watertight triangle mesh whose triangles are grouped into planar
:class:`Face` objects. Each face carries an in-plane frame (``e_u`` right and ``e_v`` down as seen from
outside, metres) used for texturing and for the marker-plane frame of :mod:`cpdetect.markers`
(``e_u x e_v`` points into the pier, away from the viewer).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .markers import MarkerSpec
from .types import MARKER_TYPES


@dataclass(frozen=True)
class Face:
    """One planar face of the pier.

    origin (3,): a point of the face; e_u, e_v (3,): orthonormal in-plane axes (right, down as seen
    from outside); normal (3,): outward unit normal, equal to e_v x e_u; kind: "side", "step", "cap".
    """

    index: int
    origin: np.ndarray
    e_u: np.ndarray
    e_v: np.ndarray
    normal: np.ndarray
    kind: str
    name: str

    def to_plane(self, points: np.ndarray) -> np.ndarray:
        """Face coordinates (n, 2) in metres of site points (n, 3) lying on the face."""
        d = np.asarray(points, float).reshape(-1, 3) - self.origin
        return np.stack([d @ self.e_u, d @ self.e_v], axis=1)

    def from_plane(self, uv: np.ndarray) -> np.ndarray:
        uv = np.asarray(uv, float).reshape(-1, 2)
        return self.origin + uv[:, :1] * self.e_u + uv[:, 1:2] * self.e_v


@dataclass
class PierMesh:
    """Closed triangle mesh of the pier in the site frame.

    vertices (n, 3) float64 metres; triangles (m, 3) int32, counter-clockwise seen from outside;
    tri_face (m,) int32: the :class:`Face` index of every triangle.
    """

    vertices: np.ndarray
    triangles: np.ndarray
    tri_face: np.ndarray
    faces: list[Face]
    height: float
    step_height: float
    footprint: np.ndarray  # (k, 2) shaft cross-section, counter-clockwise seen from above

    def face_triangles(self, face_index: int) -> np.ndarray:
        """Corner coordinates (t, 3, 2) of the face's triangles in its (u, v) frame."""
        face = self.faces[face_index]
        tris = self.triangles[self.tri_face == face_index]
        return face.to_plane(self.vertices[tris].reshape(-1, 3)).reshape(-1, 3, 2)

    def inside_face(self, face_index: int, uv: np.ndarray, clearance: float = 0.0) -> np.ndarray:
        """Mask of face points (n, 2) inside the face and at least ``clearance`` metres from its
        boundary (a boundary edge is an edge of exactly one of the face's triangles)."""
        uv = np.asarray(uv, float).reshape(-1, 2)
        tris = self.face_triangles(face_index)
        inside = np.zeros(len(uv), bool)
        for a, b, c in tris:
            inside |= _in_triangle(uv, a, b, c)
        if clearance > 0 and inside.any():
            for p, q in _boundary_edges(tris):
                inside &= _segment_distance(uv, p, q) >= clearance
        return inside

    def area(self, face_index: int) -> float:
        t = self.face_triangles(face_index)
        e1, e2 = t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]
        return float(0.5 * np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]).sum())


def _in_triangle(p: np.ndarray, a, b, c) -> np.ndarray:
    def cross(o, q, r):
        return (q[0] - o[0]) * (r[:, 1] - o[1]) - (q[1] - o[1]) * (r[:, 0] - o[0])

    d1, d2, d3 = cross(a, b, p), cross(b, c, p), cross(c, a, p)
    neg = (d1 < 0) | (d2 < 0) | (d3 < 0)
    pos = (d1 > 0) | (d2 > 0) | (d3 > 0)
    return ~(neg & pos)


def _boundary_edges(tris: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    edges: dict[tuple, list] = {}
    for t in tris:
        for i in range(3):
            p, q = t[i], t[(i + 1) % 3]
            key = tuple(sorted((tuple(np.round(p, 9)), tuple(np.round(q, 9)))))
            edges.setdefault(key, []).append((p, q))
    return [v[0] for v in edges.values() if len(v) == 1]


def _segment_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    ab = b - a
    t = np.clip(((p - a) @ ab) / max(float(ab @ ab), 1e-18), 0.0, 1.0)
    return np.linalg.norm(p - (a + t[:, None] * ab), axis=1)


def chamfered_rectangle(width: float, depth: float, chamfer: float) -> np.ndarray:
    """Octagon (8, 2): a width x depth rectangle centred on the origin with its corners cut by
    ``chamfer`` metres along both sides; counter-clockwise seen from above (+z), starting at the
    front (-y) face's left end."""
    w, d, c = 0.5 * width, 0.5 * depth, chamfer
    return np.array([[-w + c, -d], [w - c, -d], [w, -d + c], [w, d - c],
                     [w - c, d], [-w + c, d], [-w, d - c], [-w, -d + c]], float)


def offset_convex(poly: np.ndarray, dist: float) -> np.ndarray:
    """Offset a convex counter-clockwise polygon outward by ``dist`` (edges moved parallel)."""
    n = len(poly)
    out = np.empty_like(poly)
    for i in range(n):
        p0, p1, p2 = poly[i - 1], poly[i], poly[(i + 1) % n]
        n0 = _outward(p0, p1)
        n1 = _outward(p1, p2)
        bis = n0 + n1
        out[i] = p1 + bis * dist / max(float(bis @ n1), 1e-12)
    return out


def _outward(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    e = (q - p) / np.linalg.norm(q - p)
    return np.array([e[1], -e[0]])  # right-hand normal of a counter-clockwise edge points outward


def build_pier(rng: np.random.Generator, height: float = 10.0) -> PierMesh:
    """A random pier segment about ``height`` metres high: chamfered shaft on a wider plinth.

    Shaft cross-section width 2.6-3.4 m, depth 1.4-1.9 m, chamfers 0.25-0.4 m; plinth 1.2-1.8 m
    high, 0.15-0.25 m wider on every side. The mesh is closed (bottom and top caps) and watertight.
    """
    width = rng.uniform(2.6, 3.4)
    depth = rng.uniform(1.4, 1.9)
    chamfer = rng.uniform(0.25, 0.4)
    step = rng.uniform(0.15, 0.25)
    z_step = rng.uniform(1.2, 1.8)
    shaft = chamfered_rectangle(width, depth, chamfer)
    plinth = offset_convex(shaft, step)
    k = len(shaft)
    rings = [(plinth, 0.0), (plinth, z_step), (shaft, z_step), (shaft, height)]
    vertices = np.concatenate([np.column_stack([poly, np.full(k, z)]) for poly, z in rings])
    triangles: list[tuple[int, int, int]] = []
    tri_face: list[int] = []
    faces: list[Face] = []
    down = np.array([0.0, 0.0, -1.0])

    def add_face(origin, normal, e_u, kind, name) -> int:
        e_v = np.cross(e_u, normal)
        faces.append(Face(len(faces), np.asarray(origin, float), np.asarray(e_u, float), e_v,
                          np.asarray(normal, float), kind, name))
        return len(faces) - 1

    # side walls of plinth (ring 0 -> 1) and shaft (ring 2 -> 3)
    for lo, part in ((0, "plinth"), (2, "shaft")):
        for i in range(k):
            j = (i + 1) % k
            a, b = lo * k + i, lo * k + j
            c, d = (lo + 1) * k + j, (lo + 1) * k + i
            n2 = _outward(vertices[a, :2], vertices[b, :2])
            normal = np.array([n2[0], n2[1], 0.0])
            e_u = np.cross(normal, down)  # right as seen from outside
            # origin: the top-left corner seen from outside, so (u, v) >= 0 on the face
            f = add_face(vertices[d], normal, e_u, "side", f"{part}_side{i}")
            triangles += [(a, b, c), (a, c, d)]
            tri_face += [f, f]
    # step: horizontal annulus between the plinth top ring (1) and the shaft bottom ring (2)
    up = np.array([0.0, 0.0, 1.0])
    f = add_face(vertices[k], up, np.array([1.0, 0.0, 0.0]), "step", "step")
    for i in range(k):
        j = (i + 1) % k
        a, b, c, d = k + i, k + j, 2 * k + j, 2 * k + i
        triangles += [(a, b, c), (a, c, d)]
        tri_face += [f, f]
    # caps (convex fans): bottom seen from below, top seen from above
    f = add_face(vertices[0], -up, np.array([1.0, 0.0, 0.0]), "cap", "bottom")
    for i in range(1, k - 1):
        triangles.append((0, i + 1, i))
        tri_face.append(f)
    f = add_face(vertices[3 * k], up, np.array([1.0, 0.0, 0.0]), "cap", "top")
    for i in range(1, k - 1):
        triangles.append((3 * k, 3 * k + i, 3 * k + i + 1))
        tri_face.append(f)
    return PierMesh(vertices=vertices, triangles=np.asarray(triangles, np.int32),
                    tri_face=np.asarray(tri_face, np.int32), faces=faces, height=float(height),
                    step_height=float(z_step), footprint=shaft)


@dataclass(frozen=True)
class PlacedMarker:
    """A marker (printed or not) on a face of the pier, in the site frame.

    center (3,): aiming point (metres); axis_u, axis_v (3,): the marker-plane axes (u right, v down,
    ``axis_u x axis_v`` into the surface); role: "regular" (printed, surveyed), "unsurveyed"
    (printed, not surveyed), "missing" (surveyed, never printed), "hidden" (surveyed where no
    camera sees it; printed).
    """

    name: str
    spec: MarkerSpec
    face: int
    center: np.ndarray
    axis_u: np.ndarray
    axis_v: np.ndarray
    angle_rad: float
    role: str = "regular"

    @property
    def printed(self) -> bool:
        return self.role != "missing"

    @property
    def surveyed(self) -> bool:
        return self.role != "unsurveyed"

    @property
    def normal(self) -> np.ndarray:
        """Outward unit normal of the face the marker is stuck on."""
        return np.cross(self.axis_v, self.axis_u)

    @property
    def outer_radius(self) -> float:
        """Radius (metres) of a circle around the centre containing the whole printed sheet."""
        r = self.spec.half + self.spec.margin_m
        return r if self.spec.type == "circle" else r * np.sqrt(2.0)

    def plane_coords(self, points: np.ndarray) -> np.ndarray:
        """Marker-plane coordinates (n, 2) (u right, v down, metres) of site points (n, 3)."""
        d = np.asarray(points, float).reshape(-1, 3) - self.center
        return np.stack([d @ self.axis_u, d @ self.axis_v], axis=1)


def marker_on_face(face: Face, uv: np.ndarray, spec: MarkerSpec, angle_rad: float, name: str,
                   role: str = "regular", face_index: int | None = None) -> PlacedMarker:
    """Place ``spec`` at face coordinates ``uv`` (2,), rotated in-plane by ``angle_rad``."""
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    axis_u = c * face.e_u + s * face.e_v
    axis_v = -s * face.e_u + c * face.e_v
    return PlacedMarker(name=name, spec=spec, face=face.index if face_index is None else face_index,
                        center=face.from_plane(np.asarray(uv, float))[0], axis_u=axis_u, axis_v=axis_v,
                        angle_rad=float(angle_rad), role=role)


def distance_signatures(centers: np.ndarray) -> np.ndarray:
    """Sorted distances (n, n-1) from every centre to all others."""
    c = np.asarray(centers, float)
    d = np.linalg.norm(c[:, None] - c[None], axis=2)
    return np.sort(d, axis=1)[:, 1:]


def min_signature_gap(centers: np.ndarray) -> float:
    """Smallest max-difference between the distance signatures of two different markers (metres).

    Any similarity that maps the layout onto a non-trivial permutation of itself has scale 1 and
    sends some marker i to a marker j != i, so both have equal signatures; a gap of g metres means
    no such symmetry exists to within about g (infinite for fewer than two markers)."""
    sig = distance_signatures(centers)
    n = len(sig)
    if n < 2:
        return float("inf")
    gaps = [np.abs(sig[i] - sig[j]).max() for i in range(n) for j in range(i + 1, n)]
    return float(min(gaps))


@dataclass
class PlacementRequest:
    """How many markers of each role to place, their sizes and spacing (metres)."""

    regular: int = 9
    unsurveyed: int = 0
    missing: int = 0
    hidden: int = 0
    size_range: tuple[float, float] = (0.10, 0.30)
    min_separation: float = 0.45
    edge_clearance: float = 0.08
    min_views: int = 3
    asymmetry_m: float = 0.05
    roles: list[str] = field(default_factory=list)


def candidate_points(mesh: PierMesh, rng: np.random.Generator, n: int, kinds=("side",)) -> tuple[np.ndarray,
                                                                                                   np.ndarray]:
    """``n`` random points uniformly over the faces of the given kinds: (face index (n,), uv (n, 2))."""
    idx = [f.index for f in mesh.faces if f.kind in kinds]
    areas = np.array([mesh.area(i) for i in idx])
    choice = rng.choice(len(idx), size=n, p=areas / areas.sum())
    faces = np.array(idx)[choice]
    uv = np.empty((n, 2))
    for fi in np.unique(faces):
        sel = np.nonzero(faces == fi)[0]
        tris = mesh.face_triangles(int(fi))
        e1, e2 = tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0]
        ta = np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])
        t = rng.choice(len(tris), size=len(sel), p=ta / ta.sum())
        r1, r2 = rng.random(len(sel)), rng.random(len(sel))
        flip = r1 + r2 > 1
        r1[flip], r2[flip] = 1 - r1[flip], 1 - r2[flip]
        a, b, c = tris[t, 0], tris[t, 1], tris[t, 2]
        uv[sel] = a + r1[:, None] * (b - a) + r2[:, None] * (c - a)
    return faces, uv


def place_markers(mesh: PierMesh, request: PlacementRequest, rng: np.random.Generator, view_count,
                  max_tries: int = 100, glimpse_count=None) -> list[PlacedMarker]:
    """Place markers asymmetrically on the side faces of the pier.

    ``view_count(points (n, 3), normals (n, 3)) -> (n,) int`` counts the images that see a point
    well. Regular, unsurveyed and missing markers need ``min_views`` views; hidden ones need zero
    views by ``glimpse_count`` (same signature; a looser test, e.g. grazing views and points just
    outside the image, default ``view_count``).
    Markers keep ``edge_clearance`` metres between their printed sheet and the face's edges and
    ``min_separation`` between centres; types cycle so all three appear; sizes are uniform in
    ``size_range``; in-plane rotations uniform. The whole layout (and its surveyed subset) is redrawn
    until no similarity maps it onto a permutation of itself within ``asymmetry_m`` metres.
    Raises ValueError when no valid layout is found (e.g. too many markers for the covered area).
    """
    roles = (["regular"] * request.regular + ["unsurveyed"] * request.unsurveyed
             + ["missing"] * request.missing + ["hidden"] * request.hidden)
    types: list[str] = []
    for role in ("regular", "unsurveyed", "missing", "hidden"):  # every role group cycles the types
        n_role = roles.count(role)
        start = int(rng.integers(3))
        group = [MARKER_TYPES[(start + i) % 3] for i in range(n_role)]
        rng.shuffle(group)
        types += group
    n_cand = 6000  # candidate centres and their view counts, drawn once for all tries
    faces, uv = candidate_points(mesh, rng, n_cand)
    points = np.empty((n_cand, 3))
    normals = np.empty((n_cand, 3))
    for fi in np.unique(faces):
        sel = faces == fi
        points[sel] = mesh.faces[fi].from_plane(uv[sel])
        normals[sel] = mesh.faces[fi].normal
    counts = np.asarray(view_count(points, normals))
    glimpses = counts if glimpse_count is None or request.hidden == 0 else np.asarray(glimpse_count(points, normals))
    for _ in range(max_tries):
        placed = _try_layout(mesh, request, rng, (faces, uv, counts, glimpses), roles, types)
        if placed is None:
            continue
        centers = np.array([m.center for m in placed])
        surveyed = np.array([m.surveyed for m in placed])
        if (min_signature_gap(centers) >= request.asymmetry_m
                and min_signature_gap(centers[surveyed]) >= request.asymmetry_m):
            return placed
    raise ValueError(f"could not place {len(roles)} markers asymmetrically with the requested visibility "
                     f"after {max_tries} tries; ask for fewer markers or more images")


def _try_layout(mesh, request, rng, candidates, roles, types):
    faces, uv, counts, glimpses = candidates
    sizes = rng.uniform(*request.size_range, size=len(roles))
    placed: list[PlacedMarker] = []
    used = np.zeros(len(faces), bool)
    for k, (role, mtype) in enumerate(zip(roles, types)):
        margin = 0.0 if mtype == "circle" else float(rng.uniform(0.0, 0.15)) * sizes[k]
        spec = MarkerSpec(mtype, size_m=float(sizes[k]), margin_m=margin)
        want_hidden = role == "hidden"
        ok = (glimpses == 0) if want_hidden else (counts >= request.min_views)
        ok &= ~used
        order = rng.permutation(np.nonzero(ok)[0])
        chosen = None
        for c in order[:400]:
            angle = float(rng.uniform(-np.pi, np.pi))
            m = marker_on_face(mesh.faces[faces[c]], uv[c], spec, angle, name="", role=role)
            if placed and min(np.linalg.norm(m.center - p.center) for p in placed) < request.min_separation:
                continue
            r = m.outer_radius + request.edge_clearance
            if not mesh.inside_face(int(faces[c]), uv[c][None], clearance=r)[0]:
                continue
            chosen = m
            used[c] = True
            break
        if chosen is None:
            return None
        placed.append(chosen)
    return placed


def sample_surface(mesh: PierMesh, spacing: float, rng: np.random.Generator,
                   kinds=("side", "step")) -> tuple[np.ndarray, np.ndarray]:
    """Points on a jittered grid of ``spacing`` metres over the faces of the given kinds.

    Returns (points (n, 3) site frame, face index (n,) int32)."""
    pts, fidx = [], []
    for face in mesh.faces:
        if face.kind not in kinds:
            continue
        tris = mesh.face_triangles(face.index).reshape(-1, 2)
        lo, hi = tris.min(0), tris.max(0)
        us = np.arange(lo[0] + 0.5 * spacing, hi[0], spacing)
        vs = np.arange(lo[1] + 0.5 * spacing, hi[1], spacing)
        U, V = np.meshgrid(us, vs)
        uv = np.column_stack([U.ravel(), V.ravel()])
        uv += rng.uniform(-0.35 * spacing, 0.35 * spacing, size=uv.shape)
        uv = uv[mesh.inside_face(face.index, uv)]
        pts.append(face.from_plane(uv))
        fidx.append(np.full(len(uv), face.index, np.int32))
    return np.concatenate(pts), np.concatenate(fidx)


__all__ = ["Face", "PierMesh", "PlacedMarker", "PlacementRequest", "build_pier", "place_markers",
           "marker_on_face", "distance_signatures", "min_signature_gap", "sample_surface",
           "chamfered_rectangle", "offset_convex", "candidate_points"]
