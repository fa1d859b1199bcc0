"""Hypothesis tests of every certified property of the barrier kernel (docs/barrier.md).

The C kernel (host build) is exercised directly; bit-exactness with the Python reference
is asserted alongside, so the properties hold for both.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from polycc.onboard import barrier as B
from polycc.testing import synthetic

kffi = pytest.importorskip("polycc.sim.kernel_ffi")


@lru_cache(maxsize=64)
def small_scene(seed: int, n: int, boxes: bool):
    sc = synthetic.small_scene(seed, n, boxes)
    return sc, kffi.HostScene(sc)


scenes = st.builds(small_scene, st.integers(0, 10_000), st.integers(1, 7), st.booleans())
kappas = st.sampled_from([1.0, 10.0, 30.0, 100.0, 300.0, 1000.0, 1.0e4])


def sample_points(sc, seed: int, n: int, scale: float) -> np.ndarray:
    """Uniform points, points on/near faces, edges and vertices (mm..cm), and far points."""
    rng = np.random.default_rng(seed)
    m = sc.plane_matrix().astype(np.float64)
    c = np.c_[sc.polys["cx"], sc.polys["cy"], sc.polys["cz"]].astype(np.float64)
    k = rng.integers(0, sc.n_polys, n)
    first, count = sc.polys["first"].astype(int), sc.polys["count"].astype(int)
    rows = m[first[k] + rng.integers(0, 1 << 30, n) % count[k]]
    face = c[k] - ((c[k] * rows[:, :3]).sum(1) - rows[:, 3])[:, None] * rows[:, :3]
    near = face + rng.normal(size=(n, 3)) * 10.0 ** rng.uniform(-6, -1, (n, 1))
    uni = rng.uniform(-1, 5, (n, 3))
    far = rng.normal(size=(n, 3)) * scale
    return np.vstack([near, uni, far]).astype(np.float32)


def run(hs, params, x, goal=None):
    goal = np.zeros_like(x) if goal is None else goal
    out = kffi.step_batch(hs, params, x, goal)
    ref = B.step(hs.packed, params, x, goal)
    for f in ("psi", "grad", "u", "u_nom"):
        assert np.array_equal(np.asarray(ref[f]).view(np.uint32), np.ascontiguousarray(out[f]).view(np.uint32)), f
    return out


@settings(max_examples=60)
@given(scenes, kappas, st.floats(0.0, 1.0), st.integers(0, 2**31), st.sampled_from([1.0, 100.0, 1e4, 3e4]))
def test_never_optimistic(scene, kappa, radius, seed, scale):
    """psi + r <= min_k max_l (n.p - d), right side in float64, for every state."""
    sc, hs = scene
    params = B.Params(kappa=kappa, radius=radius)
    x = sample_points(sc, seed, 300, scale)
    out = run(hs, params, x)
    ok = out["flags"] & B.FLAG_INVALID == 0
    assert ok.mean() > 0.6
    lhs = out["psi"][ok].astype(np.float64) + float(np.float32(radius))
    rhs = B.exact_minmax(sc, x[ok])
    worst = np.argmax(lhs - rhs)
    assert np.all(lhs <= rhs), f"optimistic by {lhs[worst] - rhs[worst]:.3g} m at {x[ok][worst]}"


@settings(max_examples=40)
@given(scenes, st.sampled_from([10.0, 30.0, 100.0, 300.0]), st.integers(0, 2**31))
def test_gradient_matches_finite_differences(scene, kappa, seed):
    sc, hs = scene
    params = B.Params(kappa=kappa, radius=0.0)
    rng = np.random.default_rng(seed)
    x = rng.uniform(-1, 5, (200, 3))
    h = 0.02 / kappa
    g = run(hs, params, x.astype(np.float32))["grad"].astype(np.float64)
    fd = np.zeros_like(g)
    for i in range(3):
        e = np.zeros(3)
        e[i] = h
        fd[:, i] = (run(hs, params, (x + e).astype(np.float32))["psi"].astype(np.float64)
                    - run(hs, params, (x - e).astype(np.float32))["psi"].astype(np.float64))
        # divide by the step actually taken in float32
        fd[:, i] /= (x + e).astype(np.float32)[:, i].astype(np.float64) - (x - e).astype(np.float32)[:, i]
    err = np.linalg.norm(fd - g, axis=1)
    # float32 noise of psi (|psi| <= ~10 m, ulp <= 1e-6) over 2h, plus the O(kappa h^2) curvature term
    tol = 4e-6 * (1 + np.abs(x).sum(1)) / h + 0.05 * (1 + np.linalg.norm(g, axis=1))
    assert np.all(err <= tol), f"max gradient error {err.max():.3g} (tol {tol[np.argmax(err - tol)]:.3g})"


@settings(max_examples=30)
@given(scenes, kappas, st.integers(0, 2**31))
def test_continuous_along_segments(scene, kappa, seed):
    """psi changes by at most (|grad| bound) * step + float32 noise along fine segments,
    across culling and negligible-term boundaries."""
    sc, hs = scene
    params = B.Params(kappa=kappa, radius=0.0)
    rng = np.random.default_rng(seed)
    a, b = rng.uniform(-2, 6, 3), rng.uniform(-2, 6, 3)
    t = np.linspace(0, 1, 4001)[:, None]
    x = (a + t * (b - a)).astype(np.float32)
    out = run(hs, params, x)
    psi, g = out["psi"].astype(np.float64), np.linalg.norm(out["grad"], axis=1)
    dx = np.linalg.norm(np.diff(x.astype(np.float64), axis=0), axis=1)
    # |grad a_k| <= 1 + 2 (L-1)/e (docs/barrier.md), and the soft-min is a convex combination
    lip = 1.0 + 2.0 * np.exp(float(sc.log_lmax)) / np.e
    jump = np.abs(np.diff(psi))
    assert np.all(jump <= lip * dx + 2e-6), f"jump {jump.max():.3g} over {dx.max():.3g} m"
    assert np.all(g <= lip + 1e-3)


def test_tight_in_open_space():
    """Mean bias (true minus psi) in open space at kappa = 100 is below 1 cm."""
    biases = []
    for seed in range(6):
        sc, hs = small_scene(seed, 7, seed % 2 == 0)
        x = np.random.default_rng(seed).uniform(-1, 5, (20_000, 3)).astype(np.float32)
        out = run(hs, B.Params(kappa=100.0, radius=0.0), x)
        h = B.exact_minmax(sc, x)
        free = h > 0
        bias = h[free] - out["psi"][free].astype(np.float64)
        assert np.all(bias >= 0)
        biases.append(bias.mean())
    assert max(biases) <= 0.01, f"mean open-space bias per scene {biases}"


@settings(max_examples=40)
@given(scenes, kappas, st.integers(0, 2**31), st.sampled_from([1.0, 100.0, 1e4]))
def test_culling_is_certified_and_invisible(scene, kappa, seed, scale):
    """Culling (bounding-sphere test and early abort) changes psi by at most
    K exp(-17) / kappa (plus float32 rounding), and never makes it optimistic."""
    sc, hs = scene
    params = B.Params(kappa=kappa, radius=0.0)
    x = sample_points(sc, seed, 200, scale)
    psi_c, g_c, fl_c = B.barrier(sc, params, x)
    psi_n, g_n, fl_n = B.barrier(sc, params, x, cull=False)
    assert np.array_equal(fl_c, fl_n)
    ok = fl_c == 0
    bound = sc.n_polys * np.exp(-17.0) / kappa + 4e-7 * (1 + np.abs(psi_n[ok].astype(np.float64)))
    diff = psi_c[ok].astype(np.float64) - psi_n[ok].astype(np.float64)
    assert np.all(np.abs(diff) <= bound), f"culling moved psi by {np.abs(diff).max():.3g}"
    assert np.all(psi_c[ok].astype(np.float64) <= B.exact_minmax(sc, x[ok]))


@settings(max_examples=40)
@given(scenes, st.integers(0, 2**31))
def test_layout_culling_bounds_hold(scene, seed):
    """For every polytope: gamma (|p - c| - r_out) <= max_l g_l(p) <= |p - c| - r_in."""
    sc, _ = scene
    x = sample_points(sc, seed, 200, 50.0).astype(np.float64)
    for k, h in enumerate(sc.polytopes()):
        h = h.astype(np.float64)
        P = sc.polys[k]
        c = np.array([P["cx"], P["cy"], P["cz"]], np.float64)
        phi = np.max(x @ h[:, :3].T - h[:, 3], axis=1)
        r = np.linalg.norm(x - c, axis=1)
        assert np.all(phi >= (r - float(P["r_out"])) / float(P["inv_gamma"]) - 1e-12 * (1 + r))
        assert np.all(phi <= r - float(P["r_in"]) + 1e-12 * (1 + r))


@settings(max_examples=60)
@given(scenes, st.floats(0.1, 5.0), st.floats(0.0, 3.0), st.floats(0.05, 2.0), st.integers(0, 2**31))
def test_filter_is_the_qp_solution(scene, beta, c_clf, v_max, seed):
    sc, hs = scene
    params = B.Params(kappa=100.0, radius=0.05, beta=beta, c_clf=c_clf, v_max=v_max)
    rng = np.random.default_rng(seed)
    x = sample_points(sc, seed, 100, 3.0)
    goal = rng.uniform(-1, 5, x.shape).astype(np.float32)
    out = run(hs, params, x, goal)
    ok = out["flags"] & B.FLAG_INVALID == 0
    u, un, g, psi, fl = (np.asarray(out[f], np.float64)[ok] for f in ("u", "u_nom", "grad", "psi", "flags"))
    fl = out["flags"][ok]
    vm = float(np.float32(v_max))
    assert np.all(np.linalg.norm(un, axis=1) <= vm * (1 + 1e-6))
    assert np.all(np.linalg.norm(u, axis=1) <= vm * (1 + 1e-6))
    tol = 1e-5 * (1 + np.abs(psi) * beta + np.linalg.norm(g, axis=1) * np.linalg.norm(un, axis=1))
    lhs = (g * u).sum(1) + float(np.float32(beta)) * psi
    safe = psi >= 0
    assert np.all(lhs[safe] >= -tol[safe]), "the CBF constraint holds whenever psi >= 0"
    inactive = fl & B.FLAG_ACTIVE == 0
    assert np.array_equal(u[inactive], un[inactive])
    act = ~inactive & (fl & B.FLAG_SATURATED == 0)
    # active, unsaturated: u - u_nom is parallel to grad psi and the constraint is tight
    cross = np.linalg.norm(np.cross(u[act] - un[act], g[act]), axis=1)
    assert np.all(cross <= 1e-5 * (1 + np.linalg.norm(u[act] - un[act], axis=1)))
    assert np.all(np.abs(lhs[act]) <= tol[act])
    # the nominal controller is -c/2 (x - goal), saturated
    e = (x[ok].astype(np.float64) - goal[ok]) * (-0.5 * float(np.float32(c_clf)))
    sat = fl & B.FLAG_SATURATED != 0
    assert np.allclose(un[~sat], e[~sat], rtol=1e-5, atol=1e-6)


special = st.sampled_from([np.nan, np.inf, -np.inf, 0.0, -0.0, 1e5, -1e5, 1.0000001e5, 1e30, -1e-45, 3.0])
coords = st.one_of(special, st.floats(allow_nan=True, allow_infinity=True, width=32))


@settings(max_examples=200)
@given(scenes, st.lists(coords, min_size=3, max_size=3), st.lists(coords, min_size=3, max_size=3),
       st.lists(st.one_of(special, st.floats(-10, 1e5, width=32)), min_size=5, max_size=5))
def test_never_nan_and_invalid_is_zero(scene, x, goal, prm):
    sc, hs = scene
    params = B.Params(*prm)
    out = run(hs, params, np.array([x], np.float32), np.array([goal], np.float32))
    for f in ("u", "u_nom", "psi", "grad"):
        assert np.all(np.isfinite(out[f]))
    if out["flags"][0] & B.FLAG_INVALID:
        assert not np.any(out["u"]) and not np.any(out["u_nom"]) and out["psi"][0] == 0
    bad_input = not (np.all(np.abs(np.float32(x)) <= 1e5) and np.all(np.abs(np.float32(goal)) <= 1e5)
                     and params.valid())
    if bad_input:
        assert out["flags"][0] == B.FLAG_INVALID


@settings(max_examples=300)
@given(st.floats(-200.0, 88.0, width=32))
def test_exp_sign_and_bit_parity(x):
    from polycc.onboard.fastmath import exp32

    y = kffi.load().lib.polycc_exp(x)
    assert y >= 0.0 and np.float32(y) == exp32(np.float32(x))
    if x == 0.0:
        assert y == 1.0


@settings(max_examples=300)
@given(st.floats(1.0, 3.4028234663852886e38, width=32))
def test_log_nonnegative_above_one(x):
    from polycc.onboard.fastmath import log32

    y = kffi.load().lib.polycc_log(x)
    assert y >= 0.0 and np.float32(y) == log32(np.float32(x))
    if x == 1.0:
        assert y == 0.0
