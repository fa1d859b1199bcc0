"""Benchmark: the paper's simulation experiment flown by the real app (SITL), and the realization gap.

1. Paper experiment. On the demo arena and on the arena of real captures (plant, ring, tree
   on a floor), for n in {10, 30, 50, 100, 150} polytopes of the PolyMerge family: 100
   random start/goal pairs in free space (sampled once per arena, free for every n: the
   n = 10 cover contains all others), at least --min-distance apart, flown with
   * the single integrator at 100 Hz (dt = 0.01 s, the paper's protocol), and
   * the Crazyflie-like model at the paper's on-board rates 500/250/250/167/125 Hz.
   Reports success rate (within 5 cm), mean path-length ratio (successful flights), minimum
   clearance to the ground-truth ellipsoids (exact distance minus the 0.1 m radius),
   collisions and the largest modelled evalUs.
2. Realization gap. Demo arena, n = 150, Crazyflie-like model: minimum clearance as vmax goes
   0.25 -> 2 m/s, before (the paper's plain CBF filter: app built with POLYCC_APP_BRAKE_ACC = 0)
   and after the app's braking term (speed limit s(psi) with t s + s^2/(2A) = psi, see
   firmware_app/src/polycc_app.h).  The same for the full rigid-body quadrotor at 1 and 2 m/s on
   a subset of the pairs (--quad-pairs).

The main experiment flies the app as shipped (braking term on).

    python bench/bench_sim.py [--quick] [--pairs N] [--jobs J]

Writes bench/results/sim.json.
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
from common import CACHE, SCENES, print_table, write_json  # noqa: E402

NS = (10, 30, 50, 100, 150)
PAPER_RATES = {10: 500, 30: 250, 50: 250, 100: 167, 150: 125}
VOXEL = 0.05
RADIUS = 0.1
VMAX = 1.0
GAP_VMAX = (0.25, 0.5, 1.0, 1.5, 2.0)


@lru_cache(maxsize=2)
def arena(name: str):
    from polycc.demo.arena import make_demo_arena
    from polycc.demo.arenas import capture_arena

    if name == "demo":
        return make_demo_arena(0)
    return capture_arena(SCENES, seed=0)


@lru_cache(maxsize=2)
def family(name: str):
    from polycc.cover.build import build_cover
    from polycc.cover.family import CoverFamily
    from polycc.occupancy.exact import voxelize

    path = CACHE / f"sim_cover_{name}_g{VOXEL}.npz"
    if path.exists():
        return CoverFamily.load(path)
    fam = build_cover(voxelize(arena(name), VOXEL, 1))
    CACHE.mkdir(parents=True, exist_ok=True)
    fam.save(path)
    return fam


def write_header(name: str, n: int) -> Path:
    """polytopes.h + manifest.json of H^n (rewritten every run, so they follow the code generator)."""
    from polycc.codegen.header import write_outputs

    d = CACHE / "sim_headers" / f"{name}_n{n}"
    fam = family(name)
    write_outputs(d, [p.halfplanes for p in fam.materialise(min(n, fam.n_max))], {"kappa": 100.0})
    return d / "polytopes.h"


def pairs_for(header: Path, name: str, n_pairs: int, min_distance: float, seed: int):
    from polycc.sim.sitl import FlightConfig, Simulator, random_pairs, sampling_box

    sim = Simulator(header)  # the most conservative cover (smallest n)
    lo, hi = sampling_box(arena(name))
    return random_pairs(sim.packed, FlightConfig(radius=RADIUS).params(sim.kappa), lo, hi, n_pairs, min_distance, seed)


def fly_batch(job: dict) -> dict:
    """One (arena, n, dynamics, vmax, radius) cell over all pairs; runs in a worker process."""
    from polycc.sim.sitl import FlightConfig, Simulator

    t0 = time.perf_counter()
    sim = Simulator(job["header"], arena(job["arena"]), brake=job.get("brake", True))
    cfg = FlightConfig(rate_hz=job["rate_hz"], vmax=job["vmax"], radius=job["radius"], clearance_radius=RADIUS)
    trials = [sim.fly(s, g, job["dynamics"], cfg) for s, g in job["pairs"]]
    ok = [t for t in trials if t.success]
    return {
        **{k: v for k, v in job.items() if k not in ("pairs", "header")},
        "pairs": len(trials),
        "n_polys": sim.packed.n_polys,
        "n_planes": sim.packed.n_planes,
        "success_rate": len(ok) / len(trials),
        "length_ratio": float(np.mean([t.length_ratio for t in ok])) if ok else float("nan"),
        # clearance and collisions for the physical radius RADIUS, whatever radius the app was given
        "min_clearance_m": float(min(t.min_clearance_m for t in trials)),
        "collisions": int(sum(t.collisions for t in trials)),
        "outcomes": {o: sum(t.outcome == o for t in trials) for o in ("goal", "stuck", "timeout")},
        "max_eval_us": int(max(t.max_eval_us for t in trials)),
        "time_s": time.perf_counter() - t0,
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="10 pairs, n in {10, 150}, demo arena only")
    ap.add_argument("--pairs", type=int, default=100, help="start/goal pairs per cell (default: 100)")
    ap.add_argument("--min-distance", type=float, default=2.0, help="smallest start-goal distance, m (default: 2)")
    ap.add_argument("--quad-pairs", type=int, default=20, help="pairs for the quadrotor rows (default: 20)")
    ap.add_argument("--jobs", type=int, default=2, help="worker processes (default: 2)")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    n_pairs = 10 if args.quick else args.pairs
    ns = (10, 150) if args.quick else NS
    arenas = ["demo"] + ([] if args.quick or not SCENES.is_dir() else ["captures"])
    t_all = time.perf_counter()
    # covers and headers are built here, once, before the workers start
    headers = {(a, n): str(write_header(a, n)) for a in arenas for n in ns}
    pairs = {a: pairs_for(headers[a, ns[0]], a, n_pairs, args.min_distance, args.seed) for a in arenas}
    from polycc.sim.app_ffi import AppSim

    for h in headers.values():  # compile every app variant once, before the workers need them
        AppSim(h)
        AppSim(h, {"POLYCC_APP_BRAKE_ACC": "0.0f"})

    jobs = []
    for a in arenas:
        for n in ns:
            for dyn, rate in (("integrator", 100), ("crazyflie", PAPER_RATES[n])):
                jobs.append({"arena": a, "n": n, "dynamics": dyn, "rate_hz": rate, "vmax": VMAX, "radius": RADIUS,
                             "pairs": pairs[a], "header": headers[a, n]})
    gap_n = ns[-1]
    gap_jobs = []
    for dyn, vs, pp in (("crazyflie", GAP_VMAX, pairs["demo"]), ("quadrotor", (1.0, 2.0),
                                                                 pairs["demo"][: args.quad_pairs])):
        for v in vs:
            for brake in (False, True):
                gap_jobs.append({"arena": "demo", "n": gap_n, "dynamics": dyn, "rate_hz": PAPER_RATES[gap_n], "vmax": v,
                                 "radius": RADIUS, "brake": brake, "pairs": pp, "header": headers["demo", gap_n]})
    res = []
    with ProcessPoolExecutor(max_workers=args.jobs) as ex:
        for r in ex.map(fly_batch, jobs + gap_jobs):
            res.append(r)
            print(f"[{len(res)}/{len(jobs) + len(gap_jobs)}] {r['arena']} {r['dynamics']} n={r['n']} "
                  f"vmax={r['vmax']:g} "
                  f"brake={r.get('brake', True)}: success {r['success_rate']:.2f}, min clearance "
                  f"{r['min_clearance_m']:.4f} m, collisions {r['collisions']} ({r['time_s']:.0f} s)", flush=True)
    main_res, gap_res = res[: len(jobs)], res[len(jobs):]

    rows = [[r["arena"], r["dynamics"], r["n"], r["n_planes"], r["rate_hz"], r["success_rate"], r["length_ratio"],
             r["min_clearance_m"], r["collisions"], r["max_eval_us"], r["time_s"]] for r in main_res]
    print_table(f"SITL, {n_pairs} random pairs >= {args.min_distance:g} m apart, vmax {VMAX:g} m/s, r = {RADIUS:g} m",
                ["arena", "dynamics", "n", "half-planes", "rate Hz", "success", "path ratio", "min clearance m",
                 "collisions", "max evalUs", "time s"], rows)
    grows = [[r["dynamics"], r["pairs"], r["vmax"], "on" if r["brake"] else "off (paper)", r["success_rate"],
              r["length_ratio"], r["min_clearance_m"], r["collisions"]] for r in gap_res]
    print_table(f"Realization gap: demo arena, n = {gap_n}, {PAPER_RATES[gap_n]} Hz, r = {RADIUS:g} m",
                ["dynamics", "pairs", "vmax m/s", "braking term", "success", "path ratio", "min clearance m",
                 "collisions"], grows)
    write_json("sim", {"pairs": n_pairs, "min_distance_m": args.min_distance, "vmax": VMAX, "radius_m": RADIUS,
                       "experiment": main_res, "realization_gap": gap_res,
                       "total_time_s": time.perf_counter() - t_all})
    bad = sum(r["collisions"] for r in main_res)
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
