"""The app's behaviour through the host shims: TOCs, parameters, setpoints, safe behaviour."""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np
import pytest

from polycc.codegen.header import write_outputs
from polycc.geometry.halfplanes import axis_box
from polycc.onboard import app as onboard_app
from polycc.onboard.app import STATUS_NAMES, app_rate_hz
from polycc.sim.app_ffi import SRC, AppSim

LOG_VARS = [("psi", 7), ("ux", 7), ("uy", 7), ("uz", 7), ("active", 1), ("evalUs", 3), ("status", 1), ("rate", 2),
            ("late", 3), ("nNbr", 1), ("p2pRx", 2), ("p2pTx", 2), ("p2pDrop", 2),
            ("radius", 7)]
# PARAM_UINT8 = 0x08, PARAM_FLOAT = 0x06, PARAM_UINT16 = 0x09
PARAMS = [("enable", 0x08), ("goalX", 0x06), ("goalY", 0x06), ("goalZ", 0x06), ("vmax", 0x06), ("beta", 0x06),
          ("clfGain", 0x06), ("radius", 0x06), ("rateHz", 0x09), ("swarmV", 0x06), ("swarmN", 0x08),
          ("swarmId", 0x08), ("p2pMs", 0x09), ("p2pAgeMs", 0x09)]


@pytest.fixture(scope="module")
def app(tmp_path_factory) -> AppSim:
    d = tmp_path_factory.mktemp("scene")
    write_outputs(d, [axis_box([0, 0, 0], [1, 1, 1]), axis_box([2, 0, 0], [3, 1, 2])], {"kappa": 100.0})
    return AppSim(d / "polytopes.h")


@pytest.fixture
def fresh(app):
    app.reset()
    return app


def _enable(app, goal=(4.0, 0.5, 0.5), airborne=(-1.0, 0.5, 0.5)):
    if airborne is not None:
        app.airborne(airborne)
    for n, v in zip(("goalX", "goalY", "goalZ"), goal):
        app.set_param("polycc", n, v)
    app.set_param("polycc", "enable", 1)


def header_defines(path: Path) -> dict[str, str]:
    return dict(re.findall(r"#define\s+(POLYCC_\w+)\s+(\S+)", path.read_text()))


def test_log_and_param_tocs(fresh):
    logs = [e for e in fresh.log_toc() if e.group == "polycc"]
    assert [(e.name, e.type) for e in logs] == LOG_VARS
    pars = [e for e in fresh.param_toc() if e.group == "polycc"]
    assert [(e.name, e.type) for e in pars] == PARAMS
    assert [e.size for e in pars] == [1, 4, 4, 4, 4, 4, 4, 4, 2, 4, 1, 1, 2, 2]
    # The simulated estimate is in the log TOC like the firmware's core variables (LOG_CORE = 0x20).
    est = {e.name: e for e in fresh.log_toc() if e.group == "stateEstimate"}
    assert {"x", "y", "z"} <= set(est) and est["x"].type == 0x20 | 7
    # Indices are the logVarId_t values, groups sorted by name.
    toc = fresh.log_toc()
    assert [e.index for e in toc] == list(range(len(toc)))
    assert [e.group for e in toc] == sorted(e.group for e in toc)


def test_defaults_and_status_codes_match_header(fresh):
    d = header_defines(SRC / "polycc_app.h")
    assert fresh.get_param("polycc", "rateHz") == int(d["POLYCC_APP_DEFAULT_RATE_HZ"].rstrip("u"))
    assert fresh.get_param("polycc", "enable") == 0
    assert math.isclose(fresh.get_param("polycc", "vmax"), float(d["POLYCC_APP_DEFAULT_VMAX"].rstrip("f")))
    codes = {int(v.rstrip("u")): k for k, v in d.items() if k.startswith("POLYCC_STATUS_")}
    assert sorted(codes) == sorted(STATUS_NAMES)
    for name in ("DEFAULT_RATE_HZ", "MIN_RATE_HZ", "CPU_HZ", "CPU_SHARE_PERCENT"):
        assert int(d["POLYCC_APP_" + name].split()[0].rstrip("u")) == getattr(onboard_app, name), name
    for name in ("P2P_PORT", "P2P_RING"):
        assert int(d["POLYCC_APP_" + name].rstrip("u"), 0) == getattr(onboard_app, name), name
    assert fresh.get_param("polycc", "p2pMs") == int(d["POLYCC_APP_DEFAULT_P2P_MS"].rstrip("u"))
    assert fresh.get_param("polycc", "p2pAgeMs") == int(d["POLYCC_APP_DEFAULT_P2P_AGE_MS"].rstrip("u"))
    assert fresh.get_param("polycc", "swarmId") == 0 and fresh.get_param("polycc", "swarmN") == 0
    assert fresh.kappa == 100.0 and fresh.n_polys == 2


def test_disabled_sends_nothing(fresh):
    fresh.set_estimate((-1.0, 0.5, 0.5))
    for k in range(10):
        assert fresh.tick(2 * k) == 2
    assert fresh.commander().count == 0
    assert fresh.get_log("polycc", "status") == 0


def test_enabled_streams_world_velocity_setpoints(fresh):
    _enable(fresh)
    fresh.set_estimate((-1.0, 0.5, 0.5))
    for k in range(5):
        assert fresh.tick(2 * k, usec=2000 * k, section_us=17) == 2
        rec = fresh.commander()
        assert rec.count == k + 1 and rec.tick == 2 * k
    assert rec.priority == 3  # COMMANDER_PRIORITY_EXTRX: ground setpoints are ignored while the app flies
    assert rec.modes[:3] == (2, 2, 2) and rec.modes[5] == 2  # modeVelocity for x, y, z and yaw (rate)
    assert rec.modes[3:5] == (0, 0) and not rec.velocity_body and rec.yaw_rate == 0.0
    assert rec.velocity[0] > 0.0  # towards the goal at +x
    assert fresh.get_log("polycc", "status") == 1 and fresh.get_log("polycc", "evalUs") == 17
    for n, v in zip(("ux", "uy", "uz"), rec.velocity):
        assert fresh.get_log("polycc", n) == v


@pytest.mark.parametrize("rate,period", [(500, 2), (250, 4), (1000, 1), (167, 6), (100, 10), (1, 100), (0, 100)])
def test_rate_param_sets_period_and_keeps_watchdog_fed(fresh, rate, period):
    _enable(fresh)
    fresh.set_param("polycc", "rateHz", rate)
    fresh.set_estimate((-1.0, 0.5, 0.5))
    assert fresh.tick(0) == period
    assert period <= 100  # setpoints at least every 100 ms: the 500 ms watchdog never fires


def test_disable_hands_over_to_the_high_level_commander_once(fresh):
    """Disabling in the air: one go_to to the stopping point (the high-level commander holds), one
    relax, and never a stop setpoint."""
    _enable(fresh)
    fresh.set_estimate((-1.0, 0.5, 0.5))
    fresh.tick(0)
    fresh.set_param("polycc", "enable", 0)
    for k in range(1, 5):
        fresh.tick(2 * k)
    rec = fresh.commander()
    assert rec.relax_count == 1 and rec.active_priority == 1 and rec.count == 1
    assert rec.hl_gotos == 1 and rec.hl_state == 1  # flying: holding the position
    tr = fresh.trace()
    assert np.allclose(list(tr.handover)[:3], (-1.0, 0.5, 0.5), atol=1e-6) and tr.handover[3] >= 0.5
    assert fresh.get_log("polycc", "status") == 0


def test_a_land_sent_right_after_disable_is_kept(fresh):
    """Regression (README example): `enable = 0` then an HL land before the app's next tick; the
    hand-over must not replace the user's landing with its hold go_to."""
    _enable(fresh)
    fresh.set_estimate((-1.0, 0.5, 0.5))
    fresh.tick(0)
    fresh.set_param("polycc", "enable", 0)
    assert fresh.lib.crtpCommanderHighLevelLand(0.0, 2.0) == 0
    for k in range(1, 5):
        fresh.tick(2 * k)
    rec = fresh.commander()
    assert rec.hl_gotos == 0 and rec.hl_lands == 1 and rec.hl_state == 2  # landing
    assert rec.relax_count == 1 and rec.active_priority == 1
    assert fresh.get_log("polycc", "status") == 0


@pytest.mark.parametrize("when", ["settling", "settled", "no_settle"])
def test_a_land_that_arrives_inside_the_hand_over_is_kept(fresh, when):
    """Regression (issue 18, a real-firmware bench flight that hovered at 1.6 m after its land): the
    high-level commander's task carries out a land as soon as it preempts the app. One that came between the
    hand-over's check of the planner and its next send was lost: the hold setpoint stopped the planner, or the
    go_to replaced the land. The shim delivers the land at exactly that instant (shim_hl_queue_land); the app
    runs its hand-over above that task, so the land waits until the step is done and the next tick lets go.
    settling: during the settling hold (posCtl.Zi wound up); settled: at the tick whose go_to ends the settle;
    no_settle: at the first hand-over tick, whose go_to hands over at once."""
    lib = fresh.lib
    _enable(fresh)
    fresh.set_estimate((-1.0, 0.5, 0.5))
    lib.shim_set_position_integrator(0.0 if when == "no_settle" else 0.3)
    fresh.tick(0)
    fresh.set_param("polycc", "enable", 0)
    k = 1
    if when != "no_settle":
        for k in range(1, 4):  # the settling hold (status 14)
            fresh.tick(2 * k)
            assert fresh.get_log("polycc", "status") == 14
        if when == "settled":
            lib.shim_set_position_integrator(0.0)  # decayed: this tick's go_to ends the settle
        k += 1
    lib.shim_hl_queue_land(0.0, 3.0)
    fresh.tick(2 * k)
    lib.shim_hl_run_pending()  # the app's task sleeps: a land still queued is carried out now
    for j in range(k + 1, k + 4):
        fresh.tick(2 * j)
    rec = fresh.commander()
    assert rec.hl_lands == 1 and rec.hl_state == 2, (rec.hl_state, rec.hl_gotos)  # landing, not holding
    assert rec.relax_count == 1 and rec.active_priority == 1
    assert fresh.get_log("polycc", "status") == 0


def test_enabled_on_the_ground_sends_nothing(fresh):
    _enable(fresh, airborne=None)
    fresh.set_estimate((-1.0, 0.5, 0.0))
    for k in range(10):
        fresh.tick(2 * k)
    assert fresh.commander().count == 0 and fresh.get_log("polycc", "status") == 7  # take off first


def test_unsupported_controller_is_refused(fresh):
    fresh.lib.shim_set_controller(2)  # Mellinger
    _enable(fresh)
    fresh.set_estimate((-1.0, 0.5, 0.5))
    fresh.tick(0)
    assert fresh.commander().count == 0 and fresh.get_log("polycc", "status") == 9


def test_the_worst_case_lowers_the_rate(tmp_path):
    """A scene whose certified worst case does not fit half a 2 ms tick runs at a lower rate."""
    write_outputs(tmp_path, [axis_box([0, 0, 0], [1, 1, 1])], {"kappa": 100.0, "worst_cycles": 400_000})
    app = AppSim(tmp_path / "polytopes.h")
    app.reset()
    _enable(app)
    app.set_estimate((-1.0, 0.5, 0.5))
    period = app.tick(0)
    assert period == 5 and app.get_log("polycc", "rate") == 200  # 400k cycles = 2.4 ms <= half of 5 ms
    assert app_rate_hz(400_000) == 200  # what `polycc build` prints
    app.reset()


@pytest.mark.parametrize("worst,requested", [(1_000, 500), (200_000, 500), (400_000, 1000), (1_000, 37),
                                             (8_000_000, 500), (8_500_000, 500)])
def test_the_printed_rate_is_the_apps(tmp_path, worst, requested):
    """polycc.onboard.app.app_rate_hz (printed by `polycc build`) is the rate the app runs at."""
    write_outputs(tmp_path, [axis_box([0, 0, 0], [1, 1, 1])], {"kappa": 100.0, "worst_cycles": worst})
    app = AppSim(tmp_path / "polytopes.h")
    app.reset()
    app.set_param("polycc", "rateHz", requested)
    _enable(app)
    app.set_estimate((-1.0, 0.5, 0.5))
    app.tick(0)
    expect = app_rate_hz(worst, requested)
    if expect is None:
        assert app.get_log("polycc", "status") == 12
    else:
        assert app.get_log("polycc", "rate") == expect
    app.reset()


@pytest.mark.parametrize("case", ["nan", "inf", "far", "variance", "inside", "bad_param"])
def test_unsafe_inputs_hold_the_position(fresh, case):
    _enable(fresh)
    x = (-1.0, 0.5, 0.5)
    expect = {"nan": 3, "inf": 3, "far": 3, "variance": 3, "inside": 5, "bad_param": 6}[case]
    if case == "nan":
        x = (math.nan, 0.5, 0.5)
    elif case == "inf":
        x = (0.0, math.inf, 0.5)
    elif case == "far":
        x = (0.0, 0.0, 2000.0)
    elif case == "inside":
        x = (0.3, 0.45, 0.8)  # inside the first box, off its centre (where grad psi = 0)
    elif case == "bad_param":
        fresh.set_param("polycc", "vmax", 0.0)
    if case in ("nan", "inf", "far", "variance"):  # a good estimate first: the hold is where it was
        fresh.set_estimate((-1.0, 0.5, 0.5))
        fresh.tick(0)
        x0 = (-1.0, 0.5, 0.5)
    else:
        x0 = x
    if case == "variance":
        fresh.set_position_variance((0.02, 1e-4, 1e-4))
    fresh.set_estimate(x)
    fresh.tick(2)
    rec = fresh.commander()
    assert rec.modes[:3] == (1, 1, 1) and rec.position == pytest.approx(x0, abs=1e-6)  # position hold
    assert fresh.get_log("polycc", "status") == expect
    assert fresh.get_log("polycc", "active") == 0


def test_stale_estimate_hovers_until_it_moves(fresh):
    _enable(fresh)
    fresh.set_estimate((-1.0, 0.5, 0.5))
    statuses = []
    for k in range(200):
        fresh.tick(2 * k)
        statuses.append(fresh.get_log("polycc", "status"))
    stale_from = statuses.index(4)
    assert stale_from * 2 == 250  # POLYCC_APP_STALE_MS of identical bits
    assert all(s == 4 for s in statuses[stale_from:]) and fresh.commander().modes[:3] == (1, 1, 1)
    fresh.set_estimate((-1.0, 0.5, 0.50001))
    fresh.tick(400)
    assert fresh.get_log("polycc", "status") == 1


def test_missing_estimator_variables(app):
    app.lib.shim_reset()
    app.lib.shim_set_kalman_present(0)  # another estimator: the variance check is skipped
    app.lib.polycc_app_init()
    _enable(app)
    app.set_position_variance((5.0, 5.0, 5.0))
    app.set_estimate((-1.0, 0.5, 0.5))
    app.tick(0)
    assert app.get_log("polycc", "status") == 1
    app.lib.shim_reset()
    app.lib.shim_set_estimate_present(0)
    app.lib.polycc_app_init()
    _enable(app)
    app.tick(0)
    assert app.get_log("polycc", "status") == 2 and app.commander().count == 0  # nothing to hold: nothing sent
    app.reset()


def test_param_writes_convert_types(fresh):
    fresh.set_param("polycc", "rateHz", 70000)  # clamped to uint16
    assert fresh.get_param("polycc", "rateHz") == 65535
    fresh.set_param("polycc", "enable", 2.7)
    assert fresh.get_param("polycc", "enable") == 2
    fresh.set_param("polycc", "vmax", 0.1)
    assert fresh.get_param("polycc", "vmax") == float(np.float32(0.1))
    with pytest.raises(Exception, match="no parameter"):
        fresh.set_param("polycc", "nope", 1)


def test_broken_header_gives_a_one_line_error(tmp_path):
    """A header that does not compile with the app is reported with the compiler's first error."""
    from polycc.errors import PolyccError

    write_outputs(tmp_path, [axis_box([0, 0, 0], [1, 1, 1])], {"kappa": 100.0})
    h = tmp_path / "polytopes.h"
    h.write_text(h.read_text().replace("#define POLYCC_SCENE_N_POLYS", "#define POLYCC_SCENE_N_POLYS oops +"))
    with pytest.raises(PolyccError, match=r"building the host app with .*polytopes.h failed: .*error"):
        AppSim(h)


KEEP = float(np.float32(0.1) + np.float32(0.05))  # polyccShield.radius + tube, as the C adds them


def _radius_ticks(app, app_r, shield, at, ticks=3):
    _enable(app, airborne=at)
    app.set_param("polycc", "radius", app_r)
    app.set_param("polyccShield", "radius", 0.1)
    app.set_param("polyccShield", "enable", int(shield))
    app.set_estimate(at)
    out = []
    for k in range(ticks):
        app.tick(2 * k)
        out.append((app.get_log("polycc", "radius"), app.get_log("polycc", "status"), app.get_log("polycc", "psi")))
    return out


@pytest.mark.parametrize("app_r,shield,want", [(0.1, False, 0.1), (0.1, True, KEEP), (0.3, True, 0.3),
                                               (0.0, True, KEEP)])
def test_the_app_keeps_out_of_the_shields_margin(fresh, app_r, shield, want):
    """With the shield on, the go-to-goal app flies with the shield's keep-out (polyccShield.radius + tube,
    0.1 + 0.05 m) once the clearance allows: with polycc.radius below it, the app's own filter drove into the
    shield's margin and was braked there. The first tick of an engagement flies polycc.radius (no clearance
    known yet); the psi it then flies on is the kernel's at the keep-out (the kernel subtracts the radius)."""
    at = (1.5, 0.5, 0.5)  # between the two boxes, 0.5 m from each
    got = _radius_ticks(fresh, app_r, shield, at)
    assert [np.float32(r) for r, _, _ in got] == [np.float32(app_r), np.float32(want), np.float32(want)]
    fresh.reset()
    ref = _radius_ticks(fresh, want, False, at)
    assert got[-1][2] == ref[-1][2]  # the same psi as flying polycc.radius = the keep-out


def test_a_start_inside_the_shields_margin_flies_and_the_radius_rises_as_it_leaves(fresh):
    """0.12 m from the box (inside the 0.15 m keep-out, outside polycc.radius 0.1 m): the app flies (not the
    psi < 0 hold it would be at the keep-out) with polycc.radius; the radius rises with the clearance, 2 cm
    behind it, up to the keep-out, and never shrinks within the engagement (a jump back in is held, as any
    psi < 0)."""
    at = (1.12, 0.5, 0.5)  # box [0, 1]^3: 0.12 m from its x = 1 face
    got = _radius_ticks(fresh, 0.1, True, at)
    assert all(st == 1 and r == np.float32(0.1) and psi > 0 for r, st, psi in got), got
    fresh.set_estimate((1.16, 0.5, 0.5))  # 0.16 m: the radius rises to the clearance less the 2 cm slack
    for k in range(3, 6):
        fresh.tick(2 * k)
    r = fresh.get_log("polycc", "radius")
    assert 0.1 < r <= 0.16 - 0.02 and fresh.get_log("polycc", "status") == 1
    fresh.set_estimate((1.12, 0.5, 0.5))  # back in: the radius does not shrink, so the vehicle is held
    fresh.tick(12)
    assert fresh.get_log("polycc", "radius") == r and fresh.get_log("polycc", "psi") < 0
    fresh.set_estimate((1.19, 0.5, 0.5))  # 0.19 m >= 0.15 + 0.02: the keep-out
    for k in range(7, 10):
        fresh.tick(2 * k)
    assert fresh.get_log("polycc", "radius") == np.float32(KEEP) and fresh.get_log("polycc", "status") == 1
