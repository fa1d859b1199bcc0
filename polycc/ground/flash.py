"""Build the Crazyflie firmware with the polycc app and a scene header, report its size, flash it.

An out-of-tree build of ``firmware_app/`` (:func:`polycc.resources.firmware_app`) against a
user-given crazyflie-firmware tree; sizes are counted as the firmware's ``tools/make/size.py``
does; flashing goes through ``cfloader`` over a Crazyradio.
"""

from __future__ import annotations

import importlib.util
import json
import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

from polycc import resources
from polycc.errors import PolyccError
from polycc.version import __version__

APP_FILES = ["Makefile", "Kbuild", "app-config"]
SUBMODULES = {
    "vendor/FreeRTOS": "vendor/FreeRTOS/include/FreeRTOS.h",
    "vendor/CMSIS": "vendor/CMSIS/CMSIS/Core/Include",
    "vendor/libdw1000": "vendor/libdw1000/inc",
}
CRAZYRADIO_USB = ("1915", "7777")  # Bitcraze Crazyradio PA / 2.0 (vendor, product)
DEFAULT_URI = "radio://0/80/2M/E7E7E7E7E7"
# Flash and RAM of the STM32F405 on the Crazyflie 2.x (the firmware reserves the first
# 16 KB of flash for the bootloader).
FLASH_BYTES = 1024 * 1024 - 16 * 1024
RAM_BYTES = 128 * 1024
CCM_BYTES = 64 * 1024

@dataclass
class Step:
    what: str
    cmd: list[str] | None = None
    cwd: Path | None = None


def check_firmware(base: Path) -> list[str]:
    if not (base / "tools" / "make" / "oot.mk").is_file():
        raise PolyccError(f"{base}: no crazyflie-firmware tree here (tools/make/oot.mk missing); "
                          "git clone --recursive https://github.com/bitcraze/crazyflie-firmware and pass its path")
    missing = [name for name, probe in SUBMODULES.items() if not (base / probe).exists()]
    if missing:
        raise PolyccError(f"{base}: submodules {', '.join(missing)} are empty; run "
                          "`git submodule update --init --recursive` in the firmware tree")
    notes = []
    if not (base / ".git").exists():
        notes.append("the firmware tree has no .git: a build_info.json with the version tag goes into the build folder")
    return notes


def check_toolchain() -> None:
    missing = [t for t in ("arm-none-eabi-gcc", "arm-none-eabi-size", "make") if shutil.which(t) is None]
    if missing:
        raise PolyccError(f"no ARM toolchain: {', '.join(missing)} not on PATH; apt-get install gcc-arm-none-eabi "
                          "libnewlib-arm-none-eabi make (or the Arm GNU Toolchain) and retry")


def crazyradio_present() -> bool | None:
    """True/False from the USB device list; None when it cannot be read (not Linux)."""
    root = Path("/sys/bus/usb/devices")
    if not root.is_dir():
        return None
    for dev in root.iterdir():
        try:
            ids = ((dev / "idVendor").read_text().strip(), (dev / "idProduct").read_text().strip())
        except OSError:
            continue
        if ids == CRAZYRADIO_USB:
            return True
    return False


def check_flasher(uri: str) -> list[str]:
    notes = []
    if importlib.util.find_spec("cfloader") is None:
        raise PolyccError("cfloader not found: pip install cfclient (it provides `python -m cfloader`), "
                          "or use --no-flash")
    if uri.startswith("radio://"):
        present = crazyradio_present()
        if present is False:
            raise PolyccError(f"no Crazyradio on USB (vendor:product {':'.join(CRAZYRADIO_USB)}) for {uri}; "
                              "plug it in (and install its udev rules), or use --no-flash")
        if present is None:
            notes.append("cannot list USB devices here; cfloader will report a missing Crazyradio")
    return notes


def size_report(elf: Path) -> dict[str, int]:
    """Berkeley text/data/bss of an object."""
    r = subprocess.run(["arm-none-eabi-size", str(elf)], capture_output=True, text=True)
    if r.returncode != 0:
        raise PolyccError(f"arm-none-eabi-size {elf} failed: {r.stderr.strip()}")
    text, data, bss = (int(v) for v in r.stdout.splitlines()[1].split()[:3])
    return {"text": text, "data": data, "bss": bss}


def firmware_sizes(elf: Path) -> dict[str, int]:
    """Flash, RAM and CCM use of the firmware ELF, counted as the firmware's tools/make/size.py does:
    flash = .text + .data + .ccmdata, RAM = .data + .bss, CCM = .ccmbss + .ccmdata."""
    r = subprocess.run(["arm-none-eabi-size", "-A", str(elf)], capture_output=True, text=True)
    if r.returncode != 0:
        raise PolyccError(f"arm-none-eabi-size -A {elf} failed: {r.stderr.strip()}")
    sec = {}
    for line in r.stdout.splitlines():
        parts = line.split()
        if len(parts) >= 2 and parts[0].startswith(".") and parts[1].isdigit():
            sec[parts[0]] = int(parts[1])
    g = lambda k: sec.get(k, 0)  # noqa: E731
    return {"flash": g(".text") + g(".data") + g(".ccmdata"), "ram": g(".data") + g(".bss"),
            "ccm": g(".ccmbss") + g(".ccmdata")}


def plan(out: Path, base: Path, build: Path, uri: str, jobs: int, flash: bool) -> list[Step]:
    app = build / "polycc_app"
    steps = [Step(f"copy firmware_app/ and {out / 'polytopes.h'} into {app}")]
    if not (base / ".git").exists():
        steps.append(Step(f"write {app / 'build' / 'build_info.json'} (firmware tree without .git)"))
    steps.append(Step("build the firmware with the app (out-of-tree)",
                      ["make", f"-j{jobs}", f"CRAZYFLIE_BASE={base}", f"POLYCC_SCENE={app / 'polytopes.h'}"], app))
    steps.append(Step("report flash and RAM use", ["arm-none-eabi-size", str(app / "build" / "cf2.elf")], app))
    if flash:
        steps.append(Step(f"flash over the Crazyradio ({uri})",
                          [sys.executable, "-m", "cfloader", "flash", str(app / "build" / "cf2.bin"), "stm32-fw",
                           "-w", uri], app))
    return steps


def sync_file(src: Path, dst: Path) -> bool:
    """Copy ``src`` to ``dst`` unless ``dst`` already has the same bytes; a copied file gets the current
    mtime (not the source's, as copy2 would keep), so make rebuilds what depends on it even when the new
    file is older than the objects of a reused build folder. True if it copied."""
    if dst.is_file() and dst.read_bytes() == src.read_bytes():
        return False
    shutil.copyfile(src, dst)
    shutil.copymode(src, dst)
    return True


def copy_app(out: Path, app: Path, base: Path) -> None:
    """The app and ``out/polytopes.h`` into ``app`` (a reused build folder recompiles exactly what changed)."""
    app.mkdir(parents=True, exist_ok=True)
    for f in APP_FILES:
        sync_file(resources.firmware_app() / f, app / f)
    (app / "src").mkdir(exist_ok=True)
    for f in (resources.firmware_app() / "src").iterdir():
        if f.suffix in (".c", ".h") or f.name == "Kbuild":
            sync_file(f, app / "src" / f.name)
    sync_file(out / "polytopes.h", app / "polytopes.h")
    if not (base / ".git").exists():
        (app / "build").mkdir(exist_ok=True)
        (app / "build" / "build_info.json").write_text(json.dumps({"tag": f"polycc-{__version__}"}) + "\n")


# --------------------------------------------------------------------------- library build (tests, bench)
@dataclass
class FirmwareBuild:
    """An out-of-tree Cortex-M4 build: ``elf`` (cf2.elf), firmware ``sizes`` (:func:`firmware_sizes`), the
    app objects' text/data/bss, the compiler ``warnings`` (lines with ``warning:``), wall ``seconds``, ``log``."""

    elf: Path
    sizes: dict
    objects: dict
    warnings: list
    seconds: float
    log: Path


def make_oot(app: Path, base: Path, jobs: int = 2, extra: tuple = (), say=None) -> FirmwareBuild:
    """``make`` an out-of-tree app folder ``app`` (run from inside it, PWD set: oot.mk's ``OOT ?= $(PWD)``)
    against the firmware tree ``base``; a ``build_info.json`` goes into ``app/build`` when ``base`` has no
    .git (the firmware's release-version mechanism, read from the Kbuild output folder). Output to
    ``app/build.log``; a failed build is a one-line error with its first error line."""
    import os
    import re
    import time

    say = say or (lambda msg: None)
    t0 = time.monotonic()
    check_toolchain()
    if not (base / ".git").exists():
        (app / "build").mkdir(parents=True, exist_ok=True)
        bi = app / "build" / "build_info.json"
        if not bi.is_file():
            bi.write_text(json.dumps({"tag": f"polycc-{__version__}"}) + "\n")
    logf = app / "build.log"
    cmd = ["make", f"-j{max(1, int(jobs))}", f"CRAZYFLIE_BASE={base}", *extra]
    say(f"building {app.name} against {base.name} ({' '.join(cmd)})")
    with open(logf, "w") as lf:
        proc = subprocess.Popen(cmd, cwd=app, env={**os.environ, "PWD": str(app)}, stdout=subprocess.PIPE,
                                stderr=subprocess.STDOUT, text=True)
        n, last = 0, time.monotonic()
        for line in proc.stdout:
            lf.write(line)
            if line.lstrip().startswith(("CC ", "AS ", "LD ")):
                n += 1
                if time.monotonic() - last > 10.0:
                    last = time.monotonic()
                    say(f"  {n} files compiled")
        rc = proc.wait()
    text = logf.read_text(errors="replace")
    if rc != 0:
        m = re.search(r"^.*?(error|Error \d+).*$", text, re.M)
        raise PolyccError(f"firmware build of {app} failed (exit {rc}): {m.group(0).strip()[:240] if m else ''} "
                          f"(full log: {logf})")
    elf = app / "build" / "cf2.elf"
    objs = {o.stem: size_report(o) for o in sorted((app / "src").glob("*.o"))}
    warnings = [ln.strip() for ln in text.splitlines() if "warning:" in ln]
    return FirmwareBuild(elf, firmware_sizes(elf), objs, warnings, time.monotonic() - t0, logf)


def build_app(out: Path, base: Path, build: Path, jobs: int = 2, say=None) -> FirmwareBuild:
    """The polycc app with ``out/polytopes.h`` built into ``build/polycc_app`` (reused: a second header
    recompiles only the app)."""
    app = build / "polycc_app"
    copy_app(out, app, base)
    return make_oot(app, base, jobs, (f"POLYCC_SCENE={app / 'polytopes.h'}",), say)


def build_hello_world(base: Path, build: Path, jobs: int = 2, say=None) -> FirmwareBuild:
    """The firmware's own ``examples/app_hello_world`` (the baseline), copied to ``build/app_hello_world``."""
    src = base / "examples" / "app_hello_world"
    if not (src / "Makefile").is_file():
        raise PolyccError(f"{src}: the firmware's app_hello_world example is missing")
    app = build / "app_hello_world"
    if not app.exists():
        shutil.copytree(src, app)
    return make_oot(app, base, jobs, (), say)
