"""Test helpers for the link: a small stand-in for the SITL app behind the simulated
Crazyflie's DeviceModel, and frames as cflib (the host) sends them."""

from __future__ import annotations

from polycc.link.cpx_serial import CpxTarget, encode_crtp_frame
from polycc.link.crtp import CrtpPacket
from polycc.sim.crtp_device import DeviceModel, LogEntry, ParamEntry

PARAMS = [("polycc", "goalX", "float", 0.0), ("polycc", "goalY", "float", 0.0), ("polycc", "goalZ", "float", 1.0),
          ("polycc", "enable", "uint8_t", 0), ("polycc", "mode", "int16_t", -3), ("polycc", "gain", "double", 0.5)]
LOGS = [("stateEstimate", "x", "float"), ("stateEstimate", "y", "float"), ("stateEstimate", "z", "float"),
        ("polycc", "psi", "float"), ("polycc", "ticks", "uint16_t"), ("polycc", "state", "int8_t")]


class FakeModel(DeviceModel):
    """Params and logs backed by a dict; records setpoints and app-channel packets.

    ``clock_ms`` (if not ``None``) replaces the wall clock, for deterministic log timing.
    The app channel answers ``b"ack:" + data`` (truncated to 30 bytes).
    """

    def __init__(self) -> None:
        self.values: dict[str, float] = {f"{g}.{n}": v for g, n, _, v in PARAMS}
        self.values.update({f"{g}.{n}": 0.0 for g, n, _ in LOGS})
        self.values["stateEstimate.x"] = 1.5
        self.values["polycc.psi"] = 0.25
        self.values["polycc.uptime"] = 7
        params = [ParamEntry(g, n, c, self._getter(f"{g}.{n}"), self._setter(f"{g}.{n}")) for g, n, c, _ in PARAMS]
        params.append(ParamEntry("polycc", "uptime", "uint32_t", self._getter("polycc.uptime")))  # read-only
        logs = [LogEntry(g, n, c, self._getter(f"{g}.{n}")) for g, n, c in LOGS]
        super().__init__(params, logs)
        self.setpoints: list[tuple[str, dict]] = []
        self.app_rx: list[bytes] = []
        self.clock_ms: int | None = None

    def _getter(self, key):
        return lambda: self.values[key]

    def _setter(self, key):
        def set_(v):
            self.values[key] = v
        return set_

    def time_ms(self) -> int:
        return super().time_ms() if self.clock_ms is None else self.clock_ms

    def on_setpoint(self, kind: str, values: dict) -> None:
        self.setpoints.append((kind, values))

    def on_appchannel(self, data: bytes) -> bytes | None:
        self.app_rx.append(data)
        return (b"ack:" + data)[:30]


def host_frame(pk: CrtpPacket) -> bytes:
    """``pk`` framed as cflib (the host) sends it: CPX from HOST to STM32, lastPacket clear."""
    return encode_crtp_frame(pk, source=CpxTarget.HOST, destination=CpxTarget.STM32, last_packet=False)
