"""Bit-exactness of ``polycc_swarm.c`` (host cffi, -O2 -ffp-contract=off) against the float32
reference ``polycc/onboard/swarm.py``: random neighbour tables (0..16 entries, fresh and ageing
reports, coincident and far neighbours), states in the bit-exactness scenes; uint32 patterns."""

from __future__ import annotations

import numpy as np
import pytest

from polycc.onboard import swarm as SW
from polycc.testing.bitexact import PARAMS, scene, states

FIELDS = ("u", "u_nom", "psi", "grad", "flags")


def _bits(v) -> np.ndarray:
    a = np.asarray(v)
    return a.astype(np.float32).view(np.uint32) if a.dtype != np.uint32 else a


def random_case(rng, x):
    """Reports (id, p_j, age_ms, r_j, p0) and ageing steps, applied in order to both tables."""
    ops = []
    k = int(rng.integers(0, SW.MAX + 3))  # more than the table holds: the extra ones are refused
    for i in range(k):
        kind = rng.random()
        if kind < 0.05:
            pj = x.copy()  # coincident
        elif kind < 0.1:
            pj = x + rng.normal(size=3) * 1e-7
        else:
            pj = x + rng.normal(size=3) * 10.0 ** rng.uniform(-2, 1)
        p0 = x + rng.normal(size=3) * 10.0 ** rng.uniform(-4, -1)
        ops.append(("report", int(rng.integers(0, 20)), pj.astype(np.float32), int(rng.integers(0, 400)),
                    float(np.float32(rng.uniform(0.0, 0.3))), p0.astype(np.float32)))
        if rng.random() < 0.3:
            ops.append(("age", int(rng.integers(1, 200))))
        if rng.random() < 0.1:
            ops.append(("forget", int(rng.integers(0, 20))))
    if rng.random() < 0.2:
        ops.append(("report", 1, np.full(3, np.nan, np.float32), 0, 0.1, x))  # refused
    return ops


def apply(ops, ref: SW.Swarm, mod, csw):
    from polycc.sim.swarm_ffi import f3

    for op in ops:
        if op[0] == "report":
            _, nid, pj, age, rj, p0 = op
            k_ref = ref.report(nid, pj, age, rj, p0)
            k_c = mod.lib.polycc_swarm_report(csw, nid, f3(pj), age, float(np.float32(rj)), f3(p0))
            assert k_ref == k_c
        elif op[0] == "forget":
            assert ref.forget(op[1]) == bool(mod.lib.polycc_swarm_forget(csw, op[1]))
        else:
            ref.age(op[1])
            mod.lib.polycc_swarm_age(csw, op[1])
    assert ref.count == csw.count


@pytest.mark.parametrize("name", ["hulls", "boxes"])
@pytest.mark.parametrize("pi", [0, 1, 2])
def test_host_bitexact_swarm_step(name, pi):
    from polycc.sim import swarm_ffi

    mod = swarm_ffi.load()
    packed = scene(name)
    hs = swarm_ffi.SwarmScene(packed)
    params = PARAMS[pi]
    rng = np.random.default_rng(100 + pi)
    x_all, goal_all = states(packed, 160, seed=20 + pi)
    active = inside = ageing_seen = 0
    for x, goal in zip(x_all, goal_all):
        ref = SW.Swarm()
        csw = mod.ffi.new("polycc_swarm_t *")
        apply(random_case(rng, x.astype(np.float64)), ref, mod, csw)
        v = float(np.float32(rng.choice([0.0, 0.5, 1.0, 3.0])))
        a = SW.step(packed, params, ref, v, x, goal)
        c = swarm_ffi.step(hs, params, csw, v, x, goal)
        for f in FIELDS:
            assert np.array_equal(_bits(a[f]), _bits(c[f])), (f, name, x, a, c)
        active += bool(a["flags"] & 1)
        inside += bool(a["flags"] & 2)
        for nb in ref.slots:
            if nb is not None:
                ageing_seen += SW.term(nb, params.radius, v, x)[1]
    # the cases exercise the filter, the inside flag and the ageing branch
    assert active > 8 and inside > 8 and ageing_seen > 8


def test_empty_table_is_the_kernel_step():
    from polycc.sim import kernel_ffi, swarm_ffi

    packed = scene("hulls")
    hs = swarm_ffi.SwarmScene(packed)
    x, goal = states(packed, 300, seed=5)
    want = kernel_ffi.step_batch(kernel_ffi.HostScene(packed), PARAMS[0], x, goal)
    csw = swarm_ffi.load().ffi.new("polycc_swarm_t *")
    for i in range(len(x)):
        got = swarm_ffi.step(hs, PARAMS[0], csw, 1.0, x[i], goal[i])
        for f in FIELDS:
            assert np.array_equal(_bits(got[f]), _bits(want[f][i])), f
