"""`polycc info SCENE`: what a scene looks like with every scene option applied, before any heavy work."""

from __future__ import annotations

import argparse

import numpy as np
from rich.table import Table

from polycc.cli.argtypes import number
from polycc.cli.console import console, warn
from polycc.cli.scene_args import (
    add_scene_options,
    load_scene_from_args,
    print_summary,
    resolve_scene_settings,
    scene_summary_rows,
)
from polycc.occupancy.estimate import HUGE_SPLAT_VOXELS, estimate
from polycc.scene.survey import detect_floor, extent_warning, isolated_groups, robust_bounds, splat_groups


def register(sub) -> None:
    p = sub.add_parser(
        "info",
        help="splat count, bounds, outliers, splat sizes, floor and up axis, voxel count and time estimate",
        description="Print, for SCENE with every scene option applied (units: metres once --transform/--scale "
                    "are right): the splat count; robust bounds (0.5/99.5 percentiles of the centres) and full "
                    "bounds; outlier groups (far, isolated splats: centres in cells of side --group-radius that "
                    "touch no other group); the distribution of splat sizes; the floor plane and up axis (RANSAC on "
                    "the centres); and the estimated voxel count and voxelization time at --voxel. Warns when the "
                    "extent does not look metric (over 20 m or under 0.2 m). Reads nothing but the scene.",
    )
    p.add_argument("scene", metavar="SCENE", help="any scene file polycc reads (.ply, .compressed.ply, .splat, .spz)")
    p.add_argument("--group-radius", type=number(float, 0.0, lo_open=True, unit="scene units"), default=None,
                   metavar="R", help="cell side for outlier groups, in scene units (metres after the transform) "
                                     "(default: 2 %% of the robust diagonal)")
    p.add_argument("--no-timing", action="store_true",
                   help="skip the timed voxelization sample (the time estimate then uses a nominal rate)")
    add_scene_options(p)
    p.set_defaults(func=run)


def _v(x) -> str:
    return "[" + ", ".join(f"{float(a):.3g}" for a in x) + "]"


def run(args: argparse.Namespace) -> int:
    settings = resolve_scene_settings(args)
    scene = load_scene_from_args(args.scene, args)
    ell = scene.ellipsoids
    c = ell.centers
    lo, hi = robust_bounds(c)
    flo, fhi = ell.bounds()
    rows = scene_summary_rows(scene)
    rows += [(k, str(v)) for k, v in scene.info.items() if k in ("format", "coordinate_system", "frame_note")]
    rows += [
        ("robust bounds (0.5-99.5 %) lo", _v(lo)), ("robust bounds hi", _v(hi)),
        ("robust extent", _v(hi - lo)),
        ("full bounds (ellipsoids) lo", _v(flo)), ("full bounds hi", _v(fhi)),
    ]
    print_summary(f"polycc info: {args.scene}", rows)

    # outlier groups
    diag = float(np.linalg.norm(hi - lo))
    radius = args.group_radius or 0.02 * diag
    console.print("grouping splats...", soft_wrap=True) if not console.is_terminal else None
    groups = splat_groups(c, radius)
    iso = isolated_groups(c, groups, max_splats=max(10, int(0.001 * len(c))))
    n_iso = int(groups.sizes[groups.sizes < max(10, int(0.001 * len(c)))].sum())
    t = Table(title=f"outlier groups (cells of {radius:.3g}; {len(groups.sizes):,} groups, main body "
                    f"{int(groups.sizes[0]):,} splats; {n_iso:,} splats in small groups)", header_style="bold")
    for h in ("splats", "centroid", "distance to main body"):
        t.add_column(h, justify="right", overflow="fold")
    for g in iso:
        t.add_row(f"{g.count:,}", _v(g.centroid), f"{g.gap:.3g}")
    console.print(t)

    # splat sizes (k-sigma semi-axes)
    a = ell.k * ell.sigmas.max(axis=1)
    pct = np.percentile(a, [50, 90, 99, 99.9, 100])
    t = Table(title=f"splat sizes: largest {ell.k:g}-sigma semi-axis", header_style="bold")
    for h in ("median", "90 %", "99 %", "99.9 %", "max", f"> {settings.voxel:g} (voxel)", "> 0.5 m"):
        t.add_column(h, justify="right")
    t.add_row(*[f"{x:.3g}" for x in pct], f"{int((a > settings.voxel).sum()):,}", f"{int((a > 0.5).sum()):,}")
    console.print(t)

    fl = detect_floor(c)
    axis = ["x", "y", "z"][int(np.argmax(np.abs(fl.up)))]
    sign = "+" if fl.up[int(np.argmax(np.abs(fl.up)))] > 0 else "-"
    ang = float(np.degrees(np.arccos(min(1.0, abs(float(np.max(np.abs(fl.up))))))))
    rows = [("method", fl.method), ("up (unit normal)", _v(fl.up)),
            ("nearest axis", f"{sign}{axis} ({ang:.1f} deg off)"),
            ("floor height along up", f"{fl.height:.4g}"),
            ("splats on the plane / on one side", f"{100 * fl.inliers:.1f} % / {100 * fl.one_sided:.0f} %")]
    if fl.uncertain:
        rows.append(("note", "uncertain: pass --up to `polycc align`"))
    print_summary("floor and up axis", rows)

    est = estimate(ell, settings.voxel, timed=not args.no_timing)
    rows = [("voxel", f"{settings.voxel:g} m"), ("voxels, at least (splat centres)", f"{est.voxels_at_least:,}"),
            ("voxels, at most (sum over splats)", f"{est.voxels_at_most:.3g}"),
            ("estimated voxelize time", f"{est.seconds:.3g} s" + ("" if not args.no_timing else " (nominal)")),
            ("peak memory, rough", f"{est.memory_gb:.2f} GB"),
            (f"splats over {HUGE_SPLAT_VOXELS:,} voxels each", f"{est.huge_splats:,}")]
    print_summary(f"size at --voxel {settings.voxel:g}", rows)
    msg = extent_warning(lo, hi)
    if msg:
        warn(msg)
    console.print(f"info: {len(ell):,} splats, robust extent {_v(hi - lo)}, up {sign}{axis}, "
                  f"~{est.voxels_at_most:.3g} voxels at {settings.voxel:g} m", soft_wrap=True)
    return 0
