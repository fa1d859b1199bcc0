"""Software-in-the-loop flights: the real app (host build, :mod:`polycc.sim.app_ffi`) stepped tick
by tick on a simulated clock against a vehicle model (:mod:`polycc.sim.dynamics`), with
clearance measured to the ground-truth splat ellipsoids.

One app tick at FreeRTOS tick ``k`` (1 ms):
  1. the model's delayed position goes into the shim's ``stateEstimate.x/y/z``;
  2. the cycle model sets how long ``usecTimestamp`` says the kernel call took;
  3. ``polycc_app_tick()`` runs (reads the log variables, runs the kernel, calls
     ``commanderSetSetpoint``) and returns its period ``P`` in ticks;
  4. the model flies the commander's velocity setpoint for ``P`` ms; the clock moves to ``k + P``.

With ``waypoints`` (a plan, :mod:`polycc.plan`) the app flies to one goal param at a time:
``polycc.goalX/Y/Z`` switch to the next waypoint once the vehicle is within ``switch_tol_m`` of the
current one; success is still arrival within ``goal_tol_m`` of the last.

Clearance is the EXACT Euclidean distance from the vehicle centre to the nearest ellipsoid
minus the agent radius (:mod:`polycc.sim.clearance`), along the path resampled to at most
``SAMPLE_SPACING_M`` between points.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from polycc.budget import cycle_model
from polycc.errors import PolyccError
from polycc.onboard.barrier import Params
from polycc.onboard.barrier import barrier as ref_barrier
from polycc.onboard.layout import PackedScene
from polycc.sim.app_ffi import AppSim
from polycc.sim.clearance import Clearance, densify
from polycc.sim.dynamics import Vehicle, make_dynamics

GOAL_TOLERANCE_M = 0.05
CRTP_PRIORITY = 2  # COMMANDER_PRIORITY_CRTP: a ground client's setpoints


# --------------------------------------------------------------------------- flights
@dataclass
class FlightConfig:
    """App parameters (the polycc param group) and the simulation limits."""

    rate_hz: int = 500
    vmax: float = 0.5  # m/s
    beta: float = 1.0  # 1/s
    clf_gain: float = 2.0  # 1/s
    radius: float = 0.1  # m, the app's polycc.radius
    clearance_radius: float | None = None  # m, physical radius for clearance/collisions (default: radius)
    t_max_s: float | None = None  # default: 2 * distance / vmax + 10 s
    goal_tol_m: float = GOAL_TOLERANCE_M
    stuck_window_s: float = 2.0  # stop when the vehicle moved less than stuck_dist_m in this window
    stuck_dist_m: float = 0.01
    record_app_io: bool = False  # keep what the app saw and sent, tick by tick
    floor_z: float = -1e3  # m: the floor the vehicle rests on (default: far below the scene)
    switch_tol_m: float = 0.05  # waypoint following: next waypoint within this distance of the current one
    shield: bool = False  # fly the out-of-tree controller with polyccShield.enable = 1 (the shield filters the app)
    shield_tube: float | None = None  # m, polyccShield.tube (default: the app's)
    shield_radius: float | None = None  # m, polyccShield.radius (default: clearance_radius, else radius)
    shield_psi_cap: float = 0.0  # m, polyccShield.psicap (0: off): fly the shield on min(psi, cap)
    shield_gains: tuple[float, float] | None = None  # (k1 1/s, k0 1/s^2), polyccShield.k1/k0 (default: the app's)

    def params(self, kappa: float) -> Params:
        return Params(kappa=kappa, radius=self.radius, beta=self.beta, c_clf=self.clf_gain, v_max=self.vmax)


@dataclass
class Trial:
    start: np.ndarray
    goal: np.ndarray
    success: bool
    outcome: str  # "goal", "stuck", "timeout"
    time_s: float
    path_length_m: float
    straight_m: float
    positions: np.ndarray  # true positions after every app period (n, 3), metres
    max_eval_us: int  # cycle model at the states the app evaluated (largest); the app's log shows the worst case
    statuses: dict[int, int]  # polycc.status value -> number of ticks
    min_clearance_m: float = math.nan  # ground-truth ellipsoids, agent radius subtracted
    collisions: int = -1
    io: dict | None = None  # record_app_io: per tick what the app saw, sent and gave/got from the kernel
    impact_speed_ms: float = 0.0  # fastest touchdown on the floor, m/s (0: none)
    waypoints: np.ndarray | None = None  # the plan flown (k, 3) m, waypoints[0] = start, or None
    reached: int = 0  # waypoints after the start the vehicle switched past or arrived at
    shield: dict | None = None  # the shield's counters (polycc_controller_trace_t) when cfg.shield
    rate_gap: np.ndarray | None = None  # per app tick: grad psi . (v_true - u_commanded), m/s (Prop. 1 of seed 001)
    jerk: np.ndarray | None = None  # |da/dt| of the true vehicle at 100 Hz, m/s^3
    extra: dict | None = None  # simulator-specific facts (the real-firmware SITL: RTF, connect, landing)

    @property
    def length_ratio(self) -> float:
        return self.path_length_m / self.straight_m if self.straight_m > 0 else math.nan


class Simulator:
    """The app built for one ``polytopes.h``, a cycle model and (optionally) the ground truth."""

    def __init__(self, header: str | Path, ellipsoids=None, brake: bool = True):
        """``brake=False`` builds the app with its braking term compiled out (POLYCC_APP_BRAKE_ACC = 0):
        the plain CBF filter of the paper."""
        self.app = AppSim(header, None if brake else {"POLYCC_APP_BRAKE_ACC": "0.0f"})
        self.packed = self.app.packed_scene()
        self.kappa = self.app.kappa
        self.clearance = Clearance(ellipsoids) if ellipsoids is not None and len(ellipsoids) else None

    def fly(self, start, goal, dynamics: str = "integrator", cfg: FlightConfig | None = None,
            delay_s: float | None = None, waypoints=None) -> Trial:
        """One flight from ``start`` (the vehicle hovering there under the high-level commander,
        as after a takeoff) with the app enabled towards ``goal``; every 1 ms tick runs the host
        model of the firmware's commander, high-level commander and supervisor
        (``shim_stabilizer_step``) and flies the setpoint the controller gets.  ``waypoints`` (k, 3),
        if given, is a plan with ``waypoints[-1] = goal`` (``waypoints[0]``, the start, is skipped
        when it is ``start``)."""
        cfg = cfg or FlightConfig()
        app, lib, ffi = self.app, self.app.lib, self.app.ffi
        start = np.asarray(start, np.float64)
        goal = np.asarray(goal, np.float64)
        if waypoints is None:
            targets = goal[None]
        else:
            targets = np.asarray(waypoints, np.float64).reshape(-1, 3)
            if not np.allclose(targets[-1], goal):
                raise PolyccError("the plan's last waypoint is not the goal; plan again for this goal")
            if len(targets) > 1 and np.allclose(targets[0], start):
                targets = targets[1:]
        current = 0

        def set_goal(w):
            for name, val in zip(("goalX", "goalY", "goalZ"), w):
                app.set_param("polycc", name, val)

        veh = Vehicle(make_dynamics(dynamics, delay_s), floor_z=cfg.floor_z)
        veh.reset(start)
        app.reset()
        sp = ffi.new("shim_setpoint_t *")
        lib.shim_set_tick(0)
        lib.shim_hl_hover_at(*(float(v) for v in start))  # hovering under the HL commander, as after a takeoff
        pos32 = ffi.new("float[3]")
        vel32 = ffi.new("float[3]")
        set_goal(targets[0])
        if cfg.shield:
            lib.shim_set_controller(lib.ControllerTypeOot)
            app.set_param("polyccShield", "enable", 1)
            if cfg.shield_tube is not None:
                app.set_param("polyccShield", "tube", cfg.shield_tube)
            r_sh = cfg.shield_radius if cfg.shield_radius is not None else (
                cfg.clearance_radius if cfg.clearance_radius is not None else cfg.radius)
            app.set_param("polyccShield", "radius", r_sh)
            app.set_param("polyccShield", "psicap", cfg.shield_psi_cap)
            if cfg.shield_gains is not None:
                app.set_param("polyccShield", "k1", float(cfg.shield_gains[0]))
                app.set_param("polyccShield", "k0", float(cfg.shield_gains[1]))
        gaps: list[float] = []
        accs: list[np.ndarray] = []
        for name, val in (("vmax", cfg.vmax), ("beta", cfg.beta), ("clfGain", cfg.clf_gain), ("radius", cfg.radius),
                          ("rateHz", cfg.rate_hz), ("enable", 1)):
            app.set_param("polycc", name, val)
        goal32 = goal.astype(np.float32)
        straight = float(np.linalg.norm(goal - start))
        planned = float(np.sum(np.linalg.norm(np.diff(np.vstack([start, targets]), axis=0), axis=1)))
        t_max = cfg.t_max_s if cfg.t_max_s is not None else 2.0 * planned / cfg.vmax + 10.0 + 4.0 * (len(targets) - 1)
        i_psi = app._log_index["polycc.psi"]
        i_status = app._log_index["polycc.status"]
        params = cfg.params(self.kappa)
        worst_us = int(cycle_model.us(cycle_model.worst_cycles(self.packed)))
        seen = []
        rec = ffi.new("shim_commander_record_t *")
        positions = [start.copy()]
        times = [0.0]
        statuses: dict[int, int] = {}
        io = ({k: [] for k in ("x_seen", "u", "psi", "status", "calls", "x_kernel", "vmax", "out_u", "out_psi",
                                "out_flags", "goal_t")} if cfg.record_app_io else None)
        outcome = "timeout"
        stuck_ticks = None
        tick, next_app, period = 1, 1, 1
        while True:
            lib.shim_set_tick(tick)
            if tick >= next_app:
                pe, ve = veh.estimate()
                est = pe.astype(np.float32)
                lib.shim_set_estimate(float(est[0]), float(est[1]), float(est[2]), float(ve[0]), float(ve[1]),
                                      float(ve[2]))
                lib.shim_set_attitude(0.0, 0.0, 0.0, veh.thrust())
                lib.shim_set_usec(tick * 1000, worst_us)
                seen.append(est)
                period = int(lib.polycc_app_tick())
                next_app = tick + period
                lib.shim_commander_get(rec)
                st = int(lib.shim_log_value(i_status))
                statuses[st] = statuses.get(st, 0) + 1
                if io is not None:
                    tr = lib.polycc_app_trace()
                    io["x_seen"].append(est)
                    io["u"].append((rec.vx, rec.vy, rec.vz))
                    io["psi"].append(lib.shim_log_value(i_psi))
                    io["status"].append(st)
                    io["calls"].append(tr.calls)
                    io["x_kernel"].append(tuple(tr.x))
                    io["vmax"].append(tr.params.v_max)
                    io["out_u"].append(tuple(tr.out.u))
                    io["out_psi"].append(tr.out.psi)
                    io["out_flags"].append(tr.out.flags)
                    io["goal_t"].append(targets[min(current, len(targets) - 1)])
            if cfg.shield:  # the firmware's controller sees the estimate (and the model's acceleration)
                pe, ve = veh.estimate()
                pos32[0:3] = pe.tolist()
                vel32[0:3] = ve.tolist()
                acc = getattr(veh.model, "a", np.zeros(3))
                lib.shim_set_acceleration(float(acc[0]), float(acc[1]), float(acc[2]))
            else:
                pos32[0:3] = veh.p.tolist()
                vel32[0:3] = veh.v.tolist()
            lib.shim_stabilizer_step(pos32, vel32, 0.0, sp)
            if tick % 10 == 0:
                accs.append(np.array(getattr(veh.model, "a", np.zeros(3)), np.float64))
                if sp.mode_x == 2 and sp.mode_y == 2 and sp.mode_z == 2:
                    g = lib.polycc_app_trace().out.grad
                    dv = veh.v - np.array([sp.vx, sp.vy, sp.vz])
                    gaps.append(float(g[0] * dv[0] + g[1] * dv[1] + g[2] * dv[2]))
            veh.step(sp, 1e-3)
            t = tick * 1e-3
            if tick >= next_app - 1:  # sample the path once per app period
                positions.append(veh.p.copy())
                times.append(t)
            tick += 1
            if np.linalg.norm(veh.p - goal) <= cfg.goal_tol_m:
                outcome = "goal"
                current = len(targets)
                break
            while current < len(targets) - 1 and np.linalg.norm(veh.p - targets[current]) <= cfg.switch_tol_m:
                current += 1
                set_goal(targets[current])
            if t >= t_max:
                break
            if stuck_ticks is None:
                stuck_ticks = max(1, int(round(cfg.stuck_window_s * 1000 / period)))
            if len(positions) > stuck_ticks and t > cfg.stuck_window_s and \
                    np.linalg.norm(positions[-1] - positions[-1 - stuck_ticks]) < cfg.stuck_dist_m:
                outcome = "stuck"
                break
        P = np.asarray(positions)
        max_eval = int(cycle_model.us(cycle_model.state_cycles(self.packed, params, np.asarray(seen))).max())
        trial = Trial(start, goal, outcome == "goal", outcome, times[-1],
                      float(np.sum(np.linalg.norm(np.diff(P, axis=0), axis=1))), straight, P, max_eval, statuses,
                      waypoints=None if waypoints is None else np.asarray(waypoints, np.float64).reshape(-1, 3),
                      reached=current)
        trial.impact_speed_ms = veh.impact_speed_ms
        trial.rate_gap = np.asarray(gaps, np.float64)
        A = np.asarray(accs, np.float64).reshape(-1, 3)
        trial.jerk = np.linalg.norm(np.diff(A, axis=0), axis=1) / 0.01 if len(A) > 1 else np.zeros(0)
        if cfg.shield:
            tr = lib.polycc_controller_trace()
            keys = ("decisions", "certified", "backups", "infeasible", "manual", "eval_caps", "overrides", "landings",
                    "escapes", "bridged", "expired")
            trial.shield = {k: int(getattr(tr, k)) for k in keys}
        if io is not None:
            f3 = lambda k: np.asarray(io[k], np.float32).reshape(-1, 3)  # noqa: E731
            trial.io = {"x_seen": f3("x_seen"), "u": f3("u"),
                        "psi": np.asarray(io["psi"], np.float64).astype(np.float32),
                        "status": np.asarray(io["status"], np.int64),
                        "goal": goal32 if waypoints is None else f3("goal_t"),
                        "calls": np.asarray(io["calls"], np.int64), "x_kernel": f3("x_kernel"),
                        "vmax": np.asarray(io["vmax"], np.float32), "out_u": f3("out_u"),
                        "out_psi": np.asarray(io["out_psi"], np.float32),
                        "out_flags": np.asarray(io["out_flags"], np.uint32)}
        if self.clearance is not None:
            r_phys = cfg.radius if cfg.clearance_radius is None else cfg.clearance_radius
            trial.min_clearance_m, trial.collisions, _ = self.clearance.evaluate(densify(P), r_phys)
        return trial


# --------------------------------------------------------------------------- start/goal pairs
def free_points(packed: PackedScene, params: Params, lo, hi, n: int, rng: np.random.Generator,
                margin: float = 0.05, max_rounds: int = 50) -> np.ndarray:
    """``n`` uniform points in the box [lo, hi] with psi >= margin (outside every inflated polytope)."""
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    out: list[np.ndarray] = []
    got = 0
    for _ in range(max_rounds):
        cand = rng.uniform(lo, hi, size=(max(64, 2 * n), 3))
        psi, _, flags = ref_barrier(packed, params, cand.astype(np.float32))
        ok = cand[(flags == 0) & (psi >= margin)]
        out.append(ok)
        got += len(ok)
        if got >= n:
            break
    pts = np.concatenate(out) if out else np.zeros((0, 3))
    if len(pts) < n:
        raise PolyccError(f"found only {len(pts)} free points in the sampling box; enlarge it or use fewer pairs")
    return pts[:n]


def random_pairs(packed: PackedScene, params: Params, lo, hi, n_pairs: int, min_distance: float,
                 seed: int = 0) -> list[tuple[np.ndarray, np.ndarray]]:
    """The paper's protocol: ``n_pairs`` start/goal pairs in free space, at least ``min_distance`` apart."""
    rng = np.random.default_rng(seed)
    diag = float(np.linalg.norm(np.asarray(hi) - np.asarray(lo)))
    if min_distance >= diag:
        raise PolyccError(f"--min-distance {min_distance:g} m is not below the sampling box diagonal {diag:.2f} m; "
                          "lower it")
    pts = free_points(packed, params, lo, hi, 8 * n_pairs, rng)
    pairs = []
    used = np.zeros(len(pts), bool)
    for i in range(len(pts)):
        if len(pairs) == n_pairs:
            break
        if used[i]:
            continue
        d = np.linalg.norm(pts - pts[i], axis=1)
        ok = np.flatnonzero((d >= min_distance) & ~used)
        if len(ok) == 0:
            continue
        j = int(rng.choice(ok))
        used[i] = used[j] = True
        pairs.append((pts[i], pts[j]))
    if len(pairs) < n_pairs:
        raise PolyccError(f"only {len(pairs)} of {n_pairs} start/goal pairs are {min_distance:g} m apart; lower "
                          "--min-distance")
    return pairs


def sampling_box(ellipsoids, z_min: float = 0.15) -> tuple[np.ndarray, np.ndarray]:
    """Robust bounds of the splat centres (0.5-99.5 percentiles), floor raised to ``z_min``."""
    c = np.asarray(ellipsoids.centers)
    lo, hi = np.percentile(c, 0.5, axis=0), np.percentile(c, 99.5, axis=0)
    lo[2] = max(lo[2], z_min)
    hi[2] = max(hi[2], lo[2] + 0.5)
    return lo, hi
