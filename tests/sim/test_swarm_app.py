"""The app's swarm hook (polycc_app.c, `swarm:`): neighbour reports over the app channel enter the
barrier (bit-exact with polycc/onboard/swarm.py), age with the app's clock, stop the drone short of a
neighbour, and a silent neighbour makes it hold (status 13)."""

from __future__ import annotations

import numpy as np
import pytest

from polycc.codegen.header import write_outputs
from polycc.geometry.halfplanes import axis_box
from polycc.onboard import swarm as SW
from polycc.onboard.app import pack_forget, pack_neighbour
from polycc.onboard.barrier import Params
from polycc.sim.app_ffi import AppSim


@pytest.fixture(scope="module")
def app(tmp_path_factory) -> AppSim:
    d = tmp_path_factory.mktemp("scene")
    write_outputs(d, [axis_box([0, 0, 0], [1, 1, 1])], {"kappa": 100.0})
    return AppSim(d / "polytopes.h")


def _start(app, x):
    app.reset()
    app.airborne(x)
    app.set_estimate(x)
    for n, v in zip(("goalX", "goalY", "goalZ"), (4.0, 3.0, 1.0)):
        app.set_param("polycc", n, v)
    app.set_param("polycc", "enable", 1)


def _push(app, data: bytes):
    assert app.lib.shim_appchannel_push(data, len(data)) == 0


def test_report_enters_the_barrier_bit_exactly(app):
    x = np.array([2.0, 2.0, 1.0], np.float32)
    _start(app, x)
    nb = np.array([2.6, 2.3, 1.0], np.float32)
    _push(app, pack_neighbour(7, nb, 20, 0.1))
    period = app.tick(0)
    assert app.get_log("polycc", "nNbr") == 1
    tr = app.trace()
    ref = SW.Swarm()
    ref.report(7, nb, 20 + 1, 0.1, x)  # + the period the report may have waited in the queue (1 ms before the first)
    packed = app.packed_scene()
    params = Params(kappa=100.0, radius=float(tr.params.radius), beta=float(tr.params.beta),
                    c_clf=float(tr.params.c_clf), v_max=float(tr.params.v_max))
    want = SW.step(packed, params, ref, 1.0, x, np.array([4.0, 3.0, 1.0], np.float32))
    got_u = np.array(list(tr.out.u), np.float32)
    assert np.array_equal(got_u.view(np.uint32), want["u"].view(np.uint32))
    assert np.float32(tr.out.psi).view(np.uint32) == want["psi"].view(np.uint32)
    # one period later the report is older by exactly the period (and the speed limit is the braking term's of
    # the first tick's psi: the first tick of an engagement flies at most 0.05 m/s)
    app.tick(period)
    ref.age(period)
    tr = app.trace()
    params = Params(kappa=100.0, radius=float(tr.params.radius), beta=float(tr.params.beta),
                    c_clf=float(tr.params.c_clf), v_max=float(tr.params.v_max))
    want = SW.step(packed, params, ref, 1.0, x, np.array([4.0, 3.0, 1.0], np.float32))
    assert np.float32(tr.out.psi).view(np.uint32) == want["psi"].view(np.uint32)
    assert np.array_equal(np.array(list(tr.out.u), np.float32).view(np.uint32), want["u"].view(np.uint32))
    assert want["flags"] & 1  # the neighbour changed the command


def test_drone_stops_short_of_a_hovering_neighbour(app):
    """Integrating the app's own commands (single integrator), the drone flying at a neighbour that
    reports every 50 ms stays at least r_i + r_j = 0.2 m away."""
    x = np.array([0.5, 2.0, 1.5], np.float64)
    nb = np.array([2.5, 2.0, 1.5], np.float32)
    _start(app, x)
    for n, v in zip(("goalX", "goalY", "goalZ"), nb):
        app.set_param("polycc", n, float(v))  # its goal is the neighbour itself
    t, dmin = 0, 1e9
    while t < 8000:
        if t % 50 == 0:
            _push(app, pack_neighbour(1, nb, 5, 0.1))
        app.set_estimate(x.astype(np.float32))
        p = app.tick(t)
        u = np.array(app.commander().velocity, np.float64)
        x = x + u * p * 1e-3
        t += p
        dmin = min(dmin, float(np.linalg.norm(x - nb)))
    assert 0.2 <= dmin < 0.35  # close (the fair half of the gap and the buffer), never closer than the radii


def test_silent_neighbour_holds_position(app):
    x = np.array([2.0, 2.0, 1.0], np.float32)
    _start(app, x)
    _push(app, pack_neighbour(3, [3.5, 2.0, 1.0], 0, 0.1))
    t = 0

    def run(until):
        nonlocal t
        while t <= until:
            app.set_estimate(x + np.float32(1e-6 * (t % 7)))  # a live estimate (never bit-identical for 250 ms)
            t += app.tick(t)

    run(480)
    assert app.get_log("polycc", "status") == 1
    run(600)
    assert app.get_log("polycc", "status") == 13  # older than 500 ms
    rec = app.commander()
    assert rec.modes[0] == 1  # modeAbs: holding the position
    _push(app, pack_neighbour(3, [3.5, 2.0, 1.0], 0, 0.1))
    app.tick(t)
    assert app.get_log("polycc", "status") == 1
    _push(app, pack_forget(3))  # the ground drops it (landed): no hold when it goes silent
    run(t + 700)
    assert app.get_log("polycc", "nNbr") == 0 and app.get_log("polycc", "status") == 1


@pytest.mark.parametrize("size", [2, 18, 30, 31])
def test_no_reply_exceeds_the_crtp_payload(app, size):
    """Regression: the reply to an 18-byte neighbour report was 18 + 13 = 31 bytes, sized by APPCHANNEL_MTU,
    which is 31 in the CrazySim fork and the firmware of its time; crtpSendPacketBlock() ASSERTs size <= 30
    and assertFail() stops the motors. Found flying `polycc swarm-sim --firmware`: every drone's firmware
    froze in the air. The shim models that firmware (MTU 31) and its assert (motors off)."""
    x = np.array([2.0, 2.0, 1.0], np.float32)
    _start(app, x)
    data = pack_neighbour(3, [2.6, 2.3, 1.0], 20, 0.1) if size == 18 else bytes(range(1, size + 1))
    _push(app, data)
    app.tick(0)
    buf = app.ffi.new("unsigned char[64]")
    n = app.lib.shim_appchannel_pop(buf, 64)
    assert 18 <= n <= 30 and app.lib.shim_crtp_asserts() == 0
    assert bytes(buf[18:n]) == data[: n - 18]  # the echo: the first bytes of the request
