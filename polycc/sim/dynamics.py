"""Vehicle models for the SITL: what the world does with the app's velocity setpoints.

Every model takes the commander's world-frame velocity setpoint ``u`` (m/s, held between
app ticks) and advances the true state by ``dt`` seconds.  ``estimate()`` gives what the
app's log lookup sees (``stateEstimate.x/y/z/vx/vy/vz``): the true state ``delay_s`` ago.

* :class:`SingleIntegrator` -- the paper's model, ``x' = u`` (exact for a held ``u``).
* :class:`CrazyflieLike` -- the velocity setpoint is tracked the way the stock Crazyflie
  2.1 PID cascade roughly does it: a proportional velocity loop whose output (a horizontal
  acceleration, i.e. a tilt, and a vertical acceleration, i.e. thrust) is saturated by the
  firmware's tilt limit and the motors' thrust range, realized through a first-order
  attitude/thrust lag, and seen through an estimator delay.  Parameters and sources are on
  :class:`CrazyflieParams`.
* :class:`Quadrotor` -- the full rigid body (thrust, torques, motor lag) under a Crazyflie-like
  PID cascade; parameters on :class:`QuadrotorParams`.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np

G = 9.81  # m/s^2


class _Delayed:
    """Ring buffer of (time, position, velocity) giving the state ``delay`` seconds ago."""

    def __init__(self, delay_s: float):
        self.delay = float(delay_s)
        self.buf: deque[tuple[float, np.ndarray, np.ndarray]] = deque()

    def reset(self, t: float, p: np.ndarray, v: np.ndarray | None = None) -> None:
        self.buf.clear()
        self.buf.append((t, p.copy(), np.zeros(3) if v is None else v.copy()))

    def push(self, t: float, p: np.ndarray, v: np.ndarray) -> None:
        if self.delay > 0.0:
            self.buf.append((t, p.copy(), v.copy()))
            while len(self.buf) > 2 and self.buf[1][0] <= t - self.delay:
                self.buf.popleft()

    def get(self, t: float, p_now: np.ndarray, v_now: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        if self.delay <= 0.0:
            return p_now, v_now
        target = t - self.delay
        best = self.buf[0]
        for item in self.buf:
            if item[0] <= target + 1e-12:
                best = item
            else:
                break
        return best[1], best[2]


class SingleIntegrator:
    """x' = u: the paper's simulation model (Δt = the app period)."""

    name = "integrator"

    def __init__(self, delay_s: float = 0.0):
        self.t = 0.0
        self.p = np.zeros(3)
        self.v = np.zeros(3)
        self._delay = _Delayed(delay_s)

    def reset(self, p0) -> None:
        self.t = 0.0
        self.p = np.asarray(p0, np.float64).copy()
        self.v = np.zeros(3)
        self._delay.reset(0.0, self.p)

    def step(self, u, dt: float) -> None:
        self.v = np.asarray(u, np.float64).copy()
        self.p = self.p + dt * self.v
        self.t += dt
        self._delay.push(self.t, self.p, self.v)

    def estimate(self) -> tuple[np.ndarray, np.ndarray]:
        """(position, velocity) as the estimator reports them (``delay_s`` old)."""
        return self._delay.get(self.t, self.p, self.v)


@dataclass(frozen=True)
class CrazyflieParams:
    """Crazyflie 2.1 velocity-tracking model (stock PID controller, velocity setpoints).

    Sources (numbers are read from, not copied code of, bitcraze/crazyflie-firmware at
    2a18fc29, ``src/platform/interface/platform_defaults_cf2.h`` and
    ``src/modules/src/controller/position_controller_pid.c``):

    - ``k_xy``: the velocity PID maps 1 m/s of error to PID_VEL_X_KP = 25 deg of tilt;
      a tilt θ gives g·tan θ of horizontal acceleration, so near hover the loop gain is
      25·π/180·g = 4.28 1/s (the small integral term, KI = 1, is left out).
    - ``tilt_max_deg``: PID_VEL_ROLL_MAX = PID_VEL_PITCH_MAX = 20 deg times the
      controller's rpLimitOverhead 1.10 = 22 deg, i.e. at most g·tan 22° = 3.96 m/s².
    - ``tau_att_s``: the attitude loop is a P controller with PID_ROLL_KP = 6 (1/s) around a
      much faster rate loop (PID_ROLL_RATE_KP = 250), so the tilt follows its setpoint with a
      time constant of about 1/6 s.
    - ``k_z``: PID_VEL_Z_KP = 25 times thrustScale 1000 = 25000 thrust units per m/s.  With
      the per-motor thrust curve of Förster (2015), f(c) = 2.130295e-11 c² + 1.032633e-6 c +
      5.484560e-4 N, the slope at hover (c ≈ 39000 for 29 g) is 2.7e-6 N per unit, so the
      loop gain is 4 · 2.7e-6 · 25000 / 0.029 kg = 9.3 1/s.
    - ``az_max`` / ``az_min``: thrust range.  Four motors at full command give 4 f(65535) =
      0.64 N (Förster 2015), thrust-to-weight 2.2 for CF_MASS = 29 g (firmware
      platform_defaults.h), so +1.2 g up; the velocity controller never commands less than
      PID_VEL_THRUST_MIN = 20000, 4 f(20000) = 0.12 N = 0.42 g, so -0.58 g down.
    - ``tau_z_s``: motor/propeller spin-up lag, about 0.05 s (assumed; Förster 2015 reports a
      first-order motor response of this order).
    - ``delay_s``: position estimate latency (Kalman filter with external position through
      the radio or Lighthouse), 20 ms assumed; not a measured value.
    - ``drag_xy``: effective horizontal drag, 1/s, that the velocity loop fights: rotor drag
      (9.18e-7 N per m/s per rad/s of summed rotor speed, Förster 2015: about 0.26 1/s at hover) plus the
      Kalman filter's flying model, which ignores the accelerometer's x/y (kalman_core.c) and so
      over-estimates the speed under drag. Calibrated against the real firmware in the SITL
      (polycc.sim.firmware, tests/sim/test_firmware_sitl.py): at a 0.5 m/s command it cruised at
      0.444 m/s with its estimate at 0.481 m/s; k_xy / (k_xy + drag_xy) = 0.889 gives 0.53 1/s.

    J. Förster, "System Identification of the Crazyflie 2.0 Nano Quadrocopter", BSc thesis,
    ETH Zürich, 2015.  Bitcraze, "Crazyflie 2.1 datasheet" (27 g take-off weight without
    decks; a positioning deck brings it to the firmware's 29 g).
    """

    k_xy: float = 25.0 * math.pi / 180.0 * G
    tilt_max_deg: float = 22.0
    tau_att_s: float = 1.0 / 6.0
    k_z: float = 9.3
    az_max: float = 1.2 * G
    az_min: float = -0.58 * G
    tau_z_s: float = 0.05
    delay_s: float = 0.020
    drag_xy: float = 0.53
    substep_s: float = 0.001


class CrazyflieLike:
    """First-order velocity tracking with tilt and thrust limits, attitude lag and estimator delay."""

    name = "crazyflie"

    def __init__(self, params: CrazyflieParams | None = None):
        self.prm = params or CrazyflieParams()
        self.t = 0.0
        self.p = np.zeros(3)
        self.v = np.zeros(3)
        self.a = np.zeros(3)
        self._delay = _Delayed(self.prm.delay_s)
        self._axy_max = G * math.tan(math.radians(self.prm.tilt_max_deg))

    def reset(self, p0) -> None:
        self.t = 0.0
        self.p = np.asarray(p0, np.float64).copy()
        self.v = np.zeros(3)
        self.a = np.zeros(3)
        self._delay.reset(0.0, self.p)

    def _a_des(self, u: np.ndarray) -> np.ndarray:
        P = self.prm
        axy = P.k_xy * (u[:2] - self.v[:2])
        n = math.hypot(axy[0], axy[1])
        if n > self._axy_max:
            axy = axy * (self._axy_max / n)
        axy = axy - P.drag_xy * self.v[:2]
        az = min(max(P.k_z * (u[2] - self.v[2]), P.az_min), P.az_max)
        return np.array([axy[0], axy[1], az])

    def step(self, u, dt: float) -> None:
        P = self.prm
        u = np.asarray(u, np.float64)
        n = max(1, int(round(dt / P.substep_s)))
        h = dt / n
        lag = np.array([P.tau_att_s, P.tau_att_s, P.tau_z_s])
        for _ in range(n):
            a_des = self._a_des(u)
            self.a = self.a + (h / lag) * (a_des - self.a) if np.all(lag > h) else a_des
            self.v = self.v + h * self.a
            self.p = self.p + h * self.v
            self.t += h
            self._delay.push(self.t, self.p, self.v)

    def estimate(self) -> tuple[np.ndarray, np.ndarray]:
        """(position, velocity) as the estimator reports them (``delay_s`` old)."""
        return self._delay.get(self.t, self.p, self.v)


# Förster (2015): thrust of one Crazyflie motor+propeller against its 16-bit command c, N.
THRUST_COEFFS = (2.130295e-11, 1.032633e-6, 5.484560e-4)
CMD_MAX = 65535.0


def motor_thrust(c):
    c = np.clip(c, 0.0, CMD_MAX)
    a, b, k = THRUST_COEFFS
    return np.where(c > 0.0, (a * c + b) * c + k, 0.0)


def motor_command(f: float) -> float:
    """Inverse of :func:`motor_thrust` (command for thrust ``f`` N)."""
    a, b, k = THRUST_COEFFS
    return (-b + math.sqrt(b * b + 4.0 * a * (f - k))) / (2.0 * a)


@dataclass(frozen=True)
class QuadrotorParams:
    """Crazyflie 2.1 rigid body under the stock PID cascade (velocity -> attitude -> rate -> mixer).

    Rigid body (Förster 2015): mass 0.029 kg (firmware CF_MASS), arm 0.046 m (centre to
    motor, X configuration), inertia diag(16.57, 16.66, 29.26) 1e-6 kg m², per-motor thrust
    curve :data:`THRUST_COEFFS`, yaw drag torque 0.005964552 m times thrust.  Controller
    constants from crazyflie-firmware 2a18fc29 platform_defaults_cf2.h: velocity loop at
    100 Hz (PID_VEL_X_KP 25 deg per m/s, KI 1, tilt limit 20 deg x 1.1; PID_VEL_Z_KP 25 and
    KI 15 times thrustScale 1000, thrust base 36000, minimum 20000), attitude loop
    (PID_ROLL_KP 6, PID_YAW_KP 6) and rate loop (PID_ROLL_RATE_KP 250, PID_YAW_RATE_KP 120,
    command units per deg/s) at 500 Hz, legacy X mixer.  The integral terms of the attitude
    and rate loops and aerodynamic drag are left out; the motor lag (0.05 s) and the 20 ms
    estimator delay are assumptions as in :class:`CrazyflieParams`.
    """

    mass: float = 0.029
    arm: float = 0.046
    inertia: tuple[float, float, float] = (16.571710e-6, 16.655602e-6, 29.261652e-6)
    yaw_drag: float = 0.005964552
    motor_tau_s: float = 0.05
    vel_kp_deg: float = 25.0
    vel_ki_deg: float = 1.0
    tilt_max_deg: float = 22.0
    velz_kp: float = 25000.0
    velz_ki: float = 15000.0
    thrust_base: float = 36000.0
    thrust_min: float = 20000.0
    att_kp: float = 6.0
    yaw_kp: float = 6.0
    rate_kp: float = 250.0
    yaw_rate_kp: float = 120.0
    vel_period_s: float = 0.01
    att_period_s: float = 0.002
    delay_s: float = 0.020
    substep_s: float = 0.001


def _rodrigues(w: np.ndarray) -> np.ndarray:
    th = float(np.linalg.norm(w))
    if th < 1e-12:
        return np.eye(3)
    k = w / th
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + math.sin(th) * K + (1.0 - math.cos(th)) * (K @ K)


class Quadrotor:
    """Full rigid-body quadrotor flown by a Crazyflie-like PID cascade (z up, body x forward)."""

    name = "quadrotor"

    def __init__(self, params: QuadrotorParams | None = None):
        self.prm = params or QuadrotorParams()
        P = self.prm
        self.J = np.array(P.inertia)
        a = P.arm / math.sqrt(2.0)
        # Motors 1..4 at front-right, back-right, back-left, front-left; 1 and 3 spin one way.
        self.pos = np.array([[a, -a], [-a, -a], [-a, a], [a, a]])
        self.spin = np.array([1.0, -1.0, 1.0, -1.0])
        self.f_hover = P.mass * G / 4.0
        self.c_hover = motor_command(self.f_hover)
        self._delay = _Delayed(P.delay_s)
        self.reset(np.zeros(3))

    def reset(self, p0) -> None:
        P = self.prm
        self.t = 0.0
        self.p = np.asarray(p0, np.float64).copy()
        self.v = np.zeros(3)
        self.R = np.eye(3)
        self.w = np.zeros(3)
        self.f = np.full(4, self.f_hover)
        self.i_xy = np.zeros(2)
        self.i_z = (self.c_hover - P.thrust_base) / P.velz_ki  # start in trimmed hover
        self.att_des = np.zeros(2)
        self.thrust_cmd = self.c_hover
        self.cmd = np.full(4, self.c_hover)
        self._t_vel = 0.0
        self._t_att = 0.0
        self._delay.reset(0.0, self.p)

    @property
    def a(self) -> np.ndarray:
        return self.R @ np.array([0.0, 0.0, self.f.sum() / self.prm.mass]) - np.array([0.0, 0.0, G])

    def euler_deg(self) -> np.ndarray:
        R = self.R
        roll = math.atan2(R[2, 1], R[2, 2])
        pitch = math.asin(max(-1.0, min(1.0, -R[2, 0])))
        yaw = math.atan2(R[1, 0], R[0, 0])
        return np.degrees([roll, pitch, yaw])

    def _velocity_loop(self, u: np.ndarray) -> None:
        P = self.prm
        dt = P.vel_period_s
        yaw = math.radians(self.euler_deg()[2])
        c, s = math.cos(yaw), math.sin(yaw)
        e = u - self.v
        eb = np.array([c * e[0] + s * e[1], -s * e[0] + c * e[1]])  # error in the yaw frame
        self.i_xy = np.clip(self.i_xy + eb * dt, -P.tilt_max_deg / max(P.vel_ki_deg, 1e-9),
                            P.tilt_max_deg / max(P.vel_ki_deg, 1e-9))
        out = P.vel_kp_deg * eb + P.vel_ki_deg * self.i_xy
        pitch = min(max(out[0], -P.tilt_max_deg), P.tilt_max_deg)  # +pitch: thrust tilts to +x
        roll = min(max(-out[1], -P.tilt_max_deg), P.tilt_max_deg)  # -roll: thrust tilts to +y
        self.att_des = np.array([roll, pitch])
        self.i_z = min(max(self.i_z + e[2] * dt, -5.0), 5.0)
        self.thrust_cmd = min(max(P.thrust_base + P.velz_kp * e[2] + P.velz_ki * self.i_z, P.thrust_min), CMD_MAX)

    def _attitude_loop(self) -> None:
        P = self.prm
        eul = self.euler_deg()
        w_deg = np.degrees(self.w)
        rate_des = np.array([P.att_kp * (self.att_des[0] - eul[0]), P.att_kp * (self.att_des[1] - eul[1]),
                             P.yaw_kp * (0.0 - eul[2])])
        r = P.rate_kp * (rate_des[0] - w_deg[0])
        q = P.rate_kp * (rate_des[1] - w_deg[1])
        y = P.yaw_rate_kp * (rate_des[2] - w_deg[2])
        T = self.thrust_cmd
        # roll +: motors 3, 4 (left, +y) up; pitch +: motors 2, 3 (back) up; yaw +: motors 1, 3 (spin +1) up
        self.cmd = np.clip(np.array([T - r / 2 - q / 2 + y, T - r / 2 + q / 2 - y, T + r / 2 + q / 2 + y,
                                     T + r / 2 - q / 2 - y]), 0.0, CMD_MAX)

    def step(self, u, dt: float) -> None:
        P = self.prm
        u = np.asarray(u, np.float64)
        n = max(1, int(round(dt / P.substep_s)))
        h = dt / n
        m = P.mass
        for _ in range(n):
            if self.t + 1e-12 >= self._t_vel:
                self._velocity_loop(u)
                self._t_vel += P.vel_period_s
            if self.t + 1e-12 >= self._t_att:
                self._attitude_loop()
                self._t_att += P.att_period_s
            f_target = motor_thrust(self.cmd)
            self.f = self.f + (h / P.motor_tau_s) * (f_target - self.f)
            tau = np.array([np.sum(self.pos[:, 1] * self.f), -np.sum(self.pos[:, 0] * self.f),
                            P.yaw_drag * np.sum(self.spin * self.f)])
            wdot = (tau - np.cross(self.w, self.J * self.w)) / self.J
            acc = self.R @ np.array([0.0, 0.0, self.f.sum() / m]) - np.array([0.0, 0.0, G])
            self.v = self.v + h * acc
            self.p = self.p + h * self.v
            self.w = self.w + h * wdot
            self.R = self.R @ _rodrigues(self.w * h)
            self.t += h
            self._delay.push(self.t, self.p, self.v)
        U, _, Vt = np.linalg.svd(self.R)  # keep R a rotation
        self.R = U @ Vt

    def estimate(self) -> tuple[np.ndarray, np.ndarray]:
        """(position, velocity) as the estimator reports them (``delay_s`` old)."""
        return self._delay.get(self.t, self.p, self.v)


DYNAMICS = {"integrator": SingleIntegrator, "crazyflie": CrazyflieLike, "quadrotor": Quadrotor}


def make_dynamics(name: str, delay_s: float | None = None):
    """A fresh model by name; ``delay_s`` overrides the estimator delay."""
    if name == "integrator":
        return SingleIntegrator(0.0 if delay_s is None else delay_s)
    if name == "crazyflie":
        prm = CrazyflieParams() if delay_s is None else CrazyflieParams(delay_s=delay_s)
        return CrazyflieLike(prm)
    if name == "quadrotor":
        return Quadrotor(QuadrotorParams() if delay_s is None else QuadrotorParams(delay_s=delay_s))
    raise ValueError(f"unknown dynamics {name!r}; choose one of {', '.join(DYNAMICS)}")


@dataclass(frozen=True)
class PositionLoop:
    """The stock PID controller's position loop, which turns position setpoints into velocity
    setpoints (crazyflie-firmware position_controller_pid.c, platform defaults: posCtlPid xKp = yKp
    = zKp = 2 1/s, no integral or derivative term; xVelMax = yVelMax = 1 m/s, zVelMax = 1 m/s)."""

    kp_xy: float = 2.0
    kp_z: float = 2.0
    vmax_xy: float = 1.0
    vmax_z: float = 1.0
    hover_thrust: float = 36000.0  # stabilizer.thrust the app sees while the motors run


def velocity_command(sp, p: np.ndarray, v: np.ndarray, loop: PositionLoop = PositionLoop()) -> np.ndarray:
    """World-frame velocity the firmware's PID cascade aims for under setpoint ``sp`` (a
    ``shim_setpoint_t``: modes 0 disable, 1 absolute, 2 velocity)."""
    yaw = math.radians(float(sp.yaw)) if sp.mode_yaw == 1 else 0.0
    sv = np.array([sp.vx, sp.vy, sp.vz], np.float64)
    if sp.velocity_body:  # hover setpoints: body-frame x/y (the models keep yaw 0)
        c, s = math.cos(yaw), math.sin(yaw)
        sv[:2] = [c * sv[0] - s * sv[1], s * sv[0] + c * sv[1]]
    spp = np.array([sp.px, sp.py, sp.pz], np.float64)
    u = v.copy()  # mode disable: no horizontal command (level attitude keeps the velocity)
    for i, mode in enumerate((sp.mode_x, sp.mode_y, sp.mode_z)):
        kp, vmax = (loop.kp_z, loop.vmax_z) if i == 2 else (loop.kp_xy, loop.vmax_xy)
        if mode == 1:
            u[i] = min(max(sv[i] + kp * (spp[i] - p[i]), -vmax), vmax)
        elif mode == 2:
            u[i] = sv[i]
    return u


class Vehicle:
    """A vehicle model flown by the setpoint the firmware's controller gets (``shim_setpoint_t``
    from :func:`shim_stabilizer_step` or the real firmware's log), with the motors-off case and a
    floor at ``floor_z`` (m): with the null setpoint the motors stop and the vehicle falls; on the
    floor it rests (``impact_speed_ms`` records the fastest touchdown, m/s)."""

    def __init__(self, model, floor_z: float = 0.0, loop: PositionLoop = PositionLoop()):
        self.model = model
        self.floor_z = float(floor_z)
        self.loop = loop
        delay = getattr(getattr(model, "prm", None), "delay_s", None)
        if delay is None:
            delay = model._delay.delay
        self._delay = _Delayed(delay)
        self.motors_on = False
        self.impact_speed_ms = 0.0
        self.t = 0.0

    @property
    def p(self) -> np.ndarray:
        return self.model.p

    @property
    def v(self) -> np.ndarray:
        return self.model.v

    @property
    def name(self) -> str:
        return self.model.name

    def reset(self, p0, motors_on: bool = True) -> None:
        self.model.reset(p0)
        self.t = 0.0
        self.motors_on = motors_on
        self.impact_speed_ms = 0.0
        self._delay.reset(0.0, self.model.p, self.model.v)

    @property
    def on_floor(self) -> bool:
        return self.model.p[2] <= self.floor_z + 1e-9 and abs(self.model.v[2]) < 1e-9

    def thrust(self) -> float:
        return self.loop.hover_thrust if self.motors_on else 0.0

    def _floor(self) -> None:
        m = self.model
        if m.p[2] < self.floor_z:
            self.impact_speed_ms = max(self.impact_speed_ms, -float(m.v[2]))
            m.p[2] = self.floor_z
            m.v = np.zeros(3) if not self.motors_on else np.array([m.v[0], m.v[1], max(0.0, m.v[2])])

    def step(self, sp, dt: float) -> None:
        m = self.model
        if not sp.motors_on:
            if self.motors_on:
                self.motors_on = False
            if not self.on_floor:  # free fall
                m.v = m.v + dt * np.array([0.0, 0.0, -G])
                m.p = m.p + dt * m.v
            m.t += dt
            self._floor()
        else:
            if not self.motors_on:  # spin up from rest (on the floor, or after a cut in the air)
                v0 = m.v.copy()
                m.reset(m.p.copy())
                m.v = v0 if not self.on_floor else np.zeros(3)
                self.motors_on = True
            u = velocity_command(sp, m.p, m.v, self.loop)
            m.step(u, dt)
            self._floor()
        self.t += dt
        self._delay.push(self.t, m.p, m.v)

    def estimate(self) -> tuple[np.ndarray, np.ndarray]:
        """(position, velocity) as the estimator reports them (the model's delay)."""
        return self._delay.get(self.t, self.model.p, self.model.v)
