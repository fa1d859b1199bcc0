"""CPX over a serial line: the framing cflib's ``serial://`` driver speaks.

Verified against cflib 0.1.34 (``cflib/crtp/serialdriver.py``, ``cflib/cpx/__init__.py`` and
``cflib/cpx/transports.py``, class ``UARTTransport``):

* A frame is ``0xFF, len, payload[len], xor`` where ``xor`` is the XOR of every previous byte
  of the frame (start and length included) and ``1 <= len <= 100`` (cflib refuses to send more).
* The payload is a CPX packet: byte 0 = ``lastPacket << 6 | source << 3 | destination``,
  byte 1 = ``version << 6 | function`` (version 0, function 3 = CRTP), then the data; for
  CRTP the data is the CRTP header byte and payload.
* ``FF 00`` (a frame of length 0) is the handshake / clear-to-send. cflib opens the port (pyserial
  flushes the input buffer), reads until it sees ``FF 00``, answers ``FF 00`` and only then
  sends. After each frame it sends it waits for an ``FF 00`` before sending the next one, and
  it answers every frame it receives (even one with a bad checksum) with ``FF 00``. The device
  therefore repeats ``FF 00`` until the host answers, answers each host frame with ``FF 00``,
  and sends its own next frame once the host has answered the previous one.

:class:`FrameDecoder` is a streaming, resynchronising decoder; :class:`CpxSerialDevice` is the
device side of the link with no I/O of its own (feed it bytes and a clock, write what it returns).
"""

from __future__ import annotations

from collections import deque
from dataclasses import asdict, dataclass
from enum import IntEnum

from polycc.link.crtp import CrtpPacket, FramingError

START = 0xFF
HANDSHAKE_BYTES = bytes((0xFF, 0x00))
MTU = 100
"""Largest frame payload in bytes (cflib's ``UARTTransport.writePacket`` refuses more)."""


class CpxTarget(IntEnum):
    """CPX routing targets (cflib ``CPXTarget``)."""

    STM32 = 1
    ESP32 = 2
    HOST = 3
    GAP8 = 4


class CpxFunction(IntEnum):
    """CPX functions (cflib ``CPXFunction``)."""

    SYSTEM = 1
    CONSOLE = 2
    CRTP = 3
    WIFI_CTRL = 4
    APP = 5
    TEST = 0x0E
    BOOTLOADER = 0x0F


@dataclass(frozen=True)
class CpxPacket:
    """A CPX packet: routing header plus data bytes."""

    function: CpxFunction
    destination: CpxTarget
    source: CpxTarget
    data: bytes = b""
    last_packet: bool = False

    def encode(self) -> bytes:
        """The 2-byte CPX header followed by the data (the frame payload)."""
        flags = (0x40 if self.last_packet else 0) | (int(self.source) & 7) << 3 | (int(self.destination) & 7)
        return bytes((flags, int(self.function) & 0x3F)) + bytes(self.data)

    @classmethod
    def decode(cls, payload: bytes) -> CpxPacket:
        """Parse a frame payload; raise :class:`FramingError` on a short or invalid header."""
        if len(payload) < 2:
            raise FramingError(f"CPX payload of {len(payload)} bytes is shorter than its 2-byte header")
        flags, func = payload[0], payload[1]
        if func >> 6 != 0:
            raise FramingError(f"unsupported CPX version {func >> 6}")
        try:
            return cls(CpxFunction(func & 0x3F), CpxTarget(flags & 7), CpxTarget((flags >> 3) & 7),
                       bytes(payload[2:]), bool(flags & 0x40))
        except ValueError as e:
            raise FramingError(f"invalid CPX header {payload[:2].hex()}: {e}") from None


def xor_checksum(data: bytes) -> int:
    """XOR of all bytes (0 for empty input)."""
    c = 0
    for b in data:
        c ^= b
    return c


def encode_frame(payload: bytes) -> bytes:
    """``FF, len, payload, xor``; ``payload`` must be 1 to :data:`MTU` bytes."""
    if not 1 <= len(payload) <= MTU:
        raise FramingError(f"frame payload of {len(payload)} bytes (expected 1 to {MTU})")
    head = bytes((START, len(payload))) + bytes(payload)
    return head + bytes((xor_checksum(head),))


def encode_crtp_frame(pk: CrtpPacket, *, source: CpxTarget = CpxTarget.STM32,
                      destination: CpxTarget = CpxTarget.HOST, last_packet: bool = True) -> bytes:
    """A CRTP packet wrapped in CPX and framed; defaults are the device-to-host direction.

    cflib, as host, sends ``source=HOST, destination=STM32, last_packet=False``.
    """
    return encode_frame(CpxPacket(CpxFunction.CRTP, destination, source, pk.encode(), last_packet).encode())


class _Marker:
    def __init__(self, name: str) -> None:
        self.name = name

    def __repr__(self) -> str:
        return self.name


HANDSHAKE = _Marker("HANDSHAKE")
"""Decoder event: an ``FF 00`` handshake / clear-to-send."""
BAD_FRAME = _Marker("BAD_FRAME")
"""Decoder event: a complete frame that failed its checksum or CPX header check."""


@dataclass
class DecoderStats:
    """Counts kept by :class:`FrameDecoder` (all in frames, except ``garbage_bytes``)."""

    frames: int = 0
    handshakes: int = 0
    garbage_bytes: int = 0
    bad_checksum: int = 0
    oversize: int = 0
    truncated: int = 0
    bad_cpx: int = 0

    @property
    def errors(self) -> int:
        """Frame-level errors (garbage bytes are not counted here)."""
        return self.bad_checksum + self.oversize + self.truncated + self.bad_cpx

    def as_dict(self) -> dict[str, int]:
        return asdict(self)


class FrameDecoder:
    """Streaming decoder of ``FF len payload xor`` frames that resynchronises after errors.

    Bytes before a ``0xFF`` are garbage. A length above :data:`MTU` (oversize), a failed
    checksum or an invalid CPX header drops only the ``0xFF`` that started the candidate frame
    and rescans from the next byte, so a good frame hidden behind a false start is still found.
    :meth:`flush` ends a burst (the line went idle): a frame still incomplete then is truncated.

    ``feed`` and ``flush`` return events: :data:`HANDSHAKE`, :class:`CpxPacket` or :data:`BAD_FRAME`.
    """

    def __init__(self, mtu: int = MTU) -> None:
        self.mtu = mtu
        self.stats = DecoderStats()
        self._buf = bytearray()

    @property
    def pending(self) -> int:
        """Bytes held back as the start of an incomplete frame."""
        return len(self._buf)

    def feed(self, data: bytes) -> list:
        """Add received bytes; return the events they complete."""
        self._buf += data
        return self._scan(final=False)

    def flush(self) -> list:
        """The line went idle: decode what can be decoded, count the rest as truncated."""
        return self._scan(final=True)

    def reset(self) -> None:
        """Forget buffered bytes (the link was closed); counters are kept."""
        self._buf.clear()

    def _scan(self, final: bool) -> list:
        buf, st, out = self._buf, self.stats, []
        i, n = 0, len(buf)
        while i < n:
            j = buf.find(START, i)
            if j < 0:
                st.garbage_bytes += n - i
                i = n
                break
            st.garbage_bytes += j - i
            i = j
            if n - i < 2:
                if final:
                    st.truncated += 1
                    i = n
                break
            ln = buf[i + 1]
            if ln == 0:
                st.handshakes += 1
                out.append(HANDSHAKE)
                i += 2
                continue
            if ln > self.mtu:
                st.oversize += 1
                i += 1
                continue
            end = i + ln + 3
            if end > n:
                if not final:
                    break
                st.truncated += 1
                i += 1
                continue
            if xor_checksum(buf[i:end - 1]) != buf[end - 1]:
                st.bad_checksum += 1
                out.append(BAD_FRAME)
                i += 1
                continue
            try:
                pkt = CpxPacket.decode(bytes(buf[i + 2:end - 1]))
            except FramingError:  # most likely a false start that passed the 8-bit checksum
                st.bad_cpx += 1
                out.append(BAD_FRAME)
                i += 1
                continue
            st.frames += 1
            out.append(pkt)
            i = end
        del buf[:i]
        return out


@dataclass
class LinkStats:
    """Counts kept by :class:`CpxSerialDevice` (in frames)."""

    rx_crtp: int = 0
    rx_other_cpx: int = 0
    rx_not_for_us: int = 0
    bad_crtp: int = 0
    tx_frames: int = 0
    tx_dropped: int = 0
    cts_sent: int = 0
    handshakes_sent: int = 0
    cts_timeouts: int = 0
    syncs: int = 0

    def as_dict(self) -> dict[str, int]:
        return asdict(self)


class CpxSerialDevice:
    """Device (Crazyflie) side of cflib's serial CPX link, without I/O.

    Call :meth:`receive` with bytes read from the line, :meth:`send` to queue CRTP packets
    for the host, and write whatever :meth:`output` returns (call it after every receive and
    at least every few milliseconds). Times are in seconds on any monotonic clock.

    * Until the host answers, ``FF 00`` is repeated every ``handshake_period_s``; it is also
      repeated while the host has been silent for ``quiet_s`` (a new host may have opened the
      line without the old one being seen to close; an extra ``FF 00`` only tells a connected
      host that it may send).
    * Each complete frame from the host is answered with ``FF 00``.
    * One frame is in flight at a time: the next is sent when the host answers ``FF 00``, or after
      ``cts_timeout_s`` without an answer (counted in ``stats.cts_timeouts``).
    * Packets queued while no host is synchronised are dropped (``stats.tx_dropped``), as are the
      oldest when more than ``max_queue`` wait.
    """

    def __init__(self, *, handshake_period_s: float = 0.02, quiet_s: float = 0.5,
                 cts_timeout_s: float = 0.1, max_queue: int = 512) -> None:
        self.handshake_period_s = handshake_period_s
        self.quiet_s = quiet_s
        self.cts_timeout_s = cts_timeout_s
        self.max_queue = max_queue
        self.decoder = FrameDecoder()
        self.stats = LinkStats()
        self.synced = False
        self._credit = False
        self._cts_deadline = 0.0
        self._pending_cts = 0
        self._next_handshake = 0.0
        self._last_rx = float("-inf")
        self._txq: deque[bytes] = deque()

    def reset(self) -> None:
        """The host closed the line: drop partial input and queued output, wait for a new host."""
        self.decoder.reset()
        self.synced = False
        self._credit = False
        self._pending_cts = 0
        self._txq.clear()
        self._next_handshake = 0.0

    def receive(self, data: bytes, now: float) -> list[CrtpPacket]:
        """Bytes from the host; return the CRTP packets they complete."""
        self._last_rx = now
        return self._handle(self.decoder.feed(data))

    def idle(self) -> list[CrtpPacket]:
        """The line has been idle: flush the decoder (a partial frame is truncated)."""
        return self._handle(self.decoder.flush())

    def _handle(self, events: list) -> list[CrtpPacket]:
        out: list[CrtpPacket] = []
        st = self.stats
        for ev in events:
            if ev is HANDSHAKE:
                if not self.synced:
                    self.synced = True
                    st.syncs += 1
                self._credit = True
                continue
            if not self.synced:  # a frame proves a host is listening
                self.synced = True
                self._credit = True
                st.syncs += 1
            self._pending_cts += 1
            if ev is BAD_FRAME:
                continue
            if ev.destination != CpxTarget.STM32:
                st.rx_not_for_us += 1
            elif ev.function != CpxFunction.CRTP:
                st.rx_other_cpx += 1  # e.g. cflib's two SYSTEM packets at connect
            else:
                try:
                    out.append(CrtpPacket.decode(ev.data))
                    st.rx_crtp += 1
                except FramingError:
                    st.bad_crtp += 1
        return out

    def send(self, pk: CrtpPacket) -> None:
        """Queue a CRTP packet for the host."""
        if not self.synced:
            self.stats.tx_dropped += 1
            return
        if len(self._txq) >= self.max_queue:
            self._txq.popleft()
            self.stats.tx_dropped += 1
        self._txq.append(encode_crtp_frame(pk))

    def output(self, now: float) -> bytes:
        """Bytes to write to the line now."""
        st = self.stats
        out = bytearray(HANDSHAKE_BYTES * self._pending_cts)
        st.cts_sent += self._pending_cts
        self._pending_cts = 0
        if (not self.synced or now - self._last_rx >= self.quiet_s) and now >= self._next_handshake:
            out += HANDSHAKE_BYTES
            st.handshakes_sent += 1
            self._next_handshake = now + self.handshake_period_s
        if self.synced and self._txq:
            if not self._credit and now >= self._cts_deadline:
                self._credit = True
                st.cts_timeouts += 1
            if self._credit:
                out += self._txq.popleft()
                st.tx_frames += 1
                self._credit = False
                self._cts_deadline = now + self.cts_timeout_s
        return bytes(out)

    @property
    def queued(self) -> int:
        """Frames waiting for the host's clear-to-send."""
        return len(self._txq)
