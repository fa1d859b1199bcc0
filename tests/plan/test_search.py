"""Grid A* in C (polycc/plan/polycc_plan.c) against scipy's Dijkstra on the same 26-connected graph."""

from __future__ import annotations

import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import dijkstra

from polycc.plan.native import astar
from polycc.plan.planner import _octile

OFFS = [(a, b, c) for a in (-1, 0, 1) for b in (-1, 0, 1) for c in (-1, 0, 1) if (a, b, c) != (0, 0, 0)]


def reference_cost(free, spacing, src, sc, dst, dc):
    """Dijkstra from a virtual source (edges to src at sc) to a virtual goal (edges from dst at dc)."""
    shape = free.shape
    n = free.size
    idx = np.arange(n).reshape(shape)
    rows, cols, w = [], [], []
    for o in OFFS:
        s1 = tuple(slice(max(0, -d), s - max(0, d)) for d, s in zip(o, shape))
        s2 = tuple(slice(max(0, d), s - max(0, -d)) for d, s in zip(o, shape))
        m = free[s1] & free[s2]
        rows.append(idx[s1][m])
        cols.append(idx[s2][m])
        w.append(np.full(int(m.sum()), spacing * math.sqrt(sum(x * x for x in o))))
    S, G = n, n + 1
    rows += [np.full(len(src), S), dst]
    cols += [src, np.full(len(dst), G)]
    w += [sc, dc]
    g = coo_matrix((np.concatenate(w) + 1e-300, (np.concatenate(rows), np.concatenate(cols))), shape=(n + 2, n + 2))
    return dijkstra(g.tocsr(), indices=S)[G]


@settings(max_examples=60)
@given(seed=st.integers(0, 100_000), fill=st.floats(0.0, 0.6), nsrc=st.integers(1, 4), ndst=st.integers(1, 4))
def test_astar_is_optimal_and_valid(seed, fill, nsrc, ndst):
    rng = np.random.default_rng(seed)
    shape = tuple(int(v) for v in rng.integers(2, 9, 3))
    free = rng.uniform(size=shape) >= fill
    cells = np.flatnonzero(free.ravel())
    if len(cells) == 0:
        return
    spacing = float(rng.uniform(0.01, 1.0))
    src = rng.choice(cells, size=min(nsrc, len(cells)), replace=False)
    dst = rng.choice(cells, size=min(ndst, len(cells)), replace=False)
    sc, dc = rng.uniform(0, spacing, len(src)), rng.uniform(0, spacing, len(dst))
    goal_cell = np.array(np.unravel_index(int(dst[0]), shape))
    tij = np.stack(np.unravel_index(dst, shape), axis=1)
    shift = float(np.max(_octile(tij - goal_cell) * spacing - dc))
    cost, path, expanded = astar(free, spacing, src, sc, dst, dc, goal_cell, shift)
    ref = reference_cost(free, spacing, src, sc, dst, dc)
    if not np.isfinite(ref):
        assert not np.isfinite(cost) and len(path) == 0
        return
    assert math.isclose(cost, ref, rel_tol=1e-9, abs_tol=1e-12)
    # the path: from a source to a target, through free 26-neighbours, of exactly that cost
    assert path[0] in src and path[-1] in dst and np.all(free.ravel()[path])
    ijk = np.stack(np.unravel_index(path, shape), axis=1)
    steps = np.diff(ijk, axis=0)
    assert np.all(np.abs(steps) <= 1) and np.all(np.any(steps != 0, axis=1))
    length = spacing * np.sum(np.linalg.norm(steps, axis=1))
    total = sc[list(src).index(path[0])] + length + dc[list(dst).index(path[-1])]
    assert math.isclose(total, cost, rel_tol=1e-9, abs_tol=1e-12)
    assert 1 <= expanded <= free.size


def test_octile_is_the_free_grid_distance():
    free = np.ones((7, 6, 5), bool)
    for target in [(6, 5, 4), (3, 0, 4), (0, 5, 1), (6, 2, 2)]:
        t = np.ravel_multi_index(target, free.shape)
        cost, _, _ = astar(free, 1.0, np.array([0]), np.zeros(1), np.array([t]), np.zeros(1), np.array(target), 0.0)
        assert math.isclose(cost, float(_octile(np.array(target))), rel_tol=1e-12)
