"""`polycc build SCENE --flash-kb N -o OUT`: scene -> occupancy -> cover -> budget -> C header."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from polycc import cycle_model
from polycc.budget import Budget, select
from polycc.codegen import write_outputs
from polycc.barrier import KAPPA_MAX, KAPPA_MIN
from polycc.commands.argtypes import number
from polycc.commands.scene_args import (
    add_scene_options,
    floater_text,
    load_scene_and_occupancy,
    output_dir,
    print_summary,
    resolve_scene_settings,
)
from polycc.console import console, progress_bar
from polycc.cover import COVER_COSTS, DEFAULT_MERGE_COST, build_cover
from polycc.errors import PolyccError
from polycc.reduce import MIN_PLANES, polytope_vertices
from polycc.scene_layout import MAX_PLANES

FLASH_KB_MAX = 1008.0  # STM32F405: 1 MiB flash minus the 16 KiB bootloader
MC_SAMPLES_MIN = 1000
from polycc.report_plot import write_report


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
    p.add_argument("scene", metavar="SCENE", help="3DGS .ply, point-cloud .ply or .splat file")
    p.add_argument("-o", "--output", default="out", metavar="OUT", help="output folder (default: %(default)s)")
    p.add_argument("--flash-kb", type=number(float, 0.0, FLASH_KB_MAX, lo_open=True, unit="KiB"), default=64.0,
                   metavar="N",
                   help="flash budget for all generated constant data, KiB (1 KiB = 1024 bytes); at most "
                        f"{FLASH_KB_MAX:g}, the STM32F405's application flash (default: %(default)s)")
    p.add_argument("--max-halfplanes", type=number(int, MIN_PLANES, MAX_PLANES), default=None, metavar="M",
                   help="cap on the total number of stored half-planes, bounding on-board compute, "
                        f"{MIN_PLANES}..{MAX_PLANES} (default: no cap)")
    p.add_argument("--rate-hz", type=number(float, 10.0, 1000.0, unit="Hz"), default=None, metavar="R",
                   help="derive a half-plane cap from the kernel's Cortex-M4 cycle model so the worst-case "
                        "evaluation fits in --cpu-share of a 168 MHz CPU at R Hz, 10..1000 (the app's range) "
                        "(default: not used)")
    p.add_argument("--cpu-share", type=number(float, 0.0, 1.0, lo_open=True), default=cycle_model.DEFAULT_CPU_SHARE,
                   metavar="F", help="fraction of the CPU the filter may use with --rate-hz, in (0, 1] "
                                     "(default: %(default)s)")
    p.add_argument("--kappa", type=number(float, float(KAPPA_MIN), float(KAPPA_MAX), unit="1/m"), default=100.0, metavar="K",
                   help="soft-min/soft-max sharpness recorded in the header, 1/m, in [1, 10000] (the kernel's "
                        "range; outside it the app only hovers) (default: %(default)s, as in the paper)")
    p.add_argument("--neighborhood", type=number(int, 0, 4, unit="voxels"), default=1, metavar="B",
                   help="cluster radius b in voxels (L-infinity), Eq. 10, 0..4 (default: %(default)s)")
    p.add_argument("--boxes", action=argparse.BooleanOptionalAction, default=True,
                   help="add one exact all-occupied box per voxel whose cluster wastes volume to the set-cover "
                        "candidates, so the sub-cover wastes nothing (--no-boxes: the paper's clusters only) "
                        "(default: on)")
    p.add_argument("--merge-cost", choices=COVER_COSTS, default=DEFAULT_MERGE_COST,
                   help="merge cost: 'paper' = W of the union (Eq. 13), 'delta' = the free volume a merge adds, 'best' = both, keep the better; see `polycc cover --help` (default: %(default)s)")
    p.add_argument("--mc-samples", type=number(int, MC_SAMPLES_MIN, 100_000_000), default=100_000, metavar="S",
                   help=f"Monte Carlo samples per candidate for conservativeness, at least {MC_SAMPLES_MIN:,} "
                        "(default: %(default)s)")
    add_scene_options(p)
    p.set_defaults(func=run)


def _budget(args) -> Budget:
    rate_cycles = None
    if args.rate_hz is not None:
        rate_cycles = cycle_model.cycle_budget(args.rate_hz, args.cpu_share)
    return Budget(int(args.flash_kb * 1024), args.max_halfplanes, rate_cycles)


def run(args: argparse.Namespace) -> int:
    t_all = time.perf_counter()
    budget = _budget(args)
    out = output_dir(args.output)
    settings = resolve_scene_settings(args)
    scene, occ = load_scene_and_occupancy(args.scene, args)
    t = time.perf_counter()
    with console.status("cover: clusters, set cover, merging"):
        family = build_cover(occ, b=args.neighborhood, cost=args.merge_cost, boxes=args.boxes)
    t_cover = time.perf_counter() - t
    out.mkdir(parents=True, exist_ok=True)
    family.meta.update({"scene_sha256": scene.sha256})
    family.save(out / "cover.npz")

    t = time.perf_counter()
    with progress_bar("budget: reduce, quantize, measure candidates", 1) as update:
        best, cands, binding = select(family, budget, mc_samples=args.mc_samples, progress=lambda d, n: update(d / n))
    t_budget = time.perf_counter() - t
    us = cycle_model.estimate_us(best.packed)

    rec = settings.as_record()
    opts = {
        **{k: v for k, v in rec.items() if k != "world_matrix"}, "flash_kb": args.flash_kb,
        "max_halfplanes": args.max_halfplanes, "rate_hz": args.rate_hz, "cpu_share": args.cpu_share,
        "kappa": args.kappa, "neighborhood": args.neighborhood, "boxes": args.boxes, "merge_cost": args.merge_cost,
        "mc_samples": args.mc_samples,
    }
    cons_text = f"{best.conservativeness:.4f} +- {best.conservativeness_ci:.4f} (95% CI)"
    stats = {
        "splats_read": scene.stats.read, "splats_kept": scene.stats.kept, "scene_stats": scene.stats.as_dict(),
        "voxels": len(occ), "voxel_size_m": occ.voxel_size, "occupied_volume_m3": occ.volume(),
        "n_subcover": family.n_max, "n": best.n, "halfplanes": best.n_planes,
        "halfplanes_before_reduction": best.planes_before, "halfplanes_dropped": best.dropped,
        "halfplanes_merged": best.merged,
        "normals": best.n_normals, "normals_before_reduction": best.normals_before,
        "normal_table_cap": best.max_normals, "quantum_m": float(best.packed.quantum),
        "bytes": best.bytes, "budget_bytes": budget.flash_bytes, "bytes_per_halfplane": best.bytes / best.n_planes,
        "max_halfplanes": min(best.caps.values()), "binding_budget": binding,
        "conservativeness": best.conservativeness, "conservativeness_ci95": best.conservativeness_ci,
        "union_volume_m3": best.union_volume, "modelled_us": us,
        "floater_filter": occ.stats.get("floater_filter"),
        "candidates": [{"n": c.n, "normal_table_cap": c.max_normals, "normals": c.n_normals, "halfplanes": c.n_planes, "dropped": c.dropped, "bytes": c.bytes,
                        "conservativeness": c.conservativeness, "ci95": c.conservativeness_ci} for c in cands],
    }
    transform = None
    if args.transform or args.scale:
        transform = rec["world_matrix"]
    meta = {
        "scene_settings": rec, "floater_line": floater_text(occ.stats) or "none (--min-splats-per-voxel 1)",
        "kappa": args.kappa, "budget_bytes": budget.flash_bytes, "max_planes": min(best.caps.values()),
        "binding": binding, "conservativeness_text": cons_text, "options": opts, "transform": transform,
        "scene": {"name": Path(args.scene).name, "path": str(args.scene), "sha256": scene.sha256},
        "stats": stats,
    }
    write_outputs(out, best.packed, meta)

    verts = []
    for h in best.packed.polytopes():
        h64 = h.astype(np.float64)
        c = best.packed.polys[len(verts)]
        v = polytope_vertices(h64, np.array([c["cx"], c["cy"], c["cz"]], np.float64))
        verts.append(v if v is not None else np.zeros((1, 3)))
    per_n: dict = {}  # the least conservative candidate (over the table caps) at each n
    for c in cands:
        if c.n not in per_n or c.conservativeness < per_n[c.n].conservativeness:
            per_n[c.n] = c
    curve = [(c.n, c.conservativeness, c.conservativeness_ci) for _, c in sorted(per_n.items())]
    write_report(out / "report.png", scene.ellipsoids.centers, verts, curve, (best.n, best.conservativeness),
                 f"{Path(args.scene).name}: n = {best.n}, {best.n_planes} half-planes, {best.bytes} B of "
                 f"{budget.flash_bytes} B, conservativeness {best.conservativeness:.4f}")

    rows = [
        ("scene", f"{args.scene} (sha256 {scene.sha256[:12]}...)"),
        ("splats read / kept", f"{scene.stats.read:,} / {scene.stats.kept:,}"),
        ("invalid / opacity-filtered / cropped", f"{scene.stats.invalid:,} / {scene.stats.filtered_opacity:,} / {scene.stats.cropped:,}"),
        ("voxels (g)", f"{len(occ):,} ({occ.voxel_size:g} m)"),
        *([("floater filter", floater_text(occ.stats))] if floater_text(occ.stats) else []),
        ("N before merging (sub-cover)", f"{family.n_max:,}"),
        ("n chosen", f"{best.n}"),
        ("half-planes (dropped by reduction / merged)", f"{best.n_planes:,} ({best.dropped:,} / {best.merged:,})"),
        ("shared normals (table cap)", f"{best.n_normals:,} ({best.max_normals or 'uncapped'}), quantum {float(best.packed.quantum):g} m"),
        ("bytes / budget", f"{best.bytes:,} / {budget.flash_bytes:,} ({best.bytes / best.n_planes:.1f} B per half-plane)"),
        ("binding budget", binding),
        ("conservativeness Vol(union)/Vol(V+)", cons_text),
        ("modelled on-board time @168 MHz", f"typical {us['typical_us']:.0f} us, worst {us['worst_us']:.0f} us"),
        ("CPU at 500 Hz (typical / worst)", f"{us['typical_us'] * 500 / 1e4:.0f}% / {us['worst_us'] * 500 / 1e4:.0f}%"
                                            + ("" if args.rate_hz else "  (bound it with --rate-hz)")),
        ("time: occupancy / cover / budget", f"{occ.stats.get('time_s', 0):.1f} / {t_cover:.1f} / {t_budget:.1f} s"),
        ("outputs", f"{out}/polytopes.h, manifest.json, scene.bin, cover.npz, report.png"),
    ]
    print_summary("polycc build", rows)
    console.print(f"build: n = {best.n}, {best.n_planes} half-planes, {best.bytes} bytes -> {out / 'polytopes.h'} "
                  f"({time.perf_counter() - t_all:.1f} s)")
    return 0
