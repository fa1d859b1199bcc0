"""The shield (firmware_app/src/polycc_shield.c, docs/barrier.md section 8): bit-exact host and
Cortex-M4 against the float32 mirror (polycc/onboard/shield.py), and its properties (hypothesis):
a certified plan is clear of every stored polytope by r + tube along the whole modelled path,
psi is never optimistic, invalid input is refused without NaN, the candidate meets its ECBF
half-space, and a vehicle at rest in free space is certified."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from polycc.onboard import barrier as B
from polycc.onboard import shield as S
from polycc.testing.bitexact import arm_or_skip, scene

PRM = [S.ShieldParams(), S.ShieldParams(kappa=30.0, radius=0.05, tube=0.02, k1=2.0, k0=1.0, v_max=1.0, n_lat=0,
                                        n_commit=3, n_steps=120, max_evals=4, tau=0.05, psi_cap=0.4, a_brake=3.96),
       S.ShieldParams(kappa=300.0, radius=0.0, tube=0.1, v_term=0.1, a_term=1.0, max_evals=32, h=0.02, n_steps=100,
                      psi_cap=0.15, a_brake=1.5)]


def _rows(sc, n: int, seed: int) -> np.ndarray:
    """States in the room, near faces (mm to dm), fast (up to 4 m/s), plus edge rows."""
    rng = np.random.default_rng(seed)
    m = sc.plane_matrix().astype(np.float64)
    cs = np.c_[sc.polys["cx"], sc.polys["cy"], sc.polys["cz"]].astype(np.float64)
    k = rng.integers(0, sc.n_polys, n)
    first, count = sc.polys["first"].astype(int), sc.polys["count"].astype(int)
    rows_m = m[first[k] + rng.integers(0, 1 << 30, n) % count[k]]
    face = cs[k] - ((cs[k] * rows_m[:, :3]).sum(1) - rows_m[:, 3])[:, None] * rows_m[:, :3]
    off = rows_m[:, :3] * 10.0 ** rng.uniform(-3, 0, (n, 1))
    p = np.where(rng.random((n, 1)) < 0.6, face + off, rng.uniform(-1, 11, (n, 3)) * [1, 1, 0.4])
    speed = rng.uniform(0, 4, (n, 1))
    toward = -rows_m[:, :3] * speed  # mostly flying at the face
    v = np.where(rng.random((n, 1)) < 0.5, toward, rng.normal(size=(n, 3)) * speed)
    a0 = rng.normal(size=(n, 3)) * rng.uniform(0, 4, (n, 1))
    u_app = v + rng.normal(size=(n, 3)) * 0.3
    u_d = np.where(rng.random((n, 1)) < 0.5, toward, rng.normal(size=(n, 3)) * 2)
    rows = np.c_[p, v, a0, u_app, u_d].astype(np.float32)
    edge = np.zeros((8, 15), np.float32)
    edge[:, :3] = rows[0, :3]
    edge[0, 0] = np.nan
    edge[1, 3] = np.inf
    edge[2, 6] = 101.0
    edge[3, 12] = -1e3
    edge[4, 0] = 1.0000001e5
    edge[5, :3] = cs[0]  # inside a polytope
    edge[6, :3] = [1e4, 0, 0]  # far away
    edge[7, 3:6] = [60.0, 0.0, 0.0]  # too fast to stop in the horizon
    return np.vstack([rows, edge])


def _assert_same(job: S.Job, out, last, k: int, what: str) -> None:
    from polycc.sim.shield_ffi import FLOAT_FIELDS, INT_FIELDS

    for f in FLOAT_FIELDS:
        a = np.asarray(getattr(job, f), np.float32).view(np.uint32).ravel()
        b = np.ascontiguousarray(out[f][k], np.float32).view(np.uint32).ravel()
        assert np.array_equal(a, b), f"{what} row {k}: {f} C {b} ref {a}"
    for f in INT_FIELDS:
        assert int(getattr(job, f)) == int(out[f][k]), f"{what} row {k}: {f} C {out[f][k]} ref {getattr(job, f)}"
    assert np.array_equal(job.x[job.n].view(np.uint32), np.asarray(last, np.float32).view(np.uint32)), what


@pytest.mark.parametrize("n", [pytest.param(600, marks=pytest.mark.slow), 120])
@pytest.mark.parametrize("name", ["hulls", "boxes"])
@pytest.mark.parametrize("pi", [0, 1, 2])
def test_host_bitexact(name, pi, n):
    from polycc.sim.kernel_ffi import HostScene
    from polycc.sim.shield_ffi import run_batch

    sc = scene(name)
    rows = _rows(sc, n, seed=100 + pi + (n == 600))
    out, last = run_batch(HostScene(sc), PRM[pi], rows)
    for k in range(len(rows)):
        _assert_same(S.run(sc, PRM[pi], *rows[k].reshape(5, 3)), out, last[k], k, f"host {name} params {pi}")
    fl = out["flags"]
    assert np.all(fl & S.DONE)
    for f in ("u_c", "psi", "grad", "min_c"):
        assert np.all(np.isfinite(out[f]))
    # every outcome occurs: the tests exercise every branch
    assert np.any(fl & S.CERTIFIED) and np.any(fl & S.BLOCKED) and np.any(fl & S.NO_STOP) and np.any(fl & S.INVALID)
    assert np.any(fl & S.ACTIVE) and np.any(out["evals"] > 2)
    if pi == 1:
        assert np.any(fl & S.EVAL_CAP)


@pytest.mark.arm
@pytest.mark.parametrize("name", ["hulls", "boxes"])
def test_arm_bitexact(name):
    arm_or_skip()
    from polycc.sim.kernel_ffi import HostScene
    from polycc.sim.shield_ffi import FLOAT_FIELDS, INT_FIELDS, arm_program, arm_run, run_batch

    sc = scene(name)
    elf = arm_program()
    for pi in (0, 1):
        rows = _rows(sc, 2000, seed=200 + pi)
        host, last = run_batch(HostScene(sc), PRM[pi], rows)
        arm = arm_run(elf, sc, PRM[pi], rows)
        for f in FLOAT_FIELDS + INT_FIELDS:
            a = np.ascontiguousarray(arm[f]).view(np.uint8)
            b = np.ascontiguousarray(host[f]).view(np.uint8)
            assert np.array_equal(a, b), f"ARM vs host {name}: {f}"
        assert np.array_equal(arm["x_last"].view(np.uint32), last.view(np.uint32))
        for k in range(0, len(rows), 97):  # and against the reference directly
            _assert_same(S.run(sc, PRM[pi], *rows[k].reshape(5, 3)), arm, arm["x_last"][k], k, f"ARM {name}")


vec = st.tuples(*[st.floats(-4, 4, allow_nan=False, width=32)] * 3)


@settings(max_examples=80, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(name=st.sampled_from(["hulls", "boxes"]), pi=st.sampled_from([0, 1, 2]), seed=st.integers(0, 2**31 - 1),
       v=vec, a0=vec, u_d=vec, dist=st.floats(1e-3, 2.0))
def test_certified_plan_is_clear_along_the_whole_path(name, pi, seed, v, a0, u_d, dist):
    """(S) of docs/barrier.md: h(x) >= r + tube at every model point of a certified plan, and on every
    chord between them; psi at the estimate is never optimistic."""
    sc = scene(name)
    prm = PRM[pi]
    rng = np.random.default_rng(seed)
    m = sc.plane_matrix().astype(np.float64)
    k = int(rng.integers(0, sc.n_polys))
    row = m[int(sc.polys["first"][k]) + int(rng.integers(0, int(sc.polys["count"][k])))]
    c = np.array([sc.polys[k][f] for f in ("cx", "cy", "cz")], np.float64)
    p = c - ((c @ row[:3]) - row[3]) * row[:3] + row[:3] * (dist + prm.radius)
    job = S.run(sc, prm, p, v, a0, v, u_d)
    assert job.flags & S.DONE
    if job.flags & S.INVALID:
        return
    h0 = B.exact_minmax(sc, np.asarray(p, np.float32).reshape(1, 3))[0]
    assert float(job.psi) + prm.radius <= h0, "psi optimistic at the estimate"
    if job.flags & S.CERTIFIED:
        x = job.x[: job.n + 1].astype(np.float64)
        mids = 0.5 * (x[1:] + x[:-1])
        h = B.exact_minmax(sc, np.vstack([x, mids]).astype(np.float32))
        need = prm.radius + prm.tube
        assert np.all(h >= need - 1e-6), f"certified plan comes within {need - h.min():.3g} m of the cover"
        assert job.min_c >= 0.0


@settings(max_examples=60, deadline=None)
@given(name=st.sampled_from(["hulls", "boxes"]), pi=st.sampled_from([0, 1, 2]), v=vec, u_d=vec,
       p=st.tuples(*[st.floats(-1, 11, width=32)] * 3))
def test_candidate_meets_its_ecbf_half_space(name, pi, v, u_d, p):
    sc = scene(name)
    prm = PRM[pi]
    job = S.plan(sc, prm, p, v, (0, 0, 0), v, u_d)
    if job.flags & S.INVALID:
        return
    q = prm.f32()
    g = job.grad.astype(np.float64)
    gv = g @ np.asarray(v, np.float64)
    b = gv - (float(q["k1"]) * gv + float(q["k0"]) * float(job.psi)) / float(q["k_v"])
    speed = float(np.linalg.norm(job.u_c.astype(np.float64)))
    assert speed <= float(q["v_max"]) * (1 + 1e-6)
    if not job.flags & S.INFEASIBLE:
        assert g @ job.u_c.astype(np.float64) >= b - 1e-5 * (1 + abs(b)), "candidate violates its half-space"
    if not job.flags & (S.ACTIVE | S.SATURATED):
        assert np.array_equal(job.u_c, np.asarray(u_d, np.float32)), "an inactive shield changes nothing"


@pytest.mark.parametrize("name", ["hulls", "boxes"])
def test_at_rest_in_free_space_is_certified_and_fast_at_a_wall_is_not(name):
    sc = scene(name)
    prm = S.ShieldParams()
    m = sc.plane_matrix().astype(np.float64)
    row = m[int(sc.polys["first"][0])]
    c = np.array([sc.polys[0][f] for f in ("cx", "cy", "cz")], np.float64)
    face = c - ((c @ row[:3]) - row[3]) * row[:3]
    outward = row[:3]
    far = face + outward * 1.0
    zero = (0.0, 0.0, 0.0)
    job = S.run(sc, prm, far, zero, zero, zero, zero)
    if B.exact_minmax(sc, far.astype(np.float32).reshape(1, 3))[0] > prm.radius + prm.tube + 0.01:
        assert job.flags & S.CERTIFIED, S.flag_names(job.flags)
    near = face + outward * (prm.radius + prm.tube + 0.05)
    fast = tuple(-outward * 3.0)
    job = S.run(sc, prm, near, fast, zero, fast, fast)
    assert not job.flags & S.CERTIFIED, "3 m/s at 5 cm from a face cannot be certified"
    u = S.command(job, prm, fast).astype(np.float64)
    vf = np.asarray(fast, np.float64)
    e = float(np.float32(prm.a_xy) / np.float32(prm.k_v))
    h = np.hypot(vf[0], vf[1])
    assert u[2] == 0.0 and np.linalg.norm((vf - u)[:2]) == pytest.approx(min(h, e), rel=1e-5), "the backup brakes"
    assert h == 0.0 or u[0] * vf[1] - u[1] * vf[0] == pytest.approx(0.0, abs=1e-5), "against the motion"


@settings(max_examples=60, deadline=None)
@given(name=st.sampled_from(["hulls", "boxes"]), cap=st.floats(0.01, 1.0),
       p=st.tuples(*[st.floats(-1, 11, width=32)] * 3), v=vec)
def test_psi_cap_is_a_flat_lower_bound(name, cap, p, v):
    """psi_cap: every psi the shield uses is min(psi, cap) with a zero gradient where capped, so it is
    never above the uncapped one (still certified) and the candidate is not shaped beyond the cap."""
    sc = scene(name)
    zero = (0.0, 0.0, 0.0)
    free = S.plan(sc, S.ShieldParams(), p, v, zero, v, v)
    capped = S.plan(sc, S.ShieldParams(psi_cap=cap), p, v, zero, v, v)
    if free.flags & S.INVALID:
        assert capped.flags & S.INVALID
        return
    c = np.float32(cap)
    assert capped.psi == min(free.psi, c)
    if free.psi > c:
        assert np.all(capped.grad == 0.0) and not capped.flags & S.ACTIVE
        assert np.array_equal(capped.u_c, capped.u_d)
    else:
        assert np.array_equal(capped.grad, free.grad)


@pytest.mark.parametrize("name", ["hulls", "boxes"])
def test_brake_model_never_saturates_and_stops(name):
    """The brake policy as modelled decelerates at most a_brake <= a_xy against the horizontal motion
    (inside the tilt limits in any direction) and reaches hover within the horizon from 3 m/s."""
    sc = scene(name)
    prm = S.ShieldParams()
    rng = np.random.default_rng(7)
    for _ in range(20):
        v = rng.normal(size=3)
        v = v / np.linalg.norm(v) * rng.uniform(0.1, 3.0)
        ub = S.brake(v, np.float32(prm.a_brake) / np.float32(prm.k_v))
        job = S.plan(sc, prm, (5.0, 5.0, 1.0), v, (0, 0, 0), ub, ub)
        assert not job.flags & S.NO_STOP, S.flag_names(job.flags)
        x = job.x[: job.n + 1].astype(np.float64)
        acc = np.diff(x, 2, axis=0) / prm.h**2
        assert np.all(np.hypot(acc[:, 0], acc[:, 1]) <= prm.a_brake * (1 + 1e-3) + 1e-3)


def test_invalid_params_are_refused():
    sc = scene("boxes")
    zero = (0.0, 0.0, 0.0)
    for bad in (dict(tau=0.001), dict(n_steps=0), dict(n_steps=201), dict(n_lat=150, n_commit=60), dict(max_evals=0),
                dict(max_evals=33), dict(kappa=0.5), dict(h=float("nan")), dict(v_max=0.0), dict(psi_cap=-0.1),
                dict(a_brake=4.0), dict(a_brake=0.0)):
        job = S.run(sc, S.ShieldParams(**bad), (5, 5, 1), zero, zero, zero, zero)
        assert job.flags == S.INVALID | S.DONE, bad
        assert np.array_equal(S.command(job), np.zeros(3, np.float32))
