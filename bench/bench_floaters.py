"""The splat-level floater filter (--drop-isolated R,N) against the voxel-count filter (--min-splats-per-voxel M)
and no filter, on the real captures. Prints a table, writes bench/results/bench_floaters.json.

Per scene and filter: splats dropped or left partly uncovered, occupied voxels removed, the certified largest
depth of a splat outside the cover (metres; branch and bound to 1 mm: polycc.occupancy.floaters), and the
filter's time as a ratio to voxelizing without a filter, measured side by side in one run.

    python bench/bench_floaters.py [--quick]
"""

from __future__ import annotations

import sys
import time

import numpy as np
from common import print_table, write_json

from polycc.occupancy.exact import pack_keys, unpack_keys, voxelize
from polycc.occupancy.floaters import floater_loss
from polycc.scene.load import SceneOptions, load_scene
from polycc.scene.survey import isolated_mask
from polycc.testing.files import SCENES  # ../shared/scenes, or POLYCC_SHARED_SCENES

G = 0.05
# name, file, scale (metres), and the real content: which are captures with true floaters
SCENE_LIST = [("plant (phone capture)", "plant.splat", 1.0), ("plant + 300 injected floaters", "plant.splat", 1.0),
              ("donut (trained, Mip-Splatting)", "donut_fused.ply", 4.0),
              ("tree (mesh -> splats)", "tree_100k.splat", 2.0)]
VOXEL_M = (5, 30)  # 30 = the paper's hardware setting
SPLAT_RN = ((2 * G, 20), (4 * G, 50))


def _voxel_filter(ell, m, base_s):
    t = time.perf_counter()
    occ = voxelize(ell, G, m)
    loss = floater_loss(ell, occ.indices, occ.removed, G, occ.origin) if len(occ.removed) else None
    dt = time.perf_counter() - t
    return {"filter": f"voxel M={m}", "splats_dropped": 0,
            "splats_not_covered": 0 if loss is None else loss["splats_not_fully_covered"],
            "voxels_removed": int(len(occ.removed)),
            "max_depth_outside_m": 0.0 if loss is None else loss["max_depth_outside_m"],
            "time_ratio": dt / base_s}


def _splat_filter(ell, rn, base_occ, base_s):
    t = time.perf_counter()
    drop, groups = isolated_mask(ell.centers, *rn)
    kept = voxelize(ell.subset(~drop), G)
    dt = time.perf_counter() - t
    removed_keys = np.setdiff1d(pack_keys(base_occ.indices), pack_keys(kept.indices))
    depth = 0.0
    if drop.any() and len(removed_keys):
        loss = floater_loss(ell.subset(drop), kept.indices, unpack_keys(removed_keys), G, kept.origin)
        depth = loss["max_depth_outside_m"]
    return {"filter": f"splat R={rn[0]:g},N={rn[1]}", "splats_dropped": int(drop.sum()),
            "splats_not_covered": int(drop.sum()), "voxels_removed": int(len(removed_keys)),
            "max_depth_outside_m": depth, "time_ratio": dt / base_s, "groups": len(groups)}


def _with_floaters(ell, n=300, seed=0):
    """The scene plus ``n`` injected floaters: small splats in 30 clumps 0.3-1.5 m outside its bounds."""
    from polycc.scene.ellipsoids import Ellipsoids

    rng = np.random.default_rng(seed)
    lo, hi = ell.bounds()
    src = ell.subset(rng.choice(len(ell), n, replace=False))
    clump = rng.normal(size=(30, 3))
    clump /= np.linalg.norm(clump, axis=1, keepdims=True)
    mid, rad = 0.5 * (lo + hi), 0.5 * float(np.linalg.norm(hi - lo))
    c = mid + clump * (rad + rng.uniform(0.3, 1.5, (30, 1)))
    src.centers = c[rng.integers(0, 30, n)] + rng.normal(0, 0.01, (n, 3))
    return Ellipsoids.concatenate([ell, src]), np.r_[np.zeros(len(ell), bool), np.ones(n, bool)]


def main() -> int:
    quick = "--quick" in sys.argv
    rows, out = [], []
    for name, fname, scale in SCENE_LIST[:1] if quick else SCENE_LIST:
        ell = load_scene(SCENES / fname, SceneOptions(scale=scale)).ellipsoids
        if name.startswith("plant +"):
            ell, _ = _with_floaters(ell)
        t = time.perf_counter()
        base = voxelize(ell, G)
        base_s = time.perf_counter() - t
        res = [{"filter": "none", "splats_dropped": 0, "splats_not_covered": 0, "voxels_removed": 0,
                "max_depth_outside_m": 0.0, "time_ratio": 1.0}]
        res += [_voxel_filter(ell, m, base_s) for m in VOXEL_M]
        res += [_splat_filter(ell, rn, base, base_s) for rn in SPLAT_RN]
        for r in res:
            rows.append([name, r["filter"], r["splats_dropped"], r["splats_not_covered"], r["voxels_removed"],
                         f"{100 * r['voxels_removed'] / len(base):.2f} %", r["max_depth_outside_m"], r["time_ratio"]])
        out.append({"scene": name, "file": fname, "scale": scale, "voxel_m": G, "splats": len(ell),
                    "voxels": len(base), "results": res})
    print_table(f"floater filters at {G} m voxels (time: ratio to voxelizing with no filter, same run)",
                ["scene", "filter", "splats dropped", "splats not fully covered", "voxels removed", "of V+",
                 "max depth outside cover (m)", "time ratio"], rows)
    write_json("bench_floaters", {"voxel_m": G, "scenes": out})
    return 0


if __name__ == "__main__":
    sys.exit(main())
