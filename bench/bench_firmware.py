"""Benchmark of the real firmware: the Cortex-M4 build's cost and the SITL's speed and fidelity.

1. Upstream firmware (``../shared/firmware/crazyflie-firmware-2a18fc29.tar.xz``, extracted into the cache),
   arm-none-eabi-gcc with the firmware's own flags: the stock ``examples/app_hello_world`` (baseline)
   and the polycc app with the demo arena at 16 and 64 KiB (one build folder: the second header
   recompiles only the app). Flash / RAM / CCM as the firmware's ``tools/make/size.py`` counts them, the
   app task's stack (``CONFIG_APP_STACKSIZE`` words of each app-config), warnings, build time; deltas and
   ratios against hello_world.
2. SITL (``crazyflie-firmware-sitl-6a4d2d0.tar.xz``): cf2 build time, boot time, the real-time factor of a
   full flight (lock-stepped, at most 1x), and the fast shims vs the real firmware on the same flight:
   RMS 3-D position difference while the app flies (:func:`polycc.testing.flight_scenarios.diff_rms`).

    python bench/bench_firmware.py [--skip-arm] [--skip-sitl]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import CACHE, print_table, write_json  # noqa: E402


def _stack_bytes(app_config: Path) -> int:
    from polycc.sim.firmware.build import read_kconfig

    return 4 * int(read_kconfig(app_config).get("CONFIG_APP_STACKSIZE", "0"))


def headers(work: Path) -> dict[int, Path]:
    from polycc.cli import main

    arena = work / "arena.ply"
    if not arena.exists():
        assert main(["demo-scene", str(arena)]) == 0
    out = {}
    for kb in (16, 64):
        d = work / f"b{kb}"
        if not (d / "polytopes.h").exists():
            assert main(["build", str(arena), "--flash-kb", str(kb), "-o", str(d)]) == 0
        out[kb] = d
    return out


def arm(work: Path, hdrs: dict[int, Path]) -> dict:
    from polycc.firmware_trees import resolve_tree
    from polycc.ground.flash import build_app, build_hello_world
    from polycc.testing.files import upstream_tarball

    base = resolve_tree(upstream_tarball(), "upstream", print)
    fw = work / "fw"
    res = {}
    hb = build_hello_world(base, fw, jobs=2, say=print)
    res["app_hello_world"] = {**hb.sizes, "stack": _stack_bytes(fw / "app_hello_world" / "app-config"),
                              "warnings": len(hb.warnings), "seconds": hb.seconds}
    for kb, d in hdrs.items():
        b = build_app(d, base, fw, jobs=2, say=print)
        app_text = sum(v["text"] for k, v in b.objects.items() if k.startswith("polycc"))
        res[f"polycc {kb} KiB"] = {**b.sizes, "stack": _stack_bytes(fw / "polycc_app" / "app-config"),
                                   "warnings": len(b.warnings), "seconds": b.seconds, "app_objects_text": app_text,
                                   "header_bytes": (d / "polytopes.h").stat().st_size}
    return res


def sitl(work: Path, hdrs: dict[int, Path]) -> dict:
    from polycc.sim.firmware.build import build_cf2
    from polycc.testing import flight_scenarios as fs
    from polycc.testing.files import sitl_tarball
    from polycc.testing.worlds import FastWorld, FirmwareWorld

    side = json.loads((work / "arena.json").read_text())
    arena = {"start": [side["start"][0], side["start"][1], 0.0], "goal": list(side["goal"])}
    h = hdrs[16] / "polytopes.h"
    t0 = time.monotonic()
    b = build_cf2(sitl_tarball(), h, log=print)
    build_s = time.monotonic() - t0
    with FirmwareWorld(h, arena["start"], cf2=b) as w:
        boot = w.sitl.t_ready
        t1, s1 = time.monotonic(), w.time()
        real = fs.full_flight(w.uri, w, arena)
        wall, sim = time.monotonic() - t1, w.time() - s1
    t2 = time.monotonic()
    with FastWorld(h, arena["start"]) as w:
        s2 = w.time()
        fast = fs.full_flight(w.uri, w, arena)
        fast_wall, fast_sim = time.monotonic() - t2, w.time() - s2
    return {"cf2_build_s": build_s, "cf2_cached": b.cached, "boot_s": boot, "flight_sim_s": sim, "flight_wall_s": wall,
            "rtf": sim / wall, "fast_rtf": fast_sim / fast_wall, "rms_fast_vs_real_m": fs.diff_rms(fast, real),
            "real_arrived": real["arrived"], "fast_arrived": fast["arrived"],
            "real_hold_dz_m": real["hold_dz_max"], "fast_hold_dz_m": fast["hold_dz_max"]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--skip-arm", action="store_true", help="no Cortex-M4 builds")
    ap.add_argument("--skip-sitl", action="store_true", help="no SITL flights")
    args = ap.parse_args()
    work = CACHE / "firmware"
    work.mkdir(parents=True, exist_ok=True)
    hdrs = headers(work)
    payload: dict = {}
    if not args.skip_arm:
        res = arm(work, hdrs)
        hw = res["app_hello_world"]
        rows = []
        for name, r in res.items():
            rows.append([name, r["flash"], r["flash"] - hw["flash"], r["flash"] / hw["flash"], r["ram"],
                         r["ram"] - hw["ram"], r["ram"] / hw["ram"], r["ccm"], r["stack"], r["warnings"],
                         round(r["seconds"])])
        print_table("Cortex-M4 firmware (upstream 2a18fc29, -Os): bytes, vs app_hello_world",
                    ["build", "flash", "Δflash", "flash ×", "RAM", "ΔRAM", "RAM ×", "CCM", "app stack", "warnings",
                     "build s"], rows)
        payload["arm"] = res
    if not args.skip_sitl:
        r = sitl(work, hdrs)
        print_table("SITL (CrazySim 6a4d2d0, lock-stepped) and fast shims vs real firmware (full flight)",
                    ["cf2 build s", "boot s", "flight sim s", "flight wall s", "RTF real", "RTF fast",
                     "RMS fast vs real m", "hold dz real m", "hold dz fast m"],
                    [[round(r["cf2_build_s"]), r["boot_s"], r["flight_sim_s"], r["flight_wall_s"], r["rtf"],
                      r["fast_rtf"], r["rms_fast_vs_real_m"], r["real_hold_dz_m"], r["fast_hold_dz_m"]]])
        payload["sitl"] = r
    write_json("bench_firmware", payload)


if __name__ == "__main__":
    main()
