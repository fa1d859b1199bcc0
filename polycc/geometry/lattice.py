"""Convex hulls of voxel sets on the integer corner lattice (PolyMerge Eqs. 11, 15).

All hull work is done in *integer corner coordinates*: voxel ``i`` (an int triple) has
corners ``i + {0,1}^3``; world position of lattice point ``q`` is ``origin + q * g``.
qhull (scipy.spatial) therefore only ever sees small exact integers.

Half-plane form (:func:`integer_planes`, :func:`world_halfplanes`): qhull triangulates every facet; we recompute
each triangle's normal exactly as an integer cross product, reduce it by the gcd of its
components and merge triangles with the same reduced (normal, offset) key. Coplanar
facets are thus merged *exactly* (no angle tolerance). Normals are then made unit length
in float64 and each offset ``d`` is recomputed from the hull's world-space vertices and
pushed outward (:data:`OUTWARD_MARGIN_M` plus one ulp) so that rounding can only grow a
polytope, never shrink it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import QhullError

from polycc.geometry.qhull_raw import hull_raw

# Added to every world-space offset d, metres. Far below any physical length, far above
# float64 rounding at room scale (ulp(10 m) ~ 2e-15 m).
OUTWARD_MARGIN_M = 1e-9

# Lattice offsets of the 8 corners of a voxel.
CORNER_OFFSETS = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], dtype=np.int64)


def voxel_corner_points(idx: np.ndarray) -> np.ndarray:
    """(M, 3) int64 unique lattice corners of the voxels ``idx`` (N, 3)."""
    pts = (np.asarray(idx, np.int64)[:, None, :] + CORNER_OFFSETS[None]).reshape(-1, 3)
    return unique_rows(pts)  # np.unique(pts, axis=0), 5x faster on a cluster's corners


@dataclass
class LatticeHull:
    """Hull of lattice points: ``volume`` in cells (g^3), ``vertices`` (V, 3) int64,
    ``equations`` (F, 4) float64 from qhull (``A q + b <= 0`` inside, unit A),
    ``simplices`` (F, 3) indices into ``points``, ``points`` the input."""

    volume: float
    vertices: np.ndarray
    equations: np.ndarray
    simplices: np.ndarray
    points: np.ndarray


def lattice_hull(points: np.ndarray, options: bytes = b"Qt") -> LatticeHull:
    """Convex hull of (M, 3) integer lattice points (full-dimensional: voxel corners always are).

    ``options`` are qhull's; the default ``Qt`` gives exact facets of the input points.
    ``QJ`` (joggle) is faster on the highly degenerate lattice input; its volume and
    equations are correct to ~1e-11 relative and its vertex set may include a few extra
    boundary points, so it is used only to *rank* merges, never for stored planes.
    """
    pts = np.asarray(points, np.int64)
    try:
        volume, simplices, equations = hull_raw(pts.astype(np.float64), options)
    except QhullError as exc:  # pragma: no cover - voxel corners are never flat
        raise ValueError(f"degenerate hull of {len(pts)} lattice points: {exc}") from None
    used = np.zeros(len(pts), bool)  # the hull's vertices, in input order (as np.unique of the simplices)
    used[simplices.ravel()] = True
    return LatticeHull(volume, pts[used], equations, simplices, pts)


def lattice_hull_facets(points: np.ndarray, options: bytes = b"Qt") -> tuple[float, np.ndarray]:
    """(volume in cells, (F, 4) facet equations) of the hull of integer lattice points, as
    :func:`lattice_hull` gives them, without its vertex bookkeeping (ranking merge pairs needs no more)."""
    volume, _, equations = hull_raw(np.asarray(points, np.int64).astype(np.float64), options)
    return volume, equations


def integer_planes(h: LatticeHull) -> tuple[np.ndarray, np.ndarray]:
    """Exact, de-duplicated facet planes of a lattice hull: ``N q <= e``.

    Returns (F, 3) int64 primitive normals (gcd 1, outward) and (F,) int64 offsets.
    Coplanar qhull triangles collapse to one row.
    """
    P = h.points[h.simplices]  # (T, 3, 3) int64
    u, v = P[:, 1] - P[:, 0], P[:, 2] - P[:, 0]
    n = np.column_stack([u[:, 1] * v[:, 2] - u[:, 2] * v[:, 1], u[:, 2] * v[:, 0] - u[:, 0] * v[:, 2],
                         u[:, 0] * v[:, 1] - u[:, 1] * v[:, 0]])  # the exact integer cross product
    keep = np.any(n != 0, axis=1)  # qhull's triangulation may add zero-area triangles
    n, P, eq = n[keep], P[keep], h.equations[keep]
    flip = np.einsum("ij,ij->i", n.astype(np.float64), eq[:, :3]) < 0
    n[flip] = -n[flip]
    gcd = np.gcd.reduce(np.abs(n), axis=1)
    n = n // gcd[:, None]
    e = np.einsum("ij,ij->i", n, P[:, 0])
    key = unique_rows(np.column_stack([n, e]))
    return key[:, :3], key[:, 3]


def unique_rows(a: np.ndarray) -> np.ndarray:
    """``np.unique(a, axis=0)`` for a 2-D integer array (the same sorted rows), several times faster."""
    if len(a) < 2:
        return a.copy()
    s = a[np.lexsort(a.T[::-1])]
    keep = np.ones(len(s), bool)
    keep[1:] = np.any(s[1:] != s[:-1], axis=1)
    return s[keep]


def to_world(points_q: np.ndarray, g: float, origin: np.ndarray) -> np.ndarray:
    """Lattice points -> world metres, float64, computed exactly as ``origin + q * g``."""
    return np.asarray(origin, np.float64) + np.asarray(points_q, np.float64) * float(g)


def world_halfplanes(normals: np.ndarray, vertices_q: np.ndarray, g: float,
                     origin: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World-space half-planes and vertices of a lattice polytope.

    ``normals`` (F, 3) integer outward facet normals, ``vertices_q`` (V, 3) its lattice
    vertices. Returns ``(planes, vertices)``: planes (F, 4) float64 rows ``[nx, ny, nz, d]``
    meaning ``n . p <= d`` with ``|n| = 1``; vertices (V, 3) float64 metres. Each ``d`` is
    the max of ``n . p`` over the world-space vertices, plus :data:`OUTWARD_MARGIN_M`,
    rounded up one ulp: no vertex, and so no voxel corner of the hull, can end up outside
    by rounding.
    """
    nrm = np.asarray(normals, np.float64)
    nrm = nrm / np.linalg.norm(nrm, axis=1, keepdims=True)
    world = to_world(vertices_q, g, origin)
    d = (world @ nrm.T).max(axis=0) + OUTWARD_MARGIN_M
    d = np.nextafter(d, np.inf)
    return np.column_stack([nrm, d]), world
