"""Benchmark of the spatial index (docs/barrier.md section 9), side by side with today's kernel (index off).

For the demo arena and the arena of real captures at 64 and 16 KiB, one run: the budget selection with
the index (default clearance cap, --rate-hz 500 --cpu-share 0.2: a certified worst case <= 400 us)
and without it (today's default: no rate budget, worst = every polytope evaluated), each reporting n,
half-planes, index bytes, conservativeness (Monte Carlo, same samples), the modelled worst and typical
microseconds at 168 MHz, the worst/typical ratio and the speed-up of the indexed worst case over the
index-off worst case; then, on the Cortex-M4 model (unicorn + capstone, polycc/sim/cortex_m4_model.py),
the cycles at points of the leaf with the largest certified figure, against that figure.

    python bench/bench_index.py [--quick] [--samples S]
Writes bench/results/bench_index.json and prints a table.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_build import arena_ply  # noqa: E402
from common import print_table, write_json  # noqa: E402

BUDGETS_KB = (64, 16)
SCENES_ = ("demo_arena", "capture_arena")


def run_one(family, kb: int, cap: float | None, rate_cycles: float | None, samples: int) -> dict:
    from polycc.budget import cycle_model as CM
    from polycc.budget.select import Budget, select

    t = time.perf_counter()
    best, cands, binding = select(family, Budget(kb * 1024, None, rate_cycles, cap, 100.0), mc_samples=samples)
    us = CM.estimate_us(best.packed)
    ix = best.packed.index
    return {"n": best.n, "halfplanes": best.n_planes, "bytes": best.bytes, "index_bytes": ix.nbytes() if ix else 0,
            "index": None if ix is None else {"cell_m": ix.cell, "dims": list(ix.dims), "inner": ix.n_inner,
                                              "lists": ix.n_lists, "entries": len(ix.entries)},
            "conservativeness": best.conservativeness, "ci95": best.conservativeness_ci,
            "worst_us": us["worst_us"], "typical_us": us["typical_us"], "certified": ix is not None,
            "worst_over_typical": us["worst_us"] / max(us["typical_us"], 1e-9), "binding": binding,
            "select_s": time.perf_counter() - t, "packed": best.packed}


def arm_check(packed, n_points: int = 12, seed: int = 0) -> dict | None:
    """Cycles (high end of the Cortex-M4 model) at points of the leaf with the largest certified figure."""
    try:
        from polycc.budget import cycle_model as CM
        from polycc.onboard import barrier as B
        from polycc.sim import kernel_arm
        from polycc.sim.cortex_m4_model import Emulator
    except ImportError:
        return None
    if kernel_arm.missing_tools():
        return None
    emu = Emulator(kernel_arm.test_program())
    emu.load_scene(packed, B.Params())
    ids, cyc = CM.leaf_cycles(packed)
    worst_list = ids[int(np.argmax(cyc))]
    ix = packed.index
    lo = ix.origin.astype(np.float64)
    rng = np.random.default_rng(seed)
    probe = rng.uniform(lo, lo + np.array(ix.dims) * ix.cell, (200_000, 3))
    lid, _ = packed.index_leaf(probe)
    pts = probe[lid == worst_list][:n_points]
    highs = [emu.call_step("polycc_step", x, np.zeros(3))[0].high for x in pts]
    return {"certified_cycles": float(CM.worst_cycles(packed)), "measured_max_cycles": int(max(highs, default=0)),
            "points": len(highs)}


def main(argv=None) -> int:
    from polycc.budget import cycle_model as CM
    from polycc.cover.build import build_cover
    from polycc.occupancy.exact import voxelize
    from polycc.onboard.index import DEFAULT_CLEARANCE_CAP
    from polycc.scene.load import load_scene

    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true", help="demo arena at 64 KiB only")
    ap.add_argument("--samples", type=int, default=20_000, help="Monte Carlo samples per candidate")
    args = ap.parse_args(argv)
    rate = CM.cycle_budget(CM.DEFAULT_RATE_HZ, CM.DEFAULT_CPU_SHARE)
    rows, out = [], []
    for name in SCENES_[:1] if args.quick else SCENES_:
        occ = voxelize(load_scene(arena_ply(name)).ellipsoids, 0.05)
        family = build_cover(occ)
        for kb in BUDGETS_KB[:1] if args.quick else BUDGETS_KB:
            off = run_one(family, kb, None, None, args.samples)
            on = run_one(family, kb, DEFAULT_CLEARANCE_CAP, rate, args.samples)
            arm = arm_check(on["packed"])
            rec = {"scene": name, "budget_kb": kb, "clearance_cap_m": DEFAULT_CLEARANCE_CAP,
                   "off": {k: v for k, v in off.items() if k != "packed"},
                   "on": {k: v for k, v in on.items() if k != "packed"}, "arm_model": arm,
                   "speedup_worst": off["worst_us"] / on["worst_us"],
                   "conservativeness_delta_pct": 100 * (on["conservativeness"] - off["conservativeness"])}
            out.append(rec)
            for tag, r in (("off", off), ("on", on)):
                rows.append([name.replace("_arena", ""), kb, tag, r["n"], r["halfplanes"], r["index_bytes"],
                             f"{r['conservativeness']:.4f}+-{r['ci95']:.4f}", round(r["worst_us"]),
                             "yes" if r["certified"] else "no", round(r["typical_us"], 1),
                             round(r["worst_over_typical"], 1),
                             f"{rec['speedup_worst']:.1f}x" if tag == "on" else "",
                             f"{arm['measured_max_cycles']}/{arm['certified_cycles']:.0f}" if tag == "on" and arm
                             else ""])
            print_table("spatial index (so far)", HEADER, rows)
    print_table("spatial index vs today's kernel (index off), modelled Cortex-M4 @ 168 MHz", HEADER, rows)
    write_json("bench_index", {"rate_hz": CM.DEFAULT_RATE_HZ, "cpu_share": CM.DEFAULT_CPU_SHARE,
                               "mc_samples": args.samples, "results": out})
    return 0


HEADER = ["scene", "KiB", "index", "n", "half-planes", "index B", "conservativeness", "worst us", "certified",
          "typical us", "worst/typical", "worst speed-up", "ARM model cyc (meas/cert)"]

if __name__ == "__main__":
    sys.exit(main())
