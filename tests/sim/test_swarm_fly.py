"""`polycc swarm-fly` against real cflib and three `polycc sim-device` processes (the host-built app, one per
drone, each on its own UDP port): cflib's Swarm connects to all, the ground relays neighbours over the app
channel, the coverage controllers write the goals, and every drone takes off, covers and lands.

What is checked is what a user would: the command exits 0, the peak was detected, every drone ends on the
floor after the high-level landing, neighbour records were relayed, and the drones' estimates never came
closer than 2 r.
"""

from __future__ import annotations

import json
import signal
import socket
import subprocess
import sys

import numpy as np
import pytest

from polycc.cli import main

pytest.importorskip("cflib")
STARTS = [(-2.4, -1.5, 0.9), (-2.4, 0.9, 0.9), (-1.5, 1.5, 0.9)]
N = len(STARTS)


def _free_ports(n):
    socks = [socket.socket(socket.AF_INET, socket.SOCK_DGRAM) for _ in range(n)]
    for s in socks:
        s.bind(("127.0.0.1", 0))
    ports = [s.getsockname()[1] for s in socks]
    for s in socks:
        s.close()
    return ports


@pytest.fixture(scope="module")
def arena(tmp_path_factory, demo_build):
    d = demo_build(tmp_path_factory.mktemp("swfly"))
    return d


@pytest.mark.slow
def test_swarm_fly_three_sim_devices(arena, tmp_path, capsys):
    from polycc.plan.planner import NavMap

    out = arena / "b"
    starts = np.array(STARTS)  # README's (swarm-fly): free columns from the floor to 0.9 m
    nav = NavMap.from_build(out, radius=0.1, margin=0.05, spacing=0.15)
    centres = nav.grid.centres(np.argwhere(nav._free.astype(bool)))
    # one peak 1.5-3 m from the first drone, at a free cell
    d0 = np.linalg.norm(centres - starts[0], axis=1)
    peak = centres[np.flatnonzero((d0 > 1.5) & (d0 < 3.0) & (centres[:, 2] > 0.6))[0]]
    targets = tmp_path / "targets.json"
    targets.write_text(json.dumps({"targets": [{"x": peak[0], "y": peak[1], "z": peak[2], "sigma": 0.4,
                                                "weight": 1.0}]}))
    ports = _free_ports(N)
    procs = []
    try:
        for s, port in zip(starts, ports):
            cmd = [sys.executable, "-m", "polycc", "sim-device", str(out), "--udp", f"127.0.0.1:{port}",
                   "--start", f"{s[0]:.3f},{s[1]:.3f},{s[2]:.3f}"]
            procs.append(subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True))
        for p in procs:
            for line in p.stdout:
                if line.startswith("URI: "):
                    break
        uris = ",".join(f"udp://127.0.0.1:{port}" for port in ports)
        rc = main(["swarm-fly", str(out), "--uris", uris, "--targets", str(targets), "--takeoff", "0.9",
                   "--t-max", "60", "--plot", str(tmp_path / "coverage.png")])
        text = capsys.readouterr().out
    finally:
        logs = []
        for p in procs:
            p.send_signal(signal.SIGINT)
            logs.append(p.communicate(timeout=30)[0])
    assert rc == 0, text
    summary = json.loads((out / "swarm_fly.json").read_text())
    assert summary["outcome"] == "covered" and summary["coverage_ratio"] == 1.0, text
    assert summary["min_inter_drone_m"] > 0.2, text
    assert summary["relayed_records"] > 0
    assert "landed" in text and (tmp_path / "coverage.png").stat().st_size > 10_000
    for i, end in enumerate(summary["end_positions"]):  # every drone back on the floor
        assert end[2] < 0.08, (i, end, text)
    for log in logs:
        assert "Traceback" not in log, log[-3000:]
