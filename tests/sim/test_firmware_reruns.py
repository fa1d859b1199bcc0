"""FirmwareSimulator.fly flies a trial again when the simulator, not the flight, failed (no firmware needed:
the single flight is replaced by a scripted one)."""

from __future__ import annotations

import numpy as np
import pytest

from polycc.sim.firmware.flights import SHIELD_HZ, STARVED_RERUNS, FirmwareSimulator
from polycc.sim.firmware.sitl import SitlStall
from polycc.sim.sitl import Trial


def _trial(decisions_per_s: float | None, outcome: str = "goal") -> Trial:
    t = Trial(np.zeros(3), np.ones(3), outcome == "goal", outcome, 10.0, 2.0, 1.7, np.zeros((1, 3)), 60, {1: 1},
              extra={"rtf": 0.3})
    if decisions_per_s is not None:
        t.shield = {"decisions": int(decisions_per_s * 10.0)}
    return t


def _sim(script):
    fw = object.__new__(FirmwareSimulator)
    said = []
    fw.say = said.append
    flown = iter(script)

    def once(*a, **k):
        x = next(flown)
        if isinstance(x, Exception):
            raise x
        return x

    fw._fly_once = once
    return fw, said


def test_a_starved_shield_trial_is_flown_again_and_said():
    """Regression (CI): the real firmware's shield made 73 of its 100 decisions per second on a loaded host,
    its late decisions were flown as brakes and the trial ended 'stuck'; that flight is not the M4's."""
    fw, said = _sim([_trial(73, "stuck"), _trial(99)])
    t = fw.fly(np.zeros(3), np.ones(3))
    assert t.success and t.extra["sitl_reruns"] == 1 and t.extra["sitl_rerun_reasons"] == ["starved (73 decisions/s)"]
    assert "starved the app task" in said[0] and "73" in said[0]


def test_starved_reruns_are_bounded_and_the_last_trial_is_kept():
    script = [_trial(50, "stuck")] * (STARVED_RERUNS + 1) + [_trial(100)]
    fw, _ = _sim(script)
    t = fw.fly(np.zeros(3), np.ones(3))
    assert t.outcome == "stuck" and t.extra["sitl_reruns"] == STARVED_RERUNS


@pytest.mark.parametrize("rate", [None, 0.9 * SHIELD_HZ, SHIELD_HZ])
def test_a_fed_shield_or_no_shield_is_flown_once(rate):
    fw, said = _sim([_trial(rate), _trial(rate)])
    t = fw.fly(np.zeros(3), np.ones(3))
    assert t.extra["sitl_reruns"] == 0 and not said


def test_a_hung_simulator_is_flown_again_once_then_raises():
    fw, said = _sim([SitlStall("stalled"), _trial(100)])
    assert fw.fly(np.zeros(3), np.ones(3)).extra["sitl_rerun_reasons"] == ["hung"]
    fw, _ = _sim([SitlStall("stalled"), SitlStall("again")])
    with pytest.raises(SitlStall):
        fw.fly(np.zeros(3), np.ones(3))
