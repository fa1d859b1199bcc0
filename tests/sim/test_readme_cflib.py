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
from polycc.testing.worlds import FastWorld

pytest.importorskip("cflib")


def readme_example() -> str:
    return readme_block("readme-cflib-example")


def test_the_example_is_plain_cflib():
    code = readme_example()
    assert "import polycc" not in code and "from polycc" not in code  # a user's script: cflib only
    assert "udp://127.0.0.1:19850" in code and "hl.land" in code


@pytest.mark.slow
def test_readme_cflib_example_flies_and_lands(tmp_path, demo_build):

    demo_build(tmp_path)
    side = json.loads((tmp_path / "arena.json").read_text())
    start = [side["start"][0], side["start"][1], 0.0]
    code = readme_example()
    goal = np.array([float(v) for v in re.search(r'\("goalX", ([-\d.]+)\), \("goalY", ([-\d.]+)\), '
                                                 r'\("goalZ", ([-\d.]+)\)', code).groups()])
    with FastWorld(tmp_path / "b" / "polytopes.h", start) as world:
        with Recorder(world, {}) as rec:
            exec(compile(code.replace("udp://127.0.0.1:19850", world.uri), "README.md", "exec"), {})
        a = rec.array()
        p, v, on = world.truth()
    xyz = a[:, 1:4]
    assert xyz[:, 2].max() > 0.8  # it took off
    assert np.linalg.norm(xyz - goal, axis=1).min() < 0.15  # it reached the goal
    assert p[2] < 0.03 and not on  # on the floor, motors off
    assert a[:, 4].min() > -1.0  # never a descent faster than 1 m/s
