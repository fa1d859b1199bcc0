"""Fuzz the serial framing and the simulated device: it never crashes, resyncs on the next good
frame and counts every error kind.

The fast tests feed about 10^4 frames; the ``slow`` one (run in CI) feeds more than 10^5.

Two kinds of stream:

* *structured*: good frames, handshakes and faults (bad checksum, oversize length, truncated
  frame, invalid CPX header), each fault followed by an idle gap as on a real line. The
  counters must match the injected faults exactly and every good frame must come out.
* *garbage*: random bytes (full of false ``0xFF`` starts) before a good frame. With an idle gap
  before the good frame it must always come out. Without one, an 8-bit XOR checksum lets about
  1 false frame in 256 x (chance the CPX header is valid) through, which may swallow the good
  frame; so a lost good frame is only allowed when a false frame was accepted, and at most 1 %.
"""

from __future__ import annotations

import random
import struct

import pytest
from hypothesis import given
from hypothesis import strategies as st

from polycc.link.cpx_serial import (
    HANDSHAKE,
    HANDSHAKE_BYTES,
    CpxPacket,
    CpxSerialDevice,
    FrameDecoder,
    encode_frame,
)
from polycc.link.crtp import CrtpPacket, FramingError
from polycc.sim.crtp_device import CrtpDevice
from polycc.testing.link_fake_model import FakeModel, host_frame

FAULTS = ("bad_checksum", "oversize", "truncated", "bad_cpx")


def random_packet(rng: random.Random, no_ff: bool = False) -> CrtpPacket:
    """A random CRTP packet; with ``no_ff`` none of its frame bytes before the checksum is 0xFF."""
    hi = 0xFE if no_ff else 0xFF
    while True:
        port, ch = rng.randrange(16), rng.randrange(4)
        if not (no_ff and port == 15 and ch == 3):  # header 0xFF
            break
    return CrtpPacket(port, ch, bytes(rng.randint(0, hi) for _ in range(rng.randint(0, 30))))


def fault_bytes(kind: str, rng: random.Random) -> bytes:
    """One faulty frame whose bytes after the start contain no 0xFF (so the count is exact)."""
    frame = bytearray(host_frame(random_packet(rng, no_ff=True)))
    if kind == "bad_checksum":
        good = frame[-1]
        frame[-1] = rng.choice([b for b in range(0xFF) if b != good])
        return bytes(frame)
    if kind == "oversize":
        return bytes((0xFF, rng.randint(101, 0xFE))) + bytes(rng.randint(0, 0xFE) for _ in range(rng.randint(0, 20)))
    if kind == "truncated":
        return bytes(frame[:rng.randint(1, len(frame) - 1)])
    while True:  # bad_cpx: good framing around an invalid CPX header (version 1)
        frame = encode_frame(bytes((0x19, 0x43)) + bytes(rng.randint(0, 0xFE) for _ in range(rng.randint(0, 10))))
        if frame[-1] != 0xFF:
            return frame


def feed_chunked(dec: FrameDecoder, data: bytes, rng: random.Random) -> list:
    out, i = [], 0
    while i < len(data):
        n = rng.randint(1, 64)
        out += dec.feed(data[i:i + n])
        i += n
    return out


def run_structured(seed: int, n_items: int) -> int:
    """Returns the number of frames fed; asserts exact counts and that no good frame is lost."""
    rng = random.Random(seed)
    dec = FrameDecoder()
    expected = dict.fromkeys(FAULTS, 0)
    sent, got, handshakes = [], [], 0
    for _ in range(n_items):
        r = rng.random()
        if r < 0.6:
            pk = random_packet(rng)
            sent.append(pk)
            events = feed_chunked(dec, host_frame(pk), rng)
        elif r < 0.7:
            handshakes += 1
            events = feed_chunked(dec, HANDSHAKE_BYTES, rng)
        else:
            kind = rng.choice(FAULTS)
            expected[kind] += 1
            events = feed_chunked(dec, fault_bytes(kind, rng), rng) + dec.flush()  # the line goes idle
        got += [CrtpPacket.decode(e.data) for e in events if isinstance(e, CpxPacket)]
    assert got == sent
    s = dec.stats
    assert (s.bad_checksum, s.oversize, s.truncated, s.bad_cpx) == tuple(expected[k] for k in FAULTS)
    assert s.frames == len(sent) and s.handshakes == handshakes
    return n_items


def run_garbage(seed: int, n_cases: int) -> tuple[int, int]:
    """Random garbage then a good frame, alternately with and without an idle gap.

    Returns (frames fed, good frames lost without an idle gap).
    """
    rng = random.Random(seed)
    dec = FrameDecoder()
    lost = 0
    for i in range(n_cases):
        garbage = bytes(rng.choice((0xFF, rng.randrange(256))) for _ in range(rng.randint(0, 120)))
        pk = random_packet(rng)
        idle = i % 2 == 0
        passed_before = dec.stats.frames + dec.stats.bad_cpx  # frames that passed the checksum
        feed_chunked(dec, garbage, rng)
        if idle:
            dec.flush()
        events = feed_chunked(dec, host_frame(pk), rng) + dec.flush()
        packets = [e for e in events if isinstance(e, CpxPacket)]
        ok = any(e.data == pk.encode() for e in packets)
        if idle:
            assert ok, f"case {i}: good frame after an idle gap was not decoded"
        elif not ok:
            lost += 1
            # the only way to lose it: a false frame passed the checksum and swallowed its start
            assert dec.stats.frames + dec.stats.bad_cpx > passed_before
    assert dec.stats.garbage_bytes > 0 and dec.stats.errors > 0
    return 2 * n_cases, lost


def run_device(seed: int, n_items: int) -> int:
    """Random bytes and random well-framed CRTP packets into link + device: nothing raises, and
    afterwards a clean connect request still gets its answer."""
    rng = random.Random(seed)
    model = FakeModel()
    dev, link = CrtpDevice(model), CpxSerialDevice()
    t = 0.0
    for _ in range(n_items):
        t += 0.001
        if rng.random() < 0.5:
            data = host_frame(random_packet(rng))
        else:
            data = bytes(rng.randrange(256) for _ in range(rng.randint(1, 40)))
        for pk in link.receive(data, t):
            for r in dev.handle(pk):
                link.send(r)
        if rng.random() < 0.1:
            for pk in link.idle():
                dev.handle(pk)
        for pk in dev.tick():
            link.send(pk)
        link.output(t)
        if rng.random() < 0.3:
            link.receive(HANDSHAKE_BYTES, t)  # the host's CTS
    # drain, go idle, then a clean link-source query must be answered
    for pk in link.idle():
        dev.handle(pk)
    dev.reset_session()
    link.reset()
    link.receive(HANDSHAKE_BYTES, t + 1)
    while link.output(t + 1):
        link.receive(HANDSHAKE_BYTES, t + 1)
    (q,) = link.receive(host_frame(CrtpPacket(15, 1, b"\0")), t + 2)
    (r,) = dev.handle(q)
    link.send(r)
    out = link.output(t + 2)
    events = FrameDecoder().feed(out)
    assert events[0] is HANDSHAKE and CrtpPacket.decode(events[1].data) == r
    assert r.data.startswith(b"Bitcraze Crazyflie")
    assert dev.stats.handler_errors == 0  # every bad input was classified, not an accident
    assert dev.stats.unknown_port + dev.stats.unknown_command + dev.stats.malformed > 0
    return n_items


def run_udp(seed: int, n_items: int) -> int:
    rng = random.Random(seed)
    dev = CrtpDevice(FakeModel())
    for _ in range(n_items):
        raw = bytes(rng.randrange(256) for _ in range(rng.randint(0, 40)))
        try:
            pk = CrtpPacket.decode(raw)
        except FramingError:
            continue
        dev.handle(pk)
        dev.tick()
    assert dev.stats.handler_errors == 0
    return n_items


def fuzz_all(seed: int, structured: int, garbage_cases: int, device: int, udp: int) -> int:
    """All four fuzzers; returns the number of frames fed."""
    frames = run_structured(seed, structured)
    g, lost = run_garbage(seed + 1, garbage_cases)
    assert lost <= 0.01 * garbage_cases / 2
    return frames + g + run_device(seed + 2, device) + run_udp(seed + 3, udp)


def test_fuzz_fast():
    assert fuzz_all(1, 3000, 1500, 2000, 2000) >= 10_000


@pytest.mark.slow
def test_fuzz_slow():
    assert fuzz_all(11, 40_000, 15_000, 20_000, 20_000) >= 100_000


@given(st.lists(st.one_of(st.binary(max_size=40), st.builds(
    lambda port, ch, data: host_frame(CrtpPacket(port, ch, data)),
    st.integers(0, 15), st.integers(0, 3), st.binary(max_size=30))), max_size=40))
def test_hypothesis_stream_never_crashes_and_resyncs(chunks):
    """Any byte stream, then an idle gap and a good frame: the good frame always comes out."""
    dev, link = CrtpDevice(FakeModel()), CpxSerialDevice()
    for c in chunks:
        for pk in link.receive(c, 0.0):
            dev.handle(pk)
    for pk in link.idle():
        dev.handle(pk)
    (pk,) = link.receive(host_frame(CrtpPacket(15, 0, b"echo")), 1.0)
    assert dev.handle(pk) == [CrtpPacket(15, 0, b"echo")]
    assert dev.stats.handler_errors == 0


@given(st.binary(min_size=2, max_size=102))
def test_hypothesis_cpx_decode_total(payload):
    """CPX header parsing either succeeds with a round trip or raises FramingError."""
    try:
        p = CpxPacket.decode(payload)
    except FramingError:
        return
    assert p.encode()[2:] == payload[2:] and struct.unpack("<B", p.encode()[1:2])[0] == payload[1]
