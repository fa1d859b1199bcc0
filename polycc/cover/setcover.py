"""Weighted greedy set cover (Chvatal 1979), PolyMerge Sec. V-B / Remark 1.

Repeatedly take the cluster minimising ``W(C) / |C \\ covered|``. A lazy priority queue
keeps each cluster's last key; keys only grow as voxels get covered, so a popped entry
whose recomputed key is unchanged is the true minimum. Ties (many clusters have W = 0:
flat walls, full blocks, single voxels) go to the cluster covering more new voxels, then
to the lower voxel id, which makes the result deterministic.
"""

from __future__ import annotations

import heapq

import numpy as np

from polycc.cover.clusters import Clusters


def greedy_set_cover(cl: Clusters) -> np.ndarray:
    """Rows of ``cl`` (cluster C_v for row v < V, else an exact box) forming the sub-cover
    C-bar, in pick order."""
    nb = cl.neighbours
    V = cl.n_voxels
    w = cl.weight()
    covered = np.zeros(V + 1, dtype=bool)  # index -1 -> the sentinel slot V (always False)
    covered[V] = True  # -1 entries count as already covered
    nbi = np.where(nb >= 0, nb, V)
    new = cl.sizes.astype(np.int64)
    heap = [(w[v] / new[v], -int(new[v]), v) for v in range(nb.shape[0])]
    heapq.heapify(heap)
    chosen: list[int] = []
    left = V
    while left > 0:
        ratio, neg, v = heapq.heappop(heap)
        row = nbi[v]
        fresh = int(np.count_nonzero(~covered[row]))
        if fresh == 0:
            continue
        key = (w[v] / fresh, -fresh, v)
        if key != (ratio, neg, v) and heap and key > heap[0]:
            heapq.heappush(heap, key)
            continue
        covered[row] = True
        left -= fresh
        chosen.append(v)
    return np.asarray(chosen, dtype=np.int64)
