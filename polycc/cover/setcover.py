"""Weighted greedy set cover (Chvatal 1979), PolyMerge Sec. V-B / Remark 1.

Repeatedly take the cluster minimising ``W(C) / |C \\ covered|``. Ties (many clusters have W = 0:
flat walls, full blocks, single voxels) go to the cluster covering more new voxels, then to the
lower row id, which makes the result deterministic: the order is the key ``(W / fresh, -fresh, row)``.

Two phases give exactly that order, fast:

1. Zero-weight sets (``W == 0``; with ``boxes`` every voxel has one, so this phase covers all of
   V+). Their key is ``(0, -fresh, row)``: level by level from the largest fresh count f down, the
   sets still covering f new voxels are taken in row order unless an earlier pick of the level
   took one of their voxels. That is the lexicographically first maximal independent set of the
   level's conflict graph (two sets conflict when they share an uncovered voxel), computed in
   vectorised rounds: every set with no lower-row conflicting candidate is taken, the others are
   recounted, repeat.
2. The rest: a lazy priority queue keeps each set's last key; keys only grow as voxels get
   covered, so a popped entry whose recomputed key is unchanged (or still below the queue's
   minimum) is the true minimum.
"""

from __future__ import annotations

import heapq

import numpy as np

from polycc.cover.clusters import Clusters


def greedy_set_cover(cl: Clusters, covered: np.ndarray | None = None) -> np.ndarray:
    """Rows of ``cl`` (cluster C_v for row v < V, else an exact box) forming the sub-cover
    C-bar, in pick order. ``covered`` ((V,) bool) marks voxels another leaf already holds."""
    nb = cl.neighbours
    V = cl.n_voxels
    w = cl.weight()
    pre = covered
    covered = np.zeros(V + 1, dtype=bool)  # index -1 -> the sentinel slot V (always covered)
    if pre is not None:
        covered[:V] = pre
    covered[V] = True
    nbi = np.where(nb >= 0, nb, V)
    fresh = cl.sizes.astype(np.int64)  # an upper bound of each set's new voxels, exact when recounted
    chosen: list[np.ndarray] = [_zero_weight_phase(nbi, np.flatnonzero(w == 0.0), fresh, covered)]
    left = V - int(np.count_nonzero(covered[:V]))
    heap = [(w[v] / fresh[v], -int(fresh[v]), int(v)) for v in np.flatnonzero((w != 0.0) & (fresh > 0))]
    heapq.heapify(heap)
    rest: list[int] = []
    while left > 0:
        ratio, neg, v = heapq.heappop(heap)
        row = nbi[v]
        f = int(np.count_nonzero(~covered[row]))
        if f == 0:
            continue
        key = (w[v] / f, -f, v)
        if key != (ratio, neg, v) and heap and key > heap[0]:
            heapq.heappush(heap, key)
            continue
        covered[row] = True
        left -= f
        rest.append(v)
    chosen.append(np.asarray(rest, np.int64))
    return np.concatenate(chosen).astype(np.int64)


def _zero_weight_phase(nbi: np.ndarray, rows: np.ndarray, fresh: np.ndarray, covered: np.ndarray) -> np.ndarray:
    """Phase 1 (module docstring): the zero-weight picks in greedy order; updates ``covered`` and ``fresh``.

    Bucket queue instead of a heap: level f holds the rows whose fresh count is at most f (an
    upper bound until recounted); its rows are recounted in row order, a row still at f is taken,
    the others move down to their recounted level (which is processed later, in row order again).
    """
    if len(rows) == 0:
        return np.empty(0, np.int64)
    V = len(covered) - 1
    cov = bytearray(covered[:V].tobytes())
    ub = fresh[rows]
    members = [[x for x in r if x < V] for r in nbi[rows].tolist()]
    buckets: list[list[int]] = [[] for _ in range(int(ub.max()) + 1)]
    for f in np.unique(ub):
        buckets[int(f)] = np.flatnonzero(ub == f).tolist()
    out: list[int] = []
    ubl = ub.tolist()
    getc = cov.__getitem__
    for f in range(len(buckets) - 1, 0, -1):
        level = buckets[f]
        level.sort()
        for s in level:
            row = members[s]
            a = len(row) - sum(map(getc, row))
            if a == f:
                out.append(s)
                for x in row:
                    cov[x] = 1
                ubl[s] = 0
            else:
                ubl[s] = a
                if a:
                    buckets[a].append(s)
        buckets[f] = []
    covered[:V] = np.frombuffer(bytes(cov), np.uint8).astype(bool)
    fresh[rows] = ubl
    return rows[np.asarray(out, np.int64)] if out else np.empty(0, np.int64)
