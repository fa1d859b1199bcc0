"""Half-plane reduction, always outward: drop the planes whose removal adds the least volume.

Removing a half-plane from {p : n_l . p <= d_l} can only enlarge the polytope, so every
occupied voxel it contained stays inside. A plane is only dropped if the remaining ones
still bound a finite polytope (:func:`polycc.geometry.halfplanes.is_bounded` with a margin
:data:`MIN_GAMMA`). Volumes (m^3) of polytopes up to 128 planes come from one enumeration of plane triples
for every plane at once (:func:`polycc.native.cap_volumes`, C; the numpy reference is
:func:`polycc.geometry.halfplanes.drop_volumes`), larger ones from a qhull half-space intersection per
plane (:func:`polycc.geometry.halfplanes.drop_volume`).
"""

from __future__ import annotations

import heapq

import numpy as np

from polycc.geometry.halfplanes import MIN_PLANES, drop_volume, polytope_volume
from polycc.native import cap_volumes

# Up to this many planes a stale cost is read from every plane's cost of the polytope's current version (one C
# call, :func:`all_drop_costs`, ~0.3 ms at 30 planes, growing as m^3); above it one qhull per stale plane (~0.6-1 ms)
# is cheaper, as the greedy recomputes only 1-2 costs per drop.
MAX_PLANES = 64

# A polytope counts as bounded only if the origin lies at least this far inside the convex
# hull of its unit normals (gamma = min_{|u|=1} max_l n_l . u >= this), which also rules out
# needle-like polytopes that reach far from the voxels they cover.
MIN_GAMMA = 1e-4


def drop_cost(planes: np.ndarray, j: int, interior: np.ndarray, volume: float) -> float:
    """Volume added by dropping plane j (inf if the rest is unbounded): one qhull
    (:func:`polycc.geometry.halfplanes.drop_volume`)."""
    return drop_volume(planes, j, interior, volume, MIN_GAMMA)


def recompute_cost(planes: np.ndarray, j: int, interior: np.ndarray, volume: float, now=None) -> float:
    """The lazy greedy's cost of plane j after its polytope changed: read from every plane's cost at once
    (:func:`all_drop_costs`, ``now`` if given) up to :data:`MAX_PLANES` planes, one qhull (:func:`drop_cost`)
    above."""
    if len(planes) > MAX_PLANES:
        return drop_cost(planes, j, interior, volume)
    return (all_drop_costs(planes, interior, volume) if now is None else now)[j]


def _without(a: np.ndarray, j: int) -> np.ndarray:
    """``np.delete(a, j, axis=0)`` for one row, without its argument handling (10 us a call, 1.6 s of a
    6M-splat build's budget)."""
    return np.concatenate((a[:j], a[j + 1:]))


class _Stream:
    """The lazy greedy's operations on one polytope, recorded so that they are computed once.

    The global greedy pops the cheapest entry of one heap over every polytope; the entries of one
    polytope are only ever pushed when one of its own entries is popped, so the sequence of its pops
    (a drop, a stale cost recomputed, or nothing) depends on that polytope alone. Only how far along
    its sequence each polytope gets depends on the others (and on the caps). A stream records that
    sequence and extends it on demand; with a cache the candidates of one selection, and the tighter
    retries of one candidate, replay it instead of recomputing qhull volumes.

    ``cap``: the per-polytope limit when this polytope is above it (its drops down to the limit come
    first, from their own heap, as the greedy's first phase); None otherwise."""

    def __init__(self, planes: np.ndarray, interior: np.ndarray, volume: float, cap: int | None, costs0):
        self.planes = planes
        self.ids = np.arange(len(planes))
        self.interior = interior
        self.volume = volume
        self.version = 0
        self._now = None  # (version, every plane's drop cost at that version)
        c0 = costs0(planes, interior, volume)
        essential = sum(not np.isfinite(c) for c in c0)
        self.need = len(planes) if len(planes) <= MIN_PLANES else max(MIN_PLANES, essential)
        self.dropped: list[int] = []  # original rows, in drop order
        self.ops: list[tuple] = []  # popped keys (c, orig, ver) of the global phase and whether each dropped
        self.ok = True
        self.pre_costs: list[float] = []  # the volumes its first-phase drops added, in order
        heap = self._entries(c0)
        if cap is not None and len(planes) > cap:
            while len(self.planes) > cap:
                if not heap:
                    self.ok = False
                    break
                _, c = self._pop(heap)
                if c is not None:
                    self.pre_costs.append(c)
            heap = self._entries(None)
        self.heap = heap

    def _entries(self, c0):
        if len(self.planes) <= MIN_PLANES:
            return []
        cs = c0 if c0 is not None and self.version == 0 else self._costs_now()
        heap = [(c, int(self.ids[j]), self.version) for j, c in enumerate(cs) if np.isfinite(c)]
        heapq.heapify(heap)
        return heap

    def _costs_now(self) -> list[float]:
        if self._now is None or self._now[0] != self.version:
            self._now = (self.version, all_drop_costs(self.planes, self.interior, self.volume))
        return self._now[1]

    def _pop(self, heap) -> tuple:
        """One pop of the greedy on this polytope: (key, added volume m^3 or None)."""
        key = heapq.heappop(heap)
        c, orig, ver = key
        rows = np.flatnonzero(self.ids == orig)
        if not rows.size or len(self.planes) <= MIN_PLANES:
            return key, None
        j = int(rows[0])
        if ver != self.version:
            now = self._costs_now() if len(self.planes) <= MAX_PLANES else None
            c = recompute_cost(self.planes, j, self.interior, self.volume, now)
            if np.isfinite(c):
                heapq.heappush(heap, (c, orig, self.version))
            return key, None
        self.planes = _without(self.planes, j)
        self.ids = _without(self.ids, j)
        self.volume += c
        self.version += 1
        self.dropped.append(orig)
        return key, c

    def op(self, i: int):
        """The i-th pop of the global phase, (key, added volume or None), or None past the end."""
        while len(self.ops) <= i:
            if not self.heap:
                return None
            self.ops.append(self._pop(self.heap))
        return self.ops[i]

    def upto(self, lam: float) -> tuple[int, float, bool]:
        """(drops among the recorded pops before the first whose key exceeds ``lam``, that key, whether that pop
        costs nothing more to read), from the record only: past it the next pop's key is the top of the heap
        (inf at the end), and reading that pop is free only at the end or as the first pop (the heap is fresh
        then: a drop, no cost recomputed): the flag says whether every pop the greedy may read is recorded.

        The global greedy pops the heads of the streams cheapest first, so it takes a stream's i-th pop only
        once every key up to it is due: when its last drop's key is at most ``lam``, it reads no pop of this
        stream past the first one above ``lam`` (:meth:`extend` records up to that one)."""
        drops = 0
        for key, c in self.ops:
            if key[0] > lam:
                return drops, key[0], True
            drops += c is not None
        if not self.heap:
            return drops, np.inf, True
        return drops, self.heap[0][0], not self.ops and self.heap[0][0] > lam

    def extend(self, lam: float) -> None:
        """Record the pops up to and including the first whose key exceeds ``lam`` (or to the end)."""
        i = 0
        while True:
            o = self.op(i)
            if o is None or o[0][0] > lam:
                return
            i += 1

    def pending(self, lam: float) -> list[float]:
        """Keys of the entries still in the heap past the record above ``lam`` (stale costs are mostly
        lower bounds of the costs they will be recomputed to): a guess of this stream's later pops."""
        return [k[0] for k in self.heap if lam < k[0] < np.inf][: max(len(self.planes) - self.need, 0)]


def polytope_stream(store: dict, h: np.ndarray, v: np.ndarray, per_polytope: int | None) -> _Stream:
    """The recorded greedy of the polytope with planes ``h`` and vertices ``v`` (float64) under the
    per-polytope limit, from ``store`` or made and kept there (``store`` is a reduction's ``cost_cache``)."""
    key = stream_key(h, v, per_polytope)
    if key not in store:
        store[key] = _Stream(h, v.mean(axis=0), polytope_volume(v), key[3], _costs0(store))
    return store[key]


def stream_key(h: np.ndarray, v: np.ndarray, per_polytope: int | None) -> tuple:
    """The key of a polytope's :class:`_Stream` in a ``cost_cache``."""
    limit = per_polytope if per_polytope is not None and len(h) > per_polytope else None
    return ("stream", np.asarray(h, np.float64).tobytes(), np.asarray(v, np.float64).tobytes(), limit)


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
    committed after an exact boundedness check. First every polytope above ``per_polytope``
    is cut down to it on its own, then one heap over all polytopes runs.

    A plane whose removal alone leaves its polytope unbounded stays in every bounded reduction
    (fewer normals cannot span more), so if these essential planes alone exceed ``max_planes``
    the call fails before dropping anything. ``cost_cache`` (a dict the caller keeps across
    calls, e.g. over the candidates of one selection) keeps each polytope's recorded greedy
    (:class:`_Stream`), keyed by its planes, vertices and limit: the result is the same as
    without it, bit for bit.
    """
    cap = per_polytope if per_polytope is not None else 1 << 30
    total = sum(len(h) for h, _ in polytopes)
    if total <= max_planes and all(len(h) <= cap for h, _ in polytopes):
        return [np.asarray(h) for h, _ in polytopes], 0.0
    if max_planes < MIN_PLANES * len(polytopes) or cap < MIN_PLANES:
        return None
    store = {} if cost_cache is None else cost_cache
    streams = [polytope_stream(store, np.asarray(h, np.float64), np.asarray(v, np.float64), cap)
               for h, v in polytopes]
    # lower bound: essential planes (infinite drop cost) are never dropped
    if sum(s.need for s in streams) > max_planes:
        return None
    if not all(s.ok for s in streams):
        return None
    n_drop = [len(s.pre_costs) for s in streams]
    n_total = sum(len(h) for h, _ in polytopes) - sum(n_drop)
    added = 0.0
    for s in streams:  # the first phase's drops, polytope by polytope (the order they were added in)
        for c in s.pre_costs:
            added += c
    pos = [0] * len(streams)
    heap = []
    for k, s in enumerate(streams):
        first = s.op(0)
        if first is not None:
            heap.append((first[0][0], k, first[0][1], first[0][2]))
    heapq.heapify(heap)
    while n_total > max_planes:
        if not heap:
            return None
        _, k, _, _ = heapq.heappop(heap)
        s = streams[k]
        _, c = s.op(pos[k])
        pos[k] += 1
        if c is not None:
            n_drop[k] += 1
            n_total -= 1
            added += c
        nxt = s.op(pos[k])
        if nxt is not None:
            heapq.heappush(heap, (nxt[0][0], k, nxt[0][1], nxt[0][2]))
    out = []
    for (h, _), s, m in zip(polytopes, streams, n_drop):
        h = np.asarray(h, np.float64)
        out.append(np.delete(h, sorted(s.dropped[:m]), axis=0) if m else h)
    return out, added


def costs_key(planes: np.ndarray) -> tuple:
    """The key of a polytope's drop costs in a ``cost_cache`` (its float64 planes, as the reduction sees them)."""
    return ("costs", np.asarray(planes, np.float64).tobytes())


def all_drop_costs(planes: np.ndarray, interior: np.ndarray, volume: float) -> list[float]:
    """Drop cost of every plane of a polytope (``interior`` its vertices' mean, ``volume`` their hull's), as
    the reduction computes them; what a caller may precompute into a ``cost_cache`` under :func:`costs_key`.
    All planes at once (:func:`polycc.native.cap_volumes`: one enumeration of plane triples in C up to
    128 planes); the same volumes as :func:`drop_cost` to ~1e-9 of the polytope's (that one subtracts the hull
    of the unrounded vertices, so it also counts the outward margin's skin) and the same planes infinite."""
    return [float(c) for c in cap_volumes(planes, MIN_GAMMA, interior, volume)]


def _costs0(store: dict):
    """Drop costs of a polytope's original planes, memoised in ``store`` by the planes' bytes."""
    def costs0(planes, interior, volume):
        key = costs_key(planes)
        if key not in store:
            store[key] = all_drop_costs(planes, interior, volume)
        return store[key]
    return costs0
