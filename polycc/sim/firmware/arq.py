"""Retransmission of CRTP requests that the firmware answers (stdlib only).

Why: the Crazyradio link that cflib normally uses is acknowledged and retransmitted in
hardware; the SITL's UDP socket link is not, and cflib's UDP driver sets
``needs_resending = False`` (cflib/crtp/udpdriver.py), so cflib never resends either.  The
bridge's pacing (:mod:`polycc.sim.firmware.bridge`) keeps the firmware's 5-deep RX queue from
overflowing, but it can only infer the queue from the motor packets; when the cf2 process is descheduled by the
host the inference can be wrong and a packet can still be lost.  Every request below has a
reply that starts with the same bytes, so a missing reply is detected and the request sent
again, which is exactly what cflib's own radio path does for the same requests
(``send_packet(..., expected_reply=...)`` in cflib/crazyflie/{toc,param,log}.py).

Requests that are safe to repeat (queries, absolute writes, log block create/start/stop/delete:
a repeated create/delete returns an error code whose reply is suppressed when the first reply
already went to cflib) are resent after ``rto_s`` (0.15 s).  Requests that would act twice
(log APPEND_BLOCK, relative HL go_to / start_trajectory) are resent only after
``rto_unsafe_s`` (1 s) without any reply: the firmware answers them within milliseconds of
its own time, and the reply path (cf2 -> bridge over loopback) does not lose datagrams, so a
missing reply after 1 s means the request was lost.  Packets without a reply (setpoints) are
never resent.

A reply is matched by the CRTP header without the link bits (``& 0xF3``) and the first
``n`` payload bytes of the request, ``n`` from :data:`MATCH_BYTES` (0: the header alone).

A retransmission waits in the bridge's FIFO for a slot; a reply that comes meanwhile answers the request,
and the waiting copy is then not sent (:meth:`Arq.wanted`): sent, it would draw a second reply that nothing
marks as a duplicate, and cflib would see the answer twice.

Regression: the link service's SOURCE request (port 15, channel 1), the first packet of every cflib connect
(``PlatformService._request_protocol_version``), was not in :data:`MATCH_BYTES`. Lost in the firmware's RX
queue, it was never resent and cflib waited for ever: the connects that stalled "with no loss the ARQ saw"
(a README test on a loaded CI host hung 1200 s in ``SyncCrazyflie.__enter__``).
"""

from __future__ import annotations

from dataclasses import dataclass

# (port, channel) -> number of leading payload bytes shared by request and reply
MATCH_BYTES = {
    (2, 0): 3,   # param TOC: [cmd, idx_lo, idx_hi] (INFO: 1 byte, min() below)
    (2, 1): 2,   # param read: [id_lo, id_hi]
    (2, 2): 2,   # param write: [id_lo, id_hi, value...] -> [id_lo, id_hi, value...]
    (2, 3): 3,   # param misc: [cmd, id_lo, id_hi] (set by name: [cmd, group...])
    (4, 0): 2,   # mem info: [cmd, id]
    (4, 1): 5,   # mem read: [id, addr(4), len] -> [id, addr(4), status, data]
    (4, 2): 5,   # mem write: [id, addr(4), data] -> [id, addr(4), status]
    (5, 0): 3,   # log TOC
    (5, 1): 2,   # log control: [cmd, block id] -> [cmd, block id, error]
    (8, 0): 3,   # high-level commander: reply = first 3 bytes + return code
    (13, 1): 1,  # platform version commands: [cmd] -> [cmd, ...]
    (15, 1): 0,  # link service SOURCE: [0] -> b"Bitcraze Crazyflie" (cflib's first request of a connect)
}

LOG_CMD_APPEND_BLOCK = (2, 8)      # CMD_APPEND_BLOCK, CMD_APPEND_BLOCK_V2
HL_GO_TO, HL_START_TRAJECTORY = 4, 5


def _port_ch(header: int) -> tuple[int, int]:
    return (header >> 4) & 0x0F, header & 0x03


def is_unsafe_to_repeat(data: bytes) -> bool:
    """True for requests that would act twice if the firmware got them twice."""
    if len(data) < 2:
        return False
    pc, body = _port_ch(data[0]), data[1:]
    if pc == (5, 1) and body[0] in LOG_CMD_APPEND_BLOCK:
        return True
    return pc == (8, 0) and body[0] in (HL_GO_TO, HL_START_TRAJECTORY) and len(body) > 2 and body[2] != 0


def request_key(data: bytes):
    """The reply-matching key of a cflib -> firmware packet, or None when it has no reply."""
    if len(data) < 2:
        return None
    pc = _port_ch(data[0])
    n = MATCH_BYTES.get(pc)
    if n is None:
        return None
    body = data[1:]
    return (data[0] & 0xF3, bytes(body[:min(n, len(body))]))


@dataclass
class _Entry:
    data: bytes
    t_sent: float
    tries: int
    t_first: float
    rto: float


class Arq:
    """Book-keeping only; the bridge does the sending.

    ``sent(data, now)`` after a request went to the firmware; ``reply(data, now)`` for each
    firmware -> cflib packet returns False when that packet is a duplicate to drop;
    ``due(now)`` yields requests to send again."""

    def __init__(self, rto_s: float = 0.15, rto_unsafe_s: float = 1.0, max_tries: int = 8,
                 dup_window_s: float = 1.0):
        self.rto_s = rto_s
        self.rto_unsafe_s = rto_unsafe_s
        self.max_tries = max_tries
        self.dup_window_s = dup_window_s
        self.open: dict = {}
        self.recent: dict = {}   # key -> expiry of duplicate suppression
        self.retransmits = 0
        self.recovered = 0
        self.gave_up = 0
        self.duplicates_dropped = 0
        self.cancelled = 0       # retransmissions not sent: the reply came while they waited

    def sent(self, data: bytes, now: float):
        key = request_key(data)
        if key is None:
            return
        e = self.open.get(key)
        if e is not None and e.data == data:
            e.t_sent, e.tries = now, e.tries + 1   # a retransmission went out
        else:
            self.open[key] = _Entry(data, now, 1, now,
                                    self.rto_unsafe_s if is_unsafe_to_repeat(data) else self.rto_s)
            self.recent.pop(key, None)

    def reply(self, data: bytes, now: float) -> bool:
        if len(data) < 2:
            return True
        pc = _port_ch(data[0])
        n = MATCH_BYTES.get(pc)
        if n is None:
            return True
        hdr = data[0] & 0xF3
        for k in range(min(n, len(data) - 1), -1, -1):
            key = (hdr, bytes(data[1:1 + k]))
            e = self.open.pop(key, None)
            if e is not None:
                if e.tries > 1:
                    self.recovered += 1
                    self.recent[key] = now + self.dup_window_s
                return True
            exp = self.recent.get(key)
            if exp is not None:
                if now <= exp:
                    self.duplicates_dropped += 1
                    return False
                del self.recent[key]
        return True

    def wanted(self, data: bytes) -> bool:
        """Whether a retransmission of ``data`` that :meth:`due` returned is still to be sent: False once a
        reply answered the request while the copy waited for its slot."""
        key = request_key(data)
        e = self.open.get(key) if key is not None else None
        return e is not None and e.data == data

    def due(self, now: float) -> list[bytes]:
        out = []
        for key, e in list(self.open.items()):
            if now - e.t_sent >= e.rto:
                if e.tries >= self.max_tries:
                    del self.open[key]
                    self.gave_up += 1
                    continue
                e.t_sent = now  # re-armed now; sent() counts the try when it really goes out
                out.append(e.data)
                self.retransmits += 1
        return out

    def stats(self) -> dict:
        return {"arq_retransmits": self.retransmits, "arq_recovered": self.recovered,
                "arq_gave_up": self.gave_up, "arq_duplicates_dropped": self.duplicates_dropped,
                "arq_cancelled": self.cancelled,
                "arq_open": len(self.open)}
