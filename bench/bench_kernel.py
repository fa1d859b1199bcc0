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
import struct
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from polycc.geometry.halfplanes import hull_halfplanes  # noqa: E402
from polycc.onboard import barrier as B  # noqa: E402
from polycc.onboard.layout import SCENE_FORMAT, PackedScene, pack_scene  # noqa: E402
from polycc.sim import kernel_arm  # noqa: E402
from polycc.sim.kernel_ffi import OUT_DTYPE, HostScene, step_batch  # noqa: E402
from polycc.testing.synthetic import pad_to_planes, random_hull_polytopes  # noqa: E402

MHZ = 168.0
FLASH_BASE, FLASH_SIZE = 0x08000000, 0x00100000
SCENE_BASE = 0x08080000  # scene arrays are placed in flash, as the generated header would be
RAM_BASE, RAM_SIZE = 0x20000000, 0x00020000
IO_BASE = 0x2001C000  # scene root, params, x, goal, out
STOP = 0x0807FFF0  # return address: emulation stops here
BENCH_ELF = "kernel_bench"


def build_bench() -> Path:
    srcs = [REPO / "bench" / "bench_kernel_naive.c", kernel_arm.ARM_DIR / "startup.c",
            kernel_arm.ARM_DIR / "semihost.c"]
    return kernel_arm.build(BENCH_ELF, srcs, extra_headers=[kernel_arm.ARM_DIR / "semihost.h"], libs=["-lm"])


def symbols(elf: Path) -> dict[str, int]:
    out = subprocess.run(["arm-none-eabi-nm", str(elf)], capture_output=True, text=True, check=True).stdout
    return {p[2]: int(p[0], 16) for p in (line.split() for line in out.splitlines()) if len(p) == 3}


def load_segments(elf: Path) -> list[tuple[int, bytes, int]]:
    """(vaddr, file bytes, memsz) of each PT_LOAD segment of a 32-bit little-endian ELF."""
    data = elf.read_bytes()
    e_phoff, = struct.unpack_from("<I", data, 28)
    e_phentsize, e_phnum = struct.unpack_from("<HH", data, 42)
    segs = []
    for i in range(e_phnum):
        p_type, p_off, p_vaddr, _, p_filesz, p_memsz = struct.unpack_from("<IIIIII", data, e_phoff + i * e_phentsize)
        if p_type == 1:
            segs.append((p_vaddr, data[p_off:p_off + p_filesz], p_memsz))
    return segs


@dataclass
class Cost:
    instructions: int = 0
    low: int = 0
    high: int = 0
    scene_lines: int = 0  # distinct 16-byte flash lines of scene data read


class CortexM4Model:
    """Cycle model of one executed instruction stream (see the module docstring)."""

    ALU1 = {"vadd", "vsub", "vmul", "vnmul", "vabs", "vneg", "vcmp", "vcmpe", "vcvt", "vmov", "vmrs", "vmsr"}
    FMA3 = {"vmla", "vmls", "vnmla", "vnmls", "vfma", "vfms", "vfnma", "vfnms"}

    def __init__(self):
        self.cache: dict[int, tuple[str, int, int, int, bool, bool, bool]] = {}
        import capstone

        self.md = capstone.Cs(capstone.CS_ARCH_ARM, capstone.CS_MODE_THUMB | capstone.CS_MODE_MCLASS)

    def decode(self, code: bytes, addr: int):
        ins = next(self.md.disasm(code, addr, 1))
        mn = ins.mnemonic.split(".")[0]
        base = mn.rstrip("s") if mn not in ("vabs", "vmrs", "vmsr", "bls", "blx", "bx") else mn
        for cond in ("eq", "ne", "cs", "hs", "cc", "lo", "mi", "pl", "vs", "vc", "hi", "ls", "ge", "lt", "gt", "le",
                     "al"):
            if len(base) > 2 and base.endswith(cond) and base[:-2] in ("b", "bx", "bl", "blx"):
                base = base[:-2]
        ops = ins.op_str
        writes_pc = ("pc" in ops.split(",")[0] and base in ("mov", "ldr", "add")) or (base == "pop" and "pc" in ops)
        nregs = ops.count(",") + 1 if "{" in ops else 1
        if "{" in ops and "-" in ops:  # vpush {d8-d15}: count the range
            inner = ops[ops.index("{") + 1 : ops.index("}")]
            nregs = 0
            for part in inner.split(","):
                part = part.strip()
                if "-" in part:
                    a, b = part.split("-")
                    nregs += int(b[1:]) - int(a[1:]) + 1
                else:
                    nregs += 1
            if inner.strip().startswith("d"):
                nregs *= 2
        lo = hi = 1
        is_ls = False
        is_branch = base in ("b", "bl", "blx", "bx", "cbz", "cbnz") or writes_pc
        if base in ("ldr", "ldrb", "ldrh", "ldrsb", "ldrsh", "str", "strb", "strh", "vldr", "vstr", "ldrex", "strex"):
            lo = hi = 2
            is_ls = True
        elif base in ("ldrd", "strd"):
            lo = hi = 3
        elif base in ("ldm", "ldmia", "ldmdb", "stm", "stmia", "stmdb", "push", "pop", "vldm", "vldmia", "vstm",
                      "vstmia", "vstmdb", "vpush", "vpop"):
            lo = hi = 1 + nregs
        elif base in ("sdiv", "udiv"):
            lo, hi = 2, 12
        elif base in ("mla", "mls"):
            lo = hi = 2
        elif base in ("vdiv", "vsqrt"):
            lo = hi = 14
        elif base in self.FMA3:
            lo = hi = 3
        elif base == "it" or base.startswith("it"):
            lo, hi = 0, 1
        if base in ("bl", "blx") or (base == "bx") or (base == "pop" and "pc" in ops):
            always_taken = True
        else:
            always_taken = False
        return base, ins.size, lo, hi, is_ls, is_branch, always_taken

    def run(self, uc, begin: int, until: int, scene_range: tuple[int, int]) -> Cost:
        from unicorn import UC_HOOK_CODE, UC_HOOK_MEM_READ

        cost = Cost()
        state = {"prev": None, "prev_ls": False}
        lines: set[int] = set()

        def on_code(uc_, addr, size, _):
            info = self.cache.get(addr)
            if info is None:
                info = self.decode(bytes(uc_.mem_read(addr, size)), addr)
                self.cache[addr] = info
            prev = state["prev"]
            if prev is not None:  # charge the previous instruction now that we know where it went
                p_addr, (base, psz, lo, hi, is_ls, is_branch, always) = prev
                cost.instructions += 1
                if is_ls and state["prev_ls"]:
                    lo = 1
                if is_branch and (always or addr != p_addr + psz):
                    lo, hi = lo + 1, hi + 3
                cost.low += lo
                cost.high += hi
                state["prev_ls"] = is_ls
            state["prev"] = (addr, info)

        def on_read(uc_, access, addr, size, value, _):
            if scene_range[0] <= addr < scene_range[1]:
                lines.add(addr >> 4)

        h1 = uc.hook_add(UC_HOOK_CODE, on_code)
        h2 = uc.hook_add(UC_HOOK_MEM_READ, on_read)
        try:
            uc.emu_start(begin | 1, until)
        finally:
            uc.hook_del(h1)
            uc.hook_del(h2)
        if state["prev"] is not None:  # the final return (bx lr / pop {pc})
            _, (base, _, lo, hi, *_rest) = state["prev"]
            cost.instructions += 1
            cost.low += lo + 1
            cost.high += hi + 3
        cost.scene_lines = len(lines)
        return cost


class Emulator:
    def __init__(self, elf: Path):
        from unicorn import UC_ARCH_ARM, UC_MODE_MCLASS, UC_MODE_THUMB, Uc
        from unicorn import arm_const as U

        self.U = U
        self.uc = Uc(UC_ARCH_ARM, UC_MODE_THUMB | UC_MODE_MCLASS)
        try:
            self.uc.ctl_set_cpu_model(U.UC_CPU_ARM_CORTEX_M4)
        except Exception:  # older unicorn: default M-class CPU
            pass
        self.uc.mem_map(FLASH_BASE, FLASH_SIZE)
        self.uc.mem_map(RAM_BASE, RAM_SIZE)
        for vaddr, blob, memsz in load_segments(elf):
            self.uc.mem_write(vaddr, blob + bytes(memsz - len(blob)))
        self.sym = symbols(elf)
        self.uc.mem_write(STOP, b"\x00\xbf\x00\xbf")  # nop; nop
        self.model = CortexM4Model()
        self.scene_range = (SCENE_BASE, SCENE_BASE)

    def load_scene(self, sc: PackedScene, params: B.Params) -> None:
        parts = [sc.clusters.tobytes(), sc.polys_raw.tobytes(), sc.planes.tobytes(), sc.normals.tobytes()]
        self.uc.mem_write(SCENE_BASE, b"".join(parts))
        addr = np.cumsum([SCENE_BASE] + [len(p) for p in parts])
        self.scene_range = (SCENE_BASE, int(addr[-1]))
        root = struct.pack("<IIIIIfffIIII", SCENE_FORMAT, sc.n_clusters, sc.n_polys, sc.n_planes, sc.n_normals,
                           float(sc.quantum), float(sc.coord_bound), float(sc.log_lmax), *(int(a) for a in addr[:4]))
        self.uc.mem_write(IO_BASE, root)
        self.uc.mem_write(IO_BASE + 0x40, np.array(params.f32(), np.float32).tobytes())

    def call_step(self, fn: str, x, goal) -> tuple[Cost, np.ndarray]:
        U, uc = self.U, self.uc
        px, pg, po = IO_BASE + 0x80, IO_BASE + 0x90, IO_BASE + 0xA0
        uc.mem_write(px, np.asarray(x, np.float32).tobytes())
        uc.mem_write(pg, np.asarray(goal, np.float32).tobytes())
        sp = IO_BASE - 0x100
        uc.mem_write(sp, struct.pack("<I", po))  # 5th argument on the stack
        uc.reg_write(U.UC_ARM_REG_SP, sp)
        for reg, val in zip((U.UC_ARM_REG_R0, U.UC_ARM_REG_R1, U.UC_ARM_REG_R2, U.UC_ARM_REG_R3),
                            (IO_BASE, IO_BASE + 0x40, px, pg)):
            uc.reg_write(reg, val)
        uc.reg_write(U.UC_ARM_REG_LR, STOP | 1)
        cost = self.model.run(uc, self.sym[fn], STOP, self.scene_range)
        out = np.frombuffer(bytes(uc.mem_read(po, OUT_DTYPE.itemsize)), OUT_DTYPE)
        return cost, out


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


def shell_scene(sc: PackedScene, dist: float = 0.5) -> PackedScene:
    """The same polytopes translated onto a shell around the origin so that max_l g_kl(0) = dist
    for every k: all lie within the culling distance of the origin."""
    k = sc.n_polys
    i = np.arange(k) + 0.5
    phi, th = np.arccos(1 - 2 * i / k), np.pi * (1 + 5 ** 0.5) * i
    dirs = np.c_[np.cos(th) * np.sin(phi), np.sin(th) * np.sin(phi), np.cos(phi)]
    out = []
    for h, u, P in zip(sc.polytopes(), dirs, sc.polys):
        h = h.astype(np.float64)
        c = np.array([P["cx"], P["cy"], P["cz"]], np.float64)

        def phi0(s):  # max_l g_l(0) after moving the centre to s * u
            return np.max(-(h[:, 3] + h[:, :3] @ (s * u - c)))

        lo, hi = 0.0, 50.0
        for _ in range(60):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if phi0(mid) < dist else (lo, mid)
        t = hi * u - c
        out.append(np.c_[h[:, :3], h[:, 3] + h[:, :3] @ t])
    return pack_scene(out, merge_duplicates=False)


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
