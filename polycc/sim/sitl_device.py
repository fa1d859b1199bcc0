"""A live SITL behind the simulated Crazyflie: :class:`SitlDeviceModel` is a
:class:`~polycc.sim.crtp_device.DeviceModel` whose TOCs, params and logs are the host-built app's own.

* **TOCs** come from the app's ``PARAM_*``/``LOG_*`` tables as the firmware shims collect them
  (:meth:`AppSim.param_toc`/:meth:`AppSim.log_toc`, types via ``ctype_from_*_type``); the shims
  already add the standard ``stateEstimate.{x,y,z,vx,vy,vz}`` and ``kalman.var*`` log variables,
  and :class:`~polycc.sim.crtp_device.CrtpDevice` adds the read-only ``firmware.polyccVersion``.
* **Params** read and write the app's real C variables (``shim_param_value``/``shim_param_set``,
  which also runs the param's callback); **logs** read the real values.
* **Real time**: :meth:`SitlDeviceModel.start` runs a thread that, holding ``model.lock``, steps
  the app on its simulated 1 kHz FreeRTOS clock and the vehicle model (Crazyflie-like by
  default) up to the wall clock; the log timestamps use the same clock.
* **Setpoints** from a client (cflib's commander, generic setpoints, high-level commander) fly the
  vehicle while ``polycc.enable`` is 0: a position, hover height, ``takeoff``/``land`` height or
  ``go_to`` target is approached at up to :attr:`SitlDeviceModel.ext_speed` m/s (so "takeoff" is
  reaching the requested height), velocities are flown as given; low-level setpoints older than
  0.5 s (the firmware's commander watchdog) and ``stop`` leave the vehicle hovering in place
  (a simulation does not need to crash). While the app is enabled its velocity setpoint wins,
  as on the Crazyflie where the app's commander priority is above an idle client's.
* **App channel**: every packet is answered with :data:`APP_STATUS_FORMAT` (app status code,
  enable, psi, position) followed by the first bytes of the request (an echo for matching).
"""

from __future__ import annotations

import struct
import threading
import time
from pathlib import Path

import numpy as np

from polycc.errors import PolyccError
from polycc.sim.app_ffi import AppSim
from polycc.sim.crtp_device import DeviceModel, LogEntry, ParamEntry, ctype_from_log_type, ctype_from_param_type
from polycc.sim.dynamics import make_dynamics

APP_STATUS_FORMAT = "<BBffff"
"""App-channel reply head: polycc.status (uint8), polycc.enable (uint8), polycc.psi (m),
stateEstimate x, y, z (m); 18 bytes, followed by up to 12 bytes of the request."""
APP_STATUS_SIZE = struct.calcsize(APP_STATUS_FORMAT)
SETPOINT_TIMEOUT_MS = 500
"""Low-level setpoints older than this stop being flown (the firmware's commander watchdog)."""
EXT_GAIN = 2.0
"""1/s: proportional gain of the position-target model (takeoff, go_to, position, hover height)."""
MAX_CATCH_UP_MS = 1000
"""If the simulation falls this far behind the wall clock it skips ahead (counted in ``skips``)."""


def decode_app_status(data: bytes) -> dict[str, float]:
    """An app-channel reply of :class:`SitlDeviceModel` -> ``{status, enable, psi, x, y, z, echo}``."""
    status, enable, psi, x, y, z = struct.unpack(APP_STATUS_FORMAT, bytes(data[:APP_STATUS_SIZE]))
    return {"status": status, "enable": enable, "psi": psi, "x": x, "y": y, "z": z,
            "echo": bytes(data[APP_STATUS_SIZE:])}


class SitlDeviceModel(DeviceModel):
    """The host-built app for ``header`` (``polytopes.h`` or its folder) flying a vehicle model.

    Args:
        header: the scene header from ``polycc build``.
        start: initial position, m (the vehicle starts hovering there, velocity 0).
        dynamics: ``"crazyflie"`` (default), ``"integrator"`` or ``"quadrotor"`` (see :mod:`polycc.sim.dynamics`).
        delay_s: estimator delay, s (default: the model's own).
        rate_hz: initial ``polycc.rateHz`` (default: the app's).
        ext_speed: speed limit, m/s, when flying a client's position/takeoff/go_to target.
        estimate_noise_m: standard deviation, m, of white noise on the position estimate the app
            and the logs see (a real estimator never repeats itself bit for bit; with 0 a vehicle
            at rest makes the app report a stale estimate, status 4).
        seed: seed of that noise.

    The C app is one per process (its state lives in the extension module): create one model per
    header and :meth:`stop` it before making another for the same header.
    """

    def __init__(self, header: str | Path, start=(0.0, 0.0, 0.0), dynamics: str = "crazyflie",
                 delay_s: float | None = None, rate_hz: int | None = None, ext_speed: float = 1.0,
                 estimate_noise_m: float = 0.001, seed: int = 0) -> None:
        self.app = AppSim(header)
        self.app.reset()
        lib = self.app.lib
        params = []
        for e in self.app.param_toc():
            ctype, ro = ctype_from_param_type(e.type)
            params.append(ParamEntry(e.group, e.name, ctype, self._param_getter(e.index),
                                     None if ro else self._param_setter(e.index, e.full_name), read_only=ro))
        logs = [LogEntry(e.group, e.name, ctype_from_log_type(e.type), self._log_getter(e.index))
                for e in self.app.log_toc()]
        super().__init__(params, logs)
        self._i_status = self.app._log_index["polycc.status"]
        self._i_psi = self.app._log_index["polycc.psi"]
        self._i_enable = self.app._param_index["polycc.enable"]
        self.start_position = np.asarray(start, np.float64)
        if self.start_position.shape != (3,) or not np.all(np.isfinite(self.start_position)):
            raise PolyccError(f"start {start!r}: expected three finite numbers x, y, z in metres")
        self.dynamics_name = dynamics
        self.dyn = make_dynamics(dynamics, delay_s)
        self.dyn.reset(self.start_position)
        self.ext_speed = float(ext_speed)
        self.estimate_noise_m = float(estimate_noise_m)
        self._rng = np.random.default_rng(seed)
        if rate_hz is not None:
            self.app.set_param("polycc", "rateHz", rate_hz)
        self._rec = self.app.ffi.new("shim_commander_record_t *")
        self._section_us = self._worst_us()
        self.sim_ms = 0  # simulated FreeRTOS tick of the next app step
        self.steps = 0
        self.skips = 0
        self.step_errors = 0
        self.u = np.zeros(3)  # velocity setpoint flown in the last step, m/s
        self._ext: tuple[str, dict, int] | None = None  # (kind, values, time received in ms)
        self._hold = self.start_position.copy()  # hover target when nothing else applies
        self.setpoints: list[str] = []  # kinds received (last 100)
        self.appchannel_rx = 0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._t0 = time.monotonic()
        lib.shim_set_tick(0)

    # ------------------------------------------------------------------ table accessors
    def _param_getter(self, i: int):
        lib = self.app.lib
        return lambda: lib.shim_param_value(i)

    def _param_setter(self, i: int, name: str):
        lib = self.app.lib

        def set_(value):
            if lib.shim_param_set(i, float(value)) != 0:
                raise PolyccError(f"parameter {name} cannot be written")
        return set_

    def _log_getter(self, i: int):
        lib = self.app.lib
        return lambda: lib.shim_log_value(i)

    def _worst_us(self) -> int:
        """The cycle model's worst-case kernel time (as `polycc sim` gives the app); 0 if unavailable."""
        try:
            from polycc.budget import cycle_model

            return int(cycle_model.us(cycle_model.worst_cycles(self.app.packed_scene())))
        except Exception:  # evalUs is informative only
            return 0

    # ------------------------------------------------------------------ state
    @property
    def position(self) -> np.ndarray:
        return self.dyn.p.copy()

    @property
    def status(self) -> int:
        return int(self.app.lib.shim_log_value(self._i_status))

    @property
    def psi(self) -> float:
        return float(self.app.lib.shim_log_value(self._i_psi))

    @property
    def app_enabled(self) -> bool:
        return self.app.lib.shim_param_value(self._i_enable) != 0

    # ------------------------------------------------------------------ DeviceModel callbacks
    def on_setpoint(self, kind: str, values: dict[str, float]) -> None:
        self.setpoints = (self.setpoints + [kind])[-100:]
        now = self.sim_ms
        p = self.dyn.p
        if kind in ("hl_takeoff", "hl_land"):
            self._ext = ("target", {"x": p[0], "y": p[1], "z": float(values["height"])}, -1)
        elif kind == "hl_go_to":
            t = np.array([values["x"], values["y"], values["z"]], np.float64)
            if values.get("relative"):
                t = t + p
            self._ext = ("target", dict(zip("xyz", t.tolist())), -1)
        elif kind in ("hl_stop", "stop", "notify_setpoint_stop", "crash_recovery"):
            self._hold = p.copy()
            self._ext = None
        elif kind == "position":
            self._ext = ("target", {"x": values["x"], "y": values["y"], "z": values["z"]}, now)
        elif kind in ("velocity_world", "hover", "zdistance", "full_state"):
            self._ext = (kind, dict(values), now)
        # rpyt / manual (attitude and thrust) are not flown by this model: they are accepted only

    def on_appchannel(self, data: bytes) -> bytes | None:
        self.appchannel_rx += 1
        p = self.dyn.p
        head = struct.pack(APP_STATUS_FORMAT, self.status & 0xFF, int(self.app_enabled), self.psi,
                           float(p[0]), float(p[1]), float(p[2]))
        return head + bytes(data[:30 - APP_STATUS_SIZE])

    # ------------------------------------------------------------------ simulation
    def _toward(self, target: np.ndarray) -> np.ndarray:
        u = EXT_GAIN * (target - self.dyn.p)
        n = float(np.linalg.norm(u))
        return u * (self.ext_speed / n) if n > self.ext_speed else u

    def _client_velocity(self) -> np.ndarray:
        """What the client's latest setpoint asks for (m/s, world frame)."""
        if self._ext is None:
            return self._toward(self._hold)
        kind, v, t = self._ext
        if t >= 0 and self.sim_ms - t > SETPOINT_TIMEOUT_MS:
            self._hold = self.dyn.p.copy()
            self._ext = None
            return np.zeros(3)
        p = self.dyn.p
        if kind == "target":
            return self._toward(np.array([v["x"], v["y"], v["z"]]))
        if kind in ("velocity_world", "full_state"):
            if kind == "full_state":
                return self._toward(np.array([v["x"], v["y"], v["z"]])) + np.array([v["vx"], v["vy"], v["vz"]])
            return np.array([v["vx"], v["vy"], v["vz"]])
        if kind == "hover":  # body-frame velocity; the model does not yaw, so body = world
            return np.array([v["vx"], v["vy"], EXT_GAIN * (v["zdistance"] - p[2])])
        if kind == "zdistance":
            return np.array([0.0, 0.0, EXT_GAIN * (v["zdistance"] - p[2])])
        return np.zeros(3)

    def step(self) -> None:
        """One app tick at ``sim_ms`` and the vehicle flown for the app's period (caller holds ``lock``)."""
        lib = self.app.lib
        pe, ve = self.dyn.estimate()
        if self.estimate_noise_m > 0:
            pe = pe + self._rng.normal(0.0, self.estimate_noise_m, 3)
        lib.shim_set_estimate(float(pe[0]), float(pe[1]), float(pe[2]), float(ve[0]), float(ve[1]), float(ve[2]))
        period = max(1, self.app.tick(self.sim_ms, self.sim_ms * 1000, self._section_us))
        if self.app_enabled:
            lib.shim_commander_get(self._rec)
            u = np.array([self._rec.vx, self._rec.vy, self._rec.vz], np.float64)
            self._hold = self.dyn.p.copy()
            self._ext = None
        else:
            u = self._client_velocity()
        self.u = u
        self.dyn.step(u, period * 1e-3)
        self.sim_ms += period
        self.steps += 1

    def advance_to(self, t_ms: int, max_behind_ms: int | None = None) -> None:
        """Step until the simulated clock passes ``t_ms``; if it is more than ``max_behind_ms``
        behind, skip ahead instead (counted in ``skips``)."""
        with self.lock:
            if max_behind_ms is not None and t_ms - self.sim_ms > max_behind_ms:
                self.skips += 1
                self.sim_ms = t_ms
            while self.sim_ms <= t_ms:
                self.step()

    def time_ms(self) -> int:
        return int((time.monotonic() - self._t0) * 1000.0)

    def _run(self, poll_s: float) -> None:
        while not self._stop.is_set():
            try:
                self.advance_to(self.time_ms(), MAX_CATCH_UP_MS)
            except Exception:  # keep the drone alive; the count shows something is wrong
                self.step_errors += 1
                with self.lock:
                    self.sim_ms = self.time_ms() + 1
            self._stop.wait(poll_s)

    def start(self, poll_s: float = 0.002) -> "SitlDeviceModel":
        """Run the simulation in real time in a daemon thread; returns ``self``."""
        if self._thread is None:
            self._stop.clear()
            with self.lock:
                self._t0 = time.monotonic() - self.sim_ms * 1e-3
            self._thread = threading.Thread(target=self._run, args=(poll_s,), name="sitl-device", daemon=True)
            self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None

    def __enter__(self) -> "SitlDeviceModel":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    def summary(self) -> str:
        p = self.dyn.p
        return (f"t {self.sim_ms / 1000:.1f} s, position {p[0]:.2f},{p[1]:.2f},{p[2]:.2f} m, status {self.status}, "
                f"psi {self.psi:.3f} m, {'app enabled' if self.app_enabled else 'app disabled'}")

