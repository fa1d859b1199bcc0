"""Paths through the certified free space of a build: grid A*, certified shortcuts, clearances.

World frame, metres. The free space is what the drone's barrier sees: the certified lower bound
``LB <= psi`` of :mod:`polycc.plan.certified` for the stored polytopes and the agent radius. A plan
is a polyline ``start, w_1, ..., goal`` on which ``LB >= margin`` (``min(margin, LB(start) - 5 mm)``
on the first segment and ``min(margin, LB(goal) - 5 mm)`` on the last: LB at an endpoint cannot be
certified on a segment leaving it), so the ``margin``-tube around every interior segment has
``psi >= 0``: a vehicle that switches to the next waypoint within ``margin`` of the current one and
flies straight stays where the filter lets it fly.

Steps (:meth:`NavMap.plan`): the straight segment if it is certified; otherwise A* on the
26-connected grid of free cells (:mod:`polycc.plan.grid`, :mod:`polycc.plan.native`) between the
cells reachable from start and goal by certified segments, then greedy shortcutting: from each
waypoint the farthest later grid point whose segment is certified (by the grid field, else by
bisection on LB). No path raises :class:`NoPathError` whose ``reason`` is one of :data:`REASONS`.
"""

from __future__ import annotations

import hashlib
import json
import math
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from polycc.errors import PolyccError
from polycc.onboard.barrier import Params
from polycc.onboard.barrier import barrier as ref_barrier
from polycc.onboard.layout import PackedScene, scene_from_bytes, stored_vertices
from polycc.plan.certified import BarrierBound, certify_segment
from polycc.plan.grid import Grid, field_reach, lower_field

PLAN_FORMAT = "polycc-plan/1"
DEFAULT_RADIUS = 0.1  # m, the app's polycc.radius default in `polycc sim`
DEFAULT_MARGIN = 0.05  # m
DEFAULT_SPACING = 0.05  # m
REASONS = {
    "outside_map": "outside the map",
    "start_in_obstacle": "the start is inside an obstacle (or within the agent radius of one)",
    "goal_in_obstacle": "the goal is inside an obstacle (or within the agent radius of one)",
    "start_blocked": "no certified segment leaves the start",
    "goal_blocked": "no certified segment reaches the goal",
    "start_enclosed": "the start is enclosed",
    "goal_enclosed": "the goal is enclosed",
}


class NoPathError(PolyccError):
    """No certified path; ``reason`` is a key of :data:`REASONS`."""

    def __init__(self, reason: str, message: str):
        super().__init__(message)
        self.reason = reason


@dataclass
class Plan:
    """A certified path. ``waypoints[0]`` is the start and ``waypoints[-1]`` the goal (m)."""

    start: np.ndarray
    goal: np.ndarray
    waypoints: np.ndarray  # (k, 3) m
    psi_lower: np.ndarray  # (k,) certified lower bound of psi at each waypoint, m
    psi: np.ndarray | None  # (k,) psi of the float32 reference kernel at each waypoint, m (NavMap.annotate)
    segment_lower: np.ndarray  # (k-1,) certified lower bound of psi along each segment, m
    segment_psi_min: np.ndarray | None  # (k-1,) smallest reference psi sampled every 1 cm per segment (annotate)
    length_m: float
    straight_m: float
    grid_length_m: float  # A* path before shortcutting (= length_m when the straight line is certified)
    expanded: int  # grid cells A* expanded
    time_s: float
    radius: float
    margin: float
    kappa: float
    spacing: float
    meta: dict = field(default_factory=dict)
    profile: tuple[np.ndarray, np.ndarray] | None = None  # (arc length, reference psi) m, from NavMap.annotate

    @property
    def length_ratio(self) -> float:
        return self.length_m / self.straight_m if self.straight_m > 0 else 1.0

    def to_json(self) -> dict:
        return {
            "format": PLAN_FORMAT, "units": "m", "frame": "world (scene frame after the transform)",
            "start": self.start.tolist(), "goal": self.goal.tolist(),
            "waypoints": self.waypoints.tolist(),
            "switch_tolerance_m": self.margin,
            "radius_m": self.radius, "margin_m": self.margin, "kappa": self.kappa, "grid_m": self.spacing,
            "clearance": {"waypoint_psi_lower_m": self.psi_lower.tolist(),
                          "waypoint_psi_m": None if self.psi is None else self.psi.tolist(),
                          "segment_psi_lower_m": self.segment_lower.tolist(),
                          "segment_psi_min_sampled_m": None if self.segment_psi_min is None
                          else self.segment_psi_min.tolist()},
            "length_m": self.length_m, "straight_m": self.straight_m, "grid_length_m": self.grid_length_m,
            "expanded_cells": self.expanded, "time_s": self.time_s, **self.meta,
        }


def read_plan(path: str | Path) -> dict:
    """A plan JSON (``polycc plan --json``) checked for format; returns the dict."""
    try:
        d = json.loads(Path(path).read_text())
    except (OSError, ValueError) as exc:
        raise PolyccError(f"{path}: cannot read the plan ({exc})") from None
    if d.get("format") != PLAN_FORMAT or "waypoints" not in d:
        raise PolyccError(f"{path}: not a {PLAN_FORMAT} file; write one with `polycc plan DIR ... --json FILE`")
    return d


def load_build(build_dir: str | Path) -> tuple[PackedScene, float, dict]:
    """(packed scene, kappa, manifest) of a build folder (scene.bin + manifest.json)."""
    d = Path(build_dir)
    man_path, bin_path = d / "manifest.json", d / "scene.bin"
    if not man_path.is_file() or not bin_path.is_file():
        raise PolyccError(f"{d}: needs manifest.json and scene.bin from `polycc build`; run "
                          f"`polycc build SCENE -o {d}`")
    try:
        man = json.loads(man_path.read_text())
    except ValueError as exc:
        raise PolyccError(f"{man_path}: not valid JSON ({exc}); rebuild the folder") from None
    return scene_from_bytes(bin_path.read_bytes()), float(man["kappa"]), man


def cover_bounds(packed: PackedScene) -> tuple[np.ndarray, np.ndarray]:
    """Bounding box (m) of the stored polytopes (vertices; centre +- R where qhull cannot)."""
    if packed.n_polys == 0:
        raise PolyccError("the scene stores no polytope, so it has no extent; pass the map bounds explicitly")
    lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
    for k, v in enumerate(stored_vertices(packed)):
        if v is None:
            p = packed.polys[k]
            c = np.array([p["cx"], p["cy"], p["cz"]], np.float64)
            v = np.stack([c - float(p["r_out"]), c + float(p["r_out"])])
        lo, hi = np.minimum(lo, v.min(0)), np.maximum(hi, v.max(0))
    return lo, hi


def _fmt(p) -> str:
    return "(" + ", ".join(f"{v:.2f}" for v in np.asarray(p, float)) + ")"


class FreeSpace:
    """What the drone's barrier certifies about one stored scene at one agent radius, inside the
    map ``bounds`` ((3,), (3,)) m (default: the box of the stored polytopes; outside it nothing was
    captured, so nothing is planned or flown there)."""

    def __init__(self, packed: PackedScene, kappa: float, radius: float = DEFAULT_RADIUS, bounds=None,
                 cache: bool = True):
        if not radius >= 0:
            raise PolyccError(f"agent radius {radius:g} m: must be >= 0")
        self.packed, self.kappa, self.radius = packed, float(kappa), float(radius)
        self.bound = BarrierBound(packed, kappa, radius)
        self.params = Params(kappa=kappa, radius=radius)
        if bounds is None:
            lo, hi = self._cover_bounds(cache)
        else:
            lo, hi = (np.asarray(b, np.float64).reshape(3) for b in bounds)
            if not np.all(hi > lo):
                raise PolyccError(f"map bounds {_fmt(lo)} .. {_fmt(hi)} are empty; give x0,y0,z0,x1,y1,z1 with x0 < x1")
        self.lo, self.hi = lo, hi

    @classmethod
    def from_build(cls, build_dir: str | Path, **kw):
        packed, kappa, _ = load_build(build_dir)
        return cls(packed, kappa, **kw)

    def _cover_bounds(self, cache: bool) -> tuple[np.ndarray, np.ndarray]:
        """:func:`cover_bounds`, cached by the scene bytes (qhull on every polytope takes ~1 s)."""
        path = None
        if cache:
            from polycc import resources
            key = hashlib.sha256(self.packed.to_bytes()).hexdigest()[:20]
            path = resources.cache_dir("plan") / f"bounds_{key}.json"
            if path.is_file():
                try:
                    d = json.loads(path.read_text())
                    return np.asarray(d["lo"], np.float64), np.asarray(d["hi"], np.float64)
                except (ValueError, KeyError):
                    pass
        lo, hi = cover_bounds(self.packed)
        if path is not None:
            tmp = path.with_suffix(f".{time.time_ns()}.tmp")
            tmp.write_text(json.dumps({"lo": lo.tolist(), "hi": hi.tolist()}))
            tmp.replace(path)
        return lo, hi

    def inside(self, p) -> bool:
        p = np.asarray(p, np.float64)
        return bool(np.all(p >= self.lo) and np.all(p <= self.hi))

    def psi(self, p) -> np.ndarray:
        """psi of the float32 reference kernel (what the drone computes) at points p (…, 3)."""
        psi, _, flags = ref_barrier(self.packed, self.params, np.asarray(p, np.float32).reshape(-1, 3))
        return np.where(flags == 0, psi.astype(np.float64), -np.inf)

    def endpoint_problem(self, p, which: str) -> NoPathError | None:
        """The reason a flight cannot start/end at p (``which`` = "start"/"goal"), or None."""
        p = np.asarray(p, np.float64)
        if not self.inside(p):
            return NoPathError("outside_map", f"the {which} {_fmt(p)} is outside the map {_fmt(self.lo)} .. "
                                              f"{_fmt(self.hi)} m (the box of the stored polytopes, or --bounds); "
                                              "nothing was captured there: pick a point inside or pass --bounds")
        lb = float(self.bound.lower(p)[0])
        if lb >= 0:
            return None
        psi = float(self.psi(p)[0])
        if psi < 0:
            return NoPathError(f"{which}_in_obstacle",
                               f"the {which} {_fmt(p)} is inside an obstacle or within the agent radius "
                               f"{self.radius:g} m of one: the barrier there is psi = {psi:.3f} m, so the filter would "
                               f"never let the drone {'leave' if which == 'start' else 'arrive'}; move it "
                               f"{-psi:.2f} m or more away from the obstacle")
        return NoPathError(f"{which}_in_obstacle",
                           f"the {which} {_fmt(p)} is too close to an obstacle to certify: psi = {psi:.3f} m but its "
                           f"certified lower bound is {lb:.3f} m (the soft-max bias near edges); move it "
                           f"{-lb + 0.01:.2f} m away")

    def preflight(self, start, goal) -> None:
        """Raise :class:`NoPathError` if start or goal is outside the map or not certified free."""
        for p, which in ((start, "start"), (goal, "goal")):
            prob = self.endpoint_problem(p, which)
            if prob is not None:
                raise prob


class NavMap(FreeSpace):
    """The certified free space of one stored scene at one agent radius, and the planner on it.

    The grid (``spacing`` m) covers the map box (rounded up to whole cells); its field is cached
    in the build cache (``plan/``), keyed by the scene bytes and every setting.
    """

    def __init__(self, packed: PackedScene, kappa: float, radius: float = DEFAULT_RADIUS,
                 margin: float = DEFAULT_MARGIN, spacing: float = DEFAULT_SPACING, bounds=None,
                 cache: bool = True, progress=None):
        if not (margin >= 0 and spacing > 0):
            raise PolyccError(f"margin {margin:g} m must be >= 0 and the grid spacing {spacing:g} m > 0")
        t0 = time.perf_counter()
        super().__init__(packed, kappa, radius, bounds, cache)
        self.margin, self.spacing = float(margin), float(spacing)
        lo, hi = self.lo, self.hi
        shape = tuple(int(v) for v in np.maximum(np.ceil((hi - lo) / spacing - 1e-9), 1))
        cells = int(np.prod(shape))
        if cells > 60_000_000:
            raise PolyccError(f"the map {_fmt(lo)} .. {_fmt(hi)} at {spacing:g} m is {cells:,} cells; use a coarser "
                              "grid or smaller bounds")
        grid = Grid(lo, spacing, shape, np.zeros(0, np.float32), margin, 0.0)
        e = field_reach(self.bound, grid.need)
        key = hashlib.sha256(packed.to_bytes() + json.dumps(
            [self.kappa, self.radius, margin, spacing, lo.tolist(), shape, e, 1]).encode()).hexdigest()[:20]
        path = None
        if cache:
            from polycc import resources
            path = resources.cache_dir("plan") / f"field_{key}.npy"
        if path is not None and path.is_file():
            grid.field = np.load(path)
            self.cached = True
        else:
            if progress:
                progress("field", 0, 1)
            grid.field = lower_field(self.bound, lo, spacing, shape, e)
            self.cached = False
            if path is not None:
                tmp = path.with_suffix(f".{time.time_ns()}.tmp.npy")
                np.save(tmp, grid.field)
                tmp.replace(path)
        grid.cap = e - self.bound.radius
        self.grid = grid
        free = grid.free
        for a in range(3):  # cells whose centre is outside the map are not planned through
            c = lo[a] + (np.arange(shape[a]) + 0.5) * spacing
            sl = [None, None, None]
            sl[a] = slice(None)
            free &= (c <= hi[a])[tuple(sl)]
        self._free = np.ascontiguousarray(free, np.uint8)
        self.build_s = time.perf_counter() - t0

    # ------------------------------------------------------------------ planning
    def _seg_ok(self, a, b, req: float) -> tuple[bool, float]:
        g = self.grid.segment_lower(a, b)
        if g >= req:
            return True, g
        chk = certify_segment(self.bound, a, b, req)
        return chk.ok, chk.lower

    def _connect(self, p, req: float) -> tuple[np.ndarray, np.ndarray]:
        """Free cells reachable from p by a certified segment (LB >= req): (flat cells, lengths m)."""
        c0 = self.grid.cell_of(p)
        for rad in (1, 2, 4, 8):
            rng = np.arange(-rad, rad + 1)
            ijk = c0 + np.stack(np.meshgrid(rng, rng, rng, indexing="ij"), axis=-1).reshape(-1, 3)
            ijk = ijk[np.all((ijk >= 0) & (ijk < np.asarray(self.grid.shape)), axis=1)]
            ijk = ijk[self._free[ijk[:, 0], ijk[:, 1], ijk[:, 2]] != 0]
            if len(ijk) == 0:
                continue
            cen = self.grid.centres(ijk)
            dist = np.linalg.norm(cen - p, axis=1)
            order = np.argsort(dist, kind="stable")[:64]
            ok = [k for k in order if self._seg_ok(p, cen[k], req)[0]]
            if ok:
                return self.grid.flat(ijk[ok]), dist[ok]
        return np.zeros(0, np.int64), np.zeros(0)

    def _no_path(self, src: np.ndarray, dst: np.ndarray) -> NoPathError:
        from scipy import ndimage

        lab, _ = ndimage.label(self._free, structure=np.ones((3, 3, 3), bool))
        flat = lab.reshape(-1)
        cell = self.spacing**3
        counts = np.bincount(flat)
        vs = float(counts[np.unique(flat[src])].sum()) * cell
        vg = float(counts[np.unique(flat[dst])].sum()) * cell
        side = "goal" if vg <= vs else "start"
        small, big = (vg, vs) if side == "goal" else (vs, vg)
        other = "start" if side == "goal" else "goal"
        return NoPathError(f"{side}_enclosed",
                           f"no certified path: the {side} is enclosed -- its free region ({small:.2f} m^3) does not "
                           f"connect to the {other}'s ({big:.2f} m^3) with clearance radius {self.radius:g} m + margin "
                           f"{self.margin:g} m; if the obstacles really close it in, no flight reaches it, else lower "
                           "--margin or rebuild with more polytopes (larger n) so the cover hugs the obstacles")

    def plan(self, start, goal) -> Plan:
        """A certified path from start to goal (m); :class:`NoPathError` names why there is none."""
        t0 = time.perf_counter()
        start, goal = np.asarray(start, np.float64).reshape(3), np.asarray(goal, np.float64).reshape(3)
        self.preflight(start, goal)
        lb_s, lb_g = (float(v) for v in self.bound.lower(np.stack([start, goal])))
        # at an endpoint LB itself cannot be certified on a segment leaving it (LB is 1-Lipschitz):
        # ask for a little less there (at most 5 mm, at most half of it)
        req_s, req_g = (min(self.margin, lb - min(0.005, 0.5 * lb)) for lb in (lb_s, lb_g))
        straight = float(np.linalg.norm(goal - start))
        ok, _ = self._seg_ok(start, goal, min(req_s, req_g))
        expanded, grid_len = 0, straight
        if ok:
            pts = np.stack([start, goal])
        else:
            src, sc = self._connect(start, req_s)
            if len(src) == 0:
                raise NoPathError("start_blocked", f"no certified segment leaves the start {_fmt(start)} for free "
                                                   f"space within {8 * self.spacing:.2f} m (certified psi there "
                                                   f"{lb_s:.3f} m); move the start into the open or lower --margin")
            dst, dc = self._connect(goal, req_g)
            if len(dst) == 0:
                raise NoPathError("goal_blocked", f"no certified segment reaches the goal {_fmt(goal)} from free "
                                                  f"space within {8 * self.spacing:.2f} m (certified psi there "
                                                  f"{lb_g:.3f} m); move the goal into the open or lower --margin")
            from polycc.plan.native import astar

            gcell = self.grid.cell_of(goal)
            tij = self.grid.unflat(dst)
            oct_t = _octile(tij - gcell) * self.spacing
            shift = float(np.max(oct_t - dc))
            cost, cells, expanded = astar(self._free, self.spacing, src, sc, dst, dc, gcell, shift)
            if not np.isfinite(cost):
                raise self._no_path(src, dst)
            grid_len = cost
            pts = np.concatenate([start[None], self.grid.centres(self.grid.unflat(cells)), goal[None]])
        way, seg_lower = self._shortcut(pts, req_s, req_g)
        return self._finish(start, goal, way, seg_lower, straight, grid_len, expanded, time.perf_counter() - t0)

    def _shortcut(self, pts: np.ndarray, req_s: float, req_g: float) -> tuple[np.ndarray, list[float]]:
        """Greedy: from each kept point, the farthest later point whose segment is certified
        (galloping then bisection over the index; adjacent points are always certified)."""
        n = len(pts) - 1

        def req(i, j):
            r = self.margin
            if i == 0:
                r = min(r, req_s)
            if j == n:
                r = min(r, req_g)
            return r

        keep, lows = [0], []
        i = 0
        while i < n:
            good, good_low = i + 1, None
            step = 1
            bad = None
            while True:
                j = min(n, good + step)
                ok, low = self._seg_ok(pts[i], pts[j], req(i, j))
                if ok:
                    good, good_low = j, low
                    if j == n:
                        break
                    step *= 2
                else:
                    bad = j
                    break
            while bad is not None and bad - good > 1:
                mid = (good + bad) // 2
                ok, low = self._seg_ok(pts[i], pts[mid], req(i, mid))
                if ok:
                    good, good_low = mid, low
                else:
                    bad = mid
            if good_low is None:  # adjacent points: certified by construction; get its bound
                ok, good_low = self._seg_ok(pts[i], pts[good], req(i, good))
                if not ok:
                    raise PolyccError(f"internal: grid step {i}->{good} is not certified ({good_low:.4f} m); "
                                      "please report this")
            keep.append(good)
            lows.append(good_low)
            i = good
        return pts[keep], lows

    def _finish(self, start, goal, way, seg_lower, straight, grid_len, expanded, dt) -> Plan:
        length = float(np.sum(np.linalg.norm(np.diff(way, axis=0), axis=1)))
        return Plan(start, goal, way, self.bound.lower(way), None, np.asarray(seg_lower, float), None, length,
                    straight, float(grid_len), int(expanded), dt, self.radius, self.margin, self.kappa, self.spacing,
                    meta={"map_lo_m": self.lo.tolist(), "map_hi_m": self.hi.tolist()})

    def annotate(self, plan: Plan, step: float = 0.01, tight: float = 0.005) -> Plan:
        """Fill ``plan.psi`` (reference psi at the waypoints), ``plan.segment_psi_min`` (smallest
        reference psi sampled every ``step`` m along each segment) and ``plan.profile`` (arc length,
        psi) m: what the drone will compute (one batched call of the float32 reference, about
        0.5 s per thousand polytopes); and tighten ``plan.segment_lower`` to within ``tight`` m of
        each segment's smallest LB (the planner only certifies ``>= margin``)."""
        way = plan.waypoints
        for i, (a, b) in enumerate(zip(way[:-1], way[1:])):
            # far polytopes enter through a bound that caps LB near e - r: take e large enough to report
            chk = certify_segment(self.bound, a, b, min(0.0, float(plan.segment_lower[i])), tight=tight, e=1.0)
            if chk.ok:
                plan.segment_lower[i] = max(float(plan.segment_lower[i]), chk.lower)
        pieces, arcs, s0 = [], [], 0.0
        for a, b in zip(way[:-1], way[1:]):
            L = float(np.linalg.norm(b - a))
            t = np.linspace(0.0, 1.0, max(2, int(math.ceil(L / step)) + 1))
            pieces.append(a + t[:, None] * (b - a))
            arcs.append(s0 + t * L)
            s0 += L
        if not pieces:
            pieces, arcs = [way], [np.zeros(len(way))]
        psi = self.psi(np.concatenate(pieces))
        ends = np.r_[0, np.cumsum([len(p) for p in pieces])]
        plan.segment_psi_min = np.array([psi[ends[i]:ends[i + 1]].min() for i in range(len(way) - 1)])
        plan.psi = np.r_[psi[ends[:-1]], psi[-1]][: len(way)]
        plan.profile = (np.concatenate(arcs), psi)
        return plan


def _octile(d: np.ndarray) -> np.ndarray:
    a = np.sort(np.abs(np.asarray(d, np.float64)), axis=-1)[..., ::-1]
    return math.sqrt(3.0) * a[..., 2] + math.sqrt(2.0) * (a[..., 1] - a[..., 2]) + (a[..., 0] - a[..., 1])


def plan_path(build, start, goal, radius: float = DEFAULT_RADIUS, margin: float = DEFAULT_MARGIN,
              spacing: float = DEFAULT_SPACING, bounds=None, kappa: float | None = None) -> Plan:
    """A certified path from ``start`` to ``goal`` (m) through a build's free space.

    Parameters
    ----------
    build : a build folder (``polytopes.h``/``scene.bin``/``manifest.json``) or a :class:`PackedScene`
        (then ``kappa`` is required).
    start, goal : (3,) m, world frame.
    radius : agent radius the drone's app uses (``polycc.radius``), m.
    margin : certified clearance kept beyond the radius along the path, m; also the waypoint switch
        tolerance that keeps a follower inside the certified tube.
    spacing : planning grid, m.  bounds : ((3,), (3,)) map box, m (default: the stored polytopes' box).

    Returns
    -------
    Plan: waypoints (k, 3) with ``waypoints[0] = start``, ``waypoints[-1] = goal``, their clearances,
    length. Raises :class:`NoPathError` (``.reason`` in :data:`REASONS`) when there is no path.
    """
    if isinstance(build, PackedScene):
        if kappa is None:
            raise PolyccError("plan_path on a PackedScene needs kappa (the header's POLYCC_SCENE_KAPPA)")
        nav = NavMap(build, kappa, radius, margin, spacing, bounds)
    else:
        nav = NavMap.from_build(build, radius=radius, margin=margin, spacing=spacing, bounds=bounds)
    return nav.plan(start, goal)
