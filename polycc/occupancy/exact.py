"""Exact voxel occupancy V+ of a set of ellipsoids (PolyMerge Sec. V-A, Eqs. 6-9).

A voxel (closed box of side g, corners on ``origin + g Z^3``) is occupied iff it meets at
least one ellipsoid, decided by the exact test of :mod:`polycc.geometry.ellipsoid_box` (float
error counted toward "occupied").

Candidates come from each ellipsoid's axis-aligned bounding box (AABB pruning as in
the paper). Large ellipsoids are refined hierarchically: their AABB is tiled with
blocks of 2^L voxels; a block that misses the ellipsoid is dropped, a block entirely
inside it is emitted whole, and any other block is split into 8 until L = 0. Blocks
tile each AABB without overlap, so every (ellipsoid, voxel) pair is emitted at most
once and a voxel's count is the number of distinct ellipsoids that touch it.

Splats are processed in chunks, so peak memory is bounded by the chunk size and the
number of distinct occupied voxels, not by the scene size.
"""

from __future__ import annotations

import math
from typing import Callable

import numpy as np

from polycc.errors import PolyccError
from polycc.geometry.ellipsoid_box import boxes_inside, boxes_intersect
from polycc.occupancy.grid import OccupancyGrid
from polycc.scene.ellipsoids import Ellipsoids

_BITS = 21
_OFF = 1 << (_BITS - 1)  # voxel indices must lie in [-2^20, 2^20)
_MASK = (1 << _BITS) - 1
DIRECT_EXTENT = 4  # AABBs up to this many voxels per axis are enumerated voxel by voxel
SPLAT_CHUNK = 32_768
ITEM_BATCH = 400_000
MAX_VOXELS_PER_SPLAT = 1 << 27
PARALLEL_MIN_SPLATS = 50_000  # below this, slabs cost more than they save
# Splats at least this many voxels across on every axis have a solid interior; the scene is refused
# when those interiors would fill more than MAX_SOLID_VOXELS voxels (their cover costs their volume).
SOLID_MIN_DIAMETER = 8.0
MAX_SOLID_VOXELS = 250_000


def pack_keys(idx: np.ndarray) -> np.ndarray:
    """(N, 3) int voxel indices -> (N,) int64 keys that sort like the indices."""
    i = idx.astype(np.int64) + _OFF
    return (i[:, 0] << (2 * _BITS)) | (i[:, 1] << _BITS) | i[:, 2]


def unpack_keys(keys: np.ndarray) -> np.ndarray:
    out = np.empty((keys.size, 3), np.int64)
    out[:, 0] = (keys >> (2 * _BITS)) & _MASK
    out[:, 1] = (keys >> _BITS) & _MASK
    out[:, 2] = keys & _MASK
    return out - _OFF


def aabb_index_range(ell: Ellipsoids, g: float, origin: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Inclusive voxel index range (imin, imax), (N, 3) int64 each, of every ellipsoid's AABB.

    Widened by a relative 1e-9 so rounding can only add candidates.
    """
    h = ell.aabb_halfwidth() * (1.0 + 1e-9) + 1e-12
    lo = np.floor((ell.centers - h - origin) / g).astype(np.int64)
    hi = np.floor((ell.centers + h - origin) / g).astype(np.int64)
    return lo, hi


class _Accumulator:
    """Per-voxel counts merged across chunks: sorted unique keys + counts."""

    def __init__(self):
        self.parts: list[np.ndarray] = []
        self.pending = 0
        self.keys = np.empty(0, np.int64)
        self.counts = np.empty(0, np.int64)

    def add(self, keys: np.ndarray) -> None:
        if keys.size:
            self.parts.append(keys)
            self.pending += keys.size
            if self.pending > 8_000_000:
                self._merge()

    def _merge(self) -> None:
        if not self.parts:
            return
        k, c = np.unique(np.concatenate(self.parts), return_counts=True)
        self.parts, self.pending = [], 0
        allk = np.concatenate([self.keys, k])
        allc = np.concatenate([self.counts, c])
        order = np.argsort(allk, kind="stable")
        allk, allc = allk[order], allc[order]
        uk, start = np.unique(allk, return_index=True)
        self.keys, self.counts = uk, np.add.reduceat(allc, start) if allc.size else allc

    def result(self) -> tuple[np.ndarray, np.ndarray]:
        self._merge()
        return self.keys, self.counts


def _initial_blocks(imin: np.ndarray, imax: np.ndarray):
    """Tile each AABB index range with blocks of 2^L voxels; returns (owner, block_lo, level)."""
    ext = imax - imin + 1
    big = ext.max(axis=1)
    level = np.zeros(big.size, np.int64)
    over = big > DIRECT_EXTENT
    level[over] = np.ceil(np.log2(big[over] / DIRECT_EXTENT)).astype(np.int64)
    size = np.int64(1) << level
    nb = -(-ext // size[:, None])  # ceil
    n = nb.prod(axis=1)
    owner = np.repeat(np.arange(big.size), n)
    j = np.arange(owner.size) - np.repeat(np.cumsum(n) - n, n)
    nbo = nb[owner]
    b = np.stack([j % nbo[:, 0], (j // nbo[:, 0]) % nbo[:, 1], j // (nbo[:, 0] * nbo[:, 1])], axis=1)
    return owner, imin[owner] + b * size[owner, None], level[owner]


_CHILD = np.array([[(c >> 0) & 1, (c >> 1) & 1, (c >> 2) & 1] for c in range(8)], np.int64)


def _expand_blocks(block_lo: np.ndarray, level: np.ndarray, top: np.ndarray | None = None) -> np.ndarray:
    """All voxel indices of the given blocks (each 2^L per side), those above ``top`` (per block,
    inclusive; the owner's clipped AABB range) left out."""
    out = []
    for L in np.unique(level):
        s = 1 << int(L)
        g = np.stack(np.meshgrid(np.arange(s), np.arange(s), np.arange(s), indexing="ij"), axis=-1).reshape(-1, 3)
        pick = level == L
        v = block_lo[pick][:, None, :] + g[None, :, :]
        if top is not None:
            v = v[np.all(v <= top[pick][:, None, :], axis=2)]
        out.append(v.reshape(-1, 3))
    return np.concatenate(out) if out else np.empty((0, 3), np.int64)


def _voxelize_chunk(c: np.ndarray, M: np.ndarray, imin: np.ndarray, imax: np.ndarray, g: float, origin: np.ndarray,
                    acc: _Accumulator) -> int:
    """Emit the occupied voxel keys of one chunk of ellipsoids; returns the number of exact tests."""
    owner, blo, lev = _initial_blocks(imin, imax)
    tests = 0
    while owner.size:
        nxt_owner, nxt_blo, nxt_lev = [], [], []
        for s in range(0, owner.size, ITEM_BATCH):
            o, b, L = owner[s : s + ITEM_BATCH], blo[s : s + ITEM_BATCH], lev[s : s + ITEM_BATCH]
            size = (np.int64(1) << L)[:, None]
            lo = origin + b * g
            hi = origin + (b + size) * g
            hit = boxes_intersect(c[o], M[o], lo, hi)
            tests += o.size
            o, b, L, lo, hi = o[hit], b[hit], L[hit], lo[hit], hi[hit]
            leaf = L == 0
            acc.add(pack_keys(b[leaf]))
            o, b, L, lo, hi = o[~leaf], b[~leaf], L[~leaf], lo[~leaf], hi[~leaf]
            if not o.size:
                continue
            inside = boxes_inside(c[o], M[o], lo, hi)
            if inside.any():  # (a block may reach past a clipped range: cut it there)
                acc.add(pack_keys(_expand_blocks(b[inside], L[inside], imax[o[inside]])))
            o, b, L = o[~inside], b[~inside], L[~inside] - 1
            # Split into 8 children, dropping children beyond the owner's AABB range.
            half = (np.int64(1) << L)[:, None, None]
            cb = (b[:, None, :] + _CHILD[None] * half).reshape(-1, 3)
            co = np.repeat(o, 8)
            cl = np.repeat(L, 8)
            ok = np.all(cb <= imax[co], axis=1)
            nxt_owner.append(co[ok])
            nxt_blo.append(cb[ok])
            nxt_lev.append(cl[ok])
        if not nxt_owner:
            break
        owner, blo, lev = np.concatenate(nxt_owner), np.concatenate(nxt_blo), np.concatenate(nxt_lev)
    return tests


def solid_interior_voxels(ell: Ellipsoids, g: float) -> tuple[np.ndarray, np.ndarray]:
    """(per splat the voxels of g its solid interior fills, mask of the splats counted): the
    ellipsoid's volume in voxels for the splats at least :data:`SOLID_MIN_DIAMETER` voxels across
    on every axis (an upper bound of what overlapping ones fill together)."""
    d = 2.0 * ell.k * ell.sigmas  # (N, 3) diameters along the principal axes, metres
    big = np.all(d >= SOLID_MIN_DIAMETER * g, axis=1)
    vol = np.where(big, np.pi / 6.0 * np.prod(d / g, axis=1), 0.0)
    return vol, big


def _refuse_solid(ell: Ellipsoids, g: float, limit: float | None) -> None:
    """Splats much larger than a voxel cost their volume in voxels (every interior voxel is
    covered); refuse within a second, with the reason and the fix, when that volume is large."""
    if limit is None or len(ell) == 0:
        return
    vol, big = solid_interior_voxels(ell, g)
    total = float(vol.sum())
    if total <= limit:
        return
    i = int(np.argmax(vol))
    d = 2.0 * ell.k * ell.sigmas[i]
    g_ok = g * (total / limit) ** (1.0 / 3.0)
    raise PolyccError(
        f"{int(big.sum()):,} splats are much larger than a {g:g} m voxel (largest: splat {i} at "
        f"{np.round(ell.centers[i], 2).tolist()}, {d.min():.2f} x {d.max():.2f} m at {ell.k:g} sigma); their solid "
        f"interiors would fill about {total:,.0f} voxels (limit {limit:,.0f}), and every one of them must be covered. "
        f"Drop or cut them (--min-opacity, --crop), lower --sigma, or use --voxel {math.ceil(g_ok * 1000) / 1000:g} "
        "or larger")


def _voxelize_range(ell: Ellipsoids, imin: np.ndarray, imax: np.ndarray, g: float, origin: np.ndarray, chunk: int,
                    progress: Callable[[int], None] | None = None) -> tuple[np.ndarray, np.ndarray, int]:
    """(sorted keys, counts, exact tests) of the voxels in each ellipsoid's index range [imin, imax]."""
    acc = _Accumulator()
    tests = 0
    n = len(ell)
    for s in range(0, n, chunk):
        sub = ell.subset(slice(s, s + chunk))
        tests += _voxelize_chunk(sub.centers, sub.whitening(), imin[s : s + chunk], imax[s : s + chunk], g, origin, acc)
        if progress:
            progress(min(s + chunk, n))
    keys, counts = acc.result()
    return keys, counts, tests


def slab_task(centers, rotations, sigmas, k, imin, imax, g, origin, chunk) -> tuple[tuple, None]:
    """Occupancy of one slab (worker side): the ellipsoids' ranges are already clipped to it."""
    ell = Ellipsoids(centers, rotations, sigmas, k)
    return _voxelize_range(ell, imin, imax, g, origin, chunk), None


def slab_bounds(ell: Ellipsoids, imin: np.ndarray, imax: np.ndarray, slabs: int) -> np.ndarray:
    """(S + 1,) x voxel indices cutting the scene into slabs [b_k, b_k+1) of about equal work:
    each splat weighs about the surface of its bounding box in voxels, at its centre."""
    ext = (imax - imin + 1).astype(np.float64)
    w = 8.0 + 2.0 * (ext[:, 0] * ext[:, 1] + ext[:, 1] * ext[:, 2] + ext[:, 0] * ext[:, 2])
    x = (imin[:, 0] + imax[:, 0]) // 2
    order = np.argsort(x, kind="stable")
    cw = np.cumsum(w[order])
    cuts = np.searchsorted(cw, cw[-1] * np.arange(1, slabs) / slabs)
    inner = np.unique(x[order][np.minimum(cuts, len(x) - 1)] + 1)
    lo, hi = int(imin[:, 0].min()), int(imax[:, 0].max()) + 1
    return np.unique(np.concatenate([[lo], inner[(inner > lo) & (inner < hi)], [hi]]))


def _voxelize_slabs(ell, imin, imax, g, origin, runner, progress, chunk) -> tuple[np.ndarray, np.ndarray, int]:
    """The occupancy as one task per x slab (each voxel belongs to one slab, and each
    (ellipsoid, voxel) pair is tested in that slab only, so counts stay exact). Slab keys are
    x-major, so their concatenation in slab order is sorted."""
    from polycc.parallel import Task

    cuts = slab_bounds(ell, imin, imax, max(2, 4 * runner.workers))
    graph = {}
    for s, (lo, hi) in enumerate(zip(cuts[:-1], cuts[1:])):
        def args(lo=int(lo), hi=int(hi) - 1):
            sel = np.flatnonzero((imin[:, 0] <= hi) & (imax[:, 0] >= lo))
            a, b = imin.take(sel, axis=0), imax.take(sel, axis=0)  # take: a third faster than [sel] on rows
            a[:, 0] = np.maximum(a[:, 0], lo)
            b[:, 0] = np.minimum(b[:, 0], hi)
            return (ell.centers.take(sel, axis=0), ell.rotations.take(sel, axis=0), ell.sigmas.take(sel, axis=0),
                    ell.k, a, b, g, origin, chunk)
        graph[("occupancy", s)] = Task(slab_task, args)
    n = len(ell)
    res = runner.run(graph, (lambda d, t: progress(int(n * d / t))) if progress else None)
    parts = [res[k] for k in graph]
    keys = np.concatenate([p[0] for p in parts])
    counts = np.concatenate([p[1] for p in parts])
    return keys, counts, int(sum(p[2] for p in parts))


def voxelize(
    ell: Ellipsoids,
    voxel_size: float,
    min_splats_per_voxel: int = 1,
    origin: np.ndarray | None = None,
    progress: Callable[[int], None] | None = None,
    chunk: int = SPLAT_CHUNK,
    runner=None,
    max_solid_voxels: float | None = MAX_SOLID_VOXELS,
) -> OccupancyGrid:
    """The exact occupancy V+ of the ellipsoids ``ell``: every voxel that meets one of them.

    Parameters
    ----------
    ell : the splat ellipsoids, world frame, metres (``Scene.ellipsoids``).
    voxel_size : voxel side g, metres; voxel i spans ``[origin + i g, origin + (i + 1) g]``.
    min_splats_per_voxel : the floater filter, keep a voxel only if at least this many distinct
        ellipsoids touch it (1 = off; above 1 the result no longer covers every ellipsoid:
        :mod:`polycc.occupancy.floaters` reports how much).
    origin : (3,) grid origin, metres (default 0).
    progress : ``progress(n)`` with the number of ellipsoids done, after each chunk.
    runner : a :mod:`polycc.parallel` runner with more than one worker voxelizes x slabs in
        parallel (same result).
    max_solid_voxels : refuse at once (PolyccError naming the splats and the fix) a scene whose
        splats much larger than a voxel would fill more than this many voxels with solid interior
        (:func:`solid_interior_voxels`); None = no limit.

    Returns
    -------
    OccupancyGrid of sorted unique int64 voxel indices, with per-voxel ellipsoid counts and the
    voxels the floater filter removed.
    """
    g = float(voxel_size)
    if not (np.isfinite(g) and g > 0):
        raise PolyccError(f"--voxel {voxel_size}: must be a positive size in metres (e.g. 0.05)")
    if min_splats_per_voxel < 1:
        raise PolyccError(f"--min-splats-per-voxel {min_splats_per_voxel}: must be at least 1")
    origin = np.zeros(3) if origin is None else np.asarray(origin, np.float64)
    n = len(ell)
    imin, imax = aabb_index_range(ell, g, origin)
    if n and (imin.min() < -_OFF or imax.max() >= _OFF):
        raise PolyccError(
            f"the scene spans more than {2 * _OFF} voxels of {g:g} m along an axis; "
            "use --crop to cut it to the flight volume, --scale/--transform to put it in metres, or a larger --voxel"
        )
    per = np.prod((imax - imin + 1).astype(np.float64), axis=1)
    if n and per.max() > MAX_VOXELS_PER_SPLAT:
        i = int(per.argmax())
        raise PolyccError(
            f"splat {i} at {np.round(ell.centers[i], 3).tolist()} spans {per[i]:.3g} voxels of {g:g} m "
            f"(its {ell.k:g}-sigma extent is {2 * ell.aabb_halfwidth()[i].max():.3g} m); "
            "crop it away with --crop, drop it with --min-opacity, or use a larger --voxel"
        )
    _refuse_solid(ell, g, max_solid_voxels)
    if runner is not None and runner.workers > 1 and n >= PARALLEL_MIN_SPLATS:
        keys, counts, tests = _voxelize_slabs(ell, imin, imax, g, origin, runner, progress, chunk)
    else:
        keys, counts, tests = _voxelize_range(ell, imin, imax, g, origin, chunk, progress)
    n_all = int(keys.size)
    keep = counts >= min_splats_per_voxel
    removed = unpack_keys(keys[~keep])
    keys, counts = keys[keep], counts[keep]
    stats = {
        "ellipsoids": n,
        "aabb_candidate_voxels": int(per.sum()),
        "exact_tests": int(tests),
        "voxels_before_floater_filter": n_all,
        "voxels_removed_by_floater_filter": n_all - int(keys.size),
        "voxels": int(keys.size),
        "min_splats_per_voxel": int(min_splats_per_voxel),
    }
    return OccupancyGrid(
        indices=unpack_keys(keys),
        voxel_size=g,
        origin=origin,
        counts=counts.astype(np.int32),
        stats=stats,
        removed=removed,
    )
