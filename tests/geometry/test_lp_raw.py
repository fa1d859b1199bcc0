"""polycc.geometry.lp_raw against scipy's linprog(method="highs"): the same status class and the same
solution, bit for bit (the Chebyshev centres of pack_scene feed the stored scene)."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.optimize import linprog

from polycc.geometry.halfplanes import chebyshev_centre
from polycc.geometry.lp_raw import linprog_highs

COST = np.array([0.0, 0.0, 0.0, -1.0])
LB = np.array([-np.inf, -np.inf, -np.inf, 0.0])
UB = np.full(4, np.inf)


def _bits(a):
    return np.asarray(a, np.float64).view(np.uint64)


def _same(A, b, c=COST, lb=LB, ub=UB):
    ref = linprog(c=c, A_ub=A, b_ub=b, bounds=list(zip(lb, ub)), method="highs")
    status, x, y = linprog_highs(c, A, b, lb, ub)
    assert (status == 0) == (ref.status == 0), (status, ref.status)
    if status == 0:
        assert np.array_equal(_bits(ref.x), _bits(x)), (ref.x, x)
        assert np.array_equal(_bits(ref.ineqlin.marginals), _bits(y)), (ref.ineqlin.marginals, y)
    return status


@settings(max_examples=300, deadline=None)
@given(st.integers(4, 40), st.integers(0, 2**32 - 1), st.sampled_from(["gauss", "lattice"]),
       st.floats(-0.5, 1.0))
def test_chebyshev_lp_is_linprogs_bit_for_bit(m, seed, kind, shift):
    rng = np.random.default_rng(seed)
    n = rng.normal(size=(m, 3))
    if kind == "lattice":  # exact zeros in the matrix (axis-aligned and diagonal normals)
        n = np.rint(n)
        n[np.all(n == 0, axis=1)] = (0.0, 0.0, 1.0)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    d = rng.normal(size=m) * 0.2 + shift  # some empty, some unbounded, most bounded
    _same(np.c_[n, np.linalg.norm(n, axis=1)], d)


@settings(max_examples=200, deadline=None)
@given(st.integers(4, 30), st.integers(0, 2**32 - 1), st.integers(0, 5), st.floats(0.0, 0.1))
def test_the_index_box_lp_is_linprogs_bit_for_bit(m, seed, axis, delta):
    """The grid box LP of polycc.onboard.index: max e . p over a polytope grown by delta, free bounds, whose
    marginals make the certificate."""
    rng = np.random.default_rng(seed)
    n = rng.normal(size=(m, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    d = rng.uniform(0.05, 1.0, size=m)
    e = np.zeros(3)
    e[axis % 3] = 1.0 if axis < 3 else -1.0
    _same(n, d + delta, -e, np.full(3, -np.inf), np.full(3, np.inf))


def test_all_three_outcomes_and_the_centre_of_a_box():
    box = np.array([[1, 0, 0, 1], [-1, 0, 0, 1], [0, 1, 0, 2], [0, -1, 0, 2], [0, 0, 1, 3], [0, 0, -1, 3.0]])
    assert _same(np.c_[box[:, :3], np.ones(6)], box[:, 3]) == 0
    c, r = chebyshev_centre(box)
    assert r == 1.0 and np.allclose(c[0], 0.0)
    empty = box.copy()
    empty[1, 3] = -2.0  # x <= 1 and x >= 2
    assert _same(np.c_[empty[:, :3], np.ones(6)], empty[:, 3]) != 0
    open_ = box[[0, 2, 3, 4, 5]]  # x unbounded below: the radius is still bounded (by y), the LP optimal
    assert _same(np.c_[open_[:, :3], np.ones(5)], open_[:, 3]) == 0
