"""Benchmark of the budget's drop costs: every plane's drop volume of every polytope the reduction reduces.

Side by side in one run, on the polytopes of a real build (the tiled benchmark room of real captures,
`polycc.demo.arenas.tiled_room`, `polycc build --voxel G --flash-kb 64`, the family at the n that build
selected, each polytope's planes as the reduction receives them):

* qhull: one scipy half-space intersection per plane (`polycc.budget.reduce.drop_cost`, the way every
  cost was computed until 2026-12-07 and the one-plane recomputes until the C);
* numpy: one enumeration of plane triples for every plane (`polycc.geometry.halfplanes.drop_volumes`,
  the reference);
* C: the same enumeration in C (`polycc.native.cap_volumes`, what the reduction runs now).

Up to 128 planes (above, all three take qhull per plane). Reports seconds, microseconds per polytope, the
ratio to qhull, the largest disagreement with qhull relative to the polytope's volume and whether the
infinite (essential) planes agree; then the end-to-end `reduce_planes` of the family to half its planes.

    python bench/bench_caps.py [--splats 1500000] [--voxel 0.05]
Writes bench/results/bench_caps.json and prints the tables.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_occupancy import room_ply  # noqa: E402
from common import CACHE, print_table, write_json  # noqa: E402


def family_dir(splats: int, g: float) -> Path:
    out = CACHE / f"caps_{splats}_{g:g}"
    if not (out / "cover.npz").exists():
        ply = room_ply(splats)
        print(f"building {ply} at {g:g} m into {out}", flush=True)
        subprocess.run([sys.executable, "-m", "polycc", "build", ply, "--voxel", str(g), "--flash-kb", "64",
                        "-o", str(out)], check=True)
    return out


def polytopes(out: Path) -> list[tuple[np.ndarray, np.ndarray]]:
    from polycc.budget.select import _merged_rows
    from polycc.cover.family import CoverFamily

    n = json.loads((out / "manifest.json").read_text())["stats"]["n"]
    return [(_merged_rows(p), np.asarray(p.vertices, np.float64)) for p in CoverFamily.load(out).materialise(n)]


def timed(f, polys) -> tuple[float, list]:
    t = time.perf_counter()
    res = [f(h, v) for h, v in polys]
    return time.perf_counter() - t, res


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--splats", type=int, default=1_500_000, help="splats in the tiled room (default 1.5M)")
    ap.add_argument("--voxel", type=float, default=0.05, help="voxel size g, m (default 0.05)")
    args = ap.parse_args()

    from polycc import native
    from polycc.budget.reduce import MIN_GAMMA, drop_cost, reduce_planes
    from polycc.geometry.halfplanes import drop_volumes, polytope_volume

    out = family_dir(args.splats, args.voxel)
    polys = [(h, v) for h, v in polytopes(out) if len(h) <= native.MAX_PLANES]
    assert native.load() is not None, "the C did not build"
    sizes = np.array([len(h) for h, _ in polys])
    print(f"{len(polys)} polytopes of {sizes.min()}-{sizes.max()} planes (median {int(np.median(sizes))})")

    def qhull(h, v):
        c, vol = v.mean(axis=0), polytope_volume(v)
        return np.array([drop_cost(h, j, c, vol) for j in range(len(h))])

    methods = {"qhull per plane": qhull,
               "numpy triples": lambda h, v: drop_volumes(h, MIN_GAMMA, v.mean(axis=0), polytope_volume(v)),
               "C triples": lambda h, v: native.cap_volumes(h, MIN_GAMMA, v.mean(axis=0), polytope_volume(v))}
    native.cap_volumes(polys[0][0], MIN_GAMMA)  # build before timing
    res, got = {}, {}
    for name, f in methods.items():
        s, got[name] = timed(f, polys)
        res[name] = {"s": s, "us_per_polytope": 1e6 * s / len(polys)}
    ref = got["qhull per plane"]
    vols = [polytope_volume(v) for _, v in polys]
    rows = []
    for name in methods:
        same_inf = all(np.array_equal(np.isinf(a), np.isinf(b)) for a, b in zip(got[name], ref))
        err = max((float(np.max(np.abs(a[np.isfinite(b)] - b[np.isfinite(b)]), initial=0.0)) / vol
                   for a, b, vol in zip(got[name], ref, vols)), default=0.0)
        res[name].update(ratio=res["qhull per plane"]["s"] / res[name]["s"], max_rel_err=err, same_inf=same_inf)
        rows.append([name, res[name]["s"], res[name]["us_per_polytope"], f"{res[name]['ratio']:.1f}x",
                     f"{err:.1e}", "yes" if same_inf else "NO"])
    print_table(f"drop costs of every plane, {len(polys)} polytopes ({args.splats:,} splats, {args.voxel:g} m)",
                ["method", "s", "us / polytope", "speed-up", "max |err| / volume", "same infinite planes"], rows)

    from polycc.budget import reduce as red

    total = sum(len(h) for h, _ in polys)
    greedy, grows, keep = {}, [], red.MAX_PLANES
    for name, limit in (("recomputes by qhull per plane", 0), ("recomputes from the version's C costs", keep)):
        red.MAX_PLANES = limit  # recompute_cost / _Stream read it: 0 sends every recompute to qhull's drop_cost
        t = time.perf_counter()
        r = reduce_planes(polys, total // 2, per_polytope=64)
        greedy[name] = {"s": time.perf_counter() - t, "added_m3": r[1] if r else None}
        grows.append([name, greedy[name]["s"], r[1] if r else float("nan")])
    red.MAX_PLANES = keep
    first = greedy["recomputes by qhull per plane"]["s"]
    for row, g in zip(grows, greedy.values()):
        g["speed_up"] = first / g["s"]
        row.append(f"{g['speed_up']:.1f}x")
    print_table(f"reduce_planes of these polytopes from {total:,} to {total // 2:,} planes (first costs in C)",
                ["greedy", "s", "added volume m^3", "speed-up"], grows)
    write_json("bench_caps", {"splats": args.splats, "voxel_m": args.voxel, "polytopes": len(polys),
                              "planes": {"min": int(sizes.min()), "median": float(np.median(sizes)),
                                         "max": int(sizes.max())},
                              "methods": res, "reduce_half": greedy})


if __name__ == "__main__":
    main()
