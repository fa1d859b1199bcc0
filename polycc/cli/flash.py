"""`polycc flash OUT --firmware FWDIR` (or ``--crazyflie-base PATH``): build the Crazyflie firmware with the
polycc app and flash it (the steps: :mod:`polycc.ground.flash`)."""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

from polycc.cli.argtypes import number
from polycc.errors import PolyccError
from polycc.ground.flash import (
    CCM_BYTES,
    DEFAULT_URI,
    FLASH_BYTES,
    RAM_BYTES,
    check_firmware,
    check_flasher,
    check_toolchain,
    copy_app,
    firmware_sizes,
    plan,
    size_report,
)


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "flash",
        help="build the Crazyflie firmware with the polycc app and the scene header, then flash it",
        description=(
            "Copies firmware_app/ and OUT/polytopes.h into a build folder, runs the firmware's out-of-tree "
            "build (make, tools/make/oot.mk of --firmware; a tarball is extracted into the cache first), reports "
            "flash and RAM use "
            "(arm-none-eabi-size of cf2.elf) and flashes cf2.bin with `python -m cfloader flash cf2.bin "
            "stm32-fw -w URI` (cfloader comes with the cfclient package) over a Crazyradio. Put the "
            "Crazyflie in bootloader mode or let cfloader reset it over the radio (-w)."
        ),
    )
    p.add_argument("out", metavar="OUT", help="build folder of `polycc build` (holds polytopes.h)")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--firmware", metavar="FWDIR",
                     help="the upstream bitcraze/crazyflie-firmware: a checkout with submodules (git clone "
                          "--recursive) or its .tar.xz/.tar.gz (extracted once into the polycc cache, never edited)")
    src.add_argument("--crazyflie-base", metavar="PATH", help="the same as --firmware (a firmware tree folder)")
    p.add_argument("--uri", default=os.environ.get("CFLIB_URI", DEFAULT_URI), metavar="URI",
                   help="Crazyflie radio URI (default: $CFLIB_URI or radio://0/80/2M/E7E7E7E7E7)")
    p.add_argument("--build-dir", metavar="DIR", help="where to build (default: OUT/firmware)")
    p.add_argument("--jobs", "-j", type=number(int, 1, 256), default=os.cpu_count() or 1, metavar="N",
                   help="parallel make jobs (default: the number of CPUs, %(default)s here)")
    p.add_argument("--no-flash", action="store_true", help="build and report sizes, do not flash (default: flash)")
    p.add_argument("--dry-run", action="store_true", help="check the toolchain, firmware tree and radio, print every "
                                                          "step, run none (default: off)")
    p.set_defaults(func=run)

def run(args) -> int:
    from polycc.cli.console import console, summary_table

    out = Path(args.out)
    if not (out / "polytopes.h").is_file():
        raise PolyccError(f"{out / 'polytopes.h'}: not found; run `polycc build SCENE -o {out}` first")
    from polycc.firmware_trees import is_tarball, resolve_tree

    source = args.firmware or args.crazyflie_base
    if is_tarball(source):
        base = resolve_tree(source, "upstream", lambda m: console.print(m, soft_wrap=True))
    else:
        base = Path(source).expanduser().resolve()
    build = Path(args.build_dir).resolve() if args.build_dir else (out / "firmware").resolve()
    flash = not args.no_flash
    notes = []
    try:
        notes += check_firmware(base)
        check_toolchain()
        if flash:
            notes += check_flasher(args.uri)
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
    copy_app(out, app, base)
    for i, s in enumerate(steps[1:], 2):
        if s.cmd is None:
            console.print(f"step {i}: {s.what}", soft_wrap=True)
            continue
        console.print(f"step {i}: {s.what}\n    (cd {s.cwd} && {' '.join(s.cmd)})", markup=False, soft_wrap=True)
        if s.cmd[0] == "arm-none-eabi-size":
            sz = firmware_sizes(app / "build" / "cf2.elf")
            objs = {o.stem: size_report(o) for o in sorted((app / "src").glob("polycc_*.o"))}
            rows = [("firmware flash (.text + "
                     ".data)", f"{sz['flash']:,} B of {FLASH_BYTES:,} ({100 * sz['flash'] / FLASH_BYTES:.0f}%)"),
                    ("firmware RAM (.data + "
                     ".bss)", f"{sz['ram']:,} B of {RAM_BYTES:,} ({100 * sz['ram'] / RAM_BYTES:.0f}%)"),
                    ("firmware CCM "
                     "(.ccmbss)", f"{sz['ccm']:,} B of {CCM_BYTES:,} ({100 * sz['ccm'] / CCM_BYTES:.0f}%)")]
            rows += [(f"{k}.o text / data / bss", f"{v['text']:,} / {v['data']:,} / {v['bss']:,} "
                                                  "B") for k, v in objs.items()]
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

