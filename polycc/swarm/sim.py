"""N drones on the fast simulator: each its own app instance (:mod:`.instances`), its own vehicle
model and its own coverage controller; neighbour reports over the app channel.  1 ms ticks.

Per tick ``t`` (ms):
  1. drone j broadcasts its estimate every ``bcast_ms`` (staggered: offset ``j·bcast_ms/N``, like a
     TDMA P2P slot); each other drone's app channel gets the 18-byte report ``latency_ms`` later,
     stating age = latency + estimator delay (docs/swarm.md, assumption 2);
  2. every ``ctrl_ms`` each controller computes its drone's goal from the broadcast positions and
     writes ``polycc.goalX/Y/Z``;
  3. each app ticks when due (its own period), its setpoint is flown for 1 ms by its vehicle model;
  4. a peak is detected when a drone is within ``sense_m`` of it (its density is then removed).

Stops when every peak is detected or at ``t_max_s``.  Collisions: drone-drone when two centres come
closer than ``2 r`` (checked every ms), drone-obstacle by the exact ellipsoid clearance of each path.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from polycc.onboard.app import pack_neighbour
from polycc.sim.dynamics import Vehicle, make_dynamics
from polycc.swarm.coverage import Controller, CoverageMap, Targets, voronoi_cells
from polycc.swarm.instances import drone_apps

THIN_M = 0.01  # m: trajectory samples closer than this to the last kept one are dropped (see run_swarm)


def _thin(P: np.ndarray, eps: float) -> np.ndarray:
    keep, last = [0], P[0]
    for i in range(1, len(P)):
        if np.linalg.norm(P[i] - last) > eps:
            keep.append(i)
            last = P[i]
    if keep[-1] != len(P) - 1:
        keep.append(len(P) - 1)
    return P[keep]


def obstacle_clearance(traj: list, clearance, radius: float) -> tuple[list[int], list[float]]:
    """Per drone: samples inside an obstacle (clearance < r) and the minimum clearance to the splat
    ellipsoids minus r (m, a lower bound), of each (k, 3) true path; (0, nan) without ``clearance`` or
    for an empty path (a drone whose app never flew)."""
    from polycc.sim.clearance import densify

    obst, clear = [], []
    for t in traj:
        if clearance is None or not len(t):
            clear.append(math.nan)
            obst.append(0)
            continue
        # hovering drones repeat their position: keep the samples that moved > THIN_M since the last
        # kept one and check those with the radius enlarged by THIN_M (every dropped sample is within
        # THIN_M of a kept one), so a collision is never missed and the clearance is a lower bound
        c, hits, _ = clearance.evaluate(densify(_thin(np.asarray(t, float), THIN_M), THIN_M), radius + THIN_M)
        clear.append(float(c))
        obst.append(int(hits))
    return obst, clear


@dataclass
class SwarmConfig:
    rate_hz: int = 500
    vmax: float = 0.5  # m/s
    radius: float = 0.1  # m: every drone's app radius and physical radius
    swarm_v: float = 1.0  # m/s: polycc.swarmV, the neighbours' speed bound
    bcast_ms: int = 50  # neighbour report period (20 Hz)
    latency_ms: int = 10
    ctrl_ms: int = 200  # coverage controller period (5 Hz)
    sense_m: float = 0.5  # a peak is detected within this distance
    t_max_s: float = 60.0
    dynamics: str = "integrator"
    delay_s: float | None = None
    controller: str = "guided"


@dataclass
class SwarmResult:
    n: int
    positions: list  # per drone (k, 3) true positions every 10 ms
    detected_at: np.ndarray  # (K,) s, nan = never
    min_pair_m: float  # min centre distance over all pairs and ticks
    pair_collisions: int  # pairs that ever came closer than 2 r
    obstacle_collisions: list  # per drone: samples inside an ellipsoid (exact clearance < 0)
    min_clearance_m: list  # per drone
    statuses: list  # per drone {status: ticks}
    time_s: float
    path_m: list
    cells: list = field(default_factory=list)  # per drone the free-cell indices of its last cell
    step_us: float = 0.0  # wall time per drone-tick, us
    nearest_m: np.ndarray | None = None  # per drone: min distance to any other drone's centre, m
    detected_by: np.ndarray | None = None  # (K,) drone that detected each peak (-1: none)
    targets: Targets | None = None
    starts: np.ndarray | None = None

    @property
    def coverage(self) -> float:
        return float(np.mean(np.isfinite(self.detected_at)))

    @property
    def task_time_s(self) -> float:
        return float(np.nanmax(self.detected_at)) if np.all(np.isfinite(self.detected_at)) else math.nan

    @property
    def collisions(self) -> int:
        return self.pair_collisions + sum(1 for c in self.obstacle_collisions if c > 0)


def run_swarm(header, cmap: CoverageMap, starts: np.ndarray, targets: Targets, cfg: SwarmConfig,
              clearance=None, progress=None, goals=None) -> SwarmResult:
    """Flies the swarm (module docstring); ``goals`` (N, 3) m, if given, replaces the coverage controllers
    by fixed per-drone goals (pairwise tests: swaps, crossings)."""
    import time

    starts = np.asarray(starts, float)
    n = len(starts)
    apps = drone_apps(header, n)
    vehicles = []
    for i, a in enumerate(apps):
        veh = Vehicle(make_dynamics(cfg.dynamics, cfg.delay_s), floor_z=-1e3)
        veh.reset(starts[i])
        vehicles.append(veh)
        a.reset()
        a.lib.shim_set_tick(0)
        a.lib.shim_hl_hover_at(*(float(v) for v in starts[i]))
        for name, val in (("vmax", cfg.vmax), ("radius", cfg.radius), ("rateHz", cfg.rate_hz),
                          ("swarmV", cfg.swarm_v), ("goalX", starts[i][0]), ("goalY", starts[i][1]),
                          ("goalZ", starts[i][2]), ("enable", 1)):
            a.set_param("polycc", name, val)
    delay_ms = int(math.ceil(1000 * vehicles[0]._delay.delay))  # the estimate lags the truth by this
    ctrls = [Controller(cmap, cfg.controller) for _ in range(n)]
    alive = np.ones(len(targets.mu), bool)
    detected = np.full(len(targets.mu), np.nan)
    dens = cmap.density(cfg.controller, alive)
    bcast = starts.astype(np.float32).copy()  # last broadcast estimate of each drone
    pending: list[tuple[int, int, bytes]] = []  # (deliver at ms, receiver, packet)
    sps = [a.ffi.new("shim_setpoint_t *") for a in apps]
    pos32 = [a.ffi.new("float[3]") for a in apps]
    vel32 = [a.ffi.new("float[3]") for a in apps]
    i_status = [a._log_index["polycc.status"] for a in apps]
    replies = [a.ffi.new("unsigned char[32]") for a in apps]
    next_app = [1] * n
    statuses = [dict() for _ in range(n)]
    traj = [[s.copy()] for s in starts]
    min_pair, pair_hit = math.inf, set()
    near = np.full(n, math.inf)  # per drone: closest neighbour centre distance, m
    detected_by = np.full(len(targets.mu), -1)
    iu = np.triu_indices(n, 1)
    t_end = int(cfg.t_max_s * 1000)
    offsets = [j * cfg.bcast_ms // max(n, 1) for j in range(n)]
    wall0 = time.perf_counter()
    tick = 0
    whole = cfg.dynamics == "integrator"
    period_ms = int(math.ceil(1000.0 / cfg.rate_hz))
    P = starts.copy()
    for tick in range(1, t_end + 1):
        moved = False
        for j in range(n):  # 1. broadcasts
            if (tick - offsets[j]) % cfg.bcast_ms == 0:
                pe, _ = vehicles[j].estimate()
                bcast[j] = pe.astype(np.float32)
                # stated age: latency, estimator delay, and one app period (the integrator is stepped a
                # whole period ahead, so the estimate read between ticks may be up to a period newer)
                pkt = pack_neighbour(j, bcast[j], cfg.latency_ms + delay_ms + period_ms + 1, cfg.radius)
                pending.extend((tick + cfg.latency_ms, i, pkt) for i in range(n) if i != j)
        if pending:
            keep = []
            for item in pending:
                if item[0] <= tick:
                    apps[item[1]].lib.shim_appchannel_push(item[2], len(item[2]))
                else:
                    keep.append(item)
            pending = keep
        if tick % cfg.ctrl_ms == 1 and goals is not None and tick == 1:
            for i in range(n):
                for name, val in zip(("goalX", "goalY", "goalZ"), goals[i]):
                    apps[i].set_param("polycc", name, float(val))
        elif tick % cfg.ctrl_ms == 1 and goals is None:  # 2. coverage controllers
            # every drone partitions the free cells among the same broadcast positions: computed once
            lab = voronoi_cells(cmap, bcast) if cfg.controller != "repulsive" else None
            for i in range(n):
                cell = None if lab is None else np.flatnonzero(lab == i)
                g = ctrls[i].goal(bcast[i], np.delete(bcast, i, axis=0), alive, dens, cell)
                for name, val in zip(("goalX", "goalY", "goalZ"), g):
                    apps[i].set_param("polycc", name, float(val))
        for i in range(n):  # 3. apps and vehicles
            a, lib, veh = apps[i], apps[i].lib, vehicles[i]
            lib.shim_set_tick(tick)
            if tick >= next_app[i]:
                pe, ve = veh.estimate()
                e32 = pe.astype(np.float32)
                lib.shim_set_estimate(float(e32[0]), float(e32[1]), float(e32[2]), float(ve[0]), float(ve[1]),
                                      float(ve[2]))
                lib.shim_set_attitude(0.0, 0.0, 0.0, veh.thrust())
                lib.shim_set_usec(tick * 1000, 0)
                next_app[i] = tick + int(lib.polycc_app_tick())
                st = int(lib.shim_log_value(i_status[i]))
                statuses[i][st] = statuses[i].get(st, 0) + 1
                while lib.shim_appchannel_pop(replies[i], 32) > 0:  # the ground would read these
                    pass
                moved = True
                if whole:  # the single integrator flies the held setpoint exactly: one step per period
                    pos32[i][0:3] = veh.p.tolist()
                    vel32[i][0:3] = veh.v.tolist()
                    lib.shim_stabilizer_step(pos32[i], vel32[i], 0.0, sps[i])
                    veh.step(sps[i], (next_app[i] - tick) * 1e-3)
            if not whole:
                pos32[i][0:3] = veh.p.tolist()
                vel32[i][0:3] = veh.v.tolist()
                lib.shim_stabilizer_step(pos32[i], vel32[i], 0.0, sps[i])
                veh.step(sps[i], 1e-3)
                moved = True
        if moved:
            P_prev, P = P, np.array([v.p for v in vehicles])
        if n > 1 and moved:
            # exact minimum over the step: relative motion is linear within it (held setpoints)
            r0, r1 = P_prev[iu[0]] - P_prev[iu[1]], P[iu[0]] - P[iu[1]]
            dr = r1 - r0
            s_ = np.clip(-(r0 * dr).sum(1) / np.maximum((dr * dr).sum(1), 1e-300), 0.0, 1.0)
            d = np.linalg.norm(r0 + s_[:, None] * dr, axis=1)
            m = float(d.min())
            if m < min_pair:
                min_pair = m
            np.minimum.at(near, iu[0], d)
            np.minimum.at(near, iu[1], d)
            for k in np.flatnonzero(d < 2 * cfg.radius):
                pair_hit.add(int(k))
        if tick % 10 == 0:
            for i in range(n):
                traj[i].append(P[i].copy())
            dist = np.linalg.norm(P[:, None] - targets.mu[None], axis=2)
            newly = alive & (dist.min(0) <= cfg.sense_m)
            if newly.any():
                detected[newly] = tick * 1e-3
                detected_by[newly] = dist.argmin(0)[newly]
                alive &= ~newly
                dens = cmap.density(cfg.controller, alive)
            if not alive.any():
                break
        if progress is not None and tick % 1000 == 0:
            progress(tick / 1000.0)
    wall = time.perf_counter() - wall0
    traj = [np.asarray(t) for t in traj]
    obst, clear = obstacle_clearance(traj, clearance, cfg.radius)
    return SwarmResult(n, traj, detected, min_pair if n > 1 else math.inf, len(pair_hit), obst, clear, statuses,
                       tick * 1e-3, [float(np.sum(np.linalg.norm(np.diff(t, axis=0), axis=1))) for t in traj],
                       [c.cell for c in ctrls], 1e6 * wall / max(1, tick * n), near, detected_by, targets, starts)
