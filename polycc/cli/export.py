"""`polycc export DIR -o cover.glb`: the stored polytopes of a build as a mesh (glb, obj, ply)."""

from __future__ import annotations

import argparse
from pathlib import Path

from polycc.cli.console import console
from polycc.view.meshes import FORMATS, FRAMES, export


def register(sub) -> None:
    p = sub.add_parser(
        "export",
        help="write the stored polytopes of a build as a mesh (glb, obj, ply) for MeshLab, Blender, SuperSplat",
        description="Write each stored polytope of DIR (manifest.json: the values exactly as the C decodes them) as "
                    "the convex hull of its vertices, one colour per polytope. --frame world (default) writes "
                    "metres in the build's world frame; --frame trainer maps them back to the scene file's frame "
                    "(the inverse of --transform/--scale), to overlay the cover on the splats in SuperSplat.",
    )
    p.add_argument("dir", metavar="DIR", help="folder written by `polycc build`")
    p.add_argument("-o", "--output", metavar="OUT", help="output file (default: DIR/cover.FORMAT)")
    p.add_argument("--format", choices=FORMATS, default=None,
                   help="mesh format (default: from OUT's extension, else glb)")
    p.add_argument("--frame", choices=FRAMES, default="world",
                   help="world = metres, the build's frame; trainer = the scene file's own frame "
                        "(default: %(default)s)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    fmt = args.format or (Path(args.output).suffix.lstrip(".").lower() if args.output else "glb")
    out = Path(args.output) if args.output else Path(args.dir) / f"cover.{fmt}"
    path, n = export(args.dir, out, fmt, args.frame)
    console.print(f"export: {n} polytopes ({args.frame} frame) -> {path}", soft_wrap=True)
    return 0
