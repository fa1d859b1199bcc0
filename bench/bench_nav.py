"""Benchmark: flights with and without a plan through the certified free space (polycc.plan), one run.

The paper's protocol (PolyMerge, simulation experiment) on three arenas -- the demo arena, the
arena of real captures and the 1.5M-splat room -- for n in {10, 30, 50, 100, 150} polytopes of the
PolyMerge family: random start/goal pairs in free space (psi >= 0.05 m for the n = 10 cover, which
contains all others), at least --min-distance apart, flown by the real app (SITL) with the single
integrator at 100 Hz, vmax 1 m/s, agent radius 0.1 m:

* baseline: the app's CLF go-to-goal behind the CBF filter, straight to the goal;
* --plan: the waypoints of ``polycc.plan`` (margin 0.05 m, grid 0.05 m), the goal param switched to
  the next waypoint within the margin of the current one.

Per cell: pairs with no certified path (and why), success where a path exists (and of the baseline
on the same pairs and on all pairs), collisions and minimum clearance to the ground-truth ellipsoids,
path length against the shortest free path (estimated as the shortest certified plan found on the
5 cm and 2.5 cm grids; the straight line where it is certified), planning time per pair and the
one-time free-space grid. The paper's hardware success rates (Table II) are printed beside.

    python bench/bench_nav.py [--quick] [--pairs N] [--jobs J] [--arenas demo,captures,room]

Writes bench/results/nav.json. Covers and headers are cached under build/bench-cache (shared with
bench_sim.py); the room's cover family takes about 4 minutes the first time.
"""

from __future__ import annotations

import argparse
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from functools import lru_cache
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from common import CACHE, SCENES, peak_rss_mb, print_table, write_json  # noqa: E402

NS = (10, 30, 50, 100, 150)
PAPER_TABLE2 = {10: 0.7, 30: 0.8, 50: 1.0, 100: 0.8, 150: 0.9}  # hardware success rate, 10 flights each
VOXEL = 0.05
RADIUS = 0.1
VMAX = 1.0
RATE_HZ = 100
MARGIN = 0.05
GRID = 0.05
REF_GRID = 0.025
ARENA_NAMES = {"demo": "demo arena", "captures": "capture arena", "room": "1.5M room"}


@lru_cache(maxsize=1)
def ellipsoids(name: str):
    """Ground truth of an arena (per worker process, cached)."""
    if name == "room":
        from bench_build import arena_ply

        from polycc.scene.load import load_scene

        return load_scene(arena_ply("tiled_room")).ellipsoids
    from bench_sim import arena

    return arena(name)


def family(name: str):
    if name != "room":
        from bench_sim import family as sim_family

        return sim_family(name)
    from polycc.cover.build import build_cover
    from polycc.cover.family import CoverFamily
    from polycc.occupancy.exact import voxelize

    path = CACHE / f"nav_cover_room_g{VOXEL}.npz"
    if path.exists():
        return CoverFamily.load(path)
    fam = build_cover(voxelize(ellipsoids("room"), VOXEL, 1))
    CACHE.mkdir(parents=True, exist_ok=True)
    fam.save(path)
    return fam


def write_header(name: str, n: int, fam) -> Path:
    """polytopes.h, manifest.json and scene.bin of H^n (rewritten every run, like bench_sim)."""
    from polycc.codegen.header import write_outputs

    d = CACHE / "nav_headers" / f"{name}_n{n}"
    write_outputs(d, [p.halfplanes for p in fam.materialise(min(n, fam.n_max))], {"kappa": 100.0})
    return d


def sample_pairs(build_dir: Path, name: str, n_pairs: int, min_distance: float, seed: int):
    from polycc.plan.planner import load_build
    from polycc.sim.sitl import FlightConfig, random_pairs, sampling_box

    packed, kappa, _ = load_build(build_dir)
    lo, hi = sampling_box(ellipsoids(name))
    return random_pairs(packed, FlightConfig(radius=RADIUS).params(kappa), lo, hi, n_pairs, min_distance, seed)


def plan_job(job: dict) -> dict:
    """Plans every pair of one (arena, n) cell: timed on the 5 cm grid (built without the disk
    cache, so its one-time cost is measured), then the 2.5 cm reference."""
    from polycc.plan import NavMap, NoPathError

    t0 = time.perf_counter()
    nav = NavMap.from_build(job["dir"], radius=RADIUS, margin=MARGIN, spacing=GRID, cache=False)
    grid_s = time.perf_counter() - t0
    out = []
    for s, g in job["pairs"]:
        t = time.perf_counter()
        try:
            p = nav.plan(s, g)
            out.append({"waypoints": p.waypoints, "length_m": p.length_m, "straight_m": p.straight_m,
                        "grid_length_m": p.grid_length_m, "expanded": p.expanded, "reason": None,
                        "min_psi_lower_m": float(min(p.psi_lower.min(), p.segment_lower.min()))})
        except NoPathError as exc:
            out.append({"waypoints": None, "reason": exc.reason, "straight_m": float(np.linalg.norm(g - s))})
        out[-1]["time_s"] = time.perf_counter() - t
    ref = NavMap.from_build(job["dir"], radius=RADIUS, margin=MARGIN, spacing=REF_GRID)
    for r, (s, g) in zip(out, job["pairs"]):
        try:
            r["ref_length_m"] = min(ref.plan(s, g).length_m, r.get("length_m", np.inf))
        except NoPathError:
            r["ref_length_m"] = r.get("length_m", np.nan)
    return {"arena": job["arena"], "n": job["n"], "grid_s": grid_s, "grid_shape": list(nav.grid.shape),
            "free_fraction": float(nav.grid.free.mean()), "plans": out, "rss_mb": peak_rss_mb()}


def fly_job(job: dict) -> dict:
    """One (arena, n, plan?) cell of flights."""
    from polycc.sim.sitl import FlightConfig, Simulator

    t0 = time.perf_counter()
    sim = Simulator(Path(job["dir"]) / "polytopes.h", ellipsoids(job["arena"]))
    cfg = FlightConfig(rate_hz=RATE_HZ, vmax=VMAX, radius=RADIUS, switch_tol_m=MARGIN)
    res = []
    for (s, g), w in zip(job["pairs"], job["waypoints"]):
        if job["plan"] and w is None:
            res.append(None)
            continue
        t = sim.fly(s, g, "integrator", cfg, waypoints=w if job["plan"] else None)
        res.append({"success": t.success, "outcome": t.outcome, "path_m": t.path_length_m, "time_s": t.time_s,
                    "min_clearance_m": t.min_clearance_m, "collisions": t.collisions, "max_eval_us": t.max_eval_us})
    return {"arena": job["arena"], "n": job["n"], "plan": job["plan"], "flights": res,
            "n_polys": sim.packed.n_polys, "n_planes": sim.packed.n_planes, "time_s": time.perf_counter() - t0}


def _mean(v):
    v = [x for x in v if x is not None and np.isfinite(x)]
    return float(np.mean(v)) if v else float("nan")


def summarize(plans: dict, flights: dict, arenas, ns) -> list[dict]:
    rows = []
    for a in arenas:
        for n in ns:
            pj, base, plan = plans[a, n], flights[a, n, False], flights[a, n, True]
            P = pj["plans"]
            has = [p["waypoints"] is not None for p in P]
            reasons: dict[str, int] = {}
            for p in P:
                if p["reason"]:
                    reasons[p["reason"]] = reasons.get(p["reason"], 0) + 1
            fl_p = [f for f in plan["flights"] if f is not None]
            fl_b = base["flights"]
            fl_b_has = [f for f, h in zip(fl_b, has) if h]
            ratio_plan = [f["path_m"] / p["ref_length_m"] for f, p in zip(plan["flights"], P)
                          if f is not None and f["success"] and p.get("ref_length_m")]
            ratio_planned = [p["length_m"] / p["ref_length_m"] for p in P if p["waypoints"] is not None]
            ratio_base = [f["path_m"] / p["ref_length_m"] for f, p in zip(fl_b, P)
                          if f["success"] and p["waypoints"] is not None]
            times = [p["time_s"] for p in P]
            rows.append({
                "arena": a, "n": n, "n_polys": plan["n_polys"], "n_planes": plan["n_planes"], "pairs": len(P),
                "with_path": int(sum(has)), "no_path": len(P) - int(sum(has)), "no_path_reasons": reasons,
                "straight_certified": int(sum(1 for p in P if p["waypoints"] is not None and len(p["waypoints"]) == 2)),
                "success_plan": sum(f["success"] for f in fl_p) / max(1, len(fl_p)),
                "success_base_with_path": sum(f["success"] for f in fl_b_has) / max(1, len(fl_b_has)),
                "success_base_all": sum(f["success"] for f in fl_b) / max(1, len(fl_b)),
                "outcomes_plan": {o: sum(f["outcome"] == o for f in fl_p) for o in ("goal", "stuck", "timeout")},
                "outcomes_base": {o: sum(f["outcome"] == o for f in fl_b) for o in ("goal", "stuck", "timeout")},
                "collisions_plan": int(sum(f["collisions"] for f in fl_p)),
                "collisions_base": int(sum(f["collisions"] for f in fl_b)),
                "min_clearance_plan_m": float(min((f["min_clearance_m"] for f in fl_p), default=np.nan)),
                "min_clearance_base_m": float(min(f["min_clearance_m"] for f in fl_b)),
                "flown_over_shortest_mean": _mean(ratio_plan),
                "flown_over_shortest_max": float(max(ratio_plan, default=np.nan)),
                "planned_over_shortest_mean": _mean(ratio_planned),
                "planned_over_shortest_max": float(max(ratio_planned, default=np.nan)),
                "base_flown_over_shortest_mean": _mean(ratio_base),
                "plan_time_mean_s": float(np.mean(times)), "plan_time_max_s": float(np.max(times)),
                "plan_time_p95_s": float(np.percentile(times, 95)),
                "grid_s": pj["grid_s"], "grid_shape": pj["grid_shape"], "free_fraction": pj["free_fraction"],
                "flight_time_plan_mean_s": _mean([f["time_s"] for f in fl_p if f["success"]]),
                "flight_time_base_mean_s": _mean([f["time_s"] for f in fl_b if f["success"]]),
                "paper_table2_success": PAPER_TABLE2.get(n),
            })
    return rows


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="10 pairs, n in {10, 150}, demo arena only")
    ap.add_argument("--pairs", type=int, default=100, help="start/goal pairs per arena (default: 100)")
    ap.add_argument("--min-distance", type=float, default=2.0, help="smallest start-goal distance, m (default: 2)")
    ap.add_argument("--jobs", type=int, default=2, help="worker processes (default: 2)")
    ap.add_argument("--arenas", default="demo,captures,room", help="comma-separated subset of demo,captures,room")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    n_pairs = 10 if args.quick else args.pairs
    ns = (10, 150) if args.quick else NS
    arenas = ["demo"] if args.quick else [a for a in args.arenas.split(",") if a]
    if not SCENES.is_dir():
        arenas = [a for a in arenas if a == "demo"]
    t_all = time.perf_counter()
    dirs, pairs = {}, {}
    for a in arenas:
        fam = family(a)
        for n in ns:
            dirs[a, n] = str(write_header(a, n, fam))
        pairs[a] = sample_pairs(Path(dirs[a, ns[0]]), a, n_pairs, args.min_distance, args.seed)
        print(f"{ARENA_NAMES[a]}: {len(pairs[a])} pairs, covers n = {', '.join(map(str, ns))}", flush=True)
    from polycc.plan.native import load as load_native
    from polycc.sim.app_ffi import AppSim

    load_native()
    for d in dirs.values():  # compile every app variant once, before the workers need them
        AppSim(Path(d) / "polytopes.h")

    cells = [(a, n) for a in arenas for n in ns]
    plans, flights = {}, {}
    with ProcessPoolExecutor(max_workers=args.jobs) as ex:
        for r in ex.map(plan_job, [{"arena": a, "n": n, "dir": dirs[a, n], "pairs": pairs[a]} for a, n in cells]):
            plans[r["arena"], r["n"]] = r
            npath = sum(p["waypoints"] is not None for p in r["plans"])
            print(f"plan {r['arena']} n={r['n']}: {npath}/{len(r['plans'])} with a path, grid {r['grid_s']:.1f} s, "
                  f"{np.mean([p['time_s'] for p in r['plans']]) * 1e3:.0f} ms per pair", flush=True)
        jobs = [{"arena": a, "n": n, "dir": dirs[a, n], "pairs": pairs[a], "plan": pl,
                 "waypoints": [p["waypoints"] for p in plans[a, n]["plans"]]} for a, n in cells for pl in (False, True)]
        for r in ex.map(fly_job, jobs):
            flights[r["arena"], r["n"], r["plan"]] = r
            write_json("nav_partial", {"pairs": n_pairs, "flights": [  # progress, in case the run is cut short
                {k: v for k, v in f.items()} for f in flights.values()]})
            ok = [f for f in r["flights"] if f is not None]
            print(f"fly {r['arena']} n={r['n']} plan={r['plan']}: success {sum(f['success'] for f in ok)}/{len(ok)}, "
                  f"collisions {sum(f['collisions'] for f in ok)} ({r['time_s']:.0f} s)", flush=True)
    rows = summarize(plans, flights, arenas, ns)

    print_table(f"Navigation, paper's protocol: {n_pairs} random pairs >= {args.min_distance:g} m apart, integrator "
                f"{RATE_HZ} Hz, vmax {VMAX:g} m/s, r = {RADIUS:g} m; plan: margin {MARGIN:g} m, grid {GRID:g} m",
                ["arena", "n", "with path", "no path", "success no plan (all / with path)", "success --plan",
                 "paper Table II (hw)", "collisions no plan / plan", "min clear m no plan / plan",
                 "flown/shortest mean, max", "planned/shortest max"],
                [[ARENA_NAMES[r["arena"]], r["n"], r["with_path"],
                  f"{r['no_path']}" + (f" ({', '.join(f'{k} {v}' for k, v in r['no_path_reasons'].items())})"
                                       if r["no_path"] else ""),
                  f"{r['success_base_all']:.2f} / {r['success_base_with_path']:.2f}", f"{r['success_plan']:.2f}",
                  f"{r['paper_table2_success']:.1f}", f"{r['collisions_base']} / {r['collisions_plan']}",
                  f"{r['min_clearance_base_m']:.3f} / {r['min_clearance_plan_m']:.3f}",
                  f"{r['flown_over_shortest_mean']:.3f}, {r['flown_over_shortest_max']:.3f}",
                  f"{r['planned_over_shortest_max']:.3f}"] for r in rows])
    print_table("Planning cost (one worker per cell, 2 cells at a time on the 2 cores)",
                ["arena", "n", "polytopes", "half-planes", "grid cells", "free %", "grid build s",
                 "plan per pair mean ms", "p95 ms", "max ms", "straight certified", "flight time s no plan / plan"],
                [[ARENA_NAMES[r["arena"]], r["n"], r["n_polys"], r["n_planes"],
                  "x".join(map(str, r["grid_shape"])), round(100 * r["free_fraction"], 1), round(r["grid_s"], 2),
                  round(r["plan_time_mean_s"] * 1e3, 1), round(r["plan_time_p95_s"] * 1e3, 1),
                  round(r["plan_time_max_s"] * 1e3, 1), r["straight_certified"],
                  f"{r['flight_time_base_mean_s']:.1f} / {r['flight_time_plan_mean_s']:.1f}"] for r in rows])
    write_json("nav", {"pairs": n_pairs, "min_distance_m": args.min_distance, "vmax": VMAX, "radius_m": RADIUS,
                       "rate_hz": RATE_HZ, "margin_m": MARGIN, "grid_m": GRID, "reference_grid_m": REF_GRID,
                       "rows": rows, "peak_rss_mb": max(p["rss_mb"] for p in plans.values()),
                       "total_time_s": time.perf_counter() - t_all})
    return 1 if any(r["collisions_plan"] for r in rows) else 0


if __name__ == "__main__":
    sys.exit(main())
