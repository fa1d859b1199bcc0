"""The app's P2P relay (polycc_app.c `onP2p`, `drainP2p`, `broadcastP2p`; docs/swarm.md): the own estimate
broadcast as the 18-byte neighbour record on P2P port 0x0B, records heard entering the barrier bit-exactly
with their arrival age, everything refused counted (never silently dropped), and `polycc.swarmN` holding a
drone that has not heard every neighbour. The host radio is polycc/sim/shims/sim_radiolink.c; the real
radio path is tested against the real firmware in tests/sim/test_swarm_firmware.py."""

from __future__ import annotations

import struct

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from polycc.codegen.header import write_outputs
from polycc.geometry.halfplanes import axis_box
from polycc.onboard import swarm as SW
from polycc.onboard.app import NBR_FORMAT, NBR_MAGIC, P2P_PORT, P2P_RING, pack_forget, pack_neighbour
from polycc.onboard.barrier import Params
from polycc.sim.app_ffi import AppSim
from polycc.sim.firmware.bridge import P2P_CRTP_PORT


@pytest.fixture(scope="module")
def app(tmp_path_factory) -> AppSim:
    d = tmp_path_factory.mktemp("scene")
    write_outputs(d, [axis_box([0, 0, 0], [1, 1, 1])], {"kappa": 100.0})
    return AppSim(d / "polytopes.h")


def _start(app, x, enable=True, **params):
    app.reset()
    app.airborne(x)
    app.set_estimate(x)
    for n, v in zip(("goalX", "goalY", "goalZ"), (4.0, 3.0, 1.0)):
        app.set_param("polycc", n, v)
    for n, v in params.items():
        app.set_param("polycc", n, v)
    if enable:
        app.set_param("polycc", "enable", 1)


def _hear(app, record: bytes, port: int = P2P_PORT, tick: int | None = None) -> None:
    if tick is not None:
        app.lib.shim_set_tick(tick)  # the radio task stamps the arrival with the tick count
    raw = bytes([port]) + record
    assert app.lib.shim_p2p_deliver(raw, len(raw), 40) == 0


def _sent(app) -> list[bytes]:
    buf, out = app.ffi.new("unsigned char[64]"), []
    while (n := app.lib.shim_p2p_pop(buf, 64)) > 0:
        out.append(bytes(buf[0:n]))
    return out


def test_crtp_port_of_the_sitl_fix_matches_the_bridge():
    from polycc.sim.firmware.build import FIXES_SOURCE

    assert f"#define POLYCC_SITL_P2P_CRTP_PORT 0x{P2P_CRTP_PORT:02X}" in FIXES_SOURCE.read_text()


def test_broadcast_is_the_neighbour_record(app):
    x = np.array([2.0, 2.5, 1.25], np.float32)
    _start(app, x, enable=False, swarmId=3, p2pMs=50, p2pAgeMs=20, radius=0.1)
    t, sent = 0, []
    while t <= 500:
        t += app.tick(t)
        sent += _sent(app)
    assert 9 <= len(sent) <= 10 and app.get_log("polycc", "p2pTx") == len(sent)  # 20 Hz, enabled or not
    assert all(s == bytes([P2P_PORT]) + pack_neighbour(3, x, 20, 0.1) for s in sent)
    _start(app, x, enable=False, swarmId=0)  # no id: silent
    for t in range(0, 300, 2):
        app.tick(t)
    assert _sent(app) == [] and app.get_log("polycc", "p2pTx") == 0


@pytest.mark.parametrize("radius", [0.1, 0.1234567, 0.0005, 0.0])
def test_broadcast_radius_is_rounded_up(app, radius):
    _start(app, np.array([2.0, 2.0, 1.0], np.float32), enable=False, swarmId=1, p2pMs=1, radius=radius)
    app.tick(0)
    app.tick(2)
    (s,) = _sent(app)[:1]
    rmm = struct.unpack(NBR_FORMAT, s[1:])[6]
    mm = float(np.float32(radius) * np.float32(1000.0))  # the app's own product, float32 (0.1f: 100.0)
    assert rmm >= mm and rmm - 1 < mm


def test_heard_record_enters_the_barrier_bit_exactly(app):
    x = np.array([2.0, 2.0, 1.0], np.float32)
    _start(app, x)
    nb = np.array([2.6, 2.3, 1.0], np.float32)
    _hear(app, pack_neighbour(7, nb, 20, 0.1), tick=100)
    period = app.tick(130)  # heard 30 ms before the tick: the table holds it 20 + 30 ms old
    assert app.get_log("polycc", "nNbr") == 1 and app.get_log("polycc", "p2pRx") == 1
    ref = SW.Swarm()
    ref.report(7, nb, 20 + 30, 0.1, x)
    for t in (130, 130 + period):  # the second tick: braked by the first tick's psi (the first flies <= 0.05 m/s)
        if t > 130:
            app.tick(t)
            ref.age(period)
        tr = app.trace()
        params = Params(kappa=100.0, radius=float(tr.params.radius), beta=float(tr.params.beta),
                        c_clf=float(tr.params.c_clf), v_max=float(tr.params.v_max))
        want = SW.step(app.packed_scene(), params, ref, 1.0, x, np.array([4.0, 3.0, 1.0], np.float32))
        assert np.array_equal(np.array(list(tr.out.u), np.float32).view(np.uint32), want["u"].view(np.uint32))
        assert np.float32(tr.out.psi).view(np.uint32) == want["psi"].view(np.uint32)
    assert want["flags"] & 1  # the neighbour changed the command


def test_refused_records_are_counted(app):
    x = np.array([2.0, 2.0, 1.0], np.float32)
    _start(app, x, swarmId=4)
    good = pack_neighbour(5, [3.0, 2.0, 1.0], 10, 0.1)
    _hear(app, pack_neighbour(4, [3.0, 2.0, 1.0], 10, 0.1))  # own id
    _hear(app, pack_forget(5))  # a P2P record never removes (or adds) a neighbour
    _hear(app, good[:17])  # short
    _hear(app, bytes([0x41]) + good[1:])  # not a neighbour record
    _hear(app, good, port=P2P_PORT + 1)  # another app's port: not ours, not counted
    app.tick(0)
    assert app.get_log("polycc", "nNbr") == 0 and app.get_log("polycc", "p2pRx") == 0
    assert app.get_log("polycc", "p2pDrop") == 4
    _hear(app, good)
    app.tick(2)
    assert app.get_log("polycc", "nNbr") == 1 and app.get_log("polycc", "p2pRx") == 1


def test_full_ring_drops_and_counts(app):
    x = np.array([2.0, 2.0, 1.0], np.float32)
    _start(app, x)
    for k in range(P2P_RING + 5):  # more than the ring holds between two ticks
        _hear(app, pack_neighbour(1 + k % 4, [3.0, 1.0 + 0.5 * (k % 4), 1.0], 10, 0.1))
    app.tick(0)
    assert app.get_log("polycc", "p2pRx") == P2P_RING and app.get_log("polycc", "p2pDrop") == 5
    assert app.get_log("polycc", "nNbr") == 4
    _hear(app, pack_neighbour(9, [3.0, 3.5, 1.0], 10, 0.1))  # the ring is free again
    app.tick(2)
    assert app.get_log("polycc", "nNbr") == 5


def test_swarm_n_holds_until_every_neighbour_is_heard(app):
    x = np.array([2.0, 2.0, 1.0], np.float32)
    _start(app, x, swarmN=2)
    t = 0
    for _ in range(5):
        t += app.tick(t)
    assert app.get_log("polycc", "status") == 13 and app.commander().modes[0] == 1  # holding its position
    _hear(app, pack_neighbour(1, [3.0, 2.0, 1.0], 10, 0.1), tick=t)
    t += app.tick(t)
    assert app.get_log("polycc", "status") == 13
    _hear(app, pack_neighbour(2, [2.0, 3.0, 1.0], 10, 0.1), tick=t)
    app.tick(t)
    assert app.get_log("polycc", "status") == 1


def test_two_apps_over_the_air_stop_short_of_each_other(tmp_path):
    """Two app instances flying at each other (single integrator), each knowing the other only from its
    P2P broadcasts (popped from one, heard by the other 5 ms later): they stay >= r_i + r_j = 0.2 m apart."""
    from polycc.swarm.instances import drone_apps

    write_outputs(tmp_path, [axis_box([0, 0, 0], [1, 1, 1])], {"kappa": 100.0})
    a, b = drone_apps(tmp_path / "polytopes.h", 2)
    xs = [np.array([0.5, 2.0, 1.5]), np.array([3.5, 2.0, 1.5])]
    for k, (d, x, g) in enumerate(((a, xs[0], xs[1]), (b, xs[1], xs[0]))):
        _start(d, x.astype(np.float32), swarmId=k + 1, swarmN=1, p2pMs=50, p2pAgeMs=10, radius=0.1)
        for n, v in zip(("goalX", "goalY", "goalZ"), g):
            d.set_param("polycc", n, float(v))
    air: list[tuple[int, object, bytes]] = []
    nxt, dmin, held = [0, 0], 1e9, 0
    for t in range(0, 8000):
        for d in (a, b):
            d.lib.shim_set_tick(t)
        for item in [it for it in air if it[0] <= t]:
            air.remove(item)
            assert item[1].lib.shim_p2p_deliver(item[2], len(item[2]), 40) == 0
        for k, (d, other) in enumerate(((a, b), (b, a))):
            if t < nxt[k]:
                continue
            d.set_estimate(xs[k].astype(np.float32))
            p = d.tick(t)
            nxt[k] = t + p
            held += d.get_log("polycc", "status") == 13
            xs[k] = xs[k] + np.array(d.commander().velocity, np.float64) * p * 1e-3
            air += [(t + 5, other, s) for s in _sent(d)]
        dmin = min(dmin, float(np.linalg.norm(xs[0] - xs[1])))
    assert dmin >= 0.2
    assert np.linalg.norm(xs[0] - xs[1]) < 0.5  # they did come close (the goals are each other)
    assert held > 0  # before the first broadcast arrived each held (swarmN = 1)
    for d in (a, b):
        assert d.get_log("polycc", "p2pRx") > 100 and d.get_log("polycc", "p2pDrop") == 0


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.lists(st.one_of(
    st.binary(min_size=0, max_size=29),
    st.tuples(st.integers(0, 255), st.floats(-30, 30, width=32), st.floats(-30, 30, width=32),
              st.floats(allow_nan=True, width=32), st.integers(0, 0xFFFF), st.integers(0, 0xFFFF)).map(
        lambda r: struct.pack(NBR_FORMAT, NBR_MAGIC, *r))), min_size=1, max_size=P2P_RING))
def test_every_heard_record_is_taken_or_counted(app, records):
    """Whatever arrives on the app's P2P port is either in the table or in p2pDrop (nothing silently
    dropped), and what is taken is a well-formed record of another drone that does not say "forget"."""
    x = np.array([2.0, 2.0, 1.0], np.float32)
    _start(app, x, swarmId=200)
    for r in records:
        _hear(app, r)
    app.tick(0)
    rx, drop = app.get_log("polycc", "p2pRx"), app.get_log("polycc", "p2pDrop")
    assert rx + drop == len(records)
    can = [r for r in records if len(r) == 18 and r[0] == NBR_MAGIC and r[1] != 200
           and struct.unpack(NBR_FORMAT, r)[5] != 0xFFFF]
    assert rx <= len(can)
    assert app.get_log("polycc", "nNbr") <= len({r[1] for r in can})


def test_air_hands_each_broadcast_to_every_other_bridge():
    import socket

    from polycc.sim.firmware.air import P2PAir
    from polycc.sim.firmware.bridge import AIR_HELLO

    with P2PAir() as air:
        socks = [socket.socket(socket.AF_INET, socket.SOCK_DGRAM) for _ in range(3)]
        for s in socks:
            s.bind(("127.0.0.1", 0))
            s.settimeout(2.0)
            s.sendto(AIR_HELLO, air.address)
        pkt = bytes([P2P_CRTP_PORT << 4, P2P_PORT]) + pack_neighbour(1, [1.0, 2.0, 3.0], 5, 0.1)
        import time

        time.sleep(0.2)  # the hellos are in
        socks[0].sendto(pkt, air.address)
        assert socks[1].recvfrom(64)[0] == pkt and socks[2].recvfrom(64)[0] == pkt
        socks[0].settimeout(0.3)
        with pytest.raises(socket.timeout):  # not back to the sender
            socks[0].recvfrom(64)
        assert air.stats["packets"] == 1 and air.stats["delivered"] == 2
        for s in socks:
            s.close()


def test_p2p_relay_needs_one_radio_channel():
    from polycc.errors import PolyccError
    from polycc.swarm.fly import check_relay

    assert check_relay(["radio://0/80/2M/E7E7E7E701", "radio://0/80/2M/E7E7E7E702"], "p2p")
    assert not check_relay(["radio://0/80/2M/E7E7E7E701", "radio://0/90/2M/E7E7E7E702"], "ground")
    with pytest.raises(PolyccError, match="different radio channels.*--relay ground"):
        check_relay(["radio://0/80/2M/E7E7E7E701", "radio://1/90/2M/E7E7E7E702"], "p2p")
    with pytest.raises(PolyccError, match="--relay 'air'"):
        check_relay(["radio://0/80/2M/E7E7E7E701"], "air")


def test_cli_refuses_a_relay_that_cannot_work(tmp_path, capsys):
    from polycc.cli import main

    write_outputs(tmp_path, [axis_box([0, 0, 0], [1, 1, 1])], {"kappa": 100.0})
    rc = main(["swarm-fly", str(tmp_path), "--uris", "udp://127.0.0.1:1,udp://127.0.0.1:2", "--relay", "p2p"])
    err = capsys.readouterr().err
    assert rc != 0 and "--relay ground" in err and "Traceback" not in err


def test_bridge_air_is_causal_in_simulated_time():
    """The bridge (no firmware needed) delivers another instance's P2P packet only once its own simulated
    time has reached the sender's stamp, and ages a neighbour record from an instance behind it by the lag,
    rounded up to the ms; "forget" and other apps' packets pass unchanged (regression: on a loaded CI host a
    stalled instance's records arrived seconds late with their original age, and a drone went INSIDE)."""
    import struct

    from polycc.sim.firmware.bridge import AIR_STAMP, Bridge, BridgeConfig

    b = Bridge(BridgeConfig(fw_port=0, cflib_port=0, cflib_host="127.0.0.1"))
    try:
        b.fw_addr, b.calibrated, b.quad.t = ("127.0.0.1", 9), True, 5.0
        hdr = bytes([P2P_CRTP_PORT << 4, P2P_PORT])

        def stamped(t, rec, port_hdr=hdr):
            return AIR_STAMP + struct.pack("<d", t) + port_hdr + rec

        def ages():
            return [struct.unpack(NBR_FORMAT, d[2:])[5] if len(d) == 20 else None for _, d, _retx in b.pending]

        b._handle_air(stamped(4.9, pack_neighbour(1, [1, 2, 3], 20, 0.1)), 0.0)  # 100 ms behind
        assert ages() == [120]
        b._handle_air(stamped(5.25, pack_neighbour(2, [1, 2, 3], 20, 0.1)), 0.0)  # ahead: held
        b._handle_air(stamped(4.0, pack_forget(3)), 0.0)
        b._handle_air(stamped(4.0, pack_neighbour(4, [1, 2, 3], 20, 0.1),
                              bytes([P2P_CRTP_PORT << 4, P2P_PORT + 1])), 0.0)  # another app's record
        b._handle_air(hdr + pack_neighbour(5, [1, 2, 3], 20, 0.1), 0.0)  # no stamp: as it is
        assert ages() == [120, 0xFFFF, 20, 20] and len(b.air_future) == 1
        b.quad.t = 5.2
        b._release_air(0.0)
        assert len(b.air_future) == 1  # not yet
        b.quad.t = 5.3
        b._release_air(0.0)
        assert not b.air_future and ages()[-1] in (70, 71)  # 50 ms later than stamped (rounded up)
    finally:
        b.close()
