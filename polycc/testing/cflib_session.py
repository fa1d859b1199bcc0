"""A real-cflib session against a simulated Crazyflie, for tests: connect, TOCs, a param round trip,
log blocks and the app channel; and a watchdog, because cflib waits forever for a lost reply."""

from __future__ import annotations

import threading
import time

CONNECT_TIMEOUT_S = 8.0
"""Wall seconds for one connect try (TOCs and params); :func:`scenario` tries twice."""
SCENARIO_TIMEOUT_S = 30.0
"""Backstop for :func:`run_with_timeout`: two connect tries and the bounded steps after them."""


def run_with_timeout(fn, timeout_s: float = SCENARIO_TIMEOUT_S):
    """cflib waits forever for a lost reply; fail the test instead of hanging it."""
    result: dict = {}

    def target():
        try:
            result["value"] = fn()
        except BaseException as e:  # noqa: BLE001 - re-raised in the test thread
            result["error"] = e

    t = threading.Thread(target=target, daemon=True)
    t.start()
    t.join(timeout_s)
    assert not t.is_alive(), f"cflib scenario did not finish within {timeout_s} s"
    if "error" in result:
        raise result["error"]
    return result["value"]


def scenario(uri: str, model) -> dict:
    """Connect, check TOCs, set and read back a param, stream logs, use the app channel.

    Every wait is bounded and the session is closed however this ends: a session left open on a
    serial device that then goes away leaves cflib's CPX reader spinning for ever, printing a
    traceback per failed read into the captured output of every later test in that process (about
    2.5 MB/s, measured; the likely start of the CI failure of 2026-12-07, where pytest-timeout fired
    outside the serial-pty test and xdist aborted the run)."""
    import queue

    from cflib.crazyflie.log import LogConfig

    from polycc.link.cflib_tools import connect

    out: dict = {}
    t0 = time.monotonic()
    scf = connect(uri, CONNECT_TIMEOUT_S, attempts=2)  # cflib's serial connect race: see connect()
    try:
        out["connect_s"] = time.monotonic() - t0
        cf = scf.cf
        out["log_toc"] = {f"{g}.{n}" for g, names in cf.log.toc.toc.items() for n in names}
        out["param_toc"] = {f"{g}.{n}" for g, names in cf.param.toc.toc.items() for n in names}
        out["goalX_initial"] = cf.param.get_value("polycc.goalX")

        updated = threading.Event()
        cf.param.add_update_callback(group="polycc", name="goalX", cb=lambda name, value: updated.set())
        cf.param.set_value("polycc.goalX", 2.5)
        assert updated.wait(2.0), "no reply to the param write"
        updated.clear()
        cf.param.request_param_update("polycc.goalX")  # read it back from the device
        assert updated.wait(2.0), "no reply to the param read"
        out["goalX_read"] = cf.param.get_value("polycc.goalX")
        out["goalX_model"] = model.values["polycc.goalX"]

        lc = LogConfig(name="test", period_in_ms=10)
        lc.add_variable("polycc.psi", "float")
        lc.add_variable("stateEstimate.x", "float")
        samples: queue.Queue = queue.Queue()  # as cflib's SyncLogger, with a timeout on each sample
        lc.data_received_cb.add_callback(lambda ts, data, conf: samples.put((ts, data)))
        cf.log.add_config(lc)
        lc.start()
        out["log"] = []
        try:
            while len(out["log"]) < 5:
                try:
                    out["log"].append(samples.get(timeout=2.0))
                except queue.Empty:
                    raise AssertionError(f"log block: {len(out['log'])} of 5 samples, then none for 2 s") from None
        finally:
            lc.stop()
            lc.delete()

        got = threading.Event()
        replies = []
        cf.appchannel.packet_received.add_callback(lambda data: (replies.append(bytes(data)), got.set()))
        cf.appchannel.send_packet(b"hello")
        assert got.wait(2.0), "no app-channel reply"
        out["app"] = replies
    finally:
        scf.close_link()
    return out
