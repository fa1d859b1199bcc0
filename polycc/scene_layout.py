"""The on-board scene layout (``firmware_app/src/polycc_scene_layout.h``), Python side.

:func:`pack_scene` turns polytopes, each an ``(H, 4)`` array of rows ``[nx, ny, nz, d]``
(outward unit normals, ``n . p <= d`` inside), into exactly the arrays the C kernel reads:
float32 half-planes, 28-byte polytope records with the culling bounds, and the two scene
constants.  :meth:`PackedScene.to_bytes` / :func:`scene_from_bytes` give the flat byte image
(header + records + half-planes) used by the bare-metal test harness; the code generator
emits the same numbers as C literals.  :func:`hull_halfplanes` builds half-planes from a
point cloud (convex hull, coplanar facets merged).
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass

import numpy as np

from polycc.errors import PolyccError

SCENE_FORMAT = 2  # POLYCC_SCENE_FORMAT in polycc_scene_layout.h
PLANE_BYTES = 16
POLY_BYTES = 36
CLUSTER_BYTES = 36
MAX_POLY_PLANES = 256
# Octant o of p - c: bit0 x < 0, bit1 y < 0, bit2 z < 0; s_o is the octant's diagonal.
OCTANT_SIGNS = np.array([[-1.0 if o & (1 << i) else 1.0 for i in range(3)] for o in range(8)])
MAX_PLANES = 65535

PLANE_DTYPE = np.dtype([("nx", "<f4"), ("ny", "<f4"), ("nz", "<f4"), ("d", "<f4")])
POLY_DTYPE = np.dtype(
    [
        ("first", "<u2"),
        ("count", "<u2"),
        ("cx", "<f4"),
        ("cy", "<f4"),
        ("cz", "<f4"),
        ("r_out", "<f4"),
        ("inv_gamma", "<f4"),
        ("r_in", "<f4"),
        ("lead", "u1", 8),
    ]
)
HEADER = struct.Struct("<IIIIff")  # format, n_clusters, n_polys, n_planes, coord_bound, log_lmax
assert PLANE_DTYPE.itemsize == PLANE_BYTES and POLY_DTYPE.itemsize == POLY_BYTES

_UNIT_TOL = 1e-5  # |n| must be 1 within this before float32 rounding


@dataclass(frozen=True)
class PackedScene:
    """The arrays of one ``polycc_scene_t``, exactly as the C kernel reads them."""

    planes: np.ndarray  # PLANE_DTYPE, (n_planes,)
    polys: np.ndarray  # POLY_DTYPE, (n_polys,)
    clusters: np.ndarray  # POLY_DTYPE, (n_clusters,): first/count index polys
    coord_bound: np.float32
    log_lmax: np.float32
    order: np.ndarray | None = None  # order[i] = input index of packed polytope i

    @property
    def n_polys(self) -> int:
        return int(self.polys.shape[0])

    @property
    def n_planes(self) -> int:
        return int(self.planes.shape[0])

    @property
    def n_clusters(self) -> int:
        return int(self.clusters.shape[0])

    def plane_matrix(self) -> np.ndarray:
        """Half-planes as an (n_planes, 4) float32 array [nx, ny, nz, d]."""
        return self.planes.view("<f4").reshape(-1, 4)

    def polytopes(self) -> list[np.ndarray]:
        """Decode back to one (H_k, 4) float32 array per polytope, in packed order
        (``order`` maps packed positions to the input positions)."""
        m = self.plane_matrix()
        return [m[int(p["first"]) : int(p["first"]) + int(p["count"])].copy() for p in self.polys]

    def flash_bytes(self) -> int:
        """Bytes of the arrays plus the root struct on a 32-bit target."""
        return HEADER.size + 12 + self.clusters.nbytes + self.polys.nbytes + self.planes.nbytes

    def to_bytes(self) -> bytes:
        """Flat image: header (format, counts, constants), clusters, polys, planes."""
        head = HEADER.pack(SCENE_FORMAT, self.n_clusters, self.n_polys, self.n_planes, float(self.coord_bound),
                           float(self.log_lmax))
        return head + self.clusters.tobytes() + self.polys.tobytes() + self.planes.tobytes()

    def without_polytopes(self) -> "PackedScene":
        """The same constants with no polytopes (an empty scene)."""
        return PackedScene(self.planes[:0], self.polys[:0], self.clusters[:0], self.coord_bound, self.log_lmax)


def scene_from_bytes(blob: bytes) -> PackedScene:
    """Inverse of :meth:`PackedScene.to_bytes`."""
    fmt, n_clusters, n_polys, n_planes, cb, ll = HEADER.unpack_from(blob, 0)
    if fmt != SCENE_FORMAT:
        raise PolyccError(f"scene image has format {fmt}, this polycc reads format {SCENE_FORMAT}; regenerate it")
    off = HEADER.size
    clusters = np.frombuffer(blob, POLY_DTYPE, n_clusters, off).copy()
    off += clusters.nbytes
    polys = np.frombuffer(blob, POLY_DTYPE, n_polys, off).copy()
    off += polys.nbytes
    planes = np.frombuffer(blob, PLANE_DTYPE, n_planes, off).copy()
    return PackedScene(planes, polys, clusters, np.float32(cb), np.float32(ll))


def _f32_up(x: float) -> np.float32:
    """Smallest float32 >= x."""
    f = np.float32(x)
    return f if float(f) >= x else np.nextafter(f, np.float32(np.inf))


def _f32_down(x: float) -> np.float32:
    """Largest float32 <= x."""
    f = np.float32(x)
    return f if float(f) <= x else np.nextafter(f, np.float32(-np.inf))


def _chebyshev_centre(h: np.ndarray) -> tuple[np.ndarray, float]:
    """Centre and radius of the largest ball inside {n . p <= d} (float64 LP)."""
    from scipy.optimize import linprog

    n, d = h[:, :3], h[:, 3]
    norms = np.linalg.norm(n, axis=1)
    res = linprog(
        c=[0, 0, 0, -1], A_ub=np.c_[n, norms], b_ub=d, bounds=[(None, None)] * 3 + [(0, None)], method="highs"
    )
    if res.status != 0 or res.x[3] <= 0:
        raise PolyccError("a polytope is empty, flat or unbounded; every polytope needs a non-empty interior")
    return res.x[:3], float(res.x[3])


def _inv_gamma(n: np.ndarray) -> float:
    """1/gamma with gamma = min_{|u|=1} max_l n_l . u = 1 / (largest vertex norm of {x : n_l . x <= 1})."""
    from scipy.spatial import HalfspaceIntersection

    hs = np.c_[n, -np.ones(len(n))]
    try:
        verts = HalfspaceIntersection(hs, np.zeros(3)).intersections
    except Exception as exc:  # qhull: the normals do not positively span R^3
        raise PolyccError(f"a polytope is unbounded (its normals do not surround the origin): {exc}") from None
    if not np.all(np.isfinite(verts)):
        raise PolyccError("a polytope is unbounded (its normals do not surround the origin); close it")
    return float(np.max(np.linalg.norm(verts, axis=1)))


def _cluster_order(centres: np.ndarray, leaf: int) -> list[np.ndarray]:
    """Groups of at most ``leaf`` polytope indices: recursive median split on the widest axis."""
    groups, todo = [], [np.arange(len(centres))]
    while todo:
        idx = todo.pop()
        if len(idx) <= leaf:
            groups.append(idx)
            continue
        axis = int(np.argmax(np.ptp(centres[idx], axis=0)))
        srt = idx[np.argsort(centres[idx, axis], kind="stable")]
        todo += [srt[len(srt) // 2 :], srt[: len(srt) // 2]]
    return groups


def pack_scene(polytopes: list[np.ndarray], *, leaf: int | None = None, rel_safety: float = 1e-6) -> PackedScene:
    """Pack polytopes ((H_k, 4) arrays [nx, ny, nz, d], unit outward normals) into the layout.

    Polytopes are grouped into clusters of at most ``leaf`` (default ceil(sqrt(n)), at least 4)
    and stored cluster by cluster; ``PackedScene.order`` records the permutation.  The certified
    bounds are computed in float64 from the float32 values actually stored and rounded outward
    (``rel_safety`` adds a relative cushion for the float64 geometry).
    """
    if len(polytopes) == 0:
        raise PolyccError("no polytopes to pack; the scene needs at least one")
    rows = [np.asarray(h, dtype=np.float64).reshape(-1, 4) for h in polytopes]
    total = sum(len(r) for r in rows)
    if total > MAX_PLANES:
        raise PolyccError(f"{total} half-planes exceed the layout limit of {MAX_PLANES}; reduce the cover")
    recs = [_poly_record(k, h, rel_safety) for k, h in enumerate(rows)]
    centres = np.array([r[0] for r in recs])
    leaf = leaf or max(4, math.ceil(math.sqrt(len(rows))))
    groups = _cluster_order(centres, leaf)
    order = np.concatenate(groups)
    planes = np.zeros(total, PLANE_DTYPE)
    pm = planes.view("<f4").reshape(-1, 4)
    polys = np.zeros(len(rows), POLY_DTYPE)
    clusters = np.zeros(len(groups), POLY_DTYPE)
    first, pos, cb = 0, 0, 0.0
    for j, grp in enumerate(groups):
        cen = np.float32(centres[grp].mean(axis=0)).astype(np.float64)
        reach_out = reach_in = 0.0
        for k in grp:
            c, r_out, inv_g, r_in, h32 = recs[k]
            dist = float(np.linalg.norm(c - cen))
            reach_out = max(reach_out, (dist + float(r_out)) * (1 + rel_safety))
            reach_in = max(reach_in, (dist + float(r_in)) * (1 + rel_safety))
            pm[first : first + len(h32)] = h32
            lead = np.argmax(OCTANT_SIGNS @ h32[:, :3].astype(np.float64).T, axis=1)
            polys[pos] = (first, len(h32), c[0], c[1], c[2], r_out, inv_g, r_in, lead)
            cb = max(cb, float(np.max(np.abs(h32[:, 3]))), float(np.sum(np.abs(c))) + float(r_out))
            first += len(h32)
            pos += 1
        inv_gc = max(float(recs[k][2]) for k in grp)
        clusters[j] = (pos - len(grp), len(grp), cen[0], cen[1], cen[2], _f32_up(reach_out), inv_gc, _f32_up(reach_in),
                       np.zeros(8))
        cb = max(cb, float(np.sum(np.abs(cen))) + float(clusters[j]["r_out"]))
    lmax = max(len(h) for h in rows)
    return PackedScene(planes, polys, clusters, _f32_up(cb * (1 + rel_safety)),
                       _f32_up(math.log(lmax) * (1 + rel_safety)), order)


def _poly_record(k: int, h: np.ndarray, rel_safety: float):
    """(centre, r_out, inv_gamma, r_in, float32 half-planes) of one polytope, bounds rounded outward."""
    if len(h) == 0 or not np.all(np.isfinite(h)):
        raise PolyccError(f"polytope {k} has no half-planes or non-finite values")
    if len(h) > MAX_POLY_PLANES:
        raise PolyccError(f"polytope {k} has {len(h)} half-planes, the layout allows {MAX_POLY_PLANES}; split it")
    norms = np.linalg.norm(h[:, :3], axis=1)
    if np.any(np.abs(norms - 1.0) > _UNIT_TOL):
        raise PolyccError(f"polytope {k} has normals that are not unit length; normalise [nx, ny, nz, d] rows")
    h32 = h.astype(np.float32)
    n, d = h32[:, :3].astype(np.float64), h32[:, 3].astype(np.float64)  # what the C reads
    c64, _ = _chebyshev_centre(np.c_[n, d])
    c = c64.astype(np.float32).astype(np.float64)
    slack = d - n @ c
    if np.min(slack) <= 0:
        raise PolyccError(f"polytope {k} is too thin to hold a float32 interior point; drop or thicken it")
    inv_g = _inv_gamma(n) * (1 + rel_safety)
    r_out = float(np.max(slack)) * inv_g * (1 + rel_safety)
    r_in = float(np.min(slack)) * (1 - rel_safety)
    return c, _f32_up(r_out), _f32_up(inv_g), _f32_down(r_in), h32


def hull_halfplanes(points: np.ndarray, *, coplanar_tol: float = 1e-8) -> np.ndarray:
    """Half-planes [nx, ny, nz, d] (unit outward normals) of the convex hull of 3D points.

    Qhull triangulates facets; triangles on the same plane are merged into one half-plane.
    """
    from scipy.spatial import ConvexHull

    hull = ConvexHull(np.asarray(points, dtype=np.float64))
    eq = hull.equations  # [n, -d], unit n, n . x + off <= 0 inside
    out: list[np.ndarray] = []
    for row in eq:
        h = np.r_[row[:3], -row[3]]
        if not any(np.all(np.abs(h - o) <= coplanar_tol * (1 + np.abs(o))) for o in out):
            out.append(h)
    return np.array(out)


def axis_box(lo, hi) -> np.ndarray:
    """Half-planes of the axis-aligned box [lo, hi]."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    rows = []
    for i in range(3):
        e = np.zeros(3)
        e[i] = 1.0
        rows.append(np.r_[e, hi[i]])
        rows.append(np.r_[-e, -lo[i]])
    return np.array(rows)


def random_hull_polytopes(rng: np.random.Generator, n: int, *, extent=(10.0, 10.0, 3.0), size=(0.1, 0.6),
                          points=(8, 20)) -> list[np.ndarray]:
    """Synthetic obstacles: convex hulls of random points, scattered in a room [0, extent]."""
    lo, hi = size
    out = []
    for _ in range(n):
        c = rng.uniform(0.0, 1.0, 3) * np.asarray(extent)
        k = int(rng.integers(points[0], points[1] + 1))
        axes = rng.uniform(lo, hi, 3)
        out.append(hull_halfplanes(c + rng.normal(size=(k, 3)) * axes))
    return out


def pad_to_planes(polytopes: list[np.ndarray], total: int) -> list[np.ndarray]:
    """Append redundant half-planes (copies of a face moved 1 m outward) until the scene has
    exactly ``total`` half-planes; the polytopes themselves do not change."""
    out = [np.asarray(h, float).copy() for h in polytopes]
    have = sum(len(h) for h in out)
    if have > total:
        raise PolyccError(f"scene already has {have} > {total} half-planes")
    k = 0
    while have < total:
        h = out[k % len(out)]
        extra = h[0].copy()
        extra[3] += 1.0 + 0.01 * (have % 7)
        out[k % len(out)] = np.vstack([h, extra])
        have += 1
        k += 1
    return out
