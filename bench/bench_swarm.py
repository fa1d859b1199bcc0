"""Swarm benchmark (issue 19, seed 003): decentralized coverage with buffered Voronoi cells in the
on-board barrier, on the fast simulator (N independent app instances, the same C as on board).

Matrix: n in {2, 4, 8, 16} drones on the demo arena, the capture arena and the 1.5M room (the
covers of bench_sim / bench_nav, H^150), ``--trials`` trials each with random starts (free cells
>= 0.6 m apart) and a random 3-peak ToI (sigma 0.4 m, peaks >= 1 m apart); in every trial the three
controllers fly the SAME starts and targets, side by side in one run:

  guided     CVT on the geodesic ToI density (navigation function of the certified free grid, Eq. 8),
             cell restricted to reachable free cells, approached along the grid path (ours)
  lloyd      plain Lloyd with BVC (Eq. 3, Euclidean density, centroid flown straight): no guided map
  repulsive  attraction to the nearest undetected peak + inverse-square neighbour repulsion

Every drone runs the same on-board filter (obstacles + neighbour terms), integrator dynamics, vmax
0.5 m/s, r = 0.1 m, reports at 20 Hz with 10 ms latency, controllers at 5 Hz, --t-max s per trial.
Measures per (arena, n, controller): drone-drone collisions (centres < 2 r, every ms), drone-obstacle
collisions (exact clearance to the splat ellipsoids), coverage ratio (peaks within 0.5 m of a drone),
task time (time of the last detection; trials that miss a peak count as --t-max and are reported),
min inter-drone distance, wall time per drone-tick.  On-board cost: ``--arm`` runs the ARM build of
polycc_swarm_step in the Cortex-M4 cycle model of bench_kernel (16 neighbours, every term in the
soft-min) against the POLYCC_APP_SWARM_WORST_CYCLES bound the app adds to the scene's worst case.

    python bench/bench_swarm.py [--quick] [--arenas demo,captures,room] [--ns 2,4,8,16] [--trials 10]
                                [--t-max 60] [--arm]

--quick: demo arena, n in {2, 4}, 2 trials, t-max 40 s.  Writes bench/results/bench_swarm.json.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from common import peak_rss_mb, print_table, write_json  # noqa: E402

CONTROLLERS = ("guided", "lloyd", "repulsive")
ARENA_NAMES = {"demo": "demo arena", "captures": "capture arena", "room": "1.5M room"}
N_POLYS = 150
GRID = 0.15
RADIUS = 0.1
RATE_HZ = 100  # the apps' loop rate (as bench_nav): 10 ms periods keep the 16-drone rows affordable


def arena_build(name: str):
    """(build dir with polytopes.h/scene.bin/manifest.json, ellipsoids) of an arena's H^150."""
    import bench_nav

    fam = bench_nav.family(name)
    return bench_nav.write_header(name, N_POLYS, fam), bench_nav.ellipsoids(name)


def run_cell(name: str, build: Path, ellipsoids, n: int, trials: int, t_max: float, seed: int) -> list[dict]:
    from polycc.plan.planner import NavMap
    from polycc.sim.clearance import Clearance
    from polycc.swarm.coverage import CoverageMap
    from polycc.swarm.scenario import random_targets, spread_points
    from polycc.swarm.sim import SwarmConfig, run_swarm

    nav = NavMap.from_build(build, radius=RADIUS, margin=0.05, spacing=GRID)
    centres = nav.grid.centres(np.argwhere(nav._free.astype(bool)))
    clearance = Clearance(ellipsoids)
    rows = []
    for trial in range(trials):
        rng = np.random.default_rng([seed, n, trial, sum(map(ord, name))])
        targets = random_targets(centres, 3, rng)
        starts = spread_points(centres, n, 0.6, rng)
        cmap = CoverageMap(nav, targets)
        for kind in CONTROLLERS:
            t0 = time.perf_counter()
            r = run_swarm(build / "polytopes.h", cmap, starts, targets,
                          SwarmConfig(controller=kind, t_max_s=t_max, radius=RADIUS, rate_hz=RATE_HZ), clearance)
            rows.append({"arena": name, "n": n, "trial": trial, "controller": kind,
                         "drone_drone": r.pair_collisions, "drone_obstacle": sum(1 for c in r.obstacle_collisions
                                                                                 if c > 0),
                         "coverage": r.coverage, "task_time_s": None if math.isnan(r.task_time_s) else r.task_time_s,
                         "min_inter_drone_m": r.min_pair_m if math.isfinite(r.min_pair_m) else None,
                         "min_clearance_m": float(min(r.min_clearance_m)), "sim_s": r.time_s,
                         "wall_s": time.perf_counter() - t0, "us_per_drone_tick": r.step_us,
                         "hold_ticks": int(sum(v for s in r.statuses for k, v in s.items() if k != 1))})
            print(f"  {name} n={n} trial {trial} {kind}: coverage {r.coverage:.2f}, task "
                  f"{r.task_time_s:.1f} s, collisions {r.pair_collisions}+{rows[-1]['drone_obstacle']}, "
                  f"min d {r.min_pair_m:.3f} m, wall {rows[-1]['wall_s']:.0f} s", flush=True)
    return rows


def summarize(rows: list[dict], t_max: float) -> list[list]:
    out = []
    keys = sorted({(r["arena"], r["n"]) for r in rows}, key=lambda k: (list(ARENA_NAMES).index(k[0]), k[1]))
    for a, n in keys:
        for kind in CONTROLLERS:
            rs = [r for r in rows if r["arena"] == a and r["n"] == n and r["controller"] == kind]
            if not rs:
                continue
            tt = [r["task_time_s"] if r["task_time_s"] is not None else t_max for r in rs]
            md = [r["min_inter_drone_m"] for r in rs if r["min_inter_drone_m"] is not None]
            out.append([ARENA_NAMES[a], n, kind, len(rs), sum(r["drone_drone"] for r in rs),
                        sum(r["drone_obstacle"] for r in rs), float(np.mean([r["coverage"] for r in rs])),
                        float(np.min([r["coverage"] for r in rs])), sum(r["coverage"] == 1.0 for r in rs),
                        float(np.median(tt)), float(np.mean(tt)), min(md) if md else float("nan"),
                        float(min(r["min_clearance_m"] for r in rs)), float(np.mean([r["us_per_drone_tick"]
                                                                                      for r in rs]))])
    return out


def call_swarm(emu, table: bytes, v: float, x, goal):
    """polycc_swarm_step(scene, params, sw, v, x, goal, out) in the model (AAPCS-VFP: v in s0)."""
    import struct

    from polycc.sim.cortex_m4_model import IO_BASE, STOP
    from polycc.sim.kernel_ffi import OUT_DTYPE

    U, uc = emu.U, emu.uc
    # the neighbour table after the spatial index's header (Emulator.load_scene puts it at IO_BASE + 0x200)
    px, pg, po, psw = IO_BASE + 0x80, IO_BASE + 0x90, IO_BASE + 0xA0, IO_BASE + 0x1000
    uc.mem_write(px, np.asarray(x, np.float32).tobytes())
    uc.mem_write(pg, np.asarray(goal, np.float32).tobytes())
    uc.mem_write(psw, table)
    sp = IO_BASE - 0x100
    uc.mem_write(sp, struct.pack("<II", pg, po))  # 5th and 6th integer arguments on the stack
    uc.reg_write(U.UC_ARM_REG_SP, sp)
    for reg, val in zip((U.UC_ARM_REG_R0, U.UC_ARM_REG_R1, U.UC_ARM_REG_R2, U.UC_ARM_REG_R3),
                        (IO_BASE, IO_BASE + 0x40, psw, px)):
        uc.reg_write(reg, val)
    uc.reg_write(U.UC_ARM_REG_S0, struct.unpack("<I", struct.pack("<f", v))[0])
    uc.reg_write(U.UC_ARM_REG_LR, STOP | 1)
    cost = emu.model.run(uc, emu.sym["polycc_swarm_step"], STOP, emu.scene_range)
    return cost, np.frombuffer(bytes(uc.mem_read(po, OUT_DTYPE.itemsize)), OUT_DTYPE)


def arm_cost() -> dict:
    """Cycles of polycc_swarm_step with 16 neighbours (all in the soft-min) minus polycc_step, on the
    Cortex-M4 model of bench_kernel, at a few states of a 150-polytope room."""
    import bench_kernel as BK

    from polycc.onboard import barrier as B
    from polycc.onboard import swarm as SW
    from polycc.sim import kernel_arm
    from polycc.sim.swarm_arm import table_bytes

    d = kernel_arm.build("swarm_bench", [Path(__file__).resolve().parent / "bench_swarm_main.c",
                                         kernel_arm.SRC / "polycc_swarm.c", kernel_arm.ARM_DIR / "startup.c",
                                         kernel_arm.ARM_DIR / "semihost.c"],
                         extra_headers=[kernel_arm.ARM_DIR / "semihost.h", kernel_arm.SRC / "polycc_swarm.h"],
                         libs=["-lm"])
    emu = BK.Emulator(d / "swarm_bench.elf")
    sc = BK.room_scene(150, 0)
    params = B.Params()
    emu.load_scene(sc, params)
    rng = np.random.default_rng(0)
    res = []
    for _ in range(5):
        x = (rng.uniform(0, 10, 3) * np.array([1, 1, 0.3])).astype(np.float32)
        sw = SW.Swarm()
        dirs = rng.normal(size=(16, 3))
        dirs /= np.linalg.norm(dirs, axis=1)[:, None]
        for j in range(16):  # a ring at one distance: every term within 17/kappa of the minimum
            sw.report(j, (x + 0.6 * dirs[j]).astype(np.float32), 300, 0.1, x)
        blob = table_bytes(sw)
        c_k, _ = emu.call_step("polycc_step", x, x + 1)
        c_s, out = call_swarm(emu, blob, 1.0, x, x + 1)
        want = SW.step(sc, params, sw, 1.0, x, x + 1)
        for f in ("u", "u_nom", "psi", "grad", "flags"):  # the ARM build is bit-exact with the reference too
            got = np.asarray(out[f][0]).astype(np.asarray(want[f]).dtype)
            assert np.array_equal(got.view(np.uint32), np.asarray(want[f]).view(np.uint32)), f"ARM != reference: {f}"
        res.append({"kernel_high": c_k.high, "swarm_high": c_s.high, "extra_high": c_s.high - c_k.high,
                    "extra_low": c_s.low - c_k.low})
    return {"states": res, "extra_high_max": max(r["extra_high"] for r in res)}


def instances_cost(header: Path, n: int = 16) -> dict:
    """N app instances: copies of the shared object loaded in this process (what swarm-sim does)
    against one process per drone (each a fresh interpreter importing the same module), measured in
    one run: wall time to get N ready instances and the resident memory they add."""
    import subprocess

    from polycc.swarm.instances import drone_apps

    def rss_mb() -> float:
        with open("/proc/self/status") as f:
            return next(int(ln.split()[1]) for ln in f if ln.startswith("VmRSS")) / 1024.0

    drone_apps(header, 1)  # build once (not timed: both ways need it)
    r0, t0 = rss_mb(), time.perf_counter()
    apps = drone_apps(header, n)
    for a in apps:
        a.reset()
    copies = {"wall_s": time.perf_counter() - t0, "rss_mb": rss_mb() - r0}
    code = ("import sys; from polycc.sim.app_ffi import AppSim; a = AppSim(sys.argv[1]); a.reset(); "
            "print('ok', flush=True); sys.stdin.read()")
    t0 = time.perf_counter()
    procs = [subprocess.Popen([sys.executable, "-c", code, str(header)], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                              text=True) for _ in range(n)]
    for p in procs:
        p.stdout.readline()
    wall = time.perf_counter() - t0
    rss = 0.0
    for p in procs:
        with open(f"/proc/{p.pid}/status") as f:
            rss += next(int(ln.split()[1]) for ln in f if ln.startswith("VmRSS")) / 1024.0
        p.stdin.close()
        p.wait()
    return {"n": n, "copies": copies, "processes": {"wall_s": wall, "rss_mb": rss}}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="demo arena, n in {2, 4}, 2 trials, t-max 40 s")
    ap.add_argument("--arenas", default="demo,captures,room", help="comma-separated subset of demo,captures,room")
    ap.add_argument("--ns", default="2,4,8,16", help="comma-separated drone counts (default: 2,4,8,16)")
    ap.add_argument("--trials", type=int, default=10, help="trials per (arena, n) (default: 10)")
    ap.add_argument("--t-max", type=float, default=60.0, help="simulated seconds per trial (default: 60)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--arm", action="store_true", help="also measure the on-board cost of the neighbour terms")
    ap.add_argument("--instances", action="store_true", help="also measure N app copies against N processes")
    ap.add_argument("--name", default="bench_swarm", help="results file name (default: bench_swarm)")
    a = ap.parse_args(argv)
    arenas = ["demo"] if a.quick else [s for s in a.arenas.split(",") if s]
    ns = [2, 4] if a.quick else [int(s) for s in a.ns.split(",")]
    trials, t_max = (2, 40.0) if a.quick else (a.trials, a.t_max)
    t0 = time.perf_counter()
    rows = []
    for name in arenas:
        build, ell = arena_build(name)
        for n in ns:
            rows += run_cell(name, build, ell, n, trials, t_max, a.seed)
            write_json(a.name + "_partial", {"trials": rows})  # what ran so far, if the run is stopped
    table = summarize(rows, t_max)
    header = ["arena", "n", "controller", "trials", "coll d-d", "coll d-o", "coverage", "cov min", "full",
              "task med s", "task mean s", "min d-d m", "min clear m", "us/drone-tick"]
    print_table(f"swarm coverage (task time: trials missing a peak count as {t_max:g} s)", header, table)
    payload = {"config": {"arenas": arenas, "ns": ns, "trials": trials, "t_max_s": t_max, "grid_m": GRID,
                          "rate_hz": RATE_HZ,
                          "radius_m": RADIUS, "controllers": list(CONTROLLERS), "seed": a.seed},
               "table": {"header": header, "rows": table}, "trials": rows, "wall_s": time.perf_counter() - t0,
               "peak_rss_mb": peak_rss_mb()}
    write_json(a.name, payload)  # the matrix is kept whatever the extras below do
    if a.instances:
        build, _ = arena_build(arenas[0])
        ic = instances_cost(build / "polytopes.h")
        payload["instances"] = ic
        print_table("16 app instances", ["how", "wall s", "added RSS MB"],
                    [["copies of the .so, one process", ic["copies"]["wall_s"], ic["copies"]["rss_mb"]],
                     ["one process per drone", ic["processes"]["wall_s"], ic["processes"]["rss_mb"]]])
    if a.arm:
        cost = arm_cost()
        payload["onboard"] = cost
        from polycc.onboard.app import SWARM_WORST_CYCLES

        print(f"on-board neighbour terms (16, all in the soft-min): +{cost['extra_high_max']} cycles (high bound) "
              f"over polycc_step; the app budgets POLYCC_APP_SWARM_WORST_CYCLES = {SWARM_WORST_CYCLES} "
              f"({cost['extra_high_max'] / 168:.1f} us at 168 MHz)")
    write_json(a.name, payload)
    return 0


if __name__ == "__main__":
    sys.exit(main())
