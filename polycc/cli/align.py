"""`polycc align SCENE -o transform.json`: a gravity-aligned, floor-at-z=0 transform, optionally metric."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from polycc.cli.argtypes import NEGATIVE_CHOICE_OPTIONS, NEGATIVE_VALUE_OPTIONS, number, numbers
from polycc.cli.console import console, warn
from polycc.cli.scene_args import add_scene_options, load_scene_from_args, print_summary, resolve_scene_settings
from polycc.errors import PolyccError
from polycc.scene.survey import AXES, align, extent_warning, robust_bounds


def register(sub) -> None:
    p = sub.add_parser(
        "align",
        help="write a gravity-aligned, floor-at-z=0 transform (JSON) for --transform, optionally to metres",
        description="Find the floor (RANSAC on the splat centres, or the axis --up names), rotate it level with "
                    "up = +z, put it at z = 0 and the middle of the robust bounds at x = y = 0, scale by --size "
                    "or --known-distance, and write OUT.json ({\"matrix\": 4x4}). It maps the FILE to the world "
                    "frame (any --transform/--scale given here are folded in), so use it alone afterwards: "
                    "`polycc build SCENE --transform OUT.json ...`.",
    )
    p.add_argument("scene", metavar="SCENE", help="any scene file polycc reads")
    p.add_argument("-o", "--output", required=True, metavar="OUT.json", help="where to write the transform")
    p.add_argument("--up", choices=["auto", *AXES], default="auto",
                   help="the scene's up direction: auto = the floor plane's normal toward the splats, or an axis "
                        "of the scene as read (a y-down capture: -y); with an axis, a floor plane within 20 deg of "
                        "it is used when found (default: %(default)s)")
    NEGATIVE_CHOICE_OPTIONS["--up"] = set(AXES)
    s = p.add_mutually_exclusive_group()
    s.add_argument("--size", type=number(float, 0.0, lo_open=True, unit="m"), metavar="L",
                   help="scale so that the longest side of the robust bounds (0.5-99.5 %% of the centres) is L "
                        "metres (default: keep the units)")
    s.add_argument("--known-distance", type=numbers(7, "x1,y1,z1,x2,y2,z2,metres"), metavar="P1,P2,M",
                   help="scale so that two points of the scene as read (x1,y1,z1 and x2,y2,z2, e.g. picked in "
                        "SuperSplat) are M metres apart")
    NEGATIVE_VALUE_OPTIONS.add("--known-distance")
    add_scene_options(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    settings = resolve_scene_settings(args)
    scene = load_scene_from_args(args.scene, args)
    c = scene.ellipsoids.centers
    known = None
    if args.known_distance is not None:
        k = np.asarray(args.known_distance)
        if not k[6] > 0 or np.allclose(k[:3], k[3:6]):
            raise PolyccError("--known-distance: give two different points and a positive distance in metres")
        known = (k[:3], k[3:6], float(k[6]))
    a = align(c, args.up, args.size, known)
    W = np.asarray(settings.world_matrix, np.float64)
    M = a.matrix @ W  # file -> scene as read -> aligned
    out = Path(args.output)
    rec = {"matrix": M.tolist(), "polycc_align": {
        "scene": str(args.scene), "sha256": scene.sha256, "up": args.up, "floor_normal": a.floor.up.tolist(),
        "floor_height": a.floor.height, "floor_method": a.floor.method, "floor_inliers": a.floor.inliers,
        "scale": a.scale, "scale_source": a.scale_source, "robust_extent_m": a.extent.tolist(),
        "folded_in": {"transform": settings.transform, "scale": settings.scale}}}
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(rec, indent=2) + "\n")
    except OSError as exc:
        raise PolyccError(f"-o {out}: cannot write ({exc.strerror or exc}); choose a writable path") from None
    q = c @ a.matrix[:3, :3].T + a.matrix[:3, 3]
    lo, hi = robust_bounds(q)
    rows = [("floor", a.floor.method), ("up in the scene as read", "[" + ", ".join(f"{x:.3f}" for x in a.floor.up)
                                        + "]"),
            ("splats on the floor plane", f"{100 * a.floor.inliers:.1f} %"),
            ("scale", f"{a.scale:.6g} ({a.scale_source})"),
            ("aligned robust bounds lo", "[" + ", ".join(f"{x:.3f}" for x in lo) + "] m"),
            ("aligned robust bounds hi", "[" + ", ".join(f"{x:.3f}" for x in hi) + "] m"),
            ("written", str(out))]
    print_summary(f"polycc align: {args.scene}", rows)
    if a.floor.uncertain:
        warn("no floor plane found: up is the least-spread direction and its sign is a guess; check with "
             "`polycc info --transform OUT.json` or pass --up")
    msg = extent_warning(lo, hi)
    if msg:
        warn(msg.replace("put it in metres with `polycc align SCENE --size L -o t.json` and --transform t.json",
                         "pass --size L or --known-distance to `polycc align`"))
    console.print(f"align: -> {out} (use: --transform {out})", soft_wrap=True)
    return 0
