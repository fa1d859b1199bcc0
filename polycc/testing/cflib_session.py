"""A real-cflib session against a simulated Crazyflie, for tests: connect, TOCs, a param round trip,
log blocks and the app channel; and a watchdog, because cflib waits forever for a lost reply."""

from __future__ import annotations

import threading
import time

SCENARIO_TIMEOUT_S = 10.0


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
    """Connect, check TOCs, set and read back a param, stream logs, use the app channel."""
    from cflib.crazyflie import Crazyflie
    from cflib.crazyflie.log import LogConfig
    from cflib.crazyflie.syncCrazyflie import SyncCrazyflie
    from cflib.crazyflie.syncLogger import SyncLogger

    out: dict = {}
    t0 = time.monotonic()
    with SyncCrazyflie(uri, cf=Crazyflie()) as scf:
        scf.wait_for_params()
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
        out["log"] = []
        with SyncLogger(scf, lc) as logger:
            for ts, data, _ in logger:
                out["log"].append((ts, data))
                if len(out["log"]) == 5:
                    break

        got = threading.Event()
        replies = []
        cf.appchannel.packet_received.add_callback(lambda data: (replies.append(bytes(data)), got.set()))
        cf.appchannel.send_packet(b"hello")
        assert got.wait(2.0), "no app-channel reply"
        out["app"] = replies
    return out


