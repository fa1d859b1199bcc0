"""The scene options every scene-reading command shares, with one meaning everywhere.

``voxelize``, ``cover``, ``verify``, ``build`` and ``sim`` all call
:func:`add_scene_options` and :func:`load_scene_and_occupancy`.
"""

from __future__ import annotations

import argparse
import time

from polycc.console import console, progress_bar, summary_table
from polycc.errors import PolyccError
from polycc.occupancy import voxelize
from polycc.occupancy_grid import OccupancyGrid
from polycc.scene import Scene, SceneOptions, load_scene
from polycc.transform import load_transform


def _crop(text: str) -> tuple[float, ...]:
    try:
        vals = tuple(float(x) for x in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError("expected six numbers xmin,ymin,zmin,xmax,ymax,zmax (metres)") from None
    if len(vals) != 6:
        raise argparse.ArgumentTypeError(f"expected six numbers xmin,ymin,zmin,xmax,ymax,zmax (metres), got {len(vals)}")
    return vals


def add_scene_options(parser: argparse.ArgumentParser, voxel_default: float = 0.05) -> None:
    """Add --sigma --min-opacity --transform --scale --crop --drop-invalid --voxel --min-splats-per-voxel."""
    g = parser.add_argument_group("scene options (shared by every command that reads a scene)")
    g.add_argument("--sigma", type=float, default=1.0, metavar="K",
                   help="ellipsoid extent in standard deviations: E = {p : (p-c)^T Sigma^-1 (p-c) <= K^2}. "
                        "1 = the paper, 3 = the rasterizer's render extent (default: %(default)s)")
    g.add_argument("--min-opacity", type=float, default=0.0, metavar="A",
                   help="drop splats whose activated opacity (0..1) is below A; 0 keeps all (default: %(default)s)")
    g.add_argument("--transform", metavar="FILE.json",
                   help="JSON file with a 4x4 matrix {\"matrix\": ...} or a similarity {\"scale\", \"rotation\", "
                        "\"translation\"} from the trainer's frame to metres (default: identity)")
    g.add_argument("--scale", type=float, default=None, metavar="S",
                   help="uniform scale from file units to metres, applied after --transform (default: 1)")
    g.add_argument("--crop", type=_crop, default=None, metavar="XMIN,YMIN,ZMIN,XMAX,YMAX,ZMAX",
                   help="keep only splats whose ellipsoid meets this box, in metres after --transform/--scale; "
                        "ellipsoids straddling the boundary are kept whole (default: no crop)")
    g.add_argument("--drop-invalid", action="store_true",
                   help="skip splats with NaN/Inf values or a zero-length quaternion instead of refusing the file "
                        "(default: refuse)")
    g.add_argument("--voxel", type=float, default=voxel_default, metavar="G",
                   help="voxel side length g in metres; voxel corners lie on multiples of g (default: %(default)s)")
    g.add_argument("--min-splats-per-voxel", type=int, default=1, metavar="M",
                   help="floater filter: keep a voxel only if at least M distinct ellipsoids touch it; "
                        "the paper's hardware setting was 30 (default: %(default)s)")


def scene_options_from_args(args: argparse.Namespace) -> SceneOptions:
    return SceneOptions(
        sigma=args.sigma,
        min_opacity=args.min_opacity,
        transform=load_transform(args.transform) if args.transform else None,
        scale=args.scale,
        crop=args.crop,
        drop_invalid=args.drop_invalid,
    )


def load_scene_from_args(scene_path: str, args: argparse.Namespace) -> Scene:
    t = time.perf_counter()
    with console.status(f"reading {scene_path}"):
        scene = load_scene(scene_path, scene_options_from_args(args))
    scene.stats_time_s = time.perf_counter() - t
    return scene


def voxelize_scene(scene: Scene, args: argparse.Namespace) -> OccupancyGrid:
    n = len(scene.ellipsoids)
    t = time.perf_counter()
    with progress_bar(f"voxelizing at g = {args.voxel:g} m", n) as update:
        occ = voxelize(scene.ellipsoids, args.voxel, args.min_splats_per_voxel, progress=update)
    occ.stats["time_s"] = time.perf_counter() - t
    if len(occ) == 0:
        raise PolyccError(
            f"{scene.path}: no voxel has {args.min_splats_per_voxel} or more splats touching it; "
            "lower --min-splats-per-voxel or use a larger --voxel"
        )
    return occ


def load_scene_and_occupancy(scene_path: str, args: argparse.Namespace) -> tuple[Scene, OccupancyGrid]:
    """Read the scene with the shared options and voxelize it (progress shown)."""
    scene = load_scene_from_args(scene_path, args)
    return scene, voxelize_scene(scene, args)


def scene_summary_rows(scene: Scene) -> list[tuple[str, str]]:
    s = scene.stats
    rows = [
        ("scene", str(scene.path)),
        ("splats read", f"{s.read:,}"),
        ("invalid (NaN/Inf, bad quaternion)", f"{s.invalid:,}" + (" dropped" if s.invalid else "")),
        ("filtered by opacity", f"{s.filtered_opacity:,}"),
        ("cropped", f"{s.cropped:,}"),
        ("kept", f"{s.kept:,}"),
    ]
    if s.sigma_floored:
        rows.append(("sigma raised to 1e-7 m (conservative)", f"{s.sigma_floored:,}"))
    return rows


def occupancy_summary_rows(occ: OccupancyGrid) -> list[tuple[str, str]]:
    st = occ.stats
    lo = occ.lower_corners().min(axis=0)
    hi = occ.lower_corners().max(axis=0) + occ.voxel_size
    rows = [
        ("voxel size g", f"{occ.voxel_size:g} m"),
        ("occupied voxels", f"{len(occ):,}"),
        ("occupied volume", f"{occ.volume():.4g} m^3"),
        ("occupied bounds", f"[{lo[0]:.2f}, {lo[1]:.2f}, {lo[2]:.2f}] .. [{hi[0]:.2f}, {hi[1]:.2f}, {hi[2]:.2f}] m"),
        ("AABB candidate voxels tested", f"{st.get('aabb_candidate_voxels', 0):,}"),
    ]
    if st.get("min_splats_per_voxel", 1) > 1:
        rows.append((f"removed by floater filter (< {st['min_splats_per_voxel']} splats)",
                     f"{st['voxels_removed_by_floater_filter']:,}"))
    if "time_s" in st:
        n = st.get("ellipsoids", 0)
        rows.append(("voxelize time", f"{st['time_s']:.2f} s ({n / max(st['time_s'], 1e-9):,.0f} splats/s)"))
    return rows


def print_summary(title: str, rows: list[tuple[str, str]]) -> None:
    console.print(summary_table(title, rows))
