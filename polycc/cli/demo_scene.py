"""`polycc demo-scene OUT.ply`: write the synthetic flight arena as a 3DGS .ply (metres)."""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from polycc.errors import PolyccError

HELP = "write a synthetic flight arena (floor, hoops, poles, boxes) as a 3DGS .ply in metres"


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "demo-scene",
        help=HELP,
        description=(
            "Write a synthetic 6 m x 6 m x 3 m flight arena (z up, floor at z = 0 m): a floor, "
            "three upright hoops on stands, three poles and three boxes, as about 200k flat "
            "Gaussian splats (tangent sigmas 2 mm to 2 cm, normal sigma 1-2 mm). The .ply uses "
            "the graphdeco-inria 3DGS layout (62 float32 properties, pre-activation values), "
            "positions and sizes in metres. A sidecar OUT.json describes the arena: hoops "
            "(centre, unit normal, opening radius in m), poles, boxes, and start/goal points "
            "in m for a flight through each hoop."
        ),
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    p.add_argument("out", metavar="OUT.ply", help="output .ply path; the description goes to OUT.json next to it")
    p.add_argument(
        "--seed", type=int, default=0,
        help="random seed for splat placement, sizes, opacities and colour noise (the layout is fixed)",
    )
    p.add_argument("--ascii", action="store_true", help="write an ASCII .ply instead of binary little-endian")
    p.set_defaults(func=run)


def run(args) -> int:
    from polycc.cli.console import console, summary_table
    from polycc.demo.arena import build_demo_arena
    from polycc.scene.writers import write_gaussian_ply

    out = Path(args.out)
    if out.suffix.lower() != ".ply":
        raise PolyccError(f"{out}: the output must be a .ply file; give a path ending in .ply")
    sidecar = out.with_suffix(".json")
    t0 = time.perf_counter()
    with console.status("sampling the arena"):
        ell, desc = build_demo_arena(args.seed)
    t1 = time.perf_counter()
    with console.status(f"writing {out}"):
        write_gaussian_ply(out, ell, binary=not args.ascii)
        try:
            sidecar.write_text(json.dumps(desc, indent=2) + "\n")
        except OSError as exc:
            raise PolyccError(f"{sidecar}: cannot write the arena description ({exc.strerror or exc}); "
                              "choose a writable output path") from exc
    t2 = time.perf_counter()

    lo, hi = desc["bounds"]["min"], desc["bounds"]["max"]
    rows = [
        ("splats", f"{len(ell):,}"),
        ("bounds (m)", "  ".join(f"{a:+.2f}..{b:+.2f}" for a, b in zip(lo, hi))),
    ]
    for h in desc["hoops"]:
        c = ", ".join(f"{v:.2f}" for v in h["center"])
        rows.append((f"{h['name']} (m)", f"centre ({c}), opening radius {h['radius']:.2f}"))
    rows += [
        ("poles / boxes", f"{len(desc['poles'])} / {len(desc['boxes'])}"),
        ("ply", f"{out} ({'ascii' if args.ascii else 'binary'}, {out.stat().st_size / 1e6:.1f} MB)"),
        ("description", str(sidecar)),
        ("time (s)", f"sample {t1 - t0:.2f}, write {t2 - t1:.2f}"),
    ]
    table = summary_table("demo arena", rows)
    console.print(table)
    return 0
