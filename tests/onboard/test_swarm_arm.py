"""Bit-exactness of polycc_swarm.c on the Cortex-M4 (firmware ARM flags, qemu netduinoplus2) against the
float32 reference polycc/onboard/swarm.py: random neighbour tables of 1..16 entries, fresh and ageing."""

from __future__ import annotations

import numpy as np
import pytest

from polycc.onboard import swarm as SW
from polycc.testing.bitexact import PARAMS, arm_or_skip, scene, states

FIELDS = ("u", "u_nom", "psi", "grad", "flags")


@pytest.mark.arm
@pytest.mark.parametrize("name", ["hulls", "boxes"])
def test_arm_bitexact_swarm_step(name):
    arm_or_skip()
    from polycc.sim import swarm_arm

    packed = scene(name)
    x_all, goal_all = states(packed, 300, seed=40)
    rng = np.random.default_rng(41)
    cases = []
    for x, goal in zip(x_all, goal_all):
        sw = SW.Swarm()
        for j in range(int(rng.integers(1, SW.MAX + 1))):
            pj = (x + rng.normal(size=3) * 10.0 ** rng.uniform(-2, 0.7)).astype(np.float32)
            sw.report(j, pj, int(rng.integers(0, 600)), float(np.float32(rng.uniform(0, 0.3))),
                      (x + rng.normal(size=3) * 1e-2).astype(np.float32))
        cases.append((x, goal, sw))
    out = swarm_arm.run_qemu(swarm_arm.test_program(), packed, PARAMS[0], 1.0, cases)
    assert len(out) == len(cases)
    for (x, goal, sw), o in zip(cases, out):
        want = SW.step(packed, PARAMS[0], sw, 1.0, x, goal)
        for f in FIELDS:
            w = np.asarray(want[f])
            assert np.array_equal(np.asarray(o[f]).astype(w.dtype).view(np.uint32), w.view(np.uint32)), (f, x)
