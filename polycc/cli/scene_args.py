"""The scene options every scene-reading command shares, with one meaning everywhere.

``voxelize``, ``cover`` and ``build`` make a scene's settings from the options; ``verify``,
``sim`` and ``sim-device`` take them from the build folder they read (:func:`recorded_settings`),
and an explicit option that disagrees with the folder is an error
(:func:`resolve_scene_settings`), so a check never runs on other geometry than the build's.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from polycc import pipeline
from polycc.cli.argtypes import NEGATIVE_VALUE_OPTIONS, number, numbers
from polycc.cli.console import StageProgress, console, summary_table, warn
from polycc.errors import PolyccError
from polycc.occupancy.grid import OccupancyGrid
from polycc.scene.load import Scene
from polycc.scene.settings import SCENE_DEFAULTS, SceneSettings, check_scene_file, recorded_settings, world_matrix

__all__ = ["SceneSettings", "check_scene_file", "recorded_settings"]


def add_scene_options(parser: argparse.ArgumentParser, from_dir: bool = False) -> None:
    """Add --sigma --min-opacity --transform --scale --crop --drop-invalid --voxel --min-splats-per-voxel.

    Every default is None here so that a command reading a build folder (``from_dir``) can tell
    an explicit option from an absent one: absent options take the folder's recorded value, and
    an explicit one that disagrees with it is an error (:func:`resolve_scene_settings`)."""
    d = SCENE_DEFAULTS
    tail = " (default: the value DIR was built with)" if from_dir else ""
    g = parser.add_argument_group("scene options (shared by every command that reads a scene"
                                  + ("; by default taken from DIR's manifest" if from_dir else "") + ")")
    g.add_argument("--sigma", type=number(float, 0.0, 100.0, lo_open=True, unit="standard deviations"), metavar="K",
                   help="ellipsoid extent in standard deviations: E = {p : (p-c)^T Sigma^-1 (p-c) <= K^2}. "
                        f"1 = the paper, 3 = the rasterizer's render extent (default: {d['sigma']:g}){tail}")
    g.add_argument("--min-opacity", type=number(float, 0.0, 1.0), metavar="A",
                   help="drop splats whose activated opacity (0..1) is below A; 0 keeps all "
                        f"(default: {d['min_opacity']:g}){tail}")
    g.add_argument("--transform", metavar="FILE.json",
                   help="JSON file with a 4x4 matrix {\"matrix\": ...} or a similarity {\"scale\", \"rotation\", "
                        f"\"translation\"}} from the trainer's frame to metres (default: identity){tail}")
    g.add_argument("--scale", type=number(float, 0.0, lo_open=True), metavar="S",
                   help=f"uniform scale from file units to metres, applied after --transform (default: 1){tail}")
    g.add_argument("--crop", type=numbers(6, "xmin,ymin,zmin,xmax,ymax,zmax in metres"),
                   metavar="XMIN,YMIN,ZMIN,XMAX,YMAX,ZMAX",
                   help="keep only splats whose ellipsoid meets this box, in metres after --transform/--scale; "
                        f"ellipsoids straddling the boundary are kept whole (default: no crop){tail}")
    NEGATIVE_VALUE_OPTIONS.add("--crop")
    g.add_argument("--drop-invalid", action="store_const", const=True, default=None,
                   help="skip splats with NaN/Inf values, a zero-length quaternion or (packed formats) a size code "
                        f"saturated at the format's maximum instead of refusing the file; counted (default: refuse)"
                        f"{tail}")
    g.add_argument("--drop-isolated", type=_isolated, metavar="R,N",
                   help="splat-level floater filter: drop every group of fewer than N splats whose centres, in "
                        "cells of R metres, touch no other group (far, isolated splats); the cover is certified "
                        f"against the kept splats and the dropped groups are listed (default: off){tail}")
    g.add_argument("--voxel", type=number(float, 0.0, 10.0, lo_open=True, unit="m"), metavar="G",
                   help=f"voxel side length g in metres; voxel corners lie on multiples of g "
                        f"(default: {d['voxel']:g}){tail}")
    g.add_argument("--min-splats-per-voxel", type=number(int, 1, 1_000_000), metavar="M",
                   help="floater filter: keep a voxel only if at least M distinct ellipsoids touch it (the paper's "
                        "hardware setting was 30). With M > 1 the cover is certified only against the FILTERED "
                        "occupancy: splats in removed voxels may lie partly outside it (the build reports how many "
                        f"and how deep) (default: {d['min_splats_per_voxel']}){tail}")


def _isolated(text: str) -> tuple[float, int]:
    parts = text.split(",")
    try:
        r, n = float(parts[0]), int(parts[1])
        ok = len(parts) == 2 and np.isfinite(r) and r > 0 and n >= 2
    except (ValueError, IndexError):
        ok = False
    if not ok:
        raise argparse.ArgumentTypeError(f"{text!r}: expected R,N with R > 0 metres and N >= 2 splats, e.g. 0.1,50")
    return r, n


_isolated.__name__ = "R,N"


def _show(v) -> str:
    if isinstance(v, float):
        return f"{v:g}"
    if isinstance(v, (tuple, list)):
        return ",".join(_show(x) for x in v)
    return str(v)


def resolve_scene_settings(args: argparse.Namespace, recorded: SceneSettings | None = None,
                           source: str = "") -> SceneSettings:
    """The scene settings of this run: explicit options, else ``recorded`` (a build folder's),
    else the defaults.  An explicit option that disagrees with ``recorded`` raises a PolyccError
    naming both values.  Also stored as ``args.scene_settings``."""
    out = SceneSettings() if recorded is None else SceneSettings.from_record(recorded.as_record())
    for key in ("sigma", "min_opacity", "crop", "drop_invalid", "voxel", "min_splats_per_voxel", "drop_isolated"):
        v = getattr(args, key, None)
        if v is None:
            continue
        if isinstance(v, (tuple, list)):
            v = tuple(float(x) for x in v)
        if recorded is not None:
            r = getattr(recorded, key)
            same = (r is None and v is None) or (r is not None and (
                np.allclose(np.asarray(v, float), np.asarray(r, float), rtol=1e-12, atol=0)
                if isinstance(v, (tuple, float, int)) and not isinstance(v, bool) else v == r))
            if not same:
                opt = "--" + key.replace("_", "-")
                raise PolyccError(
                    f"{opt} {_show(v)} disagrees with {source}, which was built with {opt} {_show(r)}; "
                    f"drop {opt} to use the build's value, or rebuild with {opt} {_show(v)}")
        setattr(out, key, v)
    transform, scale = getattr(args, "transform", None), getattr(args, "scale", None)
    if transform is not None or scale is not None:
        T = world_matrix(transform, scale)
        if recorded is not None and not np.allclose(T, recorded.world_matrix, rtol=1e-12, atol=1e-12):
            given = " ".join(x for x in (f"--transform {transform}" if transform else "",
                                         f"--scale {scale:g}" if scale is not None else "") if x)
            raise PolyccError(
                f"{given} gives the file->world matrix {np.round(T, 6).tolist()}, but {source} was built with "
                f"{np.round(np.asarray(recorded.world_matrix), 6).tolist()}; drop --transform/--scale to use the "
                "build's frame, or rebuild with these options")
        out.transform, out.scale, out.world_matrix = transform, scale, T
    args.scene_settings = out
    return out


def output_dir(path: str | Path) -> Path:
    """The output folder ``-o``, created; a one-line error if it is a file or cannot be made."""
    out = Path(path)
    if out.exists() and not out.is_dir():
        raise PolyccError(f"-o {out}: exists and is a file, not a folder; pass a folder path (it is created if "
                          "missing)")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise PolyccError(f"-o {out}: cannot create the folder ({exc.strerror or exc}); choose a writable "
                          "path") from None
    return out


def load_scene_from_args(scene_path: str, args: argparse.Namespace) -> Scene:
    settings = getattr(args, "scene_settings", None) or resolve_scene_settings(args)
    with StageProgress() as progress:
        return pipeline.read(scene_path, settings, progress, warn)


def voxelize_scene(scene: Scene, args: argparse.Namespace, runner=None) -> OccupancyGrid:
    settings = getattr(args, "scene_settings", None) or resolve_scene_settings(args)
    with StageProgress() as progress:
        return pipeline.occupancy(scene, settings, progress, warn, runner)


def load_scene_and_occupancy(scene_path: str, args: argparse.Namespace, runner=None) -> tuple[Scene, OccupancyGrid]:
    """Read the scene with the shared options and voxelize it (progress shown; x slabs on
    ``runner``'s workers when given)."""
    scene = load_scene_from_args(scene_path, args)
    return scene, voxelize_scene(scene, args, runner)


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
    if s.invalid_saturated:
        rows.append(("saturated size codes (dropped)", f"{s.invalid_saturated:,}"))
    if s.quantized_inflated:
        rows.append(("inflated for quantization (outward)", f"{s.quantized_inflated:,}"))
    if s.triangles:
        rows.append(("mesh triangles (kept / cropped)", f"{s.triangles - s.triangles_cropped:,} / "
                                                        f"{s.triangles_cropped:,}"))
    if s.dropped_isolated:
        g = scene.dropped_groups
        far = max(g, key=lambda x: x.gap) if g else None
        rows.append(("isolated splats dropped (groups)", f"{s.dropped_isolated:,} ({len(g):,})"))
        if far is not None:
            rows.append(("  farthest dropped group", f"{far.count:,} at {np.round(far.centroid, 2).tolist()} m, "
                                                     f"{far.gap:.2f} m away"))
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
    rows += floater_rows(occ)
    if "time_s" in st:
        n = st.get("ellipsoids", 0)
        rows.append(("voxelize time", f"{st['time_s']:.2f} s ({n / max(st['time_s'], 1e-9):,.0f} splats/s)"))
    return rows


def floater_rows(occ: OccupancyGrid) -> list[tuple[str, str]]:
    st = occ.stats
    if st.get("min_splats_per_voxel", 1) <= 1:
        return []
    f = st.get("floater_filter") or {"voxels_removed": 0, "splats_not_fully_covered": 0, "max_depth_outside_m": 0.0}
    return [
        (f"floater filter (M = {st['min_splats_per_voxel']}): voxels removed", f"{f['voxels_removed']:,}"),
        ("splats not fully covered (certified vs the FILTERED occupancy only)", f"{f['splats_not_fully_covered']:,}"),
        ("largest depth outside the cover (computed, <= bound)", f"{f['max_depth_outside_m']:.4f} m"),
    ]


def print_summary(title: str, rows: list[tuple[str, str]]) -> None:
    console.print(summary_table(title, rows))
