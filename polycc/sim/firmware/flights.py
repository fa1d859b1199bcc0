"""`polycc sim --firmware`: the flights of the fast `polycc sim`, flown by the real Crazyflie firmware.

One trial (:meth:`FirmwareSimulator.fly`), all in simulated time:

1. a fresh SITL instance (:class:`~polycc.sim.firmware.sitl.FirmwareSitl`) with the vehicle on the floor
   below the start (x, y, z = 0), motors off;
2. real cflib connects (TOC and param values; the TOC cache makes later trials faster) and sets the
   ``polycc`` params of the :class:`~polycc.sim.sitl.FlightConfig`;
3. high-level takeoff to the start height (at most 0.5 m/s), then ``polycc.enable = 1`` with the goal:
   the app flies through the certified filter. The trial's clock starts here, as the fast simulator's
   starts hovering at the start;
4. it ends like the fast one: within ``goal_tol_m`` of the goal ("goal"), moved less than
   ``stuck_dist_m`` in ``stuck_window_s`` ("stuck"), or ``t_max_s`` ("timeout"); waypoints of a plan
   are switched by the same rule;
5. ``polycc.enable = 0`` (the app hands over to the high-level commander), high-level landing, session
   closed without cflib's motor-cutting stop setpoint, processes stopped.

The trial's path is the bridge's truth at 100 Hz of simulated time from step 3 to step 4; clearance to
the ground-truth ellipsoids and collisions are computed exactly as for the fast simulator
(:mod:`polycc.sim.clearance`), ``max_eval_us`` with the cycle model at the logged estimates (the SITL's
``usecTimestamp`` has 1 ms resolution, so the firmware's own ``polycc.evalUs`` says nothing), and the
barrier-rate gap from the app's logged command at 50 Hz (:meth:`FirmwareSimulator.rate_gap`).
"""

from __future__ import annotations

import threading
import time
from pathlib import Path

import numpy as np

from polycc.budget import cycle_model
from polycc.errors import PolyccError
from polycc.link.cflib_tools import close_without_stop, connect, set_param
from polycc.onboard.app import STATUS_NAMES
from polycc.sim.clearance import Clearance, densify
from polycc.sim.firmware.build import Cf2Build, build_cf2
from polycc.sim.firmware.sitl import FirmwareSitl, SitlStall
from polycc.sim.sitl import FlightConfig, Trial

TAKEOFF_SPEED = 0.5  # m/s
LAND_SPEED = 0.3     # m/s
SAMPLE_S = 0.02      # polling period of the truth, wall seconds
# one 25-byte log block (of 26) at 50 Hz: the estimate, the app's status and its last velocity command
LOG_VARS = (("stateEstimate.x", "float"), ("stateEstimate.y", "float"), ("stateEstimate.z", "float"),
            ("polycc.status", "uint8_t"), ("polycc.ux", "float"), ("polycc.uy", "float"), ("polycc.uz", "float"))
STATUS_OK = next(k for k, v in STATUS_NAMES.items() if v == "ok")  # the app sent its velocity command
# cfg.shield: the shield's counters the firmware logs (group polyccShield, polycc_controller.c), and the
# out-of-tree controller's number in the SITL fork's ControllerType enum (src/modules/interface/controller/
# controller.h: AutoSelect, PID, Mellinger, INDI, Brescianini, Oot; upstream has Lee before Oot: 6)
SHIELD_LOGS = ("decisions", "backups", "infeasible", "manual", "landings", "escapes", "bridged", "expired")
SITL_OOT_CONTROLLER = 5
SHIELD_HZ = 1000.0 / cycle_model.SHIELD_PERIOD_TICKS  # the shield's decisions per second (1 ms ticks)
STARVED_SHARE = 0.9  # fewer shield decisions than this share of SHIELD_HZ per flown second: the app was starved
STARVED_RERUNS = 2   # a starved trial is flown again at most this many times


def decisions_per_s(trial: Trial) -> float | None:
    """The shield's decisions per flown second of a trial (None without the shield)."""
    if not trial.shield or not trial.time_s:
        return None
    return trial.shield["decisions"] / trial.time_s


class FirmwareSimulator:
    """Real-firmware trials for one build folder (``polytopes.h``) and a SITL tree or tarball.

    ``packed`` (a :class:`~polycc.onboard.layout.PackedScene`) and ``kappa`` feed the cycle model;
    ``ellipsoids`` the ground-truth clearance. ``run_root``: per-trial folders with ``cf2.log``,
    ``bridge.err`` and ``trajectory.csv`` (default: temporary, removed after a clean trial).
    ``say(msg)`` gets progress lines."""

    def __init__(self, header, tree, packed, kappa: float, ellipsoids=None, run_root=None, rtf_max: float = 1.0,
                 say=None, build: Cf2Build | None = None, connect_timeout_s: float = 90.0):
        self.say = say or (lambda msg: None)
        self.build = build or build_cf2(tree, header, log=self.say)
        self.packed, self.kappa = packed, kappa
        self.clearance = Clearance(ellipsoids) if ellipsoids is not None and len(ellipsoids) else None
        self.run_root = Path(run_root) if run_root is not None else None
        self.rtf_max = rtf_max
        self.connect_timeout_s = connect_timeout_s
        self.n = 0
        # cflib's TOC cache is left off: both stalled connects seen had it on (not root-caused); ~1 s per connect
        self.toc_cache = None
        self._host_scene = None  # the kernel's scene for rate_gap, built on first use

    def fly(self, start, goal, cfg: FlightConfig | None = None, waypoints=None) -> Trial:
        """One trial on a fresh SITL instance, flown again on a fresh instance when the simulator, not the
        flight, failed; ``extra["sitl_reruns"]`` counts the reruns and ``extra["sitl_rerun_reasons"]`` says why.

        * A SITL that hangs (:class:`SitlStall`: cf2 stops taking ticks with both processes alive; seen once
          in ~30 CI trials, root cause open, its diagnostics are in the message): once.
        * A starved shield (fewer than :data:`STARVED_SHARE` of its :data:`SHIELD_HZ` decisions per flown
          second): the host did not give the app task its CPU time, so late decisions were flown as brakes
          and the trial is not what the M4 would fly (CI: 73 decisions/s at RTF 0.29, "stuck" in front of the
          first hoop). Up to :data:`STARVED_RERUNS` times; the last trial is kept either way, and
          `polycc sim` warns when it is still starved."""
        reasons: list[str] = []
        while True:
            try:
                trial = self._fly_once(start, goal, cfg, waypoints)
            except SitlStall as exc:
                if any(r.startswith("hung") for r in reasons):
                    raise
                self.say(f"{exc}; the simulator hung, not the flight: flying this trial again on a fresh instance")
                reasons.append("hung")
                continue
            rate = decisions_per_s(trial)
            if rate is not None and rate < STARVED_SHARE * SHIELD_HZ and \
                    sum(r.startswith("starved") for r in reasons) < STARVED_RERUNS:
                self.say(f"the shield decided only {rate:.0f} times per flown second of its {SHIELD_HZ:.0f} (RTF "
                         f"{trial.extra.get('rtf') or 0:.2f}): the host starved the app task, so this flight is not "
                         "what the M4 would fly; flying this trial again on a fresh instance")
                reasons.append(f"starved ({rate:.0f} decisions/s)")
                continue
            break
        trial.extra["sitl_reruns"] = len(reasons)
        trial.extra["sitl_rerun_reasons"] = reasons
        return trial

    def _fly_once(self, start, goal, cfg: FlightConfig | None = None, waypoints=None) -> Trial:
        cfg = cfg or FlightConfig()
        self.n += 1
        start = np.asarray(start, np.float64)
        goal = np.asarray(goal, np.float64)
        targets = goal[None] if waypoints is None else np.asarray(waypoints, np.float64).reshape(-1, 3)
        if not np.allclose(targets[-1], goal):
            raise PolyccError("the plan's last waypoint is not the goal; plan again for this goal")
        if len(targets) > 1 and np.allclose(targets[0], start):
            targets = targets[1:]
        run_dir = None if self.run_root is None else self.run_root / f"trial{self.n}"
        sitl = FirmwareSitl(self.build, start=(start[0], start[1], 0.0), run_dir=run_dir, rtf_max=self.rtf_max)
        with sitl:
            self.say(f"firmware booted in {sitl.t_ready:.1f} s ({sitl.uri})")
            t_c = time.monotonic()
            try:
                scf = connect(sitl.uri, self.connect_timeout_s, self.toc_cache)
            except PolyccError as exc:
                # seen twice in ~40 connects on a heavily loaded host, before the ARQ covered cflib's first
                # request (polycc.sim.firmware.arq); a fresh cflib session connected each time (reported)
                self.say(f"{exc}; retrying once with a fresh cflib session")
                scf = connect(sitl.uri, self.connect_timeout_s, None)
            try:
                self.say(f"cflib connected in {time.monotonic() - t_c:.1f} s")
                trial, extra = self._flight(sitl, scf.cf, start, goal, targets, cfg)
                if waypoints is not None:
                    trial.waypoints = np.asarray(waypoints, np.float64).reshape(-1, 3)
            finally:
                close_without_stop(scf)
            st = sitl.stats()
            extra.update(rtf=st.get("rtf"), sim_s=st.get("sim_t"), wall_s=st.get("wall_t"),
                         retransmits=st.get("arq_retransmits", 0), run_dir=str(sitl.run_dir) if run_dir else None)
        trial.extra = extra
        if self.clearance is not None:
            r_phys = cfg.radius if cfg.clearance_radius is None else cfg.clearance_radius
            trial.min_clearance_m, trial.collisions, _ = self.clearance.evaluate(densify(trial.positions), r_phys)
        return trial

    def rate_gap(self, flight, traj: np.ndarray, params) -> np.ndarray:
        """Realized minus commanded barrier rate, grad psi . (v_true - u) in m/s (Prop. 1 of seed 001), at every
        log sample where the app sent its velocity command u (status OK), as the fast simulator's
        ``Trial.rate_gap``: grad psi from the same kernel on the host (``polycc_step``, float32) at the logged
        estimate, v_true the bridge's truth velocity interpolated at the sample's firmware time (ticks / 1000 =
        simulated seconds, lock-step). The fast simulator takes the app's own grad psi at its last evaluation,
        up to 10 ms older."""
        rows = [r for r in flight if int(r[4]) == STATUS_OK and None not in r[1:4] and None not in r[5:8]]
        if not rows or len(traj) < 2:
            return np.zeros(0)
        from polycc.sim import kernel_ffi

        R = np.asarray([r[:4] + r[5:8] for r in rows], np.float64)
        t = R[:, 0] / 1000.0
        keep = (t >= traj[0, 0]) & (t <= traj[-1, 0])
        if not keep.any():
            return np.zeros(0)
        R, t = R[keep], t[keep]
        if self._host_scene is None:
            self._host_scene = kernel_ffi.HostScene(self.packed)
        grad = kernel_ffi.step_batch(self._host_scene, params, R[:, 1:4], R[:, 1:4])["grad"].astype(np.float64)
        v = np.stack([np.interp(t, traj[:, 0], traj[:, 4 + i]) for i in range(3)], axis=1)
        return np.einsum("ij,ij->i", grad, v - R[:, 4:7])

    # ------------------------------------------------------------------ one flight
    def _start_shield(self, cf, cfg: FlightConfig):
        """cfg.shield: the out-of-tree controller and the shield's params as the fast simulator sets them, and
        a log block of its counters; returns (log config, lock, latest values). The shield is switched on at
        the start height, before the app (the fast simulator starts there, hovering): from the floor, where
        the vehicle's ball touches the floor splats (psi <= 0), it would hold the vehicle on the floor."""
        from cflib.crazyflie.log import LogConfig

        if cf.param.toc.get_element_by_complete_name("polyccShield.enable") is None:
            raise PolyccError("--shield: this cf2 has no shield (param polyccShield.enable); build it with the "
                              "polycc app's app-config (CONFIG_CONTROLLER_OOT=y)")
        r_sh = cfg.shield_radius if cfg.shield_radius is not None else (
            cfg.clearance_radius if cfg.clearance_radius is not None else cfg.radius)
        set_param(cf, "polyccShield.radius", r_sh)
        if cfg.shield_tube is not None:
            set_param(cf, "polyccShield.tube", cfg.shield_tube)
        set_param(cf, "polyccShield.psicap", cfg.shield_psi_cap)
        if cfg.shield_gains is not None:
            set_param(cf, "polyccShield.k1", float(cfg.shield_gains[0]))
            set_param(cf, "polyccShield.k0", float(cfg.shield_gains[1]))
        set_param(cf, "stabilizer.controller", SITL_OOT_CONTROLLER)  # polyccShield.enable after the takeoff
        lock, latest = threading.Lock(), {}

        def on_log(ts, data, conf):
            with lock:
                latest.update(data)

        blocks = []
        for i in range(0, len(SHIELD_LOGS), 6):  # a log block holds 26 bytes: six uint32 counters each
            lc = LogConfig(name=f"polyccshield{i // 6}", period_in_ms=100)
            for k in SHIELD_LOGS[i:i + 6]:
                lc.add_variable(f"polyccShield.{k}", "uint32_t")
            lc.data_received_cb.add_callback(on_log)
            cf.log.add_config(lc)
            lc.start()
            blocks.append(lc)
        return blocks, lock, latest

    def _flight(self, sitl: FirmwareSitl, cf, start, goal, targets, cfg: FlightConfig):
        from cflib.crazyflie.log import LogConfig

        lock = threading.Lock()
        samples: list[tuple] = []
        latest: dict = {}

        def on_log(ts, data, conf):
            with lock:
                latest.update(data)
                samples.append((ts, latest.get("stateEstimate.x"), latest.get("stateEstimate.y"),
                                latest.get("stateEstimate.z"), latest.get("polycc.status", -1),
                                latest.get("polycc.ux"), latest.get("polycc.uy"), latest.get("polycc.uz")))

        lc = LogConfig(name="polyccsim", period_in_ms=20)
        for name, ctype in LOG_VARS:
            lc.add_variable(name, ctype)
        lc.data_received_cb.add_callback(on_log)
        cf.log.add_config(lc)
        lc.start()
        for name, value in (("rateHz", cfg.rate_hz), ("vmax", cfg.vmax), ("beta", cfg.beta),
                            ("clfGain", cfg.clf_gain), ("radius", cfg.radius)):
            set_param(cf, f"polycc.{name}", value)
        shield_log = self._start_shield(cf, cfg) if cfg.shield else None

        def set_goal(w):
            for axis, v in zip("XYZ", w):
                set_param(cf, f"polycc.goal{axis}", float(v))

        set_goal(targets[0])
        # a session that streamed setpoints before leaves the CRTP priority, where HL commands are ignored
        cf.commander.send_notify_setpoint_stop()
        duration = max(1.0, float(start[2]) / TAKEOFF_SPEED)
        cf.high_level_commander.takeoff(float(start[2]), duration)
        ok = sitl.wait_until(lambda: abs(sitl.truth()[0][2] - start[2]) < 0.05, duration + 5.0)
        if not ok:
            p = sitl.truth()[0]
            raise PolyccError(f"the high-level takeoff to {start[2]:.2f} m did not get there within "
                              f"{duration + 5:.0f} s simulated (z = {p[2]:.2f} m); see {sitl.cf2_log}")
        sitl.sleep(0.5)
        if shield_log is not None:
            set_param(cf, "polyccShield.enable", 1)
            sitl.sleep(0.1)
        self.say(f"took off to {start[2]:.2f} m; flying to {', '.join(f'{v:.2f}' for v in goal)}")
        t0 = sitl.time()
        n0 = len(samples)
        set_param(cf, "polycc.enable", 1)
        planned = float(np.sum(np.linalg.norm(np.diff(np.vstack([start, targets]), axis=0), axis=1)))
        t_max = cfg.t_max_s if cfg.t_max_s is not None else 2.0 * planned / cfg.vmax + 10.0 + 4.0 * (len(targets) - 1)
        outcome, current = "timeout", 0
        hist: list[tuple[float, np.ndarray]] = []
        while True:
            s = sitl.state()
            t, p = float(s["t"]) - t0, np.asarray(s["pos"])
            hist.append((t, p))
            if np.linalg.norm(p - goal) <= cfg.goal_tol_m:
                outcome, current = "goal", len(targets)
                break
            while current < len(targets) - 1 and np.linalg.norm(p - targets[current]) <= cfg.switch_tol_m:
                current += 1
                set_goal(targets[current])
            if t >= t_max:
                break
            if t > cfg.stuck_window_s:
                old = next((q for tq, q in reversed(hist) if tq <= t - cfg.stuck_window_s), None)
                if old is not None and np.linalg.norm(p - old) < cfg.stuck_dist_m:
                    outcome = "stuck"
                    break
            sitl.note_time(t + t0)
            time.sleep(SAMPLE_S)
        t_end = sitl.time()
        with lock:
            flight = list(samples[n0:])
        shield = None
        if shield_log is not None:  # the counters at the end of the flight (the landing is not counted)
            sitl.sleep(0.2)  # one more log period
            with shield_log[1]:
                shield = {k: int(shield_log[2].get(f"polyccShield.{k}", 0)) for k in SHIELD_LOGS}
        set_param(cf, "polycc.enable", 0)  # the app hands the vehicle to the high-level commander
        self.say(f"{outcome} after {t_end - t0:.1f} s simulated; landing")
        sitl.sleep(0.5)
        z = float(sitl.truth()[0][2])
        land_s = max(2.0, z / LAND_SPEED)
        cf.high_level_commander.land(0.0, land_s)
        landed = sitl.wait_until(lambda: sitl.state()["on_ground"] and not sitl.state()["motors_on"], land_s + 5.0)
        lc.stop()
        if shield_log is not None:
            for lc in shield_log[0]:
                lc.stop()
        traj = sitl.trajectory()
        sel = (traj[:, 0] >= t0) & (traj[:, 0] <= t_end + 1e-9)
        P = traj[sel, 1:4]
        if len(P) == 0:
            P = np.asarray([start])
        statuses: dict[int, int] = {}
        est = []
        for _, x, y, zz, st, *_u in flight:
            statuses[int(st)] = statuses.get(int(st), 0) + 1
            if None not in (x, y, zz):
                est.append((x, y, zz))
        params = cfg.params(self.kappa)
        max_eval = int(cycle_model.us(cycle_model.state_cycles(self.packed, params, np.asarray(est))).max()) \
            if est else 0
        impacts = sitl.impacts()
        trial = Trial(start, goal, outcome == "goal", outcome, t_end - t0,
                      float(np.sum(np.linalg.norm(np.diff(P, axis=0), axis=1))), float(np.linalg.norm(goal - start)),
                      P, max_eval, statuses, reached=current)
        trial.impact_speed_ms = max((float(i["speed"]) for i in impacts), default=0.0)
        trial.shield = shield
        # jerk of the true vehicle at 100 Hz, as the fast simulator's: from the truth's velocity (%.6g rows:
        # 1e-5 m/s steps, i.e. about 0.1 m/s^3 of jerk resolution)
        Tt, V = traj[sel, 0], traj[sel, 4:7]
        if len(V) > 2:
            A = np.diff(V, axis=0) / np.diff(Tt)[:, None]
            trial.jerk = np.linalg.norm(np.diff(A, axis=0), axis=1) / np.diff(Tt)[1:]
        else:
            trial.jerk = np.zeros(0)
        trial.rate_gap = self.rate_gap(flight, traj, params)
        extra = {"landed": bool(landed), "touchdown_ms": trial.impact_speed_ms,
                 "start_actual": P[0].tolist(), "takeoff_s": duration}
        return trial, extra
