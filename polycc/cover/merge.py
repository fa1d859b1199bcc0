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

from polycc.geometry.lattice import integer_planes, lattice_hull, lattice_hull_facets
from polycc.native import count_inside as count_inside_c

MERGE_COSTS = ("paper", "delta")
# Candidate boxes with more cells than this are first ranked by a lower bound of their
# cost (occupied count <= voxels in the box); the exact count runs only when the pair
# reaches the top of the heap.
BOUND_CELLS = 2048
# qhull options for ranking candidate pairs: joggled input is ~30% faster on the degenerate
# lattice points; volumes and planes are within ~1e-9 cells, far below the cost differences.
# Stored nodes always use exact "Qt" hulls.
EVAL_QHULL = b"QJ"
# heap entry kinds: a bound of the cost, the exact cost, or an old key handed on by a part's stage
BOUND, EXACT, STALE = 0, 1, -1
DIRECT_CELLS = 4096  # boxes up to this many cells are counted voxel by voxel (cheaper than columns)
DENSE_LIMIT = 1 << 24  # cells (bool grid + int32 summed-volume table ~ 85 MB); above: sorted column keys


def _inside_count(vox: np.ndarray, A: np.ndarray, b: np.ndarray, tol: float) -> int:
    """How many voxels ``vox`` lie entirely inside ``{A q + b <= 0}`` (farthest corner inside).
    The reference the column count of :meth:`VoxelBoxQuery.count_inside` is tested against."""
    s = (vox + 0.5) @ A.T + (0.5 * np.abs(A).sum(axis=1) + b)
    return int(np.count_nonzero(s.max(axis=1) <= tol))


class VoxelBoxQuery:
    """Occupied voxels of a local lattice (coordinates >= 0): counts in axis-aligned index boxes and
    inside convex polytopes.

    Small lattices (at most :data:`DENSE_LIMIT` cells) keep a bool grid and its summed-volume table
    (box counts in O(1)); larger ones keep, per axis, the sorted keys of the voxels with that axis
    last (a column along the axis is a contiguous key range, counted by two binary searches), so the
    memory is O(voxels), not O(box).
    """

    def __init__(self, q: np.ndarray):
        q = np.asarray(q, np.int64).reshape(-1, 3)
        self.shape = tuple(int(s) for s in (q.max(axis=0) + 1)) if len(q) else (1, 1, 1)
        self.total = len(q)
        self.dense = self.sat = None
        self.keys = None
        if np.prod(self.shape, dtype=np.float64) <= DENSE_LIMIT:
            self.dense = np.zeros(self.shape, dtype=bool)
            self.dense[q[:, 0], q[:, 1], q[:, 2]] = True
            # summed-volume table: S[x, y, z] = #voxels with index < (x, y, z)
            S = np.zeros(tuple(s + 1 for s in self.shape), np.int32)
            S[1:, 1:, 1:] = self.dense.cumsum(0, dtype=np.int32).cumsum(1).cumsum(2)
            self.sat = S
        else:
            self.keys = [np.sort(self._key(q, a)) for a in range(3)]
        # what the C count reads (polycc.native.count_inside): the grid as bytes, or the three key arrays in one
        # (self.keys then views its rows: the keys are held once)
        self._dense8 = None if self.dense is None else self.dense.view(np.uint8)
        self._keys3 = None if self.keys is None else np.stack(self.keys)
        if self._keys3 is not None:
            self.keys = list(self._keys3)

    def _key(self, q: np.ndarray, a: int) -> np.ndarray:
        """Packed key of voxels ``q`` ordered (u, v, t): t = coordinate along axis a."""
        u, v = _OTHER[a]
        s = self.shape
        return (q[..., u] * s[v] + q[..., v]) * (s[a] + 1) + q[..., a]

    def _columns(self, a: int, u: np.ndarray, v: np.ndarray, t0: np.ndarray, t1: np.ndarray) -> np.ndarray:
        """Occupied voxels of the columns (u, v) along axis a with t0 <= t <= t1 (arrays, clipped to the grid)."""
        ua, va = _OTHER[a]
        t0 = np.maximum(t0, 0)
        t1 = np.minimum(t1, self.shape[a] - 1)
        ok = t1 >= t0
        t0 = np.where(ok, t0, 0)
        t1 = np.where(ok, t1, -1)
        if self.sat is not None:
            S = self.sat
            lo = [None] * 3
            hi = [None] * 3
            lo[a], hi[a] = t0, t1 + 1
            lo[ua], hi[ua] = u, u + 1
            lo[va], hi[va] = v, v + 1
            c = (S[hi[0], hi[1], hi[2]] - S[lo[0], hi[1], hi[2]] - S[hi[0], lo[1], hi[2]] - S[hi[0], hi[1], lo[2]]
                 + S[lo[0], lo[1], hi[2]] + S[lo[0], hi[1], lo[2]] + S[hi[0], lo[1], lo[2]] - S[lo[0], lo[1], lo[2]])
            return np.where(ok, c, 0)
        s = self.shape
        base = (u * s[va] + v) * (s[a] + 1)
        k = self.keys[a]
        return np.where(ok, np.searchsorted(k, base + t1, "right") - np.searchsorted(k, base + t0, "left"), 0)

    def count(self, lo: np.ndarray, hi: np.ndarray) -> int:
        """Number of occupied voxels with lo <= v <= hi."""
        a = np.maximum(lo, 0)
        b = np.minimum(hi + 1, np.asarray(self.shape))
        if np.any(b <= a):
            return 0
        if self.sat is not None:
            S = self.sat
            return int(S[b[0], b[1], b[2]] - S[a[0], b[1], b[2]] - S[b[0], a[1], b[2]] - S[b[0], b[1], a[2]]
                       + S[a[0], a[1], b[2]] + S[a[0], b[1], a[2]] + S[b[0], a[1], a[2]] - S[a[0], a[1], a[2]])
        ax = int(np.argmax(b - a))
        uu, vv = _OTHER[ax]
        U, V = np.meshgrid(np.arange(a[uu], b[uu]), np.arange(a[vv], b[vv]), indexing="ij")
        n = U.size
        return int(self._columns(ax, U.ravel(), V.ravel(), np.full(n, a[ax]), np.full(n, b[ax] - 1)).sum())

    def count_inside(self, A: np.ndarray, b: np.ndarray, lo: np.ndarray, hi: np.ndarray, tol: float = 1e-7) -> int:
        """Occupied voxels with lo <= v <= hi lying entirely inside the convex ``{q : A q + b <= 0}``: in C
        (:func:`polycc.native.count_inside`, the arithmetic of :meth:`count_inside_numpy`), or by that
        reference where the C is not available."""
        c = count_inside_c(self._dense8, self.sat, self._keys3, self.shape, A, b, lo, hi, tol, DIRECT_CELLS)
        return self.count_inside_numpy(A, b, lo, hi, tol) if c is None else c

    def count_inside_numpy(self, A: np.ndarray, b: np.ndarray, lo: np.ndarray, hi: np.ndarray,
                           tol: float = 1e-7) -> int:
        """Occupied voxels with lo <= v <= hi lying entirely inside the convex ``{q : A q + b <= 0}``.

        A voxel is inside iff its 8 corners are (``A c + b <= tol`` for every row). Along any
        line parallel to an axis the polytope is an interval, so the box is cut into columns
        along its longest axis: on each of the ``(footprint + 1)`` corner lines the interval
        [lower, upper] of the axis coordinate comes from the rows in O(rows), and a column's
        voxels t are inside iff ``t >= max lower`` and ``t + 1 <= min upper`` over its 4 corner
        lines; the occupied ones in that range are counted from the table. Cost O(rows x
        footprint), not O(voxels in the box): same predicate as :func:`_inside_count`.
        """
        lo = np.maximum(np.asarray(lo, np.int64), 0)
        hi = np.minimum(np.asarray(hi, np.int64), np.asarray(self.shape) - 1)
        if np.any(hi < lo):
            return 0
        if self.dense is not None and np.prod(hi - lo + 1) <= DIRECT_CELLS:  # small box: test its voxels
            sub = self.dense[lo[0] : hi[0] + 1, lo[1] : hi[1] + 1, lo[2] : hi[2] + 1]
            return _inside_count(np.argwhere(sub) + lo, np.asarray(A, np.float64), np.asarray(b, np.float64), tol)
        a = int(np.argmax(hi - lo))
        ua, va = _OTHER[a]
        lu = np.arange(lo[ua], hi[ua] + 2, dtype=np.float64)  # corner lines of the footprint
        lv = np.arange(lo[va], hi[va] + 2, dtype=np.float64)
        A = np.asarray(A, np.float64)
        r = (A[:, ua, None, None] * lu[None, :, None] + A[:, va, None, None] * lv[None, None, :]
             + np.asarray(b, np.float64)[:, None, None])  # (F, Lu, Lv)
        Aa = A[:, a]
        inf = np.inf
        with np.errstate(divide="ignore", invalid="ignore"):
            bound = (tol - r) / Aa[:, None, None]
        up = np.where((Aa > 0)[:, None, None], bound, inf).min(axis=0)
        low = np.where((Aa < 0)[:, None, None], bound, -inf).max(axis=0)
        flat = Aa == 0
        if np.any(flat):
            bad = np.any(r[flat] > tol, axis=0)
            up = np.where(bad, -inf, up)
        cl = np.maximum(np.maximum(low[:-1, :-1], low[1:, :-1]), np.maximum(low[:-1, 1:], low[1:, 1:]))
        cu = np.minimum(np.minimum(up[:-1, :-1], up[1:, :-1]), np.minimum(up[:-1, 1:], up[1:, 1:]))
        t0 = np.ceil(np.clip(cl, lo[a] - 1, hi[a] + 1))
        t1 = np.floor(np.clip(cu, lo[a] - 1, hi[a] + 2)) - 1
        t0 = np.maximum(t0, lo[a]).astype(np.int64).ravel()
        t1 = np.minimum(t1, hi[a]).astype(np.int64).ravel()
        keep = np.flatnonzero(t1 >= t0)
        if not len(keep):
            return 0
        nv = hi[va] - lo[va] + 1
        return int(self._columns(a, lo[ua] + keep // nv, lo[va] + keep % nv, t0[keep], t1[keep]).sum())

    def voxels(self, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
        """(M, 3) voxels with lo <= v <= hi (inclusive voxel indices), for tests and small boxes."""
        lo = np.maximum(lo, 0)
        hi = np.minimum(hi, np.asarray(self.shape) - 1)
        if np.any(hi < lo):
            return np.empty((0, 3), np.int64)
        if self.dense is not None:
            sub = self.dense[lo[0] : hi[0] + 1, lo[1] : hi[1] + 1, lo[2] : hi[2] + 1]
            return np.argwhere(sub) + lo
        k = self.keys[2]
        s = self.shape
        a = np.searchsorted(k, (lo[0] * s[1] + lo[1]) * (s[2] + 1))
        e = np.searchsorted(k, (hi[0] * s[1] + hi[1]) * (s[2] + 1) + s[2] + 1)
        kk = k[a:e]
        z = kk % (s[2] + 1)
        xy = kk // (s[2] + 1)
        q = np.column_stack([xy // s[1], xy % s[1], z])
        return q[np.all((q >= lo) & (q <= hi), axis=1)]


_OTHER = ((1, 2), (0, 2), (0, 1))  # the two other axes of each axis, in order


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


@dataclass
class StageNodes:
    """Nodes handed to a merge stage (local lattice coordinates, as in :class:`MergeResult`).

    ref: external id of each node (stable across stages); vertices / planes / weight / volume as in
    :class:`MergeResult`; pattern: a hashable per leaf whose translates share it (the leaf-pair
    weight cache), None for merged nodes.
    """

    ref: list
    vertices: list
    planes: list
    weight: np.ndarray
    volume: np.ndarray
    pattern: list

    def __len__(self) -> int:
        return len(self.ref)

    @staticmethod
    def concatenate(parts: list["StageNodes"]) -> "StageNodes":
        return StageNodes([r for p in parts for r in p.ref], [v for p in parts for v in p.vertices],
                          [v for p in parts for v in p.planes], np.concatenate([p.weight for p in parts]),
                          np.concatenate([p.volume for p in parts]), [v for p in parts for v in p.pattern])


@dataclass
class StageResult:
    """What one merge stage did and what it hands on.

    merges: [(ref a, ref b)] in order; costs: cost of each, cells; created: the nodes it made, in
    order (their refs are ``ref_base + len(inputs) + t``); live: the nodes left; entries: the
    heap entries ``(cost, i, j, kind, occupied)`` between live nodes (positions in ``live``; kind
    BOUND, EXACT, or STALE: an old key of a pair the lazy refresh had not re-evaluated yet). Costs
    do not depend on the stage (the hull of two nodes of a region lies in its box);
    pair_evaluations, margin_rounds as in MergeResult.
    """

    merges: list
    costs: np.ndarray
    created: StageNodes
    live: StageNodes
    entries: list
    pair_evaluations: int = 0
    margin_rounds: int = 0


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
    N = len(leaf_vertices)
    nodes = StageNodes(list(range(N)), list(leaf_vertices),
                       list(leaf_planes) if leaf_planes is not None else [None] * N,
                       np.asarray(leaf_weight, np.float64), np.asarray(leaf_volume, np.float64),
                       list(leaf_patterns) if leaf_patterns is not None else [None] * N)
    st = MergeStage(nodes, voxels_local, cost, refresh, ref_base=0, cache=leaf_patterns is not None)
    res = st.run(1, widen=True, progress=progress)
    n_new = len(res.merges)
    pos = {r: k for k, r in enumerate(nodes.ref)}
    pos.update({r: N + t for t, r in enumerate(res.created.ref)})
    merges = np.array([[pos[a], pos[b]] for a, b in res.merges], np.int64).reshape(n_new, 2)
    return MergeResult(merges, res.costs, np.concatenate([nodes.weight, res.created.weight]),
                       np.concatenate([nodes.volume, res.created.volume]),
                       nodes.vertices + res.created.vertices, nodes.planes + res.created.planes,
                       margin_rounds=res.margin_rounds, pair_evaluations=res.pair_evaluations)


class MergeStage:
    """One greedy merge run over a set of nodes: vertices, exact planes, W, volume and box per
    node, the live set, the candidate heap with lazy invalidation and the adjacency of live nodes.

    Positions ``0..m-1`` are the input nodes, ``m + t`` the node made by merge t. A stage either
    starts from scratch (every touching pair evaluated) or continues the stages of its parts
    (``entries`` carried from them; only pairs between nodes of different ``groups`` are new).
    """

    def __init__(self, nodes: StageNodes, voxels_local: np.ndarray, cost: str, refresh: str = "lazy",
                 ref_base: int = 0, cache: bool = True, entries: list | None = None,
                 groups: np.ndarray | None = None, memo: dict | None = None):
        if refresh not in ("lazy", "eager"):
            raise ValueError(f"refresh must be 'lazy' or 'eager', not {refresh!r}")
        if cost not in MERGE_COSTS:
            raise ValueError(f"unknown merge cost {cost!r}; choose one of {MERGE_COSTS}")
        m = self.m = len(nodes)
        M = 2 * m - 1 if m else 0
        self.nodes = nodes
        self.ref_base = ref_base
        self.eager = refresh == "eager"
        self.paper = cost == "paper"
        self.verts: list = list(nodes.vertices) + [None] * max(m - 1, 0)
        self.planes: list = list(nodes.planes) + [None] * max(m - 1, 0)
        self.weight = np.zeros(M)
        self.volume = np.zeros(M)
        self.weight[:m], self.volume[:m] = nodes.weight, nodes.volume
        self.lo = np.zeros((M, 3), np.int64)
        self.hi = np.zeros((M, 3), np.int64)
        for i, v in enumerate(nodes.vertices):
            self.lo[i], self.hi[i] = v.min(axis=0), v.max(axis=0)
        self.alive = np.zeros(M, bool)
        self.alive[:m] = True
        self.live = _Live(M)
        for i in range(m):
            self.live.add(i, self.lo[i], self.hi[i])
        vox = np.asarray(voxels_local, np.int64).reshape(-1, 3)
        # the voxel query works in its own coordinates (>= 0): offset by the region's lower corner
        self.off = vox.min(axis=0) if len(vox) else np.zeros(3, np.int64)
        self.query = VoxelBoxQuery(vox - self.off)
        self.evals = 0
        # W of a pair of leaves depends only on (pattern, pattern, offset, occupancy of the union's
        # box): floors and walls repeat the same few, so their hulls are computed once.
        self.leaf_cache: dict = {}
        self.patterns = nodes.pattern
        self.use_cache = cache and self.query.dense is not None
        # pair evaluations by the two nodes' vertices: shared by the stages of one task over the same voxels
        # (the costs of a tile start from the same leaves and mostly evaluate the same pairs)
        self.memo = memo
        self.heap: list = []
        self.parent = list(range(M))
        self.adj: list = [set() for _ in range(m)] + [None] * max(m - 1, 0)
        self.fresh: set = set()  # pairs (a < b) that have an entry computed while both were alive
        self.margin = 0
        self.rounds = 0
        self.t = 0
        self.merges: list = []
        self.costs: list = []
        if entries is None:
            for i, j in _initial_pairs(self.lo[:m], self.hi[:m]):
                self.add_pair(int(i), int(j), batch=True)
        else:
            for e in entries:
                a, b = e[1], e[2]
                self.heap.append(tuple(e))
                self.fresh.add((a, b))
                self.adj[a].add(b)
                self.adj[b].add(a)
            if groups is not None:
                for i, j in _initial_pairs(self.lo[:m], self.hi[:m]):
                    if groups[i] != groups[j]:
                        self.add_pair(int(i), int(j), batch=True)
        heapq.heapify(self.heap)

    def _cost(self, w, i, j):
        return w if self.paper else w - self.weight[i] - self.weight[j]

    def evaluate(self, i: int, j: int, exact: bool = True, options: bytes = EVAL_QHULL):
        """(cost, exact, occupied) of merging nodes i and j; with ``exact=False`` a large box gets a
        lower bound of the cost instead (occupied is None then). ``occupied`` is the number of occupied
        voxels entirely inside the union's hull. Ranking needs only qhull's volume and facets;
        :meth:`merge` computes the exact hull of the pair it merges."""
        lo, hi, query = self.lo, self.hi, self.query
        key = None
        blo, bhi = np.minimum(lo[i], lo[j]), np.maximum(hi[i], hi[j])
        if self.use_cache and i < self.m and j < self.m and options == EVAL_QHULL \
                and self.patterns[i] is not None and self.patterns[j] is not None:
            a, b = blo - self.off, bhi - self.off
            box = query.dense[a[0] : b[0], a[1] : b[1], a[2] : b[2]]
            key = (self.patterns[i], self.patterns[j], (lo[j] - lo[i]).tobytes(), box.shape, box.tobytes())
            hit = self.leaf_cache.get(key)
            if hit is not None:
                return self._cost(hit[0], i, j), True, hit[1]
        mkey = None
        if self.memo is not None:
            mkey = (self.verts[i].tobytes(), self.verts[j].tobytes(), exact, options)
            hit = self.memo.get(mkey)
            if hit is not None:  # the same hull and count as computing them again (qhull is deterministic)
                w, ex, occ = hit
                if key is not None and ex:  # as if computed here: later translates of the pair reuse this W
                    self.leaf_cache[key] = (w, occ)
                return self._cost(w, i, j), ex, occ
        self.evals += 1
        # qhull's volume and facets only (the hull's vertices are not needed to rank a pair)
        volume, eq = lattice_hull_facets(np.concatenate([self.verts[i], self.verts[j]]), options)
        ext = bhi - blo
        big = int(ext[0]) * int(ext[1]) * int(ext[2]) > BOUND_CELLS
        if not exact and big:
            w = max(volume - query.count(blo - self.off, bhi - 1 - self.off), 0.0)
            if mkey is not None:
                self.memo[mkey] = (w, False, None)
            return self._cost(w, i, j), False, None
        if big:
            eq = np.unique(np.round(eq, 12), axis=0)  # qhull repeats coplanar facets
        # the query's coordinates are offset: A (q + off) + b = A q + (b + A off)
        occ = query.count_inside(eq[:, :3], eq[:, 3] + eq[:, :3] @ self.off, blo - self.off, bhi - 1 - self.off)
        w = max(volume - occ, 0.0)
        if key is not None:
            self.leaf_cache[key] = (w, occ)
        if mkey is not None:
            self.memo[mkey] = (w, True, occ)
        return self._cost(w, i, j), True, occ

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
        c, ex, occ = self.evaluate(a, b, exact)
        entry = (c, a, b, EXACT if ex else BOUND, occ)
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

    def pop_best(self, widen: bool):
        """The cheapest pair of two live nodes (re-evaluating stale or bound-only entries), as
        (cost, i, j, occupied); None when no touching pair is left and ``widen`` is False."""
        heap, alive = self.heap, self.alive
        while True:
            if not heap:
                if not widen:
                    return None
                self.widen()
                continue
            c, i, j, ex, occ = heapq.heappop(heap)
            if alive[i] and alive[j]:
                if ex == EXACT:
                    return c, i, j, occ
                if ex == STALE:  # handed on by a part's stage: evaluate it for these live nodes now
                    c2, ex2, occ2 = self.evaluate(i, j, False)
                    heapq.heappush(heap, (c2, i, j, EXACT if ex2 else BOUND, occ2))
                    continue
                c2, _, occ2 = self.evaluate(i, j, True)
                heapq.heappush(heap, (c2, i, j, EXACT, occ2))  # bound -> exact
                continue
            if self.eager:
                continue  # the merged node's pairs were all evaluated when it was made
            a, b = self.find(i), self.find(j)
            if a != b and (min(a, b), max(a, b)) not in self.fresh:
                self.add_pair(a, b)  # stale key: re-evaluate for the live nodes, push back

    def merge(self, i: int, j: int, occ: int | None) -> int:
        """Merge live nodes i and j into a new node with exact facets and vertices; its position."""
        k = self.m + self.t
        mkey = ("merge", self.verts[i].tobytes(), self.verts[j].tobytes()) if self.memo is not None else None
        made = self.memo.get(mkey) if mkey is not None else None
        if made is None or occ is None:
            h = lattice_hull(np.concatenate([self.verts[i], self.verts[j]]), b"Qt")
            made = (h.volume, h.vertices, integer_planes(h))
            if mkey is not None:
                self.memo[mkey] = made  # another cost's stage that merges the same two nodes makes the same node
        if occ is None:  # pragma: no cover - popped entries are exact
            blo, bhi = np.minimum(self.lo[i], self.lo[j]), np.maximum(self.hi[i], self.hi[j])
            eq = h.equations
            occ = self.query.count_inside(eq[:, :3], eq[:, 3] + eq[:, :3] @ self.off, blo - self.off,
                                          bhi - 1 - self.off)
        volume, vertices, planes = made
        # the popped entry's count is that of the same hull (ranked with joggled qhull): reuse it
        self.weight[k] = max(volume - occ, 0.0)
        self.verts[k], self.volume[k] = vertices, volume
        self.planes[k] = planes
        self.lo[k], self.hi[k] = vertices.min(axis=0), vertices.max(axis=0)
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
        self.t += 1
        return k

    def ref(self, k: int):
        return self.nodes.ref[k] if k < self.m else self.ref_base + k

    def run(self, target: int = 1, widen: bool = True, progress: Callable[[int], None] | None = None) -> StageResult:
        """Merge until ``target`` nodes are left (or, without ``widen``, no touching pair is)."""
        total = max(self.m - max(target, 1), 0)
        while self.live.n > max(target, 1):
            best = self.pop_best(widen)
            if best is None:
                break
            c, i, j, occ = best
            self.merges.append((self.ref(i), self.ref(j)))
            self.costs.append(c)
            self.merge(i, j, occ)
            if progress is not None and (self.t % 256 == 1 or self.t == total):
                progress(self.t)
        return self._result()

    def _result(self) -> StageResult:
        m, T = self.m, self.t
        made = range(m, m + T)
        created = StageNodes([self.ref_base + k for k in made], [self.verts[k] for k in made],
                             [self.planes[k] for k in made], self.weight[m : m + T].copy(),
                             self.volume[m : m + T].copy(), [None] * T)
        ids = np.sort(self.live.ids[: self.live.n])
        pos = {int(k): p for p, k in enumerate(ids)}
        live = StageNodes([self.ref(int(k)) for k in ids], [self.verts[k] for k in ids], [self.planes[k] for k in ids],
                          self.weight[ids].copy(), self.volume[ids].copy(),
                          [self.patterns[k] if k < m else None for k in ids])
        # hand on one entry per live pair: fresh ones as they are, stale ones (lazy refresh) as
        # STALE with their old key, evaluated when they reach the top, as they would be here
        entries, seen = [], set()
        for c, i, j, ex, occ in sorted(self.heap):
            if self.alive[i] and self.alive[j]:
                if (i, j) not in seen:
                    seen.add((i, j))
                    entries.append((c, pos[i], pos[j], ex, occ))
            elif not self.eager:
                a, b = self.find(i), self.find(j)
                a, b = min(a, b), max(a, b)
                if a != b and (a, b) not in self.fresh and (a, b) not in seen:
                    seen.add((a, b))
                    entries.append((c, pos[a], pos[b], STALE, None))
        return StageResult(self.merges, np.asarray(self.costs, np.float64), created, live, entries,
                           self.evals, self.rounds)
