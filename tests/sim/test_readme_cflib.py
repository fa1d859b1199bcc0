"""The README's own cflib script, run as written (only the URI changed) against the simulated
Crazyflie: it takes off, flies to the goal through the app, hands over, lands, and the motors stop,
with no descent faster than 1 m/s (issue 14: the README example must not drop the drone)."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest

from polycc.testing.files import readme_block
from polycc.testing.flight_scenarios import Recorder
from polycc.testing.worlds import FastWorld, run_script

pytest.importorskip("cflib")


def readme_example() -> str:
    return readme_block("readme-cflib-example")


def test_the_example_is_plain_cflib():
    code = readme_example()
    assert "import polycc" not in code and "from polycc" not in code  # a user's script: cflib only
    assert "udp://127.0.0.1:19850" in code and "hl.land" in code


@pytest.mark.slow
def test_readme_cflib_example_flies_and_lands_even_when_the_disable_reaches_the_drone_late(tmp_path, demo_build,
                                                                                          monkeypatch):
    """The README example as written (only the URI changed) takes off, flies to the goal through the app,
    hands over, lands, and the motors stop, with no descent faster than 1 m/s (issue 14). Regression: the
    example disabled the app, slept 1 s and sent the land. cflib queues param writes behind any request still
    waiting for its answer, so the disable can reach the drone after the land; the
    still-enabled app's next setpoint then cancels the land, the drone holds 0.9 m and the script waits in its
    SyncLogger for ever (CI, 2026-12-07: 20 minutes). The example now lands once the app's status says it
    has let go. Here the disable reaches the drone 1.5 s late."""
    import threading

    from cflib.crazyflie import param

    demo_build(tmp_path)
    side = json.loads((tmp_path / "arena.json").read_text())
    code = readme_example()
    goal = np.array([float(v) for v in re.search(r'\("goalX", ([-\d.]+)\), \("goalY", ([-\d.]+)\), '
                                                 r'\("goalZ", ([-\d.]+)\)', code).groups()])
    late = []
    real_set = param.Param.set_value

    def set_value(self, name, value):
        if name == "polycc.enable" and int(value) == 0:
            late.append(threading.Timer(1.5, real_set, (self, name, value)))
            late[-1].start()
            return
        real_set(self, name, value)

    monkeypatch.setattr(param.Param, "set_value", set_value)
    with FastWorld(tmp_path / "b" / "polytopes.h", [side["start"][0], side["start"][1], 0.0]) as world:
        with Recorder(world, {}) as rec:
            run_script(world, code.replace("udp://127.0.0.1:19850", world.uri), 60.0)
        a = rec.array()
        p, v, on = world.truth()
    assert late  # the disable did go through the delay
    xyz = a[:, 1:4]
    assert xyz[:, 2].max() > 0.8  # it took off
    assert np.linalg.norm(xyz - goal, axis=1).min() < 0.15  # it reached the goal
    assert p[2] < 0.03 and not on  # on the floor, motors off
    assert a[:, 4].min() > -1.0  # never a descent faster than 1 m/s
