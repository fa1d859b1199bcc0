"""A cycle model of the Cortex-M4F (168 MHz) running the ARM build of the kernel instruction by
instruction: unicorn executes, capstone decodes, and the documented Cortex-M4 timing table
(ARM DDI 0439, Table 3-1, and the FPU tables; see bench/bench_kernel.py) turns the trace into a
cycle range [low, high].  Used by bench/bench_kernel.py, bench/bench_index.py and the index's bound
test.  Needs the bench extras (unicorn, capstone).
"""

from __future__ import annotations

import struct
import subprocess
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from polycc.onboard import barrier as B
from polycc.onboard.layout import INDEX_DTYPE_FIELDS, INDEX_HEADER, SCENE_FORMAT, PackedScene
from polycc.sim.kernel_ffi import OUT_DTYPE

MHZ = 168.0
FLASH_BASE, FLASH_SIZE = 0x08000000, 0x00100000
SCENE_BASE = 0x08080000  # scene arrays are placed in flash, as the generated header would be
RAM_BASE, RAM_SIZE = 0x20000000, 0x00020000
IO_BASE = 0x2001C000  # scene root, params, x, goal, out
STOP = 0x0807FFF0  # return address: emulation stops here


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
        """Scene arrays into flash at SCENE_BASE (as a generated header would place them), the root
        record (and the spatial index record, if any) and the params into RAM."""
        parts = [sc.clusters.tobytes(), sc.polys_raw.tobytes(), sc.planes.tobytes(), sc.normals.tobytes()]
        ix = sc.index
        if ix is not None:
            for arr in ix.arrays():
                b = np.asarray(arr, "<u2").tobytes()
                parts.append(b + bytes(-len(b) % 4))
        self.uc.mem_write(SCENE_BASE, b"".join(parts))
        addr = np.cumsum([SCENE_BASE] + [len(p) for p in parts])
        self.scene_range = (SCENE_BASE, int(addr[-1]))
        index_ptr = 0
        if ix is not None:
            r = ix.record()
            index_ptr = IO_BASE + 0x200
            self.uc.mem_write(index_ptr, INDEX_HEADER.pack(*(r[k] for k in INDEX_DTYPE_FIELDS))
                              + struct.pack("<IIIII", *(int(a) for a in addr[4:9])))
        root = struct.pack("<IIIIIfffIIIII", SCENE_FORMAT, sc.n_clusters, sc.n_polys, sc.n_planes, sc.n_normals,
                           float(sc.quantum), float(sc.coord_bound), float(sc.log_lmax), *(int(a) for a in addr[:4]),
                           index_ptr)
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
