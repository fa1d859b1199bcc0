"""`polycc plan DIR --start X,Y,Z --goal X,Y,Z`: a certified path through a build's free space."""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from polycc.cli.argtypes import NEGATIVE_VALUE_OPTIONS, add_point_option, number, numbers
from polycc.errors import PolyccError

HELP = "plan a path through the certified free space of a build (waypoints, clearances, plan.png, plan.json)"


def add_plan_options(p, with_radius: bool = True) -> None:
    """--margin, --grid, --bounds (and --radius): shared by `polycc plan` and `polycc sim --plan`."""
    g = p.add_argument_group("planning on the certified free space")
    if with_radius:
        g.add_argument("--radius", type=number(float, 0.0, 10.0, unit="m"), default=0.1, metavar="R",
                       help="agent radius, m: the app's polycc.radius the drone flies with (default: %(default)s)")
    g.add_argument("--margin", type=number(float, 0.0, 2.0, unit="m"), default=0.05, metavar="M",
                   help="certified clearance kept beyond the radius along the path, m; also the distance at which "
                        "a follower switches to the next waypoint (default: %(default)s)")
    g.add_argument("--grid", type=number(float, 0.01, 1.0, unit="m"), default=0.05, metavar="G",
                   help="planning grid spacing, m (default: %(default)s)")
    g.add_argument("--bounds", type=numbers(6, "x0,y0,z0,x1,y1,z1 in metres"), default=None,
                   metavar="X0,Y0,Z0,X1,Y1,Z1",
                   help="the map box, m: nothing is planned outside it (default: the box of the stored polytopes)")
    NEGATIVE_VALUE_OPTIONS.add("--bounds")


def nav_map(out: Path, args, radius: float):
    """The NavMap of build folder ``out`` for the parsed plan options (with a spinner)."""
    from polycc.cli.console import console
    from polycc.plan.planner import NavMap

    bounds = None if args.bounds is None else (np.array(args.bounds[:3]), np.array(args.bounds[3:]))
    with console.status("certifying the free space on the planning grid"):
        return NavMap.from_build(out, radius=radius, margin=args.margin, spacing=args.grid, bounds=bounds)


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "plan",
        help=HELP,
        description=(
            "Plans from --start to --goal through the free space the drone's barrier certifies: on the stored "
            "polytopes of DIR (scene.bin, exactly as the C decodes them) at the agent --radius, every point of the "
            "path has a certified lower bound of psi >= --margin (docs/planning.md). A* on a --grid m grid of cells "
            "certified free as a whole, then shortcuts checked against the stored half-planes. Prints the waypoints "
            "with their clearance (psi of the on-board kernel, and its certified lower bound) and writes "
            "DIR/plan.png and the plan as JSON (DIR/plan.json, or --json FILE) for `polycc sim --plan` and "
            "`polycc fly`. When there is no path (start or goal outside the map, inside an obstacle, or enclosed) "
            "it says which, and exits 3."
        ),
    )
    p.add_argument("out", metavar="DIR", help="build folder (from `polycc build`: scene.bin and manifest.json)")
    add_point_option(p, "--start", required=True, help="start position, m (world frame)")
    add_point_option(p, "--goal", required=True, help="goal position, m (world frame)")
    add_plan_options(p)
    p.add_argument("--json", metavar="FILE", help="where to write the plan (default: DIR/plan.json)")
    p.add_argument("--plot", metavar="FILE.png", help="plan views and psi along the path (default: DIR/plan.png)")
    p.set_defaults(func=run)


class NoPath(PolyccError):
    exit_code = 3


def run(args) -> int:
    from rich.table import Table

    from polycc.cli.console import console
    from polycc.onboard.layout import stored_vertices
    from polycc.plan.planner import NoPathError
    from polycc.report.flights import plot_plan

    out = Path(args.out)
    t0 = time.perf_counter()
    nav = nav_map(out, args, args.radius)
    try:
        plan = nav.plan(args.start, args.goal)
    except NoPathError as exc:
        raise NoPath(f"no path ({exc.reason}): {exc}") from None
    with console.status("evaluating the on-board barrier along the plan"):
        nav.annotate(plan)
    way = plan.waypoints
    seg_len = np.linalg.norm(np.diff(way, axis=0), axis=1)
    table = Table(title=f"polycc plan: {len(way)} waypoints, r = {plan.radius:g} m, margin {plan.margin:g} m",
                  header_style="bold",
                  caption="psi: the on-board kernel's value (float32 reference), psi >=: its certified lower bound; "
                          "segment columns describe the segment that ends at the waypoint")
    for h in ("#", "x m", "y m", "z m", "psi m", "psi >= m", "segment m", "seg psi >= m", "seg psi min m"):
        table.add_column(h, justify="right")
    for i, w in enumerate(way):
        seg = ("", "", "") if i == 0 else (f"{seg_len[i - 1]:.3f}", f"{plan.segment_lower[i - 1]:.3f}",
                                           f"{plan.segment_psi_min[i - 1]:.3f}")
        table.add_row(str(i), f"{w[0]:.3f}", f"{w[1]:.3f}", f"{w[2]:.3f}", f"{plan.psi[i]:.3f}",
                      f"{plan.psi_lower[i]:.3f}", *seg)
    console.print(table)
    js = Path(args.json) if args.json else out / "plan.json"
    try:
        js.write_text(json.dumps({**plan.to_json(), "build": str(out)}, indent=1) + "\n")
    except OSError as exc:
        raise PolyccError(f"{js}: cannot write the plan ({exc.strerror or exc}); pass --json FILE") from None
    png = Path(args.plot) if args.plot else out / "plan.png"
    with console.status(f"drawing {png}"):
        plot_plan(png, way, stored_vertices(nav.packed), None, plan.profile, plan.margin,
                  title=f"polycc plan: {len(way)} waypoints, {plan.length_m:.2f} m (straight {plan.straight_m:.2f} m), "
                        f"r = {plan.radius:g} m, margin {plan.margin:g} m")
    console.print(f"plan: {js}   views: {png}", soft_wrap=True)
    console.print(f"summary: {len(way)} waypoints, length {plan.length_m:.3f} m (straight {plan.straight_m:.3f} m, "
                  f"ratio {plan.length_ratio:.3f}; grid path {plan.grid_length_m:.3f} m), min certified psi "
                  f"{min(plan.psi_lower.min(), plan.segment_lower.min()):.3f} m, min sampled psi "
                  f"{plan.segment_psi_min.min():.3f} m, planning {plan.time_s:.2f} s "
                  f"(free-space grid {nav.grid.shape[0]}x{nav.grid.shape[1]}x{nav.grid.shape[2]}, "
                  f"{'cached' if nav.cached else f'{nav.build_s:.1f} s'}), total {time.perf_counter() - t0:.1f} s",
                  soft_wrap=True)
    return 0
