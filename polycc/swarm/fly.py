"""`polycc swarm-fly`: real (or simulated) Crazyflies running the polycc app cover a ToI density together,
driven from one ground process through cflib's :class:`~cflib.crazyflie.swarm.Swarm`.

World frame, metres, seconds. What it does, per drone (cflib links opened in parallel by ``Swarm``):

1. check the app's params and the PID controller, start the position/status logs and the app-channel
   heartbeats (the same checks and session as ``polycc fly``, :mod:`polycc.ground.fly`);
2. high-level takeoff to ``takeoff`` m, all drones at once;
3. relay neighbours (``relay="ground"``; with ``"p2p"`` the drones do it themselves, below): every
   ``1/bcast_hz`` s each drone gets every other drone's last logged estimate as
   an app-channel neighbour record (docs/swarm.md), with ``age = time since that sample arrived +
   latency_ms`` (``latency_ms`` bounds the radio up-link of the log sample plus the down-link of the
   record; assumption 2 of docs/swarm.md). The on-board barrier adds each as a buffered Voronoi
   half-space, so drone-drone safety is the app's, not this process's. These records are also the
   heartbeats;
4. ``polycc.enable = 1``; then at ``ctrl_hz`` the coverage controller of each drone (seed 003, the one
   ``polycc swarm-sim`` flies) computes its goal from its own and its neighbours' positions and the
   certified free grid of the build, and writes ``polycc.goalX/Y/Z``. A peak within ``sense`` m of a
   drone is detected;
5. stop when every peak is detected, at ``t_max``, on Ctrl-C, or as soon as one drone's app stops
   (INSIDE, invalid, link loss, ...): every drone's app is disabled (confirmed write; it hands over to
   the high-level commander, which holds), and with ``land`` each lands under the high-level commander.
   No stop setpoint is ever sent.

Relay (``relay``, docs/swarm.md):

* ``"p2p"`` (default): the drones tell each other. Each app gets ``polycc.swarmId = i + 1``,
  ``polycc.p2pMs = 1000 / bcast_hz``, ``polycc.p2pAgeMs = latency_ms`` (the radio's latency bound) and
  ``polycc.swarmN = n - 1`` (it holds until it has heard every other drone), and broadcasts its own
  estimate with the nRF's peer-to-peer broadcast; every app takes the records it hears. The ground sends
  heartbeats only, and step 3 above is the drones'. On real radios every drone must be on one channel
  and data rate (the nRF's broadcast stays on its channel).
* ``"ground"``: step 3 as written, over cflib's links (drones on different channels or radios).
"""

from __future__ import annotations

import logging
import math
import threading
import time
from dataclasses import dataclass, field

import numpy as np

from polycc.errors import PolyccError
from polycc.ground.fly import (
    LAND_SPEED,
    LANDED_Z,
    POSITION,
    TAKEOFF_SPEED,
    FlightLog,
    _has_param,
    _Session,
    status_words,
)
from polycc.link.cflib_tools import close_without_stop, set_param
from polycc.onboard.app import FLYING, STATUS_TEXT, STOP_REASONS, pack_forget, pack_neighbour
from polycc.swarm.coverage import Controller, CoverageMap, Targets, voronoi_cells

LOG_PERIOD_MS = 50
CONNECT_TIMEOUT_S = 90.0  # per attempt: TOC and all param values (a real-firmware SITL needs 6-15 s, more when loaded)
GOAL_RESEND_M = 0.03  # a new goal is written only when it moved this much, m
P2P_LOGS = ("polycc.nNbr", "polycc.p2pRx", "polycc.p2pTx", "polycc.p2pDrop")
ESTIMATE_LOST_S = 2.0  # s without a position sample from a drone: stop (wall s; simulated drones: their own s)
PARAM_TIMEOUT_S = 10.0  # wall s for a param write to be confirmed: each drone's cflib queue writes one at a time, and
#                          four SITL instances on a loaded host answer in seconds
FIRST_ESTIMATE_S = 15.0  # wall s for every drone's first position sample (log blocks start one by one)


@dataclass
class SwarmFlight:
    """What :func:`swarm_fly` saw: per-drone logs (time s, x, y, z m, status), detections, the outcome."""

    uris: list[str]
    logs: list[FlightLog]
    detected_at: np.ndarray  # s since the app was enabled, per peak (nan: not detected)
    detected_by: np.ndarray
    outcome: str = ""
    notes: list[str] = field(default_factory=list)
    min_pair_m: float = math.inf  # closest pair of logged estimates (centres), m
    relayed: int = 0  # neighbour records sent
    wall_enabled: float = math.nan  # time.monotonic() when every app was enabled / was disabled again
    wall_disabled: float = math.nan
    targets: Targets | None = None
    cells: list = field(default_factory=list)  # each drone's last Voronoi cell (free-cell indices), for the plot
    p2p: list = field(default_factory=list)  # P2P relay: each app's last nNbr, p2pRx, p2pTx, p2pDrop logs

    @property
    def n(self) -> int:
        return len(self.uris)

    @property
    def positions(self) -> list[np.ndarray]:
        """Logged estimates (k, 3) m per drone (at least the latest one)."""
        out = []
        for lg in self.logs:
            rows = np.array([r[1:4] for r in lg.rows], float).reshape(-1, 3)
            if not len(rows):
                rows = np.array([[lg.latest.get(k, np.nan) for k in POSITION]], float)
            out.append(rows)
        return out

    @property
    def coverage(self) -> float:
        return float(np.isfinite(self.detected_at).mean()) if len(self.detected_at) else 1.0


def _connect_all(uris: list[str], timeout_s: float = CONNECT_TIMEOUT_S):
    """cflib's ``Swarm`` over links opened in parallel, each with a timeout and one retry with a fresh
    session: ``Swarm.open_links`` waits forever on a connect that stalls (seen once in four SITL
    connects on a loaded host; the same stall polycc.sim.firmware.flights retries)."""
    from cflib.crazyflie.swarm import Swarm

    from polycc.link.cflib_tools import connect

    done: dict[str, object] = {}

    def one(uri):
        try:
            done[uri] = connect(uri, timeout_s, attempts=2)
        except PolyccError as e:
            done[uri] = e

    threads = [threading.Thread(target=one, args=(u,), daemon=True) for u in uris]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    failed = [(u, r) for u, r in done.items() if isinstance(r, PolyccError)]
    if failed:
        for r in done.values():
            if not isinstance(r, PolyccError):
                close_without_stop(r)
        raise PolyccError(f"cannot connect to every drone: {failed[0][1]}; are they (or `polycc sim-device` for "
                          "each) running?")

    class _Connected:  # the factory Swarm asks for each URI's SyncCrazyflie: the open ones
        def construct(self, uri):
            return done[uri]

    return Swarm(uris, factory=_Connected())


def _check(cf, uri: str) -> None:
    for n in ("polycc.goalX", "polycc.goalY", "polycc.goalZ", "polycc.enable", "polycc.radius"):
        if not _has_param(cf, n):
            raise PolyccError(f"{uri}: parameter {n} is not on the Crazyflie; flash the polycc app (`polycc flash`)")
    if cf.log.toc.get_element_by_complete_name("polycc.nNbr") is None:
        raise PolyccError(f"{uri}: the app has no neighbour table (log polycc.nNbr); flash a current polycc app")
    if _has_param(cf, "stabilizer.controller") and int(cf.param.get_value("stabilizer.controller")) not in (0, 1):
        raise PolyccError(f"{uri}: stabilizer.controller is not PID (1); the app only flies with the PID controller")


def swarm_fly(uris: list[str], cmap: CoverageMap, targets: Targets, *, controller: str = "guided",
              takeoff: float = 0.9, radius: float = 0.1, t_max: float = 60.0, bcast_hz: float = 10.0,
              ctrl_hz: float = 5.0, latency_ms: float = 50.0, sense: float = 0.5, land: bool = True,
              on_update=None, clock=None, vmax: float | None = None, swarm_v: float | None = None,
              relay: str = "p2p", drone_times=None) -> SwarmFlight:
    """Fly the swarm (module docstring). ``on_update(flight, t)`` is called about ``bcast_hz`` times a second.
    ``clock()`` (s; default: the wall clock) times the task: ``t_max``, the takeoff and landing timeouts and
    the detection times; simulated drones slower than real time pass their (slowest) simulated time.
    ``vmax``, ``swarm_v`` (m/s), when given, set every app's ``polycc.vmax`` and ``polycc.swarmV``.
    ``relay``: ``"p2p"`` or ``"ground"`` (module docstring). ``drone_times`` (simulated drones): per drone, a
    callable giving its firmware time now (s); a drone's estimate is then lost when its last logged sample
    is :data:`ESTIMATE_LOST_S` old in that time (the log timestamp is the firmware's), so a host too loaded
    to run the simulation at real time does not stop the flight. Real drones: wall seconds since a sample
    arrived."""
    logging.getLogger("cflib.crazyflie.toccache").setLevel(logging.ERROR)
    if len(set(uris)) != len(uris) or not 1 <= len(uris) <= 16:
        raise PolyccError(f"--uris: give 1..16 distinct URIs (got {len(uris)}, the app's table holds 16 neighbours)")
    n = len(uris)
    p2p = check_relay(uris, relay)
    sw = _connect_all(uris)
    lock = threading.Lock()
    logs = [FlightLog(["time_s", *POSITION, "polycc.status"]) for _ in uris]
    sessions: list[_Session] = []
    configs = []
    arrived = [0.0] * n  # monotonic time each drone's last position sample arrived
    stamps = [-math.inf] * n  # firmware time (s) of each drone's last position sample
    flight = SwarmFlight(uris, logs, np.full(len(targets.mu), np.nan), np.full(len(targets.mu), -1), targets=targets)
    try:
        from cflib.crazyflie.log import LogConfig

        for i, uri in enumerate(uris):
            cf = sw._cfs[uri].cf
            _check(cf, uri)
            s = _Session(cf, logs[i], lock, None, t_max + 120.0)
            sessions.append(s)
            if p2p and cf.log.toc.get_element_by_complete_name("polycc.p2pRx") is None:
                raise PolyccError(f"{uri}: the app has no P2P relay (log polycc.p2pRx); flash a current polycc "
                                  "app or use --relay ground")
            lc = LogConfig(name="polyccSwarm", period_in_ms=LOG_PERIOD_MS)
            for name in (*POSITION, "polycc.status", *(P2P_LOGS if p2p else ())):
                lc.add_variable(name, cf.log.toc.get_element_by_complete_name(name).ctype)

            def on_data(ts, data, conf, i=i, s=s):
                with lock:
                    logs[i].latest.update(data)
                    s.last_pos_t = arrived[i] = time.monotonic()
                    stamps[i] = ts / 1000.0
                    logs[i].rows.append([ts / 1000.0] + [float(data[k]) for k in (*POSITION, "polycc.status")])

            cf.log.add_config(lc)
            lc.data_received_cb.add_callback(on_data)
            lc.start()
            configs.append(lc)
            if n == 1 or p2p:  # ground relay: the relayed records are the heartbeats (each is answered like one)
                s.start_heartbeats()
            set_param(cf, "polycc.radius", radius, timeout_s=PARAM_TIMEOUT_S)
            if p2p:  # before the takeoff: the drones hear each other from the floor on
                set_param(cf, "polycc.swarmN", n - 1, timeout_s=PARAM_TIMEOUT_S)
                set_param(cf, "polycc.p2pMs", max(1, round(1000.0 / bcast_hz)), timeout_s=PARAM_TIMEOUT_S)
                set_param(cf, "polycc.p2pAgeMs", min(65534, math.ceil(latency_ms)), timeout_s=PARAM_TIMEOUT_S)
                set_param(cf, "polycc.swarmId", i + 1, timeout_s=PARAM_TIMEOUT_S)
            for name, v in (("polycc.vmax", vmax), ("polycc.swarmV", swarm_v)):
                if v is not None:
                    set_param(cf, name, v, timeout_s=PARAM_TIMEOUT_S)
            if _has_param(cf, "commander.enHighLevel"):
                set_param(cf, "commander.enHighLevel", 1, timeout_s=PARAM_TIMEOUT_S)
        try:
            _fly(flight, sessions, cmap, targets, controller, takeoff, radius, t_max, bcast_hz, ctrl_hz, latency_ms,
                 sense, arrived, lock, on_update, clock or time.monotonic, p2p, stamps, drone_times)
        except KeyboardInterrupt:
            flight.outcome = "interrupted"
            raise
        finally:
            _leave_all(flight, sessions, land, clock or time.monotonic, p2p)
    finally:
        for lc in configs:
            try:
                lc.stop()
            except Exception:
                pass
        for uri in uris:
            try:
                close_without_stop(sw._cfs[uri])
            except Exception:
                pass
    return flight


def check_relay(uris: list[str], relay: str) -> bool:
    """True for the P2P relay. It needs every radio URI on one channel and data rate: the nRF's broadcast
    is heard on its own channel only (cflib's ``radio://<dongle>/<channel>/<rate>/<address>``)."""
    if relay not in ("p2p", "ground"):
        raise PolyccError(f"--relay {relay!r}: use p2p (the drones broadcast) or ground (this process relays)")
    if relay == "ground":
        return False
    radios = {tuple(u.split("/")[3:5]) for u in uris if u.startswith("radio://") and len(u.split("/")) >= 5}
    if len(radios) > 1:
        chans = ", ".join(f"channel {c} at {r}" for c, r in sorted(radios))
        raise PolyccError(f"--relay p2p: the drones are on different radio channels ({chans}) and would not hear "
                          "each other's broadcasts; put them on one channel and data rate, or use --relay ground")
    return True


def _positions(sessions) -> np.ndarray | None:
    ps = [s.position() for s in sessions]
    return None if any(p is None for p in ps) else np.array(ps, float)


def _fly(flight, sessions, cmap, targets, controller, takeoff, radius, t_max, bcast_hz, ctrl_hz, latency_ms, sense,
         arrived, lock, on_update, clock, p2p, stamps, drone_times) -> None:
    n = len(sessions)
    t_wait = time.monotonic() + FIRST_ESTIMATE_S
    while (P := _positions(sessions)) is None:
        if time.monotonic() > t_wait:
            raise PolyccError("no position estimate from every drone (stateEstimate.x/y/z); check positioning")
        time.sleep(0.05)
    d = np.linalg.norm(P[:, None] - P[None], axis=2) + np.eye(n) * 1e9
    if n > 1 and d.min() < 2 * radius:
        raise PolyccError(f"two drones start {d.min():.2f} m apart, closer than 2 r = {2 * radius:.2f} m; "
                          "place them further apart")

    def relay() -> None:
        if p2p:  # the drones broadcast themselves
            return
        now = time.monotonic()
        pts = [s.position() for s in sessions]  # takes the log lock itself
        ages = [(now - arrived[j]) * 1000.0 + latency_ms for j in range(n)]
        for i, s in enumerate(sessions):
            for j in range(n):
                if j != i:
                    s.cf.appchannel.send_packet(pack_neighbour(j, pts[j], ages[j], radius))
                    flight.relayed += 1

    def stopped() -> str | None:
        for i, s in enumerate(sessions):
            if not s.cf.is_connected():
                return f"drone {i} ({flight.uris[i]}): link lost"
            if drone_times is None:
                age, unit = time.monotonic() - s.last_pos_t, "s"
            else:
                with lock:
                    last = stamps[i]
                age, unit = drone_times[i]() - last, "s of its firmware time"
            if age > ESTIMATE_LOST_S:
                return f"drone {i} ({flight.uris[i]}): no position estimate for {ESTIMATE_LOST_S:g} {unit}"
        return None

    relay()
    z0 = P[:, 2].max()
    duration = max(1.0, abs(takeoff - z0) / TAKEOFF_SPEED)
    flight.notes.append(f"high-level takeoff of {n} drones to {takeoff:g} m in {duration:.1f} s")
    for s in sessions:
        s.cf.commander.send_notify_setpoint_stop()  # CRTP priority back to the high-level commander
        s.cf.high_level_commander.takeoff(takeoff, duration)
    t_end = clock() + duration + 5.0
    while True:
        time.sleep(1.0 / bcast_hz)
        relay()
        P = _positions(sessions)
        if np.all(np.abs(P[:, 2] - takeoff) < 0.05):
            break
        why = stopped()
        if why or clock() > t_end:
            flight.outcome = f"stopped: {why or 'the takeoff did not reach its height'}"
            return
    ctrls = [Controller(cmap, controller) for _ in range(n)]
    sent = P.copy()  # the goal last written to each app
    alive = np.ones(len(targets.mu), bool)
    dens = cmap.density(controller, alive)
    for i, s in enumerate(sessions):
        for axis, v in zip("XYZ", P[i]):
            set_param(s.cf, f"polycc.goal{axis}", float(v), timeout_s=PARAM_TIMEOUT_S)
        set_param(s.cf, "polycc.enable", 1, timeout_s=PARAM_TIMEOUT_S)
    flight.wall_enabled = time.monotonic()
    flight.notes.append("apps enabled; coverage controllers running")
    t0 = clock()
    next_ctrl = time.monotonic()
    while True:
        time.sleep(1.0 / bcast_hz)
        relay()
        now = clock()
        P = _positions(sessions)
        if n > 1:
            d = np.linalg.norm(P[:, None] - P[None], axis=2)[np.triu_indices(n, 1)]
            flight.min_pair_m = min(flight.min_pair_m, float(d.min()))
        hit = alive & (np.linalg.norm(P[:, None] - targets.mu[None], axis=2).min(0) <= sense)
        if hit.any():
            who = np.linalg.norm(P[:, None] - targets.mu[None], axis=2).argmin(0)
            flight.detected_at[hit] = now - t0
            flight.detected_by[hit] = who[hit]
            alive &= ~hit
            dens = cmap.density(controller, alive)
        if on_update is not None:
            on_update(flight, now - t0)
        if not alive.any():
            flight.outcome = "covered"
            return
        why = stopped()
        for i, s in enumerate(sessions):
            st = s.status()
            if why is None and st in STOP_REASONS:
                why = f"drone {i} ({flight.uris[i]}): {STATUS_TEXT[st]}"
        if why:
            flight.outcome = f"stopped: {why}"
            return
        if now - t0 > t_max:
            flight.outcome = "timeout"
            return
        if time.monotonic() >= next_ctrl:
            next_ctrl = time.monotonic() + 1.0 / ctrl_hz
            lab = voronoi_cells(cmap, P) if controller != "repulsive" else None
            for i, s in enumerate(sessions):
                cell = None if lab is None else np.flatnonzero(lab == i)
                g = ctrls[i].goal(P[i], np.delete(P, i, axis=0), alive, dens, cell)
                flight.cells = [c.cell for c in ctrls]
                if np.linalg.norm(g - sent[i]) > GOAL_RESEND_M:  # keep the radio for the relay
                    sent[i] = g
                    for axis, v in zip("XYZ", g):  # not confirmed: a lost write is repeated next round
                        s.cf.param.set_value(f"polycc.goal{axis}", float(v))


def _leave_all(flight: SwarmFlight, sessions, land: bool, clock, p2p: bool = False) -> None:
    """Disable every app (confirmed), then land every drone with the high-level commander. Best effort
    per drone: one whose link is gone lands by its own app's link-loss watchdog."""
    live = []
    for i, s in enumerate(sessions):
        try:
            if s.cf.is_connected():
                set_param(s.cf, "polycc.enable", 0, timeout_s=PARAM_TIMEOUT_S)
                live.append(s)
        except Exception as e:
            flight.notes.append(f"drone {i}: could not disable the app ({e}); its watchdog lands it")
    flight.wall_disabled = time.monotonic()
    # wait for the hand-over (status 14 holds until the PID's z integral has decayed): a land sent
    # while an app still streams its hold would be cancelled by it
    t_end = clock() + 10.0
    while clock() < t_end and any(s.status() in FLYING for s in live):
        time.sleep(0.05)
    flight.notes.append("apps disabled: the high-level commanders hold")
    if land and live:
        P = [s.position() for s in live]
        z = max((p[2] for p in P if p), default=1.0)
        duration = max(2.0, z / LAND_SPEED)
        for s in live:
            s.cf.high_level_commander.land(0.0, duration)
        t_end = clock() + duration + 5.0
        while clock() < t_end:
            time.sleep(0.1)
            if all((p := s.position()) is not None and p[2] < LANDED_Z for s in live):
                time.sleep(1.0)  # the planner idles at the end of the landing: motors off
                flight.notes.append("landed; the high-level commanders stopped the motors")
                break
        else:
            flight.notes.append("landing did not finish in time")
    for lg in flight.logs:
        flight.p2p.append({k.split(".")[1]: lg.latest.get(k) for k in P2P_LOGS} if p2p else {})
    if p2p:  # the swarm is over: no more broadcasts, then drop what was heard (a P2P record never removes one)
        for s in sessions:
            try:
                set_param(s.cf, "polycc.swarmId", 0, timeout_s=PARAM_TIMEOUT_S)
                set_param(s.cf, "polycc.swarmN", 0, timeout_s=PARAM_TIMEOUT_S)
            except Exception:
                pass
        t_end = clock() + 0.2  # broadcasts already in the air arrive first (in the drones' time: SITL runs slow)
        while clock() < t_end:
            time.sleep(0.02)
    for i, s in enumerate(sessions):  # the ground is leaving: drop every relayed neighbour
        try:
            for j in range(len(sessions)):
                if j != i:
                    s.cf.appchannel.send_packet(pack_forget(j + 1 if p2p else j))
        except Exception:
            pass
        s.stop_heartbeats()


def status_line(flight: SwarmFlight) -> str:
    parts = []
    for i, lg in enumerate(flight.logs):
        st = lg.latest.get("polycc.status")
        parts.append(f"{i}: {status_words(st)}")
    return "; ".join(parts)
