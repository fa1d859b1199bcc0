"""SITL: the host-built app flown against vehicle models, bit-identical to the Python reference,
clearance to ground-truth ellipsoids and `polycc sim`."""

from __future__ import annotations

import math

import numpy as np
import pytest

from polycc.cli import main
from polycc.codegen.header import write_outputs
from polycc.geometry.halfplanes import axis_box
from polycc.onboard import barrier
from polycc.onboard.barrier import Params
from polycc.scene.ellipsoids import Ellipsoids
from polycc.sim.clearance import Clearance, densify, point_ellipsoid_distance
from polycc.sim.dynamics import CrazyflieLike, CrazyflieParams, SingleIntegrator
from polycc.sim.sitl import FlightConfig, Simulator, random_pairs

# Two walls with a 0.6 m gap at y in [-0.3, 0.3]; the flight goes through it along +x.
WALLS = [((0.0, -1.5, 0.0), (0.6, -0.3, 1.5)), ((0.0, 0.3, 0.0), (0.6, 1.5, 1.5))]
START, GOAL = (-1.2, 0.05, 0.7), (1.8, -0.05, 0.7)
SPLAT_SIGMA = 0.008  # m; the polytopes are the walls grown by 2.5 sigma


def wall_splats(rng, spacing=0.03) -> Ellipsoids:
    pts = []
    for lo, hi in WALLS:
        lo, hi = np.array(lo), np.array(hi)
        n = int(np.prod((hi - lo) / spacing + 1))
        p = rng.uniform(lo, hi, size=(n, 3))
        # snap one random coordinate to a face so the surfaces are dense
        ax = rng.integers(0, 3, n)
        side = rng.integers(0, 2, n)
        p[np.arange(n), ax] = np.where(side == 1, hi[ax], lo[ax])
        pts.append(p)
    c = np.concatenate(pts)
    n = len(c)
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    from polycc.scene.ellipsoids import quaternion_to_rotation

    sig = np.full((n, 3), SPLAT_SIGMA) * rng.uniform(0.3, 1.0, size=(n, 3))
    return Ellipsoids(c, quaternion_to_rotation(q), sig, k=1.0, opacity=np.ones(n, np.float32),
                      colors=np.full((n, 3), 128, np.uint8))


@pytest.fixture(scope="module")
def walls(tmp_path_factory):
    d = tmp_path_factory.mktemp("walls")
    grow = 2.5 * SPLAT_SIGMA
    write_outputs(d, [axis_box(np.array(lo) - grow, np.array(hi) + grow) for lo, hi in WALLS], {"kappa": 100.0})
    ell = wall_splats(np.random.default_rng(0))
    return d, ell


@pytest.fixture(scope="module")
def sim(walls):
    d, ell = walls
    return Simulator(d / "polytopes.h", ell)


def bits(a) -> np.ndarray:
    return np.ascontiguousarray(a, np.float32).view(np.uint32)


@pytest.mark.parametrize("dynamics", ["integrator", "crazyflie", "quadrotor"])
def test_same_code_bit_identical_to_reference(sim, dynamics):
    """Tick by tick, the app's kernel call equals polycc.onboard.barrier.step on the same state, goal and
    params (v_max including the braking term), and the app sends exactly that velocity."""
    cfg = FlightConfig(record_app_io=True, vmax=1.0, rate_hz=250)
    tr = sim.fly(START, GOAL, dynamics, cfg)
    io = tr.io
    assert np.all(io["status"] == 1), f"unexpected app statuses {np.unique(io['status'])}"
    assert np.array_equal(io["calls"], np.arange(1, len(io["calls"]) + 1))  # one kernel call per tick
    assert np.array_equal(bits(io["x_kernel"]), bits(io["x_seen"]))
    assert np.array_equal(bits(io["u"]), bits(io["out_u"]))
    n = len(io["calls"])
    assert n > 100
    base = cfg.params(sim.kappa)
    assert np.all(io["vmax"] <= np.float32(cfg.vmax))
    braked = 0
    for r in np.unique(io["vmax"]):
        sel = np.flatnonzero(io["vmax"] == r)
        braked += len(sel) if r != np.float32(cfg.vmax) else 0
        prm = Params(base.kappa, base.radius, base.beta, base.c_clf, float(r))
        ref = barrier.step(sim.packed, prm, io["x_kernel"][sel], io["goal"])
        for f, got in (("u", io["out_u"][sel]), ("psi", io["out_psi"][sel]), ("flags", io["out_flags"][sel])):
            a = ref[f].view(np.uint32) if f != "flags" else ref[f]
            b = bits(got) if f != "flags" else got
            bad = np.nonzero(np.any((a != b).reshape(len(sel), -1), axis=1))[0]
            assert len(bad) == 0, f"{f} differs at {len(bad)} of {len(sel)} ticks (v_max {r}), first {sel[bad[0]]}"
    # The filter and the braking term really worked on this flight (the gap needs them).
    assert np.count_nonzero(io["out_flags"] & barrier.FLAG_ACTIVE) > 10
    assert braked > 10


def test_brake_can_be_compiled_out(walls):
    d, _ = walls
    sim0 = Simulator(d / "polytopes.h", brake=False)
    assert sim0.app.brake_acc == 0.0 and Simulator(d / "polytopes.h").app.brake_acc == pytest.approx(3.9)
    tr = sim0.fly(START, GOAL, "crazyflie", FlightConfig(record_app_io=True, vmax=1.0))
    assert np.all(tr.io["vmax"] == np.float32(1.0)) and tr.success


def test_the_first_tick_of_an_engagement_is_braked_to_the_minimum(sim):
    """Regression: without a psi from the previous tick the braking term returned vmax, so every flight's first
    command was the unbraked go-to-goal velocity (1.5 m/s, 6 cm from a box, at vmax 2 m/s). Now the first tick
    flies at most POLYCC_APP_BRAKE_VMIN (0.05 m/s) and the next one is braked by the first tick's psi."""
    tr = sim.fly(START, GOAL, "quadrotor", FlightConfig(record_app_io=True, vmax=1.0, t_max_s=0.5))
    io = tr.io
    assert io["calls"][0] == 1 and io["vmax"][0] == np.float32(0.05)
    assert np.linalg.norm(io["u"][0]) <= 0.05 * (1 + 1e-6)
    assert io["vmax"][1] == np.float32(1.0)  # 1.2 m from the walls: the braking speed is above vmax


def test_the_shield_does_not_fly_a_jolt_at_the_start(walls):
    """Regression (bench/bench_shield.py, app_shield at 2 m/s): the shield flies each decision for one 10 ms
    period, and it flew the app's unbraked first command, an acceleration step of 110-145 m/s^3 from a start
    near a box where the app alone had 17. Start 6 cm (psi) from the wall's cover, goal diagonally past it."""
    d, ell = walls
    start, goal = (-0.27, -0.9, 0.7), (-0.9, 0.9, 1.4)
    jerk = {}
    for shield in (False, True):
        sim = Simulator(d / "polytopes.h", ell)
        cfg = FlightConfig(vmax=2.0, radius=0.2, clearance_radius=0.1, shield=shield, shield_radius=0.1, t_max_s=0.3)
        jerk[shield] = float(np.max(sim.fly(start, goal, "quadrotor", cfg).jerk[:20]))
    assert jerk[True] <= jerk[False] * 1.2 + 1.0, jerk


@pytest.mark.parametrize("dynamics", ["integrator", "crazyflie", "quadrotor"])
def test_flight_through_gap_is_clear(sim, dynamics):
    tr = sim.fly(START, GOAL, dynamics, FlightConfig(vmax=1.0))
    assert tr.success and tr.outcome == "goal"
    assert tr.collisions == 0 and tr.min_clearance_m > 0.0
    assert 0.95 <= tr.length_ratio < 1.3  # success is declared 5 cm before the goal
    assert tr.max_eval_us > 0 and set(tr.statuses) == {1}


def test_blocked_goal_gets_stuck_not_through(sim):
    # Goal behind the wall, straight through it: the filter stops the vehicle in front.
    tr = sim.fly((-1.0, -0.9, 0.7), (1.6, -0.9, 0.7), "integrator", FlightConfig(vmax=1.0, t_max_s=15.0))
    assert not tr.success and tr.collisions == 0 and tr.min_clearance_m > 0.0
    assert tr.positions[:, 0].max() < 0.0


def test_exact_ellipsoid_distance():
    rng = np.random.default_rng(1)
    a = rng.uniform(0.01, 0.5, size=(200, 3))
    y = rng.normal(size=(200, 3))
    d = point_ellipsoid_distance(y, a)
    # Dense surface samples: the exact distance is never above, and close to, the sampled one.
    u = rng.normal(size=(20000, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    for i in range(0, 200, 20):
        surf = u * a[i]
        ds = np.linalg.norm(surf - y[i], axis=1).min()
        assert d[i] <= ds + 1e-12
        assert ds - d[i] < 0.02 * a[i].max()
    # Inside and on the surface.
    assert point_ellipsoid_distance(np.array([[0.0, 0.0, 0.0]]), np.array([[1.0, 2.0, 3.0]]))[0] == 0.0
    np.testing.assert_allclose(point_ellipsoid_distance(np.array([[0.0, 5.0, 0.0]]), np.array([[1.0, 2.0, 3.0]])), 3.0)


def test_clearance_matches_brute_force(walls):
    _, ell = walls
    cl = Clearance(ell)
    rng = np.random.default_rng(2)
    P = rng.uniform([-0.5, -0.6, 0.0], [1.0, 0.6, 1.6], size=(16, 3))
    P[:4] = [[0.3, -0.3, 0.7], [0.3, 0.29, 0.5], [-0.05, 0.0, 0.7], [0.61, 0.9, 1.0]]  # near and inside walls
    mn, events, dist = cl.evaluate(P, radius=0.05)
    y = np.einsum("nji,mnj->mni", ell.rotations, P[:, None, :] - ell.centers[None])
    brute = np.array([point_ellipsoid_distance(y[m], ell.sigmas * ell.k).min() for m in range(len(P))])
    lb, ub = cl.bounds(P)
    assert np.all(lb <= brute + 1e-12) and np.all(brute <= ub + 1e-12)
    exact = lb <= max(ub.min(), 0.05)
    np.testing.assert_allclose(dist[exact], brute[exact], rtol=0, atol=1e-12)
    assert mn == pytest.approx(brute.min() - 0.05, abs=1e-12)
    assert events == int(np.count_nonzero(np.diff(np.r_[0, (brute < 0.05).astype(int)]) == 1))


def test_densify_spacing():
    P = np.array([[0.0, 0, 0], [0.1, 0, 0], [0.1, 0.0011, 0]])
    D = densify(P, 0.0025)
    assert np.all(np.linalg.norm(np.diff(D, axis=0), axis=1) <= 0.0025 + 1e-15)
    np.testing.assert_array_equal(D[0], P[0])
    np.testing.assert_array_equal(D[-1], P[-1])


def test_crazyflie_model_limits_and_delay():
    prm = CrazyflieParams()
    m = CrazyflieLike(prm)
    m.reset((0.0, 0.0, 1.0))
    hist, acc = [], []
    for _ in range(3000):
        m.step((2.0, 0.0, 1.5), 0.001)
        hist.append(m.p.copy())
        acc.append(m.a.copy())
    acc = np.array(acc)
    assert np.abs(acc[:, 0]).max() <= 9.81 * math.tan(math.radians(prm.tilt_max_deg)) + 1e-9
    assert acc[:, 2].max() <= prm.az_max + 1e-9
    # horizontally the loop settles where its gain balances the effective drag (calibrated on the real firmware)
    assert m.v[0] == pytest.approx(2.0 * prm.k_xy / (prm.k_xy + prm.drag_xy), abs=0.02)
    assert m.v[2] == pytest.approx(1.5, abs=0.02)
    np.testing.assert_allclose(m.estimate()[0], hist[-1 - int(round(prm.delay_s / 0.001))], atol=1e-12)
    # The integrator is exact for a held setpoint.
    s = SingleIntegrator()
    s.reset((0, 0, 0))
    s.step((1.0, -2.0, 0.5), 0.01)
    np.testing.assert_allclose(s.p, [0.01, -0.02, 0.005])


def test_random_pairs_protocol(sim):
    prm = FlightConfig().params(sim.kappa)
    pairs = random_pairs(sim.packed, prm, (-1.5, -1.5, 0.2), (2.0, 1.5, 1.4), 10, 1.5, seed=3)
    assert len(pairs) == 10
    pts = np.array([p for pair in pairs for p in pair])
    psi, _, flags = barrier.barrier(sim.packed, prm, pts.astype(np.float32))
    assert np.all(flags == 0) and np.all(psi >= 0.05)
    assert all(np.linalg.norm(g - s) >= 1.5 for s, g in pairs)
    again = random_pairs(sim.packed, prm, (-1.5, -1.5, 0.2), (2.0, 1.5, 1.4), 10, 1.5, seed=3)
    assert all(np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1]) for a, b in zip(pairs, again))


def test_sim_command(walls, tmp_path, capsys):
    from polycc.scene.writers import write_gaussian_ply

    d, ell = walls
    ply = tmp_path / "walls.ply"
    write_gaussian_ply(ply, ell)
    rc = main(["sim", str(d), "--scene", str(ply), "--start=" + ",".join(map(str, START)),
               "--goal=" + ",".join(map(str, GOAL)), "--dynamics", "crazyflie", "--vmax", "1", "--trials", "2",
               "--plot", str(tmp_path / "t.png")])
    out = capsys.readouterr().out
    assert rc == 0, out
    assert "collisions: 0" in out and "success 2/2" in out
    assert (tmp_path / "t.png").stat().st_size > 10_000
    rc = main(["sim", str(d), "--scene", str(ply), "--random-pairs", "3", "--min-distance", "1.0", "--rate-hz", "100",
               "--plot", str(tmp_path / "r.png")])
    out = capsys.readouterr().out
    assert rc == 0 and "3 trials" in out and "collisions: 0" in out
    assert main(["sim", str(tmp_path), "--scene", str(ply)]) == 2  # no polytopes.h there
    assert main(["sim", str(d), "--scene", str(ply), "--rate-hz", "5", "--start", "0,0,1", "--goal", "1,1,1"]) == 2


def test_sim_command_reports_the_shield_decision_rate(walls, tmp_path, capsys):
    """The summary names the shield's decisions per flown second (100 Hz planned), and sim.json keeps it; a
    starved real-firmware app made about half of them and its late decisions were flown as brakes, which the
    summary now warns about instead of leaving a bare "stuck"."""
    import json

    from polycc.scene.writers import write_gaussian_ply

    d, ell = walls
    ply = tmp_path / "walls.ply"
    write_gaussian_ply(ply, ell)
    rc = main(["sim", str(d), "--scene", str(ply), "--start=" + ",".join(map(str, START)),
               "--goal=" + ",".join(map(str, GOAL)), "--vmax", "1", "--shield", "--plot", str(tmp_path / "t.png")])
    out = capsys.readouterr().out
    assert rc == 0, out
    sh = json.loads((d / "sim.json").read_text())["shield"]
    assert 95 <= sh["decisions_per_s"] <= 105, sh
    assert f"{sh['decisions_per_s']:.0f} decisions per flown second (it plans at 100 Hz)" in out, out
    assert "did not get its CPU time" not in out
