"""Benchmark: load + exact occupancy of the 1.5M-Gaussian tiled room.

Targets on the 2-core machine: g = 5 cm <= 20 s, g = 2 cm <= 60 s, peak RSS <= 4 GB.
Each configuration runs in a fresh subprocess so its peak RSS is its own. The naive
AABB-only voxelizer (every voxel of every splat's bounding box) runs in the same
process as a baseline; the table reports how many extra voxels it marks.

    python bench/bench_occupancy.py [--quick]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time

import numpy as np

sys.path.insert(0, str(__import__("pathlib").Path(__file__).resolve().parent))
from common import CACHE, SCENES, peak_rss_mb, print_table, write_json  # noqa: E402


def room_ply(target: int) -> str:
    """Write (once, cached) the tiled room as a graphdeco 3DGS .ply and return its path."""
    from polycc.demo.arenas import tiled_room
    from polycc.scene.writers import write_gaussian_ply

    path = CACHE / f"tiled_room_{target}.ply"
    if not path.exists():
        CACHE.mkdir(parents=True, exist_ok=True)
        ell = tiled_room(SCENES, target=target)
        tmp = path.with_suffix(".tmp.ply")
        write_gaussian_ply(tmp, ell)
        tmp.replace(path)
    return str(path)


def aabb_voxel_count(ell, g: float) -> int:
    """Naive baseline: number of distinct voxels in the union of the splats' AABBs."""
    from polycc.occupancy.exact import aabb_index_range, pack_keys

    imin, imax = aabb_index_range(ell, g, np.zeros(3))
    keys = []
    chunk = 20_000
    for s in range(0, len(ell), chunk):
        lo, hi = imin[s : s + chunk], imax[s : s + chunk]
        ext = hi - lo + 1
        n = ext.prod(axis=1)
        own = np.repeat(np.arange(lo.shape[0]), n)
        j = np.arange(own.size) - np.repeat(np.cumsum(n) - n, n)
        e = ext[own]
        idx = lo[own] + np.stack([j % e[:, 0], (j // e[:, 0]) % e[:, 1], j // (e[:, 0] * e[:, 1])], axis=1)
        keys.append(np.unique(pack_keys(idx)))
    return int(np.unique(np.concatenate(keys)).size)


def run_one(ply: str, g: float, baseline: bool) -> dict:
    """One configuration, in this process: load, voxelize, optional AABB baseline."""
    from polycc.occupancy.exact import voxelize
    from polycc.scene.load import load_scene

    t0 = time.perf_counter()
    scene = load_scene(ply)
    t1 = time.perf_counter()
    occ = voxelize(scene.ellipsoids, g)
    t2 = time.perf_counter()
    out = {
        "g": g,
        "splats": len(scene.ellipsoids),
        "load_s": t1 - t0,
        "voxelize_s": t2 - t1,
        "total_s": t2 - t0,
        "voxels": len(occ),
        "exact_tests": occ.stats["exact_tests"],
        "peak_rss_mb": peak_rss_mb(),
    }
    if baseline:
        t3 = time.perf_counter()
        out["aabb_voxels"] = aabb_voxel_count(scene.ellipsoids, g)
        out["aabb_s"] = time.perf_counter() - t3
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="300k splats instead of 1.5M (smoke run)")
    ap.add_argument("--child", nargs=3, metavar=("PLY", "G", "BASELINE"), help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        print(json.dumps(run_one(args.child[0], float(args.child[1]), args.child[2] == "1")))
        return
    target = 300_000 if args.quick else 1_500_000
    t = time.perf_counter()
    ply = room_ply(target)
    print(f"scene: {ply} (built/cached in {time.perf_counter() - t:.1f} s)")
    rows, results = [], []
    targets = {0.05: 20.0, 0.02: 60.0}
    for g in (0.05, 0.02):
        out = subprocess.run([sys.executable, __file__, "--child", ply, str(g), "1"], check=True, capture_output=True,
                             text=True)
        r = json.loads(out.stdout.strip().splitlines()[-1])
        r["target_s"] = targets[g]
        results.append(r)
        rows.append([
            f"{g * 100:g} cm", r["splats"], round(r["load_s"], 2), round(r["voxelize_s"], 2), round(r["total_s"], 2),
            f"<= {targets[g]:g}", f"{r['splats'] / r['total_s']:,.0f}", r["voxels"], r["aabb_voxels"],
            f"{r['aabb_voxels'] / r['voxels']:.2f}x", round(r["peak_rss_mb"] / 1024, 2),
        ])
    print_table(
        "load + exact occupancy, tiled room (naive AABB voxelizer as baseline)",
        ["g", "splats", "load s", "voxelize s", "total s", "target s", "splats/s", "voxels (exact)",
         "voxels (AABB)", "AABB/exact", "peak RSS GB"],
        rows,
    )
    write_json("occupancy", {"scene": ply, "results": results})


if __name__ == "__main__":
    main()
