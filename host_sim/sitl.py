"""Software-in-the-loop flights: the real app (host build, :mod:`host_sim.app_ffi`) stepped tick
by tick on a simulated clock against a vehicle model (:mod:`host_sim.dynamics`), with
clearance measured to the ground-truth splat ellipsoids.

One app tick at FreeRTOS tick ``k`` (1 ms):
  1. the model's delayed position goes into the shim's ``stateEstimate.x/y/z``;
  2. the cycle model sets how long ``usecTimestamp`` says the kernel call took;
  3. ``polycc_app_tick()`` runs (reads the log variables, runs the kernel, calls
     ``commanderSetSetpoint``) and returns its period ``P`` in ticks;
  4. the model flies the commander's velocity setpoint for ``P`` ms; the clock moves to ``k + P``.

Clearance (:class:`Clearance`) is the EXACT Euclidean distance from the vehicle centre to
the nearest ellipsoid (to float64 rounding: bisection on the Lagrange multiplier of the
closest-point problem), minus the agent radius.  Only nearby ellipsoids are evaluated: a
KD-tree over the centres gives upper and lower bounds per point, and exact distances are
computed only where the lower bound can matter.  Trajectories are resampled to at most
``SAMPLE_SPACING_M`` between points, so the reported minimum is within half that spacing
of the continuous minimum along the piecewise-linear path.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from host_sim.app_ffi import AppSim
from host_sim.dynamics import make_dynamics
from polycc import cycle_model
from polycc.barrier import Params
from polycc.barrier import barrier as ref_barrier
from polycc.errors import PolyccError
from polycc.scene_layout import PackedScene

SAMPLE_SPACING_M = 0.0025
GOAL_TOLERANCE_M = 0.05


# --------------------------------------------------------------------------- cycle model
class CycleModel:
    """Microseconds of one ``polycc_step`` on the Crazyflie's STM32F405 (Cortex-M4F, 168 MHz)
    from :mod:`polycc.cycle_model` (fitted to instruction-level measurements of the ARM build,
    bench/bench_kernel.py).

    * :meth:`worst_us`: every cluster, polytope and half-plane evaluated; the SITL gives this
      to ``usecTimestamp``, so the app's ``evalUs`` log shows the worst case;
    * :meth:`eval_us`: per state, with the polytopes the kernel actually enters and evaluates
      there (counted by the float32 reference :func:`polycc.barrier.barrier`); a trial reports
      the largest over the states it visited."""

    def __init__(self, packed: PackedScene, params: Params):
        self.packed = packed
        self.params = params
        self.mean_planes = packed.n_planes / max(packed.n_polys, 1)

    def _us(self, cycles) -> np.ndarray:
        return np.ceil(np.asarray(cycles, np.float64) / cycle_model.CPU_HZ * 1e6).astype(np.int64)

    def worst_us(self) -> int:
        p = self.packed
        return int(self._us(cycle_model.cycles(p.n_clusters, p.n_polys, p.n_polys, p.n_planes)))

    def eval_us(self, X: np.ndarray) -> np.ndarray:
        """Modelled microseconds at each state of X (n, 3)."""
        X = np.asarray(X, np.float32).reshape(-1, 3)
        if len(X) == 0:
            return np.zeros(0, np.int64)
        stats: dict = {}
        ref_barrier(self.packed, self.params, X, stats=stats)
        ev = np.asarray(stats["evaluated"], np.float64)
        return self._us(cycle_model.cycles(self.packed.n_clusters, np.asarray(stats["entered"], np.float64), ev,
                                           ev * self.mean_planes))


# --------------------------------------------------------------------------- clearance
def point_ellipsoid_distance(y: np.ndarray, a: np.ndarray, iters: int = 100) -> np.ndarray:
    """Exact distance from points ``y`` (n, 3) in each ellipsoid's principal frame to the
    ellipsoids {sum (y_i/a_i)^2 <= 1} with semi-axes ``a`` (n, 3); 0 inside.

    Outside, the closest point is x_i = a_i^2 y_i / (t + a_i^2) with t > 0 the root of
    f(t) = sum (a_i y_i / (t + a_i^2))^2 - 1, decreasing on (0, |a|_max |y|]; bisection to
    float64 resolution."""
    y = np.abs(np.asarray(y, np.float64))
    a = np.asarray(a, np.float64)
    inside = np.sum((y / a) ** 2, axis=1) <= 1.0
    a2 = a * a
    lo = np.zeros(len(y))
    hi = np.max(a, axis=1) * np.linalg.norm(y, axis=1) + 1e-300
    for _ in range(iters):
        mid = 0.5 * (lo + hi)
        f = np.sum((a * y / (mid[:, None] + a2)) ** 2, axis=1) - 1.0
        pos = f > 0
        lo = np.where(pos, mid, lo)
        hi = np.where(pos, hi, mid)
        if np.all(hi - lo <= 1e-15 * np.maximum(hi, 1e-300)):
            break
    t = 0.5 * (lo + hi)
    x = a2 * y / (t[:, None] + a2)
    d = np.linalg.norm(y - x, axis=1)
    return np.where(inside, 0.0, d)


class Clearance:
    """Distances from points to the nearest splat ellipsoid (ground truth), exact where it matters."""

    def __init__(self, ellipsoids, k_nn: int = 16):
        from scipy.spatial import cKDTree

        e = ellipsoids
        self.centers = np.asarray(e.centers, np.float64)
        self.R = np.asarray(e.rotations, np.float64)
        self.a = np.asarray(e.sigmas, np.float64) * float(e.k)
        amax = self.a.max(axis=1)
        self.amin = self.a.min(axis=1)
        self.amax = amax
        big_cut = max(0.1, 20.0 * float(np.median(amax))) if len(amax) else 0.1
        self.big = np.flatnonzero(amax > big_cut)
        self.small = np.flatnonzero(amax <= big_cut)
        self.amax_small = float(amax[self.small].max()) if len(self.small) else 0.0
        self.tree = cKDTree(self.centers[self.small]) if len(self.small) else None
        self.k = min(k_nn, len(self.small))

    def _exact(self, p: np.ndarray, idx: np.ndarray) -> float:
        if len(idx) == 0:
            return math.inf
        y = np.einsum("nji,nj->ni", self.R[idx], p[None, :] - self.centers[idx])
        return float(point_ellipsoid_distance(y, self.a[idx]).min())

    def bounds(self, P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per point (lower, upper) bounds on the distance to the nearest ellipsoid."""
        n = len(P)
        lb = np.full(n, np.inf)
        ub = np.full(n, np.inf)
        if self.tree is not None and self.k > 0:
            d, j = self.tree.query(P, k=self.k)
            d, j = d.reshape(n, -1), j.reshape(n, -1)
            g = self.small[j]
            ub = np.minimum(ub, np.min(d - self.amin[g], axis=1))
            lb = np.minimum(np.min(d - self.amax[g], axis=1), d[:, -1] - self.amax_small)
        if len(self.big):
            db = np.linalg.norm(P[:, None, :] - self.centers[self.big][None], axis=2)
            ub = np.minimum(ub, np.min(db - self.amin[self.big], axis=1))
            lb = np.minimum(lb, np.min(db - self.amax[self.big], axis=1))
        return np.maximum(lb, 0.0), np.maximum(ub, 0.0)

    def exact_at(self, p: np.ndarray, ub: float) -> float:
        """Exact distance from one point, given an upper bound ``ub`` on it."""
        cand = []
        if self.tree is not None:
            j = np.asarray(self.tree.query_ball_point(p, ub + self.amax_small), dtype=np.int64)
            if len(j):
                g = self.small[j]
                dd = np.linalg.norm(self.centers[g] - p, axis=1)
                cand.append(g[dd - self.amax[g] <= ub])
        if len(self.big):
            dd = np.linalg.norm(self.centers[self.big] - p, axis=1)
            cand.append(self.big[dd - self.amax[self.big] <= ub])
        idx = np.concatenate(cand) if cand else np.zeros(0, np.int64)
        return self._exact(p, idx)

    def evaluate(self, P: np.ndarray, radius: float) -> tuple[float, int, np.ndarray]:
        """(minimum clearance = distance - radius, collision events, exact-or-lower-bound distances).

        A collision event is a maximal run of consecutive points whose exact distance is
        below ``radius`` (the agent ball touches a splat)."""
        P = np.asarray(P, np.float64).reshape(-1, 3)
        lb, ub = self.bounds(P)
        thr = max(float(ub.min()), radius)
        dist = lb.copy()
        for i in np.flatnonzero(lb <= thr):
            dist[i] = self.exact_at(P[i], float(ub[i]))
        hit = dist < radius
        events = int(np.count_nonzero(hit[1:] & ~hit[:-1]) + (1 if hit[0] else 0)) if len(hit) else 0
        return float(dist.min()) - radius, events, dist


def densify(P: np.ndarray, spacing: float = SAMPLE_SPACING_M) -> np.ndarray:
    """Piecewise-linear resampling so consecutive points are at most ``spacing`` apart."""
    P = np.asarray(P, np.float64)
    if len(P) < 2:
        return P
    seg = np.linalg.norm(np.diff(P, axis=0), axis=1)
    k = np.maximum(1, np.ceil(seg / spacing).astype(np.int64))
    i = np.repeat(np.arange(len(seg)), k)
    t = (np.arange(len(i)) - np.repeat(np.cumsum(k) - k, k) + 1) / np.repeat(k, k)
    return np.concatenate([P[:1], P[i] + t[:, None] * (P[i + 1] - P[i])])


# --------------------------------------------------------------------------- flights
@dataclass
class FlightConfig:
    """App parameters (the polycc param group) and the simulation limits."""

    rate_hz: int = 500
    vmax: float = 0.5  # m/s
    beta: float = 1.0  # 1/s
    clf_gain: float = 2.0  # 1/s
    radius: float = 0.1  # m, the app's polycc.radius
    clearance_radius: float | None = None  # m, physical radius for clearance/collisions (default: radius)
    t_max_s: float | None = None  # default: 2 * distance / vmax + 10 s
    goal_tol_m: float = GOAL_TOLERANCE_M
    stuck_window_s: float = 2.0  # stop when the vehicle moved less than stuck_dist_m in this window
    stuck_dist_m: float = 0.01
    record_app_io: bool = False  # keep what the app saw and sent, tick by tick

    def params(self, kappa: float) -> Params:
        return Params(kappa=kappa, radius=self.radius, beta=self.beta, c_clf=self.clf_gain, v_max=self.vmax)


@dataclass
class Trial:
    start: np.ndarray
    goal: np.ndarray
    success: bool
    outcome: str  # "goal", "stuck", "timeout"
    time_s: float
    path_length_m: float
    straight_m: float
    positions: np.ndarray  # true positions after every app period (n, 3), metres
    max_eval_us: int  # cycle model at the states the app evaluated (largest); the app's log shows the worst case
    statuses: dict[int, int]  # polycc.status value -> number of ticks
    min_clearance_m: float = math.nan  # ground-truth ellipsoids, agent radius subtracted
    collisions: int = -1
    io: dict | None = None  # record_app_io: per tick what the app saw, sent and gave/got from the kernel

    @property
    def length_ratio(self) -> float:
        return self.path_length_m / self.straight_m if self.straight_m > 0 else math.nan


class Simulator:
    """The app built for one ``polytopes.h``, a cycle model and (optionally) the ground truth."""

    def __init__(self, header: str | Path, ellipsoids=None, brake: bool = True):
        """``brake=False`` builds the app with its braking term compiled out (POLYCC_APP_BRAKE_ACC = 0):
        the plain CBF filter of the paper."""
        self.app = AppSim(header, None if brake else {"POLYCC_APP_BRAKE_ACC": "0.0f"})
        self.packed = self.app.packed_scene()
        self.kappa = self.app.kappa
        self.clearance = Clearance(ellipsoids) if ellipsoids is not None and len(ellipsoids) else None

    def fly(self, start, goal, dynamics: str = "integrator", cfg: FlightConfig | None = None,
            delay_s: float | None = None) -> Trial:
        cfg = cfg or FlightConfig()
        app, lib = self.app, self.app.lib
        start = np.asarray(start, np.float64)
        goal = np.asarray(goal, np.float64)
        dyn = make_dynamics(dynamics, delay_s)
        dyn.reset(start)
        app.reset()
        for name, val in (("goalX", goal[0]), ("goalY", goal[1]), ("goalZ", goal[2]), ("vmax", cfg.vmax),
                          ("beta", cfg.beta), ("clfGain", cfg.clf_gain), ("radius", cfg.radius),
                          ("rateHz", cfg.rate_hz), ("enable", 1)):
            app.set_param("polycc", name, val)
        goal32 = goal.astype(np.float32)
        straight = float(np.linalg.norm(goal - start))
        t_max = cfg.t_max_s if cfg.t_max_s is not None else 2.0 * straight / cfg.vmax + 10.0
        i_psi = app._log_index["polycc.psi"]
        i_status = app._log_index["polycc.status"]
        cycle = CycleModel(self.packed, cfg.params(self.kappa))
        worst_us = cycle.worst_us()
        seen = []
        rec = app.ffi.new("shim_commander_record_t *")
        tick = 0
        positions = [start.copy()]
        times = [0.0]
        statuses: dict[int, int] = {}
        io = ({k: [] for k in ("x_seen", "u", "psi", "status", "calls", "x_kernel", "vmax", "out_u", "out_psi",
                                "out_flags")} if cfg.record_app_io else None)
        outcome = "timeout"
        stuck_ticks = None
        while True:
            pe, ve = dyn.estimate()
            est = pe.astype(np.float32)
            lib.shim_set_estimate(float(est[0]), float(est[1]), float(est[2]), float(ve[0]), float(ve[1]), float(ve[2]))
            lib.shim_set_tick(tick)
            lib.shim_set_usec(tick * 1000, worst_us)
            seen.append(est)
            period = int(lib.polycc_app_tick())
            lib.shim_commander_get(rec)
            u = (rec.vx, rec.vy, rec.vz)
            st = int(lib.shim_log_value(i_status))
            statuses[st] = statuses.get(st, 0) + 1
            if io is not None:
                tr = lib.polycc_app_trace()
                io["x_seen"].append(est)
                io["u"].append(u)
                io["psi"].append(lib.shim_log_value(i_psi))
                io["status"].append(st)
                io["calls"].append(tr.calls)
                io["x_kernel"].append(tuple(tr.x))
                io["vmax"].append(tr.params.v_max)
                io["out_u"].append(tuple(tr.out.u))
                io["out_psi"].append(tr.out.psi)
                io["out_flags"].append(tr.out.flags)
            dyn.step(u, period * 1e-3)
            tick += period
            t = tick * 1e-3
            positions.append(dyn.p.copy())
            times.append(t)
            if np.linalg.norm(dyn.p - goal) <= cfg.goal_tol_m:
                outcome = "goal"
                break
            if t >= t_max:
                break
            if stuck_ticks is None:
                stuck_ticks = max(1, int(round(cfg.stuck_window_s * 1000 / period)))
            if len(positions) > stuck_ticks and t > cfg.stuck_window_s and \
                    np.linalg.norm(positions[-1] - positions[-1 - stuck_ticks]) < cfg.stuck_dist_m:
                outcome = "stuck"
                break
        P = np.asarray(positions)
        max_eval = int(cycle.eval_us(np.asarray(seen)).max())
        trial = Trial(start, goal, outcome == "goal", outcome, times[-1],
                      float(np.sum(np.linalg.norm(np.diff(P, axis=0), axis=1))), straight, P, max_eval, statuses)
        if io is not None:
            f3 = lambda k: np.asarray(io[k], np.float32).reshape(-1, 3)  # noqa: E731
            trial.io = {"x_seen": f3("x_seen"), "u": f3("u"), "psi": np.asarray(io["psi"], np.float64).astype(np.float32),
                        "status": np.asarray(io["status"], np.int64), "goal": goal32,
                        "calls": np.asarray(io["calls"], np.int64), "x_kernel": f3("x_kernel"),
                        "vmax": np.asarray(io["vmax"], np.float32), "out_u": f3("out_u"),
                        "out_psi": np.asarray(io["out_psi"], np.float32),
                        "out_flags": np.asarray(io["out_flags"], np.uint32)}
        if self.clearance is not None:
            r_phys = cfg.radius if cfg.clearance_radius is None else cfg.clearance_radius
            trial.min_clearance_m, trial.collisions, _ = self.clearance.evaluate(densify(P), r_phys)
        return trial


# --------------------------------------------------------------------------- start/goal pairs
def free_points(packed: PackedScene, params: Params, lo, hi, n: int, rng: np.random.Generator,
                margin: float = 0.05, max_rounds: int = 50) -> np.ndarray:
    """``n`` uniform points in the box [lo, hi] with psi >= margin (outside every inflated polytope)."""
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    out: list[np.ndarray] = []
    got = 0
    for _ in range(max_rounds):
        cand = rng.uniform(lo, hi, size=(max(64, 2 * n), 3))
        psi, _, flags = ref_barrier(packed, params, cand.astype(np.float32))
        ok = cand[(flags == 0) & (psi >= margin)]
        out.append(ok)
        got += len(ok)
        if got >= n:
            break
    pts = np.concatenate(out) if out else np.zeros((0, 3))
    if len(pts) < n:
        raise PolyccError(f"found only {len(pts)} free points in the sampling box; enlarge it or use fewer pairs")
    return pts[:n]


def random_pairs(packed: PackedScene, params: Params, lo, hi, n_pairs: int, min_distance: float,
                 seed: int = 0) -> list[tuple[np.ndarray, np.ndarray]]:
    """The paper's protocol: ``n_pairs`` start/goal pairs in free space, at least ``min_distance`` apart."""
    rng = np.random.default_rng(seed)
    diag = float(np.linalg.norm(np.asarray(hi) - np.asarray(lo)))
    if min_distance >= diag:
        raise PolyccError(f"--min-distance {min_distance:g} m is not below the sampling box diagonal {diag:.2f} m; lower it")
    pts = free_points(packed, params, lo, hi, 8 * n_pairs, rng)
    pairs = []
    used = np.zeros(len(pts), bool)
    for i in range(len(pts)):
        if len(pairs) == n_pairs:
            break
        if used[i]:
            continue
        d = np.linalg.norm(pts - pts[i], axis=1)
        ok = np.flatnonzero((d >= min_distance) & ~used)
        if len(ok) == 0:
            continue
        j = int(rng.choice(ok))
        used[i] = used[j] = True
        pairs.append((pts[i], pts[j]))
    if len(pairs) < n_pairs:
        raise PolyccError(f"only {len(pairs)} of {n_pairs} start/goal pairs are {min_distance:g} m apart; lower --min-distance")
    return pairs


def sampling_box(ellipsoids, z_min: float = 0.15) -> tuple[np.ndarray, np.ndarray]:
    """Robust bounds of the splat centres (0.5-99.5 percentiles), floor raised to ``z_min``."""
    c = np.asarray(ellipsoids.centers)
    lo, hi = np.percentile(c, 0.5, axis=0), np.percentile(c, 99.5, axis=0)
    lo[2] = max(lo[2], z_min)
    hi[2] = max(hi[2], lo[2] + 0.5)
    return lo, hi


# --------------------------------------------------------------------------- plot
def polytope_vertices(h: np.ndarray, interior) -> np.ndarray:
    from scipy.spatial import HalfspaceIntersection

    h = np.asarray(h, np.float64)
    hs = np.c_[h[:, :3], -h[:, 3]]
    return HalfspaceIntersection(hs, np.asarray(interior, np.float64)).intersections


def plot_trajectories(path: str | Path, trials: list[Trial], packed: PackedScene, ellipsoids=None,
                      title: str = "", max_splats: int = 40000, seed: int = 0) -> Path:
    """Three views (top x-y, front x-z, side y-z) of the paths over the splats and polytopes."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Polygon
    from scipy.spatial import ConvexHull

    views = (("top (x-y)", 0, 1), ("front (x-z)", 0, 2), ("side (y-z)", 1, 2))
    fig, axes = plt.subplots(1, 3, figsize=(18, 6.5))
    verts = []
    for k, h in enumerate(packed.polytopes()):
        p = packed.polys[k]
        try:
            verts.append(polytope_vertices(h, (p["cx"], p["cy"], p["cz"])))
        except Exception:  # degenerate for qhull: skip the drawing only
            continue
    pts = cols = None
    if ellipsoids is not None and len(ellipsoids):
        rng = np.random.default_rng(seed)
        sel = rng.choice(len(ellipsoids), size=min(max_splats, len(ellipsoids)), replace=False)
        pts = ellipsoids.centers[sel]
        cols = ellipsoids.colors[sel] / 255.0 if ellipsoids.colors is not None else "0.4"
    labels = "axyz"
    # The top view leaves out the floor (polytopes and splats within 0.15 m of the lowest
    # polytope), which would hide everything else.
    z0 = min((float(v[:, 2].min()) for v in verts), default=0.0)
    for ax, (name, i, j) in zip(axes, views):
        top = j == 1
        for v in verts:
            if top and float(v[:, 2].max()) < z0 + 0.15:
                continue
            q = v[:, [i, j]]
            try:
                hull = ConvexHull(q)
                ax.add_patch(Polygon(q[hull.vertices], closed=True, facecolor="tab:blue", alpha=0.12,
                                     edgecolor="tab:blue", linewidth=0.5))
            except Exception:
                continue
        if pts is not None:
            keep = pts[:, 2] >= z0 + 0.15 if top else np.ones(len(pts), bool)
            cc = cols[keep] if isinstance(cols, np.ndarray) else cols
            ax.scatter(pts[keep, i], pts[keep, j], s=0.2, c=cc, alpha=0.5, linewidths=0, rasterized=True)
        for n, tr in enumerate(trials):
            c = "tab:green" if tr.success else ("tab:red" if tr.collisions > 0 else "tab:orange")
            ax.plot(tr.positions[:, i], tr.positions[:, j], color=c, linewidth=1.8)
            ax.plot(tr.start[i], tr.start[j], "o", color="k", markersize=4)
            ax.plot(tr.goal[i], tr.goal[j], "*", color="k", markersize=8)
        ax.set_title(name)
        ax.set_xlabel(f"{labels[i + 1]} (m)")
        ax.set_ylabel(f"{labels[j + 1]} (m)")
        ax.set_aspect("equal", adjustable="datalim")
        ax.autoscale_view()
    fig.suptitle(title or "polycc SITL: green = reached goal, orange = stuck/timeout, red = collision")
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
