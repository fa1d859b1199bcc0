"""Physics + CRTP relay process between a CrazySim SITL ``cf2`` and cflib.

One process, one event loop (``select``), three UDP sockets:

* **firmware socket**, bound to ``fw_port``.  ``cf2 <fw_port> 127.0.0.1`` sends the ``0xF3``
  handshake here and the bridge echoes it.  Everything the bridge sends to the firmware (IMU,
  EXT_POSE, relayed cflib packets) leaves from this one socket: the firmware replies to the
  sender of the *last* datagram it received (``socketlink.c:92`` passes ``&remaddr`` to
  ``recvfrom``), so a second sending socket would receive the motor packets or the cflib
  replies by accident.
* **cflib socket**, bound to ``cflib_port``: ``udp://127.0.0.1:<cflib_port>`` for cflib's UDP
  driver.  Relayed unconditionally (cflib 0.1.34 never sends the ``0xF3`` that CrazySim's
  plugin waits for, ``crazysim_plugin.cpp:250``); the client is the sender of the latest
  datagram, so a reconnecting cflib is followed.
* **P2P air socket** (with ``--air HOST:PORT``; ephemeral): the radio's peer-to-peer broadcast between
  instances.  The SITL build's ``radiolinkSendP2PPacketBroadcast`` (``support/polycc_sitl_fixes.c``,
  fix ``p2p``) sends each P2P packet as a CRTP packet on port :data:`P2P_CRTP_PORT`; the bridge takes it
  out of the firmware's traffic (cflib never sees it) and sends it to the air hub
  (:class:`polycc.sim.firmware.air.P2PAir`), which hands it to every other instance's bridge; a packet
  from the air goes into the firmware through the same paced FIFO as cflib's packets and reaches the
  app's ``p2pRegisterCB`` callback.  A cut cflib link (``cut``) does not cut P2P (the nRF's broadcast
  needs no Crazyradio).  The instances do not share a clock (each is lock-stepped to its own physics), so
  each packet carries its sender's simulated time (:data:`AIR_STAMP`) and the air is causal in simulated
  time, as the radio is in physical time: a packet from an instance that is ahead waits until this one's
  simulated time reaches its stamp, and a neighbour record from one that is behind gets the lag added to
  its stated age (the record is that much older here; "forget" is left alone). Measured on a loaded CI
  host: without this, a record from a stalled instance arrived seconds "late" with its original age and
  its fresh position jumped into a drone's buffer (status INSIDE).
* **control socket** (ephemeral, announced on stdout), one UDP datagram per command, a JSON reply:
  ``state`` (the truth: simulated time ``t`` s, ``pos`` m, ``vel`` m/s, ``q``, ``pwm``, ``motors_on``,
  ``on_ground``, impacts), ``stats``, ``flush`` (write the trajectory rows so far), ``cut S`` (drop the
  cflib relay both ways for S simulated seconds: a lost radio link), ``quit``.

Clock.  The firmware's clock is the FreeRTOS tick: a 1 kHz ``setitimer(ITIMER_REAL)`` SIGALRM
(``vendor/FreeRTOS/portable/ThirdParty/GCC/Posix/port.c:324-345``); the Kalman predictor, HL
planner, supervisor, commander watchdog, log timers and usecTimestamp all read it; only the
stabilizer loop is clocked by IMU packets.  Pending SIGALRMs do not queue, so a cf2 that is not
scheduled for a few ms loses ticks (measured: its clock ran at 86 % of wall time on this
loaded host) and its velocity estimate is then scaled by the same factor.  Two modes:

* **bridge clock** (``tick_fd`` set; default in :mod:`polycc.sim.firmware.sitl`): ``libpolycc_sitl_clock.so``
  (``support/polycc_sitl_clock.c``, LD_PRELOAD) replaces cf2's setitimer by a pipe; the
  bridge writes one byte = one tick per 1 ms physics step and sends that step's IMU.  A step
  waits until cf2 has taken the previous tick (pipe backlog <= 1), so firmware time == physics
  time to within a tick (lock-step), paced at ``rtf_max`` x real time.  The
  real-time factor is whatever the host allows (reported as ``rtf``).
* **wall clock** (no ``tick_fd``): the fork's own timer; the physics follows the wall clock
  (catching up after the bridge was late) and one IMU per 1 ms slot is sent.

Physics (:mod:`polycc.sim.firmware.physics`): 1 ms steps, zero-order hold on the latest motor packet, true pose as
EXT_POSE at ``pose_hz``.

Pacing into the firmware (``mode="paced"``).  The firmware's socket reader
task puts each datagram into a 5-deep queue with timeout 0 (``src/hal/src/socketlink.c:95,
214``); ``crtpRxTask`` (same priority 2) empties it only when the tick scheduler switches to
it, every 1-2 ticks, after which the stabilizer runs and a motor packet goes out.  Whatever
the reader takes in beyond 5 between two drains is lost silently, and cflib's UDP driver never
resends.  Losses happen at the tail of a backlog, when cf2 was not scheduled and then reads
everything buffered at once.  So the bridge

1. sends one IMU per step/slot, never two closer than 0.5 ms;
2. sends at most ``slot_extra`` (1) other packet per IMU: a cflib packet (its own FIFO;
   nothing from cflib is dropped or reordered) only within ``cflib_window_s`` (1.5 ms) after a
   motor packet and only among the first ``cflib_slots`` (3) packets since it, i.e. at the
   head of the firmware's next read, where a backlog cannot push it out; else EXT_POSE;
3. (wall clock) holds IMUs while no motor packet came for ``hold_s`` (2.5 ms, a missed
   drain: cf2 is not running), except one probe every ``probe_s`` so that a drain whose motor
   packet the firmware's one-per-tick limit suppressed (``power_distribution_sitl.c:214``)
   cannot deadlock; with the bridge clock a stalled cf2 stops taking ticks, which holds the
   steps by itself;
4. retransmits requests whose reply is missing (:mod:`polycc.sim.firmware.arq`), what cflib's radio path
   does for the same requests, and drops the duplicate answers.

Before the firmware has found its gyro bias (its ``0x90 0x01``) there are no motor packets
and its port queues may not exist yet (``crtp.c:180`` drops packets for a port without a
queue; the param/log/platform queues are created when those tasks first run): cflib packets
are held until then.

``mode="naive"`` forwards cflib packets at once (for comparison).  Events are JSON lines on
stdout; the true state at ``record_hz`` goes to a CSV.

Run: ``python -m polycc.sim.firmware.bridge --fw-port 19950 --cflib-port 19850 --start -2.4,-1.4,0`` (the
supervisor :class:`polycc.sim.firmware.sitl.FirmwareSitl` starts it with the tick pipe).
"""

from __future__ import annotations

import argparse
import collections
import faulthandler
import fcntl
import json
import os
import select
import signal
import socket
import struct
import sys
import termios
import time
from dataclasses import asdict, dataclass

from polycc.onboard.app import NBR_FORGET, NBR_MAGIC, P2P_PORT
from polycc.sim.firmware import physics
from polycc.sim.firmware.arq import Arq

IMU_PERIOD_S = 0.001
SCAN_PROBE = b"\xff"        # cflib udpdriver.scan_interface: one null CRTP packet
IMU_MIN_SPACING_S = 0.0005  # never two IMU packets closer than this (no catch-up bursts)
MAX_LATE_S = 0.003          # later than this: re-anchor the IMU slot schedule
MAX_CATCHUP_STEPS = 200     # wall mode: physics steps done at once after the bridge was late (0.2 s)
TICK_BACKLOG_MAX = 1        # bridge clock: ticks written but not yet taken by cf2 before a step waits
MAX_STEPS_PER_LOOP = int(os.environ.get("POLYCC_SITL_STEPS_PER_LOOP", "1"))  # bridge clock
MIN_STEP_SPACING_S = float(os.environ.get("POLYCC_SITL_MIN_STEP_S", "0.0009"))  # bridge clock
TICK_POLL_S = 0.0002        # bridge clock: poll period while waiting for cf2 to take its tick
MAX_LAG_S = 0.05            # bridge clock: this far behind the rtf_max schedule, give up catching up
MOTOR_SILENCE_S = 0.5       # no motor packet for this long after they started: report a stall
LOOKBACK_S = 0.001          # packets sent this long before a motor packet may not have been read
P2P_CRTP_PORT = 0x0B        # support/polycc_sitl_fixes.c POLYCC_SITL_P2P_CRTP_PORT: a P2P packet as CRTP
AIR_HELLO = b"\x00"         # bridge -> air hub: register this socket (a P2P packet is >= 2 bytes)
AIR_STAMP = b"\x02"         # bridge -> air: this prefix, the sender's simulated time (<d, s), then the packet


@dataclass
class BridgeConfig:
    fw_port: int = 19950
    cflib_port: int = 19850
    host: str = "127.0.0.1"         # the firmware socket (cf2 runs on this machine)
    cflib_host: str = "127.0.0.1"   # the cflib socket (0.0.0.0: reachable from other machines)
    start: tuple = (0.0, 0.0, 0.0)
    start_yaw: float = 0.0
    pose_hz: float = 100.0
    record_hz: float = 100.0
    trajectory_csv: str | None = None
    mode: str = "paced"            # "paced" or "naive" (forward at once, for comparison)
    slot_extra: int = 1            # non-IMU packets per 1 ms IMU slot
    hold_s: float = 0.0025         # no motor packet for this long: firmware not draining, hold
    probe_s: float = 0.010         # while holding: one IMU this often
    cflib_window_s: float = 0.0015  # cflib packets only this soon after a motor packet ...
    cflib_slots: int = 3           # ... and only as one of the first 3 packets of that window
    hold_until_calibrated: bool = True
    arq: bool = True               # retransmit answered requests whose reply is missing
    handshake_timeout_s: float = 20.0
    stats_period_s: float = 5.0
    trace_path: str | None = None  # debug: every datagram with timing
    gyro_noise_dps: float = 0.0
    acc_noise_g: float = 0.0
    tick_fd: int | None = None      # bridge clock: write end of cf2's tick pipe (sim.py sets it up)
    rtf_max: float = 1.0            # bridge clock: at most this many simulated seconds per second
    air: tuple | None = None        # (host, port) of the P2P air hub (polycc.sim.firmware.air), or None
    lose: tuple | None = None       # tests: (CRTP header, count): lose that many such cflib packets into the firmware


class Bridge:
    def __init__(self, cfg: BridgeConfig):
        self.cfg = cfg
        self.t_start = None
        self.quad = physics.Quadrotor(physics.QuadParams(gyro_noise_dps=cfg.gyro_noise_dps,
                                                         acc_noise_g=cfg.acc_noise_g),
                                      pos=cfg.start, yaw=cfg.start_yaw)
        self.fw = self._udp(cfg.host, cfg.fw_port, "firmware")
        self.cf = self._udp(cfg.cflib_host, cfg.cflib_port, "cflib")
        self.ctl = self._udp("127.0.0.1", 0, "control")
        self.air = None
        if cfg.air is not None:
            self.air = self._udp("127.0.0.1", 0, "P2P air")
            self.air.sendto(AIR_HELLO, tuple(cfg.air))
        self.cut_until = -1.0                 # simulated time until which the cflib relay is cut
        self.fw_addr = None
        self.cf_addr = None
        self.pwm = (0, 0, 0, 0)
        self.calibrated = False
        self.pending = collections.deque()   # cflib -> firmware FIFO: (t_in, bytes, an ARQ retransmission)
        self.air_future: list = []            # P2P packets stamped ahead of this instance: (sim t s, bytes)
        self.sent_times = collections.deque()
        self.arq = Arq() if (cfg.arq and cfg.mode == "paced") else None
        self.last_motor = None
        self.last_probe = 0.0
        self.stalled = False
        self.running = True
        self.t_imu0 = None
        self.rows = []
        self.csv = None
        self.trace = open(cfg.trace_path, "w") if cfg.trace_path else None
        self.stats = collections.Counter()
        self.max_hold_s = 0.0
        self.late_max_s = 0.0
        self.motor_gap_max_s = 0.0
        self.motor_gap_max_at = None
        self.impacts_reported = 0
        self.tick_fd = cfg.tick_fd
        self.n_tick = 0
        self.lose_left = 0 if cfg.lose is None else int(cfg.lose[1])
        if self.tick_fd is not None:
            os.set_blocking(self.tick_fd, False)

    def _udp(self, host, port, what):
        s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 20)
        try:
            s.bind((host, port))
        except OSError as e:
            self.emit("error", message=f"cannot bind the {what} socket to udp {host}:{port} ({e.strerror}); "
                                       "pick another port (is another simulator running?)")
            raise SystemExit(2)
        s.setblocking(False)
        return s

    @property
    def link_cut(self) -> bool:
        return self.quad.t < self.cut_until

    # ------------------------------------------------------------------ output
    def emit(self, event: str, **kw):
        kw = {"event": event, "wall": round(time.monotonic() - (self.t_start or time.monotonic()), 4), **kw}
        sys.stdout.write(json.dumps(kw) + "\n")
        sys.stdout.flush()

    def _record(self):
        self.rows.append(self.quad.state_row() + list(self.pwm))
        if self.csv and len(self.rows) >= 100:
            self._flush_rows()

    def _flush_rows(self):
        if self.csv:
            self.csv.write("".join(",".join(f"{v:.6g}" for v in r) + "\n" for r in self.rows))
            self.csv.flush()
        self.rows.clear()

    # ------------------------------------------------------------------ firmware side
    def _send_fw(self, data: bytes, now: float) -> bool:
        try:
            self.fw.sendto(data, self.fw_addr)
        except BlockingIOError:
            self.stats["fw_send_eagain"] += 1
            return False
        if self.trace:
            self.trace.write(f"{now:.6f} >fw {data[:4].hex()}\n")
        self.sent_times.append(now)
        return True

    def _window_position(self, now: float) -> int:
        """How many packets are ahead of one sent now in the firmware's next read: those sent
        since the last motor packet, plus those sent up to LOOKBACK_S before it (they may have
        arrived after that drain)."""
        st = self.sent_times
        while st and st[0] < now - 0.1:
            st.popleft()
        lo = self.last_motor - LOOKBACK_S
        n = 0
        for t in reversed(st):
            if t < lo:
                break
            n += 1
        return n

    def _arq_clock(self, now: float) -> float:
        """Retransmission timers run on the firmware's clock: with the bridge clock that is the
        simulated time, so a host stall that freezes both never looks like a lost request."""
        return self.quad.t if (self.tick_fd is not None and self.t_imu0 is not None) else now

    def _draining(self, now: float) -> bool:
        """Motor packets are coming: the firmware is reading its socket and draining its queue."""
        return self.last_motor is not None and now - self.last_motor <= self.cfg.hold_s

    def _on_motor(self, now: float):
        if self.last_motor is not None:
            gap = now - self.last_motor
            if gap > self.motor_gap_max_s:
                self.motor_gap_max_s, self.motor_gap_max_at = gap, round(self.quad.t, 3)
            if gap > self.cfg.hold_s:
                self.stats["motor_gaps_over_hold"] += 1
        self.last_motor = now
        if self.stalled:
            self.stalled = False
            self.emit("firmware_resumed", sim_t=round(self.quad.t, 3))

    def _handle_fw(self, data: bytes, addr, now: float):
        if self.fw_addr is None or addr != self.fw_addr:
            if data == physics.HANDSHAKE:
                self.fw_addr = addr
                self.fw.sendto(physics.HANDSHAKE, addr)
                self.emit("handshake", fw_addr=list(addr), ticks=self.n_tick)
            return
        if data == physics.HANDSHAKE:           # firmware re-sent it (our echo was lost): echo again
            self.fw.sendto(physics.HANDSHAKE, addr)
            return
        if self.trace:
            self.trace.write(f"{now:.6f} <fw {data[:4].hex()}\n")
        if physics.is_motor_packet(data):
            self.pwm = physics.decode_motors(data)
            self.stats["motor_rx"] += 1
            self._on_motor(now)
            return
        if physics.is_calibrated_packet(data):
            self.calibrated = True
            self.emit("calibrated", sim_t=round(self.quad.t, 3))
            return
        if len(data) >= 2 and (data[0] >> 4) == P2P_CRTP_PORT:  # a P2P broadcast: into the air, never to cflib
            if self.air is None:
                self.stats["p2p_no_air"] += 1
                return
            try:
                self.air.sendto(AIR_STAMP + struct.pack("<d", self.quad.t) + data, tuple(self.cfg.air))
                self.stats["p2p_tx"] += 1
            except OSError:
                self.stats["p2p_send_err"] += 1
            return
        if self.arq is not None and not self.arq.reply(data, self._arq_clock(now)):
            return                              # duplicate answer to a retransmitted request
        if self.link_cut:
            self.stats["cut_fw_to_cflib"] += 1
            return
        self.stats["fw_to_cflib"] += 1
        if self.cf_addr is not None:
            try:
                self.cf.sendto(data, self.cf_addr)
            except OSError:
                self.stats["cflib_send_err"] += 1

    def _handle_air(self, data: bytes, now: float):
        """Another instance's P2P broadcast: into this firmware, behind cflib's packets (the same pacing),
        once this instance's simulated time has reached the sender's (module docstring)."""
        t_s = None
        if data[:1] == AIR_STAMP and len(data) >= 9:
            t_s = struct.unpack("<d", data[1:9])[0]
            data = data[9:]
        if len(data) < 2 or (data[0] >> 4) != P2P_CRTP_PORT:
            self.stats["p2p_bad"] += 1
            return
        if self.fw_addr is None or not self.calibrated:  # the app is not running yet: the radio hears nothing
            self.stats["p2p_before_calibration"] += 1
            return
        self.stats["p2p_rx"] += 1
        if t_s is not None and t_s > self.quad.t:
            self.air_future.append((t_s, data))
            self.stats["p2p_held"] += 1
            return
        self._air_in(data, 0.0 if t_s is None else self.quad.t - t_s, now)

    def _air_in(self, data: bytes, lag_s: float, now: float) -> None:
        if lag_s > 0.0 and len(data) == 20 and data[1] == P2P_PORT and data[2] == NBR_MAGIC:  # a neighbour record
            age = struct.unpack_from("<H", data, 16)[0]
            if age != NBR_FORGET:
                aged = min(NBR_FORGET - 1, age + int(-(-lag_s * 1000.0 // 1.0)))
                data = data[:16] + struct.pack("<H", aged) + data[18:]
                self.stats["p2p_aged"] += 1
        if self.cfg.mode == "naive":
            self._send_fw(data, now)
            return
        self.pending.append((now, data, False))

    def _release_air(self, now: float) -> None:
        """Held P2P packets whose stamp this instance's simulated time has reached (in stamp order)."""
        ready = [p for p in self.air_future if p[0] <= self.quad.t]
        if ready:
            self.air_future = [p for p in self.air_future if p[0] > self.quad.t]
            for t_s, data in sorted(ready, key=lambda p: p[0]):
                self._air_in(data, self.quad.t - t_s, now)

    # ------------------------------------------------------------------ cflib side
    def _handle_cf(self, data: bytes, addr, now: float):
        if data == SCAN_PROBE:
            # cflib's UDP scan (cfclient's Scan button) sends one null CRTP packet from a throw-away
            # socket and waits 0.1 s for any reply. On a radio the nRF link layer ACKs it without the
            # STM32; the bridge plays that link, so it answers at once, and the prober's address must
            # not take over the client's (the firmware's replies would go to a closed socket).
            self.cf.sendto(SCAN_PROBE, addr)
            self.stats["scan_probes"] += 1
            return
        if addr != self.cf_addr:
            self.cf_addr = addr
            self.emit("cflib_client", addr=list(addr))
        if len(data) == 1 and data[0] in (0xF3, 0xF4):
            return  # CrazySim's relay on/off markers: the relay here is always on
        if self.link_cut:
            self.stats["cut_cflib_to_fw"] += 1
            return
        self.stats["cflib_to_fw"] += 1
        if self.cfg.mode == "naive" and self.fw_addr is not None:
            self._send_fw(data, now)
            return
        self.pending.append((now, data, False))

    def _next_extra(self, now: float, pose_due: bool):
        """The non-IMU packet for this slot: a cflib packet when it can be near the head of the
        firmware's next read (just after a drain), else EXT_POSE when due, else None."""
        cflib_ok = bool(self.pending) and (self.calibrated or not self.cfg.hold_until_calibrated)
        if cflib_ok and self.last_motor is not None:
            cflib_ok = (now - self.last_motor <= self.cfg.cflib_window_s
                        and self._window_position(now) + 1 <= self.cfg.cflib_slots)
        if cflib_ok:
            return "cflib"
        if pose_due:
            return "pose"
        return None

    def _send_cflib(self, now: float):
        t_in, data, retx = self.pending[0]
        if retx and not self.arq.wanted(data):  # answered while it waited (polycc.sim.firmware.arq)
            self.pending.popleft()
            self.arq.cancelled += 1
            return
        if self.lose_left > 0 and (data[0] & 0xF3) == (self.cfg.lose[0] & 0xF3):
            # tests: lost as the firmware's full RX queue loses a packet (gone after the bridge sent it)
            self.lose_left -= 1
            self.stats["lost_on_purpose"] += 1
            self.pending.popleft()
            if self.arq is not None:
                self.arq.sent(data, self._arq_clock(now))
            return
        if self._send_fw(data, now):
            self.pending.popleft()
            self.max_hold_s = max(self.max_hold_s, now - t_in)
            if self.arq is not None:
                self.arq.sent(data, self._arq_clock(now))

    # ------------------------------------------------------------------ control
    def _control(self, data: bytes, addr):
        cmd = data.decode(errors="replace").strip()
        word, _, arg = cmd.partition(" ")
        if cmd == "state":
            q = self.quad
            out = {"t": q.t, "pos": list(q.pos), "vel": list(q.vel), "q": list(q.q), "pwm": list(self.pwm),
                   "motors_on": any(self.pwm), "on_ground": q.on_ground, "calibrated": self.calibrated,
                   "link_cut": self.link_cut, "impacts": [asdict(i) for i in q.impacts],
                   "max_tilt_deg": q.max_tilt_deg}
        elif word == "cut":
            try:
                seconds = float(arg)
            except ValueError:
                seconds = float("nan")
            if not seconds >= 0.0:
                out = {"error": f"cut needs a duration in seconds >= 0, not {arg!r}"}
            else:
                self.cut_until = self.quad.t + seconds
                self.pending.clear()            # what cflib sent and the firmware has not seen is lost
                if self.arq is not None:
                    self.arq.open.clear()
                self.emit("link_cut", sim_t=round(self.quad.t, 4), seconds=seconds)
                out = {"ok": True, "t": self.quad.t, "until": self.cut_until}
        elif cmd == "stats":
            out = self._stats()
        elif cmd == "flush":
            self._flush_rows()
            out = {"ok": True, "csv": self.cfg.trajectory_csv}
        elif cmd == "quit":
            self.running = False
            out = {"ok": True}
        else:
            out = {"error": f"unknown command {cmd!r}"}
        self.ctl.sendto(json.dumps(out).encode(), addr)

    def _stats(self) -> dict:
        wall = time.monotonic() - self.t_imu0 if self.t_imu0 else 0.0
        extra = {"ticks": self.n_tick} if self.tick_fd is not None else {}
        return {"sim_t": round(self.quad.t, 4), "wall_t": round(wall, 4),
                "rtf": round(self.quad.t / wall, 5) if wall > 0 else None,
                "imu_delivery": round(self.stats["imu_tx"] / max(1.0, self.quad.t / IMU_PERIOD_S), 4),
                "pending": len(self.pending), "max_hold_ms": round(self.max_hold_s * 1e3, 2),
                "late_max_ms": round(self.late_max_s * 1e3, 3),
                "motor_gap_max_ms": round(self.motor_gap_max_s * 1e3, 2),
                "motor_gap_max_at_sim_t": self.motor_gap_max_at,
                **extra, **dict(self.stats), **(self.arq.stats() if self.arq else {})}

    # ------------------------------------------------------------------ main loop
    def run(self) -> int:
        cfg = self.cfg
        self.t_start = time.monotonic()
        if cfg.trajectory_csv:
            self.csv = open(cfg.trajectory_csv, "w")
            self.csv.write(",".join(physics.STATE_COLUMNS + ["m1", "m2", "m3", "m4"]) + "\n")
        self.emit("listening", fw_port=self.fw.getsockname()[1], cflib_port=self.cf.getsockname()[1],
                  control_port=self.ctl.getsockname()[1], mode=cfg.mode,
                  clock="bridge" if self.tick_fd is not None else "wall", pid=os.getpid())
        socks = [self.fw, self.cf, self.ctl] + ([self.air] if self.air is not None else [])
        self.paced = cfg.mode == "paced"
        self.pose_every = max(1, round(1000.0 / cfg.pose_hz))
        self.rec_every = max(1, round(1000.0 / cfg.record_hz))
        self.n_step = 0
        self.pose_due = False
        self.extra_budget = 0
        next_stats = time.monotonic() + cfg.stats_period_s
        deadline = time.monotonic() + cfg.handshake_timeout_s
        tick_mode = self.tick_fd is not None
        self.next_step = time.monotonic()      # tick mode: the schedule of steps (and ticks)
        self.next_imu = None                   # wall mode: the schedule of IMU slots
        self.was_holding = False
        while self.running:
            now = time.monotonic()
            if self.fw_addr is None and now > deadline:
                self.emit("error", message=f"no 0xF3 handshake from cf2 on udp {cfg.host}:"
                                           f"{self.fw.getsockname()[1]} within {cfg.handshake_timeout_s:.0f} s")
                return 3
            if tick_mode:
                timeout = max(0.0, self.next_step - now)
                if now >= self.next_step:
                    timeout = TICK_POLL_S       # waiting for the firmware to take its tick
            elif self.fw_addr is None:
                timeout = 0.05
            else:
                if self.next_imu is None:
                    self.next_imu = self.t_imu0 = now
                timeout = max(0.0, self.next_imu - now)
            if self.arq is not None and self.arq.open:
                timeout = min(timeout, self.arq.rto_s)
            r, _, _ = select.select(socks, [], [], timeout)
            now = time.monotonic()
            for s in r:
                while True:
                    try:
                        data, addr = s.recvfrom(64)
                    except (BlockingIOError, InterruptedError):
                        break
                    except ConnectionRefusedError:
                        continue
                    if s is self.fw:
                        self._handle_fw(data, addr, now)
                    elif s is self.cf:
                        self._handle_cf(data, addr, now)
                    elif s is self.air:
                        self._handle_air(data, now)
                    else:
                        self._control(data, addr)
            now = time.monotonic()
            if tick_mode:
                if not self._tick_mode(now):
                    return 4
            elif self.fw_addr is not None and self.next_imu is not None:
                self._wall_mode(now)
            if self.air_future:
                self._release_air(now)
            if self.fw_addr is not None:
                self._extras(now)
                if self.last_motor is not None and not self.stalled and now - self.last_motor > MOTOR_SILENCE_S:
                    self.stalled = True
                    self.emit("firmware_stalled", silent_s=round(now - self.last_motor, 3),
                              sim_t=round(self.quad.t, 3))
            if now >= next_stats:
                next_stats = now + cfg.stats_period_s
                self.emit("stats", **self._stats())
        return 0

    # -- one physics step (1 ms), with its book-keeping
    def _step(self):
        self.quad.step(IMU_PERIOD_S, self.pwm)
        self.n_step += 1
        if self.n_step % self.pose_every == 0:
            self.pose_due = True
        if self.n_step % self.rec_every == 0:
            self._record()
        if len(self.quad.impacts) > self.impacts_reported:
            for imp in self.quad.impacts[self.impacts_reported:]:
                self.emit("impact", **asdict(imp))
            self.impacts_reported = len(self.quad.impacts)

    def _send_imu(self, now: float):
        self._send_fw(self.quad.imu_packet(), now)
        self.stats["imu_tx"] += 1
        self.extra_budget = self.cfg.slot_extra if self.paced else 1 << 30

    def _tick_backlog(self) -> int:
        return struct.unpack("i", fcntl.ioctl(self.tick_fd, termios.FIONREAD, b"\0\0\0\0"))[0]

    def _tick_mode(self, now: float) -> bool:
        """Bridge clock: one tick per step, a step only when cf2 has taken all but at most
        TICK_BACKLOG_MAX of the ticks written (so firmware time == physics time to within a
        tick), paced at rtf_max x real time.  Behind schedule (the bridge or cf2 was not
        scheduled), up to MAX_STEPS_PER_LOOP steps per loop iteration catch up: sleeping for
        less than a millisecond costs more than that on a loaded host."""
        cfg = self.cfg
        period = IMU_PERIOD_S / cfg.rtf_max
        for _ in range(MAX_STEPS_PER_LOOP):
            if now < self.next_step:
                return True
            if self._tick_backlog() > TICK_BACKLOG_MAX:
                self.stats["tick_waits"] += 1       # firmware behind: the simulation waits for it
                return True
            if self.fw_addr is not None:
                if self.t_imu0 is None:
                    self.t_imu0 = now
                self._step()
                self._send_imu(now)
            try:
                os.write(self.tick_fd, b"\x01")
            except BlockingIOError:
                self.stats["tick_write_eagain"] += 1
                return True
            except BrokenPipeError:
                self.emit("error", message="cf2's tick pipe closed (cf2 exited)")
                return False
            self.n_tick += 1
            lag = now - self.next_step
            if self.fw_addr is not None and self.stats["imu_tx"] > 10:
                self.late_max_s = max(self.late_max_s, lag)
            if lag > MAX_LAG_S:
                self.stats["lag_resets"] += 1      # far behind real time: stop trying to catch up
                self.next_step = now + period
            else:
                self.next_step = max(self.next_step + period, now + MIN_STEP_SPACING_S)
            now = time.monotonic()
        return True

    def _wall_mode(self, now: float):
        """The fork's own clock (setitimer): physics follows the wall clock, one IMU per slot."""
        cfg = self.cfg
        holding = self.paced and self.last_motor is not None and not self._draining(now)
        if holding and not self.was_holding:
            self.last_probe = now   # first probe only after probe_s of holding
        self.was_holding = holding
        target = int((now - self.t_imu0) / IMU_PERIOD_S)
        behind = target - self.n_step
        if behind > MAX_CATCHUP_STEPS:
            self.stats["steps_dropped"] += behind - MAX_CATCHUP_STEPS
            self.n_step += behind - MAX_CATCHUP_STEPS
            behind = MAX_CATCHUP_STEPS
        for _ in range(behind):
            self._step()
        if behind > 1:
            self.stats["catchup_steps"] += behind - 1
        if now >= self.next_imu:
            if self.stats["imu_tx"] > 10:
                self.late_max_s = max(self.late_max_s, now - self.next_imu)
            probe = holding and now - self.last_probe >= cfg.probe_s
            if holding and not probe:
                self.stats["imu_held"] += 1
            else:
                if probe:
                    self.last_probe = now
                    self.stats["imu_probes"] += 1
                self._send_imu(now)
            self.next_imu = max(self.next_imu + IMU_PERIOD_S, now + IMU_MIN_SPACING_S)
            if now - self.next_imu > MAX_LATE_S:
                self.stats["imu_slips"] += 1
                self.next_imu = now + IMU_MIN_SPACING_S
        if holding:
            self.extra_budget = 0

    def _extras(self, now: float):
        """At most `slot_extra` non-IMU packets per IMU slot."""
        if self.arq is not None:
            for data in self.arq.due(self._arq_clock(now)):
                self.pending.appendleft((now, data, True))
        while self.extra_budget > 0:
            kind = self._next_extra(now, self.pose_due)
            if kind is None:
                break
            if kind == "pose":
                self._send_fw(self.quad.pose_packet(), now)
                self.stats["pose_tx"] += 1
                self.pose_due = False
            elif not self.paced:
                break  # naive: cflib packets were forwarded on arrival
            else:
                self._send_cflib(now)
            self.extra_budget -= 1

    def close(self):
        self._flush_rows()
        if self.csv:
            self.csv.close()
        if self.trace:
            self.trace.close()
        for s in (self.fw, self.cf, self.ctl, self.air):
            if s is not None:
                s.close()


def _triple(s: str):
    v = tuple(float(x) for x in s.split(","))
    if len(v) != 3:
        raise argparse.ArgumentTypeError("expected x,y,z")
    return v


def _hostport(s: str):
    host, _, port = s.rpartition(":")
    return host or "127.0.0.1", int(port)


def _header_count(s: str):
    hdr, _, n = s.partition(":")
    try:
        return int(hdr, 0) & 0xFF, int(n or "1")
    except ValueError:
        raise argparse.ArgumentTypeError("expected HEADER:N, e.g. 0xfd:1") from None


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description="CrazySim SITL physics + CRTP relay")
    ap.add_argument("--fw-port", type=int, default=19950, help="0: any free port (reported on stdout)")
    ap.add_argument("--cflib-port", type=int, default=19850, help="0: any free port (reported on stdout)")
    ap.add_argument("--cflib-host", default="127.0.0.1", help="address of the cflib socket (0.0.0.0: all)")
    ap.add_argument("--start", type=_triple, default=(0.0, 0.0, 0.0), help="x,y,z start (m)")
    ap.add_argument("--yaw", type=float, default=0.0, help="start yaw (rad)")
    ap.add_argument("--pose-hz", type=float, default=100.0)
    ap.add_argument("--trajectory", help="CSV of the true state at 100 Hz")
    ap.add_argument("--mode", choices=("paced", "naive"), default="paced")
    ap.add_argument("--slot-extra", type=int, default=1, help="non-IMU packets per 1 ms slot (paced)")
    ap.add_argument("--hold-ms", type=float, default=2.5, help="no motor packet this long: hold (paced)")
    ap.add_argument("--no-hold", action="store_true", help="do not hold cflib packets until calibrated")
    ap.add_argument("--no-arq", action="store_true", help="do not retransmit unanswered requests")
    ap.add_argument("--handshake-timeout", type=float, default=20.0)
    ap.add_argument("--stats-period", type=float, default=5.0)
    ap.add_argument("--trace", help="debug: write every datagram to this file")
    ap.add_argument("--tick-fd", type=int, help="bridge clock: write end of cf2's tick pipe (polycc.sim.firmware.sitl)")
    ap.add_argument("--rtf-max", type=float, default=1.0, help="bridge clock: max real-time factor")
    ap.add_argument("--air", type=_hostport, help="HOST:PORT of the P2P air hub (polycc.sim.firmware.air)")
    ap.add_argument("--lose", type=_header_count, metavar="HEADER:N",
                    help="tests: lose the first N cflib packets with this CRTP header (e.g. 0xfd:1) on their way "
                         "into the firmware, as its full RX queue would")
    a = ap.parse_args(argv)
    cfg = BridgeConfig(fw_port=a.fw_port, cflib_port=a.cflib_port, cflib_host=a.cflib_host, start=a.start,
                       start_yaw=a.yaw,
                       pose_hz=a.pose_hz, trajectory_csv=a.trajectory, mode=a.mode, slot_extra=a.slot_extra,
                       hold_s=a.hold_ms / 1e3, hold_until_calibrated=not a.no_hold, arq=not a.no_arq,
                       handshake_timeout_s=a.handshake_timeout, stats_period_s=a.stats_period,
                       trace_path=a.trace, tick_fd=a.tick_fd, rtf_max=a.rtf_max, air=a.air, lose=a.lose)
    b = Bridge(cfg)

    def stop(signum, frame):
        b.running = False

    faulthandler.register(signal.SIGUSR1)  # kill -USR1 <pid>: Python tracebacks to stderr
    signal.signal(signal.SIGTERM, stop)
    signal.signal(signal.SIGINT, stop)
    try:
        rc = b.run()
    finally:
        b.emit("exit", **b._stats())
        b.close()
    return rc


if __name__ == "__main__":
    sys.exit(main())
