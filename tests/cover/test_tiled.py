"""Tiled, hierarchical cover: kd tiles, stage hand-over, merge order, solid blocks, runners."""

from __future__ import annotations

import os

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from polycc.cover.build import build_cover, build_families
from polycc.cover.clusters import build_clusters, solid_blocks
from polycc.cover.merge import VoxelBoxQuery, _inside_count
from polycc.cover.setcover import greedy_set_cover
from polycc.cover.tiled import kd_regions, order_merges, region_target
from polycc.geometry.lattice import lattice_hull
from polycc.occupancy.grid import OccupancyGrid
from polycc.parallel import Runner, Task, make_runner
from polycc.verify.certify import FamilyArrays, certify_all_levels

ARRAYS = ("leaf_voxel", "leaf_ptr", "leaf_members", "merges", "merge_costs", "node_weight", "node_volume", "plane_ptr",
          "planes", "vertex_ptr", "vertices")


def grid_of(idx, g=0.05, origin=(0.0, 0.0, 0.0)) -> OccupancyGrid:
    idx = np.unique(np.asarray(idx, np.int64).reshape(-1, 3), axis=0)
    return OccupancyGrid(idx, g, np.asarray(origin, np.float64))


def scene_voxels(seed: int = 3) -> np.ndarray:
    """Blobs, a one-voxel wall, a solid block and a far-off speck: seams cut all of them."""
    rng = np.random.default_rng(seed)
    blob = rng.integers(0, 14, (400, 3))
    wall = np.stack(np.meshgrid(np.arange(0, 30), [25], np.arange(0, 8), indexing="ij"), -1).reshape(-1, 3)
    solid = np.stack(np.meshgrid(*[np.arange(30, 41)] * 3, indexing="ij"), -1).reshape(-1, 3)  # holds one 8^3 block
    return np.concatenate([blob, wall, solid, [[80, 80, 80]]])


def same(a, b) -> bool:
    return all(np.array_equal(getattr(a, k), getattr(b, k)) for k in ARRAYS)


def certified(fam) -> bool:
    return certify_all_levels(FamilyArrays.from_family(fam), fam.grid_indices) == []


# ---------------------------------------------------------------- tiles


@settings(max_examples=30)
@given(st.integers(1, 400), st.integers(1, 120), st.integers(0, 10_000))
def test_kd_regions_partition_the_voxels(n, cap, seed):
    idx = np.unique(np.random.default_rng(seed).integers(-30, 30, (n, 3)), axis=0)
    regions = kd_regions(idx, cap)
    tiles = [r for r in regions if r.children is None]
    rows = np.concatenate([r.rows for r in tiles])
    assert np.array_equal(np.sort(rows), np.arange(len(idx)))  # every voxel in exactly one tile
    assert all(len(r.rows) <= cap for r in tiles)
    for r in regions:
        if r.children:
            a, b = (regions[c] for c in r.children)
            assert np.array_equal(np.sort(np.concatenate([a.rows, b.rows])), r.rows)
            assert a.depth == b.depth == r.depth + 1 and a.parent == b.parent == r.id
            # tiles are boxes: the two halves are separated along one axis
            pa, pb = idx[a.rows], idx[b.rows]
            assert any(pa[:, k].max() < pb[:, k].min() for k in range(3))
    assert region_target(regions[0], len(idx)) == 1


def test_one_tile_is_the_plain_greedy():
    grid = grid_of(scene_voxels())
    one = build_cover(grid, 1, "delta", tile_voxels=10**9)
    assert one.meta["tiles"]["tiles"] == 1
    assert same(one, build_cover(grid, 1, "delta", tile_voxels=len(grid)))


@pytest.mark.parametrize("cost", ["delta", "paper"])
@pytest.mark.parametrize("refresh", ["lazy", "eager"])
def test_tiled_family_covers_every_level(cost, refresh):
    grid = grid_of(scene_voxels())
    fam = build_cover(grid, 1, cost, refresh=refresh, tile_voxels=200, root_nodes=30)
    assert fam.meta["tiles"]["tiles"] >= 8
    assert fam.merges.shape == (fam.n_max - 1, 2)
    assert len(np.unique(fam.merges)) == 2 * (fam.n_max - 1)  # each node merged once
    assert certified(fam)


@settings(max_examples=15, deadline=None)
@given(st.lists(st.tuples(*[st.integers(0, 14)] * 3), min_size=2, max_size=150, unique=True), st.integers(5, 60),
       st.integers(2, 20), st.sampled_from(["delta", "paper"]))
def test_tiled_covers_any_scene(vox, cap, root, cost):
    fam = build_cover(grid_of(vox), 1, cost, tile_voxels=cap, root_nodes=root)
    assert certified(fam)


def test_the_family_does_not_depend_on_the_workers():
    grid = grid_of(scene_voxels())
    kw = dict(tile_voxels=300, root_nodes=30)
    serial = build_families(grid, 1, ("delta",), **kw)
    with make_runner(2) as pool:
        par = build_families(grid, 1, ("delta",), runner=pool, **kw)
    assert all(same(serial[c], par[c]) for c in serial)


def test_the_costs_sharing_a_tile_memo_give_the_families_built_without_it(monkeypatch):
    """A tile runs every merge cost over one memo of pair evaluations: both families are the ones each
    cost builds alone, and the ones built with no memo at all (every pair evaluated)."""
    import polycc.cover.tiled as tiled

    grid = grid_of(scene_voxels())
    kw = dict(tile_voxels=300, root_nodes=30)
    both = build_families(grid, 1, ("delta", "paper"), **kw)
    for cost in ("delta", "paper"):
        assert same(both[cost], build_families(grid, 1, (cost,), **kw)[cost])
    real = tiled.MergeStage
    monkeypatch.setattr(tiled, "MergeStage", lambda *a, memo=None, **k: real(*a, **k))
    bare = build_families(grid, 1, ("delta", "paper"), **kw)
    assert all(same(both[c], bare[c]) for c in both)
    assert both["paper"].meta["pair_evaluations"] < bare["paper"].meta["pair_evaluations"]


def test_dask_local_cluster_gives_the_same_family():
    pytest.importorskip("dask.distributed")
    grid = grid_of(scene_voxels())
    kw = dict(tile_voxels=300, root_nodes=30)
    serial = build_cover(grid, 1, "delta", **kw)
    with make_runner(dask="local:2") as r:
        assert r.workers == 2 and r.local_cores == 2  # the budget forks as many local processes
        assert same(serial, build_cover(grid, 1, "delta", runner=r, **kw))
        # regression: the nanny's MALLOC_TRIM_THRESHOLD_ turned off glibc's adaptive mmap threshold in the
        # workers (the 1.5M-splat room at 2.5 cm: 49 s in the kernel instead of 15, occupancy 20.6 s instead of 6.9)
        env = r.client.run(lambda: (os.environ.get("MALLOC_TRIM_THRESHOLD_"), os.environ.get("OMP_NUM_THREADS")))
        assert set(env.values()) == {(None, "1")}


def test_order_merges_respects_dependencies_and_costs():
    # stage 0 makes node 10 from leaves 0, 1; stage 1 merges 10 with 2 (cheap, but must wait)
    recs = [{"merges": [(0, 1), (3, 4)], "costs": [5.0, 1.0], "refs": [10, 11]},
            {"merges": [(10, 2)], "costs": [0.0], "refs": [12]}]
    merges, costs, made = order_merges(recs, [0, 1, 2, 3, 4])
    assert merges == [(0, 1), (10, 2), (3, 4)] and made == [10, 12, 11]
    assert list(costs) == [5.0, 0.0, 1.0]


# ---------------------------------------------------------------- pieces


def test_solid_blocks_are_full_aligned_and_disjoint():
    idx = np.unique(np.concatenate([scene_voxels(), np.stack(np.meshgrid(*[np.arange(0, 21)] * 3, indexing="ij"),
                                                                          -1).reshape(-1, 3)]), axis=0)
    lo, lev, block = solid_blocks(idx)
    assert len(lev) and lev.min() >= 3
    occupied = {tuple(v) for v in idx}
    for k, (a, L) in enumerate(zip(lo, lev)):
        s = 1 << int(L)
        assert np.all(a % s == 0)
        cube = {tuple(v) for v in np.stack(np.meshgrid(*[np.arange(x, x + s) for x in a], indexing="ij"),
                                           -1).reshape(-1, 3)}
        assert cube <= occupied
        assert {tuple(v) for v in idx[block == k]} == cube
    # the 21^3 cube holds the aligned 16^3 block at the origin
    assert any(int(L) == 4 and not a.any() for a, L in zip(lo, lev))


def test_set_cover_skips_voxels_already_held():
    idx = scene_voxels()
    idx = np.unique(idx, axis=0)
    held = np.zeros(len(idx), bool)
    held[::3] = True
    cl = build_clusters(idx, 1, True, centres=np.flatnonzero(~held))
    chosen = greedy_set_cover(cl, held)
    cov = held.copy()
    for r in chosen:
        cov[cl.members(r)] = True
    assert cov.all()
    assert np.all(np.isin(cl.centre[chosen], np.flatnonzero(~held)))


@settings(max_examples=40)
@given(st.integers(0, 10_000), st.booleans(), st.sampled_from([0, 4096]))
def test_column_count_is_the_voxel_count(seed, sparse, direct):
    """The column count (dense table or sorted keys, numpy reference and C) is the voxel-by-voxel count."""
    import polycc.cover.merge as M

    rng = np.random.default_rng(seed)
    q = np.unique(rng.integers(0, 24, (rng.integers(1, 3000), 3)), axis=0)
    old = M.DENSE_LIMIT, M.DIRECT_CELLS
    M.DENSE_LIMIT, M.DIRECT_CELLS = (8 if sparse else 1 << 24), direct
    try:
        Q = VoxelBoxQuery(q)
        pts = rng.integers(0, 26, (rng.integers(4, 14), 3))
        pts = np.concatenate([pts, pts.min(0) + [[3, 0, 0], [0, 3, 0], [0, 0, 3]]])  # full-dimensional
        h = lattice_hull(pts, b"QJ" if seed % 2 else b"Qt")
        lo, hi = pts.min(0), pts.max(0) - 1
        box = q[np.all((q >= lo) & (q <= hi), axis=1)]
        want = _inside_count(box, h.equations[:, :3], h.equations[:, 3], 1e-7)
        assert Q.count_inside_numpy(h.equations[:, :3], h.equations[:, 3], lo, hi) == want  # the reference
        assert Q.count_inside(h.equations[:, :3], h.equations[:, 3], lo, hi) == want  # the C
        assert Q.count(lo, hi) == len(box)
    finally:
        M.DENSE_LIMIT, M.DIRECT_CELLS = old


def _add(*xs):
    s = sum(xs)
    return s, 100 * s  # kept, passed on


def test_runners_pass_results_along_the_graph():
    graph = {"a": Task(_add, (1, 2)), "b": Task(_add, lambda: (10,), ("a",)), "c": Task(_add, (5,), ("a", "b"))}
    want = {"a": 3, "b": 310, "c": 5 + 300 + 31000}
    assert Runner().run(graph) == want
    with make_runner(2) as pool:
        assert pool.run(graph) == want


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(0, 30), m=st.integers(0, 60))
def test_a_handoff_pickles_to_the_same_nodes_and_entries(seed, n, m):
    """What a merge stage hands on is packed into flat arrays (it is pickled to another worker, or through the
    parent of --jobs processes); unpacked after pickling it gives the same nodes and heap entries, value for
    value. On the 1.5M-splat room at 2.5 cm the family and the header are the same bit for bit."""
    import pickle

    from polycc.cover.merge import EXACT, STALE, StageNodes
    from polycc.cover.tiled import Handoff, Ragged

    rng = np.random.default_rng(seed)
    verts = [rng.integers(-50, 50, (int(rng.integers(4, 12)), 3)) for _ in range(n)]
    planes = [(rng.integers(-9, 9, (k, 3)), rng.integers(-500, 500, k)) for k in rng.integers(4, 20, n)]
    live = StageNodes([int(r) for r in rng.integers(0, 2**40, n)], verts, planes, rng.random(n), rng.random(n),
                      [None if rng.random() < 0.5 else rng.bytes(4) for _ in range(n)])
    entries = [(float(rng.random()) if k % 2 else np.float64(rng.random()), int(rng.integers(0, max(n, 1))),
                int(rng.integers(0, max(n, 1))), int(rng.choice([0, EXACT, STALE])),
                None if rng.random() < 0.3 else int(rng.integers(0, 10**6))) for k in range(m)]
    back, ent = pickle.loads(pickle.dumps(Handoff(live, entries))).unpack()
    assert back.ref == live.ref and back.pattern == live.pattern
    assert all(np.array_equal(a, b) and a.dtype == b.dtype for a, b in zip(back.vertices, live.vertices))
    assert len(back.vertices) == n and len(back.planes) == n
    assert all(np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1]) for a, b in zip(back.planes, live.planes))
    assert np.array_equal(back.weight, live.weight) and np.array_equal(back.volume, live.volume)
    assert ent == entries and all(type(a[0]) is float and (a[4] is None) == (b[4] is None)
                                  for a, b in zip(ent, entries))
    r = pickle.loads(pickle.dumps(Ragged(verts)))
    assert len(r) == n and all(np.array_equal(a, b) for a, b in zip(r, verts)) and (n == 0 or np.array_equal(r[-1],
                                                                                                      verts[-1]))
