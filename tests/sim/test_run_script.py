"""``polycc.testing.worlds.run_script``: a user's script that never finishes fails its test after a limit of
simulated time, with where the vehicle is, instead of hanging it (regression: the README cflib example waited
in ``SyncLogger`` for 20 minutes of a CI run)."""

from __future__ import annotations

import time

import numpy as np
import pytest

from polycc.testing.worlds import ScriptTimeout, _World, run_script


class ClockWorld(_World):
    """A vehicle hovering at 0.9 m whose simulated clock runs 100 x faster than real time."""

    poll_s = 0.005

    def __init__(self):
        self.t0 = time.monotonic()

    def time(self) -> float:
        return 100.0 * (time.monotonic() - self.t0)

    def sample(self):
        return self.time(), np.array([0.0, -1.4, 0.9]), np.zeros(3), True


def test_a_script_that_never_finishes_fails_with_the_vehicle_state():
    w = ClockWorld()
    with pytest.raises(ScriptTimeout, match=r"within 30 s of simulated time.*position \[0\.0, -1\.4, 0\.9\].*"
                                            r"motors on"):
        run_script(w, "import threading\nthreading.Event().wait()\n", 30.0)
    assert w.time() >= 30.0


def test_a_script_that_finishes_returns_and_its_errors_are_raised():
    g: dict = {}
    run_script(ClockWorld(), "x = 6 * 7\n", 30.0, g)
    assert g["x"] == 42
    with pytest.raises(KeyError, match="polycc.enable"):
        run_script(ClockWorld(), "raise KeyError('polycc.enable not in param TOC')\n", 30.0)
