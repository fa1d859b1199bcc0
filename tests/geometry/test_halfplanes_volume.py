"""Volume from the half-space intersection's dual (polycc.geometry.halfplanes.polytope_vertices_volume)
against the convex hull of the vertices, the way it was computed before (scipy.spatial.ConvexHull)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial import ConvexHull

from polycc.geometry.halfplanes import axis_box, hull_halfplanes, polytope_vertices, polytope_vertices_volume


def _check(h, interior=None):
    got = polytope_vertices_volume(h, interior)
    v = polytope_vertices(h, interior)
    if v is None:
        assert got is None
        return None
    assert np.array_equal(got[0], v)  # the same qhull run
    want = ConvexHull(v).volume
    assert got[1] == pytest.approx(want, rel=1e-10, abs=1e-15)
    return got[1]


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(4, 120), flat=st.floats(0.02, 1.0),
       redundant=st.integers(0, 6), drop=st.integers(0, 3))
def test_dual_volume_is_the_hull_volume(seed, n, flat, redundant, drop):
    """Random hulls (elongated, with redundant planes and with planes dropped, as the reduction does)."""
    rng = np.random.default_rng(seed)
    pts = rng.normal(size=(n, 3)) * np.array([1.0, flat, 0.3]) + rng.uniform(-3, 3, 3)
    try:
        h = hull_halfplanes(pts)
    except Exception:  # flat point sets have no 3-D hull: nothing to compare
        return
    c = pts.mean(axis=0)
    extra = []
    for _ in range(redundant):  # planes that touch nothing, or just touch a vertex
        u = rng.normal(size=3)
        u /= np.linalg.norm(u)
        d = float(np.max(pts @ u)) + (0.0 if rng.random() < 0.5 else rng.uniform(0, 1))
        extra.append(np.r_[u, d])
    if extra:
        h = np.vstack([h, extra])
    for _ in range(drop):
        if len(h) > 4:
            h = np.delete(h, int(rng.integers(len(h))), axis=0)
    _check(h, c)


def test_degenerate_vertices_and_duplicate_planes():
    """Octahedron (four planes at every vertex: qhull splits each into two dual facets), a box with a
    repeated face and a box cut at a corner by a plane through it."""
    octa = np.array([[sx, sy, sz, 1.0] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], float)
    octa[:, :3] /= np.sqrt(3.0)
    octa[:, 3] /= np.sqrt(3.0)
    assert _check(octa, np.zeros(3)) == pytest.approx(4.0 / 3.0)
    box = axis_box([0, 0, 0], [1, 2, 3])
    assert _check(np.vstack([box, box[:2]]), np.array([0.5, 1, 1.5])) == pytest.approx(6.0)
    corner = np.r_[np.ones(3) / np.sqrt(3.0), 6.0 / np.sqrt(3.0)]  # through the corner (1, 2, 3)
    assert _check(np.vstack([box, corner]), np.array([0.5, 1, 1.5])) == pytest.approx(6.0)


def test_unbounded_is_none():
    h = axis_box([0, 0, 0], [1, 1, 1])[:-1]
    assert polytope_vertices_volume(h, np.full(3, 0.5)) is None


def test_the_dual_path_is_taken():
    """The speed-up is real only if the dual gives the volume (not the hull fallback): for a hull of
    points (every vertex on several planes, qhull merges the dual's facets) and for the octahedron."""
    from polycc.geometry.halfplanes import _dual_volume, _intersection

    rng = np.random.default_rng(3)
    pts = rng.normal(size=(80, 3))
    h = hull_halfplanes(pts)
    hs, c = _intersection(h, pts.mean(axis=0), 1e-9, 1e6)
    assert _dual_volume(hs.dual_facets, hs.intersections, c, h) == pytest.approx(
        ConvexHull(pts).volume, rel=1e-10)
    octa = np.array([[sx, sy, sz, 1.0] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], float)
    hs, c = _intersection(octa, np.zeros(3), 1e-9, 1e6)
    assert _dual_volume(hs.dual_facets, hs.intersections, c, octa) == pytest.approx(
        4.0 / 3.0)


@settings(max_examples=80, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(4, 80), flat=st.floats(0.001, 1.0),
       drop=st.integers(0, 8), min_gamma=st.sampled_from([1e-9, 1e-4, 1e-2, 0.2, 0.5]))
def test_the_certified_intersection_is_the_checked_one(seed, n, flat, drop, min_gamma):
    """Where the intersection proves boundedness itself (gamma >= min depth / max radius), the separate
    is_bounded hull would have said True and qhull's intersection is the same; needles (flat up to 1e-3)
    and planes dropped until unbounded included."""
    from scipy.spatial import HalfspaceIntersection

    from polycc.geometry.halfplanes import _intersection_certified, is_bounded

    rng = np.random.default_rng(seed)
    pts = rng.normal(size=(n, 3)) * np.array([1.0, flat, flat]) + rng.uniform(-3, 3, 3)
    try:
        h = hull_halfplanes(pts)
    except Exception:
        return
    c = pts.mean(axis=0)
    for _ in range(drop):
        if len(h) > 4:
            h = np.delete(h, int(rng.integers(len(h))), axis=0)
    got = _intersection_certified(h, c, min_gamma, 1e6)
    if got is False:
        return  # not proved: the caller checks is_bounded as before
    assert is_bounded(h[:, :3], min_gamma)
    want = HalfspaceIntersection(np.c_[h[:, :3], -h[:, 3]], c).intersections
    assert got is not None and np.array_equal(got[0].intersections, want)


def _random_planes(rng, n: int) -> np.ndarray:
    """n planes n . p <= d around the origin in general position (vertices on three planes)."""
    u = rng.normal(size=(n, 3)) * rng.uniform(0.2, 2.0, 3)
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    return np.c_[u, rng.uniform(0.5, 2.0, n)]


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(4, 200), box=st.booleans())
def test_the_fan_volume_is_the_sorted_faces_volume(seed, n, box):
    """The edge-fan volume (vertices on three planes) against the angular sort of every face, on planes
    in general position and with an axis box (vertices on more planes: the sorted path both times)."""
    from polycc.geometry.halfplanes import _dual_volume, _dual_volume_sorted, _intersection

    rng = np.random.default_rng(seed)
    h = _random_planes(rng, n)
    if box:
        h = np.vstack([h, axis_box([-1.5, -1.5, -1.5], [1.5, 1.5, 1.5])])
    r = _intersection(h, np.zeros(3), 1e-9, 1e6)
    if r is None:
        return
    hs, c = r
    a = _dual_volume(hs.dual_facets, hs.intersections, c, h)
    b = _dual_volume_sorted(hs.dual_facets, hs.intersections, c, h)
    assert a == pytest.approx(b, rel=1e-12)
    assert a == pytest.approx(ConvexHull(hs.intersections).volume, rel=1e-10)


def test_planes_in_general_position_take_the_fan():
    """Planes in general position: every vertex on three planes, so the fan path runs (not the sort)."""
    from polycc.geometry.halfplanes import _intersection

    h = _random_planes(np.random.default_rng(5), 60)
    hs, _ = _intersection(h, np.zeros(3), 1e-9, 1e6)
    assert np.asarray(hs.dual_facets).shape[1] == 3
