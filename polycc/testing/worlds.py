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

    def __enter__(self) -> "FirmwareWorld":
        self.sitl.start()
        return self

    def __exit__(self, *exc) -> None:
        if exc[0] is not None:
            self.sitl.keep_run_dir()
        self.sitl.stop()
