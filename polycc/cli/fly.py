"""`polycc fly --uri URI --goal X,Y,Z`: fly a Crazyflie (real or `polycc sim-device`) to a goal with the
polycc app, through Bitcraze's cflib (the flight itself: :mod:`polycc.ground.fly`)."""

from __future__ import annotations

import math
import os
import time

from polycc.cli.argtypes import add_point_option, number
from polycc.errors import PolyccError
from polycc.ground.fly import DEFAULT_URI, POSITION, FlightLog, fly, log_names

HELP = "fly a Crazyflie running the polycc app (or `polycc sim-device`) to a goal, streaming its logs (needs cflib)"


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

def _table(log: FlightLog, goal, t0: float):
    from rich.table import Table

    from polycc.onboard.app import STATUS_NAMES

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

    from polycc.cli.console import console

    if not args.arrive_tol > 0 or not args.timeout > 0:
        raise PolyccError("--arrive-tol and --timeout must be > 0")
    log_vars = log_names(args.log)
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
            console.print("interrupted: app disabled, stop setpoint sent; log: "
                          f"{log.write_csv(args.csv)}", soft_wrap=True)
        raise
    console.print()
    path = log.write_csv(args.csv)
    psi = [r[log.columns.index("polycc.psi")] for r in log.rows] if "polycc.psi" in log.columns else []
    extra = f", min psi {min(psi):.3f} m" if psi else ""
    console.print(f"{log.outcome} after {time.monotonic() - t0:.1f} s, {len(log.rows)} samples{extra}; log: {path}",
                  soft_wrap=True)
    return 0 if log.outcome == "arrived" else 1
