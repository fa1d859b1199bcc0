"""`polycc fly --uri URI [--takeoff H] --goal X,Y,Z[;X,Y,Z...] [--land]`: fly a Crazyflie (real or simulated)
through waypoints with the polycc app, through Bitcraze's cflib (the flight itself: :mod:`polycc.ground.fly`)."""

from __future__ import annotations

import argparse
import json
import math
import os
import time

import numpy as np

from polycc.cli.argtypes import NEGATIVE_VALUE_OPTIONS, number
from polycc.errors import PolyccError
from polycc.ground.fly import DEFAULT_URI, POSITION, FlightLog, fly, log_names, status_words
from polycc.onboard.app import STATUS_TEXT

HELP = "fly a Crazyflie running the polycc app (or a simulated one) through waypoints, streaming its logs (needs cflib)"


def waypoints(text: str) -> np.ndarray:
    """``x,y,z;x,y,z;...`` (metres) -> (k, 3)."""
    out = []
    for part in text.split(";"):
        vals = part.strip().split(",")
        try:
            p = [float(v) for v in vals]
        except ValueError:
            raise argparse.ArgumentTypeError(f"{part!r}: expected x,y,z in metres; waypoints are separated by ';'") \
                from None
        if len(p) != 3 or not all(math.isfinite(v) for v in p):
            raise argparse.ArgumentTypeError(f"{part!r}: expected three finite numbers x,y,z (m)")
        out.append(p)
    return np.array(out)


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "fly",
        help=HELP,
        description=(
            "Connects with cflib (install it with `pip install 'polycc[crazyflie]'`). With --takeoff H the "
            "high-level commander lifts the drone from the floor to H m first. Then, for each waypoint in turn, "
            "it sets polycc.goalX/Y/Z and polycc.enable = 1: the app takes control once the drone is airborne "
            "and flies it through the certified safety filter; the next waypoint follows within --arrive-tol. At "
            "the end (or on --timeout, Ctrl-C or a stop reason) it sets polycc.enable = 0: the app hands the "
            "drone to the high-level commander, which holds the position; with --land it then lands, and the "
            "motors stop on the floor. No stop setpoint is ever sent in the air. The run stops early, with the "
            "reason in words, when the app reports an obstacle too close (inside), a refused state, a controller "
            "other than PID, link loss, a supervisor lock, or when the position estimate is lost. App-channel "
            "heartbeats go out every 100 ms: if they stop for 1 s while the app flies, it lands the drone. Writes "
            "every log row to --csv. Exit code 0 on arrival, 1 otherwise, 130 on Ctrl-C."
        ),
    )
    p.add_argument("--uri", default=os.environ.get("CFLIB_URI", DEFAULT_URI),
                   help="cflib URI: radio://0/80/2M/E7E7E7E7E7, usb://0, serial://ttyUSB-polycc0, udp://HOST:PORT "
                        "(default: $CFLIB_URI, else %(default)s as `polycc sim-device --udp` serves)")
    p.add_argument("--goal", type=waypoints, metavar="X,Y,Z[;X,Y,Z...]",
                   help="goal, or waypoints flown in order separated by ';' (quote them in a shell), m, world frame")
    NEGATIVE_VALUE_OPTIONS.add("--goal")
    p.add_argument("--plan", metavar="PLAN.json",
                   help="fly the waypoints of a `polycc plan` result instead of --goal (default: none)")
    p.add_argument("--takeoff", type=number(float, 0.1, 10.0, unit="m"), default=None, metavar="H",
                   help="first take off from the floor to H m with the high-level commander (0.5 m/s) "
                        "(default: the drone is already flying)")
    p.add_argument("--land", action="store_true",
                   help="land with the high-level commander at the end (0.3 m/s); the motors stop on the floor "
                        "(default: hover under the high-level commander)")
    p.add_argument("--log", default="psi,ux,uy,uz", metavar="VARS",
                   help="comma-separated log variables to stream besides the position and status; a name without "
                        "a group is in `polycc` (e.g. psi, ux, stateEstimate.vx) (default: %(default)s)")
    p.add_argument("--csv", metavar="FILE", default="fly_log.csv",
                   help="log file: one row per position sample, time in s from the first sample (default: %(default)s)")
    p.add_argument("--timeout", type=number(float, 0.0, 1e6, lo_open=True, unit="s"), default=60.0, metavar="S",
                   help="give up after S seconds of the drone's time (its log timestamps: wall time on a real "
                        "Crazyflie, simulated time on a SITL) (the app hands over to the high-level commander) "
                        "(default: %(default)s)")
    p.add_argument("--arrive-tol", type=number(float, 0.0, 10.0, lo_open=True, unit="m"), default=0.1, metavar="M",
                   help="arrival: distance to a waypoint, m (default: %(default)s)")
    p.add_argument("--period-ms", type=number(int, 10, 2550, unit="ms"), default=20, metavar="MS",
                   help="log period, ms (10..2550, a multiple of 10) (default: %(default)s)")
    p.set_defaults(func=run)


def _plan_waypoints(path: str) -> np.ndarray:
    try:
        data = json.loads(open(path).read())
        w = np.asarray(data["waypoints"], float).reshape(-1, 3)
    except FileNotFoundError:
        raise PolyccError(f"{path}: no such plan; write one with `polycc plan DIR --start ... --goal ...`") from None
    except (ValueError, KeyError, TypeError) as exc:
        raise PolyccError(f"{path}: not a polycc plan ({exc}); write one with `polycc plan`") from None
    return w[1:] if len(w) > 1 else w  # the first waypoint is the start


def _table(log: FlightLog, goals, t0: float):
    from rich.table import Table

    latest = log.latest
    g = goals[min(log.waypoint, len(goals) - 1)]
    t = Table(title=f"polycc fly: waypoint {log.waypoint + 1}/{len(goals)} -> {','.join(f'{v:g}' for v in g)}",
              header_style="bold")
    t.add_column("quantity")
    t.add_column("value", justify="right")
    pos = [latest.get(n) for n in POSITION]
    t.add_row("time s", f"{time.monotonic() - t0:.1f}")
    if None not in pos:
        t.add_row("position m", ",".join(f"{v:.2f}" for v in pos))
        t.add_row("distance to waypoint m", f"{math.dist(pos, g):.3f}")
    st = latest.get("polycc.status")
    t.add_row("status", status_words(st))
    if st is not None:
        t.add_row("", STATUS_TEXT.get(int(st), ""))
    for n in log.columns[5:]:
        v = latest.get(n)
        t.add_row(n, "-" if v is None else f"{v:.4g}")
    t.add_row("samples", str(len(log.rows)))
    if log.events:
        t.add_row("last event", log.events[-1])
    return t


def run(args) -> int:
    from rich.live import Live

    from polycc.cli.console import console

    if args.plan:
        goals = _plan_waypoints(args.plan)
    elif args.goal is not None:
        goals = args.goal
    else:
        raise PolyccError("give --goal X,Y,Z (or waypoints X,Y,Z;X,Y,Z) or --plan PLAN.json")
    log_vars = log_names(args.log)
    t0 = time.monotonic()
    log = None
    try:
        with Live(console=console, refresh_per_second=5, transient=False) as live:
            def update(lg):
                live.update(_table(lg, goals, t0))
            log = fly(args.uri, goals, log_vars, args.timeout, args.arrive_tol, args.period_ms, update,
                      takeoff=args.takeoff, land=args.land)
            live.update(_table(log, goals, t0))
    except KeyboardInterrupt as e:
        log = getattr(e, "flight_log", None)
        if log is not None:
            console.print("interrupted: app disabled, the high-level commander holds"
                          + (" and landed" if args.land else "") + f"; log: {log.write_csv(args.csv)}", soft_wrap=True)
        raise
    console.print()
    for e in log.events:
        console.print(f"  {e}", soft_wrap=True)
    path = log.write_csv(args.csv)
    psi = [r[log.columns.index("polycc.psi")] for r in log.rows] if "polycc.psi" in log.columns else []
    extra = f", min psi {min(psi):.3f} m" if psi else ""
    console.print(f"{log.outcome} after {time.monotonic() - t0:.1f} s, {len(log.rows)} samples{extra}; log: {path}",
                  soft_wrap=True)
    return 0 if log.outcome in ("arrived", "landed") else 1
