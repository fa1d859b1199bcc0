"""polycc.geometry.qhull_raw: scipy's qhull wrapper class called directly gives the public classes'
results bit for bit (half-space intersections: vertices, dual facets and equations; hulls: volume,
simplices and equations), on random and degenerate input."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial import ConvexHull, HalfspaceIntersection

from polycc.geometry.halfplanes import hull_halfplanes
from polycc.geometry.qhull_raw import halfspaces_raw, hull_raw


def _same_halfspaces(hs_in, c):
    want = HalfspaceIntersection(hs_in, c)
    got = halfspaces_raw(hs_in, c)
    assert got.intersections.view(np.uint64).tolist() == want.intersections.view(np.uint64).tolist()
    assert got.dual_equations.view(np.uint64).tolist() == want.dual_equations.view(np.uint64).tolist()
    assert [list(f) for f in got.dual_facets] == [list(f) for f in want.dual_facets]


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(4, 80), lattice=st.booleans())
def test_halfspaces_raw_is_halfspace_intersection(seed, n, lattice):
    """Random hulls, and lattice normals (several planes through one vertex: non-simplicial dual facets)."""
    rng = np.random.default_rng(seed)
    if lattice:
        u = rng.integers(-2, 3, size=(n, 3)).astype(np.float64)
        u = u[np.abs(u).sum(axis=1) > 0]
        u /= np.linalg.norm(u, axis=1, keepdims=True)
        h = np.c_[u, np.ones(len(u))]
        if len(h) < 4 or np.linalg.matrix_rank(u) < 3:
            return
        c = rng.normal(size=3) * 0.01
    else:
        pts = rng.normal(size=(n, 3)) * np.array([1.0, 0.5, 0.3]) + rng.uniform(-3, 3, 3)
        h = hull_halfplanes(pts)
        c = pts.mean(axis=0)
    hs_in = np.c_[h[:, :3], -h[:, 3]]
    try:
        HalfspaceIntersection(hs_in, c)
    except Exception:  # noqa: BLE001 - unbounded lattice normals: both raise, nothing to compare
        return
    _same_halfspaces(hs_in, c)


def test_halfspaces_raw_degenerate_octahedron():
    octa = np.array([[sx, sy, sz, -1.0] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], float)
    _same_halfspaces(octa, np.zeros(3))


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(4, 200), grid=st.booleans())
def test_hull_raw_is_convex_hull(seed, n, grid):
    rng = np.random.default_rng(seed)
    pts = rng.integers(0, 6, size=(n, 3)).astype(np.float64) if grid else rng.normal(size=(n, 3))
    try:
        want = ConvexHull(pts, qhull_options="Qt")
    except Exception:  # noqa: BLE001 - flat point sets
        return
    vol, simplices, eq = hull_raw(pts, b"Qt")
    assert vol == want.volume
    assert np.array_equal(simplices, want.simplices)
    assert eq.view(np.uint64).tolist() == want.equations.view(np.uint64).tolist()
