"""Readers for splat files: 3DGS .ply (any property order), point-cloud .ply, antimatter15 .splat.

Each reader returns :class:`RawSplats` in the file's own frame and units, with the
activations applied (sigma = exp(scale), opacity = sigmoid(opacity)) but quaternions
not yet normalised; validation happens in :mod:`polycc.scene.load`.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from polycc.errors import PolyccError
from polycc.scene.quantized import QuantBounds, decode_splat_quaternion, splat_opacity_hi

SH_C0 = 0.28209479177387814  # degree-0 spherical-harmonic constant (colour = 0.5 + C0 * f_dc)


@dataclass
class RawSplats:
    """Splats as stored, activations applied, file frame.

    positions: (N, 3) float64; sigmas: (N, 3) float64 linear std devs (for point clouds:
    the point radius, or 0); quats: (N, 4) float64 (w, x, y, z), not normalised, or None
    for point clouds (spheres); opacity: (N,) float32 in [0, 1]; colors: (N, 3) uint8 or None.
    is_points: True for plain point clouds, whose sigma is a radius (independent of k).
    """

    positions: np.ndarray
    sigmas: np.ndarray
    quats: np.ndarray | None
    opacity: np.ndarray
    colors: np.ndarray | None
    is_points: bool = False
    bounds: QuantBounds | None = None
    triangles: np.ndarray | None = None
    info: dict = field(default_factory=dict)


def read_splats(path: str | Path) -> RawSplats:
    """Read any supported scene file, choosing the reader by extension."""
    path = Path(path)
    if not path.exists():
        raise PolyccError(f"{path}: no such file; check the path")
    if path.is_dir():
        raise PolyccError(f"{path}: is a directory; give a .ply or .splat file")
    name = path.name.lower()
    ext = path.suffix.lower()
    if ext == ".ply":
        return read_ply(path)
    if ext == ".splat":
        return read_splat(path)
    if ext == ".spz":
        from polycc.scene.packed import read_spz

        return read_spz(path)
    for suffix, what in UNREAD_FORMATS.items():
        if name.endswith(suffix):
            raise PolyccError(
                f"{path}: {what} is a format polycc does not read; convert it to .ply first: "
                f"`npx @playcanvas/splat-transform@{SPLAT_TRANSFORM_VERSION} {path} {path.stem.split('.')[0]}.ply`"
            )
    raise PolyccError(
        f"{path}: unknown extension '{path.suffix}'; polycc reads 3DGS, SuperSplat .compressed.ply, point-cloud and "
        "mesh .ply, antimatter15 .splat and Niantic .spz files; other splat formats convert with "
        f"`npx @playcanvas/splat-transform@{SPLAT_TRANSFORM_VERSION} IN OUT.ply`"
    )


# The converter the error messages name (the ecosystem's reference; it reads all of these).
SPLAT_TRANSFORM_VERSION = "3.7.0"
UNREAD_FORMATS = {
    ".sog": "PlayCanvas SOG (WebP-compressed splats)",
    "meta.json": "an unbundled PlayCanvas SOG (meta.json + WebP images)",
    ".ksplat": "a mkkellogg GaussianSplats3D .ksplat",
    ".lcc": "an XGRIDS .lcc",
    ".lcc2": "an XGRIDS .lcc2",
    ".glb": "a glTF (KHR_gaussian_splatting) .glb",
    ".gltf": "a glTF .gltf",
    ".splatv": "a 4D .splatv",
}


# ---------------------------------------------------------------------------- .splat

_SPLAT_DTYPE = np.dtype([("pos", "<f4", 3), ("scale", "<f4", 3), ("rgba", "u1", 4), ("rot", "u1", 4)])


def read_splat(path: Path) -> RawSplats:
    """antimatter15 .splat: 32-byte records (pos f32[3], linear scale f32[3], RGBA u8[4], quat u8[4] as q*128+128)."""
    size = path.stat().st_size
    if size == 0:
        raise PolyccError(f"{path}: the file is empty; re-export the scene")
    if size % _SPLAT_DTYPE.itemsize:
        raise PolyccError(
            f"{path}: truncated .splat file ({size} bytes is not a multiple of the 32-byte record); re-export or "
            "re-download it"
        )
    rec = np.fromfile(path, dtype=_SPLAT_DTYPE)
    n = len(rec)
    # The 8-bit quaternion only says which bucket each component is in (writers truncate or round,
    # with 128 or 127.5): decode at the bucket's centre and inflate the splat to hold every rotation
    # in it (polycc.scene.quantized). Position and scale are float32, exact.
    q_hat, q_err = decode_splat_quaternion(rec["rot"])
    alpha = rec["rgba"][:, 3]
    bounds = QuantBounds(pos_err=np.zeros((n, 3)), sigma_hi=np.abs(rec["scale"].astype(np.float64)), quat_err=q_err,
                         opacity_hi=splat_opacity_hi(alpha), what=".splat 8-bit quaternion (bucket ~1.3 deg)")
    return RawSplats(
        positions=rec["pos"].astype(np.float64),
        sigmas=rec["scale"].astype(np.float64),
        quats=q_hat,
        opacity=(alpha.astype(np.float32) / np.float32(255.0)),
        colors=rec["rgba"][:, :3].copy(),
        bounds=bounds,
        info={"format": ".splat (antimatter15)"},
    )


# ---------------------------------------------------------------------------- .ply

def _suffix_sorted(names: list[str], prefix: str) -> list[str]:
    pat = re.compile(re.escape(prefix) + r"(\d+)$")
    found = [(int(m.group(1)), n) for n in names if (m := pat.match(n))]
    return [n for _, n in sorted(found)]


def read_ply(path: Path) -> RawSplats:
    """A 3DGS .ply (graphdeco layout or any subset/order, by property name) or an x y z [radius] point cloud."""
    from plyfile import PlyData, PlyElementParseError, PlyHeaderParseError

    try:
        ply = PlyData.read(str(path))
        if "vertex" not in ply:
            raise PolyccError(f"{path}: the .ply has no 'vertex' element; export the splats (or points) as vertices")
        strips = [e for e in ply.elements if e.name == "tristrips"]
        if strips:
            raise PolyccError(
                f"{path}: the mesh is stored as triangle strips ({strips[0].count:,} 'tristrips'); polycc reads "
                "'face' and 'edge' elements: re-export the mesh with faces (e.g. Blender or MeshLab, .ply with faces)"
            )
        _check_body_length(path, ply)
        from polycc.scene.packed import is_compressed_ply, read_compressed_ply

        if is_compressed_ply(ply):
            return read_compressed_ply(path, ply)
        v = ply["vertex"].data
        triangles = _mesh_triangles(path, ply, v)
    except PolyccError:
        raise
    except PlyHeaderParseError as exc:
        raise PolyccError(f"{path}: not a valid .ply header ({exc}); re-export the file") from None
    except (PlyElementParseError, ValueError, EOFError, MemoryError, IndexError) as exc:
        raise PolyccError(f"{path}: truncated or corrupt .ply data ({_one_line(exc)}); re-export or re-download the "
                          "file") from None
    except OSError as exc:
        raise PolyccError(f"{path}: cannot read the file ({exc.strerror or exc})") from None

    names = list(v.dtype.names or ())
    n = len(v)
    missing_xyz = [a for a in ("x", "y", "z") if a not in names]
    if missing_xyz:
        raise PolyccError(
            f"{path}: the vertex element has no {'/'.join(missing_xyz)} property (it has: {', '.join(names[:12])}); "
            "polycc needs splat centres named x, y, z"
        )
    scales = _suffix_sorted(names, "scale_")
    rots = _suffix_sorted(names, "rot_")
    gaussian_markers = bool(scales or rots or "opacity" in names)
    if not gaussian_markers:
        pos = np.stack([np.asarray(v[a], np.float64) for a in ("x", "y", "z")], axis=1)
        radius = np.asarray(v["radius"], np.float64) if "radius" in names else np.zeros(n)
        return RawSplats(
            positions=pos,
            sigmas=np.repeat(radius[:, None], 3, axis=1),
            quats=None,
            opacity=np.ones(n, np.float32),
            colors=_ply_colors(v, names),
            is_points=True,
            triangles=None if triangles is None else pos[triangles],
            info={"format": "mesh .ply" if triangles is not None else "point-cloud .ply"},
        )
    if triangles is not None:
        raise PolyccError(f"{path}: a .ply with both Gaussian splat properties and faces; export the splats and the "
                          "mesh as two files")

    if len(scales) != 3:
        have = ", ".join(scales) or "none"
        raise PolyccError(
            f"{path}: a 3DGS .ply needs scale_0, scale_1, scale_2 (found: {have}); re-export from the trainer, "
            "or strip the Gaussian properties to read it as an x y z point cloud"
        )
    if len(rots) != 4:
        have = ", ".join(rots) or "none"
        raise PolyccError(
            f"{path}: a 3DGS .ply needs rot_0..rot_3 (quaternion w, x, y, z; found: {have}); re-export from the trainer"
        )
    pos, sig, quats, op, colors = _gaussian_columns(v, names, scales, rots)
    return RawSplats(positions=pos, sigmas=sig, quats=quats, opacity=op, colors=colors,
                     info={"format": "3DGS .ply"})


def _gaussian_columns(v, names: list[str], scales: list[str], rots: list[str]) -> tuple:
    """(positions, sigmas = exp(scale), quaternions, opacity = sigmoid(opacity) (NaN where not finite), colours)
    of a 3DGS vertex table, filled in row chunks on every core (:func:`polycc.parallel.in_row_chunks`): one pass
    over the records, which may be a memory map of the file, where a column at a time made a strided pass
    over all of them per column (1.5 s of the 6M-splat room's read, now 0.3 s). Row by row the same numbers."""
    from polycc.parallel import in_row_chunks

    n = len(v)
    pos, sig, quats = np.empty((n, 3)), np.empty((n, 3)), np.empty((n, 4))
    op = np.ones(n, np.float32)
    colors = np.empty((n, 3), np.uint8) if _ply_colors(v[:0], names) is not None else None

    def rows(s: int, e: int) -> None:
        blk = v[s:e]
        for out, cols in ((pos, ("x", "y", "z")), (sig, scales), (quats, rots)):
            for j, a in enumerate(cols):
                out[s:e, j] = blk[a]
        with np.errstate(over="ignore"):
            np.exp(sig[s:e], out=sig[s:e])
            if "opacity" in names:
                o = np.asarray(blk["opacity"], np.float64)
                a = (1.0 / (1.0 + np.exp(-o))).astype(np.float32)
                a[~np.isfinite(o)] = np.nan
                op[s:e] = a
        if colors is not None:
            colors[s:e] = _ply_colors(blk, names)

    in_row_chunks(n, rows)
    return pos, sig, quats, op, colors


def _mesh_triangles(path: Path, ply, v) -> np.ndarray | None:
    """(T, 3) int64 vertex indices of the mesh's triangles (polygons fanned, edges as degenerate
    triangles), or None when the .ply has no 'face'/'edge' element."""
    tris = []
    n = len(v)
    for e in ply.elements:
        if e.name == "face":
            props = [p.name for p in e.properties]
            key = "vertex_indices" if "vertex_indices" in props else "vertex_index" if "vertex_index" in props else None
            if key is None:
                raise PolyccError(f"{path}: the 'face' element has no vertex_indices list (it has {props}); "
                                  "re-export the mesh")
            faces = e.data[key]
            lens = np.fromiter((len(f) for f in faces), np.int64, len(faces))
            if np.any(lens < 3):
                raise PolyccError(f"{path}: {int((lens < 3).sum()):,} faces with fewer than 3 corners; repair the mesh")
            for k in np.unique(lens):  # fan each k-gon: (0, j, j + 1)
                f = np.vstack(list(faces[lens == k])).astype(np.int64)
                j = np.arange(1, k - 1)
                tris.append(np.stack([np.repeat(f[:, 0], k - 2), f[:, j].ravel(), f[:, j + 1].ravel()], axis=1))
        elif e.name == "edge":
            a = np.asarray(e.data["vertex1"], np.int64)
            b = np.asarray(e.data["vertex2"], np.int64)
            tris.append(np.stack([a, b, b], axis=1))  # a segment is a degenerate triangle
    if not tris:
        return None
    t = np.concatenate(tris)
    if t.size and (t.min() < 0 or t.max() >= n):
        raise PolyccError(f"{path}: faces refer to vertex {int(t.max() if t.max() >= n else t.min())} of {n:,}; "
                          "repair the mesh")
    return t


def _header_length(path: Path) -> int:
    """Bytes of the .ply header, up to and including the newline after ``end_header``."""
    with open(path, "rb") as f:
        head = f.read(1 << 20)
    m = re.search(rb"end_header[ \t]*\r?\n", head)
    if m is None:
        raise PolyccError(f"{path}: no 'end_header' line in the first MiB; not a valid .ply header, re-export the file")
    return m.end()


def _check_body_length(path: Path, ply) -> None:
    """Refuse a body longer than its header declares (for a shorter one plyfile already fails).

    Data past the declared elements would be ignored: splats the header does not count would be
    silently missing from the cover."""
    size = path.stat().st_size
    declared = sum(int(e.count) for e in ply.elements)
    if ply.text:
        with open(path, "rb") as f:
            f.seek(_header_length(path))
            rows = sum(1 for line in f if line.strip())
        if rows != declared:
            raise PolyccError(
                f"{path}: the header declares {declared:,} rows but the ASCII body holds {rows:,}; "
                "the file was cut or appended to; re-export it"
            )
        return
    if any(getattr(p, "len_dtype", None) is not None for e in ply.elements for p in e.properties):
        with open(path, "rb") as f:  # list properties: let plyfile walk the body and see where it ends
            type(ply).read(f, mmap=False)
            end = f.tell()
    else:
        end = _header_length(path) + sum(int(e.count) * e.dtype().itemsize for e in ply.elements)
    if end != size:
        extra = size - end
        what = f"{extra:,} bytes more" if extra > 0 else f"{-extra:,} bytes fewer"
        recs = ""
        v = ply["vertex"]
        if extra > 0 and len(ply.elements) == 1 and extra % v.dtype().itemsize == 0:
            recs = f" ({extra // v.dtype().itemsize:,} more vertices than its {v.count:,})"
        raise PolyccError(
            f"{path}: the binary body holds {what} than the header declares{recs}; the file was cut or appended "
            "to, so some splats would be ignored; re-export it with the right vertex count"
        )


def _ply_colors(v, names: list[str]) -> np.ndarray | None:
    if all(f"f_dc_{i}" in names for i in range(3)):
        dc = np.stack([np.asarray(v[f"f_dc_{i}"], np.float64) for i in range(3)], axis=1)
        rgb = np.clip(0.5 + SH_C0 * np.nan_to_num(dc), 0.0, 1.0) * 255.0
        return np.round(rgb).astype(np.uint8)
    if all(c in names for c in ("red", "green", "blue")):
        return np.stack([np.asarray(v[c]) for c in ("red", "green", "blue")], axis=1).astype(np.uint8)
    return None


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split())[:160] or type(exc).__name__
