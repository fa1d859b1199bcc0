"""A simulated Crazyflie CRTP endpoint that Bitcraze's ``cflib`` can connect to.

The device answers everything cflib (verified against 0.1.34) needs to connect and work:
link source ("Bitcraze Crazyflie"), platform protocol/firmware version, log reset, log and
param TOCs (v1 and v2 commands), memory count (0), param read/write and the misc commands,
log blocks and periodic log data, link echo, the app channel and setpoints. Unknown ports and
commands, and malformed packets, are counted and otherwise ignored; nothing a client sends makes
:meth:`CrtpDevice.handle` raise.

The device knows nothing about the app. The app is a :class:`DeviceModel`: its param and log
tables (the SITL app fills them from the C app's ``PARAM_*``/``LOG_*`` tables collected by the
firmware shims), a clock and two callbacks. The device is transport-free: feed it packets with
:meth:`CrtpDevice.handle`, call :meth:`CrtpDevice.tick` often (every millisecond or so) for log
data; :mod:`polycc.sim.device_server` runs it over UDP and a serial pty.
"""

from __future__ import annotations

import errno
import math
import struct
import threading
import time
import zlib
from collections.abc import Callable
from dataclasses import asdict, dataclass, field

from polycc.errors import PolyccError
from polycc.link.crtp import MAX_PAYLOAD, CrtpPacket, LinkChannel, LogChannel, ParamChannel, PlatformChannel, Port
from polycc.version import __version__

PROTOCOL_VERSION = 11
"""CRTP protocol version reported to clients. >= 4 selects the v2 TOC/param/log commands; 11
selects the v2 param misc replies; below 12, so cflib uses the platform port, not the
supervisor port (9), for arming."""

LOG_MAX_BLOCKS = 16
LOG_MAX_OPS = 128
LOG_CATCH_UP_MS = 1000
"""A log block at most this far behind (ms) sends every missed packet; further behind it skips."""
LOG_MAX_LEN = MAX_PAYLOAD - 4
"""Bytes of values in one log data packet (block id and 24-bit timestamp take 4)."""

# ctype: (struct format, param TOC type id, log TOC type id or None)
CTYPES: dict[str, tuple[str, int, int | None]] = {
    "int8_t": ("<b", 0x00, 0x04),
    "int16_t": ("<h", 0x01, 0x05),
    "int32_t": ("<i", 0x02, 0x06),
    "int64_t": ("<q", 0x03, None),
    "FP16": ("<e", 0x05, 0x08),
    "float": ("<f", 0x06, 0x07),
    "double": ("<d", 0x07, None),
    "uint8_t": ("<B", 0x08, 0x01),
    "uint16_t": ("<H", 0x09, 0x02),
    "uint32_t": ("<L", 0x0A, 0x03),
    "uint64_t": ("<Q", 0x0B, None),
}
LOG_CTYPE_BY_ID = {v[2]: k for k, v in CTYPES.items() if v[2] is not None}
PARAM_READ_ONLY = 0x40
_FLOAT_MAX = {"<e": 65504.0, "<f": 3.4028234663852886e38, "<d": math.inf}

# Channel commands (cflib names)
TOC_ITEM_V1, TOC_INFO_V1, TOC_ITEM_V2, TOC_INFO_V2 = 0, 1, 2, 3
LOG_CREATE, LOG_APPEND, LOG_DELETE, LOG_START, LOG_STOP, LOG_RESET, LOG_CREATE_V2, LOG_APPEND_V2 = range(8)
(MISC_SETBYNAME, MISC_VALUE_UPDATED, MISC_GET_EXTENDED_TYPE, MISC_PERSISTENT_STORE, MISC_PERSISTENT_GET_STATE,
 MISC_PERSISTENT_CLEAR, MISC_GET_DEFAULT_VALUE, MISC_GET_EXTENDED_TYPE_V2, MISC_GET_DEFAULT_VALUE_V2) = range(9)
MEM_INFO_VER, MEM_INFO_NBR, MEM_INFO_DETAILS = 0, 1, 2
VERSION_GET_PROTOCOL, VERSION_GET_FIRMWARE, VERSION_GET_DEVICE_TYPE = 0, 1, 2
LINK_SOURCE_NAME = b"Bitcraze Crazyflie"


def pack_value(ctype: str, value: float) -> bytes:
    """``value`` as the little-endian C type ``ctype``, converted the way a C cast would be
    (integers wrap, NaN becomes 0, out-of-range floats become +-inf)."""
    fmt = CTYPES[ctype][0]
    if fmt in _FLOAT_MAX:
        v = float(value)
        if abs(v) > _FLOAT_MAX[fmt] and not math.isinf(v):
            v = math.copysign(math.inf, v)
        return struct.pack(fmt, v)
    if hasattr(value, "__index__"):
        v = value.__index__()
    else:
        v = float(value)
        v = int(v) if math.isfinite(v) else 0
    size = struct.calcsize(fmt)
    v &= (1 << (8 * size)) - 1
    if fmt[1].islower() and v >= 1 << (8 * size - 1):
        v -= 1 << (8 * size)
    return struct.pack(fmt, v)


def unpack_value(ctype: str, raw: bytes) -> float | int:
    """Inverse of :func:`pack_value` (raises ``struct.error`` on a wrong length)."""
    return struct.unpack(CTYPES[ctype][0], raw)[0]


def ctype_from_param_type(type_byte: int) -> tuple[str, bool]:
    """The firmware's ``PARAM_*`` type byte (``param.h``) -> ``(ctype, read_only)``.

    The low nibble is the wire type (``PARAM_FLOAT`` = 0x06 -> ``'float'``), 0x40 is ``PARAM_RONLY``;
    ``PARAM_CORE``, ``PARAM_EXTENDED`` and ``PARAM_PERSISTENT`` do not change the type.
    """
    for ctype, (_, pid, _) in CTYPES.items():
        if pid == type_byte & 0x0F:
            return ctype, bool(type_byte & PARAM_READ_ONLY)
    raise PolyccError(f"param type byte 0x{type_byte:02x} has no C type (low nibble 0x4 is not used)")


def ctype_from_log_type(type_byte: int) -> str:
    """The firmware's ``LOG_*`` type byte (``log.h``; ``LOG_UINT8`` = 1 ... ``LOG_FP16`` = 8,
    flags such as ``LOG_CORE`` = 0x20 ignored) -> ctype."""
    try:
        return LOG_CTYPE_BY_ID[type_byte & 0x0F]
    except KeyError:
        raise PolyccError(f"log type byte 0x{type_byte:02x} has no C type (expected 1-8)") from None


def _check_name(kind: str, group: str, name: str, ctype: str) -> None:
    for part in (group, name):
        if not part or not part.isascii() or "." in part or "\0" in part:
            raise PolyccError(f"{kind} {group}.{name}: group and name must be non-empty ASCII without '.' or NUL")
    if len(group) + len(name) > MAX_PAYLOAD - 6:
        raise PolyccError(f"{kind} {group}.{name}: group and name together exceed {MAX_PAYLOAD - 6} characters "
                          f"(a TOC entry must fit one CRTP packet); shorten the name")
    if ctype not in CTYPES:
        raise PolyccError(f"{kind} {group}.{name}: unknown C type {ctype!r}; use one of {', '.join(CTYPES)}")


@dataclass
class ParamEntry:
    """One parameter: ``group.name`` of C type ``ctype`` (e.g. ``'uint8_t'``, ``'float'``).

    ``get()`` returns the current value; ``set(value)`` stores a new one (an ``int`` for integer
    types, a ``float`` already rounded to ``ctype`` for floating ones). A parameter without
    ``set`` is read-only. Units are the app's own.
    """

    group: str
    name: str
    ctype: str
    get: Callable[[], float]
    set: Callable[[float], None] | None = None
    read_only: bool = False

    def __post_init__(self) -> None:
        _check_name("param", self.group, self.name, self.ctype)
        if self.set is None:
            self.read_only = True

    @property
    def full_name(self) -> str:
        return f"{self.group}.{self.name}"


@dataclass
class LogEntry:
    """One log variable: ``group.name`` of C type ``ctype`` whose current value is ``get()``.

    ``ctype`` must be one of the log types: ``uint8_t``, ``uint16_t``, ``uint32_t``, ``int8_t``,
    ``int16_t``, ``int32_t``, ``float``, ``FP16``.
    """

    group: str
    name: str
    ctype: str
    get: Callable[[], float]

    def __post_init__(self) -> None:
        _check_name("log variable", self.group, self.name, self.ctype)
        if CTYPES[self.ctype][2] is None:
            raise PolyccError(f"log variable {self.group}.{self.name}: {self.ctype} cannot be logged; "
                              f"use one of {', '.join(LOG_CTYPE_BY_ID.values())}")

    @property
    def full_name(self) -> str:
        return f"{self.group}.{self.name}"


class DeviceModel:
    """What the simulated Crazyflie exposes; the SITL app (:mod:`polycc.sim.sitl_device`) subclasses this.

    Attributes:
        params: the parameter table, in TOC order (ids are list indices).
        logs: the log table, in TOC order.
        lock: held by :class:`CrtpDevice` around every call into the model (params, logs and
            callbacks), so a simulation thread that holds it too sees consistent state.

    The methods are called from the device server's thread, with ``lock`` held.
    """

    def __init__(self, params: list[ParamEntry] | None = None, logs: list[LogEntry] | None = None) -> None:
        self.params: list[ParamEntry] = list(params or [])
        self.logs: list[LogEntry] = list(logs or [])
        self.lock = threading.RLock()
        self._t0 = time.monotonic()

    def time_ms(self) -> int:
        """Device time in milliseconds (log timestamps and log periods use it). Default: wall
        time since the model was created."""
        return int((time.monotonic() - self._t0) * 1000.0)

    def on_setpoint(self, kind: str, values: dict[str, float]) -> None:
        """A setpoint or flight command arrived; see :data:`SETPOINT_KINDS` for kinds and fields."""

    def on_appchannel(self, data: bytes) -> bytes | None:
        """An app-channel packet (port 13, channel 2; up to 30 bytes) arrived; the bytes
        returned (up to 30) are sent back on the app channel, ``None`` sends nothing."""
        return None


SETPOINT_KINDS: dict[str, str] = {
    "rpyt": "port 3: roll, pitch (deg), yawrate (deg/s), thrust (0-65535), as on the wire (cflib negates pitch)",
    "stop": "port 7: stop the motors",
    "velocity_world": "port 7: vx, vy, vz (m/s), yawrate (deg/s); legacy type 1 normalised to this sign",
    "zdistance": "port 7: roll, pitch (deg), yawrate (deg/s), zdistance (m)",
    "hover": "port 7: vx, vy (m/s, body frame), yawrate (deg/s), zdistance (m)",
    "position": "port 7: x, y, z (m), yaw (deg)",
    "full_state": "port 7: x, y, z (m), vx, vy, vz (m/s), ax, ay, az (m/s^2), qx, qy, qz, qw, "
                  "rollrate, pitchrate, yawrate (rad/s: the wire carries 1/1000 units, which the "
                  "firmware reads as mrad/s although cflib's docstring says deg/s)",
    "manual": "port 7: roll, pitch (deg), yawrate (deg/s), thrust (0-65535), rate (0/1)",
    "notify_setpoint_stop": "port 7 ch 1: remain_valid_ms (ms)",
    "hl_takeoff": "port 8: group_mask, height (m), yaw (rad), use_current_yaw (0/1), duration (s)",
    "hl_land": "port 8: group_mask, height (m), yaw (rad), use_current_yaw (0/1), duration (s)",
    "hl_stop": "port 8: group_mask",
    "hl_go_to": "port 8: group_mask, relative (0/1), linear (0/1), x, y, z (m), yaw (rad), duration (s)",
    "hl_set_group_mask": "port 8: group_mask",
    "arm": "port 13 ch 0: arm (1 to arm, 0 to disarm)",
    "crash_recovery": "port 13 ch 0: no fields",
}
"""Setpoint kinds passed to :meth:`DeviceModel.on_setpoint`, with their fields and units."""

_GENERIC = {  # port 7 type -> (kind, struct format after the type byte, field names, yawrate sign)
    1: ("velocity_world", "<ffff", ("vx", "vy", "vz", "yawrate"), -1.0),
    2: ("zdistance", "<ffff", ("roll", "pitch", "yawrate", "zdistance"), -1.0),
    5: ("hover", "<ffff", ("vx", "vy", "yawrate", "zdistance"), -1.0),
    7: ("position", "<ffff", ("x", "y", "z", "yaw"), 1.0),
    8: ("velocity_world", "<ffff", ("vx", "vy", "vz", "yawrate"), 1.0),
    9: ("zdistance", "<ffff", ("roll", "pitch", "yawrate", "zdistance"), 1.0),
    10: ("hover", "<ffff", ("vx", "vy", "yawrate", "zdistance"), 1.0),
    11: ("manual", "<fffHB", ("roll", "pitch", "yawrate", "thrust", "rate"), 1.0),
}
_HL = {  # port 8 command -> (kind, struct format after the command byte, field names)
    0: ("hl_set_group_mask", "<B", ("group_mask",)),
    3: ("hl_stop", "<B", ("group_mask",)),
    4: ("hl_go_to", "<BBfffff", ("group_mask", "relative", "x", "y", "z", "yaw", "duration")),
    7: ("hl_takeoff", "<Bff?f", ("group_mask", "height", "yaw", "use_current_yaw", "duration")),
    8: ("hl_land", "<Bff?f", ("group_mask", "height", "yaw", "use_current_yaw", "duration")),
    12: ("hl_go_to", "<BBBfffff", ("group_mask", "relative", "linear", "x", "y", "z", "yaw", "duration")),
}


def _decompress_quaternion(comp: int) -> tuple[float, float, float, float]:
    """Firmware ``quatdecompress``: 32-bit smallest-three encoding -> (qx, qy, qz, qw)."""
    q = [0.0] * 4
    mask = (1 << 9) - 1
    largest = comp >> 30
    ss = 0.0
    for i in range(3, -1, -1):
        if i != largest:
            mag, neg = comp & mask, (comp >> 9) & 1
            comp >>= 10
            q[i] = (-1.0 if neg else 1.0) * mag / mask / math.sqrt(2.0)
            ss += q[i] * q[i]
    q[largest] = math.sqrt(max(0.0, 1.0 - ss))
    return q[0], q[1], q[2], q[3]


@dataclass
class DeviceStats:
    """Counts kept by :class:`CrtpDevice` (in packets)."""

    rx: int = 0
    tx: int = 0
    unknown_port: int = 0
    unknown_command: int = 0
    malformed: int = 0
    handler_errors: int = 0
    setpoints: int = 0
    appchannel_rx: int = 0
    appchannel_tx: int = 0
    param_writes: int = 0
    log_data: int = 0
    log_overruns: int = 0

    def as_dict(self) -> dict[str, int]:
        return asdict(self)


@dataclass
class _LogBlock:
    ops: list[tuple[LogEntry, str]] = field(default_factory=list)  # (variable, fetch-as ctype)
    period_ms: int = 0
    next_due_ms: int = 0
    running: bool = False

    @property
    def size(self) -> int:
        return sum(struct.calcsize(CTYPES[c][0]) for _, c in self.ops)


class CrtpDevice:
    """The protocol half of a simulated Crazyflie; see the module docstring.

    Args:
        model: the app's params, logs, clock and callbacks.
        protocol_version: CRTP protocol version reported (>= 4; default :data:`PROTOCOL_VERSION`).
        firmware_version: string returned to a firmware-version query.
        version_param: ``(group, name)`` of an extra read-only ``uint32_t`` parameter holding the
            polycc version as ``major << 16 | minor << 8 | patch``; ``None`` to leave it out.
    """

    def __init__(self, model: DeviceModel, *, protocol_version: int = PROTOCOL_VERSION,
                 firmware_version: str = f"polycc-sitl {__version__}",
                 version_param: tuple[str, str] | None = ("firmware", "polyccVersion")) -> None:
        self.model = model
        self.protocol_version = protocol_version
        self.firmware_version = firmware_version
        self.stats = DeviceStats()
        self._blocks: dict[int, _LogBlock] = {}
        self._version_param = version_param
        self.rebuild_tocs()

    # ------------------------------------------------------------------ TOCs
    def rebuild_tocs(self) -> None:
        """Re-read ``model.params`` and ``model.logs`` (call after changing them; clients must
        then reconnect, as with a real Crazyflie flashed with new firmware)."""
        with self.model.lock:
            self._rebuild_tocs()

    def _rebuild_tocs(self) -> None:
        params = list(self.model.params)
        logs = list(self.model.logs)
        names = {p.full_name for p in params}
        if self._version_param and ".".join(self._version_param) not in names:
            parts = (__version__.split("+")[0].split(".") + ["0", "0"])[:3]
            code = sum(int("".join(ch for ch in x if ch.isdigit()) or 0) << s for x, s in zip(parts, (16, 8, 0)))
            params.append(ParamEntry(*self._version_param, "uint32_t", get=lambda: code))
        for kind, table in (("param", params), ("log variable", logs)):
            seen: set[str] = set()
            for e in table:
                if e.full_name in seen:
                    raise PolyccError(f"{kind} {e.full_name} is defined twice; names in a TOC must be unique")
                seen.add(e.full_name)
        if len(params) > 0xFFFF or len(logs) > 0xFFFF:
            raise PolyccError("more than 65535 params or log variables; a CRTP TOC cannot hold them")
        self.params, self.logs = params, logs
        self._param_ids = {p.full_name: i for i, p in enumerate(params)}
        self._param_items = [bytes((CTYPES[p.ctype][1] | (PARAM_READ_ONLY if p.read_only else 0),))
                             + p.group.encode() + b"\0" + p.name.encode() + b"\0" for p in params]
        self._log_items = [bytes((CTYPES[v.ctype][2],)) + v.group.encode() + b"\0" + v.name.encode() + b"\0"
                           for v in logs]
        self.param_crc = zlib.crc32(b"".join(self._param_items))
        self.log_crc = zlib.crc32(b"".join(self._log_items))
        self._param_defaults = {}
        self._blocks.clear()

    # ------------------------------------------------------------------ entry points
    def handle(self, pk: CrtpPacket) -> list[CrtpPacket]:
        """Process one packet from the client; return the replies (never raises)."""
        self.stats.rx += 1
        try:
            with self.model.lock:
                replies = self._dispatch(pk)
        except (IndexError, struct.error, UnicodeDecodeError, ValueError):
            self.stats.malformed += 1
            replies = []
        except Exception:  # a model callback failed; the link must survive it
            self.stats.handler_errors += 1
            replies = []
        self.stats.tx += len(replies)
        return replies

    def tick(self) -> list[CrtpPacket]:
        """Log data packets due at the model's current time (call every millisecond or so).

        Every period produces one packet, stamped with its scheduled time in ms, so a late call
        sends the missed packets at once; a block more than ``LOG_CATCH_UP_MS`` (or 10 periods)
        behind skips ahead instead (counted in ``stats.log_overruns``).
        """
        out: list[CrtpPacket] = []
        pending = getattr(self.model, "outgoing_appchannel", None)
        if pending is not None:
            with self.model.lock:
                for data in pending():
                    out.append(CrtpPacket(Port.PLATFORM, PlatformChannel.APP, bytes(data)[:MAX_PAYLOAD]))
            self.stats.appchannel_tx += len(out)
            self.stats.tx += len(out)
        if not any(b.running for b in self._blocks.values()):
            return out
        try:
            with self.model.lock:
                now = self.model.time_ms()
                for bid, b in list(self._blocks.items()):
                    if not b.running:
                        continue
                    if now - b.next_due_ms > max(LOG_CATCH_UP_MS, 10 * b.period_ms):
                        self.stats.log_overruns += 1
                        b.next_due_ms = now
                    while b.running and now >= b.next_due_ms:
                        out.append(self._log_packet(bid, b, b.next_due_ms))
                        if b.period_ms == 0:
                            b.running = False
                        b.next_due_ms += b.period_ms
        except Exception:
            self.stats.handler_errors += 1
        self.stats.log_data += len(out)
        self.stats.tx += len(out)
        return out

    def reset_session(self) -> None:
        """The client went away: delete all log blocks."""
        self._blocks.clear()

    @property
    def running_blocks(self) -> int:
        return sum(b.running for b in self._blocks.values())

    # ------------------------------------------------------------------ dispatch
    def _dispatch(self, pk: CrtpPacket) -> list[CrtpPacket]:
        port, ch, d = pk.port, pk.channel, pk.data
        if port == Port.LINK:
            if ch == LinkChannel.ECHO:
                return [pk]
            if ch == LinkChannel.SOURCE:
                return [CrtpPacket(Port.LINK, LinkChannel.SOURCE, LINK_SOURCE_NAME.ljust(MAX_PAYLOAD, b"\0"))]
            return []  # noise and null packets need no answer
        if port == Port.PLATFORM:
            return self._platform(ch, d)
        if port == Port.LOG:
            return self._log(ch, d)
        if port == Port.PARAM:
            return self._param(ch, d)
        if port == Port.MEM:
            return self._mem(ch, d)
        if port in (Port.COMMANDER, Port.COMMANDER_GENERIC, Port.SETPOINT_HL):
            return self._setpoint(port, ch, d)
        if port == Port.CONSOLE:
            return []
        self.stats.unknown_port += 1
        return []

    def _unknown(self) -> list[CrtpPacket]:
        self.stats.unknown_command += 1
        return []

    def _platform(self, ch: int, d: bytes) -> list[CrtpPacket]:
        if ch == PlatformChannel.APP:
            self.stats.appchannel_rx += 1
            reply = self.model.on_appchannel(bytes(d))
            if reply is None:
                return []
            self.stats.appchannel_tx += 1
            return [CrtpPacket(Port.PLATFORM, PlatformChannel.APP, bytes(reply)[:MAX_PAYLOAD])]
        if ch == PlatformChannel.VERSION:
            cmd = d[0]
            if cmd == VERSION_GET_PROTOCOL:
                return [CrtpPacket(Port.PLATFORM, ch, struct.pack("<Bi", cmd, self.protocol_version))]
            if cmd in (VERSION_GET_FIRMWARE, VERSION_GET_DEVICE_TYPE):
                text = self.firmware_version if cmd == VERSION_GET_FIRMWARE else "polycc SITL"
                return [CrtpPacket(Port.PLATFORM, ch, bytes((cmd,)) + text.encode()[:MAX_PAYLOAD - 1])]
            return self._unknown()
        if ch == PlatformChannel.COMMAND:
            cmd = d[0]
            if cmd == 1:
                self._emit_setpoint("arm", {"arm": int(d[1] != 0)})
            elif cmd == 2:
                self._emit_setpoint("crash_recovery", {})
            elif cmd not in (0, 3):  # continuous wave, user notification: nothing to simulate
                return self._unknown()
            return []
        return self._unknown()

    def _emit_setpoint(self, kind: str, values: dict[str, float]) -> None:
        self.stats.setpoints += 1
        self.model.on_setpoint(kind, values)

    def _setpoint(self, port: int, ch: int, d: bytes) -> list[CrtpPacket]:
        if port == Port.COMMANDER and ch == 0:
            r, p, y, t = struct.unpack("<fffH", d[:14])
            self._emit_setpoint("rpyt", {"roll": r, "pitch": p, "yawrate": y, "thrust": t})
        elif port == Port.COMMANDER_GENERIC and ch == 0:
            typ = d[0]
            if typ == 0:
                self._emit_setpoint("stop", {})
            elif typ == 6:
                v = struct.unpack("<hhhhhhhhhIhhh", d[1:31])
                vals = dict(zip(("x", "y", "z", "vx", "vy", "vz", "ax", "ay", "az"), (x / 1000.0 for x in v[:9])))
                vals.update(zip(("qx", "qy", "qz", "qw"), _decompress_quaternion(v[9])))
                vals.update(zip(("rollrate", "pitchrate", "yawrate"), (x / 1000.0 for x in v[10:])))
                self._emit_setpoint("full_state", vals)
            elif typ in _GENERIC:
                kind, fmt, names, ysign = _GENERIC[typ]
                vals = dict(zip(names, struct.unpack(fmt, d[1:1 + struct.calcsize(fmt)])))
                if "yawrate" in vals:
                    vals["yawrate"] *= ysign
                self._emit_setpoint(kind, vals)
            else:
                return self._unknown()
        elif port == Port.COMMANDER_GENERIC and ch == 1 and d[0] == 0:
            self._emit_setpoint("notify_setpoint_stop", {"remain_valid_ms": struct.unpack("<I", d[1:5])[0]})
        elif port == Port.SETPOINT_HL and ch == 0 and d[0] in _HL:
            kind, fmt, names = _HL[d[0]]
            vals = dict(zip(names, struct.unpack(fmt, d[1:1 + struct.calcsize(fmt)])))
            self._emit_setpoint(kind, {k: (int(v) if isinstance(v, bool) else v) for k, v in vals.items()})
        else:
            return self._unknown()
        return []

    def _mem(self, ch: int, d: bytes) -> list[CrtpPacket]:
        if ch != 0:
            return self._unknown()
        cmd = d[0]
        if cmd == MEM_INFO_NBR:
            return [CrtpPacket(Port.MEM, 0, bytes((MEM_INFO_NBR, 0)))]
        if cmd == MEM_INFO_VER:
            return [CrtpPacket(Port.MEM, 0, bytes((MEM_INFO_VER, 1)))]
        if cmd == MEM_INFO_DETAILS:  # no memories: a short answer, which cflib accepts
            return [CrtpPacket(Port.MEM, 0, bytes((MEM_INFO_DETAILS, d[1])))]
        return self._unknown()

    # ------------------------------------------------------------------ TOCs
    def _toc(self, port: int, d: bytes, items: list[bytes], crc: int) -> list[CrtpPacket]:
        cmd = d[0]
        n = len(items)
        if cmd == TOC_INFO_V2:
            extra = bytes((LOG_MAX_BLOCKS, LOG_MAX_OPS)) if port == Port.LOG else b""
            return [CrtpPacket(port, 0, struct.pack("<BHI", cmd, n, crc) + extra)]
        if cmd == TOC_INFO_V1:
            extra = bytes((LOG_MAX_BLOCKS, LOG_MAX_OPS)) if port == Port.LOG else b""
            return [CrtpPacket(port, 0, struct.pack("<BBI", cmd, min(n, 255), crc) + extra)]
        if cmd in (TOC_ITEM_V2, TOC_ITEM_V1):
            v2 = cmd == TOC_ITEM_V2
            idx = struct.unpack("<H", d[1:3])[0] if v2 else d[1]
            if idx >= n or (not v2 and idx > 255):
                self.stats.malformed += 1
                return []
            head = struct.pack("<BH", cmd, idx) if v2 else bytes((cmd, idx))
            return [CrtpPacket(port, 0, head + items[idx])]
        return self._unknown()

    # ------------------------------------------------------------------ params
    def _param_id(self, d: bytes, v2: bool) -> tuple[int, int]:
        """(id, bytes used) from the start of a param packet."""
        return (struct.unpack("<H", d[:2])[0], 2) if v2 else (d[0], 1)

    def _param(self, ch: int, d: bytes) -> list[CrtpPacket]:
        v2 = self.protocol_version >= 4
        if ch == ParamChannel.TOC:
            return self._toc(Port.PARAM, d, self._param_items, self.param_crc)
        if ch == ParamChannel.READ:
            pid, k = self._param_id(d, v2)
            if pid >= len(self.params):
                return [CrtpPacket(Port.PARAM, ch, d[:k] + bytes((errno.ENOENT,)))]
            p = self.params[pid]
            status = b"\0" if v2 else b""
            return [CrtpPacket(Port.PARAM, ch, d[:k] + status + self._value(p))]
        if ch == ParamChannel.WRITE:
            pid, k = self._param_id(d, v2)
            if pid >= len(self.params):
                return [CrtpPacket(Port.PARAM, ch, d[:k] + bytes((errno.ENOENT,)))]
            p = self.params[pid]
            if not p.read_only:
                self._param_set(p, d[k:])
            return [CrtpPacket(Port.PARAM, ch, d[:k] + self._value(p))]
        if ch == ParamChannel.MISC:
            return self._param_misc(d)
        return self._unknown()

    def _value(self, e: ParamEntry | LogEntry, ctype: str | None = None) -> bytes:
        """``e.get()`` packed as ``ctype`` (default: its own type). If the model raises, 0 is sent
        (and counted in ``stats.handler_errors``): cflib stalls forever on a missing reply."""
        try:
            v = e.get()
        except Exception:
            self.stats.handler_errors += 1
            v = 0
        return pack_value(ctype or e.ctype, v)

    def _param_set(self, p: ParamEntry, raw: bytes) -> None:
        size = struct.calcsize(CTYPES[p.ctype][0])
        value = unpack_value(p.ctype, raw[:size])  # struct.error on a short packet: malformed
        if p.full_name not in self._param_defaults:
            self._param_defaults[p.full_name] = self._value(p)
        try:
            p.set(value)
        except Exception:  # still answered (with the unchanged value) so the client goes on
            self.stats.handler_errors += 1
            return
        self.stats.param_writes += 1

    def _default(self, p: ParamEntry) -> bytes:
        """A parameter's default: its value before the first write from a client."""
        return self._param_defaults.get(p.full_name) or self._value(p)

    def _param_misc(self, d: bytes) -> list[CrtpPacket]:
        cmd = d[0]
        if cmd == MISC_SETBYNAME:
            group, name, rest = d[1:].split(b"\0", 2)
            pid = self._param_ids.get(f"{group.decode()}.{name.decode()}")
            head = d[:3 + len(group) + len(name)]
            if pid is None:
                return [CrtpPacket(Port.PARAM, 3, head + bytes((errno.ENOENT,)))]
            p = self.params[pid]
            if p.read_only:
                return [CrtpPacket(Port.PARAM, 3, head + bytes((errno.EACCES,)))]
            if rest[0] != CTYPES[p.ctype][1]:
                return [CrtpPacket(Port.PARAM, 3, head + bytes((errno.EINVAL,)))]
            self._param_set(p, rest[1:])
            value = self._value(p)
            return [CrtpPacket(Port.PARAM, 3, head + b"\0"),
                    CrtpPacket(Port.PARAM, 3, struct.pack("<BH", MISC_VALUE_UPDATED, pid) + value)]
        if cmd in (MISC_GET_EXTENDED_TYPE, MISC_GET_EXTENDED_TYPE_V2, MISC_GET_DEFAULT_VALUE,
                   MISC_GET_DEFAULT_VALUE_V2, MISC_PERSISTENT_STORE, MISC_PERSISTENT_GET_STATE,
                   MISC_PERSISTENT_CLEAR):
            pid = struct.unpack("<H", d[1:3])[0]
            head = d[:3]
            if pid >= len(self.params):
                return [CrtpPacket(Port.PARAM, 3, head + bytes((errno.ENOENT,)))]
            if cmd == MISC_GET_EXTENDED_TYPE:
                return [CrtpPacket(Port.PARAM, 3, head + b"\0")]
            if cmd == MISC_GET_EXTENDED_TYPE_V2:
                return [CrtpPacket(Port.PARAM, 3, head + b"\0\0")]
            if cmd == MISC_GET_DEFAULT_VALUE:
                return [CrtpPacket(Port.PARAM, 3, head + self._default(self.params[pid]))]
            if cmd == MISC_GET_DEFAULT_VALUE_V2:
                return [CrtpPacket(Port.PARAM, 3, head + b"\0" + self._default(self.params[pid]))]
            return [CrtpPacket(Port.PARAM, 3, head + bytes((errno.ENOENT,)))]  # nothing is persistent
        return self._unknown()

    # ------------------------------------------------------------------ logs
    def _log(self, ch: int, d: bytes) -> list[CrtpPacket]:
        if ch == LogChannel.TOC:
            return self._toc(Port.LOG, d, self._log_items, self.log_crc)
        if ch != LogChannel.SETTINGS:
            return self._unknown()
        cmd = d[0]
        bid = d[1] if len(d) > 1 else 0
        err = self._log_settings(cmd, bid, d)
        if err is None:
            return []
        return [CrtpPacket(Port.LOG, ch, bytes((cmd, bid, err)))]

    def _log_settings(self, cmd: int, bid: int, d: bytes) -> int | None:
        blocks = self._blocks
        if cmd in (LOG_CREATE, LOG_CREATE_V2, LOG_APPEND, LOG_APPEND_V2):
            create = cmd in (LOG_CREATE, LOG_CREATE_V2)
            if create and bid in blocks:
                return errno.EEXIST
            if create and len(blocks) >= LOG_MAX_BLOCKS:
                return errno.ENOMEM
            if not create and bid not in blocks:
                return errno.ENOENT
            ops = self._parse_log_ops(d[2:], v2=cmd in (LOG_CREATE_V2, LOG_APPEND_V2))
            if ops is None:
                return errno.ENOENT
            block = _LogBlock() if create else blocks[bid]
            if sum(len(b.ops) for b in blocks.values()) + len(ops) > LOG_MAX_OPS:
                return errno.ENOMEM
            if block.size + sum(struct.calcsize(CTYPES[c][0]) for _, c in ops) > LOG_MAX_LEN:
                return errno.E2BIG
            block.ops.extend(ops)
            blocks[bid] = block
            return 0
        if cmd == LOG_START:
            if bid not in blocks:
                return errno.ENOENT
            b = blocks[bid]
            b.period_ms = 10 * d[2]
            b.next_due_ms = self.model.time_ms() + b.period_ms
            b.running = True
            return 0
        if cmd == LOG_STOP:
            if bid not in blocks:
                return errno.ENOENT
            blocks[bid].running = False
            return 0
        if cmd == LOG_DELETE:
            return 0 if blocks.pop(bid, None) is not None else errno.ENOENT
        if cmd == LOG_RESET:
            blocks.clear()
            return 0
        self.stats.unknown_command += 1
        return errno.ENOEXEC

    def _parse_log_ops(self, raw: bytes, v2: bool) -> list[tuple[LogEntry, str]] | None:
        """[(variable, fetch-as ctype)] from (type, id) pairs; ``None`` if any is invalid."""
        step = 3 if v2 else 2
        if len(raw) % step:
            return None
        ops = []
        for i in range(0, len(raw), step):
            fetch = LOG_CTYPE_BY_ID.get(raw[i] & 0x0F)
            vid = struct.unpack("<H", raw[i + 1:i + 3])[0] if v2 else raw[i + 1]
            if fetch is None or vid >= len(self.logs) or (not v2 and vid == 0xFF):
                return None  # raw-memory logging is not simulated
            ops.append((self.logs[vid], fetch))
        return ops

    def _log_packet(self, bid: int, b: _LogBlock, t_ms: int) -> CrtpPacket:
        ts = t_ms & 0xFFFFFF
        body = bytes((bid, ts & 0xFF, (ts >> 8) & 0xFF, ts >> 16))
        body += b"".join(self._value(var, fetch) for var, fetch in b.ops)
        return CrtpPacket(Port.LOG, LogChannel.DATA, body)
