"""`polycc cover SCENE -o OUT/`: certified polytope cover family (PolyMerge Sec. V-B, V-C)."""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from polycc.cli.argtypes import add_parallel_options, number
from polycc.cli.console import console, progress_bar, summary_table
from polycc.cli.scene_args import (
    add_scene_options,
    load_scene_and_occupancy,
    output_dir,
    resolve_scene_settings,
)
from polycc.cover.build import COVER_COSTS, DEFAULT_MERGE_COST, build_cover, build_families, conservativeness
from polycc.cover.family import CoverFamily
from polycc.cover.merge import MERGE_COSTS
from polycc.errors import PolyccError
from polycc.geometry.union_volume import in_voxels
from polycc.occupancy.floaters import floater_text
from polycc.parallel import make_runner

PAPER_LEVELS = (10, 30, 50, 100, 150)


def register(sub) -> None:
    p = sub.add_parser(
        "cover",
        help="certified convex-polytope cover family H^n, n = N..1 (cover.npz + plots)",
        description="Voxelize a splat scene, cover the occupied voxels with convex hulls of voxel clusters "
                    "(weighted set cover) and merge them pairwise down to one polytope. Writes OUT/cover.npz "
                    "(every H^n, half-planes n.p <= d with unit n, and vertices, metres), OUT/cover.json, "
                    "OUT/tradeoff.png and OUT/cover_n<k>.png. Check the result with `polycc verify OUT SCENE`.",
    )
    p.add_argument("scene", metavar="SCENE", help="3DGS .ply, .compressed.ply, .splat, .spz, point-cloud or mesh .ply")
    p.add_argument("-o", "--output", required=True, metavar="OUT", help="output directory (created if missing)")
    add_scene_options(p)
    c = p.add_argument_group("cover options")
    c.add_argument("--neighborhood", type=number(int, 0, 4, unit="voxels"), default=1, metavar="B",
                   help="cluster radius b in voxels: C_v holds the occupied voxels within L-inf distance b*g "
                        "of v (paper Eq. 10) (default: %(default)s)")
    c.add_argument("--merge-cost", choices=COVER_COSTS, default=DEFAULT_MERGE_COST,
                   help="pair cost for merging: 'paper' = W(A u B) (Eq. 13); 'delta' = W(A u B) - W(A) - W(B), "
                        "the free volume a merge adds; 'best' = run both (in parallel) and keep the family with the "
                        "lower measured conservativeness at n = 10..150 (default: %(default)s; see "
                        "bench/bench_cover.py)")
    c.add_argument("--boxes", action=argparse.BooleanOptionalAction, default=True,
                   help="add one exact all-occupied box per voxel whose cluster wastes volume to the set-cover "
                        "candidates, so the sub-cover wastes nothing (--no-boxes: the paper's clusters only) "
                        "(default: on)")
    c.add_argument("--refresh", choices=("lazy", "eager"), default="lazy",
                   help="after a merge, re-evaluate the new node's old neighbour pairs when they reach the top of "
                        "the heap (lazy) or at once (eager, exact greedy; slower) (default: %(default)s)")
    c.add_argument("--compare", action=argparse.BooleanOptionalAction, default=True,
                   help="with --merge-cost paper or delta, also run the other cost for the second curve of "
                        "tradeoff.png ('best' runs both anyway) (default: on)")
    c.add_argument("--plot-n", default="10,50,150", metavar="N1,N2,...",
                   help="write OUT/cover_n<k>.png for these n (comma list; values above N are skipped; empty = "
                        "none) (default: %(default)s)")
    c.add_argument("--mc-samples", type=number(int, 1000, 100_000_000), default=20_000, metavar="S",
                   help="Monte Carlo samples per level for the conservativeness curve in tradeoff.png "
                        "(default: %(default)s)")
    c.add_argument("--seed", type=int, default=0, help="random seed for the Monte Carlo estimates (default: 0)")
    add_parallel_options(p)
    p.set_defaults(func=run)


class _StageBar:
    """A progress bar opened on the first report (the merge stage knows its total only then)."""

    def __init__(self, label: str):
        self.label, self.cm, self.update = label, None, None

    def __call__(self, stage: str, done: int, total: int) -> None:
        if self.cm is None:
            self.cm = progress_bar(f"{self.label}: {stage}", total)
            self.update = self.cm.__enter__()
        self.update(done)

    def close(self) -> None:
        if self.cm is not None:
            self.cm.__exit__(None, None, None)


def build_pick(families: dict):
    """The family 'best' kept (the one whose meta records the selection)."""
    return next(f for f in families.values() if "selection" in f.meta)


def _parse_levels(text: str) -> list[int]:
    try:
        return [int(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise PolyccError(f"--plot-n {text!r}: expected whole numbers separated by commas, e.g. 10,50,150") from None


def curve_levels(N: int) -> list[int]:
    """n values for the trade-off curve: log-spaced over 1..N plus the paper's flight counts."""
    levels = set(np.unique(np.round(np.geomspace(1, N, 18)).astype(int)).tolist())
    levels |= {n for n in PAPER_LEVELS if n <= N}
    return sorted(levels)


def tradeoff_curve(fam: CoverFamily, samples: int, seed: int = 0) -> list[tuple[int, float, float]]:
    """[(n, conservativeness, ci95)] over :func:`curve_levels`."""
    occupied = in_voxels(fam.grid_indices, fam.origin, fam.voxel_size)
    return [(int(n), *conservativeness(fam, n, samples, seed + k, occupied)) for k,
            n in enumerate(curve_levels(fam.n_max))]


def run(args: argparse.Namespace) -> int:
    out = output_dir(args.output)
    plot_n = _parse_levels(args.plot_n)
    settings = resolve_scene_settings(args)
    with make_runner(args.jobs, args.dask) as runner:
        scene, grid = load_scene_and_occupancy(args.scene, args, runner)
        costs = [args.merge_cost]
        if args.merge_cost != "best" and args.compare:
            costs += [c for c in MERGE_COSTS if c != args.merge_cost]
        console.print(f"covering {len(grid):,} voxels (merge cost: {args.merge_cost}; {runner.where})")
        t0 = time.perf_counter()
        bar = _StageBar("cover")
        stages: dict = {}
        try:
            if args.merge_cost == "best":
                fam = build_cover(grid, args.neighborhood, "best", stages=stages, refresh=args.refresh,
                                  progress=bar, boxes=args.boxes, runner=runner)
                families = dict(stages["families"])
            else:
                families = build_families(grid, args.neighborhood, tuple(costs), bar, args.refresh, args.boxes,
                                          runner)
                fam = families[args.merge_cost]
        finally:
            bar.close()
        for f in families.values():
            f.meta["time_s"] = time.perf_counter() - t0
    fam.meta.update({
        "scene": str(scene.path), "scene_sha256": scene.sha256, "voxel_size": grid.voxel_size,
        "scene_settings": settings.as_record(), "floater_filter": grid.stats.get("floater_filter"),
    })
    path = fam.save(out)

    curves = {}
    with console.status("estimating conservativeness for tradeoff.png"):
        for cost, f in families.items():
            curves[cost] = tradeoff_curve(f, args.mc_samples, args.seed)
    from polycc.report.cover_plots import plot_cover_views, plot_tradeoff

    plot_tradeoff(curves, out / "tradeoff.png", title=f"{Path(args.scene).name}, g = {grid.voxel_size:g} m, "
                                                      f"b = {args.neighborhood}")
    written = [path.name, "tradeoff.png"]
    centers = scene.ellipsoids.centers
    for n in plot_n:
        if 1 <= n <= fam.n_max:
            plot_cover_views(fam.materialise(n), centers, out / f"cover_n{n}.png",
                             title=f"H^{n}: {n} polytopes, {fam.halfplane_count(n)} half-planes "
                                   f"({fam.meta['merge_cost']} cost)")
            written.append(f"cover_n{n}.png")
    summary = {
        "family": fam.meta,
        "tradeoff": {c: [{"n": n, "conservativeness": v, "ci95": e} for n, v, e in pts] for c, pts in curves.items()},
        "other_costs": {c: f.meta for c, f in families.items() if f is not fam},
    }
    (out / "cover.json").write_text(json.dumps(summary, indent=2, sort_keys=True))
    written.append("cover.json")

    t = fam.meta["timings_s"]
    rows = [
        ("occupied voxels |V+|", f"{len(grid):,}"),
        *([("floater filter", floater_text(grid.stats))] if floater_text(grid.stats) else []),
        ("neighbourhood b", str(args.neighborhood) + (" (+ exact boxes)" if args.boxes else " (clusters only)")),
        ("distinct cluster patterns", f"{fam.meta['clusters_distinct_patterns']:,}"),
        ("sub-cover size N", f"{fam.n_max:,}"),
        ("merge cost", fam.meta["merge_cost"] + (" (chosen by 'best': mean conservativeness n=10..150 "
                                                  + ", ".join(f"{c} {v:.4f}" for c, v in
                                                              fam.meta["selection"]["mean_conservativeness"].items())
                                                  + ")" if "selection" in fam.meta else "")),
        ("pair evaluations", f"{fam.meta['pair_evaluations']:,}"),
        ("tiles / where it ran", f"{fam.meta['tiles']['tiles']:,} of <= {fam.meta['tiles']['tile_voxels']:,} voxels / "
                                 f"{fam.meta['tiles']['where']}"),
        ("task time: clusters / set cover / merge / half-planes",
         " / ".join(f"{t[k]:.2f}" for k in ("clusters", "set_cover", "merge", "halfplanes")) + " s"
         + f" (wall {t['wall']:.1f} s)"),
    ]
    for cost, pts in curves.items():
        d = {n: (v, e) for n, v, e in pts}
        for n in PAPER_LEVELS:
            if n in d:
                rows.append((f"conservativeness n={n} ({cost})", f"{d[n][0]:.3f} +/- {d[n][1]:.3f}"))
    rows.append(("written", ", ".join(str(out / w) for w in written)))
    console.print(summary_table("polycc cover", rows))
    console.print(f"cover: N = {fam.n_max} polytopes from {len(grid):,} voxels -> {path}")
    return 0
