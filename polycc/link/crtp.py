"""CRTP packets: the Crazyflie's packet protocol, independent of the transport.

A CRTP packet is one header byte followed by at most 30 payload bytes. The header is
``port << 4 | channel`` with bits 2-3 set, as Bitcraze's ``cflib`` does ("legacy support of
the bootloader"); a decoder ignores those two bits. Verified against cflib 0.1.34
(``cflib/crtp/crtpstack.py``).
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum

MAX_PAYLOAD = 30
"""Largest CRTP payload in bytes (``CRTP_MAX_DATA_SIZE`` in the firmware)."""

RESERVED_BITS = 0x0C
"""Header bits 2-3, which cflib always sets."""


class FramingError(ValueError):
    """Bytes that are not a well-formed packet or frame (a link fault, not a user error)."""


class Port(IntEnum):
    """CRTP ports, as numbered by cflib's ``CRTPPort``."""

    CONSOLE = 0
    PARAM = 2
    COMMANDER = 3
    MEM = 4
    LOG = 5
    LOCALIZATION = 6
    COMMANDER_GENERIC = 7
    SETPOINT_HL = 8
    SUPERVISOR = 9
    PLATFORM = 13
    LINK = 15


class LinkChannel(IntEnum):
    """Channels of the link-control port 15."""

    ECHO = 0
    SOURCE = 1
    NOISE = 2
    NULL = 3


class PlatformChannel(IntEnum):
    """Channels of the platform port 13."""

    COMMAND = 0
    VERSION = 1
    APP = 2


class ParamChannel(IntEnum):
    """Channels of the parameter port 2."""

    TOC = 0
    READ = 1
    WRITE = 2
    MISC = 3


class LogChannel(IntEnum):
    """Channels of the log port 5."""

    TOC = 0
    SETTINGS = 1
    DATA = 2


def make_header(port: int, channel: int) -> int:
    """The header byte cflib sends for ``port`` (0-15) and ``channel`` (0-3)."""
    if not (0 <= port <= 15 and 0 <= channel <= 3):
        raise FramingError(f"CRTP port {port} / channel {channel} out of range (0-15 / 0-3)")
    return (port << 4) | RESERVED_BITS | channel


@dataclass(frozen=True)
class CrtpPacket:
    """One CRTP packet: ``port`` (0-15), ``channel`` (0-3) and up to 30 payload bytes."""

    port: int
    channel: int
    data: bytes = b""

    def __post_init__(self) -> None:
        make_header(self.port, self.channel)
        object.__setattr__(self, "data", bytes(self.data))
        if len(self.data) > MAX_PAYLOAD:
            raise FramingError(f"CRTP payload of {len(self.data)} bytes exceeds {MAX_PAYLOAD}")

    @property
    def header(self) -> int:
        """The header byte, with bits 2-3 set as cflib sets them."""
        return make_header(self.port, self.channel)

    def encode(self) -> bytes:
        """Header byte followed by the payload (1 to 31 bytes)."""
        return bytes((self.header,)) + self.data

    @classmethod
    def decode(cls, raw: bytes) -> CrtpPacket:
        """Parse 1 to 31 bytes; bits 2-3 of the header are ignored."""
        if not 1 <= len(raw) <= MAX_PAYLOAD + 1:
            raise FramingError(f"CRTP packet of {len(raw)} bytes (expected 1 to {MAX_PAYLOAD + 1})")
        return cls(raw[0] >> 4, raw[0] & 0x03, bytes(raw[1:]))

    def __repr__(self) -> str:
        return f"CrtpPacket(port={self.port}, channel={self.channel}, data={self.data.hex()})"
