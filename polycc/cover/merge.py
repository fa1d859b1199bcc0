"""Iterative merging of the sub-cover (PolyMerge Sec. V-C, Eqs. 12-15).

Nodes ``0..N-1`` are the sub-cover clusters; merge ``t`` creates node ``N + t`` from two
live nodes, until one node is left. Only pairs whose bounding boxes overlap or touch are
candidates (as in the paper); their costs sit in a heap with lazy invalidation (an entry
is skipped when either node has died). If the heap runs dry with more than one node left
(disconnected parts), the touch margin is doubled (1, 2, 4, ... voxels) and the pairs
re-enumerated, so the family always reaches n = 1.

A node keeps only its hull vertices: ``Hull(A u B) = Hull(verts(A) u verts(B))``.

Weight of a node (Eq. 11, documented bound): ``W = Vol(Hull) - g^3 #{v in V+ : v inside
Hull}``. Voxels only partly inside the hull are not subtracted, so W over-estimates the
exact free volume by at most ``g^3`` times the number of partly covered voxels. For the
sub-cover clusters it is exact (see :mod:`polycc.cover.clusters`).

Merge costs:

- ``paper``: ``W(A u B)`` (Eq. 13).
- ``delta``: ``W(A u B) - W(A) - W(B)``, the free volume the merge *adds*. The paper's
  cost charges a merge for waste its parts already had, so it prefers merging small
  clusters even when that adds more free space than merging two large, already-wasteful
  neighbours whose union adds none.
"""

from __future__ import annotations

import heapq
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from polycc.geometry.lattice import integer_planes, lattice_hull

MERGE_COSTS = ("paper", "delta")
# Candidate boxes with more cells than this are first ranked by a lower bound of their
# cost (occupied count <= voxels in the box); the exact count runs only when the pair
# reaches the top of the heap.
BOUND_CELLS = 2048
BRICK = 8
# qhull options for ranking candidate pairs: joggled input is ~30% faster on the degenerate
# lattice points; volumes and planes are within ~1e-9 cells, far below the cost differences.
# Stored nodes always use exact "Qt" hulls.
EVAL_QHULL = b"QJ"
CORNER_MASK = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], dtype=bool)
DENSE_LIMIT = 1 << 24  # cells (bool grid + int32 summed-volume table ~ 85 MB); above: bricks


def _inside_count(vox: np.ndarray, A: np.ndarray, b: np.ndarray, tol: float) -> int:
    """How many voxels ``vox`` lie entirely inside ``{A q + b <= 0}`` (farthest corner inside)."""
    s = (vox + 0.5) @ A.T + (0.5 * np.abs(A).sum(axis=1) + b)
    return int(np.count_nonzero(s.max(axis=1) <= tol))


class VoxelBoxQuery:
    """Occupied voxels inside an axis-aligned index box (local coordinates >= 0)."""

    BRICK = 16

    def __init__(self, q: np.ndarray):
        self.shape = tuple(int(s) for s in (q.max(axis=0) + 1)) if len(q) else (1, 1, 1)
        self.total = len(q)
        if np.prod(self.shape, dtype=np.float64) <= DENSE_LIMIT:
            self.dense = np.zeros(self.shape, dtype=bool)
            self.dense[q[:, 0], q[:, 1], q[:, 2]] = True
            self.bricks = None
            # summed-volume table: S[x, y, z] = #voxels with index < (x, y, z)
            S = np.zeros(tuple(s + 1 for s in self.shape), np.int32)
            S[1:, 1:, 1:] = self.dense.cumsum(0, dtype=np.int32).cumsum(1).cumsum(2)
            self.sat = S
        else:
            self.dense = None
            self.sat = None
            bk = q // self.BRICK
            order = np.lexsort((bk[:, 2], bk[:, 1], bk[:, 0]))
            bk, qs = bk[order], q[order]
            cut = np.flatnonzero(np.any(np.diff(bk, axis=0) != 0, axis=1)) + 1
            starts = np.concatenate([[0], cut])
            ends = np.concatenate([cut, [len(qs)]])
            self.bricks = {tuple(bk[s]): qs[s:e] for s, e in zip(starts, ends)}

    def count(self, lo: np.ndarray, hi: np.ndarray) -> int:
        """Number of occupied voxels with lo <= v <= hi (an upper bound without the table)."""
        if self.sat is None:
            return self.total
        a = np.maximum(lo, 0)
        b = np.minimum(hi + 1, np.asarray(self.shape))
        if np.any(b <= a):
            return 0
        S = self.sat
        return int(S[b[0], b[1], b[2]] - S[a[0], b[1], b[2]] - S[b[0], a[1], b[2]] - S[b[0], b[1], a[2]]
                   + S[a[0], a[1], b[2]] + S[a[0], b[1], a[2]] + S[b[0], a[1], a[2]] - S[a[0], a[1], a[2]])

    def count_inside(self, A: np.ndarray, b: np.ndarray, lo: np.ndarray, hi: np.ndarray, tol: float = 1e-7) -> int:
        """Occupied voxels with lo <= v <= hi lying entirely inside ``{q : A q + b <= 0}``.

        A voxel is inside iff its farthest corner is: ``A c + |A|_1 / 2 + b <= 0`` (c = centre).
        Large boxes are first cut into bricks of 8^3 voxels: a brick whose 8 corners are all
        inside counts whole (summed-volume table), a brick whose corners all violate one
        plane is skipped, and only voxels of the other bricks are tested one by one.
        """
        cand = self.voxels(lo, hi)
        if len(cand) == 0:
            return 0
        B = BRICK
        if self.sat is None or len(cand) < 4 * B**3:
            return _inside_count(cand, A, b, tol)
        lo = np.maximum(lo, 0)
        hi = np.minimum(hi, np.asarray(self.shape) - 1)
        blo, bhi = lo // B, hi // B
        nb = bhi - blo + 1
        kk = np.stack(np.meshgrid(*[np.arange(n) for n in nb], indexing="ij"), -1).reshape(-1, 3) + blo
        c0 = np.maximum(kk * B, lo)  # clipped brick voxel range [c0, c1]
        c1 = np.minimum(kk * B + B - 1, hi)
        corners = np.where(CORNER_MASK[None], c1[:, None, :] + 1, c0[:, None, :])  # (K, 8, 3)
        sc = corners.astype(np.float64) @ A.T + b  # (K, 8, F)
        full = sc.max(axis=(1, 2)) <= tol
        out = np.any(sc.min(axis=1) > tol, axis=1)
        a, e = c0[full], c1[full] + 1  # clipped bricks lie inside the grid
        S = self.sat
        total = int((S[e[:, 0], e[:, 1], e[:, 2]] - S[a[:, 0], e[:, 1], e[:, 2]] - S[e[:, 0], a[:, 1], e[:, 2]]
                     - S[e[:, 0], e[:, 1], a[:, 2]] + S[a[:, 0], a[:, 1], e[:, 2]] + S[a[:, 0], e[:, 1], a[:, 2]]
                     + S[e[:, 0], a[:, 1], a[:, 2]] - S[a[:, 0], a[:, 1], a[:, 2]]).sum())
        cb = (cand // B - blo) @ np.array([nb[1] * nb[2], nb[2], 1])
        part = ~(full | out)
        test = cand[part[cb]]
        if len(test):
            total += _inside_count(test, A, b, tol)
        return total

    def voxels(self, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
        """(M, 3) voxels with lo <= v <= hi (inclusive voxel indices)."""
        lo = np.maximum(lo, 0)
        hi = np.minimum(hi, np.asarray(self.shape) - 1)
        if np.any(hi < lo):
            return np.empty((0, 3), np.int64)
        if self.dense is not None:
            sub = self.dense[lo[0] : hi[0] + 1, lo[1] : hi[1] + 1, lo[2] : hi[2] + 1]
            return np.argwhere(sub) + lo
        blo, bhi = lo // self.BRICK, hi // self.BRICK
        parts = []
        for bx in range(blo[0], bhi[0] + 1):
            for by in range(blo[1], bhi[1] + 1):
                for bz in range(blo[2], bhi[2] + 1):
                    a = self.bricks.get((bx, by, bz))
                    if a is not None:
                        parts.append(a)
        if not parts:
            return np.empty((0, 3), np.int64)
        a = np.concatenate(parts)
        return a[np.all((a >= lo) & (a <= hi), axis=1)]


@dataclass
class MergeResult:
    """The merge sequence over ``2N-1`` nodes (local lattice coordinates).

    merges:   (N-1, 2) int64 node ids merged at step t into node N + t.
    costs:    (N-1,) float64 cost of each merge, cells (g^3).
    weight:   (2N-1,) float64 W of each node, cells.
    volume:   (2N-1,) float64 hull volume of each node, cells.
    vertices: list of (H, 3) int64 hull vertices per node (local lattice coordinates).
    planes:   list of ((F, 3) int64 normals, (F,) int64 offsets) per node, exact
              (None for the leaves: the caller has them per cluster pattern).
    margin_rounds: how often the touch margin had to grow (disconnected parts).
    pair_evaluations: number of candidate pairs whose union hull was computed.
    """

    merges: np.ndarray
    costs: np.ndarray
    weight: np.ndarray
    volume: np.ndarray
    vertices: list
    planes: list = field(default_factory=list)
    margin_rounds: int = 0
    pair_evaluations: int = 0


class _Live:
    """Compact arrays of live node ids and their boxes, for vectorised touch queries."""

    def __init__(self, cap: int):
        self.ids = np.empty(cap, np.int64)
        self.lo = np.empty((cap, 3), np.int64)
        self.hi = np.empty((cap, 3), np.int64)
        self.pos = np.full(cap, -1, np.int64)
        self.n = 0

    def add(self, i: int, lo, hi) -> None:
        k = self.n
        self.ids[k], self.lo[k], self.hi[k], self.pos[i] = i, lo, hi, k
        self.n += 1

    def remove(self, i: int) -> None:
        k, last = self.pos[i], self.n - 1
        j = self.ids[last]
        self.ids[k], self.lo[k], self.hi[k], self.pos[j] = j, self.lo[last], self.hi[last], k
        self.pos[i] = -1
        self.n -= 1

    def touching(self, lo, hi, margin: int) -> np.ndarray:
        n = self.n
        ok = np.all((self.lo[:n] <= hi + margin) & (lo <= self.hi[:n] + margin), axis=1)
        return self.ids[:n][ok]


def _initial_pairs(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """All (i < j) with touching closed boxes, via a uniform grid of cell = max box size."""
    n = len(lo)
    if n < 2:
        return np.empty((0, 2), np.int64)
    S = max(int((hi - lo).max()), 1)
    cell = lo // S
    cell -= cell.min(axis=0)
    dims = cell.max(axis=0) + 3
    key = (cell[:, 0] * dims[1] + cell[:, 1]) * dims[2] + cell[:, 2]
    order = np.argsort(key, kind="stable")
    skey = key[order]
    out = []
    for dx in (-1, 0, 1):
        for dy in (-1, 0, 1):
            for dz in (-1, 0, 1):
                nkey = key + (dx * dims[1] + dy) * dims[2] + dz
                a = np.searchsorted(skey, nkey, "left")
                b = np.searchsorted(skey, nkey, "right")
                cnt = b - a
                if cnt.sum() == 0:
                    continue
                i = np.repeat(np.arange(n), cnt)
                start = np.repeat(a, cnt)
                within = np.arange(cnt.sum()) - np.repeat(np.cumsum(cnt) - cnt, cnt)
                j = order[start + within]
                keep = i < j
                out.append(np.column_stack([i[keep], j[keep]]))
    p = np.concatenate(out)
    ok = np.all((lo[p[:, 0]] <= hi[p[:, 1]]) & (lo[p[:, 1]] <= hi[p[:, 0]]), axis=1)
    return p[ok]


def merge_all(
    leaf_vertices: list,
    leaf_weight: np.ndarray,
    leaf_volume: np.ndarray,
    voxels_local: np.ndarray,
    cost: str = "delta",
    progress: Callable[[int], None] | None = None,
    refresh: str = "lazy",
    leaf_planes: list | None = None,
    leaf_patterns: list | None = None,
) -> MergeResult:
    """Merge N leaves (hull vertices in local lattice coordinates) down to one node.

    ``voxels_local`` (V, 3) are all occupied voxels in the same local coordinates (>= 0),
    used to count the occupied voxels inside each candidate hull.
    ``progress(k)`` is called with the number of merges done. ``leaf_patterns`` (one
    hashable per leaf: equal for leaves that are translates of each other) enables a cache
    of leaf-pair weights.

    ``refresh``: what happens to the pairs of the two merged nodes. ``eager`` evaluates
    every touching pair of the new node at once (exact greedy argmin of Eq. 13).
    ``lazy`` evaluates only pairs that are new neighbours; a neighbour's old entry
    ``(i, o)`` keeps its key until popped, then is re-evaluated as ``(new, o)`` and
    pushed back. For ``paper`` the old key is a lower bound (W grows with the hull:
    ``Vol(H \\ V+)`` is monotone), so lazy is the exact greedy up to partly covered
    voxels; for ``delta`` it is an approximation. See bench/bench_cover.py.
    """
    if refresh not in ("lazy", "eager"):
        raise ValueError(f"refresh must be 'lazy' or 'eager', not {refresh!r}")
    if cost not in MERGE_COSTS:
        raise ValueError(f"unknown merge cost {cost!r}; choose one of {MERGE_COSTS}")
    m = _Merger(leaf_vertices, leaf_weight, leaf_volume, voxels_local, cost, refresh == "eager", leaf_planes,
                leaf_patterns)
    return m.run(progress)


class _Merger:
    """State of one merge run: nodes (vertices, exact planes, W, volume, box), the live set, the
    candidate heap with lazy invalidation, and the adjacency of live nodes."""

    def __init__(self, leaf_vertices, leaf_weight, leaf_volume, voxels_local, cost, eager, leaf_planes,
                 leaf_patterns):
        N = self.N = len(leaf_vertices)
        M = 2 * N - 1
        self.eager = eager
        self.paper = cost == "paper"
        self.verts: list = list(leaf_vertices) + [None] * (N - 1)
        # exact integer planes (N q <= e) of every node; the caller passes the leaves' (cached per pattern)
        self.planes: list = (list(leaf_planes) if leaf_planes is not None else [None] * N) + [None] * (N - 1)
        self.weight = np.zeros(M)
        self.volume = np.zeros(M)
        self.weight[:N], self.volume[:N] = leaf_weight, leaf_volume
        self.lo = np.zeros((M, 3), np.int64)
        self.hi = np.zeros((M, 3), np.int64)
        for i, v in enumerate(leaf_vertices):
            self.lo[i], self.hi[i] = v.min(axis=0), v.max(axis=0)
        self.alive = np.zeros(M, bool)
        self.alive[:N] = True
        self.live = _Live(M)
        for i in range(N):
            self.live.add(i, self.lo[i], self.hi[i])
        self.query = VoxelBoxQuery(voxels_local)
        self.evals = 0
        # W of a pair of leaves depends only on (pattern, pattern, offset, occupancy of the union's
        # box): floors and walls repeat the same few, so their hulls are computed once.
        self.leaf_cache: dict = {}
        self.leaf_patterns = leaf_patterns
        self.use_cache = leaf_patterns is not None and self.query.dense is not None
        self.heap: list = []
        self.parent = list(range(M))
        self.adj: list = [set() for _ in range(N)] + [None] * (N - 1)
        self.fresh: set = set()  # pairs (a < b) that have an entry computed while both were alive
        self.margin = 0
        self.rounds = 0

    def _cost(self, w, i, j):
        return w if self.paper else w - self.weight[i] - self.weight[j]

    def evaluate(self, i: int, j: int, exact: bool = True, options: bytes = EVAL_QHULL):
        """(cost, W, hull, exact) of merging nodes i and j; with ``exact=False`` a large
        box gets a lower bound of the cost instead (W is None then). The hull is None when
        the W of a leaf pair came from the cache."""
        lo, hi, query = self.lo, self.hi, self.query
        key = None
        if self.use_cache and i < self.N and j < self.N and options == EVAL_QHULL:
            blo, bhi = np.minimum(lo[i], lo[j]), np.maximum(hi[i], hi[j])
            box = query.dense[blo[0] : bhi[0], blo[1] : bhi[1], blo[2] : bhi[2]]
            key = (self.leaf_patterns[i], self.leaf_patterns[j], (lo[j] - lo[i]).tobytes(), box.shape, box.tobytes())
            w = self.leaf_cache.get(key)
            if w is not None:
                return self._cost(w, i, j), w, None, True
        self.evals += 1
        h = lattice_hull(np.concatenate([self.verts[i], self.verts[j]]), options)
        blo, bhi = np.minimum(lo[i], lo[j]), np.maximum(hi[i], hi[j])
        if not exact and np.prod(bhi - blo) > BOUND_CELLS:
            w = max(h.volume - query.count(blo, bhi - 1), 0.0)
            return self._cost(w, i, j), None, h, False
        eq = h.equations
        if np.prod(bhi - blo) > BOUND_CELLS:
            eq = np.unique(np.round(eq, 12), axis=0)  # qhull repeats coplanar facets
        occ = query.count_inside(eq[:, :3], eq[:, 3], blo, bhi - 1)
        w = max(h.volume - occ, 0.0)
        if key is not None:
            self.leaf_cache[key] = w
        return self._cost(w, i, j), w, h, True

    def find(self, a: int) -> int:
        parent = self.parent
        r = a
        while parent[r] != r:
            r = parent[r]
        while parent[a] != r:
            parent[a], a = r, parent[a]
        return r

    def add_pair(self, a: int, b: int, batch: bool = False, exact: bool = False) -> None:
        a, b = (a, b) if a < b else (b, a)
        c, _, _, ex = self.evaluate(a, b, exact)
        entry = (c, a, b, ex)
        self.heap.append(entry) if batch else heapq.heappush(self.heap, entry)
        self.fresh.add((a, b))
        self.adj[a].add(b)
        self.adj[b].add(a)

    def widen(self) -> None:
        """Disconnected parts left: widen what "touching" means and enumerate the new pairs."""
        self.margin = max(1, 2 * self.margin)
        self.rounds += 1
        for i in self.live.ids[: self.live.n].copy():
            others = self.live.touching(self.lo[i], self.hi[i], self.margin)
            for j in others[others > i]:
                if (int(i), int(j)) not in self.fresh:
                    self.add_pair(int(i), int(j), batch=True)
        heapq.heapify(self.heap)

    def pop_best(self) -> tuple[float, int, int]:
        """The cheapest pair of two live nodes (re-evaluating stale or bound-only entries)."""
        heap, alive = self.heap, self.alive
        while True:
            if not heap:
                self.widen()
                continue
            c, i, j, ex = heapq.heappop(heap)
            if alive[i] and alive[j]:
                if ex:
                    return c, i, j
                heapq.heappush(heap, (self.evaluate(i, j, True)[0], i, j, True))  # bound -> exact
                continue
            if self.eager:
                continue  # the merged node's pairs were all evaluated when it was made
            a, b = self.find(i), self.find(j)
            if a != b and (min(a, b), max(a, b)) not in self.fresh:
                self.add_pair(a, b)  # stale key: re-evaluate for the live nodes, push back

    def merge(self, t: int, i: int, j: int) -> None:
        """Merge step t: node N + t from live nodes i and j, with exact facets and vertices."""
        k = self.N + t
        _, self.weight[k], h, _ = self.evaluate(i, j, True, b"Qt")
        self.evals -= 1
        self.verts[k], self.volume[k] = h.vertices, h.volume
        self.planes[k] = integer_planes(h)
        self.lo[k], self.hi[k] = h.vertices.min(axis=0), h.vertices.max(axis=0)
        self.alive[i] = self.alive[j] = False
        self.parent[i] = self.parent[j] = k
        self.live.remove(i)
        self.live.remove(j)
        adj = self.adj
        nb = (adj[i] | adj[j]) - {i, j}
        adj[i] = adj[j] = None
        for o in nb:
            adj[o].discard(i)
            adj[o].discard(j)
            adj[o].add(k)
        adj[k] = nb
        self.alive[k] = True
        for o in self.live.touching(self.lo[k], self.hi[k], self.margin):
            if self.eager or int(o) not in nb:
                self.add_pair(int(o), k)
        self.live.add(k, self.lo[k], self.hi[k])

    def run(self, progress) -> MergeResult:
        N = self.N
        for i, j in _initial_pairs(self.lo[:N], self.hi[:N]):
            self.add_pair(int(i), int(j), batch=True)
        heapq.heapify(self.heap)
        merges = np.zeros((max(N - 1, 0), 2), np.int64)
        costs = np.zeros(max(N - 1, 0))
        for t in range(N - 1):
            c, i, j = self.pop_best()
            merges[t], costs[t] = (i, j), c
            self.merge(t, i, j)
            if progress is not None and (t % 256 == 0 or t == N - 2):
                progress(t + 1)
        return MergeResult(merges, costs, self.weight, self.volume, self.verts, self.planes,
                           margin_rounds=self.rounds, pair_evaluations=self.evals)
