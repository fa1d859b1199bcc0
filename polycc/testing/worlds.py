"""Simulated Crazyflies for the flight scenarios (:mod:`polycc.testing.flight_scenarios`), with one API:

* :class:`FastWorld` -- `polycc sim-device`'s model (the app's C code on host shims) on a UDP port, in
  real time;
* :class:`FirmwareWorld` -- the real Crazyflie firmware (CrazySim SITL ``cf2`` with the app compiled
  in) behind the physics/relay bridge, lock-stepped (:mod:`polycc.sim.firmware`).

Each has ``uri`` (for cflib), ``truth()`` -> (position m, velocity m/s, motors_on), ``sample()`` -> (t,
position, velocity, motors_on), ``time()`` (simulated seconds), ``sleep(s)`` and ``wait_until(pred,
timeout_s)`` in simulated time, and ``cut_link(seconds)`` (drop the link both ways). Scenarios wait in
simulated time, so a real-firmware run that is slower than real time on a loaded host gives the same
flight.
"""

from __future__ import annotations

import time

import numpy as np


class _World:
    poll_s = 0.01

    def time(self) -> float:
        raise NotImplementedError

    def sample(self):
        raise NotImplementedError

    def truth(self):
        _, p, v, on = self.sample()
        return p, v, on

    def wait_until(self, pred, timeout_s: float) -> bool:
        """True once ``pred()`` holds, False after ``timeout_s`` simulated seconds."""
        t_end = self.time() + timeout_s
        while True:
            if pred():
                return True
            if self.time() >= t_end:
                return False
            time.sleep(self.poll_s)

    def sleep(self, seconds: float) -> None:
        t_end = self.time() + seconds
        while self.time() < t_end:
            time.sleep(self.poll_s)

    def report(self) -> str:
        """One paragraph on the simulated vehicle now, for a test that gives up on it."""
        t, p, v, on = self.sample()
        return (f"simulated t = {t:.2f} s, position {np.round(p, 3).tolist()} m, velocity "
                f"{np.round(v, 3).tolist()} m/s, motors {'on' if on else 'off'}")


class FastWorld(_World):
    """`polycc sim-device`'s model (the app's C code on host shims) on a UDP port, in real time."""

    name = "fast"

    def __init__(self, header, start, dynamics: str = "crazyflie", on_floor: bool = True):
        from polycc.sim.crtp_device import CrtpDevice
        from polycc.sim.device_server import UdpDeviceServer
        from polycc.sim.sitl_device import SitlDeviceModel

        self.model = SitlDeviceModel(header, start=start, dynamics=dynamics, on_floor=on_floor)
        self.server = UdpDeviceServer(CrtpDevice(self.model), "127.0.0.1", 0)

    @property
    def uri(self) -> str:
        return self.server.uri

    def time(self) -> float:
        with self.model.lock:
            return self.model.sim_ms * 1e-3

    def sample(self):
        with self.model.lock:
            m = self.model
            return m.sim_ms * 1e-3, np.array(m.dyn.p), np.array(m.dyn.v), bool(m.dyn.motors_on)

    def cut_link(self, seconds: float) -> None:
        self.model.cut_link(seconds)

    def __enter__(self) -> "FastWorld":
        self.model.start()
        self.server.start()
        return self

    def __exit__(self, *exc) -> None:
        self.server.stop()
        self.model.stop()


class FirmwareWorld(_World):
    """The real firmware in its SITL: ``cf2`` built from ``tree`` (a CrazySim SITL folder or tarball; default
    the shared fixture :func:`polycc.testing.files.sitl_tarball`) with ``header`` compiled in, on the floor
    at ``start`` (x, y; z is the floor, 0)."""

    name = "firmware"
    poll_s = 0.02
    connect_retry = True  # flight_scenarios._connect: one fresh cflib session after a stalled connect

    def __init__(self, header, start, tree=None, run_dir=None, rtf_max: float = 1.0, cf2=None, bridge_args=None):
        from polycc.sim.firmware.build import build_cf2
        from polycc.sim.firmware.sitl import FirmwareSitl
        from polycc.testing.files import sitl_tarball

        self.build = cf2 if cf2 is not None else build_cf2(tree if tree is not None else sitl_tarball(), header)
        self.sitl = FirmwareSitl(self.build, start=(float(start[0]), float(start[1]), 0.0), run_dir=run_dir,
                                 rtf_max=rtf_max, bridge_args=bridge_args)
        self.toc_cache = None  # cflib's TOC cache off: the stalled connects seen had it on (sim.firmware.flights)

    @property
    def uri(self) -> str:
        return self.sitl.uri

    def time(self) -> float:
        return self.sitl.time()

    def sample(self):
        s = self.sitl.state()
        return float(s["t"]), np.array(s["pos"]), np.array(s["vel"]), bool(s["motors_on"])

    def cut_link(self, seconds: float) -> None:
        self.sitl.cut_link(seconds)

    def wait_until(self, pred, timeout_s: float) -> bool:
        return self.sitl.wait_until(pred, timeout_s, self.poll_s)

    def sleep(self, seconds: float) -> None:
        self.sitl.sleep(seconds)

    def report(self) -> str:
        return f"{super().report()}; {self.sitl.stall_report()}; {self.sitl._last_lines()}"

    def __enter__(self) -> "FirmwareWorld":
        self.sitl.start()
        return self

    def __exit__(self, *exc) -> None:
        if exc[0] is not None:
            self.sitl.keep_run_dir()
        self.sitl.stop()


class ScriptTimeout(AssertionError):
    """A user's script (a README example) did not finish within its simulated-time limit."""


def run_script(world: _World, code: str, limit_s: float, globals_: dict | None = None,
               filename: str = "README.md") -> None:
    """Run ``code`` (a user's cflib script, URI already pointed at ``world``) as a script, in a thread, and
    wait at most ``limit_s`` seconds of simulated time for it; an exception in it is raised here.

    Why: such a script waits on cflib queues with no timeout of its own (``SyncLogger``, ``SyncCrazyflie``),
    so a vehicle that never reaches the state it waits for hangs it for ever, and a test with it, until
    pytest-timeout's 20 minutes (CI, 2026-12-07: the README example in ``SyncLogger`` after the land). Here it
    fails after ``limit_s`` of the simulator's clock with where the vehicle is; a simulation that stops
    advancing raises the world's own stall error. The script's thread is a daemon: left blocked, it does
    not keep the test process alive."""
    import threading

    err: list[BaseException] = []

    def main():
        try:
            exec(compile(code, filename, "exec"), {} if globals_ is None else globals_)
        except BaseException as exc:  # noqa: BLE001 -- re-raised in the caller's thread
            err.append(exc)

    th = threading.Thread(target=main, name=f"script {filename}", daemon=True)
    th.start()
    if not world.wait_until(lambda: not th.is_alive(), limit_s):
        raise ScriptTimeout(f"{filename}: the script did not finish within {limit_s:.0f} s of simulated time; "
                            f"{world.report()}")
    th.join()
    if err:
        raise err[0]
