"""Supervisor of one real-firmware SITL instance: ``cf2`` + the physics/relay bridge, always cleaned up.

    from polycc.sim.firmware.build import build_cf2
    from polycc.sim.firmware.sitl import FirmwareSitl
    fw = build_cf2(SITL_TREE_OR_TARBALL, "out/demo")
    with FirmwareSitl(fw, start=(-2.4, -1.4, 0.0)) as sitl:     # on the floor, motors off
        sitl.uri                    # udp://127.0.0.1:<port> for cflib
        sitl.truth()                # (position m, velocity m/s, motors_on), world frame, z up
        sitl.time()                 # simulated seconds since the bridge started
        sitl.sleep(2.0)             # wait 2 s of simulated time
        sitl.cut_link(5.0)          # drop the cflib relay both ways for 5 simulated seconds

Clock: the bridge drives cf2's FreeRTOS tick (``libpolycc_sitl_clock.so`` via LD_PRELOAD and a pipe,
:mod:`polycc.sim.firmware.bridge`): firmware time = physics time, lock-stepped, at most ``rtf_max`` x real
time and as fast as the host allows, so results do not depend on the host's load. Wall-clock timed cflib
helpers (MotionCommander, PositionHlCommander.land) still see a slower drone when the real-time factor
(:meth:`stats` ``rtf``) is below 1; every wait here (:meth:`sleep`, :meth:`wait_until`) is in simulated time.

Start-up: the bridge binds its ports (ephemeral unless given) and announces them; then
``cf2 <fw_port> 127.0.0.1`` starts; :meth:`start` returns once the firmware has handshaken *and* found
its gyro bias (the bridge holds cflib traffic until then). Several instances run side by side: every
instance has its own ports and its own run folder (``run_dir``, else a fresh temporary folder that is
removed on a clean stop and kept, and named, after an error).

Clean-up: each child runs in its own session with ``PR_SET_PDEATHSIG`` = SIGKILL, so it dies with this
process even on SIGKILL; :meth:`stop` (also from ``__exit__``, ``atexit`` and SIGINT/SIGTERM while the
instance runs) sends SIGTERM to each process group, SIGKILL after a grace period, reaps both and frees the
ports. Failures are one-line :class:`SitlError` s (a :class:`~polycc.errors.PolyccError`): cf2 missing or
exited, no handshake within the timeout, no calibration, a bridge error, a simulation that stopped
advancing.
"""

from __future__ import annotations

import atexit
import ctypes
import json
import os
import queue
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from polycc.errors import PolyccError

PR_SET_PDEATHSIG = 1
STALL_S = 20.0  # wall seconds without simulated time advancing: the simulation is stuck
TRAJECTORY_COLUMNS = ("t", "x", "y", "z", "vx", "vy", "vz", "qw", "qx", "qy", "qz", "wx", "wy", "wz", "thrust",
                      "m1", "m2", "m3", "m4")


class SitlError(PolyccError):
    """A one-line failure of the real-firmware SITL (start, run or stop)."""


class SitlExited(SitlError):
    """cf2 or the bridge exited: a crash of the firmware (or of the simulator), never retried."""


class SitlStall(SitlError):
    """The simulation stopped advancing: cf2 took no tick for :data:`STALL_S` wall seconds while both
    processes were alive. The simulator hung, not the flight: the message names the threads' states and
    ``stall.txt`` in the run folder holds the bridge's counters and cf2's backtraces (gdb, when installed)."""


try:  # resolved here, in the parent: a dlopen between fork and exec can deadlock on a lock another thread held
    _PRCTL = ctypes.CDLL("libc.so.6", use_errno=True).prctl
except (OSError, AttributeError):  # not glibc Linux
    _PRCTL = None


def _die_with_parent():
    """preexec_fn: SIGKILL when the parent dies (Linux). Runs between fork and exec in a parent that has
    threads (the bridge reader, xdist's), so it only makes the system call."""
    if _PRCTL is not None:
        _PRCTL(PR_SET_PDEATHSIG, signal.SIGKILL)


_live: list["FirmwareSitl"] = []
_old_handlers: dict = {}


def stop_all() -> None:
    """Stop every running instance of this process."""
    for s in list(_live):
        s.stop()


def _on_signal(signum, frame):
    for s in list(_live):
        s._failed = True
    stop_all()
    raise KeyboardInterrupt if signum == signal.SIGINT else SystemExit(128 + signum)


def _register(inst: "FirmwareSitl") -> None:
    """While any instance runs, SIGINT/SIGTERM stop them all first (main thread only)."""
    if not _live and threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGINT, signal.SIGTERM):
            _old_handlers[sig] = signal.getsignal(sig)
            signal.signal(sig, _on_signal)
    _live.append(inst)


def _unregister(inst: "FirmwareSitl") -> None:
    if inst in _live:
        _live.remove(inst)
    if not _live and _old_handlers and threading.current_thread() is threading.main_thread():
        for sig, h in _old_handlers.items():
            try:
                signal.signal(sig, h if h is not None else signal.SIG_DFL)
            except (TypeError, ValueError):
                pass
        _old_handlers.clear()


atexit.register(stop_all)


def _last_line(path) -> str:
    try:
        lines = [ln for ln in Path(path).read_text(errors="replace").splitlines() if ln.strip()]
        return lines[-1].strip()[:200] if lines else ""
    except OSError:
        return ""


class FirmwareSitl:
    """One ``cf2`` + bridge (module docstring).

    Args:
        cf2: a :class:`~polycc.sim.firmware.build.Cf2Build` or the path of a built ``cf2`` (the clock shim
            is next to it).
        start: x, y, z of the vehicle at start, m (z = 0: on the floor).
        yaw: start yaw, rad.
        run_dir: folder for ``cf2.log``, ``bridge.err`` and ``trajectory.csv`` (default: a temporary folder).
        fw_port, cflib_port: UDP ports (0: any free port); ``cflib_host`` the cflib socket's address.
        rtf_max: at most this many simulated seconds per wall second.
        handshake_timeout_s, calibration_timeout_s: wall-clock limits of the start-up.
        bridge_args: more ``polycc.sim.firmware.bridge`` options.
    """

    def __init__(self, cf2, start=(0.0, 0.0, 0.0), yaw: float = 0.0, run_dir: str | os.PathLike | None = None,
                 fw_port: int = 0, cflib_port: int = 0, cflib_host: str = "127.0.0.1", rtf_max: float = 1.0,
                 handshake_timeout_s: float = 10.0, calibration_timeout_s: float = 20.0, quiet: bool = True,
                 bridge_args: list[str] | None = None, python: str | None = None):
        path = getattr(cf2, "cf2", cf2)
        self.cf2 = Path(path).resolve()
        self.clock_shim = Path(getattr(cf2, "clock_shim", self.cf2.parent / "libpolycc_sitl_clock.so"))
        self.start_pos = tuple(float(v) for v in start)
        if len(self.start_pos) != 3 or not all(np.isfinite(self.start_pos)):
            raise SitlError(f"start {start!r}: expected three finite numbers x, y, z in metres")
        self.yaw = float(yaw)
        self._own_run_dir = run_dir is None
        self.run_dir = Path(run_dir).resolve() if run_dir is not None else None
        self.fw_port_req, self.cflib_port_req, self.cflib_host = int(fw_port), int(cflib_port), cflib_host
        self.rtf_max = float(rtf_max)
        self.handshake_timeout_s = float(handshake_timeout_s)
        self.calibration_timeout_s = float(calibration_timeout_s)
        self.quiet = quiet
        self.bridge_args = list(bridge_args or [])
        self.python = python or sys.executable
        self.bridge: subprocess.Popen | None = None
        self.fw: subprocess.Popen | None = None
        self.events: list[dict] = []
        self._q: queue.Queue = queue.Queue()
        self._reader: threading.Thread | None = None
        self.fw_port = self.cflib_port = self.control_port = None
        self._stopped = False
        self._failed = False
        self.t_handshake = self.t_ready = None
        self._lock = threading.Lock()
        self._adv_t, self._adv_wall = -1.0, time.monotonic()  # the stall watchdog (note_time)

    # ------------------------------------------------------------------ paths
    @property
    def uri(self) -> str:
        host = "127.0.0.1" if self.cflib_host in ("0.0.0.0", "") else self.cflib_host
        return f"udp://{host}:{self.cflib_port}"

    @property
    def trajectory_csv(self) -> Path:
        return self.run_dir / "trajectory.csv"

    @property
    def cf2_log(self) -> Path:
        return self.run_dir / "cf2.log"

    @property
    def bridge_err(self) -> Path:
        return self.run_dir / "bridge.err"

    # ------------------------------------------------------------------ start
    def __enter__(self) -> "FirmwareSitl":
        return self.start()

    def __exit__(self, *exc) -> None:
        if exc[0] is not None:
            self._failed = True
        self.stop()

    def start(self) -> "FirmwareSitl":
        if not self.cf2.is_file() or not os.access(self.cf2, os.X_OK):
            raise SitlError(f"{self.cf2}: no cf2 executable; build it with polycc.sim.firmware.build.build_cf2")
        if not self.clock_shim.is_file():
            raise SitlError(f"{self.clock_shim}: the clock shim is not next to cf2; rebuild with build_cf2")
        if self.run_dir is None:
            self.run_dir = Path(tempfile.mkdtemp(prefix="polycc-sitl-"))
        self.run_dir.mkdir(parents=True, exist_ok=True)
        _register(self)
        try:
            self._start()
        except BaseException:
            self._failed = True
            self.stop()
            raise
        return self

    def _read_bridge(self) -> None:
        assert self.bridge is not None and self.bridge.stdout is not None
        for line in self.bridge.stdout:
            line = line.strip()
            if not line:
                continue
            try:
                ev = json.loads(line)
            except ValueError:
                ev = {"event": "text", "line": line}
            self.events.append(ev)
            self._q.put(ev)
            if not self.quiet and ev.get("event") != "stats":
                print("[bridge]", line, file=sys.stderr)
        self._q.put({"event": "bridge_eof"})

    def _wait_event(self, names: set, timeout: float, what: str) -> dict:
        end = time.monotonic() + timeout
        while True:
            left = end - time.monotonic()
            if left <= 0:
                raise SitlError(what)
            try:
                ev = self._q.get(timeout=min(left, 0.2))
            except queue.Empty:
                if self.fw is not None and self.fw.poll() is not None:
                    raise SitlExited(f"cf2 exited with status {self.fw.returncode} during start-up (last line of "
                                    f"{self.cf2_log}: {_last_line(self.cf2_log)!r})") from None
                continue
            name = ev.get("event")
            if name in names:
                return ev
            if name == "error":
                raise SitlError(f"SITL bridge: {ev.get('message')}")
            if name == "bridge_eof":
                raise SitlExited(f"the SITL bridge exited with status {self.bridge.wait()} during start-up "
                                f"({_last_line(self.bridge_err)!r}; see {self.bridge_err})")

    def _start(self) -> None:
        tick_r, tick_w = os.pipe()
        cmd = [self.python, "-u", "-m", "polycc.sim.firmware.bridge", "--fw-port", str(self.fw_port_req),
               "--cflib-port", str(self.cflib_port_req), "--cflib-host", self.cflib_host,
               "--start=" + ",".join(repr(v) for v in self.start_pos), f"--yaw={self.yaw!r}",
               "--trajectory", str(self.trajectory_csv), "--handshake-timeout", str(self.handshake_timeout_s + 5),
               "--tick-fd", str(tick_w), "--rtf-max", str(self.rtf_max)] + self.bridge_args
        env = dict(os.environ)
        pkg_root = str(Path(__file__).resolve().parents[3])
        env["PYTHONPATH"] = os.pathsep.join(filter(None, [pkg_root, env.get("PYTHONPATH", "")]))
        try:
            with open(self.bridge_err, "w") as err:
                self.bridge = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=err, text=True, env=env,
                                               preexec_fn=_die_with_parent, start_new_session=True,
                                               cwd=self.run_dir, pass_fds=(tick_w,))
        finally:
            os.close(tick_w)
        self._reader = threading.Thread(target=self._read_bridge, name="sitl-bridge-reader", daemon=True)
        self._reader.start()
        try:
            ev = self._wait_event({"listening"}, 20.0, f"the SITL bridge did not start within 20 s (see "
                                                       f"{self.bridge_err})")
        except BaseException:
            os.close(tick_r)
            raise
        self.fw_port, self.cflib_port, self.control_port = ev["fw_port"], ev["cflib_port"], ev["control_port"]
        fenv = dict(os.environ)
        # the shim turns cf2's 1 ms setitimer into ticks read from the pipe, and line-buffers stdout
        fenv["LD_PRELOAD"] = " ".join(filter(None, [str(self.clock_shim), fenv.get("LD_PRELOAD", "")]))
        fenv["POLYCC_SITL_TICK_FD"] = str(tick_r)
        self.t0 = time.monotonic()
        try:
            with open(self.cf2_log, "w") as log:
                self.fw = subprocess.Popen([str(self.cf2), str(self.fw_port), "127.0.0.1"], stdout=log,
                                           stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, env=fenv,
                                           preexec_fn=_die_with_parent, start_new_session=True, cwd=self.run_dir,
                                           pass_fds=(tick_r,))
        finally:
            os.close(tick_r)
        self._wait_event({"handshake"}, self.handshake_timeout_s,
                         f"the SITL firmware never sent its 0xF3 handshake to udp 127.0.0.1:{self.fw_port} within "
                         f"{self.handshake_timeout_s:.0f} s (last line of {self.cf2_log}: "
                         f"{_last_line(self.cf2_log)!r}); check that FWDIR is the CrazySim sitl-release tree")
        self.t_handshake = time.monotonic() - self.t0
        try:
            self._wait_event({"calibrated"}, self.calibration_timeout_s, "")
        except SitlError as exc:
            if str(exc):
                raise
            raise SitlError(f"the SITL firmware handshaked but did not find its gyro bias within "
                            f"{self.calibration_timeout_s:.0f} s ({self._diag()})") from None
        self.t_ready = time.monotonic() - self.t0

    def _diag(self) -> str:
        try:
            st = self.stats(timeout=0.5)
            b = f"bridge sent {st.get('imu_tx', 0)} IMU packets, simulated {st.get('sim_t')} s"
        except SitlError:
            b = "bridge not answering"
        return f"{b}; last cf2 line {_last_line(self.cf2_log)!r}; cf2 log {self.cf2_log}"

    # ------------------------------------------------------------------ queries
    def _ctl(self, cmd: str, timeout: float = 2.0) -> dict:
        if self.control_port is None:
            raise SitlError("the SITL is not running")
        s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        s.settimeout(timeout)
        try:
            for _ in range(3):  # a loaded host may be slow to answer; UDP on loopback is not lost
                try:
                    s.sendto(cmd.encode(), ("127.0.0.1", self.control_port))
                    data, _ = s.recvfrom(1 << 20)
                    return json.loads(data)
                except socket.timeout:
                    self.check_alive()
            raise SitlError(f"the SITL bridge (control port {self.control_port}) did not answer {cmd!r} within "
                            f"{3 * timeout:.0f} s ({self._last_lines()})")
        except OSError as e:
            raise SitlError(f"the SITL bridge control port {self.control_port}: {e}") from None
        finally:
            s.close()

    def _last_lines(self) -> str:
        return f"cf2: {_last_line(self.cf2_log)!r}; bridge: {_last_line(self.bridge_err)!r}"

    def state(self) -> dict:
        """The bridge's truth now: ``t`` s, ``pos`` m, ``vel`` m/s, ``q``, ``pwm``, ``motors_on``, ``on_ground``,
        ``impacts``, ``max_tilt_deg``."""
        return self._ctl("state")

    def truth(self):
        """(position m, velocity m/s, motors_on): the simulated vehicle, world frame, z up."""
        s = self.state()
        return np.array(s["pos"]), np.array(s["vel"]), bool(s["motors_on"])

    def time(self) -> float:
        """Simulated seconds since the bridge started (= firmware ticks / 1000)."""
        return float(self.state()["t"])

    def stats(self, timeout: float = 2.0) -> dict:
        """The bridge's counters: ``sim_t``, ``wall_t``, ``rtf``, IMU delivery, relay and retransmission counts."""
        return self._ctl("stats", timeout)

    def cut_link(self, seconds: float) -> None:
        """Drop everything between cflib and the firmware, both ways, for ``seconds`` of simulated time."""
        r = self._ctl(f"cut {float(seconds)!r}")
        if "error" in r:
            raise SitlError(f"cut_link: {r['error']}")

    def note_time(self, t: float) -> None:
        """Stall watchdog for loops that poll the simulation: call with each simulated time read; raises
        :class:`SitlStall` (with diagnostics) when it has not advanced for :data:`STALL_S` wall seconds."""
        now = time.monotonic()
        if t > self._adv_t:
            self._adv_t, self._adv_wall = t, now
        elif now - self._adv_wall > STALL_S:
            self.check_alive()
            raise SitlStall(f"the SITL simulation stopped advancing at t = {t:.3f} s for {STALL_S:.0f} wall "
                            f"seconds with cf2 and the bridge alive ({self.stall_report()}; {self._last_lines()})")

    def stall_report(self) -> str:
        """One line on why the simulation may be stuck; the details (bridge counters, cf2's per-thread
        kernel state and, with gdb on PATH, every thread's backtrace) go to ``run_dir/stall.txt``."""
        lines, short = [], []
        try:
            st = self.stats(timeout=1.0)
            lines.append("bridge stats: " + json.dumps(st))
            short.append(f"bridge: {st.get('ticks', '?')} ticks written, {st.get('tick_waits', '?')} waits for cf2")
        except SitlError as exc:
            lines.append(f"bridge stats: {exc}")
        pid = self.fw.pid if self.fw is not None else None
        states: dict[str, int] = {}
        if pid is not None:
            for task in sorted(Path(f"/proc/{pid}/task").glob("*")):
                try:
                    comm = (task / "comm").read_text().strip()
                    state = (task / "stat").read_text().rsplit(")", 1)[1].split()[0]
                    wchan = (task / "wchan").read_text().strip() or "-"
                    sig = dict(ln.split(":\t", 1) for ln in (task / "status").read_text().splitlines()
                               if ln.startswith(("SigBlk", "SigPnd", "ShdPnd")))
                except OSError:
                    continue
                lines.append(f"thread {task.name} {comm!r}: {state} {wchan} {sig}")
                key = f"{state} {wchan}"
                states[key] = states.get(key, 0) + 1
            short.append("cf2 threads: " + ", ".join(f"{v} x {k}" for k, v in sorted(states.items())))
            gdb = shutil.which("gdb")
            if gdb:
                try:
                    bt = subprocess.run([gdb, "-p", str(pid), "-batch", "-nx", "-ex", "thread apply all bt"],
                                        capture_output=True, text=True, timeout=60)
                    lines.append(bt.stdout[-200_000:])
                except (OSError, subprocess.TimeoutExpired) as exc:
                    lines.append(f"gdb: {exc}")
        if self.run_dir is not None:
            try:
                (self.run_dir / "stall.txt").write_text("\n".join(lines) + "\n")
                short.append(f"details in {self.run_dir / 'stall.txt'}")
            except OSError:
                pass
        return "; ".join(short)

    def wait_until(self, pred, timeout_s: float, poll_s: float = 0.02) -> bool:
        """Poll ``pred()`` until it is true (True) or ``timeout_s`` of simulated time passed (False); a
        simulation that stops advancing for :data:`STALL_S` wall seconds raises :class:`SitlStall`."""
        t_end = self.time() + timeout_s
        while True:
            if pred():
                return True
            t = self.time()
            if t >= t_end:
                return False
            self.note_time(t)
            time.sleep(poll_s)

    def sleep(self, seconds: float) -> None:
        """Wait ``seconds`` of simulated time."""
        self.wait_until(lambda: False, seconds)

    def flush_trajectory(self) -> Path:
        self._ctl("flush")
        return self.trajectory_csv

    def trajectory(self) -> np.ndarray:
        """The bridge's truth at 100 Hz of simulated time so far, columns :data:`TRAJECTORY_COLUMNS`."""
        path = self.flush_trajectory()
        try:
            a = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)
        except ValueError:  # a row being written: try once more
            a = np.loadtxt(self.flush_trajectory(), delimiter=",", skiprows=1, ndmin=2)
        return a.reshape(-1, len(TRAJECTORY_COLUMNS))

    def impacts(self) -> list[dict]:
        """Touchdowns faster than 0.05 m/s (``t``, ``speed``, ``vz``, ``pos``, ``thrust_n``)."""
        return [e for e in self.events if e.get("event") == "impact"]

    def check_alive(self) -> None:
        if self.fw is not None and self.fw.poll() is not None:
            raise SitlExited(f"the SITL firmware (cf2) exited with status {self.fw.returncode} "
                            f"({_last_line(self.cf2_log)!r}; see {self.cf2_log})")
        if self.bridge is not None and self.bridge.poll() is not None:
            raise SitlExited(f"the SITL bridge exited with status {self.bridge.returncode} "
                            f"({_last_line(self.bridge_err)!r}; see {self.bridge_err})")

    # ------------------------------------------------------------------ stop
    def stop(self, grace_s: float = 3.0) -> None:
        with self._lock:
            if self._stopped:
                return
            self._stopped = True
        for p in (self.fw, self.bridge):  # firmware first: the bridge then writes its files
            if p is None:
                continue
            if p.poll() is None:
                try:
                    os.killpg(p.pid, signal.SIGTERM)
                except ProcessLookupError:
                    pass
                try:
                    p.wait(grace_s)
                except subprocess.TimeoutExpired:
                    try:
                        os.killpg(p.pid, signal.SIGKILL)
                    except ProcessLookupError:
                        pass
                    p.wait()
            try:  # anything left in its process group goes too
                os.killpg(p.pid, signal.SIGKILL)
            except (ProcessLookupError, PermissionError):
                pass
        if self.bridge is not None and self.bridge.stdout is not None:
            if self._reader is not None:
                self._reader.join(timeout=2.0)
            self.bridge.stdout.close()
        _unregister(self)
        if self._own_run_dir and not self._failed and self.run_dir is not None:
            shutil.rmtree(self.run_dir, ignore_errors=True)

    def keep_run_dir(self) -> None:
        """Keep the temporary run folder after :meth:`stop` (its logs)."""
        self._own_run_dir = False

    def ports_free(self) -> bool:
        """True when the bridge's UDP ports can be bound again (after :meth:`stop`)."""
        for host, port in (("127.0.0.1", self.fw_port), (self.cflib_host, self.cflib_port)):
            if not port:
                continue
            s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            try:
                s.bind((host, port))
            except OSError:
                return False
            finally:
                s.close()
        return True

