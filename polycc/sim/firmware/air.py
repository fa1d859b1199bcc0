"""The radio "air" between real-firmware SITL instances: the nRF's peer-to-peer broadcast, simulated.

On a Crazyflie, ``radiolinkSendP2PPacketBroadcast`` makes the nRF51 send a packet that every other
drone on the same radio channel hears and hands to its ``p2pRegisterCB`` callback. In the SITL the
``p2p`` build fix (``support/polycc_sitl_fixes.c``) sends it as a CRTP packet on an unused port; each
instance's bridge (:mod:`polycc.sim.firmware.bridge` ``--air HOST:PORT``) takes those out of the
firmware's traffic and sends them here (stamped with the sender's simulated time), and this hub sends
each one to every *other* registered bridge, which feeds it into its firmware causally in simulated time
(the instances have no common clock; the bridge holds a packet from an instance ahead of it and ages a
neighbour record from one behind it by the lag). A bridge registers with a one-byte hello
(:data:`polycc.sim.firmware.bridge.AIR_HELLO`) from the socket it will use.

The air loses nothing and adds no delay beyond the host's UDP and each bridge's pacing; ``drop`` (a
probability) loses packets on purpose, per receiver, to test the app's staleness handling. One UDP
socket on 127.0.0.1, one daemon thread. Use as a context manager; :attr:`address` is ``(host, port)``.
"""

from __future__ import annotations

import random
import select
import socket
import threading

from polycc.sim.firmware.bridge import AIR_HELLO


class P2PAir:
    """Fan-out hub for P2P broadcasts between bridges (module docstring)."""

    def __init__(self, drop: float = 0.0, seed: int = 0):
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.address = self.sock.getsockname()
        self.drop = float(drop)
        self.rng = random.Random(seed)
        self.members: list[tuple] = []  # bridge addresses, in registration order
        self.stats = {"packets": 0, "delivered": 0, "dropped": 0, "from_unknown": 0}
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="p2p-air", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            r, _, _ = select.select([self.sock], [], [], 0.1)
            if not r:
                continue
            try:
                data, addr = self.sock.recvfrom(2048)
            except OSError:
                return
            if data == AIR_HELLO:
                if addr not in self.members:
                    self.members.append(addr)
                continue
            if addr not in self.members:
                self.stats["from_unknown"] += 1
                continue
            self.stats["packets"] += 1
            for m in self.members:
                if m == addr:
                    continue
                if self.drop > 0.0 and self.rng.random() < self.drop:
                    self.stats["dropped"] += 1
                    continue
                try:
                    self.sock.sendto(data, m)
                    self.stats["delivered"] += 1
                except OSError:
                    self.stats["dropped"] += 1

    @property
    def arg(self) -> str:
        """The bridge option value: ``HOST:PORT``."""
        return f"{self.address[0]}:{self.address[1]}"

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=1.0)
        self.sock.close()

    def __enter__(self) -> P2PAir:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
