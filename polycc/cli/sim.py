"""`polycc sim OUT --scene SCENE`: fly the real Crazyflie app (host build) in the scene."""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from polycc.cli.argtypes import add_point_option, number
from polycc.cli.plan import add_plan_options
from polycc.cli.scene_args import (
    add_scene_options,
    check_scene_file,
    load_scene_from_args,
    recorded_settings,
    resolve_scene_settings,
)
from polycc.errors import PolyccError
from polycc.sim.firmware.flights import SHIELD_HZ, STARVED_SHARE

HELP = "fly the Crazyflie app (same C code, host build) through the scene and check clearance"


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "sim",
        help=HELP,
        description=(
            "Software-in-the-loop flight: compiles firmware_app/src/polycc_app.c and the kernel for this "
            "machine against firmware API shims, with OUT/polytopes.h, and steps the app tick by tick on a "
            "simulated 1 kHz FreeRTOS clock. The vehicle model flies the app's velocity setpoints. Reports, "
            "per trial: success (within 5 cm of the goal), time, path length, minimum clearance to the "
            "ground-truth splat ellipsoids of SCENE (exact distance minus --radius), collisions (must be 0) "
            "and the largest evalUs of the cycle model. Writes OUT/trajectories.png, OUT/sim.json and "
            "OUT/trajectories.npz (true positions per trial, m, one array per trial after every app period). "
            "The scene and its options (transform, sigma, crop, ...) are the ones OUT was built with. "
            "Exit code 1 if any trial collides."
        ),
    )
    p.add_argument("out", metavar="OUT", help="build folder with polytopes.h and manifest.json (from `polycc build`)")
    p.add_argument("--scene", metavar="SCENE",
                   help="the splat scene (.ply/.splat) as ground truth; default: the path stored in OUT/manifest.json")
    add_point_option(p, "--start",
                     help="start position, m (default: the scene's sidecar .json 'start', as `polycc demo-scene` "
                          "writes)")
    add_point_option(p, "--goal", help="goal position, m (default: the scene's sidecar .json 'goal')")
    p.add_argument("--dynamics", choices=("integrator", "crazyflie", "quadrotor"), default=None,
                   help="vehicle model: the paper's single integrator; the Crazyflie 2.1-like velocity tracking model "
                        "(tilt/thrust limits, attitude lag, 20 ms estimator delay); or the full rigid-body quadrotor "
                        "under a Crazyflie-like PID cascade (slowest) (default: integrator; not with --firmware)")
    p.add_argument("--firmware", metavar="FWDIR",
                   help="fly the REAL Crazyflie firmware instead of the host shims: FWDIR is the CrazySim SITL tree "
                        "(llanesc/crazyflie-firmware sitl-release) or its .tar.xz. Builds a native cf2 with the app "
                        "and OUT/polytopes.h (cached by content hash), runs it lock-stepped with a rigid-body "
                        "physics model (Kalman estimator, PID controller) and flies each trial with real cflib: "
                        "from the floor, high-level takeoff to the start, the app to the goal, high-level landing. "
                        "About real time or slower (the README has the speed); progress lines per trial")
    p.add_argument("--firmware-logs", metavar="DIR",
                   help="with --firmware: keep each trial's cf2.log, bridge.err and trajectory.csv (100 Hz truth) in "
                        "DIR/trialN (default: not kept, except after an error)")
    p.add_argument("--trials", type=number(int, 1, 100_000), default=1, metavar="N",
                   help="flights from --start to --goal; trials after the first start up to --jitter m away (default: "
                        "%(default)s)")
    p.add_argument("--seed", type=int, default=0, metavar="S", help="random seed for start jitter and random pairs "
                                                                    "(default: %(default)s)")
    p.add_argument("--jitter", type=number(float, 0.0, 10.0, unit="m"), default=0.05, metavar="M",
                   help="largest start offset (m) of trials 2..N, per axis (default: %(default)s)")
    p.add_argument("--random-pairs", type=number(int, 0, 100_000), default=0, metavar="N",
                   help="instead of --start/--goal: the paper's protocol, N random start/goal pairs in free space "
                        "(psi >= 0.05 m) inside the splats' 0.5-99.5 percentile box, z >= 0.15 m; 0 = off (default: "
                        "%(default)s)")
    p.add_argument("--min-distance", type=number(float, 0.0, 1000.0, unit="m"), default=2.0, metavar="D",
                   help="random pairs: smallest start-goal distance, m (default: %(default)s)")
    p.add_argument("--rate-hz", type=number(int, 10, 1000, unit="Hz"), default=500, metavar="HZ",
                   help="app loop rate (param polycc.rateHz, 10..1000); the paper's simulations used 100 (dt = 0.01 s) "
                        "(default: %(default)s)")
    p.add_argument("--vmax", type=number(float, 0.0, 10.0, lo_open=True, unit="m/s"), default=0.5, metavar="V",
                   help="speed limit (param polycc.vmax), m/s (default: %(default)s)")
    p.add_argument("--beta", type=number(float, 0.0, 1e6, lo_open=True, unit="1/s"), default=1.0, metavar="B",
                   help="CBF gain (param polycc.beta), 1/s (default: %(default)s)")
    p.add_argument("--clf-gain", type=number(float, 0.0, 1e6, unit="1/s"), default=2.0, metavar="C",
                   help="CLF decay rate (param polycc.clfGain), 1/s: u_nom = -(C/2)(x - goal) (default: %(default)s)")
    p.add_argument("--radius", type=number(float, 0.0, 10.0, unit="m"), default=0.1, metavar="R",
                   help="agent radius (param polycc.radius), m; clearance is distance minus R (default: %(default)s)")
    p.add_argument("--delay-ms", type=number(float, 0.0, 1000.0, unit="ms"), default=None, metavar="MS",
                   help="estimator delay, ms (default: 0 for integrator, 20 for crazyflie and quadrotor)")
    p.add_argument("--t-max", type=number(float, 0.0, 1e5, lo_open=True, unit="s"), default=None, metavar="S",
                   help="time limit per flight, s (default: 2 * distance / vmax + 10)")
    p.add_argument("--plot", metavar="FILE.png", help="trajectory plot (default: OUT/trajectories.png)")
    p.add_argument("--shield", action="store_true",
                   help="fly the shield too: stabilizer.controller = out-of-tree, polyccShield.enable = 1 (every "
                        "setpoint of the app through the velocity-aware backup CBF, docs/barrier.md section 8; "
                        "polyccShield.radius = --radius)")
    p.add_argument("--plan", action="store_true",
                   help="plan each flight through the certified free space first (as `polycc plan`, at --radius) and "
                        "fly its waypoints: the app's goal switches to the next waypoint within --margin of the "
                        "current one. Pairs without a path are reported separately and not flown")
    add_plan_options(p, with_radius=False)
    add_scene_options(p, from_dir=True)
    p.set_defaults(func=run)


def build_scene(args, out: Path) -> tuple[str | None, object, dict]:
    """(scene path, recorded scene settings, recorded scene) of the build folder ``out``: the scene
    is ``--scene`` if given (it must be the file the build was made from) or the manifest's."""
    recorded, rec_scene = recorded_settings(out)
    if args.scene:
        check_scene_file(args.scene, rec_scene, str(out))
        return args.scene, recorded, rec_scene
    path = rec_scene.get("path")
    if path and not Path(path).is_file():
        raise PolyccError(f"{out}: the scene it was built from, {path}, is not there any more; pass --scene SCENE "
                          "(the same file, moved)")
    return path, recorded, rec_scene


def _scene_path(args, out: Path) -> str:
    path, recorded, _ = build_scene(args, out)
    if not path:
        raise PolyccError(f"{out}: no --scene given and manifest.json names no scene; pass --scene SCENE")
    resolve_scene_settings(args, recorded, str(out))
    return path


def _sidecar_flight(scene_path: str) -> tuple[np.ndarray, np.ndarray] | None:
    side = Path(scene_path).with_suffix(".json")
    if side.is_file():
        try:
            d = json.loads(side.read_text())
            return np.asarray(d["start"], float), np.asarray(d["goal"], float)
        except (ValueError, KeyError, TypeError):
            return None
    return None


def _fly_firmware(args, header: Path, sim, scene, cfg, pairs, plans, flown, out: Path) -> list:
    """The trials flown by the real firmware (polycc.sim.firmware.flights), with progress lines."""
    from polycc.cli.console import console
    from polycc.sim.firmware.flights import FirmwareSimulator

    for i in flown:
        z = float(pairs[i][0][2])
        if z < 0.2:
            raise PolyccError(f"start z {z:g} m: the firmware flight takes off from the floor to the start, so it "
                              "must be at least 0.2 m up")
    prefix = ["firmware"]

    def say(msg: str) -> None:
        console.print(f"{prefix[0]}: {msg}", soft_wrap=True, highlight=False)

    fw = FirmwareSimulator(header, args.firmware, sim.packed, sim.kappa, scene.ellipsoids,
                           run_root=args.firmware_logs, say=say)
    say(f"cf2 {'from the cache' if fw.build.cached else f'built in {fw.build.seconds:.0f} s'}: {fw.build.cf2}")
    trials = []
    for n, i in enumerate(flown):
        s, g = pairs[i]
        prefix[0] = f"trial {n + 1}/{len(flown)}"
        t = fw.fly(s, g, cfg, waypoints=None if plans[i] is None else plans[i].waypoints)
        e = t.extra or {}
        say(f"{'ok' if t.success else t.outcome}, {t.time_s:.1f} s simulated, RTF {e.get('rtf') or 0:.2f}, "
            f"{'landed' if e.get('landed') else 'NOT landed'} (touchdown {e.get('touchdown_ms', 0):.2f} m/s)"
            + (f", flown again ({'; '.join(e.get('sitl_rerun_reasons') or ['a SITL hang'])})"
               if e.get("sitl_reruns") else "")
            + (f", logs {e['run_dir']}" if e.get("run_dir") else ""))
        trials.append(t)
    return trials


def run(args) -> int:
    from rich.table import Table

    from polycc.cli.console import console, progress_bar
    from polycc.onboard.layout import stored_vertices
    from polycc.report.flights import plot_trajectories
    from polycc.sim.sitl import FlightConfig, Simulator, random_pairs, sampling_box

    out = Path(args.out)
    header = out / "polytopes.h"
    if not header.is_file():
        raise PolyccError(f"{header}: not found; run `polycc build SCENE -o {out}` first")
    if args.firmware:
        for opt, val in (("--dynamics", args.dynamics), ("--delay-ms", args.delay_ms)):
            if val is not None:
                raise PolyccError(f"{opt} does not apply with --firmware: the real firmware flies the rigid-body model "
                                  "of polycc.sim.firmware.physics through its own Kalman estimator; drop the option")
        args.dynamics = "firmware"
    elif args.firmware_logs:
        raise PolyccError("--firmware-logs needs --firmware FWDIR")
    elif args.dynamics is None:
        args.dynamics = "integrator"
    scene_path = _scene_path(args, out)
    scene = load_scene_from_args(scene_path, args)
    t0 = time.perf_counter()
    with console.status("building the app for this machine"):
        sim = Simulator(header, scene.ellipsoids)
    cfg = FlightConfig(rate_hz=args.rate_hz, vmax=args.vmax, beta=args.beta, clf_gain=args.clf_gain,
                       radius=args.radius, t_max_s=args.t_max, shield=args.shield)
    delay = None if args.delay_ms is None else args.delay_ms * 1e-3

    if args.random_pairs:
        lo, hi = sampling_box(scene.ellipsoids)
        pairs = random_pairs(sim.packed, cfg.params(sim.kappa), lo, hi, args.random_pairs, args.min_distance, args.seed)
    else:
        start, goal = args.start, args.goal
        if start is None or goal is None:
            side = _sidecar_flight(scene_path)
            if side is None:
                raise PolyccError("give --start X,Y,Z and --goal X,Y,Z (m), or --random-pairs N")
            start = side[0] if start is None else start
            goal = side[1] if goal is None else goal
        rng = np.random.default_rng(args.seed)
        pairs = [(start + (rng.uniform(-args.jitter, args.jitter, 3) if i else 0.0), goal) for i in range(args.trials)]

    plans, no_path = [None] * len(pairs), {}
    if args.plan:
        from polycc.cli.plan import NoPath, nav_map
        from polycc.plan import NoPathError

        nav = nav_map(out, args, args.radius)
        cfg.switch_tol_m = args.margin
        with progress_bar("planning", len(pairs)) as update:
            for i, (s, g) in enumerate(pairs):
                try:
                    plans[i] = nav.plan(s, g)
                except NoPathError as exc:
                    if not args.random_pairs:
                        raise NoPath(f"no path ({exc.reason}): {exc}") from None
                    no_path[i] = exc
                update(i + 1)
    trials, flown = [], [i for i in range(len(pairs)) if i not in no_path]
    if args.firmware:
        trials = _fly_firmware(args, header, sim, scene, cfg, pairs, plans, flown, out)
    else:
        with progress_bar(f"flying ({args.dynamics})", len(flown)) as update:
            for n, i in enumerate(flown):
                s, g = pairs[i]
                trials.append(sim.fly(s, g, args.dynamics, cfg, delay_s=delay,
                                      waypoints=None if plans[i] is None else plans[i].waypoints))
                update(n + 1)

    title = "real firmware (SITL)" if args.firmware else args.dynamics
    table = Table(title=f"polycc sim: {title}, {args.rate_hz} Hz, vmax {args.vmax:g} m/s, r = {args.radius:g} "
                        "m",
                  header_style="bold", caption="start, goal in m; ok = within 5 cm of the goal; clear = min distance "
                                               "to the "
                  "splat ellipsoids minus r; ratio = path / straight line; evalUs = largest modelled kernel time")
    for h in ("#", "start", "goal", "result", "time s", "path m", "ratio", "clear m", "coll", "evalUs"):
        table.add_column(h, justify="right", overflow="fold", no_wrap=h not in ("start", "goal"))
    by_pair = dict(zip(flown, trials))
    for i, (s, g) in enumerate(pairs):
        xyz = (",".join(f"{v:.1f}" for v in s), ",".join(f"{v:.1f}" for v in g))
        if i in no_path:
            table.add_row(str(i + 1), *xyz, f"no path ({no_path[i].reason})", "", "", "", "", "", "")
            continue
        t = by_pair[i]
        table.add_row(str(i + 1), *xyz, "ok" if t.success else t.outcome, f"{t.time_s:.2f}", f"{t.path_length_m:.2f}",
                      f"{t.length_ratio:.3f}", f"{t.min_clearance_m:.4f}", str(t.collisions), str(t.max_eval_us))
    console.print(table)
    if not trials:
        raise PolyccError(f"none of the {len(pairs)} pairs has a certified path (e.g. {next(iter(no_path.values()))}); "
                          "lower --margin or use another --seed")
    plot = Path(args.plot) if args.plot else out / "trajectories.png"
    plot_trajectories(plot, trials, stored_vertices(sim.packed), scene.ellipsoids,
                      title=f"polycc sim ({args.dynamics}): {Path(scene_path).name}, n = {sim.packed.n_polys} "
                            "polytopes")
    n_ok = sum(t.success for t in trials)
    collisions = sum(t.collisions for t in trials)
    min_clear = min(t.min_clearance_m for t in trials)
    summary = {
        "dynamics": args.dynamics, "rate_hz": args.rate_hz, "vmax": args.vmax, "radius": args.radius,
        "trials": [{"start": t.start.tolist(), "goal": t.goal.tolist(), "success": t.success, "outcome": t.outcome,
                    "time_s": t.time_s, "path_length_m": t.path_length_m, "length_ratio": t.length_ratio,
                    "min_clearance_m": t.min_clearance_m, "collisions": t.collisions, "max_eval_us": t.max_eval_us,
                    **({"firmware": t.extra} if t.extra else {}),
                    **({} if plans[i] is None else {"plan": {
                        "waypoints": plans[i].waypoints.tolist(), "length_m": plans[i].length_m,
                        "waypoints_reached": t.reached}})}
                   for i, t in zip(flown, trials)],
        "success_rate": n_ok / len(trials), "collisions": collisions, "min_clearance_m": min_clear,
    }
    if args.shield:
        summary["shield"] = {k: int(sum(t.shield[k] for t in trials)) for k in trials[0].shield}
        flown_s = sum(t.time_s for t in trials)
        # counted from the switch-on (just before the flight) to the end: about SHIELD_HZ per flown second
        summary["shield"]["decisions_per_s"] = round(summary["shield"]["decisions"] / flown_s, 1) if flown_s else 0.0
    if args.plan:
        summary["plan"] = {"margin_m": args.margin, "grid_m": args.grid, "switch_tolerance_m": args.margin,
                           "no_path": [{"pair": i + 1, "start": pairs[i][0].tolist(), "goal": pairs[i][1].tolist(),
                                        "reason": e.reason, "message": str(e)} for i, e in no_path.items()]}
    (out / "sim.json").write_text(json.dumps(summary, indent=1) + "\n")
    np.savez_compressed(out / "trajectories.npz", **{f"trial{i + 1}": t.positions for i, t in enumerate(trials)},
                        starts=np.array([t.start for t in trials]), goals=np.array([t.goal for t in trials]))
    console.print(f"trajectories: {plot}", soft_wrap=True)
    if args.plan:
        reasons = sorted({e.reason for e in no_path.values()})
        console.print(f"planned: {len(pairs) - len(no_path)} of {len(pairs)} pairs have a certified path"
                      + (f"; no path for {len(no_path)} ({', '.join(reasons)}), not flown" if no_path else ""),
                      soft_wrap=True)
    console.print(f"summary: {len(trials)} trials, success {n_ok}/{len(trials)} ({100.0 * n_ok / len(trials):.0f}%), "
                  f"collisions: {collisions}, min clearance {min_clear:.4f} m, "
                  f"max evalUs {max(t.max_eval_us for t in trials)}, {time.perf_counter() - t0:.1f} s", soft_wrap=True)
    if args.shield:
        sh = summary["shield"]
        words = (("decisions", "decisions"), ("certified", "certified"), ("backups", "backups (braking)"),
                 ("infeasible", "infeasible"), ("manual", "manual ticks"))
        console.print("shield: " + ", ".join(f"{sh[k]} {w}" for k, w in words if k in sh)
                      + ("" if "certified" in sh else " (the real firmware logs no certified count)")
                      + f"; {sh['decisions_per_s']:.0f} decisions per flown second (it plans at {SHIELD_HZ:.0f} Hz)",
                      soft_wrap=True)
        if sh["decisions_per_s"] < STARVED_SHARE * SHIELD_HZ:
            console.print(f"[yellow]warning:[/] the shield decided only {sh['decisions_per_s']:.0f} times per "
                          f"second of its {SHIELD_HZ:.0f}: the app task did not get its CPU time, so these flights "
                          "are not what the M4 would fly (a starved simulator, or --rate-hz too high for the "
                          "scene); its late decisions were flown as brakes", soft_wrap=True)
    return 1 if collisions else 0
