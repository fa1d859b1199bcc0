"""Exact occupancy: agrees with a brute-force bounded least-squares reference, errs toward occupied."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.optimize import lsq_linear

from polycc.geometry.ellipsoid_box import boxes_inside, boxes_intersect, min_whitened_distance
from polycc.occupancy.exact import aabb_index_range, pack_keys, unpack_keys, voxelize
from polycc.occupancy.grid import OccupancyGrid
from polycc.scene.ellipsoids import Ellipsoids, quaternion_to_rotation


def random_ellipsoids(n, rng, log_sigma=(np.log(1e-3), np.log(0.1)), span=0.5, k=1.0):
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1)[:, None]
    return Ellipsoids(rng.uniform(-span, span, (n, 3)), quaternion_to_rotation(q),
                      np.exp(rng.uniform(*log_sigma, (n, 3))), k)


def exact_min(M, c, lo, hi):
    """Brute-force reference: min over the box of |M (p - c)|.

    Active-set enumeration over all 27 faces of the box (SVD least squares on each face's
    free coordinates, kept only if feasible), combined with scipy's BVLS solver. Every
    candidate is a point of the box, so the smaller is the better; BVLS alone is
    unreliable for needle-thin ellipsoids (condition numbers of 1e6 and more).
    """
    best = np.linalg.norm(M @ (lsq_linear(M, M @ c, bounds=(lo, hi), method="bvls", tol=1e-15).x - c))
    for code in range(27):
        state = [(code // 3**a) % 3 for a in range(3)]  # 0: at lo, 1: at hi, 2: free
        p = np.where(np.array(state) == 1, hi, lo).astype(np.float64)
        free = [a for a in range(3) if state[a] == 2]
        if free:
            A = M[:, free]
            rhs = -(M @ (p - c))
            sol = np.linalg.lstsq(A, rhs, rcond=None)[0]
            p[free] = p[free] + sol
            if np.any(p < lo - 1e-12) or np.any(p > hi + 1e-12):
                continue
        best = min(best, np.linalg.norm(M @ (p - c)))
    return best


def reference_occupancy(ell: Ellipsoids, g: float, tol=1e-9):
    """(sure, maybe): voxel keys the reference says occupied, and ones within tol of the boundary."""
    imin, imax = aabb_index_range(ell, g, np.zeros(3))
    M = ell.whitening()
    sure, maybe = set(), set()
    for i in range(len(ell)):
        for ix in range(imin[i, 0] - 1, imax[i, 0] + 2):
            for iy in range(imin[i, 1] - 1, imax[i, 1] + 2):
                for iz in range(imin[i, 2] - 1, imax[i, 2] + 2):
                    lo = np.array([ix, iy, iz]) * g
                    d = exact_min(M[i], ell.centers[i], lo, lo + g)
                    if d <= 1 - tol:
                        sure.add((ix, iy, iz))
                    elif d <= 1 + tol:
                        maybe.add((ix, iy, iz))
    return sure, maybe


def occupied_set(occ: OccupancyGrid):
    return set(map(tuple, occ.indices.tolist()))


@pytest.mark.parametrize("kind", ["mixed", "needles", "discs", "huge"])
def test_matches_bruteforce_reference(kind):
    rng = np.random.default_rng({"mixed": 1, "needles": 2, "discs": 3, "huge": 4}[kind])
    g = 0.05
    if kind == "mixed":
        ell = random_ellipsoids(60, rng, (np.log(1e-4), np.log(0.08)))
    elif kind == "needles":
        ell = random_ellipsoids(20, rng)
        ell.sigmas[:, 0] = 0.15
        ell.sigmas[:, 1:] = np.exp(rng.uniform(np.log(1e-7), np.log(1e-4), (20, 2)))
    elif kind == "discs":
        ell = random_ellipsoids(25, rng)
        ell.sigmas[:, :2] = 0.06
        ell.sigmas[:, 2] = 1e-6
    else:
        ell = random_ellipsoids(2, rng, (np.log(0.12), np.log(0.25)), span=0.05)
    occ = set(map(tuple, voxelize(ell, g).indices.tolist()))
    sure, maybe = reference_occupancy(ell, g)
    assert sure - occ == set(), "a voxel the ellipsoid truly meets came out empty"
    assert occ - sure - maybe == set(), "a voxel the ellipsoid clearly misses came out occupied"


def test_touching_faces_edges_corners_and_grid_aligned():
    g = 0.1
    r = 0.03
    I = np.eye(3)[None]
    centers = np.array([
        [0.05, 0.05, 0.1 + r],                              # touches the top face of voxel (0,0,0)
        [0.1 + r / np.sqrt(2), 0.1 + r / np.sqrt(2), 0.05],  # touches the vertical edge x=y=0.1
        np.array([0.1, 0.1, 0.1]) + r / np.sqrt(3),          # touches the corner (0.1,0.1,0.1)
    ])
    for c in centers:
        ell = Ellipsoids(c[None], I.copy(), np.full((1, 3), r), 1.0)
        assert (0, 0, 0) in occupied_set(voxelize(ell, g)), c
    # a box-shaped splat exactly on the grid: a sphere centred on a voxel corner touches all 8 voxels
    ell = Ellipsoids(np.array([[0.2, 0.2, 0.2]]), I.copy(), np.full((1, 3), 1e-7), 1.0)
    got = occupied_set(voxelize(ell, g))
    assert got == {(i, j, k) for i in (1, 2) for j in (1, 2) for k in (1, 2)}


@settings(max_examples=200)
@given(
    seed=st.integers(0, 2**31 - 1),
    log_sig=st.tuples(*[st.floats(np.log(1e-6), np.log(0.5))] * 3),
    u=st.tuples(*[st.floats(-1, 1)] * 3),
    k=st.sampled_from([1.0, 2.0, 3.0]),
    g=st.sampled_from([0.01, 0.02, 0.05, 0.1]),
)
def test_points_inside_an_ellipsoid_lie_in_occupied_voxels(seed, log_sig, u, k, g):
    rng = np.random.default_rng(seed)
    ell = random_ellipsoids(1, rng, span=1.0, k=k)
    ell.sigmas[0] = np.exp(log_sig)
    u = np.asarray(u)
    u = u / max(1.0, np.linalg.norm(u))  # |u| <= 1, on the surface when the norm was >= 1
    p = ell.centers[0] + ell.axes()[0] @ u
    # exactness, not the refusal of huge solid interiors (tests/occupancy/test_scale.py tests that)
    occ = occupied_set(voxelize(ell, g, max_solid_voxels=None))
    v = np.floor(p / g).astype(int)
    # a point on a voxel face belongs to both closed voxels; floor picks one of them
    assert tuple(v) in occ


def test_hierarchical_refinement_equals_direct_enumeration(monkeypatch):
    rng = np.random.default_rng(9)
    ell = random_ellipsoids(30, rng, (np.log(0.02), np.log(0.3)))
    a = voxelize(ell, 0.02)
    import polycc.occupancy.exact as occ_mod
    monkeypatch.setattr(occ_mod, "DIRECT_EXTENT", 10_000)
    b = voxelize(ell, 0.02)
    np.testing.assert_array_equal(a.indices, b.indices)
    np.testing.assert_array_equal(a.counts, b.counts)


def test_chunking_does_not_change_the_result():
    rng = np.random.default_rng(11)
    ell = random_ellipsoids(2000, rng, (np.log(0.002), np.log(0.03)))
    a = voxelize(ell, 0.03)
    b = voxelize(ell, 0.03, chunk=97)
    np.testing.assert_array_equal(a.indices, b.indices)
    np.testing.assert_array_equal(a.counts, b.counts)


def test_floater_filter_counts_distinct_ellipsoids():
    g = 0.1
    I = np.broadcast_to(np.eye(3), (4, 3, 3)).copy()
    # three tiny splats in voxel (0,0,0), one in voxel (5,0,0)
    c = np.array([[0.05, 0.05, 0.05], [0.02, 0.03, 0.04], [0.07, 0.06, 0.05], [0.55, 0.05, 0.05]])
    ell = Ellipsoids(c, I, np.full((4, 3), 1e-3), 1.0)
    occ = voxelize(ell, g, min_splats_per_voxel=3)
    assert occupied_set(occ) == {(0, 0, 0)}
    assert occ.counts.tolist() == [3]
    assert occ.stats["voxels_removed_by_floater_filter"] == 1


def test_box_predicates_are_consistent():
    rng = np.random.default_rng(5)
    ell = random_ellipsoids(500, rng, (np.log(0.01), np.log(0.5)))
    lo = rng.uniform(-0.6, 0.6, (500, 3))
    hi = lo + rng.uniform(0.001, 0.2, (500, 3))
    M = ell.whitening()
    inside = boxes_inside(ell.centers, M, lo, hi)
    meets = boxes_intersect(ell.centers, M, lo, hi)
    assert np.all(meets[inside])
    d, err = min_whitened_distance(ell.centers, M, lo, hi)
    ref = np.array([exact_min(M[i], ell.centers[i], lo[i], hi[i]) for i in range(500)])
    assert np.all(np.abs(d - ref) <= err + 1e-12 * np.maximum(ref, 1))


def test_keys_roundtrip_and_npz(tmp_path):
    idx = np.array([[-5, 0, 7], [1_000_000, -1_000_000, 3], [0, 0, 0]])
    np.testing.assert_array_equal(unpack_keys(pack_keys(idx)), idx)
    occ = OccupancyGrid(idx, 0.05, np.array([0.0, 0.0, 0.0]), np.array([1, 2, 3], np.int32))
    occ.save(tmp_path / "o.npz")
    back = OccupancyGrid.load(tmp_path / "o.npz")
    np.testing.assert_array_equal(back.indices, idx)
    assert back.voxel_size == 0.05 and back.counts.tolist() == [1, 2, 3]


def test_real_capture_contains_every_centre(scenes_dir):
    from polycc.scene.load import SceneOptions, load_scene
    s = load_scene(scenes_dir / "ring_10k.splat", SceneOptions(scale=0.5))
    occ = voxelize(s.ellipsoids, 0.02)
    keys = set(pack_keys(occ.indices).tolist())
    centre_keys = pack_keys(np.floor(s.ellipsoids.centers / 0.02).astype(np.int64))
    assert all(k in keys for k in centre_keys.tolist())
