"""Half-plane reduction, always outward: drop the planes whose removal adds the least volume.

Removing a half-plane from {p : n_l . p <= d_l} can only enlarge the polytope, so every
occupied voxel it contained stays inside. A plane is only dropped if the remaining ones
still bound a finite polytope (:func:`polycc.geometry.halfplanes.is_bounded` with a margin
:data:`MIN_GAMMA`). Volumes come from qhull (scipy.spatial): the vertices of the reduced
polytope by half-space intersection, then their convex hull.
"""

from __future__ import annotations

import heapq

import numpy as np

from polycc.geometry.halfplanes import MIN_PLANES, polytope_vertices, polytope_volume

# A polytope counts as bounded only if the origin lies at least this far inside the convex
# hull of its unit normals (gamma = min_{|u|=1} max_l n_l . u >= this), which also rules out
# needle-like polytopes that reach far from the voxels they cover.
MIN_GAMMA = 1e-4


def drop_cost(planes: np.ndarray, j: int, interior: np.ndarray, volume: float) -> float:
    """Volume added by dropping plane j (inf if the rest is unbounded)."""
    v = polytope_vertices(np.delete(planes, j, axis=0), interior, MIN_GAMMA)
    return np.inf if v is None else max(polytope_volume(v) - volume, 0.0)


def reduce_planes(
    polytopes: list[tuple[np.ndarray, np.ndarray]], max_planes: int, per_polytope: int | None = None,
    cost_cache: dict | None = None,
) -> tuple[list[np.ndarray], float] | None:
    """Drop planes, cheapest added volume first, until the total is <= ``max_planes`` and no
    polytope has more than ``per_polytope`` planes (the layout's per-polytope limit).

    ``polytopes``: (halfplanes (H,4), vertices (V,3)) pairs. Returns (reduced half-plane
    arrays, total added volume m^3), or None if the planes cannot be cut down that far
    while every polytope stays bounded.

    Lazy greedy: a cost computed before its polytope last changed is recomputed when it
    reaches the top of the heap and pushed back, so only a few costs are recomputed per
    drop (removing planes makes the others' caps grow, so stale costs are mostly lower
    bounds). Safety does not depend on the costs: every drop is outward and is only
    committed after an exact boundedness check.

    A plane whose removal alone leaves its polytope unbounded stays in every bounded reduction
    (fewer normals cannot span more), so if these essential planes alone exceed ``max_planes``
    the call fails before dropping anything. ``cost_cache`` (a dict the caller keeps across
    calls, e.g. over the candidates of one selection) memoises the drop costs of a polytope's
    original planes, keyed by their bytes.
    """
    cap = per_polytope if per_polytope is not None else 1 << 30
    total = sum(len(h) for h, _ in polytopes)
    if total <= max_planes and all(len(h) <= cap for h, _ in polytopes):
        return [np.asarray(h) for h, _ in polytopes], 0.0
    if max_planes < MIN_PLANES * len(polytopes) or cap < MIN_PLANES:
        return None
    planes = [np.asarray(h, np.float64) for h, _ in polytopes]
    ids = [np.arange(len(h)) for h in planes]  # original row of each current plane
    interior = [np.asarray(v, np.float64).mean(axis=0) for _, v in polytopes]
    volume = [polytope_volume(np.asarray(v, np.float64)) for _, v in polytopes]
    version = [0] * len(planes)
    added = 0.0

    def costs(k) -> list[float]:
        if cost_cache is None or version[k]:
            return [drop_cost(planes[k], j, interior[k], volume[k]) for j in range(len(planes[k]))]
        key = planes[k].tobytes()
        if key not in cost_cache:
            cost_cache[key] = [drop_cost(planes[k], j, interior[k], volume[k]) for j in range(len(planes[k]))]
        return cost_cache[key]

    def entries(ks):
        heap = []
        for k in ks:
            if len(planes[k]) <= MIN_PLANES:
                continue
            for j, c in enumerate(costs(k)):
                if np.isfinite(c):
                    heap.append((c, k, int(ids[k][j]), version[k]))
        heapq.heapify(heap)
        return heap

    # lower bound: essential planes (infinite drop cost) are never dropped
    need = 0
    for k in range(len(planes)):
        if len(planes[k]) <= MIN_PLANES:
            need += len(planes[k])
        else:
            need += max(MIN_PLANES, sum(1 for c in costs(k) if not np.isfinite(c)))
    if need > max_planes:
        return None
    n_total = [sum(len(h) for h in planes)]

    def drop_until(heap, done) -> bool:
        nonlocal added
        while not done():
            if not heap:
                return False
            c, k, orig, ver = heapq.heappop(heap)
            rows = np.flatnonzero(ids[k] == orig)
            if not rows.size or len(planes[k]) <= MIN_PLANES:
                continue
            j = int(rows[0])
            if ver != version[k]:
                c = drop_cost(planes[k], j, interior[k], volume[k])
                if np.isfinite(c):
                    heapq.heappush(heap, (c, k, orig, version[k]))
                continue
            planes[k] = np.delete(planes[k], j, axis=0)
            ids[k] = np.delete(ids[k], j)
            n_total[0] -= 1
            volume[k] += c
            version[k] += 1
            added += c
        return True

    for k in [k for k in range(len(planes)) if len(planes[k]) > cap]:
        if not drop_until(entries([k]), lambda k=k: len(planes[k]) <= cap):
            return None
    if not drop_until(entries(range(len(planes))), lambda: n_total[0] <= max_planes):
        return None
    return planes, added
