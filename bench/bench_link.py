"""Benchmark: the cflib link to the simulated Crazyflie, over UDP and over a serial pty.

Targets: connection time to fully connected (TOCs downloaded and every param read) <= 1 s;
100 Hz logging of 6 floats for 60 s with zero lost log packets. The device runs in its own
process (as ``polycc sim-device`` will) and stamps each log packet with its scheduled time,
so a lost packet is a gap in the received timestamp sequence (each step must be exactly 10 ms).

    python bench/bench_link.py [--quick]      # --quick: 5 s of logging, 3 connections

The serial case needs root (to create the /dev symlink cflib's comports() lists); without it
the serial rows are skipped.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import logging
import math
import statistics
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import print_table, write_json  # noqa: E402

LOG_VARS = ("x", "y", "z", "vx", "vy", "vz")
PERIOD_MS = 10
CONNECT_TARGET_S = 1.0


def serve(kind: str) -> None:
    """Child process: serve a device with 6 float log variables until stdin closes."""
    from polycc.sim.crtp_device import CrtpDevice, DeviceModel, LogEntry, ParamEntry
    from polycc.sim.device_server import SerialDeviceServer, UdpDeviceServer

    goal = [0.0]
    logs = [LogEntry("stateEstimate", n, "float", lambda i=i: math.sin(time.monotonic() + i))
            for i, n in enumerate(LOG_VARS)]
    params = [ParamEntry("polycc", "goalX", "float", lambda: goal[0], lambda v: goal.__setitem__(0, v))]
    device = CrtpDevice(DeviceModel(params, logs))
    srv = UdpDeviceServer(device, port=0) if kind == "udp" else SerialDeviceServer(device)
    with srv:
        try:
            uri = srv.uri
        except Exception as e:  # no /dev symlink
            print(f"SKIP {e}", flush=True)
            return
        print(uri, flush=True)
        sys.stdin.read()
        stats = {"device": device.stats.as_dict(), "loop_errors": srv.loop_errors}
        if kind == "serial":
            stats["link"] = srv.link.stats.as_dict()
            stats["decoder"] = srv.link.decoder.stats.as_dict()
        else:
            stats["bad_datagrams"] = srv.bad_datagrams
        print(json.dumps(stats), flush=True)


def connect_times(uri: str, n: int) -> list[float]:
    """Seconds from open_link to fully connected (all params read), ``n`` times."""
    from cflib.crazyflie import Crazyflie
    from cflib.crazyflie.syncCrazyflie import SyncCrazyflie

    times = []
    for _ in range(n):
        scf = SyncCrazyflie(uri, cf=Crazyflie())
        t0 = time.perf_counter()
        scf.open_link()
        scf.wait_for_params()
        times.append(time.perf_counter() - t0)
        scf.close_link()
    return times


def log_run(uri: str, duration_s: float) -> dict:
    """Stream 6 floats at 100 Hz for ``duration_s`` and analyse the timestamp sequence (ms)."""
    from cflib.crazyflie import Crazyflie
    from cflib.crazyflie.log import LogConfig
    from cflib.crazyflie.syncCrazyflie import SyncCrazyflie

    stamps: list[int] = []
    arrivals: list[float] = []
    with SyncCrazyflie(uri, cf=Crazyflie()) as scf:
        scf.wait_for_params()
        lc = LogConfig(name="bench", period_in_ms=PERIOD_MS)
        for v in LOG_VARS:
            lc.add_variable(f"stateEstimate.{v}", "float")

        def on_data(ts, data, conf):
            stamps.append(ts)
            arrivals.append(time.perf_counter())

        lc.data_received_cb.add_callback(on_data)
        scf.cf.log.add_config(lc)
        lc.start()
        time.sleep(duration_s)
        lc.stop()
        time.sleep(0.2)
    steps = [(b - a) % (1 << 24) for a, b in zip(stamps, stamps[1:])]
    lost = sum(max(0, s // PERIOD_MS - 1) for s in steps)
    irregular = sum(1 for s in steps if s % PERIOD_MS or s == 0)
    jitter = [1000.0 * (b - a) for a, b in zip(arrivals, arrivals[1:])]
    return {"duration_s": duration_s, "received": len(stamps), "expected_about": int(duration_s * 1000 / PERIOD_MS),
            "lost": lost, "irregular_steps": irregular,
            "arrival_gap_ms_max": max(jitter) if jitter else None,
            "arrival_gap_ms_p99": (statistics.quantiles(jitter, n=100)[98] if len(jitter) > 100 else None)}


def run_transport(kind: str, duration_s: float, n_connect: int) -> dict | None:
    child = subprocess.Popen([sys.executable, __file__, "--serve", kind], stdin=subprocess.PIPE,
                             stdout=subprocess.PIPE, text=True)
    try:
        uri = child.stdout.readline().strip()
        if not uri or uri.startswith("SKIP"):
            print(f"{kind}: skipped ({uri or 'device did not start'})", file=sys.stderr)
            return None
        import psutil

        proc = psutil.Process(child.pid)
        times = connect_times(uri, n_connect)
        cpu0, t0 = proc.cpu_times(), time.perf_counter()
        logs = log_run(uri, duration_s)
        cpu1, t1 = proc.cpu_times(), time.perf_counter()
        child.stdin.close()
        stats = json.loads(child.stdout.readline() or "{}")
    finally:
        if child.poll() is None:
            try:
                child.wait(timeout=10)
            except subprocess.TimeoutExpired:
                child.kill()
    return {"transport": kind, "uri": uri, "connect_s": times, "connect_s_median": statistics.median(times),
            "connect_s_max": max(times), **logs,
            "device_cpu_pct": 100.0 * ((cpu1.user + cpu1.system) - (cpu0.user + cpu0.system)) / (t1 - t0),
            "device_stats": stats}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="5 s of logging and 3 connections per transport")
    ap.add_argument("--serve", choices=["udp", "serial"], help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.serve:
        serve(args.serve)
        return 0
    try:
        import cflib.crtp
    except ImportError:
        print("cflib is not installed: pip install -e '.[dev]'", file=sys.stderr)
        return 2
    cflib.crtp.init_drivers(enable_serial_driver=True)
    logging.getLogger("cflib").setLevel(logging.ERROR)  # "Could not save cache" on every connect
    duration, n_connect = (5.0, 3) if args.quick else (60.0, 5)
    with contextlib.redirect_stdout(io.StringIO()):  # cflib's serial driver chatters on stdout
        results = [r for r in (run_transport(k, duration, n_connect) for k in ("udp", "serial")) if r]
    for kind in ("udp", "serial"):
        if not any(r["transport"] == kind for r in results):
            print(f"{kind}: skipped (see above; serial needs root for its /dev symlink)")
    rows = [[r["transport"], r["connect_s_median"], r["connect_s_max"], f"<= {CONNECT_TARGET_S}",
             r["received"], r["expected_about"], r["lost"], r["irregular_steps"],
             r["arrival_gap_ms_max"], r["device_cpu_pct"],
             "PASS" if r["connect_s_max"] <= CONNECT_TARGET_S and r["lost"] == 0 and r["irregular_steps"] == 0
             else "FAIL"] for r in results]
    print_table(f"cflib link to the simulated Crazyflie: 6 floats at 100 Hz for {duration:g} s",
                ["transport", "connect median s", "connect max s", "target", "log packets", "expected",
                 "lost", "irregular", "max arrival gap ms", "device CPU %", "verdict"], rows)
    write_json("link", {"quick": args.quick, "log_period_ms": PERIOD_MS, "log_vars": len(LOG_VARS),
                        "connect_target_s": CONNECT_TARGET_S, "results": results})
    return 0 if rows and all(r[-1] == "PASS" for r in rows) else 1


if __name__ == "__main__":
    raise SystemExit(main())
