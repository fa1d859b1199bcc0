"""`polycc fly --uri URI --goal X,Y,Z`: fly a Crazyflie (real or `polycc sim-device`) to a goal with the
polycc app, through Bitcraze's cflib."""

from __future__ import annotations

import csv
import logging
import math
import os
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

from polycc.commands.argtypes import add_point_option, number
from polycc.errors import PolyccError

HELP = "fly a Crazyflie running the polycc app (or `polycc sim-device`) to a goal, streaming its logs (needs cflib)"
DEFAULT_URI = "udp://127.0.0.1:19850"
POSITION = ("stateEstimate.x", "stateEstimate.y", "stateEstimate.z")
LOG_MAX_BYTES = 26  # values in one log block (a CRTP packet of 30 bytes minus id and timestamp)
_SIZES = {"uint8_t": 1, "int8_t": 1, "uint16_t": 2, "int16_t": 2, "uint32_t": 4, "int32_t": 4, "float": 4, "FP16": 2}


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "fly",
        help=HELP,
        description=(
            "Connects with cflib (install it with `pip install 'polycc[crazyflie]'`), sets polycc.goalX/Y/Z and "
            "polycc.enable = 1, streams stateEstimate.x/y/z, polycc.status and the --log variables live, and stops "
            "cleanly on arrival (within --arrive-tol of the goal), --timeout or Ctrl-C: polycc.enable = 0 and a stop "
            "setpoint. Writes every log row to --csv. Exit code 0 on arrival, 1 otherwise, 130 on Ctrl-C."
        ),
    )
    p.add_argument("--uri", default=os.environ.get("CFLIB_URI", DEFAULT_URI),
                   help="cflib URI: radio://0/80/2M/E7E7E7E7E7, usb://0, serial://ttyUSB-polycc0, udp://HOST:PORT "
                        "(default: $CFLIB_URI, else %(default)s as `polycc sim-device --udp` serves)")
    add_point_option(p, "--goal", required=True, help="goal position, m (world frame)")
    p.add_argument("--log", default="psi,ux,uy,uz", metavar="VARS",
                   help="comma-separated log variables to stream besides the position and status; a name without "
                        "a group is in `polycc` (e.g. psi, ux, stateEstimate.vx) (default: %(default)s)")
    p.add_argument("--csv", metavar="FILE", default="fly_log.csv",
                   help="log file: one row per position sample, time in s from the first sample (default: %(default)s)")
    p.add_argument("--timeout", type=number(float, 0.0, 1e6, lo_open=True, unit="s"), default=60.0, metavar="S",
                   help="give up (and stop) after S seconds of flight (default: %(default)s)")
    p.add_argument("--arrive-tol", type=number(float, 0.0, 10.0, lo_open=True, unit="m"), default=0.1, metavar="M",
                   help="arrival: distance to the goal, m (default: %(default)s)")
    p.add_argument("--period-ms", type=number(int, 10, 2550, unit="ms"), default=20, metavar="MS",
                   help="log period, ms (10..2550, a multiple of 10) (default: %(default)s)")
    p.set_defaults(func=run)


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


def _log_names(text: str) -> list[str]:
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


def _table(log: FlightLog, goal, t0: float):
    from rich.table import Table

    from host_sim.app_ffi import STATUS_NAMES

    latest = log.latest
    t = Table(title=f"polycc fly -> goal {','.join(f'{v:g}' for v in goal)}", header_style="bold")
    t.add_column("quantity")
    t.add_column("value", justify="right")
    pos = [latest.get(n) for n in POSITION]
    t.add_row("time s", f"{time.monotonic() - t0:.1f}")
    if None not in pos:
        t.add_row("position m", ",".join(f"{v:.2f}" for v in pos))
        t.add_row("distance to goal m", f"{math.dist(pos, goal):.3f}")
    st = latest.get("polycc.status")
    if st is not None:
        t.add_row("status", f"{int(st)} ({STATUS_NAMES.get(int(st), '?')})")
    for n in log.columns[5:]:
        v = latest.get(n)
        t.add_row(n, "-" if v is None else f"{v:.4g}")
    t.add_row("samples", str(len(log.rows)))
    return t


def run(args) -> int:
    from rich.live import Live

    from polycc.console import console

    if not args.arrive_tol > 0 or not args.timeout > 0:
        raise PolyccError("--arrive-tol and --timeout must be > 0")
    log_vars = _log_names(args.log)
    t0 = time.monotonic()
    log = None
    goal = tuple(float(v) for v in args.goal)
    try:
        with Live(console=console, refresh_per_second=5, transient=False) as live:
            def update(lg):
                live.update(_table(lg, goal, t0))
            log = fly(args.uri, goal, log_vars, args.timeout, args.arrive_tol, args.period_ms, update)
            live.update(_table(log, goal, t0))
    except KeyboardInterrupt as e:
        log = getattr(e, "flight_log", None)
        if log is not None:
            console.print(f"interrupted: app disabled, stop setpoint sent; log: {log.write_csv(args.csv)}", soft_wrap=True)
        raise
    console.print()
    path = log.write_csv(args.csv)
    psi = [r[log.columns.index("polycc.psi")] for r in log.rows] if "polycc.psi" in log.columns else []
    extra = f", min psi {min(psi):.3f} m" if psi else ""
    console.print(f"{log.outcome} after {time.monotonic() - t0:.1f} s, {len(log.rows)} samples{extra}; log: {path}",
                  soft_wrap=True)
    return 0 if log.outcome == "arrived" else 1
