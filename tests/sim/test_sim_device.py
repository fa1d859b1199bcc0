"""`polycc sim-device` and `polycc fly`: the host-built app behind the simulated Crazyflie.

Bitcraze's real cflib connects over UDP and over the serial pty, reads the TOCs that come from the
app's own tables, writes a param into the app's variable, streams logs and uses the app channel;
a cflib takeoff script flies the vehicle model; and `polycc fly` flies a small scene end to end
against `polycc sim-device` running as a separate process (as in the two-terminal usage).

Serial discovery: cflib only opens a NAME that pyserial's ``comports()`` lists, which needs the
``/dev/ttyUSB-polyccN`` symlink (root). Without root the serial test patches
``SerialDriver.get_devices`` -- the one lookup the symlink provides; the pty I/O stays real.
"""

from __future__ import annotations

import csv
import json
import os
import signal
import subprocess
import sys
import time
from contextlib import ExitStack
from unittest import mock

import numpy as np
import pytest

from polycc.cli import main
from polycc.codegen.header import write_outputs
from polycc.geometry.halfplanes import axis_box
from polycc.sim.crtp_device import CrtpDevice
from polycc.sim.device_server import SerialDeviceServer, UdpDeviceServer
from polycc.sim.sitl_device import SitlDeviceModel, decode_app_status
from polycc.testing.files import CHECKOUT

# Two walls with a 0.6 m gap at y in [-0.3, 0.3]; the flight goes through it along +x.
WALLS = [((0.0, -1.5, 0.0), (0.6, -0.3, 1.5)), ((0.0, 0.3, 0.0), (0.6, 1.5, 1.5))]
START, GOAL = (-0.6, 0.05, 0.7), (0.9, -0.05, 0.7)
REPO = str(CHECKOUT)


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory):
    d = tmp_path_factory.mktemp("walls")
    write_outputs(d, [axis_box(np.array(lo) - 0.02, np.array(hi) + 0.02) for lo, hi in WALLS], {"kappa": 100.0})
    return d


@pytest.fixture
def model(scene_dir):
    m = SitlDeviceModel(scene_dir, start=START)  # the C app is one per process: one model at a time
    yield m
    m.stop()


# ---------------------------------------------------------------- without cflib
def test_tocs_come_from_the_app(model):
    app = model.app
    assert [p.full_name for p in model.params] == [e.full_name for e in app.param_toc()]
    assert [v.full_name for v in model.logs] == [e.full_name for e in app.log_toc()]
    types = {p.full_name: p.ctype for p in model.params}
    assert types["polycc.enable"] == "uint8_t" and types["polycc.goalX"] == "float"
    assert types["polycc.rateHz"] == "uint16_t"
    logs = {v.full_name: v.ctype for v in model.logs}
    assert logs["polycc.psi"] == "float" and logs["polycc.status"] == "uint8_t"
    assert {f"stateEstimate.{a}" for a in ("x", "y", "z", "vx", "vy", "vz")} <= set(logs)
    dev = CrtpDevice(model)
    assert "firmware.polyccVersion" in {p.full_name for p in dev.params}


def test_params_and_logs_are_the_app_variables(model):
    goal_x = next(p for p in model.params if p.full_name == "polycc.goalX")
    goal_x.set(1.25)
    assert model.app.get_param("polycc", "goalX") == 1.25 and goal_x.get() == 1.25
    x = next(v for v in model.logs if v.full_name == "stateEstimate.x")
    model.advance_to(10)
    assert x.get() == pytest.approx(START[0], abs=0.01)  # estimate noise 1 mm


@pytest.fixture
def floor_model(scene_dir):
    m = SitlDeviceModel(scene_dir, start=(START[0], START[1], 0.0), on_floor=True)
    yield m
    m.stop()


def test_hl_takeoff_go_to_land_from_the_floor(floor_model):
    """The high-level commander as on a Crazyflie: takeoff from the floor, go_to, land; the motors
    stop on the floor at the end."""
    m = floor_model
    m.advance_to(500)
    assert not m.motors_on and m.position[2] == 0.0
    m.on_setpoint("hl_takeoff", {"height": 1.0, "duration": 2.0})
    m.advance_to(4000)
    assert np.allclose(m.position, (START[0], START[1], 1.0), atol=0.02), m.summary()
    m.on_setpoint("hl_go_to", {"relative": 1, "x": 0.3, "y": 0.0, "z": -0.2, "yaw": 0.0, "duration": 1.0})
    m.advance_to(6500)
    assert np.allclose(m.position, (START[0] + 0.3, START[1], 0.8), atol=0.02), m.summary()
    m.on_setpoint("hl_land", {"height": 0.0, "duration": 2.0})
    m.advance_to(10000)
    assert m.position[2] < 0.01 and not m.motors_on and m.dyn.impact_speed_ms < 0.5


def test_position_setpoints_fly_and_a_stop_setpoint_cuts_the_motors(model):
    for t in range(100, 4000, 100):  # a streaming client resends low-level setpoints
        model.on_setpoint("position", {"x": -0.5, "y": 0.0, "z": 0.9, "yaw": 0.0})
        model.advance_to(t)
    assert np.allclose(model.position, (-0.5, 0.0, 0.9), atol=0.02), model.summary()
    model.on_setpoint("stop", {})
    model.advance_to(4300)
    assert not model.motors_on and model.position[2] < 0.8  # as on a Crazyflie: it falls


def test_hover_setpoint_and_watchdog(model):
    """The supervisor's watchdog: a setpoint older than 0.5 s levels the vehicle, older than 2 s
    stops the motors (the real firmware's behaviour, which the fast model follows)."""
    model.on_setpoint("hover", {"vx": 0.2, "vy": 0.0, "yawrate": 0.0, "zdistance": 1.0})
    model.advance_to(400)
    assert model.motors_on
    model.advance_to(2600)
    assert not model.motors_on


def test_app_enabled_wins_and_flies_to_goal(model):
    for name, v in zip(("goalX", "goalY", "goalZ", "enable"), (*GOAL, 1)):
        model.app.set_param("polycc", name, v)
    model.advance_to(15000)
    assert np.linalg.norm(model.position - GOAL) < 0.05 and model.status == 1
    model.on_appchannel(b"ping")
    model.advance_to(15010)
    reply = decode_app_status(model.outgoing_appchannel()[-1])
    assert reply["status"] == 1 and reply["enable"] == 1 and reply["echo"] == b"ping"
    assert reply["x"] == pytest.approx(model.dyn.estimate()[0][0], abs=0.01)


def test_realtime_thread_follows_the_wall_clock(model):
    with model:
        time.sleep(0.3)
        with model.lock:
            lag = model.time_ms() - model.sim_ms
    assert -10 <= lag <= 50 and model.steps >= 100 and model.step_errors == 0


def test_sim_device_cli_errors(scene_dir, tmp_path, capsys):
    assert main(["sim-device", str(scene_dir)]) == 2
    assert "--udp" in capsys.readouterr().err
    assert main(["sim-device", str(tmp_path), "--udp"]) == 2
    assert main(["sim-device", str(scene_dir), "--udp", "nohostport"]) == 2


def test_fly_without_cflib_is_a_clear_error(monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "cflib", None)
    monkeypatch.setitem(sys.modules, "cflib.crtp", None)
    assert main(["fly", "--uri", "udp://127.0.0.1:1", "--goal", "0,0,1", "--timeout", "1"]) == 2
    assert "pip install 'polycc[crazyflie]'" in capsys.readouterr().err


# ---------------------------------------------------------------- real cflib
cflib_crtp = pytest.importorskip("cflib.crtp", reason="cflib is not installed (pip install 'polycc[crazyflie]')")
from cflib.crazyflie import Crazyflie  # noqa: E402
from cflib.crazyflie.syncCrazyflie import SyncCrazyflie  # noqa: E402
from cflib.crtp.serialdriver import SerialDriver  # noqa: E402

from polycc.testing.cflib_session import run_with_timeout, scenario  # noqa: E402


@pytest.fixture(scope="module", autouse=True)
def drivers():
    if SerialDriver not in cflib_crtp.CLASSES:  # init_drivers appends on every call
        cflib_crtp.init_drivers(enable_serial_driver=True)


class AppValues:
    """What test_cflib_connect's scenario reads as ``model.values[name]``: the app's real variables."""

    def __init__(self, model: SitlDeviceModel) -> None:
        self.model = model
        self.values = self

    def __getitem__(self, name: str) -> float:
        with self.model.lock:
            return self.model.app.get_param(*name.split("."))


def check(out: dict, model: SitlDeviceModel, dev: CrtpDevice) -> None:
    """The outcome of test_cflib_connect's scenario (connect, TOCs, goalX = 2.5 written and read back,
    5 samples of polycc.psi and stateEstimate.x at 10 ms, app channel "hello") against the SITL."""
    assert out["log_toc"] == {v.full_name for v in model.logs}
    assert out["param_toc"] == {p.full_name for p in dev.params}
    assert {"polycc.psi", "stateEstimate.x"} <= out["log_toc"] and "polycc.goalX" in out["param_toc"]
    assert float(out["goalX_initial"]) == 0.0  # the app's default
    assert float(out["goalX_read"]) == 2.5 and out["goalX_model"] == 2.5  # in the app's C variable
    assert [d["stateEstimate.x"] for _, d in out["log"]] == pytest.approx([START[0]] * 5, abs=0.01)
    assert all(d["polycc.psi"] == 0.0 for _, d in out["log"])  # app disabled: psi not evaluated yet
    stamps = [ts for ts, _ in out["log"]]
    assert all(b - a == 10 for a, b in zip(stamps, stamps[1:])), stamps
    app = decode_app_status(out["app"][0])
    assert app["echo"] == b"hello" and app["status"] == 0 and app["enable"] == 0
    assert app["x"] == pytest.approx(START[0], abs=0.01)  # the estimate (1 mm noise)


def takeoff(uri: str, model: SitlDeviceModel, height: float) -> float:
    """A user's takeoff script (high-level commander, from the floor), then wait for the height;
    returns z reached (cflib's close_link then stops the motors, as on a Crazyflie)."""
    with SyncCrazyflie(uri, cf=Crazyflie(rw_cache=None)) as scf:
        # the first session's cflib close_link left the commander at CRTP priority (its parting
        # setpoint): high-level commands are ignored until the priority is handed back
        scf.cf.commander.send_notify_setpoint_stop()
        scf.cf.high_level_commander.takeoff(height, 1.0)
        deadline = time.monotonic() + 5.0
        while time.monotonic() < deadline and abs(model.position[2] - height) > 0.02:
            time.sleep(0.05)
        return float(model.position[2])


def test_cflib_drives_sitl_over_udp(floor_model):
    model = floor_model
    dev = CrtpDevice(model)
    with model, UdpDeviceServer(dev, port=0) as srv:
        out = run_with_timeout(lambda: scenario(srv.uri, AppValues(model)))
        z = run_with_timeout(lambda: takeoff(srv.uri, model, 1.0))  # a second session
        assert srv.bad_datagrams == 0
    check(out, model, dev)
    assert z == pytest.approx(1.0, abs=0.02)
    assert dev.stats.malformed == 0 and dev.stats.setpoints >= 1 and model.step_errors == 0


def test_cflib_drives_sitl_over_serial_pty(model):
    dev = CrtpDevice(model)
    with ExitStack() as stack:
        stack.enter_context(model)
        srv = stack.enter_context(SerialDeviceServer(dev, link_name=f"ttyUSB-polycc-sd{os.getpid()}"))
        if srv.link_path is not None:
            uri = srv.uri  # listed by comports(), as cflib looks it up
        else:
            # No root: /dev is not writable, so comports() cannot list the pty; patch the one lookup
            # the symlink provides. pyserial, the CPX framing and the handshake stay real.
            name = os.path.basename(srv.pty_path)
            stack.enter_context(mock.patch.object(SerialDriver, "get_devices", lambda self: {name: srv.pty_path}))
            uri = f"serial://{name}"
        out = run_with_timeout(lambda: scenario(uri, AppValues(model)))
        assert srv.link.decoder.stats.errors == 0
    check(out, model, dev)


def _start_sim_device(scene_dir, *extra):
    env = dict(os.environ, PYTHONUNBUFFERED="1", PYTHONPATH=REPO + os.pathsep + os.environ.get("PYTHONPATH", ""))
    proc = subprocess.Popen([sys.executable, "-m", "polycc.cli", "sim-device", str(scene_dir), "--udp",
                             "127.0.0.1:0", *extra], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            env=env, cwd=REPO)
    lines = []
    deadline = time.monotonic() + 30.0
    while time.monotonic() < deadline:
        line = proc.stdout.readline()
        if not line:
            break
        lines.append(line)
        if line.startswith("URI: udp://"):
            return proc, line.split()[1], lines
    proc.kill()
    raise AssertionError("sim-device printed no URI:\n" + "".join(lines))


def test_ctrl_c_reaches_the_devices_the_tests_start():
    """Regression: `make test` started in the background (nohup, ``&``) ran with SIGINT ignored, every
    sim-device it spawned inherited that, ignored the tests' Ctrl-C and was killed after 10 s (rc -9: three
    cflib tests failed). tests/conftest.py restores the terminal default; a child must see Python's handler."""
    probe = "import signal; print(signal.getsignal(signal.SIGINT) is signal.default_int_handler)"
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "True", "SIGINT is ignored in the test's children: Ctrl-C would not stop them"


def fly_end_to_end(scene_dir, start, goal, csv_path, timeout_s: float = 15.0, floor: bool = False) -> list[dict]:
    """Two terminals: `polycc sim-device OUT --udp ...` (a subprocess, stopped with Ctrl-C) and
    `polycc fly --uri ... --goal ...` (in-process; from the floor with --takeoff ... --land). Returns
    the CSV rows after checking arrival."""
    extra = [] if floor else ["--airborne"]
    proc, uri, lines = _start_sim_device(scene_dir, "--start=" + ",".join(map(str, start)), *extra)
    fly_args = ["--takeoff", str(start[2]), "--land"] if floor else []
    try:
        rc = run_with_timeout(lambda: main(["fly", "--uri", uri, "--goal", ",".join(map(str, goal)), "--csv",
                                            str(csv_path), "--timeout", str(timeout_s), "--arrive-tol", "0.05",
                                            *fly_args]),
                              timeout_s + 30.0)
        assert rc == 0
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            rest, _ = proc.communicate(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            rest, _ = proc.communicate()
    assert proc.returncode == 0, "".join(lines) + rest
    assert "stopped:" in rest
    with open(csv_path) as f:
        rows = list(csv.DictReader(f))
    assert len(rows) > 50
    status = [r["polycc.status"] for r in rows]
    first, last = status.index("1"), len(status) - 1 - status[::-1].index("1")
    flying = rows[first:last + 1]
    assert min(float(r["polycc.psi"]) for r in flying) >= 0.0
    assert set(status[first:last + 1]) == {"1"}  # the app flew the whole way once engaged (status ok)
    assert float(rows[0]["stateEstimate.x"]) == pytest.approx(start[0], abs=0.05)
    end = np.array([float(flying[-1][f"stateEstimate.{a}"]) for a in "xyz"])
    assert np.linalg.norm(end - np.asarray(goal)) <= 0.06
    if floor:
        assert float(rows[-1]["stateEstimate.z"]) < 0.08  # landed
    t = [float(r["time_s"]) for r in rows]
    assert all(b > a for a, b in zip(t, t[1:]))
    return rows


def test_fly_end_to_end_against_sim_device(scene_dir, tmp_path):
    fly_end_to_end(scene_dir, START, GOAL, tmp_path / "fly.csv")


def test_fly_takeoff_to_landing_against_sim_device(scene_dir, tmp_path):
    fly_end_to_end(scene_dir, START, GOAL, tmp_path / "fly.csv", timeout_s=20.0, floor=True)


@pytest.mark.slow
def test_fly_demo_arena_end_to_end(tmp_path):
    """The demo arena (out/demo from `make demo`, $POLYCC_DEMO_OUT, or built here at 64 KiB),
    start to goal through the hoop (~8 s of flight)."""
    demo = os.environ.get("POLYCC_DEMO_OUT") or os.path.join(REPO, "out", "demo")
    if not os.path.isfile(os.path.join(demo, "polytopes.h")) or not os.path.isfile(os.path.join(demo, "arena.json")):
        from polycc.cli import main as polycc_main

        demo = str(tmp_path / "demo")
        assert polycc_main(["demo-scene", os.path.join(demo, "arena.ply")]) == 0
        assert polycc_main(["build", os.path.join(demo, "arena.ply"), "--flash-kb", "64", "--mc-samples", "20000",
                            "-o", demo]) == 0
    with open(os.path.join(demo, "arena.json")) as f:
        arena = json.load(f)
    fly_end_to_end(demo, arena["start"], arena["goal"], tmp_path / "fly.csv", timeout_s=30.0, floor=True)


def test_fly_env_uri_default(monkeypatch):
    monkeypatch.setenv("CFLIB_URI", "udp://10.0.0.1:1234")
    import argparse

    from polycc.cli import fly

    p = argparse.ArgumentParser()
    fly.register(p.add_subparsers())
    assert p.parse_args(["fly", "--goal", "0,0,1"]).uri == "udp://10.0.0.1:1234"


def test_fly_ctrl_c_disables_the_app_and_holds(model):
    """Ctrl-C mid-flight (raised from the live display callback): polycc.enable = 0 reaches the device,
    the app hands over to the high-level commander (which holds), no stop setpoint is sent, and the
    partial log is on the exception for the CSV."""
    from polycc.cli import fly

    calls = []

    def interrupt(log):
        calls.append(len(log.rows))
        if log.latest.get("polycc.status") == 1 and log.latest.get("stateEstimate.x", START[0]) > START[0] + 0.1:
            raise KeyboardInterrupt  # mid-flight, with the app flying

    with model, UdpDeviceServer(CrtpDevice(model), port=0) as srv:
        def go():
            with pytest.raises(KeyboardInterrupt) as exc:
                fly.fly(srv.uri, GOAL, ["polycc.psi"], on_update=interrupt)
            return exc.value.flight_log
        log = run_with_timeout(go)
        time.sleep(0.1)
        with model.lock:
            enabled, kinds, x = model.app_enabled, list(model.setpoints), model.position[0]
    assert log.outcome == "interrupted" and log.rows and log.columns[-1] == "polycc.psi"
    assert not enabled and "stop" not in kinds and START[0] < x < GOAL[0]
    assert model.motors_on and model.app.commander().hl_gotos >= 1  # handed over, holding
