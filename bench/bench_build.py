"""Benchmark of `polycc build` (budgets, reduction, quantization).

For the arena of real captures and the demo arena, at 8, 16, 32 and 64 KiB: n, half-planes,
bytes per half-plane, conservativeness and modelled on-board microseconds, next to a
"paper-faithful" storage at the same budget (qhull's triangle facets unmerged, float32
n and d per plane, no reduction: the largest n whose planes fit), first on our merge family,
then on the paper's own cover (its clusters only, its merge cost): "paper pipeline". Wasted
volume is Vol(union H \\ V+), estimated directly (polycc.geometry.union_volume.union_waste), with the
same samples for every column. Also times `polycc build` end to end on the 1.5M-splat room.

    python bench/bench_build.py [--quick]
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from scipy.spatial import ConvexHull

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import CACHE, SCENES, print_table, write_json  # noqa: E402

BUDGETS_KB = (8, 16, 32, 64)
PLANE_BYTES_PAPER = 16


def arena_ply(name: str) -> Path:
    from polycc.demo.arena import make_demo_arena
    from polycc.demo.arenas import capture_arena, tiled_room
    from polycc.scene.writers import write_gaussian_ply

    path = CACHE / ("tiled_room_1500000.ply" if name == "tiled_room" else f"{name}.ply")  # as bench_occupancy
    if not path.exists():
        CACHE.mkdir(parents=True, exist_ok=True)
        ell = {"demo_arena": lambda: make_demo_arena(0), "capture_arena": lambda: capture_arena(SCENES),
               "tiled_room": lambda: tiled_room(SCENES)}[name]()
        tmp = path.with_suffix(".tmp.ply")
        write_gaussian_ply(tmp, ell)
        tmp.replace(path)
    return path


def paper_faithful(family, budget_bytes: int, occ_vol: float, samples: int):
    """Largest n whose unmerged triangle facets (float32 n, d) fit; its wasted volume."""
    from polycc.geometry.union_volume import in_voxels, union_waste

    tri = np.array([len(ConvexHull(family.vertices[family.vertex_ptr[k]:family.vertex_ptr[k + 1]]).simplices)
                    for k in range(len(family.plane_ptr) - 1)])
    best = None
    N = family.n_max
    lo, hi = 1, N
    def fits(n):
        nodes = family.active_nodes(n)
        return 28 + n * 28 + tri[nodes].sum() * PLANE_BYTES_PAPER <= budget_bytes
    if not fits(1):
        return None
    while lo < hi:  # triangle counts grow with n almost monotonically; binary search
        mid = (lo + hi + 1) // 2
        if fits(mid):
            lo = mid
        else:
            hi = mid - 1
    n = lo
    polys = family.materialise(n)
    boxes = [(p.vertices.min(0), p.vertices.max(0)) for p in polys]
    occupied = in_voxels(family.grid_indices, family.origin, family.voxel_size)
    _, _, waste, wci = union_waste([p.halfplanes for p in polys], boxes, occupied, samples=samples)
    nodes = family.active_nodes(n)
    best = {"n": n, "halfplanes": int(tri[nodes].sum()), "conservativeness": 1 + waste / occ_vol, "wasted_m3": waste,
            "wasted_ci_m3": wci,
            "bytes_at": lambda m: 28 + m * 28 + int(tri[family.active_nodes(m)].sum()) * PLANE_BYTES_PAPER}
    return best


def table_for(name: str, samples: int) -> list[dict]:
    from polycc.budget import cycle_model
    from polycc.budget.select import Budget, select
    from polycc.cover.build import build_cover
    from polycc.occupancy.exact import voxelize
    from polycc.scene.load import load_scene

    scene = load_scene(arena_ply(name))
    occ = voxelize(scene.ellipsoids, 0.05)
    t = time.perf_counter()
    family = build_cover(occ)
    t_cover = time.perf_counter() - t
    paper_family = build_cover(occ, cost="paper", boxes=False)  # the paper's own cover, for the pipeline baseline
    occ_vol = occ.volume()
    rows = []
    for kb in BUDGETS_KB:
        t = time.perf_counter()
        best, _, binding = select(family, Budget(kb * 1024), mc_samples=samples)
        us = cycle_model.estimate_us(best.packed)
        pf = paper_faithful(family, kb * 1024, occ_vol, samples)
        pp = paper_faithful(paper_family, kb * 1024, occ_vol, samples)
        rows.append({
            "scene": name, "budget_kb": kb, "n": best.n, "halfplanes": best.n_planes,
            "bytes_per_halfplane": best.bytes / best.n_planes, "conservativeness": best.conservativeness,
            "ci95": best.conservativeness_ci, "wasted_m3": best.union_volume - occ_vol,
            "wasted_ci_m3": best.union_ci, "binding_short": binding.split(" ")[0],
            "typical_us": us["typical_us"], "worst_us": us["worst_us"], "binding": binding,
            "select_s": time.perf_counter() - t, "cover_s": t_cover,
            "paper_n": pf["n"] if pf else None, "paper_halfplanes": pf["halfplanes"] if pf else None,
            "paper_conservativeness": pf["conservativeness"] if pf else None,
            "paper_wasted_m3": pf["wasted_m3"] if pf else None,
            "paper_bytes_same_n": pf["bytes_at"](best.n) if pf else None,
            "pipeline_n": pp["n"] if pp else None,
            "pipeline_conservativeness": pp["conservativeness"] if pp else None,
            "pipeline_wasted_m3": pp["wasted_m3"] if pp else None,
        })
    return rows


def end_to_end(quick: bool) -> dict:
    ply = arena_ply("capture_arena" if quick else "tiled_room")
    out = CACHE / "build_e2e"
    t = time.perf_counter()
    subprocess.run([sys.executable, "-m", "polycc", "build", str(ply), "--flash-kb", "64", "-o", str(out)],
                   check=True, capture_output=True)
    return {"scene": ply.name, "seconds": time.perf_counter() - t, "target_s": 90.0}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="fewer Monte Carlo samples, small end-to-end scene")
    args = ap.parse_args()
    samples = 30_000 if args.quick else 200_000
    rows = []
    for name in ("capture_arena", "demo_arena"):
        rows += table_for(name, samples)
    def ratio(paper, ours):
        return f"{paper / max(ours, 1e-12):.1f}x" if paper is not None else "-"

    print_table(
        "polycc build vs paper-faithful storage at equal bytes (float32 n, d per qhull triangle facet, no "
        "reduction, largest n that fits), g = 5 cm; 'paper pipeline' also uses the paper's cover (no boxes, paper "
        "cost)",
        ["scene", "KiB", "n", "planes", "B/plane", "cons. (95%)", "wasted m^3", "typ/worst us", "binding",
         "paper n", "paper cons.", "wasted ratio", "paper KiB at our n", "pipeline n", "pipeline cons.", "ratio"],
        [[r["scene"].replace("_arena", ""), r["budget_kb"], r["n"], r["halfplanes"], round(r["bytes_per_halfplane"], 2),
          f"{r['conservativeness']:.4f} +- {r['ci95']:.4f}", f"{r['wasted_m3']:.5f}",
          f"{r['typical_us']:.0f} / {r['worst_us']:.0f}", r["binding_short"],
          r["paper_n"], f"{r['paper_conservativeness']:.4f}" if r["paper_conservativeness"] else "-",
          ratio(r["paper_wasted_m3"], r["wasted_m3"]),
          round(r["paper_bytes_same_n"] / 1024, 1) if r["paper_bytes_same_n"] else "-",
          r["pipeline_n"], f"{r['pipeline_conservativeness']:.4f}" if r["pipeline_conservativeness"] else "-",
          ratio(r["pipeline_wasted_m3"], r["wasted_m3"])]
         for r in rows],
    )
    e2e = end_to_end(args.quick)
    print_table("polycc build end to end, --flash-kb 64", ["scene", "seconds", "target s"],
                [[e2e["scene"], round(e2e["seconds"], 1), e2e["target_s"]]])
    write_json("build", {"rows": rows, "end_to_end": e2e})


if __name__ == "__main__":
    main()
