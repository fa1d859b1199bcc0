"""Byte-level tests of the link layers (CRTP, CPX serial framing, UDP) and the simulated device.

Golden frames were produced by cflib 0.1.34's own encoder (``UARTTransport.writePacket`` for
host-to-device frames) and checked with its decoder (``UARTTransport.readPacket`` and
``LogConfig.unpack_log_data`` for the device-to-host log frame); the hex is hard-coded so the
tests run without cflib, and the ``*_cflib`` tests re-derive it when cflib is installed.
"""

from __future__ import annotations

import errno
import struct
import threading

import pytest

from polycc.errors import PolyccError
from polycc.link.cpx_serial import (
    BAD_FRAME,
    HANDSHAKE,
    HANDSHAKE_BYTES,
    CpxFunction,
    CpxPacket,
    CpxSerialDevice,
    CpxTarget,
    FrameDecoder,
    encode_crtp_frame,
    encode_frame,
    xor_checksum,
)
from polycc.link.crtp import CrtpPacket, FramingError, Port, make_header
from polycc.link.udp import decode_datagram, encode_datagram, parse_udp_uri
from polycc.sim.crtp_device import (
    CrtpDevice,
    DeviceModel,
    LogEntry,
    ParamEntry,
    ctype_from_log_type,
    ctype_from_param_type,
    pack_value,
    unpack_value,
)
from polycc.testing.link_fake_model import FakeModel, host_frame

# host -> device: link source query, CRTP port 15 ch 1, payload 00
GOLDEN_LINK_SOURCE = "ff041903fd001c"
# host -> device: param read (v2) of id 1, CRTP port 2 ch 1, payload 01 00
GOLDEN_PARAM_READ = "ff0519032d0100cc"
# device -> host: log data of block 1 at t = 1000 ms with floats 1.5 and 0.25
GOLDEN_LOG_DATA = "ff0f4b035e01e803000000c03f0000803e4d"
# device -> host: the answer to the link source query
GOLDEN_LINK_SOURCE_REPLY = ("ff214b03fd" + b"Bitcraze Crazyflie".hex() + "00" * 12 + "2e")
LOG_DATA_PACKET = CrtpPacket(Port.LOG, 2, bytes((1, 0xE8, 0x03, 0)) + struct.pack("<ff", 1.5, 0.25))


# ---------------------------------------------------------------- CRTP
def test_crtp_header_sets_bits_2_3_like_cflib():
    assert make_header(15, 1) == 0xFD
    assert make_header(2, 1) == 0x2D
    assert make_header(0, 0) == 0x0C
    assert CrtpPacket(5, 2, b"\x01").encode() == b"\x5e\x01"


def test_crtp_decode_ignores_reserved_bits_and_round_trips():
    for h in (0xF1, 0xF5, 0xF9, 0xFD):
        pk = CrtpPacket.decode(bytes((h, 7)))
        assert (pk.port, pk.channel, pk.data) == (15, 1, b"\x07")
    pk = CrtpPacket(13, 2, bytes(range(30)))
    assert CrtpPacket.decode(pk.encode()) == pk


def test_crtp_limits():
    CrtpPacket(2, 3, bytes(30))
    with pytest.raises(FramingError):
        CrtpPacket(2, 3, bytes(31))
    with pytest.raises(FramingError):
        CrtpPacket(16, 0)
    with pytest.raises(FramingError):
        CrtpPacket(0, 4)
    for bad in (b"", bytes(32)):
        with pytest.raises(FramingError):
            CrtpPacket.decode(bad)


def test_udp_datagram_is_raw_crtp():
    pk = CrtpPacket(15, 1, b"\0")
    assert encode_datagram(pk) == bytes.fromhex("fd00")
    assert decode_datagram(bytes.fromhex("2d0100")) == CrtpPacket(2, 1, b"\x01\x00")
    assert parse_udp_uri("udp://127.0.0.1:19851") == ("127.0.0.1", 19851)
    assert parse_udp_uri("udp://localhost") == ("localhost", 19850)
    with pytest.raises(PolyccError):
        parse_udp_uri("serial://ttyUSB0")


# ---------------------------------------------------------------- golden frames
def test_golden_frames_from_our_encoder():
    assert host_frame(CrtpPacket(15, 1, b"\0")).hex() == GOLDEN_LINK_SOURCE
    assert host_frame(CrtpPacket(2, 1, struct.pack("<H", 1))).hex() == GOLDEN_PARAM_READ
    assert encode_crtp_frame(LOG_DATA_PACKET).hex() == GOLDEN_LOG_DATA


def test_golden_frames_decode():
    (a,) = FrameDecoder().feed(bytes.fromhex(GOLDEN_LINK_SOURCE))
    assert (a.function, a.destination, a.source, a.last_packet) == (CpxFunction.CRTP, CpxTarget.STM32,
                                                                    CpxTarget.HOST, False)
    assert CrtpPacket.decode(a.data) == CrtpPacket(15, 1, b"\0")
    (b,) = FrameDecoder().feed(bytes.fromhex(GOLDEN_LOG_DATA))
    assert (b.destination, b.source, b.last_packet) == (CpxTarget.HOST, CpxTarget.STM32, True)
    assert CrtpPacket.decode(b.data) == LOG_DATA_PACKET


def test_device_answers_golden_link_source_with_golden_reply():
    link, dev = CpxSerialDevice(), CrtpDevice(FakeModel())
    link.receive(HANDSHAKE_BYTES, 0.0)
    for pk in link.receive(bytes.fromhex(GOLDEN_LINK_SOURCE), 0.0):
        for r in dev.handle(pk):
            link.send(r)
    assert link.output(0.0).hex() == "ff00" + GOLDEN_LINK_SOURCE_REPLY  # CTS first, then the reply


class _FakeSerial:
    """Just enough of pyserial's Serial for cflib's UARTTransport."""

    def __init__(self, rx: bytes = b"") -> None:
        self.tx, self.rx = bytearray(), bytearray(rx)

    def write(self, data) -> None:
        self.tx += bytes(data)

    def read(self, n: int) -> bytes:
        out = bytes(self.rx[:n])
        del self.rx[:n]
        return out


def _cflib_uart(rx: bytes = b""):
    transports = pytest.importorskip("cflib.cpx.transports", reason="cflib not installed")
    t = transports.UARTTransport.__new__(transports.UARTTransport)  # skip connect(): no real port
    t._serial = _FakeSerial(rx)
    t._tx_ready, t._tx_lock, t._serial_write_lock = threading.Event(), threading.Lock(), threading.Lock()
    t._tx_ready.set()
    return t


def test_golden_host_frames_match_cflib_encoder():
    t = _cflib_uart()
    from cflib.cpx import CPXFunction, CPXPacket, CPXTarget
    from cflib.crtp.crtpstack import CRTPPacket

    def cflib_frame(port, channel, data):
        pk = CRTPPacket()
        pk.set_header(port, channel)
        pk.data = data
        t._serial.tx.clear()
        t._tx_ready.set()
        # what cflib's SerialDriver.send_packet does
        raw = (pk.header,) + struct.unpack("B" * len(pk.data), pk.data)
        t.writePacket(CPXPacket(destination=CPXTarget.STM32, function=CPXFunction.CRTP, data=raw))
        return bytes(t._serial.tx).hex()

    assert cflib_frame(15, 1, (0,)) == GOLDEN_LINK_SOURCE  # PlatformService._request_protocol_version
    assert cflib_frame(2, 1, struct.pack("<H", 1)) == GOLDEN_PARAM_READ  # _ParamUpdater.request_param_update


def test_golden_log_frame_decodes_in_cflib():
    t = _cflib_uart(bytes.fromhex(GOLDEN_LOG_DATA))
    from cflib.crazyflie.log import LogConfig, LogTocElement, LogVariable
    from cflib.crtp.crtpstack import CRTPPacket

    cpx = t.readPacket()
    assert bytes(t._serial.tx) == HANDSHAKE_BYTES  # cflib answers every frame with FF 00
    data = struct.unpack("B" * cpx.length, cpx.data)
    pk = CRTPPacket(data[0], list(data[1:]))  # what cflib's _CPXReceiveThread does
    assert (pk.port, pk.channel) == (5, 2)
    got = []
    lc = LogConfig("golden", 10)
    lc.variables = [LogVariable("stateEstimate.x", "float"), LogVariable("polycc.psi", "float")]
    lc.data_received_cb.add_callback(lambda ts, values, conf: got.append((ts, values)))
    ts = pk.data[1] | pk.data[2] << 8 | pk.data[3] << 16
    lc.unpack_log_data(pk.data[4:], ts)
    assert got == [(1000, {"stateEstimate.x": 1.5, "polycc.psi": 0.25})]
    assert LogTocElement.get_id_from_cstring("float") == 7


def test_golden_udp_datagrams_match_cflib():
    udpdriver = pytest.importorskip("cflib.crtp.udpdriver", reason="cflib not installed")
    from cflib.crtp.crtpstack import CRTPPacket

    sent = []

    class Sock:
        def send(self, data):
            sent.append(bytes(data))

    drv = udpdriver.UdpDriver()
    drv.socket = Sock()
    pk = CRTPPacket()
    pk.set_header(15, 1)
    pk.data = (0,)
    drv.send_packet(pk)
    assert sent == [encode_datagram(CrtpPacket(15, 1, b"\0"))] == [bytes.fromhex("fd00")]


# ---------------------------------------------------------------- framing
def test_frame_encoding_and_checksum():
    assert xor_checksum(b"") == 0
    assert encode_frame(b"\x01") == bytes((0xFF, 1, 1, 0xFF ^ 1 ^ 1))
    encode_frame(bytes(100))
    for bad in (b"", bytes(101)):
        with pytest.raises(FramingError):
            encode_frame(bad)
    with pytest.raises(FramingError):
        CpxPacket.decode(b"\x19")
    with pytest.raises(FramingError):
        CpxPacket.decode(b"\x19\x43")  # version 1
    with pytest.raises(FramingError):
        CpxPacket.decode(b"\x07\x03")  # target 7


def test_decoder_byte_by_byte_and_handshakes():
    d = FrameDecoder()
    stream = HANDSHAKE_BYTES + bytes.fromhex(GOLDEN_LINK_SOURCE) + HANDSHAKE_BYTES
    events = [e for b in stream for e in d.feed(bytes((b,)))]
    assert events[0] is HANDSHAKE and events[2] is HANDSHAKE
    assert isinstance(events[1], CpxPacket) and len(events) == 3
    assert d.stats.frames == 1 and d.stats.handshakes == 2 and d.stats.errors == 0 and d.pending == 0


def test_decoder_counts_each_error_kind_and_resyncs():
    good = bytes.fromhex(GOLDEN_PARAM_READ)
    bad_ck = bytearray(good)
    bad_ck[-1] ^= 0x55
    oversize = bytes((0xFF, 101)) + bytes(5)
    bad_cpx = encode_frame(b"\x07\x03\x2d")
    garbage = b"\x01\x02\x03"
    d = FrameDecoder()
    ev = d.feed(garbage + good + bytes(bad_ck) + good + oversize + good + bad_cpx + good)
    assert [e for e in ev if isinstance(e, CpxPacket)] == [CpxPacket.decode(good[2:-1])] * 4
    assert ev.count(BAD_FRAME) == 2
    st = d.stats
    assert (st.frames, st.bad_checksum, st.oversize, st.bad_cpx) == (4, 1, 1, 1)
    # after a false start only its FF is dropped; the bytes behind it are rescanned as garbage
    assert st.garbage_bytes == len(garbage) + (len(bad_ck) - 1) + (len(oversize) - 1) + (len(bad_cpx) - 1)
    # truncated: half a frame, then the line goes idle
    assert d.feed(good[:4]) == [] and d.pending == 4
    assert d.flush() == [] and d.stats.truncated == 1 and d.pending == 0
    assert len(d.feed(good)) == 1


def test_decoder_finds_good_frame_behind_false_start():
    good = bytes.fromhex(GOLDEN_LINK_SOURCE)
    d = FrameDecoder()
    # a stray FF with a long length swallows the good frame until the line goes idle
    assert d.feed(b"\xff\x40" + good) == []
    ev = d.flush()
    assert [e for e in ev if isinstance(e, CpxPacket)] == [CpxPacket.decode(good[2:-1])]
    assert d.stats.truncated == 1
    # a stray FF with a short length fails its checksum and the scan restarts after it
    d = FrameDecoder()
    ev = d.feed(b"\xff\x02" + good)
    assert ev[-1] == CpxPacket.decode(good[2:-1]) and d.stats.bad_checksum >= 1


# ---------------------------------------------------------------- handshake (FF 00) semantics
def test_device_repeats_handshake_until_host_answers():
    link = CpxSerialDevice(handshake_period_s=0.02)
    assert link.output(0.0) == HANDSHAKE_BYTES
    assert link.output(0.01) == b""
    assert link.output(0.02) == HANDSHAKE_BYTES
    link.send(CrtpPacket(0, 0, b"x"))  # nobody listening: dropped
    assert link.stats.tx_dropped == 1
    link.receive(HANDSHAKE_BYTES, 0.03)  # the host answers (cflib UARTTransport.connect)
    assert link.synced and link.output(0.05) == b""


def test_device_acks_every_host_frame_and_waits_for_cts():
    link = CpxSerialDevice(cts_timeout_s=0.1)
    link.receive(HANDSHAKE_BYTES, 0.0)
    sysf = encode_frame(CpxPacket(CpxFunction.SYSTEM, CpxTarget.STM32, CpxTarget.HOST, b"\x21\x01").encode())
    assert link.receive(sysf, 0.0) == []  # cflib's "switch to CPX" system packet: acked, not CRTP
    assert link.output(0.0) == HANDSHAKE_BYTES and link.stats.rx_other_cpx == 1
    a, b = CrtpPacket(15, 0, b"a"), CrtpPacket(15, 0, b"b")
    link.send(a)
    link.send(b)
    assert link.output(0.0) == encode_crtp_frame(a)  # credit from the host's sync answer
    assert link.output(0.01) == b""  # b waits for the host's FF 00
    link.receive(HANDSHAKE_BYTES, 0.02)
    assert link.output(0.02) == encode_crtp_frame(b)
    link.send(a)
    assert link.output(0.05) == b"" and link.output(0.13) == encode_crtp_frame(a)  # CTS lost: timeout
    assert link.stats.cts_timeouts == 1
    # a corrupted frame is still answered, as cflib does, so the host never stalls
    bad = bytearray(bytes.fromhex(GOLDEN_LINK_SOURCE))
    bad[-1] ^= 1
    link.receive(bytes(bad), 0.2)
    assert link.output(0.2) == HANDSHAKE_BYTES


def test_device_resyncs_after_reset_and_on_a_frame():
    link = CpxSerialDevice()
    link.receive(HANDSHAKE_BYTES, 0.0)
    link.reset()  # the host closed the port
    assert not link.synced and link.output(1.0) == HANDSHAKE_BYTES
    (pk,) = link.receive(bytes.fromhex(GOLDEN_LINK_SOURCE), 1.0)  # a frame proves the host is there
    assert link.synced and pk == CrtpPacket(15, 1, b"\0")


# ---------------------------------------------------------------- device protocol
def ask(dev: CrtpDevice, port: int, channel: int, data: bytes) -> list[CrtpPacket]:
    return dev.handle(CrtpPacket(port, channel, data))


def test_device_connection_sequence_replies():
    model = FakeModel()
    dev = CrtpDevice(model)
    (src,) = ask(dev, 15, 1, b"\0")
    assert src.data[:18] == b"Bitcraze Crazyflie" and len(src.data) == 30
    (ver,) = ask(dev, 13, 1, b"\0")
    assert ver.data[0] == 0 and ver.data[1] >= 4
    (fw,) = ask(dev, 13, 1, b"\x01")
    assert fw.data[1:].startswith(b"polycc")
    assert ask(dev, 5, 1, b"\x05") == [CrtpPacket(5, 1, b"\x05\x00\x00")]  # log reset
    (info,) = ask(dev, 5, 0, b"\x03")
    n, crc = struct.unpack("<HI", info.data[1:7])
    assert n == len(model.logs) and crc == dev.log_crc
    (item,) = ask(dev, 5, 0, b"\x02\x00\x00")
    assert item.data == b"\x02\x00\x00\x07stateEstimate\0x\0"
    assert ask(dev, 4, 0, b"\x01") == [CrtpPacket(4, 0, b"\x01\x00")]  # no memories
    (pinfo,) = ask(dev, 2, 0, b"\x03")
    assert struct.unpack("<H", pinfo.data[1:3])[0] == len(model.params) + 1  # + firmware.polyccVersion
    names = []
    for i in range(len(dev.params)):
        (it,) = ask(dev, 2, 0, struct.pack("<BH", 2, i))
        group, name, _ = it.data[4:].split(b"\0")
        names.append((it.data[3], f"{group.decode()}.{name.decode()}"))
    assert names[0] == (0x06, "polycc.goalX") and names[3] == (0x08, "polycc.enable")
    assert (0x4A, "polycc.uptime") in names and (0x4A, "firmware.polyccVersion") in names
    assert ask(dev, 15, 0, b"ping") == [CrtpPacket(15, 0, b"ping")]
    (v1,) = ask(dev, 2, 0, b"\x01")  # v1 TOC info: count as one byte
    assert v1.data[1] == len(dev.params)


def test_device_param_read_write_and_misc():
    model = FakeModel()
    dev = CrtpDevice(model)
    (r,) = ask(dev, 2, 1, struct.pack("<H", 0))
    assert r.data == struct.pack("<HBf", 0, 0, 0.0)
    (w,) = ask(dev, 2, 2, struct.pack("<Hf", 0, 2.5))
    assert w.data == struct.pack("<Hf", 0, 2.5) and model.values["polycc.goalX"] == 2.5
    ask(dev, 2, 2, struct.pack("<HB", 3, 1))
    assert model.values["polycc.enable"] == 1 and isinstance(model.values["polycc.enable"], int)
    (ro,) = ask(dev, 2, 2, struct.pack("<HI", 6, 99))  # read-only: answered with the unchanged value
    assert ro.data == struct.pack("<HI", 6, 7) and model.values["polycc.uptime"] == 7
    assert ask(dev, 2, 1, struct.pack("<H", 999)) == [CrtpPacket(2, 1, struct.pack("<HB", 999, errno.ENOENT))]
    # set by name (cflib Param.set_value_raw), then the value-updated notification
    ok, upd = ask(dev, 2, 3, b"\x00polycc\0goalY\0\x06" + struct.pack("<f", -1.0))
    assert ok.data == b"\x00polycc\0goalY\0\x00" and upd.data == struct.pack("<BHf", 1, 1, -1.0)
    (default,) = ask(dev, 2, 3, struct.pack("<BH", 8, 0))  # default v2: value before the first write
    assert default.data == struct.pack("<BHBf", 8, 0, 0, 0.0)
    (ext,) = ask(dev, 2, 3, struct.pack("<BH", 7, 0))
    assert ext.data == struct.pack("<BHBB", 7, 0, 0, 0)
    (store,) = ask(dev, 2, 3, struct.pack("<BH", 3, 0))
    assert store.data[3] == errno.ENOENT


def test_device_log_blocks_stream_at_the_requested_period():
    model = FakeModel()
    model.clock_ms = 1000
    dev = CrtpDevice(model)
    ops = struct.pack("<BHBH", 0x77, 0, 0x77, 3)  # stateEstimate.x, polycc.psi as float
    assert ask(dev, 5, 1, b"\x06\x01" + ops) == [CrtpPacket(5, 1, b"\x06\x01\x00")]
    assert ask(dev, 5, 1, b"\x06\x01" + ops)[0].data[2] == errno.EEXIST
    assert ask(dev, 5, 1, b"\x03\x01\x02") == [CrtpPacket(5, 1, b"\x03\x01\x00")]  # start, 20 ms
    assert dev.tick() == []
    model.clock_ms = 1020
    (p,) = dev.tick()
    assert p == CrtpPacket(5, 2, bytes((1,)) + (1020).to_bytes(3, "little") + struct.pack("<ff", 1.5, 0.25))
    model.clock_ms = 1060
    assert [q.data[1:4] for q in dev.tick()] == [(1040).to_bytes(3, "little"), (1060).to_bytes(3, "little")]
    ask(dev, 5, 1, b"\x04\x01")  # stop
    model.clock_ms = 2000
    assert dev.tick() == []
    # fetch-as conversion: float stored, fetched as int16; uint16 fetched as uint8
    ops = struct.pack("<BHBH", 0x75, 0, 0x21, 4)
    assert ask(dev, 5, 1, b"\x06\x02" + ops)[0].data[2] == 0
    ask(dev, 5, 1, b"\x03\x02\x01")
    model.clock_ms = 2010
    (q,) = dev.tick()
    assert q.data[4:] == struct.pack("<hB", 1, 0)
    # errors: unknown block, unknown variable, too big, unknown command
    assert ask(dev, 5, 1, b"\x03\x09\x01")[0].data[2] == errno.ENOENT
    assert ask(dev, 5, 1, b"\x06\x03" + struct.pack("<BH", 0x77, 999))[0].data[2] == errno.ENOENT
    assert ask(dev, 5, 1, b"\x06\x04" + struct.pack("<BH", 0x77, 0) * 7)[0].data[2] == errno.E2BIG
    assert ask(dev, 5, 1, b"\x2a\x01")[0].data[2] == errno.ENOEXEC
    assert ask(dev, 5, 1, b"\x02\x02") == [CrtpPacket(5, 1, b"\x02\x02\x00")]  # delete
    assert ask(dev, 5, 1, b"\x05") == [CrtpPacket(5, 1, b"\x05\x00\x00")] and dev.running_blocks == 0


def test_device_setpoints_appchannel_and_unknown_ports():
    model = FakeModel()
    dev = CrtpDevice(model)
    ask(dev, 3, 0, struct.pack("<fffH", 1.0, -2.0, 3.0, 40000))
    ask(dev, 7, 0, struct.pack("<Bffff", 10, 0.1, 0.2, 30.0, 0.4))
    ask(dev, 7, 0, struct.pack("<Bffff", 5, 0.1, 0.2, 30.0, 0.4))  # legacy hover: yawrate negated
    ask(dev, 7, 0, b"\x00")
    ask(dev, 8, 0, struct.pack("<BBff?f", 7, 0, 0.5, 0.0, False, 2.0))
    ask(dev, 7, 1, struct.pack("<BI", 0, 250))
    kinds = [k for k, _ in model.setpoints]
    assert kinds == ["rpyt", "hover", "hover", "stop", "hl_takeoff", "notify_setpoint_stop"]
    assert model.setpoints[0][1] == {"roll": 1.0, "pitch": -2.0, "yawrate": 3.0, "thrust": 40000}
    assert model.setpoints[1][1]["yawrate"] == 30.0 and model.setpoints[2][1]["yawrate"] == -30.0
    assert model.setpoints[4][1]["height"] == 0.5 and model.setpoints[4][1]["duration"] == 2.0
    assert ask(dev, 13, 2, b"hello") == [CrtpPacket(13, 2, b"ack:hello")] and model.app_rx == [b"hello"]
    before = dev.stats.as_dict()
    assert ask(dev, 11, 0, b"\x01") == [] and ask(dev, 7, 0, b"\x63") == [] and ask(dev, 5, 3, b"") == []
    assert ask(dev, 2, 1, b"") == [] and ask(dev, 3, 0, b"\x01") == []  # truncated payloads
    after = dev.stats.as_dict()
    assert after["unknown_port"] == before["unknown_port"] + 1
    assert after["unknown_command"] == before["unknown_command"] + 2
    assert after["malformed"] == before["malformed"] + 2


def test_device_survives_a_failing_model():
    """A model that raises still gets every request answered (cflib stalls on a missing reply)."""
    def boom(*_):
        raise RuntimeError("app bug")

    model = DeviceModel(params=[ParamEntry("a", "b", "float", boom, boom)], logs=[LogEntry("a", "c", "float", boom)])
    model.on_setpoint = boom
    dev = CrtpDevice(model)
    assert ask(dev, 2, 1, b"\0\0") == [CrtpPacket(2, 1, struct.pack("<HBf", 0, 0, 0.0))]
    assert ask(dev, 2, 2, struct.pack("<Hf", 0, 1.0)) == [CrtpPacket(2, 2, struct.pack("<Hf", 0, 0.0))]
    assert dev.stats.handler_errors == 4 and dev.stats.param_writes == 0
    assert ask(dev, 5, 1, b"\x06\x01\x07\x00\x00")[0].data[2] == 0
    ask(dev, 5, 1, b"\x03\x01\x01")
    model._t0 -= 5.0  # far behind: skips ahead to one packet
    assert len(dev.tick()) == 1 and dev.stats.handler_errors == 5 and dev.stats.log_overruns == 1
    assert ask(dev, 7, 0, b"\x00") == [] and dev.stats.handler_errors == 6


def test_model_validation_errors_are_user_errors():
    with pytest.raises(PolyccError, match="unknown C type"):
        ParamEntry("g", "n", "float32", lambda: 0)
    with pytest.raises(PolyccError, match="exceed"):
        LogEntry("g" * 20, "n" * 10, "float", lambda: 0)
    with pytest.raises(PolyccError, match="cannot be logged"):
        LogEntry("g", "n", "double", lambda: 0)
    with pytest.raises(PolyccError, match="twice"):
        CrtpDevice(DeviceModel(logs=[LogEntry("g", "n", "float", lambda: 0)] * 2))


@pytest.mark.parametrize("ctype,value,expected", [
    ("uint8_t", 257, 1), ("int8_t", 255, -1), ("uint16_t", -1, 65535), ("int32_t", 2.9, 2),
    ("uint8_t", float("nan"), 0), ("float", 1e39, float("inf")), ("FP16", 0.5, 0.5), ("double", 0.1, 0.1),
    ("uint64_t", 2**64 - 1, 2**64 - 1), ("float", True, 1.0),
])
def test_pack_value_casts_like_c(ctype, value, expected):
    assert unpack_value(ctype, pack_value(ctype, value)) == expected


def test_firmware_type_bytes_map_to_ctypes():
    # param.h: PARAM_FLOAT = 0x06, PARAM_UINT8 | PARAM_RONLY | PARAM_CORE = 0x68, PARAM_INT16 = 0x01
    assert ctype_from_param_type(0x06) == ("float", False)
    assert ctype_from_param_type(0x68) == ("uint8_t", True)
    assert ctype_from_param_type(0x01 | 0x100) == ("int16_t", False)  # PARAM_PERSISTENT
    # log.h: LOG_FLOAT = 7, LOG_UINT16 | LOG_CORE = 0x22
    assert ctype_from_log_type(7) == "float" and ctype_from_log_type(0x22) == "uint16_t"
    with pytest.raises(PolyccError):
        ctype_from_param_type(0x04)
    with pytest.raises(PolyccError):
        ctype_from_log_type(0)


def test_device_v1_commands_for_old_clients():
    model = FakeModel()
    dev = CrtpDevice(model, protocol_version=3)
    assert ask(dev, 13, 1, b"\0")[0].data[1] == 3
    assert ask(dev, 2, 1, b"\x00") == [CrtpPacket(2, 1, b"\x00" + struct.pack("<f", 0.0))]  # no status byte
    assert ask(dev, 2, 2, b"\x00" + struct.pack("<f", 4.0))[0].data == b"\x00" + struct.pack("<f", 4.0)
    (item,) = ask(dev, 5, 0, b"\x00\x03")
    assert item.data == b"\x00\x03\x07polycc\0psi\0"
    assert ask(dev, 5, 1, b"\x00\x05\x77\x00") == [CrtpPacket(5, 1, b"\x00\x05\x00")]  # v1 create
    assert ask(dev, 5, 1, b"\x01\x05\x77\x03") == [CrtpPacket(5, 1, b"\x01\x05\x00")]  # v1 append
    assert ask(dev, 5, 1, b"\x00\x06\x77\xff")[0].data[2] == errno.ENOENT  # raw memory: not simulated
