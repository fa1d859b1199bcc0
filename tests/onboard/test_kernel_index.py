"""The spatial index (docs/barrier.md section 9): certified lists, clearance cap, the outside path, the
certified worst case, bit-exactness of the indexed kernel (host cffi and Cortex-M4 QEMU) and the bound
on the work (counted by the reference, and cycles on the Cortex-M4 model)."""

from __future__ import annotations

from functools import lru_cache

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from polycc.budget import cycle_model as CM
from polycc.onboard import barrier as B
from polycc.onboard.index import build_index, grid_box, index_slack
from polycc.onboard.layout import pack_scene, scene_from_bytes
from polycc.testing.bitexact import (
    PARAMS,
    SCENES,
    arm_or_skip,
    assert_bitexact,
    edge_states,
    index_states,
    indexed_scene,
    states,
)
from polycc.testing.synthetic import shell_scene, small_scene

kffi = pytest.importorskip("polycc.sim.kernel_ffi")

CONFIGS = [("hulls", 0.6, 1.0, 30_000.0), ("boxes", 0.3, 0.5, 30_000.0), ("planes4096", 0.6, 2.0, 80_000.0)]


def _all_states(sc, n, seed):
    x1, g1 = states(sc, n, seed)
    x2, g2 = index_states(sc, n, seed + 1)
    x3, g3 = edge_states(sc)
    return np.vstack([x1, x2, x3]), np.vstack([g1, g2, g3])


@pytest.mark.parametrize("name, cap, cell, target", CONFIGS)
def test_host_bitexact_and_never_optimistic_with_index(name, cap, cell, target):
    sc = indexed_scene(name, cap, cell, target)
    assert sc.index.n_inner > 0 or name != "planes4096"  # the octree is exercised
    x, goal = _all_states(sc, 8000, 50)
    for prm in PARAMS:
        out = kffi.step_batch(kffi.HostScene(sc), prm, x, goal)
        assert_bitexact(B.step(sc, prm, x, goal), out, f"host indexed {name}")
        ok = out["flags"] & B.FLAG_INVALID == 0
        assert ok.mean() > 0.8
        lhs = out["psi"][ok].astype(np.float64) + float(np.float32(prm.radius))
        assert np.all(lhs <= B.exact_minmax(sc, x[ok])), "optimistic with the index"
        # the cap: psi0 <= D everywhere
        assert np.all(out["psi"][ok] + np.float32(prm.radius) <= sc.index.cap)


@pytest.mark.arm
@pytest.mark.parametrize("name, cap, cell, target", CONFIGS)
def test_arm_qemu_bitexact_with_index(name, cap, cell, target):
    kernel_arm = arm_or_skip()
    sc = indexed_scene(name, cap, cell, target)
    x, goal = _all_states(sc, 4000, 60)
    for prm in PARAMS[:2]:
        out = kernel_arm.run_qemu(kernel_arm.test_program(), sc, prm, x, goal)
        assert_bitexact(B.step(sc, prm, x, goal), out, f"cortex-m4 indexed {name}")


def test_image_round_trip_with_index():
    sc = indexed_scene("hulls")
    back = scene_from_bytes(sc.to_bytes())
    assert back.to_bytes() == sc.to_bytes()
    assert np.array_equal(back.index.children, sc.index.children)
    assert sc.flash_bytes() == 52 + len(sc.to_bytes()) - 32 - 36 + 56  # root + index records without images' words
    assert CM.worst_cycles(back) == CM.worst_cycles(sc)


def test_capped_and_outside_values():
    """Far from everything (outside B) psi0 = D exactly with zero gradient, and h >= D there."""
    sc = indexed_scene("hulls")
    lo, hi = sc.index.origin.astype(np.float64), sc.index.origin + np.array(sc.index.dims) * sc.index.cell
    x = np.array([hi + 0.01, lo - 0.01, [1e4, 0, 0], [0, -3e4, 5]], np.float32)
    psi, grad, fl = B.barrier(sc, B.Params(radius=0.0), x)
    assert np.all(fl == 0) and not np.any(grad)
    assert np.all(sc.index_leaf(x)[0] == -1)
    marg = B.MARGIN_REL * (((np.abs(x).sum(1)) + sc.coord_bound) + np.float32(32.0) / np.float32(100.0))
    assert np.allclose(psi, sc.index.cap - marg, rtol=0, atol=1e-6)
    assert np.all(B.exact_minmax(sc, x) >= float(sc.index.cap))


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 10_000), st.integers(1, 12), st.booleans(), st.sampled_from([0.1, 0.3, 0.6, 2.0]),
       st.sampled_from([0.25, 0.5, 1.0]), st.integers(0, 2**31))
def test_grid_box_is_certified(seed, n, boxes, cap, cell, pseed):
    """Outside B every polytope has phi_k >= D + slack (the per-face LP certificates)."""
    sc = _small(seed, n, boxes)
    delta = cap + index_slack(sc, 100.0)
    lo, hi = grid_box(sc, delta)
    rng = np.random.default_rng(pseed)
    x = rng.uniform(lo - 3, hi + 3, (4000, 3))
    ax = rng.integers(0, 3, len(x))
    up = rng.integers(0, 2, len(x)).astype(bool)
    step = rng.uniform(0, 2, len(x)) ** 3
    x[np.arange(len(x)), ax] = np.where(up, hi[ax] + step, lo[ax] - step)
    assert np.all(B.exact_minmax(sc, x) >= delta * (1 - 1e-12))


def _every_lp_box(sc, delta):
    """grid_box as first written: every face of every polytope from its own LP (or exact axis plane)."""
    from fractions import Fraction

    from polycc.onboard.index import _face_bound

    pm = sc.plane_matrix().astype(np.float64)
    lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
    for p in sc.polys:
        rows = pm[int(p["first"]) : int(p["first"]) + int(p["count"])]
        for j in range(3):
            for sign in (1.0, -1.0):
                e = np.zeros(3)
                e[j] = sign
                exact = np.nonzero(np.all(rows[:, :3] == e, axis=1))[0]
                if len(exact):
                    X = Fraction(float(np.min(rows[exact, 3]))) + Fraction(delta)
                    b = float(X) if Fraction(float(X)) >= X else float(np.nextafter(float(X), np.inf))
                else:
                    b = _face_bound(rows[:, :3], rows[:, 3], e, delta)
                if sign > 0:
                    hi[j] = max(hi[j], b)
                else:
                    lo[j] = min(lo[j], -b)
    return lo, hi


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 10_000), st.integers(1, 40), st.booleans(), st.sampled_from([0.1, 0.3, 0.6]))
def test_grid_box_skips_lps_without_changing_the_box(seed, n, boxes, cap):
    """Regression for the ball-bound skip (most polytopes get no LP): the box is bit for bit the one
    with an LP for every face of every polytope."""
    sc = _small(seed, n, boxes)
    delta = cap + index_slack(sc, 100.0)
    lo, hi = grid_box(sc, delta)
    want_lo, want_hi = _every_lp_box(sc, delta)
    assert lo.tobytes() == want_lo.tobytes() and hi.tobytes() == want_hi.tobytes()


@lru_cache(maxsize=64)
def _small(seed: int, n: int, boxes: bool):
    return small_scene(seed, n, boxes)


@lru_cache(maxsize=64)
def _small_indexed(seed, n, boxes, cap, cell, target, kappa):
    sc = _small(seed, n, boxes)
    return sc.with_index(build_index(sc, cap, cell, kappa=kappa, target=target))


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 10_000), st.integers(1, 12), st.booleans(), st.sampled_from([0.05, 0.3, 0.6, 3.0]),
       st.sampled_from([0.125, 0.5, 1.0, 2.0]), st.sampled_from([None, 3000.0, 10_000.0]),
       st.sampled_from([30.0, 100.0, 1000.0]), st.sampled_from([1.0, 100.0, 1e4]), st.integers(0, 2**31))
def test_never_optimistic_with_index(seed, n, boxes, cap, cell, target, kappa, kappa_run, pseed):
    """psi + r <= min_k max_l (n.p - d) with the index, whatever D, cells, refinement and the kappa the
    index was built for; points at cell corners, on faces, near many polytopes, outside B, far."""
    sc = _small_indexed(seed, n, boxes, cap, cell, target, kappa)
    hs = kffi.HostScene(sc)
    x, goal = index_states(sc, 400, pseed)
    x2, g2 = states(sc, 200, pseed)
    x, goal = np.vstack([x, x2]), np.vstack([goal, g2])
    prm = B.Params(kappa=kappa_run, radius=0.05)
    out = kffi.step_batch(hs, prm, x, goal)
    assert_bitexact(B.step(sc, prm, x, goal), out, "indexed small")
    ok = out["flags"] & B.FLAG_INVALID == 0
    lhs = out["psi"][ok].astype(np.float64) + float(np.float32(prm.radius))
    rhs = B.exact_minmax(sc, x[ok])
    worst = int(np.argmax(lhs - rhs))
    assert np.all(lhs <= rhs), f"optimistic by {lhs[worst] - rhs[worst]:.3g} m at {x[ok][worst]}"


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 10_000), st.integers(2, 12), st.booleans(), st.integers(0, 2**31))
def test_index_is_tight_where_not_capped(seed, n, boxes, pseed):
    """Built for the kappa it runs at, the index changes psi by at most the culling bound (section 4)
    where psi0 < D: the listed polytopes hold the soft-min."""
    sc0 = _small(seed, n, boxes)
    sc = _small_indexed(seed, n, boxes, 0.6, 0.5, 3000.0, 100.0)
    x, _ = index_states(sc, 400, pseed)
    prm = B.Params(kappa=100.0, radius=0.0)
    p0, _, f0 = B.barrier(sc0, prm, x)
    p1, _, f1 = B.barrier(sc, prm, x)
    ok = (f0 == 0) & (f1 == 0)
    marg = B.MARGIN_REL * 1e3  # psi0 well below D
    below = ok & (p0.astype(np.float64) < float(sc.index.cap) - 0.01 - marg)
    d = np.abs(p1[below].astype(np.float64) - p0[below])
    assert np.all(d <= sc.n_polys * np.exp(-17.0) / 100.0 + 4e-7 * (1 + np.abs(p0[below]))), d.max(initial=0)
    capped = ok & (p0 >= sc.index.cap)
    assert np.all(p1[capped] <= p0[capped])


@pytest.mark.parametrize("name, cap, cell, target", CONFIGS)
def test_counted_work_never_exceeds_the_leaf_bound(name, cap, cell, target):
    """Dense and adversarial positions: the polytopes the reference enters and evaluates are at most the
    leaf's list, and the modelled cycles of that work at most the certified figure of the leaf and the
    scene's certified worst case."""
    sc = indexed_scene(name, cap, cell, target)
    x, _ = _all_states(sc, 20_000, 70)
    ok = B._coord_ok(x)
    x = x[ok]
    from polycc.onboard.index import leaf_work

    w = leaf_work(sc)
    acc = {}
    for row in w:  # the largest exp-path bound among the leaves with this (list, depth)
        acc[(row[0], row[1])] = max(acc.get((row[0], row[1]), 0), int(row[4]))
    work = sc.index.list_work(sc.polys["count"])
    worst = CM.worst_cycles(sc)
    lid, depth = sc.index_leaf(x)
    for prm in PARAMS[:1] + [B.Params(kappa=300.0)]:  # the bound holds at and above the build kappa (100)
        stats: dict = {}
        B.barrier(sc, prm, x, stats=stats)
        m = np.where(lid >= 0, work[np.maximum(lid, 0), 0], 0)
        assert np.all(stats["entered"] <= m) and np.all(stats["evaluated"] <= stats["entered"])
        bound = np.array([acc.get((int(a), int(d)), 0) for a, d in zip(lid, depth)])
        assert np.all(stats["exp_planes"] <= bound), "more exp-path planes than the leaf's certified bound"
        planes = np.where(lid >= 0, work[np.maximum(lid, 0), 1], 0)
        cyc = CM.indexed_cycles(stats["entered"], planes, depth, stats["exp_planes"])
        assert np.all(cyc <= worst)


def test_refinement_lowers_the_worst_case():
    sc = indexed_scene("planes4096", 0.6, 2.0, None)  # refined as far as it goes
    flat = sc.with_index(build_index(sc, 0.6, 2.0, max_bytes=0))  # no refinement fits 0 bytes: flat grid
    assert flat.index.n_inner == 0
    assert CM.worst_cycles(sc) < CM.worst_cycles(flat) < CM.worst_cycles(sc.with_index(None))


@pytest.mark.arm
def test_arm_cycles_at_the_worst_leaf_within_certified():
    """Cortex-M4 model (unicorn + timing table): at positions in the leaf with the largest certified
    figure (corners, centre, random points), and on a shell scene where every listed polytope is
    evaluated, the high end of the modelled cycles stays at or below the certified worst case."""
    pytest.importorskip("unicorn")
    pytest.importorskip("capstone")
    kernel_arm = arm_or_skip()
    from polycc.sim.cortex_m4_model import Emulator

    emu = Emulator(kernel_arm.test_program())
    rng = np.random.default_rng(5)
    scenes = [indexed_scene("hulls"), indexed_scene("planes4096", 0.6, 2.0, 80_000.0)]
    # every polytope of a 40-hull room on a shell of radius 0.3 m around the origin: none is culled there
    from polycc.testing.synthetic import random_hull_polytopes as rh

    shell = shell_scene(pack_scene(rh(np.random.default_rng(3), 40, points=(8, 14))), 0.3)
    scenes.append(shell.with_index(build_index(shell, 0.6, 1.0, target=None)))
    for sc in scenes:
        emu.load_scene(sc, PARAMS[0])
        certified = CM.worst_cycles(sc)
        ids, cyc = CM.leaf_cycles(sc)
        worst_list = ids[int(np.argmax(cyc))]
        lo = sc.index.origin.astype(np.float64)
        probe = rng.uniform(lo, lo + np.array(sc.index.dims) * sc.index.cell, (20_000, 3))
        lid, _ = sc.index_leaf(probe)
        pts = probe[lid == worst_list][:12]
        pts = np.vstack([pts, np.zeros((2, 3)), rng.normal(size=(2, 3)) * 1e-3])
        for x in pts:
            cost, out = emu.call_step("polycc_step", x, np.zeros(3))
            ref = B.step(sc, PARAMS[0], x[None], np.zeros((1, 3)))
            assert out["psi"][0].view(np.uint32) == ref["psi"][0].view(np.uint32)
            assert cost.high <= certified, f"{cost.high} cycles > certified {certified:.0f} at {x}"


def test_scenes_list_is_complete():
    assert {c[0] for c in CONFIGS} == set(SCENES)


@settings(max_examples=8, deadline=None)
@given(st.integers(0, 10_000), st.integers(1, 16), st.booleans(), st.sampled_from([0.05, 0.3, 0.6]),
       st.sampled_from([0.25, 0.5]), st.sampled_from([2, 4]))
def test_blocked_top_level_lists_exactly_what_the_full_one_does(seed, n, boxes, cap, cell, block):
    """The top cells evaluated block by block against the polytopes near each block only (a speed-up: the
    full evaluation grew with cells x half-planes) list the same polytopes with the same expensive-plane
    counts as every cell against every polytope."""
    from polycc.onboard.index import NEGLIGIBLE_NATS, _Geometry, lookup_eps

    sc = _small(seed, n, boxes)
    D = float(np.float32(cap))
    slack = index_slack(sc, 100.0)
    lo, hi = grid_box(sc, D + slack)
    eps = lookup_eps(float(np.max(np.abs(np.r_[lo, hi]))) + 2.0 * max(cell, float(np.max(hi - lo))))
    geo = _Geometry(sc, D, slack, eps, NEGLIGIBLE_NATS / 100.0)
    origin = np.floor((lo - 2 * eps) / cell) * cell
    dims = np.maximum(1, np.ceil((hi + 2 * eps - origin) / cell).astype(np.int64))
    ijk = np.stack(np.meshgrid(*[np.arange(d) for d in dims], indexing="ij"), -1).reshape(-1, 3)
    assume(len(ijk) <= 6000)  # sharp polytopes can grow the box far: the full evaluation below is m x planes
    centres = origin + (ijk + 0.5) * cell
    parts = [geo.listed(centres[i:i + 512], 0.5 * cell, np.arange(sc.n_polys)) for i in range(0, len(centres), 512)]
    full, full_acc = np.concatenate([a for a, _ in parts]), np.concatenate([b for _, b in parts])
    got, got_acc = geo.listed_grid(ijk, centres, 0.5 * cell, block)
    assert np.array_equal(got, full)
    assert np.array_equal(np.where(full, got_acc, 0), np.where(full, full_acc, 0))


@settings(max_examples=10, deadline=None)
@given(st.integers(0, 10_000), st.integers(1, 12), st.booleans(), st.sampled_from([0.05, 0.3, 0.6]),
       st.sampled_from([0.25, 0.5]), st.sampled_from([None, 3000.0]), st.integers(0, 2**31))
def test_index_does_not_depend_on_how_its_boxes_are_batched(seed, n, boxes, cap, cell, target, pseed):
    """The octree's splits and the top cells are listed many boxes per numpy pass (``listed_many``); the
    index is the same bit for bit with one box group per pass, and a batch gives each group what a call of
    its own gives (regression for the batching: a test of 60 index builds took 100 s, now 31 s)."""
    import polycc.onboard.index as IX

    sc = _small(seed, n, boxes)
    fields = ("origin", "cell_list", "list_start", "entries", "poly_first", "children", "work", "cap")
    a = build_index(sc, cap, cell, kappa=100.0, target=target)
    saved = IX.SPLIT_BATCH_MAX, IX.GRID_PAIRS_PER_PASS
    try:
        IX.SPLIT_BATCH_MAX, IX.GRID_PAIRS_PER_PASS = 1, 1  # one group per pass
        b = build_index(sc, cap, cell, kappa=100.0, target=target)
    finally:
        IX.SPLIT_BATCH_MAX, IX.GRID_PAIRS_PER_PASS = saved
    assert all(np.asarray(getattr(a, f)).tobytes() == np.asarray(getattr(b, f)).tobytes() for f in fields)
    # a batch of random groups (boxes, half side, candidates) against one call per group
    rng = np.random.default_rng(pseed)
    geo = IX._Geometry(sc, float(np.float32(cap)), index_slack(sc, 100.0), 1e-6, IX.NEGLIGIBLE_NATS / 100.0)
    lo, hi = geo.c.min(axis=0) - 1.0, geo.c.max(axis=0) + 1.0
    groups = []
    for _ in range(int(rng.integers(1, 9))):
        m = int(rng.integers(1, 9))
        cand = np.sort(rng.choice(sc.n_polys, int(rng.integers(0, sc.n_polys + 1)), replace=False))
        groups.append((rng.uniform(lo, hi, (m, 3)), float(rng.choice([0.0625, 0.25, 1.0])), cand))
    for (cen, half, cand), (x, y) in zip(groups, geo.listed_many(groups)):
        x1, y1 = geo.listed_many([(cen, half, cand)])[0]
        assert x.tobytes() == x1.tobytes() and y.tobytes() == y1.tobytes()
        assert x.shape == (len(cen), len(cand))
