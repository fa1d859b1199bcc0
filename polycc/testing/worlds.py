"""Simulated Crazyflies for the flight scenarios (:mod:`polycc.testing.flight_scenarios`): the fast
host model served over UDP (:class:`FastWorld`). Each has ``uri``, ``truth()`` -> (position m,
velocity m/s, motors_on) and ``cut_link(seconds)``."""

from __future__ import annotations

import numpy as np


class FastWorld:
    """`polycc sim-device`'s model (the app's C code on host shims) on a UDP port, in real time."""

    def __init__(self, header, start, dynamics: str = "crazyflie", on_floor: bool = True):
        from polycc.sim.crtp_device import CrtpDevice
        from polycc.sim.device_server import UdpDeviceServer
        from polycc.sim.sitl_device import SitlDeviceModel

        self.model = SitlDeviceModel(header, start=start, dynamics=dynamics, on_floor=on_floor)
        self.server = UdpDeviceServer(CrtpDevice(self.model), "127.0.0.1", 0)

    @property
    def uri(self) -> str:
        return self.server.uri

    def truth(self):
        with self.model.lock:
            return np.array(self.model.dyn.p), np.array(self.model.dyn.v), bool(self.model.dyn.motors_on)

    def cut_link(self, seconds: float) -> None:
        self.model.cut_link(seconds)

    def __enter__(self) -> "FastWorld":
        self.model.start()
        self.server.start()
        return self

    def __exit__(self, *exc) -> None:
        self.server.stop()
        self.model.stop()
