"""Flight behaviour a Crazyflie user expects, with real cflib against the fast simulated Crazyflie:
take off, hand over, land, lose the link, never drop the drone (the same scenarios run against the
real firmware in tests/sim/test_firmware_sitl.py, and the two are compared there)."""

from __future__ import annotations

import json

import pytest

from polycc.testing import flight_scenarios as fs
from polycc.testing.worlds import FastWorld

pytest.importorskip("cflib")


@pytest.fixture(scope="module")
def arena(tmp_path_factory, demo_build):

    d = demo_build(tmp_path_factory.mktemp("arena"))
    side = json.loads((d / "arena.json").read_text())
    start = list(side["start"])
    return {"dir": d / "b", "start": [start[0], start[1], 0.0], "goal": list(side["goal"])}


def run(arena, scenario):
    with FastWorld(arena["dir"] / "polytopes.h", arena["start"]) as w:
        return fs.SCENARIOS[scenario](w.uri, w, arena)


@pytest.mark.slow
def test_full_flight_from_the_floor(arena):
    r = run(arena, "full_flight")
    assert r["took_off"] and r["arrived"]
    assert r["hold_dz_max"] < 0.05  # disabled in the air: z stays within 5 cm for 3 s
    assert r["landed"] and not r["motors_on_end"]


@pytest.mark.slow
def test_enabled_on_the_floor_keeps_the_motors_off(arena):
    r = run(arena, "enabled_on_floor")
    assert not r["motors_on_any"] and r["z_max"] < 0.01
    assert r["status"] == 7  # not flying: take off first


@pytest.mark.slow
def test_disable_at_speed_stops_and_holds(arena):
    r = run(arena, "disable_at_speed")
    assert r["took_off"] and r["speed_at_disable"] > 0.4
    assert r["speed_end"] < 0.05 and r["travel_after_disable"] < 0.3 and r["motors_on_end"]


@pytest.mark.slow
def test_link_loss_lands(arena):
    r = run(arena, "link_loss")
    assert r["status_before_cut"] == 1
    assert r["landed"] and not r["motors_on_end"] and r["max_descent_speed"] < 1.0
    assert r["status_after"] == 10  # link lost (landed)


@pytest.mark.slow
def test_unsupported_controller_is_refused(arena):
    r = run(arena, "unsupported_controller")
    assert r["status"] == 9 and r["moved"] < 0.05


@pytest.mark.slow
def test_ground_setpoints_are_ignored_while_enabled(arena):
    r = run(arena, "ground_setpoints_while_enabled")
    assert r["arrived"] and r["z_min_flight"] > 0.5


@pytest.mark.slow
def test_polycc_fly_from_the_floor(arena):
    r = run(arena, "polycc_fly_from_floor")
    assert r["outcome"] == "landed", r["events"]
    assert r["max_descent_speed"] < 1.0 and not r["motors_on_end"]
    assert abs(r["end"][2]) < 0.05
