"""Run a :class:`~polycc.sim.crtp_device.CrtpDevice` in real time over UDP or a serial pty.

* :class:`UdpDeviceServer` -- ``udp://HOST:PORT``: one raw CRTP packet per datagram; replies go
  to the address of the last datagram received. A null packet (the single byte ``FF`` cflib's
  scan sends) is answered with a null packet.
* :class:`SerialDeviceServer` -- ``serial://NAME``: a pseudo-terminal speaking cflib's CPX
  framing (:mod:`polycc.link.cpx_serial`). cflib only connects to a NAME that pyserial's
  ``comports()`` lists. On Linux ``comports()`` globs ``/dev/ttyS*``, ``/dev/ttyUSB*``,
  ``/dev/ttyACM*`` (and a few more) and keeps every match whose ``/sys/class/tty/NAME/device``
  is absent or not a "platform" device -- a symlink ``/dev/ttyUSB-polycc0 -> /dev/pts/N``
  is listed with name ``ttyUSB-polycc0`` (verified with pyserial 3.5). So the server creates
  such a symlink (needs write access to ``/dev``, i.e. root) and the URI is
  ``serial://ttyUSB-polycc0``. cflib's URI pattern allows only ``[-a-zA-Z0-9/.]``, hence no
  underscore in the name. Without the symlink the pty still works for our own clients, and
  :attr:`SerialDeviceServer.uri` explains what is missing.

The device side reads and writes the pty master with ``os.read``/``os.write``: the master is a
file descriptor with no path, which pyserial cannot open; the client side (cflib) uses pyserial.

Each server runs its loop in a background thread (``start``/``stop`` or a ``with`` block); the
loop never dies on bad input (everything is counted) and stops within one poll period.
"""

from __future__ import annotations

import argparse
import errno
import os
import select
import socket
import sys
import threading
import time
import tty
from pathlib import Path

from polycc.errors import PolyccError
from polycc.link.cpx_serial import CpxSerialDevice
from polycc.link.crtp import CrtpPacket, FramingError, LinkChannel, Port
from polycc.link.udp import DEFAULT_PORT, MAX_DATAGRAM, parse_host_port
from polycc.sim.crtp_device import CrtpDevice, DeviceModel

LINK_PREFIX = "ttyUSB-polycc"
"""Default name of the /dev symlink (matches comports()'s /dev/ttyUSB* glob)."""


class _ServerThread:
    """Background loop with clean shutdown; subclasses implement ``_step`` and ``_close``."""

    name = "device-server"

    def __init__(self, device: CrtpDevice, poll_s: float) -> None:
        self.device = device
        self.poll_s = poll_s
        self.loop_errors = 0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self):
        """Start the real-time loop in a daemon thread; returns ``self``."""
        if self._thread is None:
            self._stop.clear()
            self._thread = threading.Thread(target=self._run, name=self.name, daemon=True)
            self._thread.start()
        return self

    def stop(self) -> None:
        """Stop the loop (within one poll period) and release the transport."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None
        self._close()

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                self._step()
            except Exception:  # keep serving; a bug here must not look like a dead drone
                self.loop_errors += 1
                time.sleep(self.poll_s)

    def _step(self) -> None:  # pragma: no cover - abstract
        raise NotImplementedError

    def _close(self) -> None:  # pragma: no cover - abstract
        raise NotImplementedError


class UdpDeviceServer(_ServerThread):
    """The device on a UDP socket bound to ``host:port`` (port 0 picks a free one).

    Attributes: ``address`` (host, port) actually bound, ``uri`` for cflib, ``bad_datagrams``
    (malformed datagrams received), ``peer`` (where replies go).
    """

    name = "udp-device-server"

    def __init__(self, device: CrtpDevice, host: str = "127.0.0.1", port: int = DEFAULT_PORT,
                 poll_s: float = 0.001) -> None:
        super().__init__(device, poll_s)
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            self.sock.bind((host, port))
        except OSError as e:
            self.sock.close()
            raise PolyccError(f"cannot bind UDP {host}:{port} ({e.strerror}); pick another port") from None
        self.sock.setblocking(False)
        self.address = self.sock.getsockname()
        self.peer: tuple[str, int] | None = None
        self.bad_datagrams = 0

    @property
    def uri(self) -> str:
        return f"udp://{self.address[0]}:{self.address[1]}"

    def _send(self, pk: CrtpPacket) -> None:
        if self.peer is not None:
            try:
                self.sock.sendto(pk.encode(), self.peer)
            except OSError:
                pass  # peer gone (ICMP unreachable); UDP has no connection to lose

    def _step(self) -> None:
        ready, _, _ = select.select([self.sock], [], [], self.poll_s)
        while ready:
            try:
                raw, addr = self.sock.recvfrom(2048)
            except (BlockingIOError, InterruptedError):
                break
            except OSError:  # e.g. ECONNREFUSED reported for an earlier sendto
                continue
            self.peer = addr
            if len(raw) > MAX_DATAGRAM:
                self.bad_datagrams += 1
                continue
            try:
                pk = CrtpPacket.decode(raw)
            except FramingError:
                self.bad_datagrams += 1
                continue
            if getattr(self.device.model, "link_cut", False):
                continue  # simulated link loss: nothing gets through
            if pk.port == Port.LINK and pk.channel == LinkChannel.NULL:
                self._send(CrtpPacket(Port.LINK, LinkChannel.NULL))  # answer cflib's scan probe
            for r in self.device.handle(pk):
                self._send(r)
        for pk in self.device.tick():
            if not getattr(self.device.model, "link_cut", False):
                self._send(pk)

    def _close(self) -> None:
        self.sock.close()


def _make_link(target: str, link_dir: Path, name: str | None) -> Path | None:
    """Symlink ``link_dir/name`` -> ``target``; with ``name=None`` the first free
    ``ttyUSB-polyccN``. Returns ``None`` when ``link_dir`` is not writable."""
    candidates = [name] if name else [f"{LINK_PREFIX}{i}" for i in range(100)]
    for cand in candidates:
        path = link_dir / cand
        if os.path.islink(path) and not os.path.exists(path):
            try:  # stale link left by a killed server
                path.unlink()
            except OSError:
                pass
        try:
            os.symlink(target, path)
            return path
        except FileExistsError:
            if name:
                raise PolyccError(f"{path} already exists; choose another --link name or remove it") from None
        except OSError:
            return None
    raise PolyccError(f"no free {LINK_PREFIX}N name in {link_dir}; remove stale links")


class SerialDeviceServer(_ServerThread):
    """The device on a new pseudo-terminal, framed as cflib's serial (CPX) driver expects.

    Args:
        link_name: name of the symlink created in ``link_dir`` so that cflib's ``comports()``
            lists the pty (``None``: the first free ``ttyUSB-polyccN``; ``""``: no symlink).
        link_dir: where the symlink goes (``/dev`` for cflib discovery).
        idle_s: a partial frame older than this (s) is dropped as truncated.

    Attributes: ``pty_path`` (``/dev/pts/N``), ``link_path`` (the symlink or ``None``),
    ``uri`` (``serial://NAME``), ``link`` (the :class:`CpxSerialDevice` with its counters).
    """

    name = "serial-device-server"

    def __init__(self, device: CrtpDevice, link_name: str | None = None, link_dir: str | Path = "/dev",
                 poll_s: float = 0.001, idle_s: float = 0.02) -> None:
        super().__init__(device, poll_s)
        self.idle_s = idle_s
        self.master, slave = os.openpty()
        tty.setraw(slave)
        self.pty_path = os.ttyname(slave)
        os.close(slave)  # so the master sees POLLHUP whenever no client has the pty open
        os.set_blocking(self.master, False)
        self.link = CpxSerialDevice()
        self.link_path = None if link_name == "" else _make_link(self.pty_path, Path(link_dir), link_name)
        self._poll = select.poll()
        self._poll.register(self.master, select.POLLIN)
        self._client_open = False
        self._last_rx = 0.0
        self._out = bytearray()
        self.hangups = 0

    @property
    def uri(self) -> str:
        """``serial://NAME`` for cflib (``cflib.crtp.init_drivers(enable_serial_driver=True)``)."""
        if self.link_path is None:
            raise PolyccError(f"the pty {self.pty_path} has no /dev/{LINK_PREFIX}N symlink, so cflib's "
                              f"comports() will not list it; run the device server as root (it needs to "
                              f"write to /dev)")
        return f"serial://{self.link_path.name}"

    def _hangup(self) -> None:
        if self._client_open:
            self.hangups += 1
            self.link.reset()
            self.device.reset_session()
        self._client_open = False
        self._out.clear()

    def _feed(self, pkts: list[CrtpPacket]) -> None:
        for pk in pkts:
            for r in self.device.handle(pk):
                self.link.send(r)

    def _step(self) -> None:
        events = self._poll.poll(self.poll_s * 1000.0)
        now = time.monotonic()
        mask = events[0][1] if events else 0
        if mask & select.POLLIN:
            try:
                data = os.read(self.master, 4096)
            except BlockingIOError:
                data = b""
            except OSError as e:
                if e.errno != errno.EIO:
                    raise
                self._hangup()
                time.sleep(self.poll_s)
                return
            if data:
                self._client_open = True
                self._last_rx = now
                self._feed(self.link.receive(data, now))
        elif mask & select.POLLHUP:  # no client has the pty open
            self._hangup()
            time.sleep(self.poll_s)
            return
        self._client_open = True
        if self.link.decoder.pending and now - self._last_rx > self.idle_s:
            self._feed(self.link.idle())
        for pk in self.device.tick():
            self.link.send(pk)
        self._out += self.link.output(now)
        if self._out:
            try:
                n = os.write(self.master, self._out)
                del self._out[:n]
            except BlockingIOError:
                pass
            if len(self._out) > 65536:  # client not reading at all
                self._out.clear()

    def _close(self) -> None:
        if self.link_path is not None:
            try:
                if os.readlink(self.link_path) == self.pty_path:
                    self.link_path.unlink()
            except OSError:
                pass
        try:
            os.close(self.master)
        except OSError:
            pass


def main(argv: list[str] | None = None) -> int:
    """Serve a bare device (no app: only the version param) for trying cflib by hand."""
    ap = argparse.ArgumentParser(prog="python -m polycc.sim.device_server", description=main.__doc__)
    ap.add_argument("--udp", metavar="HOST:PORT", help=f"serve udp:// (e.g. 127.0.0.1:{DEFAULT_PORT})")
    ap.add_argument("--serial", action="store_true", help="serve serial:// on a new pty")
    args = ap.parse_args(argv)
    if not args.udp and not args.serial:
        ap.error("give --udp HOST:PORT and/or --serial")
    model = DeviceModel()  # one device per transport: each has its own log blocks
    servers: list[_ServerThread] = []
    try:
        if args.udp:
            host, port = parse_host_port(args.udp)
            servers.append(UdpDeviceServer(CrtpDevice(model), host, port).start())
            print(f"UDP device at {servers[-1].uri}")
        if args.serial:
            srv = SerialDeviceServer(CrtpDevice(model)).start()
            servers.append(srv)
            print(f"serial device on {srv.pty_path}" + (f", cflib URI {srv.uri}" if srv.link_path else
                                                        " (no /dev symlink: cflib cannot find it)"))
        while True:
            time.sleep(1.0)
    except KeyboardInterrupt:
        return 0
    except PolyccError as e:
        print(f"error: {e}", file=sys.stderr)
        return e.exit_code
    finally:
        for s in servers:
            s.stop()


if __name__ == "__main__":
    raise SystemExit(main())
