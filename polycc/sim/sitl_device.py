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
* **Flight control** follows the firmware: every client setpoint (cflib's commander, generic and
  high-level packets) goes into the host model of the commander, high-level commander and
  supervisor (``polycc/sim/shims/sim_commander.c``) at CRTP priority, as the app's go in at its own;
  each 1 ms tick the setpoint the controller would get is flown by the vehicle model
  (:class:`~polycc.sim.dynamics.Vehicle`). So, as on a Crazyflie, a stop setpoint or a stopped
  high-level planner after a relax cuts the motors and the vehicle falls; a setpoint older than
  0.5 s levels it and older than 2 s cuts the motors; HL takeoff/go_to/land fly 7th-order
  trajectories; ``stabilizer.controller`` selects the controller the app checks.
* **App channel**: packets go to the app (its heartbeat watchdog), which answers each with its
  status (``polycc.onboard.app.REPLY_FORMAT``) from its next tick.
* :meth:`SitlDeviceModel.cut_link` simulates link loss (``crtpIsConnected`` false, packets dropped).
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
from polycc.sim.dynamics import Vehicle, make_dynamics, velocity_command

CRTP_PRIORITY = 2  # COMMANDER_PRIORITY_CRTP
APP_STATUS_FORMAT = "<BBffff"
"""App-channel reply head: polycc.status (uint8), polycc.enable (uint8), polycc.psi (m),
stateEstimate x, y, z (m); 18 bytes, followed by up to 12 bytes of the request."""
APP_STATUS_SIZE = struct.calcsize(APP_STATUS_FORMAT)
RADIO_TIMEOUT_MS = 1000
"""crtpIsConnected() on the radio turns false this long after the last packet (CONFIG_RADIO_ACTIVITY_TIMEOUT_MS)."""
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
        start: initial position, m (on the floor if ``on_floor``, else hovering there under the
            high-level commander, as after a takeoff).
        dynamics: ``"crazyflie"`` (default), ``"integrator"`` or ``"quadrotor"`` (see :mod:`polycc.sim.dynamics`).
        delay_s: estimator delay, s (default: the model's own).
        rate_hz: initial ``polycc.rateHz`` (default: the app's).
        estimate_noise_m: standard deviation, m, of white noise on the position estimate the app
            and the logs see (a real estimator never repeats itself bit for bit; with 0 a vehicle
            at rest makes the app report a stale estimate, status 4).
        seed: seed of that noise.

    The C app is one per process (its state lives in the extension module): create one model per
    header and :meth:`stop` it before making another for the same header.
    """

    def __init__(self, header: str | Path, start=(0.0, 0.0, 0.0), dynamics: str = "crazyflie",
                 delay_s: float | None = None, rate_hz: int | None = None,
                 estimate_noise_m: float = 0.001, seed: int = 0, on_floor: bool = False,
                 floor_z: float | None = None) -> None:
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
        self.floor_z = float(self.start_position[2] if on_floor else -1e3) if floor_z is None else float(floor_z)
        self.dyn = Vehicle(make_dynamics(dynamics, delay_s), floor_z=self.floor_z)
        self.dyn.reset(self.start_position, motors_on=not on_floor)
        self.estimate_noise_m = float(estimate_noise_m)
        self._rng = np.random.default_rng(seed)
        if rate_hz is not None:
            self.app.set_param("polycc", "rateHz", rate_hz)
        ffi = self.app.ffi
        self._rec = ffi.new("shim_commander_record_t *")
        self._sp = ffi.new("shim_setpoint_t *")
        self._client = ffi.new("shim_setpoint_t *")
        self._pos = ffi.new("float[3]")
        self._vel = ffi.new("float[3]")
        self._app_buf = ffi.new("unsigned char[32]")
        self._outgoing: list[bytes] = []
        self._link_cut_until = -1
        self._cut_start = -1
        self._section_us = self._worst_us()
        self.sim_ms = 0  # simulated FreeRTOS tick of the next stabilizer step
        self._next_app = 0
        self.steps = 0
        self.skips = 0
        self.step_errors = 0
        self.u = np.zeros(3)  # velocity the controller aimed for in the last step, m/s
        self.setpoints: list[str] = []  # kinds received (last 100)
        self.appchannel_rx = 0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._t0 = time.monotonic()
        lib.shim_set_tick(0)
        if not on_floor:  # airborne, hovering under the high-level commander as after a takeoff
            lib.shim_hl_hover_at(*(float(v) for v in self.start_position))

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

    @property
    def motors_on(self) -> bool:
        return bool(self.dyn.motors_on)

    # ------------------------------------------------------------------ DeviceModel callbacks
    def _set_client(self, motors: bool, mode=(0, 0, 0), p=(0.0, 0.0, 0.0), v=(0.0, 0.0, 0.0), a=(0.0, 0.0, 0.0),
                    yaw_mode: int = 2, yaw: float = 0.0, yaw_rate: float = 0.0, body: bool = False,
                    rp=None, thrust: float = 0.0) -> None:
        c = self._client
        c.motors_on = int(motors)
        c.mode_x, c.mode_y, c.mode_z = (int(m) for m in mode)
        c.mode_roll = c.mode_pitch = 1 if rp is not None else 0
        c.mode_yaw = yaw_mode
        c.velocity_body = int(body)
        c.px, c.py, c.pz = (float(x) for x in p)
        c.vx, c.vy, c.vz = (float(x) for x in v)
        c.ax, c.ay, c.az = (float(x) for x in a)
        c.roll, c.pitch = (float(x) for x in (rp or (0.0, 0.0)))
        c.yaw, c.yaw_rate, c.thrust = float(yaw), float(yaw_rate), float(thrust)
        self.app.lib.shim_commander_set(c, CRTP_PRIORITY)

    def on_setpoint(self, kind: str, values: dict[str, float]) -> None:
        """A client's commander or high-level packet, into the firmware model (caller holds ``lock``)."""
        self.setpoints = (self.setpoints + [kind])[-100:]
        if self.link_cut:
            return
        lib, v = self.app.lib, values
        if kind == "stop":
            self._set_client(False)
        elif kind == "rpyt":
            if v["thrust"] <= 0:
                self._set_client(False)
            else:  # attitude flight is not modelled: hold the altitude, level
                self._set_client(True, mode=(0, 0, 2), rp=(0.0, 0.0), yaw_rate=v["yawrate"], thrust=v["thrust"])
        elif kind == "velocity_world":
            self._set_client(True, mode=(2, 2, 2), v=(v["vx"], v["vy"], v["vz"]), yaw_rate=v["yawrate"])
        elif kind == "hover":
            self._set_client(True, mode=(2, 2, 1), v=(v["vx"], v["vy"], 0.0), p=(0.0, 0.0, v["zdistance"]),
                             yaw_rate=v["yawrate"], body=True)
        elif kind == "zdistance":
            self._set_client(True, mode=(0, 0, 1), p=(0.0, 0.0, v["zdistance"]), rp=(v["roll"], v["pitch"]),
                             yaw_rate=v["yawrate"])
        elif kind == "position":
            self._set_client(True, mode=(1, 1, 1), p=(v["x"], v["y"], v["z"]), yaw_mode=1, yaw=v["yaw"])
        elif kind == "full_state":
            self._set_client(True, mode=(1, 1, 1), p=(v["x"], v["y"], v["z"]), v=(v["vx"], v["vy"], v["vz"]),
                             a=(v["ax"], v["ay"], v["az"]))
        elif kind == "manual":
            self._set_client(v["thrust"] > 0, mode=(0, 0, 2), rp=(v["roll"], v["pitch"]), thrust=v["thrust"])
        elif kind == "notify_setpoint_stop":
            lib.shim_commander_notify_stop(int(v["remain_valid_ms"]))
        elif kind == "hl_takeoff":
            lib.crtpCommanderHighLevelTakeoff(float(v["height"]), float(v["duration"]))
        elif kind == "hl_land":
            lib.crtpCommanderHighLevelLand(float(v["height"]), float(v["duration"]))
        elif kind == "hl_go_to":
            lib.crtpCommanderHighLevelGoTo(float(v["x"]), float(v["y"]), float(v["z"]), float(v["yaw"]),
                                           float(v["duration"]), bool(v["relative"]))
        elif kind == "hl_stop":
            lib.crtpCommanderHighLevelStop()
        # arm, crash_recovery, hl_set_group_mask: nothing to model

    def on_appchannel(self, data: bytes) -> bytes | None:
        """To the app's channel; its reply comes from its next tick (:meth:`outgoing_appchannel`)."""
        self.appchannel_rx += 1
        if not self.link_cut:
            self.app.lib.shim_appchannel_push(data, len(data))
        return None

    def outgoing_appchannel(self) -> list[bytes]:
        out, self._outgoing = self._outgoing, []
        return [] if self.link_cut else out

    @property
    def link_cut(self) -> bool:
        return self.sim_ms < self._link_cut_until

    def cut_link(self, seconds: float) -> None:
        """Link loss for ``seconds``: packets both ways are dropped and ``crtpIsConnected`` is false
        (what the radio link reports after 1 s without packets)."""
        with self.lock:
            self._cut_start = self.sim_ms
            self._link_cut_until = self.sim_ms + int(seconds * 1000)

    # ------------------------------------------------------------------ simulation
    def step(self) -> None:
        """One 1 ms tick at ``sim_ms``: the app when due, the stabilizer's setpoint choice and the
        vehicle (caller holds ``lock``)."""
        lib = self.app.lib
        lib.shim_set_tick(self.sim_ms & 0xFFFFFFFF)
        # the radio link's crtpIsConnected: false 1 s after the last packet
        lib.shim_set_connected(0 if self.link_cut and self.sim_ms - self._cut_start >= RADIO_TIMEOUT_MS else 1)
        if self.sim_ms >= self._next_app:
            pe, ve = self.dyn.estimate()
            if self.estimate_noise_m > 0:
                pe = pe + self._rng.normal(0.0, self.estimate_noise_m, 3)
            lib.shim_set_estimate(float(pe[0]), float(pe[1]), float(pe[2]), float(ve[0]), float(ve[1]),
                                  float(ve[2]))
            lib.shim_set_attitude(0.0, 0.0, 0.0, self.dyn.thrust())
            lib.shim_set_usec(self.sim_ms * 1000, self._section_us)
            period = max(1, int(lib.polycc_app_tick()))
            self._next_app = self.sim_ms + period
            self.steps += 1
            while True:
                n = lib.shim_appchannel_pop(self._app_buf, 30)
                if n == 0:
                    break
                self._outgoing.append(bytes(self.app.ffi.buffer(self._app_buf, n)))
        if lib.controllerGetType() == lib.ControllerTypeOot:  # the shield's controller sees the estimate
            pe, ve = self.dyn.estimate()
            acc = getattr(self.dyn.model, "a", np.zeros(3)) if self.dyn.motors_on else np.zeros(3)
            lib.shim_set_acceleration(float(acc[0]), float(acc[1]), float(acc[2]))
            self._pos[0:3] = pe.tolist()
            self._vel[0:3] = ve.tolist()
        else:
            self._pos[0:3] = self.dyn.p.tolist()
            self._vel[0:3] = self.dyn.v.tolist()
        lib.shim_stabilizer_step(self._pos, self._vel, 0.0, self._sp)
        self.u = velocity_command(self._sp, self.dyn.p, self.dyn.v) if self._sp.motors_on else np.zeros(3)
        self.dyn.step(self._sp, 1e-3)
        self.sim_ms += 1

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

