"""`polycc flash OUT --crazyflie-base PATH`: build the Crazyflie firmware with the polycc app and flash it."""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

from polycc import __version__
from polycc.commands.argtypes import number
from polycc.errors import PolyccError

REPO = Path(__file__).resolve().parents[2]
APP_DIR = REPO / "firmware_app"
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


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "flash",
        help="build the Crazyflie firmware with the polycc app and the scene header, then flash it",
        description=(
            "Copies firmware_app/ and OUT/polytopes.h into a build folder, runs the firmware's out-of-tree "
            "build (make, tools/make/oot.mk of --crazyflie-base), reports flash and RAM use "
            "(arm-none-eabi-size of cf2.elf) and flashes cf2.bin with `python -m cfloader flash cf2.bin "
            "stm32-fw -w URI` (cfloader comes with the cfclient package) over a Crazyradio. Put the "
            "Crazyflie in bootloader mode or let cfloader reset it over the radio (-w)."
        ),
    )
    p.add_argument("out", metavar="OUT", help="build folder of `polycc build` (holds polytopes.h)")
    p.add_argument("--crazyflie-base", required=True, metavar="PATH",
                   help="bitcraze/crazyflie-firmware checkout with submodules (git clone --recursive)")
    p.add_argument("--uri", default=os.environ.get("CFLIB_URI", DEFAULT_URI), metavar="URI",
                   help="Crazyflie radio URI (default: $CFLIB_URI or radio://0/80/2M/E7E7E7E7E7)")
    p.add_argument("--build-dir", metavar="DIR", help="where to build (default: OUT/firmware)")
    p.add_argument("--jobs", "-j", type=number(int, 1, 256), default=os.cpu_count() or 1, metavar="N",
                   help="parallel make jobs (default: the number of CPUs, %(default)s here)")
    p.add_argument("--no-flash", action="store_true", help="build and report sizes, do not flash (default: flash)")
    p.add_argument("--dry-run", action="store_true", help="check the toolchain, firmware tree and radio, print every step, run none (default: off)")
    p.set_defaults(func=run)


@dataclass
class Step:
    what: str
    cmd: list[str] | None = None
    cwd: Path | None = None


def _check_firmware(base: Path) -> list[str]:
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


def _check_toolchain() -> None:
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


def _check_flasher(uri: str) -> list[str]:
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


def _copy_app(out: Path, app: Path, base: Path) -> None:
    app.mkdir(parents=True, exist_ok=True)
    for f in APP_FILES:
        shutil.copy2(APP_DIR / f, app / f)
    (app / "src").mkdir(exist_ok=True)
    for f in (APP_DIR / "src").iterdir():
        if f.suffix in (".c", ".h") or f.name == "Kbuild":
            shutil.copy2(f, app / "src" / f.name)
    shutil.copy2(out / "polytopes.h", app / "polytopes.h")
    if not (base / ".git").exists():
        (app / "build").mkdir(exist_ok=True)
        (app / "build" / "build_info.json").write_text(json.dumps({"tag": f"polycc-{__version__}"}) + "\n")


def run(args) -> int:
    from polycc.console import console, summary_table

    out = Path(args.out)
    if not (out / "polytopes.h").is_file():
        raise PolyccError(f"{out / 'polytopes.h'}: not found; run `polycc build SCENE -o {out}` first")
    base = Path(args.crazyflie_base).expanduser().resolve()
    build = Path(args.build_dir).resolve() if args.build_dir else (out / "firmware").resolve()
    flash = not args.no_flash
    notes = []
    try:
        notes += _check_firmware(base)
        _check_toolchain()
        if flash:
            notes += _check_flasher(args.uri)
    except PolyccError as exc:
        if not args.dry_run:
            raise
        notes.append(f"WOULD FAIL: {exc}")
    steps = plan(out, base, build, args.uri, args.jobs, flash)
    for n in notes:
        console.print(f"note: {n}", soft_wrap=True)
    if args.dry_run:
        for i, s in enumerate(steps, 1):
            console.print(f"step {i}: {s.what}", soft_wrap=True)
            if s.cmd:
                console.print(f"    (cd {s.cwd} && {' '.join(s.cmd)})", markup=False, soft_wrap=True)
        return 2 if any(n.startswith("WOULD FAIL") for n in notes) else 0

    app = build / "polycc_app"
    console.print(f"step 1: {steps[0].what}", soft_wrap=True)
    _copy_app(out, app, base)
    for i, s in enumerate(steps[1:], 2):
        if s.cmd is None:
            console.print(f"step {i}: {s.what}", soft_wrap=True)
            continue
        console.print(f"step {i}: {s.what}\n    (cd {s.cwd} && {' '.join(s.cmd)})", markup=False, soft_wrap=True)
        if s.cmd[0] == "arm-none-eabi-size":
            sz = firmware_sizes(app / "build" / "cf2.elf")
            objs = {o.stem: size_report(o) for o in sorted((app / "src").glob("polycc_*.o"))}
            rows = [("firmware flash (.text + .data)", f"{sz['flash']:,} B of {FLASH_BYTES:,} ({100 * sz['flash'] / FLASH_BYTES:.0f}%)"),
                    ("firmware RAM (.data + .bss)", f"{sz['ram']:,} B of {RAM_BYTES:,} ({100 * sz['ram'] / RAM_BYTES:.0f}%)"),
                    ("firmware CCM (.ccmbss)", f"{sz['ccm']:,} B of {CCM_BYTES:,} ({100 * sz['ccm'] / CCM_BYTES:.0f}%)")]
            rows += [(f"{k}.o text / data / bss", f"{v['text']:,} / {v['data']:,} / {v['bss']:,} B") for k, v in objs.items()]
            console.print(summary_table("polycc flash: sizes", rows))
            continue
        r = subprocess.run(s.cmd, cwd=s.cwd, env={**os.environ, "PWD": str(s.cwd)})
        if r.returncode != 0:
            what = "firmware build" if s.cmd[0] == "make" else "cfloader"
            hint = ("see the compiler output above" if what == "firmware build"
                    else "check the Crazyradio, the URI and that the Crazyflie is on")
            raise PolyccError(f"{what} failed (exit {r.returncode}); {hint}")
    console.print(f"firmware: {app / 'build' / 'cf2.bin'}" + ("" if flash else " (not flashed: --no-flash)"))
    return 0

