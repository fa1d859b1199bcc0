"""Swarms on the fast simulator (polycc/swarm/): independent app instances, the neighbour barrier in
closed loop (no two drones closer than r_i + r_j), coverage of a ToI mixture, and `polycc swarm-sim`
end to end on the demo arena (slow)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from polycc.codegen.header import write_outputs
from polycc.geometry.halfplanes import axis_box
from polycc.onboard import barrier as B
from polycc.swarm.coverage import CoverageMap, Targets
from polycc.swarm.instances import drone_apps
from polycc.swarm.sim import SwarmConfig, run_swarm


@pytest.fixture(scope="module")
def room(tmp_path_factory):
    """A 4 x 4 x 2 m room with a wall piece and a pillar (polytopes only: fast)."""
    from polycc.plan.planner import NavMap, load_build

    d = tmp_path_factory.mktemp("room")
    write_outputs(d, [axis_box([1.6, 0.0, 0.0], [2.0, 2.6, 2.0]), axis_box([0.6, 2.9, 0.0], [0.9, 3.2, 2.0])],
                  {"kappa": 100.0})
    packed, kappa, _ = load_build(d)
    nav = NavMap(packed, kappa, radius=0.1, margin=0.05, spacing=0.2, bounds=([0, 0, 0.2], [4, 4, 1.8]))
    return d, packed, nav


def test_instances_have_independent_state(room):
    d, _, _ = room
    apps = drone_apps(d / "polytopes.h", 3)
    for i, a in enumerate(apps):
        a.reset()
        a.set_param("polycc", "goalX", float(i))
    assert [a.get_param("polycc", "goalX") for a in apps] == [0.0, 1.0, 2.0]
    assert len({a.lib.polycc_app_trace() for a in apps}) == 3  # distinct C statics


def _psi_along(packed, paths):
    p = np.vstack(paths).astype(np.float32)
    psi, _, flags = B.barrier(packed, B.Params(kappa=100.0, radius=0.1), p)
    assert not flags.any()
    return float(psi.min())


def test_head_on_swap_keeps_the_drones_apart(room):
    """Two drones whose goals are each other's start (the worst case for a pair): the neighbour terms keep
    their centres >= r_i + r_j = 0.2 m apart; the obstacle barrier stays >= 0 along both paths."""
    d, packed, nav = room
    a, b = np.array([0.4, 1.0, 1.0]), np.array([1.3, 1.02, 1.0])
    tg = Targets(np.array([[3.0, 3.5, 1.0]]), np.full(1, 0.3), np.ones(1))  # far away: never detected
    cmap = CoverageMap(nav, tg)
    res = run_swarm(d / "polytopes.h", cmap, np.array([a, b]), tg, SwarmConfig(t_max_s=8.0), goals=np.array([b, a]))
    assert res.pair_collisions == 0 and res.min_pair_m >= 0.2
    assert res.min_pair_m < 0.5  # they did come close: the test exercises the barrier
    assert _psi_along(packed, res.positions) >= -1e-3  # sampled every 10 ms (the app keeps psi >= 0 per tick)


@pytest.mark.parametrize("bcast_ms", [350, 450])
def test_stale_reports_hold_and_stay_safe(room, bcast_ms):
    """Reports every 350 ms with 100 ms latency: ages reach ~455 ms, the ageing buffer is large and the
    drones keep flying apart.  Every 450 ms: ages pass the 500 ms timeout before the next report, so
    the drones hold (status 13) for those ticks; still apart."""
    d, packed, nav = room
    starts = np.array([[0.4, 0.4, 1.0], [1.2, 0.4, 1.0], [0.4, 1.4, 1.0], [1.2, 1.4, 1.0]])
    tg = Targets(np.array([[3.0, 3.5, 1.0]]), np.full(1, 0.3), np.ones(1))
    cmap = CoverageMap(nav, tg)
    res = run_swarm(d / "polytopes.h", cmap, starts, tg, SwarmConfig(t_max_s=8.0, bcast_ms=bcast_ms, latency_ms=100),
                    goals=starts[::-1].copy())  # diagonal swaps through the middle
    assert res.pair_collisions == 0 and res.min_pair_m >= 0.2
    assert res.min_pair_m < 0.6
    assert all((13 in s) == (bcast_ms == 450) for s in res.statuses)  # hold only when a report is > 500 ms old


@pytest.mark.parametrize("kind", ["guided", "lloyd"])
def test_coverage_behind_the_wall(room, kind):
    """Four drones on one side of the wall, peaks on the other: the guided map (navigation function)
    goes around it; every run is collision free."""
    d, packed, nav = room
    starts = np.array([[0.5, 0.5, 1.0], [1.2, 0.5, 1.0], [0.5, 1.5, 1.0], [1.2, 1.5, 1.0]])
    tg = Targets(np.array([[3.0, 0.8, 1.0], [3.2, 2.0, 1.0]]), np.full(2, 0.4), np.ones(2))
    cmap = CoverageMap(nav, tg)
    assert np.isfinite(cmap.nf).all(axis=1).any()
    res = run_swarm(d / "polytopes.h", cmap, starts, tg, SwarmConfig(controller=kind, t_max_s=25.0))
    assert res.pair_collisions == 0 and res.min_pair_m >= 0.2
    assert _psi_along(packed, res.positions) >= -1e-3
    if kind == "guided":
        assert res.coverage == 1.0 and res.task_time_s < 25.0


@pytest.mark.slow
def test_swarm_sim_cli_on_the_demo_arena(tmp_path, demo_build):
    from polycc.cli import main

    demo_build(tmp_path)
    assert main(["swarm-sim", str(tmp_path / "b"), "--drones", "4", "--random-targets", "3", "--t-max", "30"]) == 0
    s = json.loads((tmp_path / "b" / "swarm.json").read_text())
    assert s["collisions"] == 0 and s["collisions_drone_drone"] == 0 and s["collisions_drone_obstacle"] == 0
    assert s["min_inter_drone_m"] >= 0.2 and s["coverage_ratio"] == 1.0
    assert (tmp_path / "b" / "coverage.png").stat().st_size > 10_000


def test_targets_file_and_cli_errors_are_one_line(tmp_path, room, capsys):
    from polycc.cli import main
    from polycc.errors import PolyccError
    from polycc.swarm.coverage import load_targets

    good = tmp_path / "t.json"
    good.write_text(json.dumps({"targets": [{"x": 1, "y": 2, "z": 1, "sigma": 0.3}, {"x": 2, "y": 2, "z": 1}]}))
    t = load_targets(good)
    assert t.mu.shape == (2, 3) and list(t.sigma) == [0.3, 0.4] and list(t.weight) == [1.0, 1.0]
    bad = tmp_path / "bad.json"
    for text in ("not json", json.dumps({"targets": []}), json.dumps({"targets": [{"x": 1, "y": 2, "z": 1,
                                                                                     "sigma": -1}]})):
        bad.write_text(text)
        with pytest.raises(PolyccError):
            load_targets(bad)
    d, _, _ = room
    assert main(["swarm-sim", str(tmp_path / "nowhere"), "--drones", "2"]) == 2  # no polytopes.h
    assert main(["swarm-sim", str(d), "--drones", "2"]) == 2  # the manifest names no scene
    err = capsys.readouterr().err
    assert "Traceback" not in err and "polycc build" in err and "--scene" in err
    assert main(["swarm-sim", str(d), "--drones", "17"]) == 2  # the app's table holds 16
    assert "out of range" in capsys.readouterr().err


def test_a_drone_whose_app_never_flew_has_no_clearance_and_no_collision():
    """Regression: run_swarm_firmware measured the clearance of a drone whose app was never enabled (a
    flight stopped during the takeoff) at its landed position, on the floor, and reported every such drone
    as a drone-obstacle collision (CI's failed p2p-4 run: "collisions: 4"). An empty path now has none; a
    path through the floor still counts."""
    from polycc.scene.ellipsoids import Ellipsoids
    from polycc.sim.clearance import Clearance
    from polycc.swarm.sim import obstacle_clearance

    floor = Ellipsoids(np.array([[0.0, 0.0, -0.05]]), np.eye(3)[None], np.array([[2.0, 2.0, 0.05]]))
    obst, clear = obstacle_clearance([np.empty((0, 3)), np.array([[0.0, 0.0, 0.5]]), np.array([[0.0, 0.0, 0.0]])],
                                     Clearance(floor), 0.1)
    assert obst[0] == 0 and np.isnan(clear[0])
    assert obst[1] == 0 and clear[1] > 0.3
    assert obst[2] > 0 and clear[2] < 0
