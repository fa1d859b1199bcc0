"""The stored polytopes of a build as triangle meshes (trimesh): for ``polycc export`` and ``polycc view``.

Each polytope ``{p : n_j . p <= d_j}`` (manifest.json, the values exactly as the C decodes them, world
frame, metres) becomes the convex hull of its vertices. ``frame="trainer"`` maps the meshes back to the
scene file's own frame with the inverse of the build's file -> world matrix, so they overlay the splats
in SuperSplat or any viewer of the original file.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from polycc.errors import PolyccError
from polycc.geometry.halfplanes import polytope_vertices

FORMATS = ("glb", "obj", "ply")
FRAMES = ("world", "trainer")


def read_build(path: str | Path) -> dict:
    """manifest.json of a `polycc build` folder (one-line error naming the fix otherwise)."""
    man = Path(path) / "manifest.json"
    if not man.is_file():
        raise PolyccError(f"{path}: no manifest.json; give a folder written by `polycc build`")
    try:
        m = json.loads(man.read_text())
    except (OSError, ValueError) as exc:
        raise PolyccError(f"{man}: not readable JSON ({exc}); rebuild with `polycc build`") from None
    if "polytopes" not in m:
        raise PolyccError(f"{man}: has no stored polytopes; rebuild with `polycc build`")
    return m


def world_matrix(manifest: dict) -> np.ndarray:
    rec = manifest.get("scene_settings") or {}
    T = rec.get("world_matrix") or manifest.get("transform")
    return np.eye(4) if T is None else np.asarray(T, np.float64)


def polytope_meshes(manifest: dict, frame: str = "world") -> list:
    """One ``trimesh.Trimesh`` per stored polytope, in ``frame``; a colour per polytope (tab20)."""
    import trimesh

    if frame not in FRAMES:
        raise PolyccError(f"--frame {frame}: choose one of {', '.join(FRAMES)}")
    inv = np.linalg.inv(world_matrix(manifest)) if frame == "trainer" else None
    out = []
    for i, p in enumerate(manifest["polytopes"]):
        h = np.asarray(p["halfplanes"], np.float64)
        v = polytope_vertices(h)
        if v is None or len(v) < 4:
            continue
        if inv is not None:
            v = v @ inv[:3, :3].T + inv[:3, 3]
        m = trimesh.convex.convex_hull(v)
        m.visual.face_colors = np.array(_color(i), np.uint8)
        out.append(m)
    return out


def _color(i: int) -> tuple[int, int, int, int]:
    import matplotlib

    r, g, b, _ = matplotlib.colormaps["tab20"](i % 20)
    return int(255 * r), int(255 * g), int(255 * b), 160


def export(build_dir: str | Path, out: str | Path, fmt: str | None = None, frame: str = "world") -> tuple[Path, int]:
    """Write the stored polytopes of ``build_dir`` as one mesh file; returns (path, polytopes written)."""
    import trimesh

    out = Path(out)
    fmt = (fmt or out.suffix.lstrip(".")).lower()
    if fmt not in FORMATS:
        raise PolyccError(f"--format {fmt or '?'}: choose glb, obj or ply (or give OUT a .glb/.obj/.ply name)")
    meshes = polytope_meshes(read_build(build_dir), frame)
    if not meshes:
        raise PolyccError(f"{build_dir}: no bounded stored polytope to export; rebuild with `polycc build`")
    if fmt == "glb":
        scene = trimesh.Scene()
        for i, m in enumerate(meshes):
            scene.add_geometry(m, node_name=f"polytope_{i}", geom_name=f"polytope_{i}")
        data = scene.export(file_type="glb")
    else:
        data = trimesh.util.concatenate(meshes).export(file_type=fmt)
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_bytes(data if isinstance(data, bytes) else data.encode())
    except OSError as exc:
        raise PolyccError(f"{out}: cannot write ({exc.strerror or exc}); choose a writable path") from None
    return out, len(meshes)
