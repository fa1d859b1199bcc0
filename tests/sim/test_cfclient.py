"""cfclient, the real Bitcraze GUI, connects to `polycc sim-device` as a user would: its own scan finds
``udp://127.0.0.1:1985x``, Connect downloads the TOCs and parameters, and its tabs (flight tab with the
assisted-mode deck checks, battery and motor logs) run without an error (:mod:`polycc.testing.cfclient_connect`,
a subprocess with Qt offscreen). The real-firmware SITL case is in tests/sim/test_firmware_sitl.py.

Regression: the fast device lacked ``deck.bcZRanger``/``deck.bcFlow`` and ``motor.m1..m4``, which the real
firmware has; cfclient's flight tab raised KeyError on connect.
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys

import pytest

from polycc.testing.cfclient_connect import free_scan_port, run_cfclient

pytest.importorskip("cflib")
pytest.importorskip("cfclient", reason="pip install cfclient (in the [dev] extra)")


@pytest.fixture(scope="module")
def arena(tmp_path_factory, demo_build):
    d = demo_build(tmp_path_factory.mktemp("cfc"))
    return d / "b"


def test_cfclient_connects_to_the_fast_sim_device(arena, tmp_path):
    port = free_scan_port()
    proc = subprocess.Popen([sys.executable, "-m", "polycc", "sim-device", str(arena), "--udp", f"127.0.0.1:{port}"],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        for line in proc.stdout:
            if line.startswith("URI: "):
                break
        res = run_cfclient(f"udp://127.0.0.1:{port}", tmp_path)
    finally:
        proc.send_signal(signal.SIGINT)
        proc.communicate(timeout=30)
    assert res["connected"] and res["still_connected"], json.dumps(res)
    assert res["errors"] == [], "\n".join(res["errors"])
    assert res["has_vbat"] and res["battery_v"] and 3.0 < res["battery_v"] < 4.3  # the fast device has pm.vbat
