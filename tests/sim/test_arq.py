"""The SITL bridge's retransmission book-keeping (polycc.sim.firmware.arq): every request cflib waits on is
covered, and cflib sees each answer exactly once, however the host delays and loses copies."""

from __future__ import annotations

import heapq

from hypothesis import given, settings
from hypothesis import strategies as st

from polycc.sim.firmware.arq import Arq, request_key

SOURCE = bytes([0xFD, 0x00])                     # cflib PlatformService._request_protocol_version
SOURCE_REPLY = bytes([0xFD]) + b"Bitcraze Crazyflie"
PARAM_READ = bytes([0x2D, 0x07, 0x00])           # param read, id 7 (TOC v2)
PARAM_REPLY = bytes([0x2D, 0x07, 0x00, 0x00, 0x2A])


def test_the_first_request_of_a_connect_is_covered():
    """Regression: the link service SOURCE request had no reply pattern, so lost in the firmware's RX queue it
    was never resent and cflib's connect waited for ever (a README test hung 1200 s on a loaded CI host)."""
    arq = Arq()
    assert request_key(SOURCE) is not None
    arq.sent(SOURCE, 0.0)
    assert arq.due(0.1) == []
    assert arq.due(0.2) == [SOURCE]          # lost: sent again after the timeout
    arq.sent(SOURCE, 0.2)
    assert arq.reply(SOURCE_REPLY, 0.21)     # the answer reaches cflib
    assert not arq.open
    assert arq.recovered == 1


def test_the_requests_cflib_connects_with_are_all_covered():
    """Every request of cflib 0.1.34's connect that it waits on (headers as cflib sends them, link bits 0xC):
    link SOURCE, platform version, log reset / TOC, memory info, param TOC / read / misc."""
    for req in (SOURCE, bytes([0xDD, 0x00]), bytes([0x5D, 0x05]), bytes([0x5C, 0x03]), bytes([0x5C, 0x02, 1, 0]),
                bytes([0x4C, 0x01]), bytes([0x2C, 0x03]), bytes([0x2C, 0x02, 5, 0]), PARAM_READ,
                bytes([0x2F, 0x03, 7, 0])):
        assert request_key(req) is not None, req.hex()


def test_a_retransmission_answered_while_it_waits_is_not_sent():
    """Regression: a copy that due() returned waited for its slot in the bridge's FIFO; the late answer to the
    first copy closed the request, the copy then went out as a new request and its answer reached cflib too."""
    arq = Arq()
    arq.sent(PARAM_READ, 0.0)
    assert arq.due(0.16) == [PARAM_READ]      # queued behind the FIFO ...
    assert arq.reply(PARAM_REPLY, 0.161)     # ... when the (slow) first answer comes
    assert not arq.wanted(PARAM_READ)        # the bridge drops the waiting copy


@settings(max_examples=300, deadline=None)
@given(
    st.lists(st.tuples(st.booleans(), st.floats(0.0, 0.4), st.floats(0.0, 0.05)), min_size=1, max_size=8),
    st.booleans(),
)
def test_each_answer_reaches_cflib_exactly_once(copies, source):
    """A request with its retransmissions on a discrete-event model of the bridge: copy k is lost in the
    firmware or answered after a latency (s), and each retransmission waits a host delay (s) for its slot.
    Whatever the schedule, cflib sees exactly one answer once any copy got through, and none before."""
    req, rep = (SOURCE, SOURCE_REPLY) if source else (PARAM_READ, PARAM_REPLY)
    arq = Arq()
    events: list = []  # (t, seq, kind, payload)
    seq = 0

    def push(t, kind):
        nonlocal seq
        heapq.heappush(events, (t, seq, kind))
        seq += 1

    fate = iter(copies)
    sent_copies = 0
    delivered = 0
    t = 0.0

    def send(now):
        nonlocal sent_copies
        arq.sent(req, now)
        sent_copies += 1
        lost, latency, _ = next(fate, (True, 0.0, 0.0))
        if not lost:
            push(now + latency, "reply")

    send(0.0)
    tick = 0.01
    while t < 3.0:
        t = round(t + tick, 6)
        while events and events[0][0] <= t:
            _, _, kind = heapq.heappop(events)
            if kind == "reply":
                delivered += arq.reply(rep, t)
            elif kind == "slot":
                if arq.wanted(req):
                    send(t)
                else:
                    arq.cancelled += 1
        for data in arq.due(t):
            _, _, wait = copies[min(sent_copies, len(copies) - 1)]
            push(t + wait, "slot")
    answered = any(not lost for lost, _, _ in copies[:sent_copies])
    assert delivered == (1 if answered else 0), (delivered, sent_copies, arq.stats())
