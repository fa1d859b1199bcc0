"""Bit-exactness of the C kernel against the float32 Python reference (polycc/barrier.py).

Host: the C built by cffi with -O2 -ffp-contract=off, >= 1e5 random states per scene.
Cortex-M4: the same sources cross-compiled with the firmware flags, >= 1e4 states per scene
in qemu-system-arm -M netduinoplus2 (semihosting).  Outputs are compared as uint32 patterns.
"""

from __future__ import annotations

import numpy as np
import pytest

from polycc.onboard import barrier as B
from polycc.testing.bitexact import FIELDS, PARAMS, SCENES, arm_or_skip, assert_bitexact, edge_states, scene, states

N_HOST = 100_000  # 1e5 states, run in CI (slow)
N_HOST_QUICK = 30_000  # local default run
N_ARM = 10_000

@pytest.mark.parametrize("n", [pytest.param(N_HOST, marks=pytest.mark.slow), N_HOST_QUICK])
@pytest.mark.parametrize("name", SCENES)
def test_host_bitexact_random_states(name, n):
    from polycc.sim.kernel_ffi import HostScene, step_batch

    sc = scene(name)
    hs = HostScene(sc)
    x, goal = states(sc, n, seed=10 if n == N_HOST else 11)
    out = step_batch(hs, PARAMS[0], x, goal)
    assert_bitexact(B.step(sc, PARAMS[0], x, goal), out, f"host {name}")
    # the outputs are meaningful, not all flagged away
    assert np.mean(out["flags"] & B.FLAG_INVALID == 0) > 0.9
    assert np.mean(out["flags"] & B.FLAG_ACTIVE != 0) > 0.01


@pytest.mark.parametrize("name", SCENES)
@pytest.mark.parametrize("pi", [1, 2])
def test_host_bitexact_other_params(name, pi):
    from polycc.sim.kernel_ffi import HostScene, step_batch

    sc = scene(name)
    x, goal = states(sc, 20_000, seed=20 + pi)
    assert_bitexact(B.step(sc, PARAMS[pi], x, goal), step_batch(HostScene(sc), PARAMS[pi], x, goal), f"host {name}")


@pytest.mark.parametrize("name", SCENES)
def test_host_bitexact_edge_cases(name):
    from polycc.sim.kernel_ffi import HostScene, step_batch

    sc = scene(name)
    x, goal = edge_states(sc)
    out = step_batch(HostScene(sc), PARAMS[0], x, goal)
    assert_bitexact(B.step(sc, PARAMS[0], x, goal), out, f"host edge {name}")
    fl = out["flags"]
    for f in FIELDS:  # never NaN/Inf
        assert np.all(np.isfinite(out[f]))
    assert fl[4] & B.FLAG_INSIDE, "the centre of a polytope is inside"
    h = B.exact_minmax(sc, x[6:9])
    assert not np.any(fl[6:9] & (B.FLAG_INVALID | B.FLAG_INSIDE)), "1e4 m away is valid"
    assert np.all(out["psi"][6:9] + PARAMS[0].radius <= h) and np.all(out["psi"][6:9] > 0.99 * h), "and tight"
    assert not fl[9] & B.FLAG_INVALID and not fl[10] & B.FLAG_INVALID and fl[11] & B.FLAG_INVALID  # |x| <= 1e5 valid
    for i in (12, 13, 14, 17, 18, 19):  # NaN/Inf in x or goal, goal out of range
        assert fl[i] == B.FLAG_INVALID and not np.any(out["u"][i])
    assert np.all(out["u_nom"][0] == 0) and np.all(out["u_nom"][3] == 0), "at the goal u_nom = 0"
    assert np.all(out["u_nom"][16] == 0) and np.all(out["u_nom"][20] == 0)


def test_host_invalid_params_and_scene():
    from polycc.sim.kernel_ffi import HostScene, step_batch

    sc = scene("boxes")
    x, goal = states(sc, 100, seed=3)
    for bad in (B.Params(kappa=0.5), B.Params(kappa=float("nan")), B.Params(v_max=0.0), B.Params(beta=-1.0),
                B.Params(radius=float("inf"))):
        out = step_batch(HostScene(sc), bad, x, goal)
        assert_bitexact(B.step(sc, bad, x, goal), out, "bad params")
        assert np.all(out["flags"] == B.FLAG_INVALID) and not np.any(out["u"])
    out = step_batch(HostScene(sc, fmt=99), PARAMS[0], x, goal)
    assert np.all(out["flags"] == B.FLAG_INVALID), "a scene of another format is refused"


def test_host_empty_scene_is_safe():
    from polycc.sim.kernel_ffi import HostScene, step_batch

    sc = scene("boxes")
    empty = sc.without_polytopes()
    x, goal = states(sc, 1000, seed=4)
    out = step_batch(HostScene(empty), PARAMS[0], x, goal)
    assert_bitexact(B.step(empty, PARAMS[0], x, goal), out, "empty scene")
    assert np.all(out["flags"] & B.FLAG_ACTIVE == 0) and np.all(out["psi"] > 0)


@pytest.mark.arm
@pytest.mark.parametrize("name", SCENES)
@pytest.mark.parametrize("pi, n", [(0, N_ARM), (1, N_ARM), (2, N_ARM),
                                   pytest.param(0, N_HOST, marks=pytest.mark.slow)])
def test_arm_qemu_bitexact(name, pi, n):
    """>= 1e4 states (1e5 in CI) plus the edge cases, in qemu netduinoplus2 (Cortex-M4F)."""
    kernel_arm = arm_or_skip()
    sc = scene(name)
    x, goal = states(sc, n, seed=30 + pi + n)
    ex, eg = edge_states(sc)
    x, goal = np.vstack([ex, x]), np.vstack([eg, goal])
    out = kernel_arm.run_qemu(kernel_arm.test_program(), sc, PARAMS[pi], x, goal)
    assert len(out) == len(x)
    assert_bitexact(B.step(sc, PARAMS[pi], x, goal), out, f"cortex-m4 {name} params {pi}")
