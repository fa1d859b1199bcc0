"""`polycc verify OUT SCENE`: independent certification of a cover or a build (:func:`polycc.verify.api.verify`)."""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from polycc.cli.argtypes import number
from polycc.cli.console import StageProgress, console
from polycc.cli.scene_args import (
    add_scene_options,
    check_scene_file,
    load_scene_and_occupancy,
    recorded_settings,
    resolve_scene_settings,
)
from polycc.errors import PolyccError
from polycc.occupancy.floaters import floater_text
from polycc.verify import verify


def register(sub) -> None:
    p = sub.add_parser(
        "verify",
        help="independently certify a cover: every voxel and every splat ellipsoid covered (exit 0 = safe)",
        description="Re-derive the occupied voxels and splat ellipsoids from SCENE and check the cover family "
                    "in OUT without using the cover code: (a) all 8 corners of every occupied voxel inside one "
                    "polytope, at the listed levels directly and at every level n = N..1 by a merge certificate; "
                    "(b) points sampled on and inside every kept ellipsoid inside some polytope; (c) Monte Carlo "
                    "conservativeness Vol(U H^n)/Vol(V+) with a 95 % confidence interval. Tolerances count against "
                    "the cover. The scene options default to the ones OUT was made with (an explicit option that "
                    "disagrees is an error). With a floater filter (--min-splats-per-voxel > 1) the cover is "
                    "certified against the FILTERED occupancy: the splats that touch removed voxels are listed and "
                    "left out of (b). Exit 0 only if (a) and (b) hold; the last line holds the figures.",
    )
    p.add_argument("out", metavar="OUT",
                   help="directory written by `polycc build` (its manifest.json: the stored, decoded polytopes the C "
                        "reads are checked) or by `polycc cover` (its cover.npz: the merge family)")
    p.add_argument("scene", metavar="SCENE", help="the scene file the cover was made from")
    add_scene_options(p, from_dir=True)
    v = p.add_argument_group("verify options")
    v.add_argument("--levels", default="default", metavar="N1,N2,...|all|default",
                   help="levels n checked directly with (a), (b), (c): a comma list, 'all' (every n, slow) or "
                        "'default' = N,150,100,50,30,10,1 (default: %(default)s)")
    v.add_argument("--all-levels-certificate", action=argparse.BooleanOptionalAction, default=True,
                   help="also certify (a) at every level n = N..1 through the merge sequence (default: on)")
    v.add_argument("--samples-per-ellipsoid", type=number(int, 64, 100_000), default=64, metavar="K",
                   help="points sampled per ellipsoid for (b), at least 64 (default: %(default)s)")
    v.add_argument("--min-samples", type=number(int, 0, 1_000_000_000), default=1_000_000, metavar="M",
                   help="at least this many points in total per level for (b) (default: %(default)s)")
    v.add_argument("--mc-samples", type=number(int, 1000, 100_000_000), default=200_000, metavar="S",
                   help="Monte Carlo samples per level for (c) (default: %(default)s)")
    v.add_argument("--seed", type=int, default=0, help="random seed for (b) and (c) (default: %(default)s)")
    v.add_argument("--report", metavar="FILE.json", help="also write the figures as JSON (default: none)")
    p.set_defaults(func=run)


def _levels(text: str) -> list[int] | str:
    if text == "all":
        return "all"
    try:
        return sorted({int(x) for x in text.split(",") if x.strip()}, reverse=True)
    except ValueError:
        raise PolyccError(f"--levels {text!r}: expected 'all', 'default' or whole numbers like 150,50,10") from None


def run(args: argparse.Namespace) -> int:
    path = Path(args.out)
    if not path.exists():
        raise PolyccError(f"{path}: no such folder or file; give the output of `polycc build` or `polycc cover`")
    recorded, rec_scene = recorded_settings(path)
    check_scene_file(args.scene, rec_scene, str(path))
    st = resolve_scene_settings(args, recorded, str(path))
    scene, grid = load_scene_and_occupancy(args.scene, args)
    ell = scene.ellipsoids
    loss = grid.floater_loss
    if st.min_splats_per_voxel > 1:
        console.print(f"certifying against the FILTERED occupancy (--min-splats-per-voxel {st.min_splats_per_voxel}, "
                      f"g = {grid.voxel_size:g} m): {floater_text(grid.stats)}; those splats are left out of (b)",
                      soft_wrap=True)
        if loss is not None and len(loss["splats"]):
            keep = np.ones(len(ell), bool)
            keep[loss["splats"]] = False
            ell = ell.subset(keep)
    else:
        console.print(f"certifying against the exact occupancy of {args.scene} (g = {grid.voxel_size:g} m, "
                      "no floater filter): every kept splat ellipsoid must be inside the cover", soft_wrap=True)
    if scene.stats.dropped_isolated:
        r, m = st.drop_isolated
        console.print(f"the splat-level floater filter (--drop-isolated {r:g},{m}) dropped "
                      f"{scene.stats.dropped_isolated:,} splats in {len(scene.dropped_groups):,} groups, as the "
                      "build did: certifying against the kept splats", soft_wrap=True)
    centers, axes = ell.centers, ell.axes()
    if scene.triangles is not None and len(scene.triangles):  # a mesh: points on every triangle must be covered too
        from polycc.occupancy.triangles import triangle_samples

        pts = triangle_samples(scene.triangles)
        centers, axes = np.concatenate([centers, pts]), np.concatenate([axes, np.zeros((len(pts), 3, 3))])
        console.print(f"and {len(pts):,} points on the {len(scene.triangles):,} mesh triangles (corners, edge "
                      "midpoints, centroids, random)", soft_wrap=True)
    levels = None if args.levels == "default" else _levels(args.levels)
    t0 = time.perf_counter()
    with StageProgress() as progress:
        rep = verify(path, centers, axes, grid.indices, grid.voxel_size, grid.origin,
                     levels=levels, all_levels_certificate=args.all_levels_certificate,
                     samples_per_ellipsoid=args.samples_per_ellipsoid, min_samples=args.min_samples,
                     mc_samples=args.mc_samples, seed=args.seed, progress=progress)
    rep.occupancy = "filtered" if st.min_splats_per_voxel > 1 else "exact"
    rep.floater_filter = grid.stats.get("floater_filter")
    if rep.stored:
        console.print(f"checked the {len(rep.levels) and rep.levels[0].n} stored polytopes of {path} (decoded values, "
                      "as the C reads them)")
    if not rep.grid_matches_cover:
        console.print("[yellow]note: the voxels of SCENE with these options differ from the ones the cover was built "
                      "from; pass the same scene options as to `polycc cover`[/yellow]")
    elapsed = time.perf_counter() - t0

    from rich.table import Table

    t = Table(title=f"polycc verify: {path}", header_style="bold")
    for h in ("n", "half-planes", "voxels checked", "uncovered voxels", "points sampled", "uncovered points",
              "conservativeness (95 % CI)"):
        t.add_column(h, justify="right", overflow="fold")
    for l in rep.levels:
        t.add_row(str(l.n), f"{l.halfplanes:,}", f"{l.voxels_checked:,}", str(l.voxels_uncovered),
                  f"{l.points_sampled:,}", str(l.points_uncovered),
                  f"{l.conservativeness:.3f} +/- {l.conservativeness_ci:.3f}")
    console.print(t)
    if rep.certificate_failures:
        console.print(f"[red]certificate failed at levels {[f['n'] for f in rep.certificate_failures][:20]}[/red]")
    if args.report:
        Path(args.report).write_text(json.dumps({**rep.as_dict(), "time_s": elapsed}, indent=2))
    vox = sum(l.voxels_checked for l in rep.levels)
    pts = sum(l.points_sampled for l in rep.levels)
    unv = sum(l.voxels_uncovered for l in rep.levels) + sum(max(f["uncovered_voxels"],
                                                                1) for f in rep.certificate_failures)
    unp = sum(l.points_uncovered for l in rep.levels)
    cons = " ".join(f"n={l.n}:{l.conservativeness:.3f}+/-{l.conservativeness_ci:.3f}" for l in rep.levels)
    occ_text = ("exact occupancy" if rep.occupancy == "exact" else
                f"FILTERED occupancy (M = {st.min_splats_per_voxel}; "
                f"{(rep.floater_filter or {}).get('splats_not_fully_covered', 0):,} splats not covered)")
    print(f"verify: {'PASS' if rep.ok else 'FAIL'} against the {occ_text} | levels checked directly {len(rep.levels)}, "
          "by certificate "
          f"{rep.certificate_levels} | voxels checked {vox:,} | points sampled {pts:,} | uncovered voxels {unv:,} "
          f"points {unp:,} | conservativeness (95 % CI) {cons}")
    return 0 if rep.ok else 1
