"""`polycc swarm-sim --firmware FWDIR`: N real-firmware SITL instances (CrazySim ``cf2`` with the app, one
bridge each, :mod:`polycc.sim.firmware.sitl`) flown as a swarm by real cflib through :func:`polycc.swarm.fly.
swarm_fly` -- the same ground process that flies real drones.

World frame, metres. Each drone starts on the floor below its start and takes off vertically to the
common height, so starts are picked in free columns (:func:`column_starts`). The instances do not share
a clock: each is lock-stepped to its own physics at up to real time. So

* the task is timed in the slowest instance's simulated time (``clock`` of swarm_fly);
* drone-drone distances are measured on the bridges' 100 Hz truth mapped to a common wall-clock axis by
  (wall, simulated time) pairs sampled ~10 times a second during the flight, linearly interpolated; the
  minimum is a measurement (the interpolation can miss up to v·Δt ≈ 1 cm at 0.5 m/s and 20 ms of
  mapping error), not a certificate -- the certificate is the on-board one (docs/swarm.md);
* drone-obstacle clearance is exact on each truth path (:func:`polycc.swarm.sim.obstacle_clearance`).
"""

from __future__ import annotations

import math
import time
from contextlib import ExitStack

import numpy as np

from polycc.errors import PolyccError
from polycc.swarm.coverage import CoverageMap, Targets
from polycc.swarm.sim import SwarmConfig, SwarmResult, obstacle_clearance


def column_starts(cmap: CoverageMap, n: int, height: float, min_sep: float, rng: np.random.Generator,
                  floor_clear: float = 0.4) -> np.ndarray:
    """``n`` points (x, y, height) at least ``min_sep`` m apart whose whole column from ``floor_clear`` m
    up to ``height`` is certified free on the coverage grid (a vertical takeoff stays clear)."""
    free = cmap.lut >= 0  # (nx, ny, nz) certified free cells of the coverage grid
    g, lo = cmap.spacing, np.asarray(cmap.grid.lo, float)
    zc = lo[2] + (np.arange(free.shape[2]) + 0.5) * g
    ks = np.flatnonzero((zc >= floor_clear) & (zc <= height + 0.5 * g))
    if not len(ks):
        raise PolyccError(f"the coverage grid does not reach from {floor_clear:g} to {height:g} m")
    ok = free[:, :, ks].all(axis=2)
    good = [np.array([lo[0] + (i + 0.5) * g, lo[1] + (j + 0.5) * g, height]) for i, j in np.argwhere(ok)]
    out: list[np.ndarray] = []
    for i in rng.permutation(len(good)):
        if all(np.linalg.norm(good[i][:2] - o[:2]) >= min_sep for o in out):
            out.append(good[i])
            if len(out) == n:
                return np.array(out)
    raise PolyccError(f"only {len(out)} free takeoff columns {min_sep:g} m apart up to {height:g} m for {n} "
                      "drones; use fewer drones or a lower --takeoff")


def run_swarm_firmware(fwdir, header, cmap: CoverageMap, starts: np.ndarray, targets: Targets, cfg: SwarmConfig,
                       clearance=None, takeoff: float = 0.9, say=print, relay: str = "p2p",
                       air_drop: float = 0.0) -> tuple[SwarmResult, dict]:
    """Fly ``len(starts)`` real-firmware drones (module docstring). Returns the result in the fast
    simulator's form (positions = truth every 10 ms of each drone's time) and the run's facts
    (``outcome``, ``rtf``, ``build_s``, ``relayed``, ``p2p``). ``relay="p2p"``: the instances broadcast to
    each other through a :class:`polycc.sim.firmware.air.P2PAir` (losing ``air_drop`` of the packets per
    receiver); ``"ground"``: this process relays over cflib. A flight the simulator fails (any
    :class:`PolyccError` but a cf2 or bridge exit, :class:`~polycc.sim.firmware.sitl.SitlExited`) is
    reported through ``say`` and flown once more on fresh instances; ``facts["sitl_reruns"]`` lists why."""
    from polycc.sim.firmware.build import build_cf2
    from polycc.sim.firmware.sitl import SitlExited

    t0 = time.monotonic()
    build = build_cf2(fwdir, header)
    say(f"cf2 with the app: {'cached' if build.cached else 'built'} in {build.seconds:.0f} s")
    n = len(starts)
    reruns = []
    while True:
        try:
            fl, marks, trajs, stats, air_stats = _fly_once(build, starts, cmap, targets, cfg, takeoff, relay,
                                                           air_drop, t0, say)
            break
        except SitlExited:  # a crash of cf2 or the bridge is a failure, never flown again
            raise
        except PolyccError as exc:
            # the simulator itself failed (a bridge that stopped answering, a link that would not confirm on
            # a loaded host): reported, and the whole swarm flown once more from the floor on fresh instances
            if reruns:
                raise PolyccError(f"{exc} (and on the first attempt: {reruns[0]})") from None
            reruns.append(str(exc))
            say(f"the SITL flight failed ({exc}); flying the swarm once more on fresh instances")
    wall = np.array([m[0] for m in marks])
    sims = np.array([m[1] for m in marks])  # (k, n)
    # common wall axis at 100 Hz over the flight; each drone's truth at the simulated time it had then
    axis = np.arange(wall[0], wall[-1], 0.01)
    P_common = []
    for i, tr in enumerate(trajs):
        t_i = np.interp(axis, wall, sims[:, i])
        P_common.append(np.stack([np.interp(t_i, tr[:, 0], tr[:, c]) for c in (1, 2, 3)], axis=1))
    P_common = np.array(P_common)  # (n, k, 3)
    min_pair, pairs, near = math.inf, set(), np.full(n, math.inf)
    for i in range(n):
        for j in range(i + 1, n):
            d = np.linalg.norm(P_common[i] - P_common[j], axis=1)
            m = float(d.min()) if len(d) else math.inf
            min_pair = min(min_pair, m)
            near[i], near[j] = min(near[i], m), min(near[j], m)
            if m < 2 * cfg.radius:
                pairs.add((i, j))
    traj = [tr[:, 1:4] for tr in trajs]
    # clearance over the app's part of the flight (enable to disable), as `polycc sim --firmware`: before it
    # the drone stands on the floor (an obstacle) and takes off under the high-level commander
    flown = []
    for i, tr in enumerate(trajs):
        if math.isfinite(fl.wall_enabled):
            t_on = np.interp(fl.wall_enabled, wall, sims[:, i])
            t_off = np.interp(fl.wall_disabled if math.isfinite(fl.wall_disabled) else wall[-1], wall, sims[:, i])
            seg = tr[(tr[:, 0] >= t_on) & (tr[:, 0] <= t_off), 1:4]
        else:
            seg = tr[:0, 1:4]
        flown.append(seg)  # empty when the app never flew: no clearance (on the floor it would read as a hit)
    obst, clear = obstacle_clearance(flown, clearance, cfg.radius)
    statuses = []
    for lg in fl.logs:
        st: dict[int, int] = {}
        for row in lg.rows:
            st[int(row[4])] = st.get(int(row[4]), 0) + 1
        statuses.append(st)
    res = SwarmResult(n, traj, fl.detected_at, min_pair, len(pairs), obst, clear, statuses,
                      float(min(tr[-1, 0] for tr in trajs)),
                      [float(np.sum(np.linalg.norm(np.diff(t, axis=0), axis=1))) for t in traj], fl.cells, 0.0, near,
                      fl.detected_by, targets, np.asarray(starts, float))
    facts = {"outcome": fl.outcome, "notes": fl.notes, "relayed": fl.relayed, "build_s": build.seconds,
             "rtf": [s.get("rtf") for s in stats], "wall_s": time.monotonic() - t0,
             "relay": relay, "p2p": fl.p2p, "air": air_stats, "sitl_reruns": reruns,
             "landed": any(x.startswith("landed") for x in fl.notes)}
    return res, facts


def _fly_once(build, starts, cmap, targets, cfg, takeoff, relay, air_drop, t0, say):
    """One flight on fresh SITL instances: (SwarmFlight, [(wall, [sim t per drone])], truths, bridge stats,
    air stats)."""
    from polycc.sim.firmware.air import P2PAir
    from polycc.sim.firmware.sitl import FirmwareSitl
    from polycc.swarm.fly import swarm_fly

    n = len(starts)
    with ExitStack() as stack:
        air = stack.enter_context(P2PAir(drop=air_drop)) if relay == "p2p" else None
        sitls = []
        for s in starts:
            sitls.append(stack.enter_context(FirmwareSitl(build, start=(float(s[0]), float(s[1]), 0.0),
                                                          bridge_args=["--air", air.arg] if air else [])))
        say(f"{n} SITL instances up in {time.monotonic() - t0:.0f} s")
        marks: list[tuple[float, list[float]]] = []

        def drone_time(sl) -> float:  # raises SitlStall when its simulation has not advanced for STALL_S wall s
            t = sl.time()
            sl.note_time(t)
            return t

        def clock() -> float:  # the task's clock (the slowest drone's), and so the landing's: never waits forever
            ts = [drone_time(sl) for sl in sitls]
            marks.append((time.monotonic(), ts))
            return min(ts)

        fl = swarm_fly([sl.uri for sl in sitls], cmap, targets, controller=cfg.controller, takeoff=takeoff,
                       radius=cfg.radius, t_max=cfg.t_max_s, bcast_hz=min(10.0, 1000.0 / cfg.bcast_ms),
                       latency_ms=max(50.0, cfg.latency_ms), sense=cfg.sense_m, clock=clock, vmax=cfg.vmax,
                       swarm_v=cfg.swarm_v, relay=relay,
                       drone_times=[lambda sl=sl: drone_time(sl) for sl in sitls])
        clock()
        air_stats = dict(air.stats) if air else {}
        trajs = [sl.trajectory() for sl in sitls]
        stats = [sl.stats() for sl in sitls]
    return fl, marks, trajs, stats, air_stats
