"""`polycc fly` times its waits in the drone's seconds (polycc.ground.fly's docstring): the firmware's log
timestamps, plus the wall seconds since the latest sample. The log stream here is a thread feeding the
session as cflib's log callback does, at half real time (a simulator on a loaded host); that the SITL's
log timestamps are its simulated clock is checked on the real firmware
(tests/sim/test_firmware_sitl.py::test_polycc_fly_from_the_floor)."""

from __future__ import annotations

import threading
import time

from polycc.ground import fly as fly_mod


class _Link:
    def is_connected(self):
        return True


def _session(timeout_s: float):
    log = fly_mod.FlightLog(["time_s"])
    return fly_mod._Session(_Link(), log, threading.Lock(), None, timeout_s)


def _feed(s, rtf: float, stop: threading.Event, period_ms: int = 20, t0_ms: int = 123_456):
    """A position sample every ``period_ms`` of the drone's time, at ``rtf`` x real time."""
    def run():
        ts = t0_ms
        while not stop.wait(period_ms / 1000.0 / rtf):
            ts += period_ms
            with s.lock:
                s.last_pos_t = time.monotonic()
                s.stamp(ts)
    th = threading.Thread(target=run, daemon=True)
    th.start()
    return th


def test_a_wait_counts_the_drones_seconds_on_a_slow_simulator():
    """Regression (CI: "landing did not finish (timeout)" at RTF ~0.35): a 0.6 s wait at half real time
    lasts about 1.2 wall seconds; the old wall-clock wait gave up after 0.6."""
    s = _session(60.0)
    stop = threading.Event()
    _feed(s, 0.5, stop)
    try:
        time.sleep(0.1)
        d0, w0 = s.now(), time.monotonic()
        assert s.wait(lambda: False, "landing", 0.6, watch_app=False) == "timeout"
        wall, drone = time.monotonic() - w0, s.now() - d0
    finally:
        stop.set()
    assert 1.1 <= wall <= 2.5, wall
    assert 0.6 <= drone <= 0.8, drone


def test_the_flight_timeout_is_the_drones_seconds_too():
    s = _session(0.4)
    stop = threading.Event()
    _feed(s, 0.5, stop)
    try:
        w0 = time.monotonic()
        assert s.wait(lambda: False, "flying to waypoint 1") == "timeout"
        wall = time.monotonic() - w0
    finally:
        stop.set()
    assert 0.7 <= wall <= 2.0, wall


def test_no_sample_for_a_wall_second_stops_whatever_the_drones_clock():
    """The estimate watchdog stays in wall seconds: with no sample at all the drone's clock runs at
    wall rate from the last one, and the flight stops after ESTIMATE_LOST_S."""
    s = _session(60.0)
    stop = threading.Event()
    th = _feed(s, 1.0, stop)
    time.sleep(0.2)
    stop.set()
    th.join()
    w0 = time.monotonic()
    why = s.wait(lambda: False, "landing", 30.0, watch_app=False)
    assert why == f"stopped: no position estimate for {fly_mod.ESTIMATE_LOST_S:g} s while landing"
    assert time.monotonic() - w0 <= fly_mod.ESTIMATE_LOST_S + 0.5


def test_the_drones_clock_never_runs_backwards():
    """Between samples the wall seconds since the latest one are added; a slow simulator's next sample
    would move that back by up to a sample's wall period, which :meth:`now` does not show."""
    s = _session(60.0)
    with s.lock:
        s.stamp(1000)
    time.sleep(0.2)
    a = s.now()
    with s.lock:
        s.stamp(1020)  # 20 ms of the drone's time in 200 ms of wall time
    b = s.now()
    assert b >= a >= 0.2


def test_the_hand_over_wait_outlasts_the_apps_settling_hold():
    """Regression: `polycc fly` waited 10 s for the app to let go before its land, the app's settling hold lasts up
    to 12 s, and a land sent during the hold can be stopped by the hold's next setpoint (the high-level
    commander's task preempts the app between its check for a new plan and that setpoint): the land was lost."""
    import re

    from polycc.resources import firmware_app

    src = (firmware_app() / "src" / "polycc_app.h").read_text()
    settle_ms = int(re.search(r"#define POLYCC_APP_SETTLE_MAX_MS (\d+)u", src).group(1))
    assert fly_mod.HANDOVER_WAIT_S > settle_ms / 1000.0
