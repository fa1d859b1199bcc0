"""CRTP over UDP: one raw CRTP packet (header byte + payload) per datagram, nothing else.

This is what cflib's ``udp://host:port`` driver speaks (cflib >= 0.1.32,
``cflib/crtp/udpdriver.py``). Its scan sends the single byte ``FF`` (a null packet on link
port 15, channel 3) to ports 19850-19859 and treats any reply as "a Crazyflie is here".
"""

from __future__ import annotations

from polycc.errors import PolyccError
from polycc.link.crtp import CrtpPacket

DEFAULT_PORT = 19850
"""First port cflib's UDP scan probes."""
SCAN_PROBE = b"\xff"
"""The datagram cflib's scan sends."""
MAX_DATAGRAM = 31
"""Largest valid datagram in bytes (header + 30 payload bytes)."""


def encode_datagram(pk: CrtpPacket) -> bytes:
    """The datagram carrying ``pk``."""
    return pk.encode()


def decode_datagram(data: bytes) -> CrtpPacket:
    """The packet in a datagram; raises :class:`~polycc.link.crtp.FramingError` if malformed."""
    return CrtpPacket.decode(data)


def parse_host_port(text: str, default_port: int | None = None, what: str = "--udp") -> tuple[str, int]:
    """``HOST:PORT`` -> ``(host, port)``, PORT in 0..65535 (0: pick a free one when binding); without
    ``:PORT``, ``default_port`` (an error if None)."""
    host, sep, port = text.rpartition(":")
    if not sep and default_port is not None:
        host, port = text, str(default_port)
    try:
        n = int(port)
    except ValueError:
        n = -1
    if not host or not 0 <= n <= 65535:
        raise PolyccError(f"{what} {text!r}: expected HOST:PORT with PORT in 0-65535, e.g. 127.0.0.1:{DEFAULT_PORT}")
    return host, n


def parse_udp_uri(uri: str) -> tuple[str, int]:
    """``udp://host:port`` -> ``(host, port)``; the port defaults to 19850."""
    if not uri.startswith("udp://") or len(uri) <= len("udp://"):
        raise PolyccError(f"{uri!r} is not a UDP link URI; use udp://HOST:PORT, e.g. udp://127.0.0.1:{DEFAULT_PORT}")
    host, port = parse_host_port(uri[len("udp://"):].rstrip("/"), DEFAULT_PORT, "URI")
    if port == 0:
        raise PolyccError(f"{uri!r} has an invalid port; use udp://HOST:PORT with PORT in 1-65535")
    return host, port
