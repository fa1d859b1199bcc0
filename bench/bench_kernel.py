"""Cycle benchmark of the on-board barrier kernel on a modelled Cortex-M4F (168 MHz).

Method: the ARM build (firmware flags, -Os, -ffp-contract=off) runs instruction by instruction
in unicorn (Cortex-M4 model); capstone decodes every executed instruction and a documented
Cortex-M4 timing model (ARM DDI 0439 "Cortex-M4 TRM", Table 3-1, and the FPU tables) turns
the trace into a cycle range:

  class                                       low   high
  ALU / MOV / CMP / shift / extend / IT        1     1   (IT: 0 when folded, low bound)
  MUL, UMULL/SMULL/UMLAL/SMLAL                 1     1
  MLA / MLS                                    2     2
  SDIV / UDIV                                  2    12
  LDR / STR / VLDR / VSTR (single)             2     2   (1 when it follows a load/store: pipelined, low)
  LDRD / STRD                                  3     3
  LDM / STM / PUSH / POP / VLDM / VSTM / VPUSH / VPOP   1+N
  branch not taken (incl. CBZ/CBNZ)            1     1
  branch taken, BL/BLX/BX, POP {pc}, LDR pc    +1    +3  pipeline refill
  VADD / VSUB / VMUL / VNMUL / VABS / VNEG / VCMP / VCVT / VMOV / VMRS / VMSR   1   1
  VMLA / VMLS / VNMLA / VNMLS / VFMA / VFMS     3     3
  VDIV / VSQRT                                14    14

Not modelled: flash wait states (the STM32F405 ART accelerator hides them for code; scene data
streamed from flash can add up to 5 cycles per 16-byte line, reported separately as
``flash_extra_us``) and interrupts.

Workloads: synthetic rooms with n in {10, 30, 50, 100, 150} random-hull polytopes (unique
normals), the 150-polytope room padded to 3720 half-planes (what 64 KiB held in format 2),
the same padded to fill 64 KiB in format 3, and 150 hulls of voxel corners (lattice normals,
table capped at 512) for the storage of a PolyMerge-like cover.  Typical: positions along a
closed-loop flight (host kernel, dt = 10 ms) from a start to a goal across the room.  Worst: the
same polytopes moved onto a shell around the query point so that every polytope lies within the
culling distance (none is culled).
Baseline in the same run: bench/bench_kernel_naive.c (every half-plane, libm expf/logf,
plain log-sum-exp).

Usage:  .venv/bin/python bench/bench_kernel.py [--quick]
Writes bench/results/bench_kernel.json and prints a table.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from polycc.geometry.halfplanes import hull_halfplanes  # noqa: E402
from polycc.onboard import barrier as B  # noqa: E402
from polycc.onboard.layout import PackedScene, pack_scene  # noqa: E402
from polycc.sim import kernel_arm  # noqa: E402
from polycc.sim.cortex_m4_model import MHZ, CortexM4Model, Cost, Emulator  # noqa: E402,F401
from polycc.sim.kernel_ffi import HostScene, step_batch  # noqa: E402
from polycc.testing.synthetic import pad_to_planes, random_hull_polytopes, shell_scene  # noqa: E402

BENCH_ELF = "kernel_bench"


def build_bench() -> Path:
    srcs = [REPO / "bench" / "bench_kernel_naive.c", kernel_arm.ARM_DIR / "startup.c",
            kernel_arm.ARM_DIR / "semihost.c"]
    return kernel_arm.build(BENCH_ELF, srcs, extra_headers=[kernel_arm.ARM_DIR / "semihost.h"], libs=["-lm"])


def room_scene(n: int, seed: int, fill_bytes: int | None = None, planes: int | None = None) -> PackedScene:
    """Random hulls (unique normals: the table holds one normal per plane).  ``fill_bytes``/``planes``
    pad with redundant half-planes (duplicates of a face: no new normals) up to that size."""
    rng = np.random.default_rng(seed)
    polys = random_hull_polytopes(rng, n, points=(8, 14))
    sc = pack_scene(polys)
    if fill_bytes:  # add redundant half-planes until the flash image reaches fill_bytes
        planes = sc.n_planes + (fill_bytes - sc.flash_bytes()) // 4
    if planes:
        sc = pack_scene(pad_to_planes(polys, planes), merge_duplicates=False)
    return sc


def voxel_scene(n: int, seed: int, max_normals: int | None = 512, vox: float = 0.05) -> PackedScene:
    """Hulls of voxel corners (a PolyMerge-like cover: lattice normals), the normal table capped."""
    rng = np.random.default_rng(seed)
    corners = np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)], float)
    hs, vs = [], []
    for _ in range(n):
        c = rng.uniform(0, 1, 3) * np.array([10.0, 10.0, 3.0])
        pts = np.round((c + rng.normal(size=(int(rng.integers(4, 12)), 3)) * rng.uniform(0.05, 0.4, 3)) / vox)
        allp = (pts[:, None, :] + corners[None]).reshape(-1, 3) * vox
        hs.append(hull_halfplanes(allp))
        vs.append(allp)
    return pack_scene(hs, vs, max_normals=max_normals)


def format2_bytes(sc: PackedScene) -> int:
    """Flash bytes the same polytopes took in format 2 (16 B/plane, 36 B per polytope and cluster)."""
    return 36 + 16 * sc.n_planes + 36 * sc.n_polys + 36 * sc.n_clusters


def flight_path(sc: PackedScene, params: B.Params, n_samples: int, seed: int) -> np.ndarray:
    """Positions along a closed-loop flight of the host kernel from a free start to a free goal."""
    rng = np.random.default_rng(seed)
    hs = HostScene(sc)
    for _ in range(100):
        cand = rng.uniform([0.5, 0.5, 0.3], [9.5, 9.5, 2.7], (64, 3)).astype(np.float32)
        psi = step_batch(hs, params, cand, cand)["psi"]
        free = cand[psi > 0.3]
        if len(free) >= 2:
            a, b = free[np.argmax(np.linalg.norm(free - free[0], axis=1))], free[0]
            break
    else:
        raise RuntimeError("no free start/goal pair found in the benchmark room")
    x, path = a.copy(), [a.copy()]
    for _ in range(3000):
        out = step_batch(hs, params, x[None], b[None])
        x = (x + 0.01 * out["u"][0]).astype(np.float32)
        path.append(x.copy())
        if np.linalg.norm(x - b) < 0.05:
            break
    path = np.array(path)
    return path[np.linspace(0, len(path) - 1, n_samples).astype(int)]


def us(cycles: float) -> float:
    return cycles / MHZ


def bench_scene(emu: Emulator, name: str, sc: PackedScene, params: B.Params, n_path: int, seed: int) -> dict:
    path = flight_path(sc, params, n_path, seed)
    goal = path[-1]
    emu.load_scene(sc, params)
    typ, naive = [], []
    ref = B.step(sc, params, path, np.broadcast_to(goal, path.shape))
    for i, x in enumerate(path):
        c, out = emu.call_step("polycc_step", x, goal)
        assert out["psi"][0].view(np.uint32) == ref["psi"][i].view(np.uint32), "emulated psi differs from reference"
        typ.append(c)
        naive.append(emu.call_step("naive_step", x, goal)[0])
    shell = shell_scene(sc)
    emu.load_scene(shell, params)
    rng = np.random.default_rng(seed)
    worst = [emu.call_step("polycc_step", rng.normal(size=3) * 0.005, goal)[0] for _ in range(3)]
    evaluated = _evaluated_count(shell, params)

    def agg(costs, f):
        return [f([getattr(c, a) for c in costs]) for a in ("instructions", "low", "high", "scene_lines")]

    t_i, t_lo, t_hi, t_l = agg(typ, np.mean)
    tm_i, tm_lo, tm_hi, _ = agg(typ, np.max)
    w_i, w_lo, w_hi, w_l = agg(worst, np.max)
    n_i, n_lo, n_hi, _ = agg(naive, np.mean)
    return {
        "scene": name, "n_polys": sc.n_polys, "n_planes": sc.n_planes, "n_normals": sc.n_normals,
        "flash_bytes": sc.flash_bytes(), "bytes_per_plane": sc.flash_bytes() / sc.n_planes,
        "format2_bytes_per_plane": format2_bytes(sc) / sc.n_planes,
        "typical_instr": t_i, "typical_us": [us(t_lo), us(t_hi)], "typical_max_us": [us(tm_lo), us(tm_hi)],
        "worst_instr": w_i, "worst_us": [us(w_lo), us(w_hi)], "worst_polys_evaluated": evaluated,
        "naive_instr": n_i, "naive_us": [us(n_lo), us(n_hi)],
        "speedup_typical": [n_lo / t_lo, n_hi / t_hi],
        "flash_extra_us": {"typical": us(5 * t_l), "worst": us(5 * w_l)},
        "path_samples": len(path),
    }


def _evaluated_count(sc: PackedScene, params: B.Params) -> int:
    """Polytopes evaluated (not culled) at the origin, from the Python reference (same logic)."""
    stats: dict = {}
    B.barrier(sc, params, np.zeros((1, 3)), stats=stats)
    return int(stats["evaluated"][0])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="fewer path samples (CI smoke run)")
    ap.add_argument("--out", type=Path, default=REPO / "bench" / "results" / "bench_kernel.json")
    args = ap.parse_args(argv)
    t0 = time.time()
    bdir = build_bench()
    elf = bdir / f"{BENCH_ELF}.elf"
    emu = Emulator(elf)
    params = B.Params(kappa=100.0, radius=0.05, beta=1.0, c_clf=1.0, v_max=1.0)
    n_path = 6 if args.quick else 20
    rows = []
    for n in (10, 30, 50, 100, 150):
        rows.append(bench_scene(emu, f"room{n}", room_scene(n, seed=n), params, n_path, seed=n))
    rows.append(bench_scene(emu, "planes3720", room_scene(150, seed=7, planes=3720), params, n_path, seed=7))
    rows.append(bench_scene(emu, "fill64k", room_scene(150, seed=7, fill_bytes=65536), params, n_path, seed=7))
    rows.append(bench_scene(emu, "vox150", voxel_scene(150, seed=5), params, n_path, seed=5))
    test_dir = kernel_arm.test_program().parent
    stack, chain = kernel_arm.worst_stack(test_dir)
    size = kernel_arm.size_of(test_dir / "polycc_kernel.o")
    result = {"mhz": MHZ, "params": params.__dict__, "rows": rows, "stack_bytes": stack, "stack_chain": chain,
              "kernel_size": size, "elf": str(elf), "seconds": time.time() - t0}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1, default=float))
    print(table(result))
    return 0


def table(res: dict) -> str:
    def rng(v):
        return f"{v[0]:.1f}-{v[1]:.1f}"

    lines = [f"Cortex-M4F @ {res['mhz']:.0f} MHz, kappa=100 (modelled cycle range low-high; see bench_kernel.py)",
             "| scene | polys | half-planes | normals | flash B | B/half-plane (fmt 2) | typical instr | typical us | "
             "typical max us | worst instr |"
             " worst us (polys evaluated) | naive instr | naive us | speed-up (typical) |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in res["rows"]:
        lines.append(
            f"| {r['scene']} | {r['n_polys']} | {r['n_planes']} | {r['n_normals']} | {r['flash_bytes']} |"
            f" {r['bytes_per_plane']:.2f} ({r['format2_bytes_per_plane']:.2f}) | {r['typical_instr']:.0f} |"
            f" {rng(r['typical_us'])} | {rng(r['typical_max_us'])} | {r['worst_instr']:.0f} |"
            f" {rng(r['worst_us'])} ({r['worst_polys_evaluated']}) |"
            f" {r['naive_instr']:.0f} | {rng(r['naive_us'])} | "
            f"{r['speedup_typical'][0]:.0f}x-{r['speedup_typical'][1]:.0f}x |")
    s = res["kernel_size"]
    lines.append(f"kernel stack (worst, -fstack-usage): {res['stack_bytes']} B ({' -> '.join(res['stack_chain'])}); "
                 f"arm-none-eabi-size polycc_kernel.o: text={s['text']} data={s['data']} bss={s['bss']}")
    lines.append("flash data wait states not modelled; upper estimate of their cost (us), typical/worst: " + ", ".join(
        f"{r['scene']} {r['flash_extra_us']['typical']:.1f}/{r['flash_extra_us']['worst']:.1f}" for r in res["rows"]))
    return "\n".join(lines)


if __name__ == "__main__":
    sys.exit(main())
