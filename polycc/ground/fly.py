"""Fly a Crazyflie that runs the polycc app (real, or `polycc sim-device`) through Bitcraze's cflib.

:func:`fly` connects, sets ``polycc.goalX/Y/Z`` and ``polycc.enable``, streams the position
(``stateEstimate.x/y/z``, metres, world frame), ``polycc.status`` and chosen log variables, and
stops on arrival, timeout, link loss or Ctrl-C. :class:`FlightLog` holds the rows (time in s).
"""

from __future__ import annotations

import csv
import logging
import math
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

from polycc.errors import PolyccError

DEFAULT_URI = "udp://127.0.0.1:19850"
POSITION = ("stateEstimate.x", "stateEstimate.y", "stateEstimate.z")
LOG_MAX_BYTES = 26  # values in one log block (a CRTP packet of 30 bytes minus id and timestamp)
_SIZES = {"uint8_t": 1, "int8_t": 1, "uint16_t": 2, "int16_t": 2, "uint32_t": 4, "int32_t": 4, "float": 4, "FP16": 2}


@dataclass
class FlightLog:
    """What `polycc fly` recorded: ``columns`` and ``rows`` (the CSV), and how the flight ended."""

    columns: list[str]
    rows: list[list[float]] = field(default_factory=list)
    outcome: str = "running"  # "arrived", "timeout", "interrupted", "lost"
    latest: dict[str, float] = field(default_factory=dict)

    def write_csv(self, path: str | Path) -> Path:
        path = Path(path)
        with path.open("w", newline="") as f:
            w = csv.writer(f)
            w.writerow(self.columns)
            w.writerows(self.rows)
        return path


def _import_cflib():
    try:
        import cflib.crtp
        from cflib.crazyflie import Crazyflie
        from cflib.crazyflie.log import LogConfig
        from cflib.crazyflie.syncCrazyflie import SyncCrazyflie
    except ImportError:
        raise PolyccError("`polycc fly` needs Bitcraze's cflib: pip install 'polycc[crazyflie]' "
                          "(or pip install 'cflib>=0.1.32')") from None
    return cflib.crtp, Crazyflie, LogConfig, SyncCrazyflie


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


def _set_param(cf, name: str, value: float, timeout_s: float = 3.0) -> None:
    """Write a param and wait until the Crazyflie confirms it (cflib does not retransmit)."""
    done = threading.Event()
    group, short = name.split(".", 1)

    def cb(_name, _value):
        done.set()

    cf.param.add_update_callback(group=group, name=short, cb=cb)
    try:
        cf.param.set_value(name, value)
        if not done.wait(timeout_s):
            raise PolyccError(f"no confirmation of {name} = {value:g} within {timeout_s:g} s; check the link")
    finally:
        try:
            cf.param.remove_update_callback(group=group, name=short, cb=cb)
        except Exception:  # older cflib without remove_update_callback
            pass


def fly(uri: str, goal, log_vars: list[str], timeout_s: float = 60.0, arrive_tol: float = 0.1,
        period_ms: int = 20, on_update=None) -> FlightLog:
    """Connect, set the goal and enable the app, log until arrival/timeout/Ctrl-C, then disable the app
    and send a stop setpoint. ``on_update(log)`` is called about 10 times a second from this thread.
    A KeyboardInterrupt is re-raised after the clean stop, with ``log.outcome = "interrupted"``
    available on the exception's ``flight_log`` attribute."""
    crtp, Crazyflie, LogConfig, SyncCrazyflie = _import_cflib()
    logging.getLogger("cflib.crazyflie.toccache").setLevel(logging.ERROR)  # "Could not save cache": no cache used
    if not 10 <= period_ms <= 2550:
        raise PolyccError(f"--period-ms {period_ms}: cflib log periods are 10..2550 ms")
    goal = tuple(float(v) for v in goal)
    from cflib.crtp.serialdriver import SerialDriver

    if SerialDriver not in crtp.CLASSES:  # init_drivers appends the drivers again on every call
        crtp.init_drivers(enable_serial_driver=True)
    lock = threading.Lock()
    try:
        scf = SyncCrazyflie(uri, cf=Crazyflie(rw_cache=None))
        scf.open_link()
    except Exception as e:
        raise PolyccError(f"cannot connect to {uri}: {e}; is the Crazyflie (or `polycc sim-device`) running?") from None
    cf = scf.cf
    configs = []
    try:
        scf.wait_for_params()
        toc = cf.log.toc
        wanted = list(POSITION) + ["polycc.status"] + log_vars
        types = {}
        for n in wanted:
            el = toc.get_element_by_complete_name(n)
            if el is None:
                raise PolyccError(f"log variable {n} is not in the Crazyflie's log TOC; is the polycc app flashed?")
            types[n] = el.ctype
        for n in ("polycc.goalX", "polycc.goalY", "polycc.goalZ", "polycc.enable"):
            if cf.param.toc.get_element_by_complete_name(n) is None:
                raise PolyccError(f"parameter {n} is not on the Crazyflie; flash the polycc app (`polycc flash`)")
        log = FlightLog(["time_s"] + wanted)
        t_first: list[int] = []
        recording = threading.Event()  # rows are kept from the confirmed enable to the stop

        def on_data(timestamp, data, conf):
            with lock:
                log.latest.update(data)
                if recording.is_set() and "stateEstimate.x" in data and len(log.latest) == len(wanted):
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
        for axis, v in zip("XYZ", goal):
            _set_param(cf, f"polycc.goal{axis}", v)
        _set_param(cf, "polycc.enable", 1)
        recording.set()
        t0 = time.monotonic()
        try:
            while True:
                time.sleep(0.1)
                with lock:
                    pos = [log.latest.get(n) for n in POSITION]
                if on_update is not None:
                    on_update(log)
                if None not in pos and math.dist(pos, goal) <= arrive_tol:
                    log.outcome = "arrived"
                    break
                if not cf.is_connected():
                    log.outcome = "lost"
                    break
                if time.monotonic() - t0 > timeout_s:
                    log.outcome = "timeout"
                    break
        except KeyboardInterrupt as e:
            log.outcome = "interrupted"
            e.flight_log = log
            raise
        finally:
            recording.clear()
            _stop(cf, configs)
    finally:
        scf.close_link()
    return log


def _stop(cf, configs) -> None:
    """Disable the app and send a stop (zero) setpoint; then stop logging. Best effort: the link may be gone."""
    try:
        if cf.is_connected():
            cf.param.set_value("polycc.enable", 0)
            cf.commander.send_stop_setpoint()
            cf.commander.send_notify_setpoint_stop()
            time.sleep(0.1)
            for lc in configs:
                lc.stop()
    except Exception:
        pass
