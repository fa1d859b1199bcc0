"""`polycc swarm-sim DIR --drones N --random-targets K`: N drones, each its own app instance, covering
a Gaussian-mixture ToI density on the fast simulator (docs/swarm.md)."""

from __future__ import annotations

import json
import math
import time
from pathlib import Path

import numpy as np

from polycc.cli.argtypes import number
from polycc.cli.scene_args import add_scene_options, load_scene_from_args
from polycc.errors import PolyccError

HELP = "fly N drones (each its own app instance, neighbours in the barrier) covering targets of interest"


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "swarm-sim",
        help=HELP,
        description=(
            "Swarm software-in-the-loop on the fast simulator: N independent instances of the host-built app "
            "(firmware_app/src/polycc_app.c + polycc_swarm.c, the same C as on board) with DIR/polytopes.h, one "
            "vehicle model each, on a 1 kHz clock. Every drone broadcasts its estimate (--bcast-hz, --latency-ms); "
            "the others' apps get it over the app channel and add its buffered Voronoi half-space to the barrier "
            "(docs/swarm.md). A per-drone coverage controller (seed 003: CVT on the ToI density with the navigation "
            "function of the certified free grid as the guided map) writes each app's goal. Prints a per-drone "
            "table, collisions (drone-drone: centres closer than 2 r; drone-obstacle: exact clearance to the "
            "ground-truth splat ellipsoids below r), the minimum inter-drone distance, the coverage ratio (peaks "
            "detected within --sense m) and the task time; writes DIR/coverage.png and DIR/swarm.json. Exit code 1 "
            "on any collision."
        ),
    )
    p.add_argument("out", metavar="DIR", help="build folder with polytopes.h and manifest.json (from `polycc build`)")
    p.add_argument("--drones", type=number(int, 1, 16), default=4, metavar="N",
                   help="number of drones, 1..16 (the app's neighbour table holds 16) (default: %(default)s)")
    add_coverage_options(p)
    p.add_argument("--t-max", type=number(float, 0.0, 3600.0, lo_open=True, unit="s"), default=60.0, metavar="S",
                   help="simulated time limit, s (default: %(default)s)")
    p.add_argument("--vmax", type=number(float, 0.0, 5.0, lo_open=True, unit="m/s"), default=0.5, metavar="V",
                   help="each app's polycc.vmax, m/s (default: %(default)s)")
    p.add_argument("--swarm-v", type=number(float, 0.0, 100.0, unit="m/s"), default=1.0, metavar="V",
                   help="polycc.swarmV: the neighbours' speed bound used by the ageing buffer, m/s (default: "
                        "%(default)s)")
    p.add_argument("--rate-hz", type=number(int, 10, 1000, unit="Hz"), default=500, metavar="HZ",
                   help="requested app loop rate, Hz (default: %(default)s)")
    p.add_argument("--bcast-hz", type=number(int, 1, 200, unit="Hz"), default=20, metavar="HZ",
                   help="neighbour report rate per drone, Hz (default: %(default)s)")
    p.add_argument("--latency-ms", type=number(int, 0, 400, unit="ms"), default=10, metavar="MS",
                   help="report delivery latency, ms (stated in the report's age) (default: %(default)s)")
    p.add_argument("--dynamics", choices=("integrator", "crazyflie", "quadrotor"), default="integrator",
                   help="vehicle model of every drone (as `polycc sim`) (default: %(default)s)")
    p.add_argument("--scene", metavar="SCENE",
                   help="the splat scene as ground truth; default: the path stored in DIR/manifest.json")
    p.add_argument("--plot", metavar="FILE.png", help="coverage plot (default: DIR/coverage.png)")
    p.add_argument("--firmware", metavar="FWDIR",
                   help="fly N REAL Crazyflie firmwares instead: FWDIR is the CrazySim SITL tree or its .tar.xz (as "
                        "`polycc sim --firmware`). Builds one cf2 with the app and DIR/polytopes.h (cached), runs N "
                        "SITL instances (each starting on the floor below a free takeoff column) and flies them with "
                        "real cflib exactly as `polycc swarm-fly` flies real drones: high-level takeoff to --takeoff, "
                        "neighbours relayed as --relay says, the coverage controllers on the ground, HL landing. "
                        "Slower than real time with several instances on few cores; --dynamics does not apply")
    p.add_argument("--takeoff", type=number(float, 0.3, 3.0, unit="m"), default=0.9, metavar="Z",
                   help="with --firmware: the common takeoff height, m (default: %(default)s)")
    add_relay_option(p, "with --firmware: ")
    add_scene_options(p, from_dir=True)
    p.set_defaults(func=run)


def add_relay_option(p, prefix: str = "", default: str = "p2p") -> None:
    p.add_argument("--relay", choices=("p2p", "ground"), default=None,
                   help=prefix + "how each drone learns its neighbours' positions: p2p (the apps broadcast their "
                        "own estimates with the radio's peer-to-peer broadcast, every 1/--bcast-hz s; the drones "
                        "must share one radio channel) or ground (this process relays every drone's logged position "
                        f"to the others over cflib's links) (default: {default})")


def add_coverage_options(p) -> None:
    """The coverage task's options, shared by `swarm-sim` and `swarm-fly`."""
    t = p.add_mutually_exclusive_group()
    t.add_argument("--targets", metavar="FILE.json",
                   help='targets of interest: {"targets": [{"x": m, "y": m, "z": m, "sigma": m, "weight": w}, ...]}')
    t.add_argument("--random-targets", type=number(int, 1, 64), default=None, metavar="K",
                   help="K random peaks at free points >= 1 m apart, sigma 0.4 m (default when --targets is absent: 3)")
    p.add_argument("--controller", choices=("guided", "lloyd", "repulsive"), default="guided",
                   help="nominal controller: guided (CVT with the navigation function, seed 003), lloyd (plain Lloyd "
                        "with BVC, no guided map) or repulsive (attraction + neighbour repulsion) (default: "
                        "%(default)s)")
    p.add_argument("--seed", type=int, default=0, metavar="S", help="random starts and targets (default: %(default)s)")
    p.add_argument("--radius", type=number(float, 0.0, 1.0, unit="m"), default=0.1, metavar="R",
                   help="agent radius, m: each app's polycc.radius and the physical radius (default: %(default)s)")
    p.add_argument("--sense", type=number(float, 0.0, 10.0, lo_open=True, unit="m"), default=0.5, metavar="M",
                   help="a peak is detected when a drone comes this close, m (default: %(default)s)")
    p.add_argument("--grid", type=number(float, 0.05, 1.0, unit="m"), default=0.15, metavar="G",
                   help="coverage grid spacing, m (certified free cells, polycc plan's grid) (default: %(default)s)")


def coverage_setup(args, out: Path):
    """(NavMap, CoverageMap, Targets, free-cell centres (M, 3) m, rng) for the build ``out`` and the coverage
    options."""
    from polycc.cli.console import console
    from polycc.plan.planner import NavMap
    from polycc.swarm.coverage import CoverageMap, load_targets
    from polycc.swarm.scenario import random_targets

    with console.status("certifying the free space on the coverage grid"):
        nav = NavMap.from_build(out, radius=args.radius, margin=0.05, spacing=args.grid)
    rng = np.random.default_rng(args.seed)
    centres = nav.grid.centres(np.argwhere(nav._free.astype(bool)))
    if len(centres) < 2:
        raise PolyccError(f"{out}: fewer than 2 certified free cells at --grid {args.grid:g} m; use a finer grid")
    targets = load_targets(args.targets) if args.targets else random_targets(centres, args.random_targets or 3, rng)
    return nav, CoverageMap(nav, targets), targets, centres, rng


def run(args) -> int:
    from rich.table import Table

    from polycc.cli.console import console, progress_bar
    from polycc.cli.sim import _scene_path
    from polycc.onboard.app import STATUS_NAMES
    from polycc.sim.clearance import Clearance
    from polycc.swarm.plot import plot_coverage
    from polycc.swarm.scenario import spread_points
    from polycc.swarm.sim import SwarmConfig, run_swarm

    out = Path(args.out)
    header = out / "polytopes.h"
    if not header.is_file():
        raise PolyccError(f"{header}: not found; run `polycc build SCENE -o {out}` first")
    t0 = time.perf_counter()
    scene_path = _scene_path(args, out)
    scene = load_scene_from_args(scene_path, args)
    nav, cmap, targets, centres, rng = coverage_setup(args, out)
    if args.firmware:
        from polycc.swarm.firmware import column_starts

        starts = column_starts(cmap, args.drones, args.takeoff, 0.8, rng)
    else:
        starts = spread_points(centres, args.drones, 0.6, rng)
    cfg = SwarmConfig(rate_hz=args.rate_hz, vmax=args.vmax, radius=args.radius, swarm_v=args.swarm_v,
                      bcast_ms=max(1, round(1000 / args.bcast_hz)), latency_ms=args.latency_ms, sense_m=args.sense,
                      t_max_s=args.t_max, dynamics=args.dynamics, controller=args.controller)
    facts = None
    if args.relay and not args.firmware:
        raise PolyccError("--relay applies to --firmware only: the fast simulator hands each drone's broadcast to "
                          "the others' apps itself (--bcast-hz, --latency-ms)")
    if args.firmware:
        from polycc.swarm.firmware import run_swarm_firmware

        console.print(f"flying {args.drones} real-firmware SITL drones ({args.controller}) with cflib; "
                      f"task limit {args.t_max:g} s simulated", soft_wrap=True)
        res, facts = run_swarm_firmware(args.firmware, header, cmap, starts, targets, cfg,
                                        Clearance(scene.ellipsoids), takeoff=args.takeoff,
                                        say=lambda m: console.print(m, soft_wrap=True), relay=args.relay or "p2p")
    else:
        with console.status("building the app for this machine"):
            from polycc.sim.app_ffi import load

            load(header)
        with progress_bar(f"flying {args.drones} drones ({args.controller}, simulated s)", int(args.t_max)) as update:
            res = run_swarm(header, cmap, starts, targets, cfg, Clearance(scene.ellipsoids),
                            progress=lambda s: update(int(s)))

    dyn = "real firmware" if args.firmware else args.dynamics
    table = Table(title=f"polycc swarm-sim: {args.drones} drones, {args.controller}, {dyn}, vmax "
                        f"{args.vmax:g} m/s, r = {args.radius:g} m",
                  header_style="bold", caption="positions in m; nearest = min distance to another drone's centre "
                                               "(>= 2 r); clear = min distance to the splat ellipsoids minus r; "
                                               "hold = app ticks not in status ok")
    for h in ("drone", "start", "end", "path m", "nearest m", "clear m", "obst coll", "peaks", "hold", "statuses"):
        table.add_column(h, justify="right", overflow="fold")
    for i in range(res.n):
        st = res.statuses[i]
        hold = sum(v for k, v in st.items() if k != 1)
        table.add_row(str(i), ",".join(f"{v:.1f}" for v in res.starts[i]),
                      ",".join(f"{v:.1f}" for v in res.positions[i][-1]), f"{res.path_m[i]:.2f}",
                      f"{res.nearest_m[i]:.3f}" if math.isfinite(res.nearest_m[i]) else "-",
                      f"{res.min_clearance_m[i]:.3f}" if math.isfinite(res.min_clearance_m[i]) else "-",
                      str(res.obstacle_collisions[i]),
                      str(int(np.sum(res.detected_by == i))), str(hold),
                      ", ".join(f"{STATUS_NAMES.get(k, k)} {v}" for k, v in sorted(st.items())))
    console.print(table)
    dd = res.pair_collisions
    do = sum(1 for c in res.obstacle_collisions if c > 0)
    plot = Path(args.plot) if args.plot else out / "coverage.png"
    plot_coverage(plot, cmap, res, f"polycc swarm-sim: {args.drones} drones ({args.controller}), coverage "
                                   f"{res.coverage:.2f}, {Path(scene_path).name}")
    summary = {
        "drones": args.drones, "controller": args.controller, "dynamics": args.dynamics, "seed": args.seed,
        "vmax": args.vmax, "radius": args.radius, "swarm_v": args.swarm_v, "bcast_hz": args.bcast_hz,
        "latency_ms": args.latency_ms, "collisions": dd + do, "collisions_drone_drone": dd,
        "collisions_drone_obstacle": do, "min_inter_drone_m": res.min_pair_m if math.isfinite(res.min_pair_m) else None,
        "coverage_ratio": res.coverage, "task_time_s": None if math.isnan(res.task_time_s) else res.task_time_s,
        "sim_time_s": res.time_s, "targets": targets.to_json()["targets"],
        "detected_at_s": [None if math.isnan(v) else float(v) for v in res.detected_at],
        "drones_detail": [{"start": res.starts[i].tolist(), "end": res.positions[i][-1].tolist(),
                           "path_m": res.path_m[i], "nearest_m": float(res.nearest_m[i]),
                           "min_clearance_m": res.min_clearance_m[i] if math.isfinite(res.min_clearance_m[i])
                           else None,
                           "obstacle_collisions": res.obstacle_collisions[i],
                           "statuses": {STATUS_NAMES.get(k, str(k)): v for k, v in res.statuses[i].items()}}
                          for i in range(res.n)],
        "wall_us_per_drone_tick": res.step_us,
    }
    if facts is not None:
        summary["firmware"] = {k: facts[k] for k in ("outcome", "notes", "relay", "relayed", "p2p", "air", "build_s",
                                                     "rtf", "wall_s", "landed", "sitl_reruns")}
        summary["dynamics"] = "real firmware SITL (rigid body)"
    (out / "swarm.json").write_text(json.dumps(summary, indent=1) + "\n")
    mind = f"{res.min_pair_m:.3f} m (bound 2 r = {2 * args.radius:.3f} m)" if math.isfinite(res.min_pair_m) else "-"
    task = f"{res.task_time_s:.2f} s" if math.isfinite(res.task_time_s) else f"not all found in {res.time_s:.1f} s"
    console.print(f"collisions: {dd + do} (drone-drone {dd}, drone-obstacle {do})", soft_wrap=True)
    console.print(f"min inter-drone distance: {mind}", soft_wrap=True)
    console.print(f"coverage ratio: {res.coverage:.2f} ({int(np.isfinite(res.detected_at).sum())} of "
                  f"{len(targets.mu)} peaks), task time: {task}", soft_wrap=True)
    console.print(f"coverage plot: {plot}; summary: {out / 'swarm.json'} ({time.perf_counter() - t0:.1f} s)",
                  soft_wrap=True)
    if facts is not None:
        rtf = ", ".join(f"{r:.2f}" for r in facts["rtf"] if r is not None)
        if facts["relay"] == "p2p":
            p2p = facts["p2p"]
            heard = (f"P2P: {sum(d.get('p2pTx') or 0 for d in p2p)} broadcasts, "
                     f"{sum(d.get('p2pRx') or 0 for d in p2p)} records heard, "
                     f"{sum(d.get('p2pDrop') or 0 for d in p2p)} refused, neighbours known "
                     + "/".join(str(d.get("nNbr")) for d in p2p))
        else:
            heard = f"{facts['relayed']} neighbour records relayed by the ground"
        console.print(f"real firmware: {facts['outcome']}, {'landed' if facts['landed'] else 'NOT landed'}; "
                      f"{heard}; RTF {rtf}; {facts['wall_s']:.0f} s wall"
                      + (f"; flown twice, the first attempt failed: {facts['sitl_reruns'][0]}"
                         if facts["sitl_reruns"] else ""), soft_wrap=True)
        if facts["outcome"] not in ("covered", "timeout") or not facts["landed"]:
            return 1
    return 1 if dd + do else 0
