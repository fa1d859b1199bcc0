"""Rigid-body Crazyflie 2.x model and the CrazySim SITL wire formats (numpy + stdlib only).

Frames: world is x/y horizontal, z up (the firmware's and EXT_POSE's frame); body is FLU
(x forward, y left, z up), the frame of the SITL's IMU packets.  Quaternions are
(w, x, y, z), body -> world.

Constants, with where they come from (paths inside the CrazySim SITL tree):

* mass 0.0282 kg = base_link 0.025 + 4 props x 0.0008, inertia diag(1.6572e-5, 1.6656e-5,
  2.9262e-5) kg m^2 (base_link), rotor positions (+-0.031, +-0.031) m, motor time constants
  up 0.0125 s / down 0.025 s, rotor drag coefficient 9.1785e-7 N s/m per rad/s:
  ``tools/crazyflie-simulation/simulator_files/gazebo/models/crazyflie/model.sdf.jinja``;
* thrust per motor F = 0.091492681 p^2 + 0.067673604 p, p = pwm / 65535, and the yaw moment
  per newton 0.005964552 m: ``src/modules/src/power_distribution_sitl.c:67-71``;
* pwm -> rotor speed (for the drag term only) w = 0.04076521 pwm + 380.8359 rad/s, 0 below
  pwm 1000: ``.../plugins/CrazySim/CrtpUtils.h`` (PWM2OMEGA);
* motor layout M1 front-right, M2 back-right, M3 back-left, M4 front-left; M1 and M3 turn
  counter-clockwise seen from above (reaction moment -z), M2 and M4 clockwise (+z).  This
  is the sign convention of the firmware's force/torque mixer
  (``power_distribution_sitl.c:124-127``: m1 = T - roll - pitch - yaw) and of the legacy
  mixer with the PID controller's ``control->yaw = -control->yaw``
  (``src/modules/src/controller/controller_pid.c:131``); it matches the SDF's
  ``turningDirection`` (m1 ccw, m2 cw, m3 ccw, m4 cw);
* IMU scaling 1/2048 g and 4000/65536 deg/s per LSB: ``src/hal/src/sensors_sitl.c:47-48``.

Ground contact: a flat floor.  The body origin rests at ``ground_z`` (default 0, so the
Kalman estimate reads z = 0 on the floor).  While the thrust cannot lift the weight the
vehicle sits still and level (static friction, no bounce); the accelerometer then reads
the normal force (+1 g on body z).  Every touchdown with a downward speed above
``IMPACT_MIN_SPEED`` is recorded as an :class:`Impact`.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass

import numpy as np

G = 9.81  # m/s^2, the firmware's GRAVITY_MAGNITUDE
PWM_MAX = 65535.0

# --------------------------------------------------------------------------- SITL packets
HDR_SIM = 0x90            # CRTP port 9 (CRTP_PORT_SETPOINT_SIM), channel 0
HDR_EXT_POSE = 0x61       # CRTP port 6 (localization), channel 1 (generic)
EXT_POSE_TYPE = 8         # EXT_POSE in crtp_localization_service.h
HANDSHAKE = b"\xf3"
SENSOR_GYRO_ACC = 0
ACC_LSB_G = 32.0 / 65536.0          # sensors_sitl.c SENSORS_G_PER_LSB_CFG
GYRO_LSB_DPS = 4000.0 / 65536.0     # sensors_sitl.c SENSORS_DEG_PER_LSB_CFG

_IMU = struct.Struct("<BB6h")
_POSE = struct.Struct("<BB7f")
_MOTORS = struct.Struct("<B4H")


def _i16(v: float) -> int:
    return max(-32768, min(32767, int(round(v))))


def encode_imu(acc_g, gyro_dps) -> bytes:
    """IMU packet (0x90, type 0): int16 acc[3] (1/2048 g) then int16 gyro[3] (4000/65536 deg/s),
    body frame FLU."""
    return _IMU.pack(HDR_SIM, SENSOR_GYRO_ACC,
                     _i16(acc_g[0] / ACC_LSB_G), _i16(acc_g[1] / ACC_LSB_G), _i16(acc_g[2] / ACC_LSB_G),
                     _i16(gyro_dps[0] / GYRO_LSB_DPS), _i16(gyro_dps[1] / GYRO_LSB_DPS),
                     _i16(gyro_dps[2] / GYRO_LSB_DPS))


def encode_ext_pose(pos, quat_wxyz) -> bytes:
    """EXT_POSE packet (0x61, id 8): float x, y, z, qx, qy, qz, qw."""
    w, x, y, z = quat_wxyz
    return _POSE.pack(HDR_EXT_POSE, EXT_POSE_TYPE, float(pos[0]), float(pos[1]), float(pos[2]),
                      float(x), float(y), float(z), float(w))


def is_motor_packet(data: bytes) -> bool:
    """Motor packets are the only 9-byte datagrams with header 0x90 (power_distribution_sitl.c)."""
    return len(data) == 9 and data[0] == HDR_SIM


def decode_motors(data: bytes) -> tuple[int, int, int, int]:
    return _MOTORS.unpack(data)[1:]


def is_calibrated_packet(data: bytes) -> bool:
    """The firmware answers ``0x90 0x01`` once when the gyro bias is found (sensors_sitl.c:217-223)."""
    return len(data) == 2 and data[0] == HDR_SIM and data[1] == 1


# --------------------------------------------------------------------------- model
@dataclass
class QuadParams:
    mass: float = 0.025 + 4 * 0.0008
    inertia: tuple = (1.6572e-5, 1.6656e-5, 2.9262e-5)
    rotor_xy: tuple = ((0.031, -0.031), (-0.031, -0.031), (-0.031, 0.031), (0.031, 0.031))  # M1..M4
    # reaction moment sign per unit thrust: M1, M3 ccw (-z); M2, M4 cw (+z)
    yaw_sign: tuple = (-1.0, 1.0, -1.0, 1.0)
    thrust_a: float = 0.091492681
    thrust_b: float = 0.067673604
    thrust_to_torque: float = 0.005964552
    tau_up: float = 0.0125
    tau_down: float = 0.025
    rotor_drag_xy: float = 9.1785e-7     # N per (m/s) per (rad/s) of summed rotor speed
    rotor_drag_z: float = 10.311e-7      # (Foerster 2015; the SDF has only the xy value)
    ground_z: float = 0.0
    gyro_noise_dps: float = 0.0          # white noise std on each IMU sample
    acc_noise_g: float = 0.0
    seed: int = 0


IMPACT_MIN_SPEED = 0.05  # m/s: slower touchdowns are not recorded


@dataclass
class Impact:
    t: float          # sim time, s
    speed: float      # |v| at touchdown, m/s
    vz: float         # vertical velocity at touchdown (negative), m/s
    pos: tuple        # where
    thrust_n: float   # total commanded thrust at touchdown, N


def pwm_to_thrust(pwm, a=QuadParams.thrust_a, b=QuadParams.thrust_b):
    """The firmware's thrust model, N per motor."""
    p = np.clip(np.asarray(pwm, float) / PWM_MAX, 0.0, 1.0)
    return a * p * p + b * p


def pwm_to_omega(pwm):
    """CrazySim's PWM2OMEGA (rad/s)."""
    pwm = np.asarray(pwm, float)
    return np.where(pwm < 1000.0, 0.0, 0.04076521 * pwm + 380.8359)


def quat_to_rot(q) -> np.ndarray:
    w, x, y, z = q
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def quat_mul(a, b) -> np.ndarray:
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return np.array([aw * bw - ax * bx - ay * by - az * bz,
                     aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx,
                     aw * bz + ax * by - ay * bx + az * bw])


def yaw_of(q) -> float:
    w, x, y, z = q
    return math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))


def quat_from_yaw(yaw: float) -> np.ndarray:
    return np.array([math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)])


class Quadrotor:
    """6-DoF rigid body with four first-order motors, rotor drag and a floor.

    ``step(dt, pwm)`` advances by ``dt`` with the motor PWM command (4 uint16, M1..M4);
    ``imu()`` returns (specific force in g, angular rate in deg/s), body FLU, for the state
    after the last step.  The hot path uses plain floats (a 1 kHz loop in CPython: about
    25 us per step instead of about 190 us with 3-element numpy arrays); the attributes
    ``pos``, ``vel``, ``q``, ``omega`` are numpy views built on demand."""

    def __init__(self, params: QuadParams | None = None, pos=(0.0, 0.0, 0.0), yaw: float = 0.0):
        self.p = P = params or QuadParams()
        self._J = tuple(float(j) for j in P.inertia)
        self._rx = tuple(float(r[0]) for r in P.rotor_xy)
        self._ry = tuple(float(r[1]) for r in P.rotor_xy)
        self._ys = tuple(float(s) for s in P.yaw_sign)
        self.rng = np.random.default_rng(P.seed)
        self.t = 0.0
        self._p = [float(pos[0]), float(pos[1]), max(float(pos[2]), P.ground_z)]
        self._v = [0.0, 0.0, 0.0]
        self._q = [math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)]
        self._w = [0.0, 0.0, 0.0]
        self._r = [0.0, 0.0, 0.0, 0.0]      # lagged motor command p = pwm / 65535
        self._F = [0.0, 0.0, 0.0, 0.0]      # N per motor
        self._a = [0.0, 0.0, G]             # specific force, world frame (m/s^2)
        self.on_ground = self._p[2] <= P.ground_z + 1e-9
        self.impacts: list[Impact] = []
        self.max_tilt_deg = 0.0

    # numpy views (copies) of the state
    pos = property(lambda self: np.array(self._p))
    vel = property(lambda self: np.array(self._v))
    q = property(lambda self: np.array(self._q))
    omega = property(lambda self: np.array(self._w))
    thrusts = property(lambda self: np.array(self._F))

    def set_state(self, pos=None, vel=None, q=None, omega=None, ratio=None, on_ground=None):
        """Overwrite parts of the state (tests, initial conditions)."""
        if pos is not None:
            self._p = [float(v) for v in pos]
        if vel is not None:
            self._v = [float(v) for v in vel]
        if q is not None:
            self._q = [float(v) for v in q]
        if omega is not None:
            self._w = [float(v) for v in omega]
        if ratio is not None:
            self._r = [float(v) for v in np.broadcast_to(ratio, 4)]
        if on_ground is not None:
            self.on_ground = bool(on_ground)

    def _rot(self):
        w, x, y, z = self._q
        return ((1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)),
                (2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)),
                (2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)))

    def _rest(self):
        P = self.p
        w, x, y, z = self._q
        yaw = math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
        self._q = [math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)]
        self._v = [0.0, 0.0, 0.0]
        self._w = [0.0, 0.0, 0.0]
        self._p[2] = P.ground_z
        self._a = [0.0, 0.0, G]
        self.on_ground = True

    # -- dynamics
    def step(self, dt: float, pwm) -> None:
        P = self.p
        r = self._r
        F = self._F
        wsum = 0.0
        for i in range(4):
            c = min(max(float(pwm[i]) / PWM_MAX, 0.0), 1.0)
            tau = P.tau_up if c > r[i] else P.tau_down
            r[i] += (c - r[i]) * (1.0 - math.exp(-dt / tau))
            F[i] = P.thrust_a * r[i] * r[i] + P.thrust_b * r[i]
            pw = r[i] * PWM_MAX
            wsum += 0.0 if pw < 1000.0 else 0.04076521 * pw + 380.8359
        R = self._rot()
        vx, vy, vz = self._v
        # body velocity = R^T v
        vbx = R[0][0] * vx + R[1][0] * vy + R[2][0] * vz
        vby = R[0][1] * vx + R[1][1] * vy + R[2][1] * vz
        vbz = R[0][2] * vx + R[1][2] * vy + R[2][2] * vz
        fbx = -P.rotor_drag_xy * wsum * vbx
        fby = -P.rotor_drag_xy * wsum * vby
        fbz = F[0] + F[1] + F[2] + F[3] - P.rotor_drag_z * wsum * vbz
        rx, ry, ys = self._rx, self._ry, self._ys
        tx = ry[0] * F[0] + ry[1] * F[1] + ry[2] * F[2] + ry[3] * F[3]
        ty = -(rx[0] * F[0] + rx[1] * F[1] + rx[2] * F[2] + rx[3] * F[3])
        tz = P.thrust_to_torque * (ys[0] * F[0] + ys[1] * F[1] + ys[2] * F[2] + ys[3] * F[3])
        m = P.mass
        ax = (R[0][0] * fbx + R[0][1] * fby + R[0][2] * fbz) / m
        ay = (R[1][0] * fbx + R[1][1] * fby + R[1][2] * fbz) / m
        az = (R[2][0] * fbx + R[2][1] * fby + R[2][2] * fbz) / m

        if self.on_ground and az - G <= 0.0:
            self._rest()     # the floor carries the weight: still and level
            self.t += dt
            return
        self.on_ground = False

        # translation (semi-implicit Euler)
        v = self._v
        v[0] += ax * dt
        v[1] += ay * dt
        v[2] += (az - G) * dt
        p = self._p
        p[0] += v[0] * dt
        p[1] += v[1] * dt
        p[2] += v[2] * dt
        self._a = [ax, ay, az]
        # rotation: J w' = tau - w x (J w); q <- q * exp(w dt / 2)
        J = self._J
        wx, wy, wz = self._w
        hx, hy, hz = J[0] * wx, J[1] * wy, J[2] * wz
        wx += (tx - (wy * hz - wz * hy)) / J[0] * dt
        wy += (ty - (wz * hx - wx * hz)) / J[1] * dt
        wz += (tz - (wx * hy - wy * hx)) / J[2] * dt
        self._w = [wx, wy, wz]
        n = math.sqrt(wx * wx + wy * wy + wz * wz)
        if n > 0.0:
            h = 0.5 * n * dt
            s = math.sin(h) / n
            bw, bx, by, bz = math.cos(h), wx * s, wy * s, wz * s
            aw, ax_, ay_, az_ = self._q
            qw = aw * bw - ax_ * bx - ay_ * by - az_ * bz
            qx = aw * bx + ax_ * bw + ay_ * bz - az_ * by
            qy = aw * by - ax_ * bz + ay_ * bw + az_ * bx
            qz = aw * bz + ax_ * by - ay_ * bx + az_ * bw
            k = 1.0 / math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
            self._q = [qw * k, qx * k, qy * k, qz * k]
        self.t += dt
        _, qx, qy, _ = self._q
        tilt = math.degrees(math.acos(max(-1.0, min(1.0, 1 - 2 * (qx * qx + qy * qy)))))
        if tilt > self.max_tilt_deg:
            self.max_tilt_deg = tilt

        # floor
        if p[2] <= P.ground_z:
            if -v[2] >= IMPACT_MIN_SPEED:
                self.impacts.append(Impact(self.t, math.sqrt(v[0] ** 2 + v[1] ** 2 + v[2] ** 2), v[2],
                                           (round(p[0], 4), round(p[1], 4), round(p[2], 4)), sum(F)))
            self._rest()

    # -- sensors
    def imu(self):
        """(specific force in g, angular rate in deg/s), body frame FLU, as numpy arrays."""
        R = self._rot()
        a = self._a
        acc = np.array([(R[0][i] * a[0] + R[1][i] * a[1] + R[2][i] * a[2]) / G for i in range(3)])
        gyro = np.degrees(np.array(self._w))
        if self.p.acc_noise_g > 0:
            acc = acc + self.rng.normal(0.0, self.p.acc_noise_g, 3)
        if self.p.gyro_noise_dps > 0:
            gyro = gyro + self.rng.normal(0.0, self.p.gyro_noise_dps, 3)
        return acc, gyro

    def imu_packet(self) -> bytes:
        if self.p.acc_noise_g > 0 or self.p.gyro_noise_dps > 0:
            return encode_imu(*self.imu())
        R = self._rot()
        a = self._a
        k = 1.0 / (G * ACC_LSB_G)
        d = 180.0 / math.pi / GYRO_LSB_DPS
        w = self._w
        return _IMU.pack(HDR_SIM, SENSOR_GYRO_ACC,
                         *(_i16((R[0][i] * a[0] + R[1][i] * a[1] + R[2][i] * a[2]) * k) for i in range(3)),
                         _i16(w[0] * d), _i16(w[1] * d), _i16(w[2] * d))

    def pose_packet(self) -> bytes:
        return encode_ext_pose(self._p, self._q)

    def hover_pwm(self) -> float:
        """PWM per motor that carries the weight."""
        P = self.p
        f = P.mass * G / 4
        pr = (-P.thrust_b + math.sqrt(P.thrust_b ** 2 + 4 * P.thrust_a * f)) / (2 * P.thrust_a)
        return pr * PWM_MAX

    def state_row(self) -> list:
        """t, x, y, z, vx, vy, vz, qw, qx, qy, qz, wx, wy, wz, thrust_N (see STATE_COLUMNS)."""
        return [self.t, *self._p, *self._v, *self._q, *self._w, sum(self._F)]


STATE_COLUMNS = ["t", "x", "y", "z", "vx", "vy", "vz", "qw", "qx", "qy", "qz", "wx", "wy", "wz", "thrust"]
