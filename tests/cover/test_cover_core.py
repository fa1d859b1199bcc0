"""PolyMerge cover: hulls, clusters, set cover, merging and the family file."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from polycc.cover.build import build_cover
from polycc.cover.clusters import build_clusters, neighbour_offsets
from polycc.cover.family import CoverFamily
from polycc.cover.merge import VoxelBoxQuery
from polycc.cover.setcover import greedy_set_cover
from polycc.errors import PolyccError
from polycc.geometry.lattice import integer_planes, lattice_hull, voxel_corner_points, world_halfplanes
from polycc.occupancy.grid import OccupancyGrid
from polycc.verify.certify import FamilyArrays, PolytopeSet, voxel_corners


def grid_of(idx, g=0.05, origin=(0.0, 0.0, 0.0)) -> OccupancyGrid:
    idx = np.unique(np.asarray(idx, np.int64).reshape(-1, 3), axis=0)
    return OccupancyGrid(idx, g, np.asarray(origin, np.float64))


def box_voxels(lo, hi):
    r = [np.arange(a, b + 1) for a, b in zip(lo, hi)]
    return np.stack(np.meshgrid(*r, indexing="ij"), -1).reshape(-1, 3)


def uncovered_voxels(fam: CoverFamily, n: int) -> int:
    ps = PolytopeSet(FamilyArrays.from_family(fam), fam.active_nodes(n))
    return int(np.count_nonzero(ps.voxel_witness(voxel_corners(fam.grid_indices, fam.voxel_size, fam.origin)) < 0))


def assert_every_level_covers(fam: CoverFamily):
    for n in range(fam.n_max, 0, -1):
        P = fam.materialise(n)
        assert len(P) == n
        for p in P:
            assert np.allclose(np.linalg.norm(p.halfplanes[:, :3], axis=1), 1.0)
            assert np.all(p.contains(p.vertices))
        assert uncovered_voxels(fam, n) == 0, f"H^{n} misses a voxel"


# ---------------------------------------------------------------- hulls


def test_cube_hull_has_six_merged_planes():
    h = lattice_hull(voxel_corner_points(box_voxels((0, 0, 0), (2, 2, 2))))
    assert h.volume == pytest.approx(27.0)
    N, e = integer_planes(h)
    assert len(N) == 6  # qhull gives 12 triangles; coplanar ones merge exactly
    assert sorted(map(tuple, np.abs(N))) == sorted([(1, 0, 0)] * 2 + [(0, 1, 0)] * 2 + [(0, 0, 1)] * 2)
    assert len(h.vertices) == 8


def test_world_halfplanes_round_outward():
    g, origin = 0.05, np.array([0.1234567, -3.3, 7.77])
    vox = box_voxels((3, -2, 5), (5, 0, 5))
    h = lattice_hull(voxel_corner_points(vox))
    P, V = world_halfplanes(integer_planes(h)[0], h.vertices, g, origin)
    cor = voxel_corners(vox, g, origin).reshape(-1, 3)
    assert np.all(cor @ P[:, :3].T <= P[:, 3])  # strict float test, no tolerance
    assert len(P) == 6 and np.allclose(V.min(0), origin + np.array([3, -2, 5]) * g)


def test_box_query_counts_match_brute_force():
    rng = np.random.default_rng(1)
    q = np.unique(rng.integers(0, 40, (20000, 3)), axis=0)
    Q = VoxelBoxQuery(q)
    for _ in range(10):
        pts = rng.integers(0, 41, (10, 3))
        h = lattice_hull(pts)
        A, b = h.equations[:, :3], h.equations[:, 3]
        lo, hi = pts.min(0), pts.max(0) - 1
        c = Q.voxels(lo, hi)
        ref = np.count_nonzero(((c + 0.5) @ A.T + (0.5 * np.abs(A).sum(1) + b)).max(1) <= 1e-7)
        assert Q.count_inside(A, b, lo, hi) == ref
        assert Q.count(lo, hi) == len(c)


# ---------------------------------------------------------------- clusters and set cover


def test_clusters_match_definition():
    rng = np.random.default_rng(0)
    idx = np.unique(rng.integers(0, 6, (80, 3)), axis=0)
    cl = build_clusters(idx, 1)
    for v in range(len(idx)):
        want = {i for i in range(len(idx)) if np.abs(idx[i] - idx[v]).max() <= 1}
        assert set(cl.members(v).tolist()) == want
        hull = lattice_hull(voxel_corner_points(idx[cl.members(v)]))
        assert cl.weight()[v] == pytest.approx(hull.volume - len(want))


def test_cluster_weight_is_translation_invariant_pattern():
    idx = np.array([[0, 0, 0], [1, 1, 0], [10, 10, 10], [11, 11, 10]])
    cl = build_clusters(idx, 1)
    assert cl.pattern[0] == cl.pattern[2] and cl.weight()[0] == cl.weight()[2] > 0
    assert len(neighbour_offsets(2)) == 125


@settings(max_examples=20, deadline=None)
@given(st.integers(0, 10_000), st.integers(0, 2), st.integers(1, 40))
def test_the_process_wide_pattern_hulls_give_the_clusters_of_a_fresh_process(seed, b, cap):
    """Regression for the per-process cache of cluster-pattern hulls (shared by the tiles a worker builds): the
    clusters of a grid are the same whether the cache is empty, warm from other grids (with other b), or so small
    that it starts afresh in the middle of the grid."""
    import polycc.cover.clusters as C

    rng = np.random.default_rng(seed)
    grids = [np.unique(rng.integers(0, 7, (rng.integers(5, 90), 3)), axis=0) for _ in range(3)]

    def fields(cl):
        return [cl.neighbours, cl.pattern, cl.weights, cl.volumes, cl.sizes, cl.centre] + list(cl.hull_vertices)

    C._PATTERN_HULLS.clear()
    fresh = fields(build_clusters(grids[0], b))
    for g in grids[1:]:
        build_clusters(g, (b + 1) % 3)
        build_clusters(g, b)
    warm = fields(build_clusters(grids[0], b))
    old_max = C.PATTERN_HULLS_MAX
    C.PATTERN_HULLS_MAX = cap
    C._PATTERN_HULLS.clear()
    try:
        small = fields(build_clusters(grids[0], b))
        assert len(C._PATTERN_HULLS) <= cap
    finally:
        C.PATTERN_HULLS_MAX = old_max
        C._PATTERN_HULLS.clear()
    for other in (warm, small):
        assert len(other) == len(fresh) and all(np.array_equal(x, y) for x, y in zip(fresh, other))


@settings(max_examples=25)
@given(st.lists(st.tuples(*[st.integers(0, 7)] * 3), min_size=1, max_size=60, unique=True), st.integers(0, 2))
def test_box_rows_are_exact_occupied_boxes(vox, b):
    """Extra rows: one per voxel whose C_v wastes volume, an all-occupied box around it, W = 0."""
    idx = np.unique(np.array(vox), axis=0)
    cl = build_clusters(idx, b)
    V = cl.n_voxels
    assert V == len(idx) and np.array_equal(cl.centre[:V], np.arange(V))
    lossy = set(np.flatnonzero(cl.weight()[:V] > 1e-9).tolist())
    assert set(cl.centre[V:].tolist()) == lossy
    for r in range(V, len(cl.centre)):
        m = cl.members(r)
        v = int(cl.centre[r])
        assert v in m.tolist() and cl.weight()[r] == 0.0
        lo, hi = idx[m].min(0), idx[m].max(0)
        assert len(m) == np.prod(hi - lo + 1)  # every cell of the box is occupied and a member
        assert np.abs(idx[m] - idx[v]).max() <= b
    plain = build_clusters(idx, b, boxes=False)
    assert len(plain.centre) == V and np.array_equal(plain.neighbours, cl.neighbours[:V])


@settings(max_examples=25)
@given(st.lists(st.tuples(*[st.integers(0, 7)] * 3), min_size=1, max_size=60, unique=True), st.integers(0, 2),
       st.booleans())
def test_set_cover_covers_everything(vox, b, boxes):
    idx = np.unique(np.array(vox), axis=0)
    cl = build_clusters(idx, b, boxes)
    chosen = greedy_set_cover(cl)
    covered = np.zeros(len(idx), bool)
    for v in chosen:
        covered[cl.members(v)] = True
    assert covered.all()
    assert len(set(chosen.tolist())) == len(chosen)
    if boxes:  # every voxel has a zero-waste set, so the sub-cover wastes nothing
        assert np.all(cl.weight()[chosen] == 0.0)


# ---------------------------------------------------------------- merging and the family


@pytest.mark.parametrize("cost", ["paper", "delta"])
@pytest.mark.parametrize("refresh", ["lazy", "eager"])
def test_every_level_covers_random_blobs(cost, refresh):
    rng = np.random.default_rng(3)
    idx = np.concatenate([rng.integers(0, 8, (60, 3)), rng.integers(12, 16, (30, 3))])
    fam = build_cover(grid_of(idx), 1, cost, refresh=refresh)
    assert fam.merges.shape == (fam.n_max - 1, 2)
    assert_every_level_covers(fam)


def test_single_voxel():
    fam = build_cover(grid_of([[4, -2, 7]], g=0.1, origin=(0.3, 0.2, -1.0)), 1)
    assert fam.n_max == 1 and len(fam.merges) == 0
    (p,) = fam.materialise(1)
    assert len(p.halfplanes) == 6
    assert p.volume == pytest.approx(1e-3)
    assert_every_level_covers(fam)


def test_one_voxel_thick_wall():
    wall = box_voxels((0, 0, 0), (19, 0, 9))  # 20 x 1 x 10 voxels
    fam = build_cover(grid_of(wall), 1)
    assert_every_level_covers(fam)
    (p,) = fam.materialise(1)
    assert p.volume == pytest.approx(len(wall) * 0.05**3)  # a flat wall wastes nothing
    assert len(p.halfplanes) == 6


def test_disconnected_clusters_still_reach_one():
    a = box_voxels((0, 0, 0), (2, 2, 2))
    b = box_voxels((30, 0, 0), (31, 1, 1))
    c = np.array([[0, 40, 20]])
    fam = build_cover(grid_of(np.concatenate([a, b, c])), 1)
    assert fam.meta["touch_margin_rounds"] >= 1
    assert fam.n_max >= 3
    assert_every_level_covers(fam)


def test_all_one_box_scene():
    vox = box_voxels((0, 0, 0), (7, 5, 4))
    fam = build_cover(grid_of(vox), 1)
    assert_every_level_covers(fam)
    # exact W (Eq. 11) is 0 everywhere; the stored bound ignores partly covered voxels, so it is
    # exact for the clusters and for the final box, and at most g^3 per cut voxel in between
    assert fam.node_weight[: fam.n_max].sum() == pytest.approx(0.0, abs=1e-12)
    assert fam.node_weight[fam.active_nodes(1)].sum() == pytest.approx(0.0, abs=1e-12)
    (p,) = fam.materialise(1)
    assert len(p.halfplanes) == 6 and len(p.vertices) == 8


def test_family_roundtrip(tmp_path):
    rng = np.random.default_rng(5)
    fam = build_cover(grid_of(rng.integers(0, 10, (120, 3))), 1, "paper")
    path = fam.save(tmp_path)
    assert path.name == "cover.npz"
    back = CoverFamily.load(tmp_path)
    assert back.meta["merge_cost"] == "paper"
    for n in (1, back.n_max // 2 + 1, back.n_max):
        for p, q in zip(fam.materialise(n), back.materialise(n)):
            assert np.array_equal(p.halfplanes, q.halfplanes) and np.array_equal(p.vertices, q.vertices)
    with pytest.raises(PolyccError):
        back.materialise(back.n_max + 1)
    with pytest.raises(PolyccError):
        CoverFamily.load(tmp_path / "missing")


def test_empty_grid_is_a_user_error():
    with pytest.raises(PolyccError):
        build_cover(OccupancyGrid(np.empty((0, 3), np.int64), 0.05), 1)


def test_delta_cost_prefers_merges_that_add_little():
    # two long bars in a row plus a far-off small block: delta merges the bars first
    a = box_voxels((0, 0, 0), (9, 0, 0))
    b = box_voxels((10, 0, 0), (19, 0, 0))
    c = box_voxels((0, 3, 3), (0, 3, 3))
    fam = build_cover(grid_of(np.concatenate([a, b, c])), 1, "delta")
    assert_every_level_covers(fam)
