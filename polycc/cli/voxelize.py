"""`polycc voxelize SCENE -o FILE.npz`: exact voxel occupancy of a splat scene."""

from __future__ import annotations

import argparse

from polycc.cli.console import console
from polycc.cli.scene_args import (
    add_scene_options,
    load_scene_and_occupancy,
    occupancy_summary_rows,
    print_summary,
    scene_summary_rows,
)


def register(sub) -> None:
    p = sub.add_parser(
        "voxelize",
        help="exact voxel occupancy of a splat scene (.npz)",
        description="Read a splat scene and write its exact voxel occupancy grid V+: a voxel is occupied iff it "
                    "meets at least one kept splat ellipsoid. Output: .npz with integer (N,3) voxel indices "
                    "(voxel i spans [origin + i*g, origin + (i+1)*g] metres), voxel_size g, origin and counts.",
    )
    p.add_argument("scene", metavar="SCENE",
                   help="3DGS .ply, .compressed.ply, .splat, .spz, point-cloud .ply (x y z [radius]) or mesh .ply")
    p.add_argument("-o", "--output", required=True, metavar="FILE.npz", help="where to write the occupancy grid")
    add_scene_options(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    scene, occ = load_scene_and_occupancy(args.scene, args)
    occ.save(args.output)
    print_summary("polycc "
                  "voxelize", scene_summary_rows(scene) + occupancy_summary_rows(occ) + [("written", args.output)])
    console.print(f"occupancy: {len(occ):,} voxels at g = {occ.voxel_size:g} m -> {args.output}")
    return 0
