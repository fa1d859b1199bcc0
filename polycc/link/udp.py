"""CRTP over UDP: one raw CRTP packet (header byte + payload) per datagram, nothing else.

This is what cflib's ``udp://host:port`` driver speaks (cflib >= 0.1.32,
``cflib/crtp/udpdriver.py``). Its scan sends the single byte ``FF`` (a null packet on link
port 15, channel 3) to ports 19850-19859 and treats any reply as "a Crazyflie is here".
"""

from __future__ import annotations

import socket
from urllib.parse import urlparse

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


def parse_udp_uri(uri: str) -> tuple[str, int]:
    """``udp://host:port`` -> ``(host, port)``; the port defaults to 19850."""
    u = urlparse(uri)
    if u.scheme != "udp" or not u.hostname:
        raise PolyccError(f"{uri!r} is not a UDP link URI; use udp://HOST:PORT, e.g. udp://127.0.0.1:{DEFAULT_PORT}")
    try:
        port = u.port or DEFAULT_PORT
    except ValueError:
        raise PolyccError(f"{uri!r} has an invalid port; use udp://HOST:PORT with PORT in 1-65535") from None
    return u.hostname, port


class UdpCrtpClient:
    """A minimal host-side UDP link (for tests and tools that do not use cflib)."""

    def __init__(self, host: str, port: int) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.connect((host, port))

    def send(self, pk: CrtpPacket) -> None:
        self.sock.send(encode_datagram(pk))

    def receive(self, timeout_s: float = 1.0) -> CrtpPacket | None:
        """Next packet, or ``None`` after ``timeout_s`` seconds."""
        self.sock.settimeout(timeout_s)
        try:
            return decode_datagram(self.sock.recv(64))
        except (socket.timeout, ConnectionRefusedError):
            return None

    def close(self) -> None:
        self.sock.close()

    def __enter__(self) -> UdpCrtpClient:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
