"""Exact voxel occupancy of mesh triangles (world frame, metres), merged with the splats' V+.

A voxel (closed box of side g, corners on ``origin + g Z^3``) is occupied iff it meets a triangle,
decided by the separating-axis theorem for a triangle and a box (Akenine-Möller 2001): the 3 box
face normals, the triangle normal and the 9 cross products of triangle edges with box axes. For
two convex sets these 13 axes are complete, so the test is exact; it only declares "separated"
when an axis separates by more than a float64 error bound (relative 1e-12 of the squared extent,
far above the few roundings involved), so float error counts toward "occupied". Degenerate
triangles (segments from a mesh's ``edge`` element, points) go through the same axes, which stay
complete for them (their cross products vanish and separate nothing).

Triangles are refined hierarchically like splats (:mod:`polycc.occupancy.exact`): each AABB is
tiled with blocks of 2^L voxels, blocks that miss are dropped and the others split in 8 until
L = 0, so every (triangle, voxel) pair is emitted once and a voxel's count is the number of
distinct triangles touching it.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from polycc.errors import PolyccError
from polycc.occupancy.exact import _CHILD, _OFF, _Accumulator, _initial_blocks, pack_keys, unpack_keys
from polycc.occupancy.grid import OccupancyGrid

REL_TOL = 1e-12
TRI_CHUNK = 16_384
ITEM_BATCH = 400_000


def triangles_box_overlap(tri: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """(M,) bool: closed triangle ``tri[m]`` (M, 3, 3) meets the closed box [lo[m], hi[m]]; never a false miss."""
    c = 0.5 * (lo + hi)
    h = 0.5 * (hi - lo)
    u = tri - c[:, None, :]  # (M, 3 vertices, 3)
    scale = np.abs(u).max(axis=(1, 2)) + h.max(axis=1)
    tol1 = REL_TOL * scale
    tol2 = REL_TOL * scale * scale
    sep = np.any((u.min(axis=1) > h + tol1[:, None]) | (u.max(axis=1) < -h - tol1[:, None]), axis=1)
    e = np.stack([u[:, 1] - u[:, 0], u[:, 2] - u[:, 1], u[:, 0] - u[:, 2]], axis=1)  # (M, 3 edges, 3)
    n = np.cross(e[:, 0], e[:, 1])
    d = np.einsum("mi,mi->m", n, u[:, 0])
    sep |= np.abs(d) > np.einsum("mi,mi->m", np.abs(n), h) + tol2
    eye = np.eye(3)
    for j in range(3):
        for i in range(3):
            a = np.cross(e[:, j], eye[i])  # (M, 3)
            p = np.einsum("mvi,mi->mv", u, a)
            r = np.einsum("mi,mi->m", np.abs(a), h)
            sep |= (p.min(axis=1) > r + tol2) | (p.max(axis=1) < -r - tol2)
    return ~sep


def _chunk(tri: np.ndarray, imin: np.ndarray, imax: np.ndarray, g: float, origin: np.ndarray,
           acc: _Accumulator) -> int:
    owner, blo, lev = _initial_blocks(imin, imax)
    tests = 0
    while owner.size:
        nxt = []
        for s in range(0, owner.size, ITEM_BATCH):
            o, b, L = owner[s: s + ITEM_BATCH], blo[s: s + ITEM_BATCH], lev[s: s + ITEM_BATCH]
            size = (np.int64(1) << L)[:, None]
            hit = triangles_box_overlap(tri[o], origin + b * g, origin + (b + size) * g)
            tests += o.size
            o, b, L = o[hit], b[hit], L[hit]
            leaf = L == 0
            acc.add(pack_keys(b[leaf]))
            o, b, L = o[~leaf], b[~leaf], L[~leaf] - 1
            if not o.size:
                continue
            half = (np.int64(1) << L)[:, None, None]
            cb = (b[:, None, :] + _CHILD[None] * half).reshape(-1, 3)
            co, cl = np.repeat(o, 8), np.repeat(L, 8)
            ok = np.all(cb <= imax[co], axis=1)
            nxt.append((co[ok], cb[ok], cl[ok]))
        if not nxt:
            break
        owner, blo, lev = (np.concatenate([x[k] for x in nxt]) for k in range(3))
    return tests


def voxelize_triangles(tri: np.ndarray, voxel_size: float, origin: np.ndarray | None = None,
                       progress: Callable[[int], None] | None = None) -> tuple[np.ndarray, np.ndarray, int]:
    """(sorted unique voxel keys, distinct-triangle counts, exact tests) of the voxels meeting ``tri``
    (T, 3, 3) metres; keys as :func:`polycc.occupancy.exact.pack_keys`."""
    g = float(voxel_size)
    origin = np.zeros(3) if origin is None else np.asarray(origin, np.float64)
    tri = np.asarray(tri, np.float64)
    acc = _Accumulator()
    if len(tri) == 0:
        k, c = acc.result()
        return k, c, 0
    pad = REL_TOL * (np.abs(tri).max() + g) + 1e-12
    imin = np.floor((tri.min(axis=1) - pad - origin) / g).astype(np.int64)
    imax = np.floor((tri.max(axis=1) + pad - origin) / g).astype(np.int64)
    if imin.min() < -_OFF or imax.max() >= _OFF:
        raise PolyccError(f"the mesh spans more than {2 * _OFF} voxels of {g:g} m along an axis; use --crop, "
                          "--scale/--transform to put it in metres, or a larger --voxel")
    tests = 0
    for s in range(0, len(tri), TRI_CHUNK):
        tests += _chunk(tri[s: s + TRI_CHUNK], imin[s: s + TRI_CHUNK], imax[s: s + TRI_CHUNK], g, origin, acc)
        if progress:
            progress(min(s + TRI_CHUNK, len(tri)))
    k, c = acc.result()
    return k, c, tests


def merge_triangles(grid: OccupancyGrid, tri: np.ndarray, progress: Callable[[int], None] | None = None
                    ) -> OccupancyGrid:
    """``grid`` (the splats' V+ without floater filter) plus every voxel a triangle meets; counts add
    (distinct splats + distinct triangles touching the voxel)."""
    if grid.stats.get("min_splats_per_voxel", 1) > 1:
        raise PolyccError("the floater filter (--min-splats-per-voxel > 1) counts splats, and a mesh has none; "
                          "use --min-splats-per-voxel 1 with a mesh .ply")
    tk, tc, tests = voxelize_triangles(tri, grid.voxel_size, grid.origin, progress)
    keys = np.concatenate([pack_keys(grid.indices), tk])
    counts = np.concatenate([np.ones(len(grid), np.int64) if grid.counts is None else grid.counts.astype(np.int64),
                             tc.astype(np.int64)])
    uk, inv = np.unique(keys, return_inverse=True)
    uc = np.bincount(inv, weights=counts, minlength=uk.size).astype(np.int32)
    stats = dict(grid.stats, triangles=int(len(tri)), triangle_voxels=int(tk.size), triangle_tests=int(tests),
                 voxels=int(uk.size))
    return OccupancyGrid(indices=unpack_keys(uk), voxel_size=grid.voxel_size, origin=grid.origin, counts=uc,
                         stats=stats, removed=grid.removed)


def triangle_samples(tri: np.ndarray, per: int = 16, seed: int = 0) -> np.ndarray:
    """Points on each triangle (corners, edge midpoints, centroid and ``per`` random), metres; for checks."""
    tri = np.asarray(tri, np.float64)
    rng = np.random.default_rng(seed)
    fixed = np.array([[1, 0, 0], [0, 1, 0], [0, 0, 1], [0.5, 0.5, 0], [0, 0.5, 0.5], [0.5, 0, 0.5],
                      [1 / 3, 1 / 3, 1 / 3]])
    r = rng.random((per, 2))
    flip = r.sum(axis=1) > 1
    r[flip] = 1 - r[flip]
    bary = np.concatenate([fixed, np.column_stack([r, 1 - r.sum(axis=1)])])
    return np.einsum("bk,tki->tbi", bary, tri).reshape(-1, 3)
