"""The real Crazyflie firmware in the loop: CrazySim SITL ``cf2`` with the polycc app and a demo-arena
header compiled in (:mod:`polycc.sim.firmware`), flown with real cflib.

* the issue-14 scenarios (a)-(g) (:mod:`polycc.testing.flight_scenarios`) on the real firmware, with
  the same assertions as the fast sim (tests/sim/test_flight_behaviour.py) where the firmware agrees;
* unmodified cflib scripts: the README example, MotionCommander, PositionHlCommander, SyncLogger;
* `polycc sim DIR --firmware FWDIR` (several trials through the arena);
* the differential test: the same scenario on the fast shims and on the real firmware, position RMS
  after the enable within the bound measured here (:data:`DIFF_RMS_M`).

One cf2 build for the module (cached by content hash across runs); each flight boots its own SITL (3 s)
so scenarios cannot leak state into each other. Everything waits in simulated time (lock-stepped), so a
loaded host only makes it slower. Needs cmake, a host C compiler and the SITL tarball
(``../shared/firmware/``, or POLYCC_SHARED_FIRMWARE).
"""

from __future__ import annotations

import builtins
import json
import math
import os
import re
import shutil
import types

import numpy as np
import pytest

from polycc.testing import flight_scenarios as fs
from polycc.testing.files import sitl_tarball
from polycc.testing.worlds import run_script

pytest.importorskip("cflib")
pytestmark = pytest.mark.skipif(shutil.which("cmake") is None and not os.environ.get("CI"),
                                reason="cmake not installed (.ci/run installs it)")

# RMS of the 3-D position difference, fast shims vs real firmware, while the app flies the full flight
# (flight_scenarios.diff_rms). Measured on the demo arena: 14.7 cm before the fast model got the
# effective drag calibrated on this firmware (dynamics.CrazyflieParams.drag_xy), 2.1, 3.4 and 4.2 cm in three
# runs after (x 0.5 cm, z 2.0 cm in the first: the real vehicle sags 2-3 cm while cruising). The real run is not
# deterministic (cflib's commands reach the lock-stepped firmware at host-timed instants), so the bound
# leaves 2 cm over the worst run seen, above the 5 cm target.
DIFF_RMS_M = 0.06
# simulated seconds a README example may take here (each flies for about 20 s); over it the test fails with
# where the vehicle is instead of hanging in the script's SyncLogger until pytest-timeout (CI, 2026-12-07)
README_LIMIT_S = 90.0
STARVED_LATE = 0.05  # share of the app's ticks that woke late above which a real-firmware flight was starved


@pytest.fixture(scope="module")
def arena(tmp_path_factory, demo_build):

    tree = sitl_tarball()
    if not tree.exists():
        if os.environ.get("CI"):
            pytest.fail(f"{tree}: SITL firmware tarball not found; CI needs ../shared/firmware beside the clone")
        pytest.skip(f"{tree}: SITL firmware tarball not found (set POLYCC_SHARED_FIRMWARE)")
    d = demo_build(tmp_path_factory.mktemp("fwarena"))
    side = json.loads((d / "arena.json").read_text())
    start = list(side["start"])
    from polycc.sim.firmware.build import build_cf2

    build = build_cf2(tree, d / "b" / "polytopes.h")
    assert build.app_warnings == []  # the app compiles without a warning in the SITL too
    return {"dir": d / "b", "start": [start[0], start[1], 0.0], "goal": list(side["goal"]), "build": build,
            "tree": tree, "scene": d / "arena.ply"}


def world(arena):
    from polycc.testing.worlds import FirmwareWorld

    return FirmwareWorld(arena["dir"] / "polytopes.h", arena["start"], cf2=arena["build"])


_runs: dict = {}


def run(arena, scenario):
    """Each scenario once per module (the differential test reuses the firmware's full flight)."""
    if scenario not in _runs:
        with world(arena) as w:
            _runs[scenario] = fs.SCENARIOS[scenario](w.uri, w, arena)
    return _runs[scenario]


# --------------------------------------------------------------------------- the issue-14 scenarios
@pytest.mark.slow
def test_full_flight_hand_over_and_land(arena):
    r = run(arena, "full_flight")
    assert r["took_off"] and r["arrived"]
    assert r["hold_dz_max"] < 0.05  # disabled in the air: the hand-over holds z within 5 cm for 3 s
    # the land is sent during the settling hold (status 14): the path of the land lost to the hand-over's race
    # (docs/barrier.md section 8; the race itself: test_app_sitl_shims.py, the land at the worst instant)
    assert r["status_after_disable"] == 14, r["status_after_disable"]
    assert r["landed"] and not r["motors_on_end"]


@pytest.mark.slow
def test_enabled_on_the_floor_keeps_the_motors_off(arena):
    r = run(arena, "enabled_on_floor")
    assert not r["motors_on_any"] and r["z_max"] < 0.01
    assert r["status"] == 7


@pytest.mark.slow
def test_disable_at_speed_stops_and_holds(arena):
    r = run(arena, "disable_at_speed")
    assert r["took_off"] and r["speed_at_disable"] > 0.4
    assert r["speed_end"] < 0.05 and r["travel_after_disable"] < 0.3 and r["motors_on_end"]
    assert r["z_min_after"] > 0.6  # no drop


@pytest.mark.slow
def test_link_loss_lands(arena):
    r = run(arena, "link_loss")
    assert r["status_before_cut"] == 1
    assert r["landed"] and not r["motors_on_end"] and r["max_descent_speed"] < 1.0
    assert r["status_after"] == 10


@pytest.mark.slow
def test_unsupported_controller_is_refused(arena):
    r = run(arena, "unsupported_controller")
    assert r["status"] == 9 and r["moved"] < 0.05


@pytest.mark.slow
def test_ground_setpoints_are_ignored_while_enabled(arena):
    r = run(arena, "ground_setpoints_while_enabled")
    assert r["arrived"] and r["z_min_flight"] > 0.5


@pytest.mark.slow
def test_polycc_fly_from_the_floor(arena):
    r = run(arena, "polycc_fly_from_floor")
    assert r["outcome"] == "landed", r["events"]
    assert r["max_descent_speed"] < 1.0 and not r["motors_on_end"]
    # `polycc fly` times its waits by the log timestamps (tests/ground/test_fly_clock.py): on the SITL they
    # are the simulated clock, whatever the host's real-time factor (within a sample period or two, and
    # the simulator's time read up to 50 ms after the sample)
    log_s, sim_s = r["clock_spans_s"]
    assert sim_s > 15.0 and abs(log_s - sim_s) < 0.2, r["clock_spans_s"]


# --------------------------------------------------------------------------- unmodified cflib scripts
def _sim_time(w):
    """A ``time`` module whose clock is the SITL's simulated time (it may run slower than real time on a
    loaded host; on a real Crazyflie the two are the same): for scripts and cflib helpers that time
    their steps with ``time.sleep`` (MotionCommander's moves and land, PositionHlCommander's waits)."""
    return types.SimpleNamespace(sleep=w.sleep, time=w.time, monotonic=w.time, perf_counter=w.time)


def _sim_time_import(w):
    """``__import__`` for an exec'd user script whose ``import time`` gets :func:`_sim_time`."""
    real = builtins.__import__
    fake = _sim_time(w)

    def imp(name, *a, **k):
        return fake if name == "time" else real(name, *a, **k)
    return imp


@pytest.mark.slow
def test_readme_cflib_example_on_the_real_firmware(arena):
    from polycc.testing.files import readme_block

    code = readme_block("readme-cflib-example")
    goal = np.array([float(v) for v in re.search(r'\("goalX", ([-\d.]+)\), \("goalY", ([-\d.]+)\), '
                                                 r'\("goalZ", ([-\d.]+)\)', code).groups()])
    with world(arena) as w:
        with fs.Recorder(w, {}) as rec:
            g = {"__builtins__": dict(vars(builtins), __import__=_sim_time_import(w))}
            run_script(w, code.replace("udp://127.0.0.1:19850", w.uri), README_LIMIT_S, g)
            w.sleep(1.0)
        a = rec.array()
        p, v, on = w.truth()
    xyz = a[:, 1:4]
    assert xyz[:, 2].max() > 0.8
    assert np.linalg.norm(xyz - goal, axis=1).min() < 0.15
    assert p[2] < 0.03 and not on  # landed, motors off
    assert a[:, 4].min() > -1.0  # no drop


def _connect(w):
    return fs._connect(w.uri, w)


@pytest.mark.slow
def test_a_connect_whose_first_request_the_firmware_loses_completes(arena):
    """Regression: cflib's first request of a connect (link service SOURCE, port 15 channel 1) had no reply
    pattern in the bridge's retransmission; lost in the firmware's RX queue, as on a loaded host, it was never
    resent and cflib waited for ever (a README test hung 1200 s in CI). The bridge loses it on purpose here."""
    from polycc.link.cflib_tools import close_without_stop, connect
    from polycc.testing.worlds import FirmwareWorld

    with FirmwareWorld(arena["dir"] / "polytopes.h", arena["start"], cf2=arena["build"],
                       bridge_args=["--lose", "0xfd:1"]) as w:
        scf = connect(w.uri, 60.0)  # no retry: the stall fails here with a one-line error after 60 s
        close_without_stop(scf)
        st = w.sitl.stats()
    assert st["lost_on_purpose"] == 1
    assert st["arq_recovered"] >= 1 and st["arq_gave_up"] == 0


@pytest.mark.slow
def test_motion_commander_and_sync_logger(arena, monkeypatch):
    from cflib.crazyflie.log import LogConfig
    from cflib.crazyflie.syncLogger import SyncLogger
    from cflib.positioning import motion_commander
    from cflib.positioning.motion_commander import MotionCommander

    from polycc.link.cflib_tools import close_without_stop

    with world(arena) as w:
        monkeypatch.setattr(motion_commander, "time", _sim_time(w))
        scf = _connect(w)
        try:
            lc = LogConfig(name="pos", period_in_ms=50)
            for n in ("stateEstimate.x", "stateEstimate.y", "stateEstimate.z"):
                lc.add_variable(n, "float")
            rows = []
            with SyncLogger(scf, lc) as logger:
                for entry in logger:
                    rows.append(entry[1])
                    if len(rows) >= 10:
                        break
            assert len(rows) == 10 and all(abs(r["stateEstimate.z"]) < 0.05 for r in rows)
            p0 = w.truth()[0].copy()
            scf.cf.commander.send_notify_setpoint_stop()
            mc = MotionCommander(scf, default_height=0.6)
            mc.take_off(0.6, 0.3)
            z_up = w.truth()[0][2]
            mc.forward(0.5, 0.25)
            p1 = w.truth()[0].copy()
            mc.land(0.3)
            p_end, _, on = w.truth()
            assert w.wait_until(lambda: not w.truth()[2], 5.0)  # motors stop on the floor (MC sends stop)
            touchdown = max((float(i["speed"]) for i in w.sitl.impacts()), default=0.0)
        finally:
            close_without_stop(scf)
    assert z_up > 0.4
    assert p1[0] - p0[0] > 0.2  # forward = +x in the world frame (yaw 0)
    # cflib's MotionCommander.land descends for height/velocity seconds and then sends stop: the real PID
    # lags the velocity command, so the motors stop ~0.15 m up (measured 0.15 m) and it drops the rest
    # (cflib's behaviour, the same on hardware; the polycc examples land with the high-level commander)
    assert p_end[2] < 0.2 and touchdown < 2.5 and touchdown < 1.0


@pytest.mark.slow
def test_position_hl_commander(arena, monkeypatch):
    from cflib.positioning import position_hl_commander
    from cflib.positioning.position_hl_commander import PositionHlCommander

    from polycc.link.cflib_tools import close_without_stop

    with world(arena) as w:
        monkeypatch.setattr(position_hl_commander, "time", _sim_time(w))
        scf = _connect(w)
        x0, y0 = arena["start"][0], arena["start"][1]
        try:
            scf.cf.commander.send_notify_setpoint_stop()
            with PositionHlCommander(scf, x=x0, y=y0, z=0.0, default_velocity=0.4, default_height=0.7,
                                     controller=PositionHlCommander.CONTROLLER_PID) as pc:
                pc.go_to(x0 + 0.4, y0, 0.7)
                w.sleep(1.0)
                p_goto = w.truth()[0].copy()
            p_end = w.truth()[0].copy()  # leaving the with landed (its land waits the landing's duration)
            touchdown = max((float(i["speed"]) for i in w.sitl.impacts()), default=0.0)
        finally:
            close_without_stop(scf)
    assert math.dist(p_goto, (x0 + 0.4, y0, 0.7)) < 0.1
    # PositionHlCommander.land waits the landing's duration and then stops: measured 0.11 m up (PID lag)
    assert p_end[2] < 0.2 and touchdown < 2.5


# --------------------------------------------------------------------------- the shield on the real firmware
SHIELD_START = (-0.2, -0.6, 0.0)  # in front of the demo arena's box_2 (tests/sim/test_readme_shield.py)
OOT_CONTROLLER_FORK = 5  # ControllerTypeOot in the CrazySim fork's enum (no Lee controller); 6 upstream


def _box_clearance(xyz, r: float = 0.1):
    """Closest approach of the vehicle (radius r = the shield's default, m) to box_2, minus r (m)."""
    return float(fs.demo_box_distance(xyz, "box_2").min() - r)


@pytest.mark.slow
@pytest.mark.parametrize("shield", [1, 0])
def test_readme_shield_example_on_the_real_firmware(arena, monkeypatch, shield):
    """The README's MotionCommander script (a user's own, 1 m/s straight at box_2) on the real firmware with
    the app's out-of-tree controller: with the shield on it stops with clearance >= r and lands with the
    shield still on (the motors stop on the floor); left off, the same script flies into the box (so the
    test can fail). Changed from the README: the URI, the controller's
    number (5 in this fork) and, off, the enable value; time runs on the SITL's clock."""
    from cflib.positioning import motion_commander

    from polycc.testing.files import readme_block
    from polycc.testing.worlds import FirmwareWorld

    oot = f'"stabilizer.controller", {OOT_CONTROLLER_FORK}'
    code = readme_block("readme-shield-example").replace('"stabilizer.controller", 6', oot)
    assert oot in code
    if not shield:
        code = code.replace('"polyccShield.enable", 1', '"polyccShield.enable", 0')
    with FirmwareWorld(arena["dir"] / "polytopes.h", SHIELD_START, cf2=arena["build"]) as w:
        monkeypatch.setattr(motion_commander, "time", _sim_time(w))
        with fs.Recorder(w, {}) as rec:
            g = {"__builtins__": dict(vars(builtins), __import__=_sim_time_import(w))}
            run_script(w, code.replace("udp://127.0.0.1:19850", w.uri), README_LIMIT_S, g)
        rows = rec.array()
    xyz = rows[:, 1:4]
    assert xyz[:, 2].max() > 0.4  # it took off
    c = _box_clearance(xyz)
    cut = fs.motors_stop_height(rows, SHIELD_START[2])
    print(f"shield {'on' if shield else 'off'}: closest approach to box_2 minus r = {c:+.3f} m, motors stopped "
          f"{cut:.3f} m above the floor")
    if shield:
        assert c >= 0.0, f"shield on, real firmware: {-c:.3f} m into the box (r = 0.1 m)"
        # landed with the shield on as with it off (regression: held beside the box, the motors stopped 0.51 m
        # up). MotionCommander's land() goes down by its own height estimate and stops the motors about 0.1 m
        # up either way (measured: 0.107 on, 0.095 off)
        assert cut < 0.13, f"shield on, real firmware: the motors stopped {cut:.3f} m above the floor"
    else:
        assert c < -0.05, "shield off: the same script must fly into the box (the test can fail)"


@pytest.mark.slow
@pytest.mark.parametrize("shield", [1, 0])
def test_high_level_go_to_through_a_box_on_the_real_firmware(arena, shield):
    """A high-level go_to straight through box_2 (2.8 m at about 1 m/s) with the app's out-of-tree
    controller: with the shield on it is stopped in front of the box and never enters it, and switching the
    shield off there is deferred (the go_to's setpoint still lies behind the box) until a go_to back to the
    start; off, it flies in.  Regression: an "at rest" hand-over let go of the held vehicle, and the PID
    flew it on into the box."""
    from polycc.link.cflib_tools import close_without_stop, set_param
    from polycc.testing.worlds import FirmwareWorld

    x0, y0 = SHIELD_START[0], SHIELD_START[1]
    with FirmwareWorld(arena["dir"] / "polytopes.h", SHIELD_START, cf2=arena["build"]) as w:
        scf = _connect(w)
        try:
            cf = scf.cf
            set_param(cf, "stabilizer.controller", OOT_CONTROLLER_FORK)
            with fs.Recorder(w, {}) as rec:
                cf.high_level_commander.takeoff(0.5, 2.0)
                w.sleep(3.0)
                set_param(cf, "polyccShield.enable", shield)
                cf.high_level_commander.go_to(x0, y0 - 2.8, 0.5, 0.0, 2.8)
                w.sleep(4.0)
                p_end = w.truth()[0].copy()
                set_param(cf, "polyccShield.enable", 0)  # still aimed behind the box
                w.sleep(2.0)
                cf.high_level_commander.go_to(x0, y0, 0.5, 0.0, 3.0)
                w.sleep(4.0)
                cf.high_level_commander.land(0.0, 3.0)
                w.wait_until(lambda: not w.truth()[2], 8.0)
            xyz = rec.array()[:, 1:4]
        finally:
            close_without_stop(scf)
    c = _box_clearance(xyz)
    print(f"go_to, shield {'on' if shield else 'off'}: closest approach to box_2 minus r = {c:+.3f} m, "
          f"held at {np.round(p_end, 2)}")
    assert xyz[:, 2].max() > 0.4
    if shield:
        assert c >= 0.0, f"shield on, real firmware: the go_to took it {-c:.3f} m into the box"
        assert np.linalg.norm(xyz[-1, :2] - [x0, y0]) < 0.2  # flew back and landed at the start
    else:
        assert c < -0.05, "shield off: the go_to must fly into the box (the test can fail)"


def _septic_piece(p0: float, p1: float, T: float) -> list[float]:
    """Coefficients (increasing powers of t, s) of the rest-to-rest septic from p0 to p1 in T seconds."""
    a = (0.0, 0.0, 0.0, 0.0, 35.0, -84.0, 70.0, -20.0)
    return [p0] + [(p1 - p0) * a[k] / T**k for k in range(1, 8)]


@pytest.mark.slow
@pytest.mark.parametrize("shield", [1, 0])
def test_uploaded_trajectory_grazing_the_hoop_rim_on_the_real_firmware(arena, shield):
    """Issue 18 scenario: a trajectory uploaded to the high-level commander's memory (cflib's TrajectoryMemory,
    one Poly4D piece) straight through hoop_0 at 0.36 m above its centre, so 4 cm from the rim's inner
    surface: with the shield on it never comes within r of the rim, and then lands with the shield still on
    (the land starts from the trajectory's end, away from the held vehicle: regression, the vehicle was
    held and dropped from 1.48 m when the planner stopped the motors); off, the same trajectory grazes the
    rim (the test can fail)."""
    from cflib.crazyflie.mem import MemoryElement
    from cflib.crazyflie.mem.trajectory_memory import Poly4D

    from polycc.link.cflib_tools import close_without_stop, set_param
    from polycc.testing.worlds import FirmwareWorld

    x0, x1, y, z, T = -2.2, -0.2, -1.4, 1.26, 3.0
    traj = [Poly4D(T, Poly4D.Poly(_septic_piece(x0, x1, T)), Poly4D.Poly([y] + [0.0] * 7),
                   Poly4D.Poly([z] + [0.0] * 7), Poly4D.Poly())]
    with FirmwareWorld(arena["dir"] / "polytopes.h", (x0, y, 0.0), cf2=arena["build"]) as w:
        scf = _connect(w)
        try:
            cf = scf.cf
            set_param(cf, "stabilizer.controller", OOT_CONTROLLER_FORK)
            mem = cf.mem.get_mems(MemoryElement.TYPE_TRAJ)[0]
            mem.trajectory = traj
            mem.write_data_sync()
            hl = cf.high_level_commander
            hl.define_trajectory(1, 0, len(traj))
            with fs.Recorder(w, {}) as rec:
                hl.takeoff(z, 2.5)
                w.sleep(3.5)
                set_param(cf, "polyccShield.enable", shield)
                hl.start_trajectory(1, 1.0, False)
                w.sleep(T + 1.5)
                hl.land(0.0, 3.0)
                w.wait_until(lambda: not w.truth()[2], 8.0)
                w.sleep(0.3)
            rows = rec.array()
        finally:
            close_without_stop(scf)
    xyz = rows[:, 1:4]
    c = float(fs.demo_hoop_distance(xyz, "hoop_0").min() - 0.1)
    cut = fs.motors_stop_height(rows)
    print(f"trajectory, shield {'on' if shield else 'off'}: closest approach to hoop_0's rim minus r = {c:+.3f} m, "
          f"x reached {xyz[:, 0].max():+.2f}, motors stopped {cut:.3f} m above the floor")
    assert xyz[:, 2].max() > 1.1
    if shield:
        assert c >= 0.0, f"shield on, real firmware: the trajectory took it {-c:.3f} m into the rim's r-ball"
        assert cut < 0.05, f"shield on, real firmware: the motors stopped {cut:.3f} m above the floor"
    else:
        assert c < -0.05, "shield off: the trajectory must graze the rim (the test can fail)"
        assert xyz[:, 0].max() > x1 - 0.1  # flown to its end


# --------------------------------------------------------------------------- polycc sim --firmware
@pytest.mark.slow
def test_polycc_sim_firmware_trials(arena, tmp_path, capsys):
    from polycc.cli import main

    out = arena["dir"]
    assert main(["sim", str(out), "--scene", str(arena["scene"]), "--firmware", str(arena["tree"]),
                 "--trials", "2", "--jitter", "0.2"]) == 0
    text = capsys.readouterr().out
    assert "collisions: 0" in text and "success 2/2" in text, text[-2000:]
    assert (out / "trajectories.png").is_file() and (out / "trajectories.npz").is_file()


@pytest.mark.slow
def test_polycc_sim_firmware_with_the_shield(arena, tmp_path, capsys):
    """Regression: `polycc sim --firmware --shield` flew the real firmware without the shield (the firmware
    trials ignored FlightConfig.shield) and then stopped with a TypeError traceback summing the shield
    counters it never read. Now the shield flies (out-of-tree controller, polyccShield.enable from the start
    height) and its logged counters are in the summary."""
    import json

    from polycc.cli import main

    out = tmp_path / "b"
    shutil.copytree(arena["dir"], out)
    assert main(["sim", str(out), "--scene", str(arena["scene"]), "--firmware", str(arena["tree"]), "--shield",
                 "--vmax", "1.0"]) == 0
    text = capsys.readouterr().out
    assert "collisions: 0" in text and "success 1/1" in text, text[-2000:]
    sh = json.loads((out / "sim.json").read_text())["shield"]
    assert sh["decisions"] > 100 and sh["manual"] == 0, sh  # 100 Hz decisions over the flight
    assert sh["decisions_per_s"] >= 90, sh  # the app got its CPU (see the starved-host test below)


@pytest.mark.slow
def test_the_shield_flies_on_a_starved_host(arena, tmp_path):
    """Regression: on a loaded host the shield on the real firmware made 36-61 of its 100 decisions per
    second, its late decisions were flown as brakes and the drone stalled in the first hoop ("stuck", CI's
    flaky failure). The fork's socket reader kept the CPU from the app (polycc_sitl_clock.c explains how).
    Reproduced for sure by one core with a busy loop on it; now the app makes its 100/s there too."""
    import subprocess
    import sys

    # taskset, not a preexec_fn: this worker has threads, and code between fork and exec can deadlock there
    pin = ["taskset", "-c", str(min(os.sched_getaffinity(0)))]
    out = tmp_path / "b"
    shutil.copytree(arena["dir"], out)
    busy = subprocess.Popen([*pin, sys.executable, "-c", "while True: pass"])
    try:
        r = subprocess.run([*pin, sys.executable, "-m", "polycc", "sim", str(out), "--scene", str(arena["scene"]),
                            "--firmware", str(arena["tree"]), "--shield", "--vmax", "1.0"],
                           capture_output=True, text=True, timeout=900)
    finally:
        busy.kill()
        busy.wait(30)
    assert r.returncode == 0 and "success 1/1" in r.stdout, r.stdout[-3000:] + r.stderr[-2000:]
    sh = json.loads((out / "sim.json").read_text())["shield"]
    assert sh["decisions_per_s"] >= 90 and sh["backups"] <= 5, sh


@pytest.mark.slow
def test_a_hung_firmware_is_reported_as_a_stall_with_its_threads(arena, tmp_path, monkeypatch):
    """A cf2 that stops taking ticks (here frozen with SIGSTOP, as the one CI hang looked from outside)
    raises SitlStall within STALL_S wall seconds, naming cf2's thread states, and leaves stall.txt."""
    import signal

    from polycc.sim.firmware import sitl as sitl_mod

    monkeypatch.setattr(sitl_mod, "STALL_S", 2.0)
    with sitl_mod.FirmwareSitl(arena["build"], start=arena["start"], run_dir=tmp_path / "run") as s:
        s.sleep(0.2)  # advancing: no stall
        os.kill(s.fw.pid, signal.SIGSTOP)
        try:
            with pytest.raises(sitl_mod.SitlStall, match=r"stopped advancing .*cf2 threads: \d+ x T"):
                s.wait_until(lambda: False, 60.0)
        finally:
            os.kill(s.fw.pid, signal.SIGCONT)
    text = (tmp_path / "run" / "stall.txt").read_text()
    assert "bridge stats:" in text and "thread " in text


# --------------------------------------------------------------------------- fast vs real
@pytest.mark.slow
def test_fast_shims_agree_with_the_real_firmware(arena):
    from polycc.testing.worlds import FastWorld

    real = run(arena, "full_flight")
    with FastWorld(arena["dir"] / "polytopes.h", arena["start"]) as w:
        fast = fs.SCENARIOS["full_flight"](w.uri, w, arena)
    assert fast["late_share"] == 0.0  # the fast shims run the app on time by construction
    rms = fs.diff_rms(fast, real)
    # Over the bound on a host that starved the firmware (its app woke late on more than STARVED_LATE of its
    # ticks; 2 % on an idle host, 9 % next to two busy loops): that flight is the host's, not the M4's (CI: 6.2 cm
    # while the same host starved the shield to 73 of its 100 decisions/s), so it is flown again, at most twice.
    # The real flight also varies from run to run without starvation (thread timing in the lock-stepped SITL:
    # 4.7, 5.6 and 6.1 cm for the same fast flight at 1.5-1.9 % late, this host and CI), so a first flight over the
    # bound is flown again whatever its late share, a second one only if the host starved it; the bound still holds
    # for the flight that is kept.
    for i in range(2):
        if rms <= DIFF_RMS_M or (i > 0 and real["late_share"] <= STARVED_LATE):
            break
        print(f"full_flight on the real firmware: RMS {rms * 100:.1f} cm with {real['late_share']:.1%} of the app's "
              "ticks late; flying it again")
        with world(arena) as w:
            real = fs.SCENARIOS["full_flight"](w.uri, w, arena)
        rms = fs.diff_rms(fast, real)
    print(f"full_flight: fast vs real firmware RMS {rms * 100:.1f} cm while the app flies, "
          f"{real['late_share']:.1%} of its ticks late")
    assert rms <= DIFF_RMS_M, f"{real['late_share']:.1%} of the app's ticks late"


# Barrier-rate gap grad psi . (v_true - u) (Prop. 1 of seed 001), real firmware against the fast quadrotor
# model on the same flight, m/s. Measured: this test's flight p50 0.0002 apart, p1 0.106 and p99 0.078 apart;
# one bench pair at 2 m/s (shield on) p50 0.015, p1 0.17, p99 0.011 apart; pooled over 21-22 bench pairs per
# speed p50 within 0.003, p1 within 0.14, p99 within 0.06 (the fast model's tails are wider at p1). A gap
# without the command (grad psi . v) is 0.18 m/s off at p50 and 0.64 at p99 on that bench pair.
GAP_P50_M_S = 0.02
GAP_TAIL_M_S = 0.2


@pytest.mark.slow
def test_the_barrier_rate_gap_on_the_real_firmware_agrees_with_the_fast_sim(arena):
    """Regression (issue 18): the firmware trials had no barrier-rate gap, so the bench showed "-" for the
    real firmware. Now each firmware trial has it at every 50 Hz log sample where the app sent its command
    (FirmwareSimulator.rate_gap), and its distribution agrees with the fast quadrotor model's on the same
    flight (its median within GAP_P50_M_S; a gap computed without the command is far from it)."""
    from polycc.sim.firmware.flights import FirmwareSimulator
    from polycc.sim.sitl import FlightConfig, Simulator

    side = json.loads(arena["scene"].with_suffix(".json").read_text())
    start, goal = np.asarray(side["start"], float), np.asarray(side["goal"], float)
    header = arena["dir"] / "polytopes.h"
    sim = Simulator(header)
    fw = FirmwareSimulator(header, arena["tree"], sim.packed, sim.kappa, build=arena["build"])
    cfg = FlightConfig(vmax=1.0)
    real = fw.fly(start, goal, cfg)
    fast = sim.fly(start, goal, "quadrotor", cfg)
    assert real.success and fast.success, (real.outcome, fast.outcome)
    gap = real.rate_gap
    assert len(gap) >= 0.8 * 50 * real.time_s and np.isfinite(gap).all(), (len(gap), real.time_s)
    q = [1, 50, 99]
    diff = np.abs(np.percentile(gap, q) - np.percentile(fast.rate_gap, q))
    print(f"rate gap p1/p50/p99: firmware {np.percentile(gap, q).round(4)}, fast "
          f"{np.percentile(fast.rate_gap, q).round(4)} m/s")
    assert diff[1] <= GAP_P50_M_S and max(diff[0], diff[2]) <= GAP_TAIL_M_S, diff


# --------------------------------------------------------------------------- polycc sim-device --firmware
@pytest.mark.slow
def test_sim_device_firmware_serves_cflib_and_cfclient_and_stops_on_ctrl_c(arena, tmp_path):
    import signal
    import socket
    import subprocess
    import sys

    from polycc.link.cflib_tools import close_without_stop, connect
    from polycc.testing.cfclient_connect import free_scan_port, run_cfclient

    port = free_scan_port()  # cfclient's scan only looks at 19850..19859
    cmd = [sys.executable, "-m", "polycc", "sim-device", str(arena["dir"]), "--firmware", str(arena["tree"]),
           "--udp", f"127.0.0.1:{port}"]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    lines = []
    try:
        for line in proc.stdout:
            lines.append(line)
            if line.startswith("URI: "):
                break
        uri = lines[-1].split()[1]
        assert uri == f"udp://127.0.0.1:{port}", "".join(lines)
        scf = connect(uri, 90.0)
        try:
            toc = scf.cf.param.toc
            assert toc.get_element_by_complete_name("polycc.enable") is not None
            assert toc.get_element_by_complete_name("kalman.resetEstimation") is not None  # the real firmware's TOC
            assert int(scf.cf.param.get_value("polycc.enable")) == 0
        finally:
            close_without_stop(scf)
        # cfclient as a user runs it: scan, pick the URI, Connect; its tabs run on the firmware's full TOC.
        # The SITL fork builds no power management (pm_stm32f4.c), so there is no pm.vbat for cfclient's
        # battery log (it warns and goes on, as it would on such a firmware); its other tabs must run cleanly.
        res = run_cfclient(uri, tmp_path, seconds=8.0)
        assert res["connected"] and res["still_connected"], json.dumps(res)
        assert res["errors"] == [], "\n".join(res["errors"])
        assert res["params"] >= 20 and (res["battery_v"] is not None or not res["has_vbat"]), json.dumps(res)
    finally:
        proc.send_signal(signal.SIGINT)
        rest, _ = proc.communicate(timeout=60)
    assert proc.returncode == 0, "".join(lines) + rest
    assert "ports freed" in rest
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", port))  # freed


@pytest.mark.slow
def test_p2p_radio_on_the_real_firmware(arena):
    """Differential test of the host radio shim (polycc/sim/shims/sim_radiolink.c, which
    tests/sim/test_swarm_p2p.py drives) against the real firmware's P2P path (the SITL build's radiolink.h
    calls, the real CRTP RX task), through the air hub: with polycc.swarmId = 5 the firmware broadcasts the
    same 18-byte record the shim does (id, stated age, radius in mm exactly; position = its estimate, within
    5 cm of the truth on the floor) every p2pMs; a record heard enters the table (nNbr, p2pRx); the own id
    and "forget" are refused and counted (p2pDrop) exactly as on the host; another port is ignored."""
    import socket
    import struct
    import time

    from cflib.crazyflie.log import LogConfig

    from polycc.link.cflib_tools import close_without_stop, set_param
    from polycc.onboard.app import NBR_FORMAT, NBR_MAGIC, P2P_PORT, pack_forget, pack_neighbour
    from polycc.sim.firmware.air import P2PAir
    from polycc.sim.firmware.bridge import AIR_HELLO, AIR_STAMP, P2P_CRTP_PORT
    from polycc.testing.worlds import FirmwareWorld

    hdr = bytes([P2P_CRTP_PORT << 4])
    with P2PAir() as air, socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as ear:
        ear.bind(("127.0.0.1", 0))
        ear.settimeout(10.0)
        ear.sendto(AIR_HELLO, air.address)
        with FirmwareWorld(arena["dir"] / "polytopes.h", arena["start"], cf2=arena["build"],
                           bridge_args=["--air", air.arg]) as w:
            scf = _connect(w)
            try:
                latest: dict = {}
                lc = LogConfig(name="p2p", period_in_ms=50)
                for n in ("polycc.nNbr", "polycc.p2pRx", "polycc.p2pTx", "polycc.p2pDrop"):
                    lc.add_variable(n, scf.cf.log.toc.get_element_by_complete_name(n).ctype)
                lc.data_received_cb.add_callback(lambda ts, data, conf: latest.update(data))
                scf.cf.log.add_config(lc)
                lc.start()
                for name, v in (("radius", 0.1), ("p2pAgeMs", 20), ("p2pMs", 50), ("swarmId", 5)):
                    set_param(scf.cf, f"polycc.{name}", v)
                heard, t_end = [], time.monotonic() + 60.0
                while len(heard) < 10 and time.monotonic() < t_end:
                    data, _ = ear.recvfrom(64)
                    assert data[:1] == AIR_STAMP  # the sender's simulated time, then the packet
                    heard.append(data[9:])
                truth = w.truth()[0]
                assert len(heard) == 10
                for d in heard:
                    assert d[:2] == hdr + bytes([P2P_PORT]) and len(d) == 20
                    magic, nid, x, y, z, age, rmm = struct.unpack(NBR_FORMAT, d[2:])
                    assert (magic, nid, age, rmm) == (NBR_MAGIC, 5, 20, 100)
                    assert np.linalg.norm(np.array([x, y, z]) - truth) < 0.05
                    assert d[2:] == pack_neighbour(5, [x, y, z], 20, 0.1)  # byte for byte the host's record

                def hear(rec: bytes, port: int = P2P_PORT) -> None:
                    ear.sendto(hdr + bytes([port]) + rec, air.address)

                def logs(*keys) -> tuple:
                    return tuple(latest.get(f"polycc.{k}") for k in keys)

                def heard_once_more(rec: bytes, counter: str, **same) -> None:
                    """Send ``rec`` until ``counter`` rises; the other logged counters stay ``same``. A P2P
                    broadcast is unacknowledged on the nRF too, and one record in ~700 CI runs was lost on the
                    way (host UDP, the firmware's 5-deep CRTP RX queue): what is tested is what a record that
                    arrives does, so a lost one is sent again; a late duplicate only raises ``counter`` more."""
                    base = latest.get(f"polycc.{counter}")
                    for _ in range(5):
                        hear(rec)
                        if w.wait_until(lambda: latest.get(f"polycc.{counter}") != base, 2.0):
                            break
                    w.sleep(0.3)  # a log period or more after the change: the other counters are current
                    assert latest.get(f"polycc.{counter}") > base, (counter, latest)
                    assert logs(*same) == tuple(same.values()), (same, latest)

                assert w.wait_until(lambda: logs("nNbr", "p2pRx", "p2pDrop") == (0, 0, 0), 10.0), latest
                nb = np.asarray(truth) + np.array([1.0, 0.0, 0.5])
                heard_once_more(pack_neighbour(9, nb, 10, 0.1), "p2pRx", nNbr=1, p2pDrop=0)
                rx = latest["polycc.p2pRx"]
                heard_once_more(pack_neighbour(5, nb, 10, 0.1), "p2pDrop", nNbr=1, p2pRx=rx)  # own id
                drop = latest["polycc.p2pDrop"]
                heard_once_more(pack_forget(9), "p2pDrop", nNbr=1, p2pRx=rx)  # a P2P record never removes one
                drop2 = latest["polycc.p2pDrop"]
                assert drop2 > drop >= 1
                for _ in range(3):  # another app's P2P port: however many arrive, none is counted
                    hear(pack_neighbour(10, nb, 10, 0.1), port=P2P_PORT + 1)
                w.sleep(1.0)  # the packets on the other port have long been handled: still not counted
                assert logs("nNbr", "p2pRx", "p2pDrop") == (1, rx, drop2), latest
                assert latest["polycc.p2pTx"] >= 10
                lc.stop()
            finally:
                close_without_stop(scf)
        assert air.stats["from_unknown"] == 0
