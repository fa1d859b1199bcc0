"""Fly a Crazyflie that runs the polycc app (real, or a simulated one) through Bitcraze's cflib.

:func:`fly` is what ``polycc fly`` does:

1. connect, check the app's params and that the PID controller is selected (the app refuses
   the others), and enable the high-level commander where the firmware has the switch;
2. optionally take off with the high-level commander (``takeoff`` metres, at most 0.5 m/s);
3. for each waypoint: set ``polycc.goalX/Y/Z`` and ``polycc.enable = 1``; the app takes control
   once airborne and flies through the certified filter; wait until within ``arrive_tol``;
4. set ``polycc.enable = 0``: the app hands the vehicle to the high-level commander, which holds
   the position;
5. optionally land with the high-level commander, which turns the motors off on the floor.

Nothing here sends a stop setpoint: in the air that would cut the motors. The run stops early,
with the reason in words, on the app's INSIDE, kernel-invalid, controller, link-loss, supervisor
or too-slow statuses and when the position estimate is lost. While connected, app-channel
heartbeats go out every 100 ms, so the app's link-loss watchdog (polycc_app.h) lands the vehicle
if the ground disappears. Positions are ``stateEstimate.x/y/z``, metres, world frame;
:class:`FlightLog` holds the rows (time in s).

Every wait (the ``timeout``, the takeoff's, the hand-over's and the landing's) is counted in the
drone's own seconds: the firmware's log timestamps, plus the wall seconds since the latest sample.
On a real Crazyflie that is wall time; a simulated one (the firmware's SITL on a loaded host runs at
a fraction of real time) gets the simulated seconds its manoeuvres take. Only the estimate watchdog
counts wall seconds: a second without any sample is a link problem whatever the drone's clock.
"""

from __future__ import annotations

import csv
import logging
import math
import struct
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

from polycc.errors import PolyccError
from polycc.link.cflib_tools import close_without_stop, connect, set_param
from polycc.onboard.app import FLYING, REPLY_FORMAT, STATUS_NAMES, STATUS_TEXT, STOP_REASONS

DEFAULT_URI = "udp://127.0.0.1:19850"
POSITION = ("stateEstimate.x", "stateEstimate.y", "stateEstimate.z")
LOG_MAX_BYTES = 26  # values in one log block (a CRTP packet of 30 bytes minus id and timestamp)
_SIZES = {"uint8_t": 1, "int8_t": 1, "uint16_t": 2, "int16_t": 2, "uint32_t": 4, "int32_t": 4, "float": 4, "FP16": 2}
TAKEOFF_SPEED = 0.5  # m/s, high-level takeoff
LAND_SPEED = 0.3  # m/s, high-level landing
HANDOVER_WAIT_S = 13.0  # s, longer than the app's settling hold (POLYCC_APP_SETTLE_MAX_MS = 12 s)
HEARTBEAT_S = 0.1  # app-channel heartbeat period
ESTIMATE_LOST_S = 1.0  # no position sample for this many wall seconds: stop
LANDED_Z = 0.08  # m: on the floor
CONNECT_TIMEOUT_S = 30.0  # wall s for one connect try (link, TOCs, param values); two tries


@dataclass
class FlightLog:
    """What `polycc fly` recorded: ``columns`` and ``rows`` (the CSV), and how the flight ended."""

    columns: list[str]
    rows: list[list[float]] = field(default_factory=list)
    outcome: str = "running"  # "arrived", "landed", "timeout", "interrupted", "lost", "stopped: <why>"
    latest: dict[str, float] = field(default_factory=dict)
    events: list[str] = field(default_factory=list)  # what happened, in words, in order
    waypoint: int = 0  # index of the waypoint being flown
    app_replies: int = 0  # app-channel replies (heartbeats answered)

    def write_csv(self, path: str | Path) -> Path:
        path = Path(path)
        with path.open("w", newline="") as f:
            w = csv.writer(f)
            w.writerow(self.columns)
            w.writerows(self.rows)
        return path

    def note(self, text: str) -> None:
        self.events.append(text)


def _import_cflib():
    try:
        import cflib.crtp
        from cflib.crazyflie.log import LogConfig
    except ImportError:
        raise PolyccError("`polycc fly` needs Bitcraze's cflib: pip install 'polycc[crazyflie]' "
                          "(or pip install 'cflib>=0.1.32')") from None
    return cflib.crtp, LogConfig


def log_names(text: str) -> list[str]:
    names = []
    for part in text.split(","):
        part = part.strip()
        if part:
            name = part if "." in part else f"polycc.{part}"
            if name not in names and name not in POSITION and name != "polycc.status":
                names.append(name)
    return names


def _blocks(names: list[str], types: dict[str, str]) -> list[list[str]]:
    """Variables packed into log blocks of at most LOG_MAX_BYTES, in order (the position first)."""
    blocks: list[list[str]] = [[]]
    used = 0
    for n in names:
        size = _SIZES[types[n]]
        if used + size > LOG_MAX_BYTES:
            blocks.append([])
            used = 0
        blocks[-1].append(n)
        used += size
    return blocks


def _has_param(cf, name: str) -> bool:
    return cf.param.toc.get_element_by_complete_name(name) is not None


class _Session:
    """One connected flight: logs, heartbeats and the waits, with the reason to stop."""

    def __init__(self, cf, log: FlightLog, lock: threading.Lock, on_update, timeout_s: float):
        self.cf, self.log, self.lock, self.on_update = cf, log, lock, on_update
        self.last_pos_t = self._wall0 = time.monotonic()
        self._stamp: tuple[float, float] | None = None  # (drone s since the first sample, its wall time)
        self._first_ms: tuple[int, float] | None = None  # the first sample's firmware ms and its wall time
        self._now = 0.0
        self.deadline = timeout_s  # in :meth:`now`'s seconds
        self._stop_hb = threading.Event()
        self._hb = threading.Thread(target=self._heartbeat, daemon=True)

    def start_heartbeats(self) -> None:
        def reply(data):
            if len(data) >= struct.calcsize(REPLY_FORMAT):
                with self.lock:
                    self.log.app_replies += 1
        self.cf.appchannel.packet_received.add_callback(reply)
        self._hb.start()

    def _heartbeat(self) -> None:
        while not self._stop_hb.wait(HEARTBEAT_S):
            try:
                self.cf.appchannel.send_packet(b"hb")
            except Exception:  # link gone: the app lands by itself
                return

    def stop_heartbeats(self) -> None:
        self._stop_hb.set()

    def stamp(self, timestamp_ms: int) -> None:
        """A log sample with the firmware's ``timestamp_ms`` arrived now (call with the lock held)."""
        wall = time.monotonic()
        if self._first_ms is None:
            self._first_ms = (timestamp_ms, wall - self._wall0)
        self._stamp = ((timestamp_ms - self._first_ms[0]) / 1000.0 + self._first_ms[1], wall)

    def now(self) -> float:
        """The drone's seconds since the session began (module docstring); never decreasing."""
        with self.lock:
            st = self._stamp
            t = time.monotonic() - (self._wall0 if st is None else st[1]) + (0.0 if st is None else st[0])
            self._now = max(self._now, t)
            return self._now

    def position(self):
        with self.lock:
            pos = [self.log.latest.get(n) for n in POSITION]
        return None if None in pos else pos

    def status(self) -> int | None:
        with self.lock:
            st = self.log.latest.get("polycc.status")
        return None if st is None else int(st)

    def wait(self, done, what: str, timeout_s: float | None = None, watch_app: bool = True) -> str | None:
        """Poll until ``done()``; returns None, or why it stopped (``timeout``, ``lost``, ``stopped: ...``).
        ``timeout_s`` and the session's deadline are the drone's seconds (:meth:`now`)."""
        t_end = self.deadline if timeout_s is None else min(self.deadline, self.now() + timeout_s)
        while True:
            time.sleep(0.05)
            if self.on_update is not None:
                self.on_update(self.log)
            if not self.cf.is_connected():
                return "lost"
            now = self.now()
            with self.lock:
                silent = time.monotonic() - self.last_pos_t
            if silent > ESTIMATE_LOST_S:
                return f"stopped: no position estimate for {ESTIMATE_LOST_S:g} s while {what}"
            st = self.status()
            if watch_app and st in STOP_REASONS:
                return f"stopped: {STATUS_TEXT[st]}"
            if done():
                return None
            if now > t_end:
                return "timeout"


def fly(uri: str, goal, log_vars: list[str], timeout_s: float = 60.0, arrive_tol: float = 0.1,
        period_ms: int = 20, on_update=None, takeoff: float | None = None, land: bool = False) -> FlightLog:
    """Fly to ``goal`` (x, y, z) or through the waypoints ``goal`` ((k, 3)) with the app, from an
    optional high-level takeoff to an optional high-level landing (module docstring).

    ``on_update(log)`` is called about 20 times a second from this thread.  A KeyboardInterrupt
    is re-raised after the app is disabled (and, with ``land``, the vehicle landed), with the
    log on the exception's ``flight_log`` attribute."""
    crtp, LogConfig = _import_cflib()  # the session itself: cflib_tools.connect
    logging.getLogger("cflib.crazyflie.toccache").setLevel(logging.ERROR)  # "Could not save cache": no cache used
    if not 10 <= period_ms <= 2550:
        raise PolyccError(f"--period-ms {period_ms}: cflib log periods are 10..2550 ms")
    goals = [tuple(float(v) for v in g) for g in (goal if hasattr(goal[0], "__len__") else [goal])]
    from cflib.crtp.serialdriver import SerialDriver

    if SerialDriver not in crtp.CLASSES:  # init_drivers appends the drivers again on every call
        crtp.init_drivers(enable_serial_driver=True)
    lock = threading.Lock()
    try:  # bounded, and one fresh session after a stalled one (cflib waits for ever on a lost reply)
        scf = connect(uri, CONNECT_TIMEOUT_S, attempts=2)
    except PolyccError as e:
        raise PolyccError(f"{e}; is the Crazyflie (or `polycc sim-device`) running?") from None
    cf = scf.cf
    configs = []
    log = None
    try:
        toc = cf.log.toc
        wanted = list(POSITION) + ["polycc.status"] + log_vars
        types = {}
        for n in wanted:
            el = toc.get_element_by_complete_name(n)
            if el is None:
                raise PolyccError(f"log variable {n} is not in the Crazyflie's log TOC; is the polycc app flashed?")
            types[n] = el.ctype
        for n in ("polycc.goalX", "polycc.goalY", "polycc.goalZ", "polycc.enable"):
            if not _has_param(cf, n):
                raise PolyccError(f"parameter {n} is not on the Crazyflie; flash the polycc app (`polycc flash`)")
        if _has_param(cf, "stabilizer.controller") and int(cf.param.get_value("stabilizer.controller")) not in (0, 1):
            raise PolyccError("stabilizer.controller is not PID (1); the app only flies with the PID controller: "
                              "set it with cf.param.set_value('stabilizer.controller', 1) or in cfclient")
        log = FlightLog(["time_s"] + wanted)
        session = _Session(cf, log, lock, on_update, timeout_s)
        t_first: list[int] = []

        def on_data(timestamp, data, conf):
            with lock:
                log.latest.update(data)
                if "stateEstimate.x" in data:
                    session.last_pos_t = time.monotonic()
                    session.stamp(timestamp)
                if "stateEstimate.x" in data and len(log.latest) == len(wanted):
                    if not t_first:
                        t_first.append(timestamp)
                    log.rows.append([(timestamp - t_first[0]) / 1000.0] + [log.latest.get(n, math.nan) for n in wanted])

        for i, names in enumerate(_blocks(wanted, types)):
            lc = LogConfig(name=f"polycc{i}", period_in_ms=period_ms)
            for n in names:
                lc.add_variable(n, types[n])
            cf.log.add_config(lc)
            lc.data_received_cb.add_callback(on_data)
            configs.append(lc)
        for lc in configs:
            lc.start()
        session.start_heartbeats()
        if _has_param(cf, "commander.enHighLevel"):
            set_param(cf, "commander.enHighLevel", 1)  # firmware with the switch: the HL commander is off by default
        try:
            _flight(cf, session, log, goals, arrive_tol, takeoff, land)
        except KeyboardInterrupt as e:
            log.outcome = "interrupted"
            _leave(cf, session, log, land)
            e.flight_log = log
            raise
    finally:
        if log is not None and configs:
            try:
                for lc in configs:
                    lc.stop()
            except Exception:
                pass
        close_without_stop(scf)
    return log


def _flight(cf, session: _Session, log: FlightLog, goals, arrive_tol: float, takeoff, land: bool) -> None:
    hl = cf.high_level_commander
    if session.wait(lambda: session.position() is not None, "waiting for the first position", 5.0, False):
        raise PolyccError("no position estimate from the Crazyflie (stateEstimate.x/y/z); check the positioning system")
    if takeoff is not None:
        z0 = session.position()[2]
        duration = max(1.0, abs(takeoff - z0) / TAKEOFF_SPEED)
        log.note(f"high-level takeoff to {takeoff:g} m in {duration:.1f} s")
        # a client that streamed setpoints before (cflib's close_link sends one) leaves the commander at
        # CRTP priority, where high-level commands are ignored: hand the priority back first
        cf.commander.send_notify_setpoint_stop()
        hl.takeoff(takeoff, duration)
        why = session.wait(lambda: abs(session.position()[2] - takeoff) < 0.05, "taking off", duration + 5.0,
                           watch_app=False)
        if why:
            log.outcome = why if why != "timeout" else "stopped: the takeoff did not reach its height"
            _leave(cf, session, log, land)
            return
    for k, g in enumerate(goals):
        log.waypoint = k
        for axis, v in zip("XYZ", g):
            set_param(cf, f"polycc.goal{axis}", v)
        if k == 0:
            set_param(cf, "polycc.enable", 1)
        log.note(f"waypoint {k + 1}/{len(goals)}: {','.join(f'{v:g}' for v in g)}")
        why = session.wait(lambda: math.dist(session.position(), g) <= arrive_tol, f"flying to waypoint {k + 1}")
        if why:
            log.outcome = why
            _leave(cf, session, log, land)
            return
    log.outcome = "arrived"
    _leave(cf, session, log, land)


def _leave(cf, session: _Session, log: FlightLog, land: bool) -> None:
    """Disable the app (it hands over to the high-level commander, holding), then land if asked.
    Best effort when the link is gone: the app's own watchdog lands the vehicle then."""
    try:
        if not cf.is_connected():
            return
        set_param(cf, "polycc.enable", 0)  # confirmed: a queued write could be overtaken by the land
        # the hand-over (status 14) holds until the PID's z integral has decayed; a land sent while the app
        # still streams its hold would be cancelled by it (the high-level commander's task preempts the app
        # between its check for a new plan and its hold setpoint, which stops the plan): wait past the hold's
        # longest, POLYCC_APP_SETTLE_MAX_MS = 12 s (firmware_app/src/polycc_app.h); it was 10 s
        session.wait(lambda: session.status() not in FLYING, "handing over", HANDOVER_WAIT_S, watch_app=False)
        log.note("app disabled: the high-level commander holds the position")
        if land:
            pos = session.position()
            z = pos[2] if pos else 1.0
            duration = max(2.0, z / LAND_SPEED)
            log.note(f"high-level landing in {duration:.1f} s")
            cf.high_level_commander.land(0.0, duration)
            why = session.wait(lambda: session.position()[2] < LANDED_Z, "landing", duration + 5.0, watch_app=False)
            if why is None:  # the planner idles at the end of the landing: motors off
                session.wait(lambda: False, "landing", 1.0, watch_app=False)
                if log.outcome == "arrived":
                    log.outcome = "landed"
                log.note("landed; the high-level commander stopped the motors")
            else:
                log.note(f"landing did not finish ({why})")
    except Exception:
        pass
    finally:
        session.stop_heartbeats()


def status_words(st) -> str:
    if st is None:
        return "-"
    return f"{int(st)} {STATUS_NAMES.get(int(st), '?')}"
