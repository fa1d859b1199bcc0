"""`polycc sim-device OUT (--udp HOST:PORT | --serial)`: the SITL app as a Crazyflie cflib can connect to."""

from __future__ import annotations

import sys
import time
from pathlib import Path

from polycc.cli.argtypes import add_point_option, number
from polycc.cli.sim import _sidecar_flight, build_scene
from polycc.errors import PolyccError
from polycc.link.udp import parse_host_port

HELP = "run the Crazyflie app (host build) in real time as a simulated Crazyflie for cflib (udp:// or serial://)"
DEFAULT_UDP = "127.0.0.1:19850"


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "sim-device",
        help=HELP,
        description=(
            "Builds firmware_app/src/polycc_app.c for this machine against OUT/polytopes.h (as `polycc sim` does), "
            "runs it in real time on a simulated vehicle and serves it as a Crazyflie that Bitcraze's cflib "
            "connects to: param and log TOCs from the app's own PARAM_/LOG_ tables (plus stateEstimate.* and "
            "firmware.polyccVersion), params that write the app's variables, log blocks at the requested period, "
            "the standard groups cflib and cfclient use (kalman, stabilizer.controller, commander, supervisor, "
            "pm, deck), and a host "
            "model of the firmware's flight control: the commander's priorities, the high-level commander "
            "(takeoff/go_to/land trajectories), the supervisor's watchdog and motors-off cases, as on a Crazyflie "
            "(a stop setpoint in the air drops it). The vehicle starts on the floor with the motors off below "
            "--start (or hovering there with --airborne). Prints the URI to use and runs until Ctrl-C. Drive it "
            "with your own cflib script or `polycc fly --uri URI --takeoff 0.9 --goal X,Y,Z --land`."
        ),
    )
    p.add_argument("out", metavar="OUT", help="build folder with polytopes.h (from `polycc build`)")
    p.add_argument("--udp", metavar="HOST:PORT", nargs="?", const=DEFAULT_UDP,
                   help=f"serve udp://HOST:PORT, one CRTP packet per datagram (cflib >= 0.1.32); without a value "
                        f"{DEFAULT_UDP}; port 0 picks a free one")
    p.add_argument("--serial", action="store_true",
                   help="serve serial://ttyUSB-polyccN on a new pseudo-terminal with cflib's CPX framing; the "
                        "/dev/ttyUSB-polyccN symlink that cflib's port lookup needs requires root")
    p.add_argument("--scene", metavar="SCENE",
                   help="the splat scene; only its sidecar .json (as `polycc demo-scene` writes) is read, for the "
                        "default --start and the goal suggested for `polycc fly` (default: the scene in "
                        "OUT/manifest.json)")
    add_point_option(p, "--start",
                   help="initial position, m; the vehicle rests on the floor (--floor-z) below it, or hovers there "
                        "with --airborne (default: the scene sidecar's 'start', else 0,0,0)")
    p.add_argument("--airborne", action="store_true",
                   help="start hovering at --start under the high-level commander, as after a takeoff "
                        "(default: on the floor, motors off)")
    p.add_argument("--floor-z", type=number(float, -1000.0, 1000.0, unit="m"), default=0.0, metavar="Z",
                   help="height of the floor the vehicle stands and lands on, m (default: %(default)s)")
    p.add_argument("--dynamics", choices=("crazyflie", "integrator", "quadrotor"), default=None,
                   help="vehicle model: Crazyflie 2.1-like velocity tracking, the single integrator, or the full "
                        "rigid-body quadrotor (see `polycc sim --help`) (default: crazyflie; not with --firmware)")
    p.add_argument("--firmware", metavar="FWDIR",
                   help="serve the REAL Crazyflie firmware instead of the host model: FWDIR is the CrazySim SITL "
                        "tree (llanesc/crazyflie-firmware sitl-release) or its .tar.xz. Builds a native cf2 with "
                        "the app and OUT/polytopes.h (cached), runs it lock-stepped with a rigid-body physics model "
                        "and relays CRTP on --udp: the firmware's full TOC (kalman, supervisor, high-level "
                        "commander, ...) for cflib, MotionCommander, PositionHlCommander and cfclient. UDP only; "
                        "the vehicle starts on the floor below --start")
    p.add_argument("--firmware-logs", metavar="DIR",
                   help="with --firmware: keep cf2.log, bridge.err and trajectory.csv (100 Hz truth) in DIR "
                        "(default: a temporary folder, removed on a clean stop)")
    p.add_argument("--delay-ms", type=number(float, 0.0, 1000.0, unit="ms"), default=None, metavar="MS",
                   help="estimator delay, ms (default: the model's own, 20 for crazyflie and quadrotor)")
    p.add_argument("--rate-hz", type=number(int, 10, 1000, unit="Hz"), default=None, metavar="HZ",
                   help="initial app loop rate (param polycc.rateHz, 10..1000 Hz; a client may change it) "
                        "(default: the app's, 500)")
    p.add_argument("--estimate-noise", type=number(float, 0.0, 1.0, unit="m"), default=0.001, metavar="M",
                   help="standard deviation of white noise on the position estimate, m; 0 makes a vehicle at rest "
                        "look like a stale estimate to the app (status 4) (default: %(default)s)")
    p.add_argument("--duration", type=number(float, 0.0, 1e7, lo_open=True, unit="s"), default=None, metavar="S",
                   help="stop after S seconds (default: run until Ctrl-C)")
    p.set_defaults(func=run)


def _start_goal(args, out: Path):
    """--start (else the scene sidecar's start, else the origin) and the sidecar's goal (or None)."""
    start, goal = args.start, None
    scene, _, _ = build_scene(args, out) if (out / "manifest.json").is_file() else (args.scene, None, None)
    side = _sidecar_flight(scene) if scene else None
    if side is not None:
        goal = side[1]
        if start is None:
            start = side[0]
    if start is None:
        start = (0.0, 0.0, 0.0)
    return start, goal


def _run_firmware(args, out: Path, header: Path, udp) -> int:
    """The real firmware's SITL as the device (polycc.sim.firmware)."""
    from polycc.cli.console import console
    from polycc.sim.firmware.build import build_cf2
    from polycc.sim.firmware.sitl import FirmwareSitl

    for opt, bad in (("--serial", args.serial), ("--airborne", args.airborne), ("--dynamics", args.dynamics),
                     ("--delay-ms", args.delay_ms), ("--rate-hz", args.rate_hz),
                     ("--floor-z", args.floor_z != 0.0), ("--estimate-noise", args.estimate_noise != 0.001)):
        if bad:
            raise PolyccError(f"{opt} does not apply with --firmware: the real firmware runs its own estimator and "
                              "controller on the rigid-body model, from the floor at z = 0, over UDP (set polycc.* "
                              "params from your client); drop the option")
    if udp is None:
        raise PolyccError(f"--firmware serves UDP only: give --udp HOST:PORT (e.g. --udp {DEFAULT_UDP})")
    start, goal = _start_goal(args, out)

    def say(msg: str) -> None:
        console.print(f"firmware: {msg}", soft_wrap=True, highlight=False)

    fw = build_cf2(args.firmware, header, log=say)
    say(f"cf2 {'from the cache' if fw.cached else f'built in {fw.seconds:.0f} s'}: {fw.cf2}")
    x, y = float(start[0]), float(start[1])
    sitl = FirmwareSitl(fw, start=(x, y, 0.0), cflib_host=udp[0], cflib_port=udp[1], run_dir=args.firmware_logs)
    try:
        with sitl:
            say(f"booted in {sitl.t_ready:.1f} s: the real Crazyflie firmware (CrazySim SITL, Kalman + PID) with "
                f"{out}/polytopes.h, on the floor at {x:g},{y:g},0 m, motors off")
            console.print(f"URI: {sitl.uri}", soft_wrap=True)
            g = ",".join(f"{v:g}" for v in goal) if goal is not None else "X,Y,Z"
            console.print(f"try: polycc fly --uri {sitl.uri} --takeoff 0.9 --goal {g} --land    (Ctrl-C stops the "
                          "device)", soft_wrap=True)
            sys.stdout.flush()  # the URI must reach a pipe at once (scripts wait for it)
            t_end = None if args.duration is None else time.monotonic() + args.duration
            last = time.monotonic()
            while t_end is None or time.monotonic() < t_end:
                time.sleep(0.2)
                sitl.check_alive()
                if time.monotonic() - last >= 10.0:
                    last = time.monotonic()
                    s, st = sitl.state(), sitl.stats()
                    p = s["pos"]
                    console.print(f"t {s['t']:.1f} s simulated (RTF {st.get('rtf') or 0:.2f}), position "
                                  f"{p[0]:.2f},{p[1]:.2f},{p[2]:.2f} m, motors {'on' if s['motors_on'] else 'off'}, "
                                  f"cflib packets {st.get('cflib_to_fw', 0)} in / {st.get('fw_to_cflib', 0)} out",
                                  soft_wrap=True, highlight=False)
            st = sitl.stats()
    except KeyboardInterrupt:
        st = None
    console.print(f"stopped: {st['sim_t']:.1f} s simulated in {st['wall_t']:.1f} s (RTF {st.get('rtf') or 0:.2f}); "
                  f"ports freed" if st else "stopped (Ctrl-C); processes ended, ports freed", soft_wrap=True)
    return 0


def run(args) -> int:
    from polycc.cli.console import console
    from polycc.sim.crtp_device import CrtpDevice
    from polycc.sim.device_server import SerialDeviceServer, UdpDeviceServer
    from polycc.sim.sitl_device import SitlDeviceModel

    out = Path(args.out)
    header = out / "polytopes.h"
    if not header.is_file():
        raise PolyccError(f"{header}: not found; run `polycc build SCENE -o {out}` first")
    if not args.udp and not args.serial:
        raise PolyccError(f"give --udp HOST:PORT (e.g. --udp {DEFAULT_UDP}) and/or --serial")
    udp = parse_host_port(args.udp) if args.udp else None
    if args.firmware:
        return _run_firmware(args, out, header, udp)
    if args.firmware_logs:
        raise PolyccError("--firmware-logs needs --firmware FWDIR")
    if args.dynamics is None:
        args.dynamics = "crazyflie"

    start, goal = _start_goal(args, out)

    with console.status("building the app for this machine"):
        if not args.airborne:
            start = (float(start[0]), float(start[1]), args.floor_z)
        model = SitlDeviceModel(header, start=start, dynamics=args.dynamics,
                                delay_s=None if args.delay_ms is None else args.delay_ms * 1e-3,
                                rate_hz=args.rate_hz, estimate_noise_m=args.estimate_noise,
                                on_floor=not args.airborne, floor_z=args.floor_z)
    servers = []
    try:
        if udp is not None:  # one CrtpDevice per transport: each client has its own log blocks
            servers.append(UdpDeviceServer(CrtpDevice(model), udp[0], udp[1]))
        if args.serial:
            servers.append(SerialDeviceServer(CrtpDevice(model)))
        model.start()
        for s in servers:
            s.start()
        x, y, z = (float(v) for v in start)
        where = "hovering at" if args.airborne else "on the floor at"
        console.print(f"simulated Crazyflie: {out}/polytopes.h, {args.dynamics} dynamics, {where} {x:g},{y:g},{z:g} m",
                      soft_wrap=True)
        for s in servers:
            if isinstance(s, UdpDeviceServer):
                console.print(f"URI: {s.uri}", soft_wrap=True)
            elif s.link_path is not None:
                console.print(f"URI: {s.uri}  (pty {s.pty_path}; cflib.crtp.init_drivers(enable_serial_driver=True))",
                              soft_wrap=True)
            else:
                console.print(f"serial pty {s.pty_path}: no /dev/ttyUSB-polyccN symlink (not root), so cflib's "
                              f"serial://NAME lookup will not find it; use --udp instead", soft_wrap=True)
        uri = next((s.uri for s in servers if isinstance(s, UdpDeviceServer)), None) or \
            next((s.uri for s in servers if s.link_path is not None), "URI")
        g = ",".join(f"{v:g}" for v in goal) if goal is not None else "X,Y,Z"
        takeoff = "" if args.airborne else "--takeoff 0.9 "
        console.print(f"try: polycc fly --uri {uri} {takeoff}--goal {g} --land    (Ctrl-C stops the device)",
                      soft_wrap=True)
        sys.stdout.flush()  # the URI must reach a pipe at once (scripts wait for it)
        t_end = None if args.duration is None else time.monotonic() + args.duration
        last = 0.0
        while t_end is None or time.monotonic() < t_end:
            time.sleep(0.2)
            if time.monotonic() - last >= 10.0:
                last = time.monotonic()
                with model.lock:
                    console.print(model.summary(), soft_wrap=True)
    except KeyboardInterrupt:
        pass
    finally:
        for s in servers:
            s.stop()
        model.stop()
    stats = [s.device.stats for s in servers]
    console.print(f"stopped: {model.steps} app ticks, packets rx {sum(st.rx for st in stats)} tx "
                  f"{sum(st.tx for st in stats)}, malformed {sum(st.malformed for st in stats)}",
                  soft_wrap=True)
    return 0
