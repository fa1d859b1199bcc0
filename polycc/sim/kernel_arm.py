"""Cross-build the kernel for the Crazyflie's Cortex-M4F and run it in QEMU (netduinoplus2).

The kernel sources are compiled with the firmware's flags plus ``-ffp-contract=off``; the
test program (``polycc/sim/arm/``) exchanges data with the host through semihosting files.  Builds are
cached in the build cache under ``arm/<name>-<hash>/`` and published atomically (``os.replace`` of a finished
temporary directory), so concurrent pytest workers are safe.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import subprocess
import tempfile
from pathlib import Path

import numpy as np

from polycc import resources
from polycc.errors import PolyccError
from polycc.onboard.barrier import Params
from polycc.onboard.layout import PackedScene
from polycc.sim.kernel_ffi import KERNEL_HEADERS, KERNEL_SOURCES, OUT_DTYPE, SRC

ARM_DIR = resources.arm_harness()
CC = "arm-none-eabi-gcc"
QEMU = "qemu-system-arm"
SIZE = "arm-none-eabi-size"
ARM_CFLAGS = ["-mcpu=cortex-m4", "-mthumb", "-mfloat-abi=hard", "-mfpu=fpv4-sp-d16", "-Os", "-std=gnu11", "-Wall",
              "-Wdouble-promotion", "-Werror", "-fno-math-errno", "-ffp-contract=off", "-ffunction-sections",
              "-fdata-sections"]
# The kernel itself also passes a stricter set than the firmware's.
KERNEL_EXTRA = ["-Wextra", "-Wconversion", "-fstack-usage"]
LDFLAGS = ["-nostartfiles", "--specs=nano.specs", "-Wl,--gc-sections"]


def missing_tools() -> list[str]:
    return [t for t in (CC, QEMU, SIZE) if shutil.which(t) is None]


def _hash(paths: list[Path], flags: list[str]) -> str:
    h = hashlib.sha256()
    for p in sorted(paths):
        h.update(p.name.encode())
        h.update(p.read_bytes())
    h.update(" ".join(flags).encode())
    return h.hexdigest()[:16]


def build(name: str, app_sources: list[Path], *, extra_headers: list[Path] = (), libs: list[str] = ()) -> Path:
    """Build an ELF of the kernel plus ``app_sources``; returns its directory (``<name>.elf``,
    ``*.su`` stack-usage files, ``polycc_kernel.o``)."""
    if missing_tools():
        raise PolyccError(f"missing {', '.join(missing_tools())}; apt-get install gcc-arm-none-eabi "
                          "libnewlib-arm-none-eabi qemu-system-arm")
    inputs = list(KERNEL_SOURCES) + list(KERNEL_HEADERS) + list(app_sources) + list(extra_headers) + [
        ARM_DIR / "link.ld"]
    out = resources.cache_dir("arm") / f"{name}-{_hash(inputs, ARM_CFLAGS + KERNEL_EXTRA + LDFLAGS + list(libs))}"
    if (out / f"{name}.elf").exists():
        return out
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f"{name}-", dir=out.parent))
    try:
        objs = []
        for src in list(KERNEL_SOURCES) + list(app_sources):
            obj = tmp / (src.stem + ".o")
            flags = ARM_CFLAGS + (KERNEL_EXTRA if src in KERNEL_SOURCES else [])
            _run([CC, *flags, f"-I{SRC}", f"-I{ARM_DIR}", "-c", str(src.resolve()), "-o", str(obj)], cwd=tmp)
            objs.append(str(obj))
        _run([CC, *ARM_CFLAGS, *LDFLAGS, "-T", str(ARM_DIR / "link.ld"), *objs, *libs, "-lc", "-lgcc", "-o",
              str(tmp / f"{name}.elf")], cwd=tmp)
        try:
            os.replace(tmp, out)
        except OSError:  # another worker published the same build first
            pass
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return out


def _run(cmd: list[str], cwd: Path, timeout: float = 120.0) -> subprocess.CompletedProcess:
    r = subprocess.run(cmd, cwd=cwd, capture_output=True, text=True, timeout=timeout)
    if r.returncode != 0:
        raise PolyccError(f"{Path(cmd[0]).name} failed ({r.returncode}): {(r.stderr or r.stdout).strip()}")
    return r


def test_program() -> Path:
    """The semihosting bit-exactness program (polycc/sim/arm/main.c); returns the ELF path."""
    srcs = [ARM_DIR / "main.c", ARM_DIR / "startup.c", ARM_DIR / "semihost.c"]
    heads = [ARM_DIR / "semihost.h", ARM_DIR / "scene_image.h"]
    return build("kernel_test", srcs, extra_headers=heads) / "kernel_test.elf"


def run_qemu(elf: Path, scene: PackedScene, params: Params, x: np.ndarray, goal: np.ndarray,
             timeout: float = 600.0) -> np.ndarray:
    """Run ``polycc_step`` for every state inside QEMU; returns OUT_DTYPE records."""
    x = np.asarray(x, np.float32).reshape(-1, 3)
    goal = np.broadcast_to(np.asarray(goal, np.float32).reshape(-1, 3), x.shape)
    with tempfile.TemporaryDirectory(prefix="polycc-qemu-") as d:
        d = Path(d)
        (d / "scene.bin").write_bytes(scene.to_bytes())
        head = np.array(params.f32(), np.float32).tobytes() + np.uint32(len(x)).tobytes()
        (d / "states.bin").write_bytes(head + np.ascontiguousarray(np.c_[x, goal], np.float32).tobytes())
        cmd = [QEMU, "-M", "netduinoplus2", "-nographic", "-monitor", "none", "-serial", "none",
               "-semihosting-config", "enable=on,target=native", "-kernel", str(elf)]
        r = subprocess.run(cmd, cwd=d, capture_output=True, text=True, timeout=timeout)
        if r.returncode != 0:
            raise PolyccError(f"qemu run failed (exit {r.returncode}): {(r.stdout + r.stderr).strip()[:300]}")
        return np.frombuffer((d / "out.bin").read_bytes(), OUT_DTYPE).copy()


def stack_usage(build_dir: Path) -> dict[str, tuple[int, str]]:
    """Per-function stack bytes from GCC's ``-fstack-usage`` output of the kernel object."""
    res = {}
    for line in (build_dir / "polycc_kernel.su").read_text().splitlines():
        loc, size, kind = line.split("\t")
        res[loc.rsplit(":", 1)[-1]] = (int(size), kind)
    return res


def size_of(path: Path) -> dict[str, int]:
    """``arm-none-eabi-size`` text/data/bss of an object or ELF."""
    r = _run([SIZE, str(path)], cwd=path.parent)
    text, data, bss = (int(v) for v in r.stdout.splitlines()[1].split()[:3])
    return {"text": text, "data": data, "bss": bss}


def call_graph(obj: Path) -> dict[str, set[str]]:
    """Direct calls per function of an object file (from its BL relocations)."""
    r = _run(["arm-none-eabi-objdump", "-dr", str(obj)], cwd=obj.parent)
    graph: dict[str, set[str]] = {}
    fn = None
    for line in r.stdout.splitlines():
        line = line.strip()
        if line.endswith(">:"):
            fn = line.split("<", 1)[1][:-2]
            graph.setdefault(fn, set())
        elif fn and ("R_ARM_THM_CALL" in line or "R_ARM_THM_JUMP24" in line):
            graph[fn].add(line.split()[-1])
    return graph


def worst_stack(build_dir: Path, root: str = "polycc_step") -> tuple[int, list[str]]:
    """Worst-case stack bytes of ``root`` over the kernel's static call graph (-fstack-usage).

    Raises if a frame is dynamic or a callee lies outside the kernel object."""
    su = stack_usage(build_dir)
    graph = call_graph(build_dir / "polycc_kernel.o")

    def walk(f: str) -> tuple[int, list[str]]:
        if f not in su:
            raise PolyccError(f"{f} is called by the kernel but has no stack-usage entry (external call)")
        size, kind = su[f]
        if kind != "static":
            raise PolyccError(f"{f} has a {kind} stack frame")
        best = (0, [])
        for g in sorted(graph.get(f, ())):
            best = max(best, walk(g))
        return size + best[0], [f] + best[1]

    return walk(root)
