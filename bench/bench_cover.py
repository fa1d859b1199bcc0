"""Benchmark: PolyMerge cover (set cover and iterative merging).

1. Speed: the 1.5M-Gaussian tiled room at g = 5 cm, b = 1, voxels -> full merge family
   (target <= 60 s on the 2-core machine), time per stage, default merge cost.
2. Quality: conservativeness Vol(U H^n)/Vol(V+) (Monte Carlo, 95% CI) and total
   half-planes at n in {10, 30, 50, 100, 150} for both merge costs on three scenes: the
   demo arena, the arena of real captures (plant, ring, tree on a floor) and the donut.
3. Peer baseline: CoACD on a surface mesh of the same occupancy (the boundary faces of
   the occupied voxels): hull count, conservativeness, coverage fraction (share of the
   occupied volume inside its hulls; PolyMerge is 1 by construction) and time, side by
   side with PolyMerge at the same hull count.

    python bench/bench_cover.py [--quick] [--no-coacd] [--no-room]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import SCENES, peak_rss_mb, print_table, write_json  # noqa: E402

LEVELS = (10, 30, 50, 100, 150)
COACD_THRESHOLDS = (0.1, 0.05)  # CoACD's concavity threshold; ~5 min per run on the donut here
G = 0.05


def scenes(quick: bool) -> dict:
    from polycc.demo.arena import make_demo_arena
    from polycc.demo.arenas import capture_arena, load_capture

    out = {"demo arena": make_demo_arena(0)}
    if not quick:
        out["capture arena"] = capture_arena(SCENES)
    out["donut"] = load_capture(SCENES / "donut_fused.ply", 1.0)
    return out


def conservativeness(fam, n: int, samples: int, rng) -> tuple[float, float]:
    from polycc.verify.certify import FamilyArrays, PolytopeSet, union_volume_mc

    ps = PolytopeSet(FamilyArrays.from_family(fam), fam.active_nodes(n))
    v, ci = union_volume_mc(ps, samples, rng)
    occ = len(fam.grid_indices) * fam.voxel_size**3
    return v / occ, ci / occ


# ------------------------------------------------------------------ speed


def bench_speed(quick: bool) -> dict:
    from bench_occupancy import room_ply

    from polycc.cover.build import DEFAULT_MERGE_COST, build_cover
    from polycc.occupancy.exact import voxelize
    from polycc.scene.load import load_scene

    target = 300_000 if quick else 1_500_000
    ply = room_ply(target)
    t0 = time.perf_counter()
    scene = load_scene(ply)
    grid = voxelize(scene.ellipsoids, G)
    t_vox = time.perf_counter() - t0
    runs, rows = {}, []
    for cost in ("delta", "paper", DEFAULT_MERGE_COST):
        t0 = time.perf_counter()
        fam = build_cover(grid, 1, cost)
        total = time.perf_counter() - t0
        t = fam.meta["timings_s"]
        runs[cost] = {"N": fam.n_max, "pair_evaluations": fam.meta["pair_evaluations"], "stages_s": t,
                      "voxels_to_family_s": total, "picked": fam.meta["merge_cost"]}
        rows.append([cost + (" (default)" if cost == DEFAULT_MERGE_COST else ""), len(grid), fam.n_max,
                     fam.meta["pair_evaluations"], round(t["clusters"], 2), round(t["set_cover"], 2),
                     round(t["merge"], 2), round(t["halfplanes"], 2), round(total, 2), "<= 60"])
    import os

    res = {"scene": ply, "splats": len(scene.ellipsoids), "voxels": len(grid), "load_voxelize_s": t_vox,
           "load_average_1_5_15": list(os.getloadavg()),
           "runs": runs, "target_s": 60.0, "default_merge_cost": DEFAULT_MERGE_COST, "peak_rss_mb": peak_rss_mb()}
    print_table(f"speed: tiled room {len(scene.ellipsoids):,} splats, g = 5 cm, b = 1 "
                f"(load + voxelize {t_vox:.1f} s, not counted; machine load average {os.getloadavg()[0]:.1f})",
                ["merge cost", "voxels", "N", "pair evals", "clusters s", "set cover s", "merge s",
                 "half-planes s", "voxels->family s", "target s"], rows)
    return res


# ------------------------------------------------------------------ quality


def bench_quality(scene_sets: dict, samples: int) -> tuple[dict, dict]:
    from polycc.cover.build import build_cover
    from polycc.occupancy.exact import voxelize

    results, grids = {}, {}
    rows = []
    for name, ell in scene_sets.items():
        grid = voxelize(ell, G)
        grids[name] = grid
        stages: dict = {}
        per_cost = {}
        for cost in ("paper", "delta"):
            t0 = time.perf_counter()
            fam = build_cover(grid, 1, cost, stages=stages)
            dt = time.perf_counter() - t0
            rng = np.random.default_rng(0)
            lv = {}
            for n in LEVELS:
                if n <= fam.n_max:
                    c, ci = conservativeness(fam, n, samples, rng)
                    lv[n] = {"conservativeness": c, "ci95": ci, "halfplanes": fam.halfplane_count(n)}
            per_cost[cost] = {"N": fam.n_max, "time_s": dt, "levels": lv, "family": fam}
        from polycc.cover.build import selection_score

        scores = {c: selection_score(r["family"]) for c, r in per_cost.items()}
        best = "delta" if scores["delta"] < scores["paper"] else "paper"
        for n in LEVELS:
            if n not in per_cost["paper"]["levels"]:
                continue
            p, d = per_cost["paper"]["levels"][n], per_cost["delta"]["levels"][n]
            waste_cut = 1 - (d["conservativeness"] - 1) / max(p["conservativeness"] - 1, 1e-12)
            rows.append([name, n, f"{p['conservativeness']:.4f} ± {p['ci95']:.4f}", p["halfplanes"],
                         f"{d['conservativeness']:.4f} ± {d['ci95']:.4f}", d["halfplanes"], f"{100 * waste_cut:+.1f}%",
                         best])
        results[name] = {"voxels": len(grid), "splats": len(ell), "best_picks": best, "selection_scores": scores,
                         **{c: {k: v for k, v in r.items() if k != "family"} for c, r in per_cost.items()}}
        results[name]["_families"] = {c: r["family"] for c, r in per_cost.items()}
    print_table("quality: conservativeness Vol(U H^n)/Vol(V+) (95% CI) and total half-planes, g = 5 cm, b = 1",
                ["scene", "n", "paper: cons.", "paper: half-planes", "delta: cons.", "delta: half-planes",
                 "wasted volume cut by delta", "default 'best' keeps"], rows)
    return results, grids


# ------------------------------------------------------------------ CoACD baseline


def surface_mesh(grid) -> tuple[np.ndarray, np.ndarray]:
    """Boundary faces of the occupied voxels as a triangle mesh (vertices in metres)."""
    idx = grid.indices
    keys = {tuple(v) for v in idx.tolist()}
    quads = []
    axes = np.eye(3, dtype=np.int64)
    for ax in range(3):
        for sgn in (-1, 1):
            nb = idx + sgn * axes[ax]
            free = np.array([tuple(v) not in keys for v in nb.tolist()])
            base = idx[free] + (axes[ax] if sgn > 0 else 0)
            u, w = axes[(ax + 1) % 3], axes[(ax + 2) % 3]
            q = np.stack([base, base + u, base + u + w, base + w], axis=1)
            if sgn < 0:
                q = q[:, ::-1]
            quads.append(q)
    q = np.concatenate(quads)
    verts, inv = np.unique(q.reshape(-1, 3), axis=0, return_inverse=True)
    inv = inv.reshape(-1, 4)
    faces = np.concatenate([inv[:, [0, 1, 2]], inv[:, [0, 2, 3]]])
    return grid.origin + verts * grid.voxel_size, faces


def hull_set(hulls, g):
    """verify.PolytopeSet-compatible arrays for a list of vertex clouds (via qhull)."""
    from scipy.spatial import ConvexHull

    from polycc.verify.certify import FamilyArrays, PolytopeSet

    planes, verts, pp, vp = [], [], [0], [0]
    for v in hulls:
        h = ConvexHull(v)
        eq = np.unique(np.round(h.equations, 12), axis=0)
        planes.append(np.column_stack([eq[:, :3], -eq[:, 3]]))
        verts.append(v[h.vertices])
        pp.append(pp[-1] + len(eq))
        vp.append(vp[-1] + len(h.vertices))
    fa = FamilyArrays(g, np.zeros(3), np.empty((0, 3)), np.empty((0, 2), np.int64), np.array(pp),
                      np.concatenate(planes), np.array(vp), np.concatenate(verts), {})
    return PolytopeSet(fa, np.arange(len(hulls)))


def coverage_fraction(ps, grid, samples: int, rng) -> float:
    """Share of the occupied volume inside the union of ``ps`` (uniform points in V+)."""
    k = rng.integers(0, len(grid), samples)
    pts = grid.origin + (grid.indices[k] + rng.random((samples, 3))) * grid.voxel_size
    return float(np.mean(ps.count_containing(pts) > 0))


def bench_coacd(grids: dict, quality: dict, samples: int, names: list[str]) -> dict:
    import coacd

    from polycc.verify.certify import FamilyArrays, PolytopeSet, union_volume_mc

    coacd.set_log_level("error")
    out, rows = {}, []
    for name in names:
        grid = grids[name]
        V, F = surface_mesh(grid)
        occ = len(grid) * grid.voxel_size**3
        for thr in COACD_THRESHOLDS:
            t0 = time.perf_counter()
            parts = coacd.run_coacd(coacd.Mesh(V, F), threshold=thr, seed=0)
            dt = time.perf_counter() - t0
            hulls = [np.asarray(p[0], np.float64) for p in parts]
            ps = hull_set(hulls, grid.voxel_size)
            rng = np.random.default_rng(0)
            vol, ci = union_volume_mc(ps, samples, rng)
            cov = coverage_fraction(ps, grid, samples, rng)
            n = len(hulls)
            keep = quality[name]["best_picks"]  # the family the default ('best') keeps
            fam = quality[name]["_families"][keep]
            n_ours = min(n, fam.n_max)
            fa = FamilyArrays.from_family(fam)
            ours_ps = PolytopeSet(fa, fam.active_nodes(n_ours))
            ov, oci = union_volume_mc(ours_ps, samples, np.random.default_rng(0))
            ocov = coverage_fraction(ours_ps, grid, samples, np.random.default_rng(1))
            ours_t = quality[name]["paper"]["time_s"] + quality[name]["delta"]["time_s"]
            r = {"threshold": thr, "hulls": n, "time_s": dt, "conservativeness": vol / occ, "ci95": ci / occ,
                 "coverage_fraction": cov, "mesh_triangles": int(len(F)),
                 "polymerge": {"merge_cost": keep, "n": n_ours, "conservativeness": ov / occ, "ci95": oci / occ,
                               "coverage_fraction": ocov, "time_s_full_family": ours_t}}
            out.setdefault(name, []).append(r)
            rows.append([name, f"CoACD thr {thr}", n, f"{vol / occ:.3f} ± {ci / occ:.3f}", f"{cov:.4f}",
                         round(dt, 2)])
            rows.append([name, f"PolyMerge (best = {keep})", n_ours, f"{ov / occ:.3f} ± {oci / occ:.3f}",
                         f"{ocov:.4f}", f"{ours_t:.2f} (both costs, all n)"])
    print_table("peer baseline: CoACD on the voxel surface mesh vs PolyMerge at the same hull count",
                ["scene", "method", "hulls", "conservativeness", "coverage fraction", "time s"], rows)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="300k-splat room, no capture arena (smoke run)")
    ap.add_argument("--no-coacd", action="store_true", help="skip the CoACD baseline")
    ap.add_argument("--no-room", action="store_true", help="skip the speed run on the tiled room")
    ap.add_argument("--samples", type=int, default=300_000, help="Monte Carlo samples per estimate")
    ap.add_argument("--only-speed", action="store_true", help="only the speed run (writes cover_speed.json)")
    args = ap.parse_args()
    payload = {}
    if not args.no_room:
        payload["speed"] = bench_speed(args.quick)
    if args.only_speed:
        write_json("cover_speed", payload)
        return
    quality, grids = bench_quality(scenes(args.quick), args.samples)
    if not args.no_coacd:
        names = ["donut"]  # CoACD needs minutes per run; the capture arena would take far longer
        payload["coacd"] = bench_coacd(grids, quality, args.samples, names)
    for r in quality.values():
        r.pop("_families", None)
    payload["quality"] = quality
    write_json("cover", payload)


if __name__ == "__main__":
    main()
