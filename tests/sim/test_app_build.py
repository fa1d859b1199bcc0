"""The Crazyflie app compiles against the firmware API shims with the firmware's flags (host and
arm-none-eabi), refuses a scene header of another layout format, and has the OOT layout."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
from pathlib import Path

import pytest

from polycc import resources
from polycc.codegen.header import write_outputs
from polycc.geometry.halfplanes import axis_box
from polycc.onboard.layout import SCENE_FORMAT
from polycc.sim.app_ffi import FIRMWARE_WARN_FLAGS, SHIMS, SRC

APP = resources.firmware_app()
ARM_FLAGS = ["-mcpu=cortex-m4", "-mthumb", "-mfloat-abi=hard", "-mfpu=fpv4-sp-d16", "-Os"]
FIRMWARE_HEADERS = ("app.h", "commander.h", "FreeRTOS.h", "log.h", "param.h", "task.h", "usec_time.h", "debug.h")


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("scene")
    write_outputs(d, [axis_box([0, 0, 0], [1, 1, 1]), axis_box([2, 0, 0], [3, 1, 2])], {"kappa": 100.0})
    return d


def _compile(cc: str, flags: list[str], header_dir: Path, out: Path, src: Path = SRC / "polycc_app.c"):
    cmd = [cc, *flags, *FIRMWARE_WARN_FLAGS, f"-I{SHIMS}", f"-I{SRC}", f"-I{header_dir}", "-c", str(src), "-o",
           str(out)]
    return subprocess.run(cmd, capture_output=True, text=True)


def _arm_or_skip():
    if shutil.which("arm-none-eabi-gcc") is None or shutil.which("arm-none-eabi-size") is None:
        msg = "needs arm-none-eabi-gcc (apt-get install gcc-arm-none-eabi libnewlib-arm-none-eabi)"
        if os.environ.get("POLYCC_REQUIRE_ARM") == "1":
            pytest.fail(msg + "; POLYCC_REQUIRE_ARM=1 forbids skipping")
        pytest.skip(msg)


@pytest.mark.parametrize("host_tables", [False, True], ids=["firmware-sections", "host-registry"])
def test_host_compile_with_firmware_flags(scene_dir, tmp_path, host_tables):
    cc = shutil.which("cc") or shutil.which("gcc")
    flags = ["-O2", "-Wextra"] + (["-DPOLYCC_SHIM_HOST=1"] if host_tables else [])
    r = _compile(cc, flags, scene_dir, tmp_path / "app.o")
    assert r.returncode == 0, r.stderr


def test_arm_compile_against_shims_and_size(scene_dir, tmp_path):
    _arm_or_skip()
    sizes = {}
    for src in (SRC / "polycc_app.c", SRC / "polycc_kernel.c", SRC / "polycc_shield.c", SRC / "polycc_controller.c",
                SRC / "polycc_swarm.c"):
        obj = tmp_path / (src.stem + ".o")
        r = _compile("arm-none-eabi-gcc", ARM_FLAGS, scene_dir, obj, src)
        assert r.returncode == 0, r.stderr
        out = subprocess.run(["arm-none-eabi-size", str(obj)], capture_output=True, text=True, check=True).stdout
        text, data, bss = (int(v) for v in out.splitlines()[1].split()[:3])
        sizes[src.stem] = (text, data, bss)
    print("arm-none-eabi text/data/bss:", sizes)
    text, data, bss = sizes["polycc_app"]
    # The app glue (2 test polytopes inline) stays small; the parameter/log tables are data; the
    # swarm's neighbour table (16 x 32 B + 4, docs/swarm.md) and the P2P ring (16 x 24 B) are most of the bss.
    assert text < 5120 and data < 1024 and bss < 512 + 516 + 16 * 24
    assert sizes["polycc_kernel"][1:] == (0, 0)  # the kernel has no mutable state
    assert sizes["polycc_shield"][1:] == (0, 0) and sizes["polycc_shield"][0] < 4096  # nor the shield
    # the controller glue holds one plan (201 points: 4 kB) in RAM, nothing else of size
    assert sizes["polycc_controller"][0] < 4096 and sizes["polycc_controller"][2] < 4096 + 512
    assert sizes["polycc_swarm"][1:] == (0, 0)  # nor has the swarm module (the app owns its table)


def test_format_mismatch_refuses_to_build(scene_dir, tmp_path):
    cc = shutil.which("cc") or shutil.which("gcc")
    text = (scene_dir / "polytopes.h").read_text()
    tag = f"#define POLYCC_HEADER_FORMAT {SCENE_FORMAT}u"
    assert tag in text
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "polytopes.h").write_text(text.replace(tag, f"#define POLYCC_HEADER_FORMAT {SCENE_FORMAT + 1}u"))
    r = _compile(cc, [], bad, tmp_path / "a.o")
    assert r.returncode != 0 and "format" in r.stderr
    # A header without the format tag is refused by the app itself.
    nofmt = tmp_path / "nofmt"
    nofmt.mkdir()
    stripped = re.sub(tag + r"\n#if .*?#endif\n", "", text, flags=re.S)
    (nofmt / "polytopes.h").write_text(stripped)
    r = _compile(cc, [], nofmt, tmp_path / "b.o")
    assert r.returncode != 0 and "POLYCC_HEADER_FORMAT" in r.stderr and "polycc build" in r.stderr


def test_out_of_tree_layout():
    mk = (APP / "Makefile").read_text()
    assert re.search(r"^CRAZYFLIE_BASE \?=", mk, re.M)
    assert "include $(CRAZYFLIE_BASE)/tools/make/oot.mk" in mk
    assert re.search(r"^POLYCC_SCENE \?=", mk, re.M)
    cfg = dict(line.split("=", 1) for line in (APP / "app-config").read_text().split())
    assert cfg["CONFIG_APP_ENABLE"] == "y" and int(cfg["CONFIG_APP_STACKSIZE"]) >= 300
    assert "obj-y += src/" in (APP / "Kbuild").read_text()
    kb = (APP / "src" / "Kbuild").read_text()
    assert "ccflags-y += -ffp-contract=off" in kb
    assert "polycc_app.o" in kb and "polycc_kernel.o" in kb
    assert "polycc_shield.o" in kb and "polycc_controller.o" in kb and cfg["CONFIG_CONTROLLER_OOT"] == "y"


def test_only_the_app_includes_firmware_headers():
    inc = re.compile(r'#include\s+"([^"]+)"')
    for f in SRC.iterdir():
        if f.suffix in (".c", ".h") and f.name not in ("polycc_app.c", "polycc_controller.c"):  # the two glue files
            assert not set(inc.findall(f.read_text())) & set(FIRMWARE_HEADERS), f.name
    assert set(FIRMWARE_HEADERS) <= set(inc.findall((SRC / "polycc_app.c").read_text()))
    # The shield's controller glue: only firmware headers that have a shim, and the kernel/shield stay portable.
    for h in set(inc.findall((SRC / "polycc_controller.c").read_text())) - {p.name for p in SRC.iterdir()}:
        assert (SHIMS / h).is_file(), h
    # Every firmware header the app includes has a shim.
    for h in FIRMWARE_HEADERS:
        assert (SHIMS / h).is_file(), h
