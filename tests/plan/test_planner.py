"""The planner on the certified free space: certified waypoints, near-shortest paths, the reasons
for no path, the plan file, and flights that get through where the plain CLF + CBF gets stuck."""

from __future__ import annotations

import json

import numpy as np
import pytest

from polycc.codegen.header import write_outputs
from polycc.errors import PolyccError
from polycc.geometry.halfplanes import axis_box
from polycc.onboard.barrier import Params, barrier
from polycc.onboard.layout import scene_from_bytes
from polycc.plan import FreeSpace, NavMap, NoPathError, plan_path, read_plan
from polycc.plan.certified import LIP
from polycc.sim.sitl import FlightConfig, Simulator

# Two walls with a 0.56 m gap at y in [-0.28, 0.28] (as tests/sim/test_sitl.py), and a closed box
# shell (inner 0.6 m cube at x in [1.5, 2.1]) to enclose a goal.
WALLS = [((0.0, -1.5, 0.0), (0.6, -0.28, 1.5)), ((0.0, 0.28, 0.0), (0.6, 1.5, 1.5))]
SHELL_LO, SHELL_HI, T = np.array([1.5, -1.3, 0.3]), np.array([2.1, -0.7, 0.9]), 0.05
BOUNDS = (np.array([-1.5, -1.8, 0.0]), np.array([2.6, 1.8, 1.5]))
BLOCKED = ((-1.0, -0.9, 0.7), (1.1, -0.9, 0.7))  # straight through the lower wall
MARGIN = 0.05


def shell():
    lo, hi = SHELL_LO - T, SHELL_HI + T
    out = []
    for a in range(3):
        for side in (0, 1):
            blo, bhi = lo.copy(), hi.copy()
            if side == 0:
                bhi[a] = SHELL_LO[a]
            else:
                blo[a] = SHELL_HI[a]
            out.append(axis_box(blo, bhi))
    return out


@pytest.fixture(scope="module")
def build(tmp_path_factory):
    d = tmp_path_factory.mktemp("walls_plan")
    write_outputs(d, [axis_box(lo, hi) for lo, hi in WALLS] + shell(), {"kappa": 100.0})
    return d


@pytest.fixture(scope="module")
def nav(build):
    return NavMap.from_build(build, radius=0.1, margin=MARGIN, spacing=0.05, bounds=BOUNDS)


def ref_psi(nav, p):
    psi, _, flags = barrier(nav.packed, Params(kappa=nav.kappa, radius=nav.radius), np.asarray(p, np.float32))
    assert np.all(flags == 0)
    return psi.astype(np.float64)


def dense(a, b, step=0.005):
    k = max(2, int(np.ceil(np.linalg.norm(b - a) / step)) + 1)
    return a + np.linspace(0, 1, k)[:, None] * (b - a)


def test_straight_line_when_it_is_certified(nav):
    p = nav.plan((-1.0, 0.0, 0.7), (1.5, 0.0, 0.7))  # through the gap, on its centre line
    assert len(p.waypoints) == 2 and p.length_m == pytest.approx(2.5) and p.expanded == 0
    assert np.all(p.segment_lower >= MARGIN)


def test_plan_around_the_wall_is_certified_and_short(nav):
    s, g = (np.array(v) for v in BLOCKED)
    p = nav.plan(s, g)
    w = p.waypoints
    assert len(w) >= 3 and np.allclose(w[0], s) and np.allclose(w[-1], g)
    assert p.expanded > 0 and p.length_m < p.grid_length_m + 1e-9
    # every segment is clear as the drone's kernel computes it; interior segments by the margin,
    # and so is their margin-tube (psi >= 0)
    rng = np.random.default_rng(0)
    for i, (a, b) in enumerate(zip(w[:-1], w[1:])):
        pts = dense(a, b)
        psi = ref_psi(nav, pts)
        assert psi.min() >= p.segment_lower[i] - 1e-6 >= 0
        if 0 < i < len(w) - 2:
            assert psi.min() >= MARGIN - 1e-6
            u = rng.normal(size=pts.shape)
            u *= (MARGIN / LIP) * rng.uniform(0, 1, (len(u), 1)) / np.linalg.norm(u, axis=1, keepdims=True)
            assert ref_psi(nav, pts + u).min() >= -1e-6
    assert np.all(ref_psi(nav, w) >= p.psi_lower - 1e-9)
    # near-shortest: a plan on a grid twice as fine is not much shorter
    fine = NavMap(nav.packed, nav.kappa, radius=0.1, margin=MARGIN, spacing=0.025, bounds=BOUNDS, cache=False)
    assert p.length_m <= 1.1 * fine.plan(s, g).length_m
    assert p.length_ratio < 1.6


@pytest.mark.parametrize("start,goal,reason", [
    ((-1.0, 0.0, 0.7), (0.3, -1.0, 0.7), "goal_in_obstacle"),  # inside the wall
    ((0.3, -1.0, 0.7), (-1.0, 0.0, 0.7), "start_in_obstacle"),
    ((-1.0, 0.0, 0.7), (0.3, -0.19, 0.7), "goal_in_obstacle"),  # within the radius of the wall
    ((-1.0, 0.0, 0.7), (5.0, 0.0, 0.7), "outside_map"),
    ((-1.0, 0.0, -0.2), (1.0, 0.0, 0.7), "outside_map"),
    ((-1.0, 0.0, 0.7), (1.8, -1.0, 0.6), "goal_enclosed"),  # inside the closed shell
    ((1.8, -1.0, 0.6), (-1.0, 0.0, 0.7), "start_enclosed"),
])
def test_no_path_names_the_reason(nav, start, goal, reason):
    with pytest.raises(NoPathError) as exc:
        nav.plan(start, goal)
    assert exc.value.reason == reason
    msg = str(exc.value)
    assert "\n" not in msg and ("start" in msg or "goal" in msg)
    assert isinstance(exc.value, PolyccError)


def test_preflight_checks_without_the_grid(build):
    fs = FreeSpace.from_build(build, radius=0.1, bounds=BOUNDS)
    fs.preflight((-1.0, 0.0, 0.7), (1.0, 0.0, 0.7))
    with pytest.raises(NoPathError) as exc:
        fs.preflight((-1.0, 0.0, 0.7), (0.3, 0.2, 0.7))
    assert exc.value.reason == "goal_in_obstacle" and "psi" in str(exc.value)


def test_default_map_is_the_cover_box(build):
    fs = FreeSpace.from_build(build, radius=0.1)
    assert np.all(fs.lo <= [0.0, -1.5, 0.0]) and np.all(fs.hi >= [2.15, 1.5, 1.5])
    assert np.all(fs.lo >= [-0.01, -1.51, -0.01]) and np.all(fs.hi <= [2.16, 1.51, 1.51])


def test_plan_file_round_trip(nav, tmp_path):
    p = nav.annotate(nav.plan(*BLOCKED))
    assert p.psi is not None and np.all(p.segment_psi_min >= p.segment_lower - 1e-6)
    f = tmp_path / "plan.json"
    f.write_text(json.dumps(p.to_json()))
    d = read_plan(f)
    assert np.allclose(d["waypoints"], p.waypoints) and d["units"] == "m"
    assert d["switch_tolerance_m"] == MARGIN and len(d["clearance"]["segment_psi_lower_m"]) == len(p.waypoints) - 1
    (tmp_path / "bad.json").write_text("{}")
    with pytest.raises(PolyccError, match="polycc-plan/1"):
        read_plan(tmp_path / "bad.json")


def test_field_cache_and_packed_scene_entry(build, nav):
    again = NavMap.from_build(build, radius=0.1, margin=MARGIN, spacing=0.05, bounds=BOUNDS)
    assert again.cached and np.array_equal(again.grid.field, nav.grid.field)
    packed = scene_from_bytes((build / "scene.bin").read_bytes())
    with pytest.raises(PolyccError, match="kappa"):
        plan_path(packed, *BLOCKED)
    p = plan_path(packed, *BLOCKED, kappa=100.0, bounds=BOUNDS)
    assert np.allclose(p.waypoints, nav.plan(*BLOCKED).waypoints)


@pytest.mark.parametrize("dynamics", ["integrator", "crazyflie"])
def test_flight_with_plan_gets_past_the_wall(build, nav, dynamics):
    """The issue's regression: straight at the goal the CLF + CBF stops in front of the wall; with
    the plan the same app flies around it and arrives, clear of the walls."""
    sim = Simulator(build / "polytopes.h")
    cfg = FlightConfig(vmax=1.0, rate_hz=250, switch_tol_m=MARGIN, t_max_s=30.0)
    s, g = BLOCKED
    base = sim.fly(s, g, dynamics, cfg)
    assert not base.success
    p = nav.plan(s, g)
    tr = sim.fly(s, g, dynamics, cfg, waypoints=p.waypoints)
    assert tr.success and tr.reached == len(p.waypoints) - 1
    assert ref_psi(nav, tr.positions).min() >= 0.0
    assert tr.path_length_m <= 1.05 * p.length_m
