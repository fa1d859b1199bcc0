"""`polycc swarm-fly DIR --uris URI,URI,...`: Crazyflies running the polycc app cover a ToI density
together through cflib's Swarm (polycc.swarm.fly)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from polycc.cli.argtypes import number
from polycc.cli.swarm_sim import add_coverage_options, add_relay_option, coverage_setup
from polycc.errors import PolyccError

HELP = "fly real (or simulated) Crazyflies with the polycc app as a swarm covering targets of interest (cflib Swarm)"


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "swarm-fly",
        help=HELP,
        description=(
            "Connects to every URI at once with cflib's Swarm, takes all drones off with the high-level commander, "
            "lets every drone know the others' positions (--relay: the apps' own P2P radio broadcasts, or this "
            "process relaying each logged position over the app channel; the apps add the buffered Voronoi "
            "half-spaces to the certified barrier: drone-drone safety is on board), runs one coverage "
            "controller per drone on this machine (the one `polycc swarm-sim` flies) writing polycc.goalX/Y/Z, and "
            "stops when every peak is detected, at --t-max, on Ctrl-C, or when one app stops. Then every app is "
            "disabled (the high-level commander holds) and, unless --no-land, every drone lands. No stop setpoint "
            "is sent. Each URI may be a real Crazyflie (radio://...) or `polycc sim-device` (udp://...). Prints a "
            "per-drone table, the minimum inter-drone distance of the estimates, coverage ratio and task time; "
            "writes DIR/coverage.png and DIR/swarm_fly.json. Exit code 1 unless every drone landed (or held, with "
            "--no-land) after the task."
        ),
    )
    p.add_argument("out", metavar="DIR", help="build folder (from `polycc build`) whose polytopes.h the drones fly")
    p.add_argument("--uris", required=True, metavar="URI,URI,...",
                   help="the drones, comma separated, e.g. radio://0/80/2M/E7E7E7E701,radio://0/80/2M/E7E7E7E702 "
                        "or udp://127.0.0.1:19850,udp://127.0.0.1:19851")
    add_coverage_options(p)
    p.add_argument("--takeoff", type=number(float, 0.1, 5.0, unit="m"), default=0.9, metavar="Z",
                   help="high-level takeoff height, m (default: %(default)s)")
    p.add_argument("--t-max", type=number(float, 0.0, 3600.0, lo_open=True, unit="s"), default=60.0, metavar="S",
                   help="task time limit after the takeoff, s (default: %(default)s)")
    p.add_argument("--bcast-hz", type=number(float, 2.0, 50.0, unit="Hz"), default=10.0, metavar="HZ",
                   help="neighbour relay rate, Hz; >= 2 keeps every app's neighbour timeout (0.5 s) from firing "
                        "(default: %(default)s)")
    p.add_argument("--latency-ms", type=number(float, 0.0, 400.0, unit="ms"), default=50.0, metavar="MS",
                   help="bound on the log up-link plus relay down-link delay, ms, added to every relayed position's "
                        "age (default: %(default)s)")
    add_relay_option(p, default="p2p for radio:// URIs, ground for simulated udp:// drones")
    p.add_argument("--no-land", action="store_true", help="leave the drones hovering under the high-level "
                                                          "commander at the end instead of landing them")
    p.add_argument("--plot", metavar="FILE.png", help="coverage plot (default: DIR/coverage.png)")
    p.set_defaults(func=run)


def run(args) -> int:
    from rich.table import Table

    from polycc.cli.console import console
    from polycc.swarm.fly import status_line, swarm_fly
    from polycc.swarm.plot import plot_coverage

    out = Path(args.out)
    if not (out / "polytopes.h").is_file():
        raise PolyccError(f"{out / 'polytopes.h'}: not found; run `polycc build SCENE -o {out}` first")
    try:
        import cflib  # noqa: F401
    except ImportError:
        raise PolyccError("swarm-fly needs cflib: pip install 'polycc[crazyflie]'") from None
    uris = [u.strip() for u in args.uris.split(",") if u.strip()]
    radio = all(u.startswith("radio://") for u in uris)
    relay = args.relay or ("p2p" if radio else "ground")
    if relay == "p2p" and not radio:
        raise PolyccError("--relay p2p needs Crazyflies on radio:// URIs: simulated drones (udp://, `polycc "
                          "sim-device`) have no radio between them; use --relay ground (their default)")
    _nav, cmap, targets, _centres, _rng = coverage_setup(args, out)
    last = [-1.0]

    def update(flight, t):
        if t - last[0] >= 5.0:
            last[0] = t
            console.print(f"t {t:5.1f} s, peaks {int(np.isfinite(flight.detected_at).sum())}/{len(targets.mu)}, "
                          f"{status_line(flight)}", soft_wrap=True)

    how = "the drones broadcast their positions (P2P)" if relay == "p2p" else "this process relays their positions"
    console.print(f"connecting to {len(uris)} drones ({how}) ...", soft_wrap=True)
    try:
        fl = swarm_fly(uris, cmap, targets, controller=args.controller, takeoff=args.takeoff, radius=args.radius,
                       t_max=args.t_max, bcast_hz=args.bcast_hz, latency_ms=args.latency_ms, sense=args.sense,
                       land=not args.no_land, on_update=update, relay=relay)
    except KeyboardInterrupt:
        console.print("interrupted: apps disabled" + ("" if args.no_land else ", drones landed"))
        return 130
    table = Table(title=f"polycc swarm-fly: {len(uris)} drones, {args.controller}", header_style="bold",
                  caption="positions are the drones' own estimates, m")
    for h in ("drone", "uri", "start", "end", "path m", "peaks", "status"):
        table.add_column(h, justify="right", overflow="fold")
    P = fl.positions
    for i, uri in enumerate(uris):
        p = P[i]
        path = float(np.linalg.norm(np.diff(p, axis=0), axis=1).sum()) if len(p) > 1 else 0.0
        table.add_row(str(i), uri, ",".join(f"{v:.2f}" for v in p[0]), ",".join(f"{v:.2f}" for v in p[-1]),
                      f"{path:.2f}", str(int(np.sum(fl.detected_by == i))), status_line(fl).split("; ")[i])
    console.print(table)
    for note in fl.notes:
        console.print(f"  {note}", soft_wrap=True)
    plot = Path(args.plot) if args.plot else out / "coverage.png"
    plot_coverage(plot, cmap, fl, f"polycc swarm-fly: {len(uris)} drones ({args.controller}), coverage "
                                  f"{fl.coverage:.2f}")
    found = np.isfinite(fl.detected_at)
    task = float(np.nanmax(fl.detected_at)) if found.all() and len(found) else None
    summary = {"uris": uris, "controller": args.controller, "outcome": fl.outcome, "coverage_ratio": fl.coverage,
               "task_time_s": task, "min_inter_drone_m": fl.min_pair_m if math.isfinite(fl.min_pair_m) else None,
               "relay": relay, "relayed_records": fl.relayed, "p2p": fl.p2p,
               "end_positions": [p[-1].tolist() for p in P],
               "targets": targets.to_json()["targets"],
               "detected_at_s": [None if not f else float(v) for f, v in zip(found, fl.detected_at)],
               "notes": fl.notes}
    (out / "swarm_fly.json").write_text(json.dumps(summary, indent=1) + "\n")
    mind = f"{fl.min_pair_m:.3f} m" if math.isfinite(fl.min_pair_m) else "-"
    console.print(f"outcome: {fl.outcome}; coverage ratio {fl.coverage:.2f} ({int(found.sum())} of {len(found)} "
                  f"peaks), task time {'-' if task is None else f'{task:.1f} s'}; min inter-drone distance "
                  f"(estimates) {mind}", soft_wrap=True)
    console.print(f"coverage plot: {plot}; summary: {out / 'swarm_fly.json'}", soft_wrap=True)
    ended = any(n.startswith("landed") for n in fl.notes) or args.no_land
    return 0 if fl.outcome in ("covered", "timeout") and ended else 1
