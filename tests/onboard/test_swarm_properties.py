"""Properties of the neighbour terms (polycc/onboard/swarm.py, bit-exact with polycc_swarm.c),
docs/swarm.md: the certificate in exact rational arithmetic, the soft-min bound, the fair split
of a fresh report, the ageing buffer, and the table's input checks."""

from __future__ import annotations

from fractions import Fraction as Q

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from polycc.onboard import barrier as B
from polycc.onboard import swarm as SW
from polycc.testing.bitexact import scene

F = np.float32
coord = st.floats(-30.0, 30.0, width=32)
small = st.floats(0.0, 0.375, width=32)


def _q3(v):
    return [Q(float(a)) for a in np.asarray(v, np.float32)]


@settings(max_examples=400, deadline=None)
@given(p0=st.tuples(coord, coord, coord), dirn=st.tuples(st.floats(-1, 1), st.floats(-1, 1), st.floats(-1, 1)),
       dist=st.floats(1e-4, 8.0), r_i=small, r_j=small, age=st.integers(0, 3000), v=st.floats(0.0, 3.0, width=32),
       t=st.floats(0.0, 1.0), side=st.tuples(st.floats(-1, 1), st.floats(-1, 1), st.floats(-1, 1)),
       jitter=st.floats(-3.0, 3.0))
def test_neighbour_term_never_optimistic(p0, dirn, dist, r_i, r_j, age, v, t, side, jitter):
    """h_j(p) >= 0 implies |p - p_j| >= r_i + r_j + V tau (exactly: every position within V tau
    of the report is at least r_i + r_j away), for points p near the plane that matters."""
    d = np.asarray(dirn, np.float64)
    if np.linalg.norm(d) < 1e-3:
        d = np.array([1.0, 0.0, 0.0])
    d /= np.linalg.norm(d)
    p0 = np.asarray(p0, np.float64)
    pj = (p0 + dist * d).astype(F)
    sw = SW.Swarm()
    assert sw.report(3, pj, age, r_j, p0.astype(F)) == 0
    nb = sw.slots[0]
    rho = float(F(r_i)) + float(F(r_j))
    # points around both branches' planes, and along the segment
    h_fair = 0.5 * (float(nb.a) + float(nb.b) - rho)
    h_aged = float(nb.b) - rho - float(v) * age * 1e-3
    e = min(h_fair, h_aged)
    n = nb.n.astype(np.float64)
    base = p0 + t * (pj - p0) + np.asarray(side) * 0.3
    p = (base + (e - n @ base + jitter * 10.0 ** -np.clip(abs(jitter) * 3, 0, 7)) * n).astype(F)
    h, _ = SW.term(nb, r_i, v, p)
    if h >= 0:
        dp = [a - b for a, b in zip(_q3(p), _q3(pj))]
        need = Q(float(F(r_i))) + Q(float(F(r_j))) + Q(float(F(v))) * Q(age, 1000)
        assert sum(x * x for x in dp) >= need * need
    # |n| <= 1 exactly, b <= n . p_j exactly
    nn = _q3(nb.n)
    assert sum(x * x for x in nn) <= 1
    assert Q(float(nb.b)) <= sum(a * b for a, b in zip(nn, _q3(pj)))


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 10_000), k=st.integers(1, 16), v=st.floats(0.0, 2.0, width=32))
def test_combined_never_above_any_term(seed, k, v):
    """Psi <= min(psi_kernel, min_j h_j): Psi >= 0 implies every certificate."""
    rng = np.random.default_rng(seed)
    packed = scene("hulls")
    params = B.Params()
    x = rng.uniform(-1, 11, 3).astype(F) * np.array([1, 1, 0.4], F)
    sw = SW.Swarm()
    for i in range(k):
        sw.report(i, (x + rng.normal(size=3) * rng.uniform(0.05, 3)).astype(F), int(rng.integers(0, 600)),
                  float(rng.uniform(0, 0.2)), (x + rng.normal(size=3) * 0.01).astype(F))
    out = SW.step(packed, params, sw, v, x, rng.uniform(0, 10, 3))
    if out["flags"] & B.FLAG_INVALID:
        return
    psi_k = B.step(packed, params, x[None], np.zeros((1, 3), F))["psi"][0]
    terms = [SW.term(nb, params.radius, v, x)[0] for nb in sw.slots if nb is not None]
    assert out["psi"] <= min(psi_k, min(terms))
    assert bool(out["flags"] & B.FLAG_INSIDE) == bool(out["psi"] < 0)


@settings(max_examples=200, deadline=None)
@given(p0=st.tuples(coord, coord, coord), dist=st.floats(0.3, 6.0), r=st.floats(0.0, 0.125, width=32))
def test_fresh_report_is_the_buffered_bisector(p0, dist, r):
    """Age 0, equal radii: at the own position h = |p_j - p0|/2 - r (Eq. 7's buffered bisector)."""
    p0 = np.asarray(p0, F)
    pj = (p0 + np.array([dist, 0.3 * dist, -0.2 * dist])).astype(F)
    sw = SW.Swarm()
    sw.report(0, pj, 0, r, p0)
    h, ageing = SW.term(sw.slots[0], r, F(1.0), p0)
    D = float(np.linalg.norm(pj.astype(np.float64) - p0.astype(np.float64)))
    assert not ageing
    tol = 1e-5 * (np.abs(p0).sum() + np.abs(pj).sum() + 1.0)  # the rounding margins (2^-18 per metre of |p|_1)
    assert D / 2 - float(F(r)) - tol <= h <= D / 2 - float(F(r))


@settings(max_examples=200, deadline=None)
@given(p=st.tuples(coord, coord, coord), dist=st.floats(0.3, 4.0), dt=st.integers(1, 5000), v=st.floats(0.01, 2.0))
def test_ageing_only_shrinks_the_cell(p, dist, dt, v):
    p = np.asarray(p, F)
    pj = (p + np.array([0.0, dist, 0.0])).astype(F)
    sw = SW.Swarm()
    sw.report(0, pj, 0, 0.1, p)
    h0, _ = SW.term(sw.slots[0], 0.1, v, p)
    sw.age(dt)
    h1, ag = SW.term(sw.slots[0], 0.1, v, p)
    assert h1 <= h0
    if ag:  # the ageing branch: the buffer grew by V tau from the report
        assert h1 <= dist - 0.2 - float(F(v)) * dt * 1e-3 + 1e-4
    assert sw.stale(SW.TIMEOUT_MS) == (dt > SW.TIMEOUT_MS)


def test_table_refuses_bad_input_and_overflow():
    sw = SW.Swarm()
    x = np.zeros(3, F)
    assert sw.report(0, [np.nan, 0, 0], 0, 0.1, x) == -1
    assert sw.report(0, [1, 0, 0], 0, -0.1, x) == -1
    assert sw.report(0, [1, 0, 0], 0, 11.0, x) == -1
    assert sw.report(0, [2e5, 0, 0], 0, 0.1, x) == -1
    for i in range(SW.MAX):
        assert sw.report(i, [i + 1.0, 0, 0], 0, 0.1, x) == i
    assert sw.report(99, [1, 1, 1], 0, 0.1, x) == -1  # full
    assert sw.report(5, [1, 1, 1], 0, 0.1, x) == 5  # an update keeps its slot
    assert sw.count == SW.MAX
    assert sw.forget(5) and not sw.forget(5) and sw.count == SW.MAX - 1
    assert sw.report(99, [1, 1, 1], 0, 0.1, x) == 5  # the freed slot


def test_coincident_neighbour_is_inside():
    sw = SW.Swarm()
    x = np.array([1.0, 2.0, 1.0], F)
    sw.report(0, x, 0, 0.1, x)
    out = SW.step(scene("boxes"), B.Params(), sw, 1.0, x, x + 1)
    # no direction away is known: degenerate (the app holds position on INVALID as on INSIDE)
    assert out["flags"] == B.FLAG_INVALID | B.FLAG_DEGENERATE and not out["u"].any()
    sw.report(0, x + F(0.05), 0, 0.1, x)  # 8.7 cm apart, radii 0.1 + 0.1: inside, pushed apart
    out = SW.step(scene("boxes"), B.Params(), sw, 1.0, x, x)
    assert out["flags"] & B.FLAG_INSIDE and out["psi"] < 0 and out["u"] @ np.ones(3) < 0
