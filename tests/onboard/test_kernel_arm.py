"""Cortex-M4 build facts of the kernel: strict warnings, stack use, code size."""

from __future__ import annotations

import subprocess

import pytest

from polycc.sim.kernel_ffi import SRC
from polycc.testing.bitexact import arm_or_skip

STRICT = ["-std=c99", "-Wall", "-Wextra", "-Wdouble-promotion", "-Wconversion", "-Werror", "-ffp-contract=off",
          "-fno-math-errno", "-pedantic"]


@pytest.mark.parametrize("opt", ["-O0", "-O2", "-Os"])
def test_kernel_compiles_warning_free_on_host(tmp_path, opt):
    for src in ("polycc_kernel.c", "polycc_swarm.c"):
        r = subprocess.run(["gcc", *STRICT, opt, "-c", str(SRC / src), "-o", str(tmp_path / "k.o")],
                           capture_output=True, text=True)
        assert r.returncode == 0, r.stderr


@pytest.mark.arm
def test_kernel_compiles_warning_free_for_cortex_m4(tmp_path):
    kernel_arm = arm_or_skip()
    r = subprocess.run([kernel_arm.CC, "-mcpu=cortex-m4", "-mthumb", "-mfloat-abi=hard", "-mfpu=fpv4-sp-d16", "-Os",
                        *STRICT, "-c", str(SRC / "polycc_kernel.c"), "-o", str(tmp_path / "k.o")],
                       capture_output=True, text=True)
    assert r.returncode == 0, r.stderr


@pytest.mark.arm
def test_stack_usage_at_most_512_bytes():
    kernel_arm = arm_or_skip()
    build_dir = kernel_arm.test_program().parent
    total, path = kernel_arm.worst_stack(build_dir)
    assert total <= 512, f"worst-case kernel stack {total} B along {' -> '.join(path)}"
    assert path[:2] == ["polycc_step", "polycc_barrier"]


@pytest.mark.arm
def test_kernel_is_self_contained_and_small():
    kernel_arm = arm_or_skip()
    build_dir = kernel_arm.test_program().parent
    graph = kernel_arm.call_graph(build_dir / "polycc_kernel.o")
    called = set().union(*graph.values())
    assert called <= set(graph), f"the kernel calls outside itself: {sorted(called - set(graph))}"
    size = kernel_arm.size_of(build_dir / "polycc_kernel.o")
    assert size["data"] == 0 and size["bss"] == 0 and size["text"] <= 5120, size  # 4640 B with the index walk
