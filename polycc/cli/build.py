"""`polycc build SCENE --flash-kb N -o OUT`: scene -> occupancy -> cover -> budget -> C header."""

from __future__ import annotations

import argparse

from polycc import pipeline
from polycc.budget import cycle_model
from polycc.budget.reduce import MIN_PLANES
from polycc.cli.argtypes import add_parallel_options, number
from polycc.cli.console import StageProgress, console, warn
from polycc.cli.scene_args import add_scene_options, output_dir, print_summary, resolve_scene_settings
from polycc.cover.build import COVER_COSTS, DEFAULT_MERGE_COST
from polycc.occupancy.floaters import floater_text
from polycc.onboard.barrier import KAPPA_MAX, KAPPA_MIN
from polycc.onboard.index import DEFAULT_CLEARANCE_CAP
from polycc.onboard.layout import MAX_PLANES
from polycc.pipeline import BuildOptions

FLASH_KB_MAX = 1008.0  # STM32F405: 1 MiB flash minus the 16 KiB bootloader
MC_SAMPLES_MIN = 1000


def register(sub) -> None:
    p = sub.add_parser(
        "build",
        help="build the on-board C header (polytopes.h) of a scene under flash/compute budgets",
        description="Read a splat scene, voxelize it exactly, cover it with PolyMerge polytopes, pick the least "
                    "conservative cover H^n that fits the budgets after outward plane reduction and outward "
                    "quantization (scene format 3: shared normal table, 4-byte half-planes), and write "
                    "OUT/polytopes.h, OUT/manifest.json, OUT/scene.bin (the same bytes as the header's arrays), "
                    "OUT/cover.npz and OUT/report.png. Every stored polytope contains its exact one.",
    )
    p.add_argument("scene", metavar="SCENE", help="3DGS .ply, .compressed.ply, .splat, .spz, point-cloud or mesh .ply")
    p.add_argument("-o", "--output", default="out", metavar="OUT", help="output folder (default: %(default)s)")
    p.add_argument("--flash-kb", type=number(float, 0.0, FLASH_KB_MAX, lo_open=True, unit="KiB"), default=64.0,
                   metavar="N",
                   help="flash budget for all generated constant data, KiB (1 KiB = 1024 bytes); at most "
                        f"{FLASH_KB_MAX:g}, the STM32F405's application flash (default: %(default)s)")
    p.add_argument("--max-halfplanes", type=number(int, MIN_PLANES, MAX_PLANES), default=None, metavar="M",
                   help="cap on the total number of stored half-planes, bounding on-board compute, "
                        f"{MIN_PLANES}..{MAX_PLANES} (default: no cap)")
    p.add_argument("--rate-hz", type=number(float, 10.0, 1000.0, unit="Hz"), default=cycle_model.DEFAULT_RATE_HZ,
                   metavar="R",
                   help="the certified worst-case evaluation (spatial index, Cortex-M4 cycle model) must fit in "
                        "--cpu-share of a 168 MHz CPU at R Hz, 10..1000 (the app's range) (default: %(default)s)")
    p.add_argument("--clearance-cap", type=number(float, 0.05, 100.0, unit="m"), default=DEFAULT_CLEARANCE_CAP,
                   metavar="D",
                   help="clearance cap of the spatial index: psi is reported as min(psi, D), so obstacles farther "
                        "than D need not be listed (docs/barrier.md section 9), metres (default: %(default)s)")
    p.add_argument("--cpu-share", type=number(float, 0.0, 1.0, lo_open=True), default=cycle_model.DEFAULT_CPU_SHARE,
                   metavar="F", help="fraction of the CPU the filter may use with --rate-hz, in (0, 1] "
                                     "(default: %(default)s)")
    p.add_argument("--kappa", type=number(float, float(KAPPA_MIN), float(KAPPA_MAX), unit="1/m"), default=100.0,
                   metavar="K",
                   help="soft-min/soft-max sharpness recorded in the header, 1/m, in [1, 10000] (the kernel's "
                        "range; outside it the app only hovers) (default: %(default)s, as in the paper)")
    p.add_argument("--neighborhood", type=number(int, 0, 4, unit="voxels"), default=1, metavar="B",
                   help="cluster radius b in voxels (L-infinity), Eq. 10, 0..4 (default: %(default)s)")
    p.add_argument("--boxes", action=argparse.BooleanOptionalAction, default=True,
                   help="add one exact all-occupied box per voxel whose cluster wastes volume to the set-cover "
                        "candidates, so the sub-cover wastes nothing (--no-boxes: the paper's clusters only) "
                        "(default: on)")
    p.add_argument("--merge-cost", choices=COVER_COSTS, default=DEFAULT_MERGE_COST,
                   help="merge cost: 'paper' = W of the union (Eq. 13), 'delta' = the free volume a merge adds, 'best' "
                        "= both, keep the better; see `polycc cover --help` (default: %(default)s)")
    p.add_argument("--mc-samples", type=number(int, MC_SAMPLES_MIN, 100_000_000), default=100_000, metavar="S",
                   help=f"Monte Carlo samples per candidate for conservativeness, at least {MC_SAMPLES_MIN:,} "
                        "(default: %(default)s)")
    add_scene_options(p)
    add_parallel_options(p)
    p.set_defaults(func=run)


def _index_text(onb: dict) -> str:
    ix = onb["index"]
    return (f"{' x '.join(str(d) for d in ix['dims'])} cells of {ix['cell_m']:g} m, {ix['lists']:,} lists, "
            f"{ix['entries']:,} entries, {ix['bytes']:,} B; clearance cap D = {onb['clearance_cap_m']:g} m")


def run(args: argparse.Namespace) -> int:
    out = output_dir(args.output)
    settings = resolve_scene_settings(args)
    options = BuildOptions(**{k: getattr(args, k) for k in BuildOptions.__dataclass_fields__})
    with StageProgress() as progress:
        r = pipeline.build(args.scene, out, settings, options, progress, warn)
    scene, occ, family, best, us = r.scene, r.occupancy, r.family, r.best, r.modelled_us
    fl = floater_text(occ.stats)
    rows = [
        ("scene", f"{args.scene} (sha256 {scene.sha256[:12]}...)"),
        ("splats read / kept", f"{scene.stats.read:,} / {scene.stats.kept:,}"),
        ("invalid / opacity-filtered / cropped",
         f"{scene.stats.invalid:,} / {scene.stats.filtered_opacity:,} / {scene.stats.cropped:,}"),
        *([("isolated splats dropped (--drop-isolated; listed in manifest.json)",
            f"{scene.stats.dropped_isolated:,} in {len(scene.dropped_groups):,} groups")]
          if scene.stats.dropped_isolated else []),
        ("voxels (g)", f"{len(occ):,} ({occ.voxel_size:g} m)"),
        *([("floater filter", fl)] if fl else []),
        ("N before merging (sub-cover)", f"{family.n_max:,}"),
        ("n chosen", f"{best.n}"),
        ("half-planes (dropped by reduction / merged)", f"{best.n_planes:,} ({best.dropped:,} / {best.merged:,})"),
        ("shared normals (table cap)",
         f"{best.n_normals:,} ({best.max_normals or 'uncapped'}), quantum {float(best.packed.quantum):g} m"),
        ("bytes / budget", f"{best.bytes:,} / {r.manifest['stats']['budget_bytes']:,} "
                           f"({best.bytes / best.n_planes:.1f} B per half-plane)"),
        ("binding budget", r.binding),
        ("conservativeness Vol(union)/Vol(V+)", f"{best.conservativeness:.4f} +- {best.conservativeness_ci:.4f} (95 % "
                                                "CI)"),
        ("modelled on-board time @168 MHz", f"typical {us['typical_us']:.0f} us, worst {us['worst_us']:.0f} us "
                                            + ("(certified over every position by the spatial index)"
                                               if us.get("worst_is_certified") else "(every polytope evaluated)")),
        *([("spatial index", _index_text(r.manifest["stats"]["onboard"]))] if us.get("worst_is_certified") else []),
        (f"CPU at {args.rate_hz:g} Hz (typical / worst)",
         f"{us['typical_us'] * args.rate_hz / 1e4:.0f}% / {us['worst_us'] * args.rate_hz / 1e4:.0f}%"
         f" (budget {args.cpu_share * 100:g}%)"),
        ("on-board loop rate (polycc.rate)", _rate_text(r.manifest["stats"]["app_rate_hz"])),
        ("cover tiles / where it ran", f"{family.meta['tiles']['tiles']:,} / {family.meta['tiles']['where']}"),
        ("time: occupancy / cover / budget",
         f"{r.timings_s['occupancy']:.1f} / {r.timings_s['cover']:.1f} / {r.timings_s['budget']:.1f} s"),
        ("outputs", f"{out}/polytopes.h, manifest.json, scene.bin, cover.npz, report.png"),
    ]
    print_summary("polycc build", rows)
    console.print(f"build: n = {best.n}, {best.n_planes} half-planes, {best.bytes} bytes -> {out / 'polytopes.h'} "
                  f"({r.timings_s['total']:.1f} s)")
    return 0


def _rate_text(rate: int | None) -> str:
    """The rate the app will run this header at (its default 500 Hz request), in words."""
    from polycc.onboard.app import CPU_SHARE_PERCENT, DEFAULT_RATE_HZ, MIN_RATE_HZ

    if rate is None:
        return (f"none: the worst case does not fit {CPU_SHARE_PERCENT} % of a {1000 // MIN_RATE_HZ} ms period "
                "(the app refuses it, status 12); rebuild with --rate-hz")
    if rate < DEFAULT_RATE_HZ:
        return f"{rate} Hz (lowered from {DEFAULT_RATE_HZ} Hz so the worst case fits {CPU_SHARE_PERCENT} % of a period)"
    return f"{rate} Hz"
