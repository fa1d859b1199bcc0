"""Write ellipsoids as a real 3DGS ``.ply`` (graphdeco-inria layout) and plain point clouds.

The 3DGS layout is one ``vertex`` element with 62 float32 properties, in this order::

    x y z nx ny nz f_dc_0 f_dc_1 f_dc_2 f_rest_0 .. f_rest_44 opacity
    scale_0 scale_1 scale_2 rot_0 rot_1 rot_2 rot_3

Values are stored pre-activation, as a trainer saves them: ``scale_i = log(sigma_i)``,
``opacity = logit(alpha)``, ``rot = (w, x, y, z)`` and ``f_dc = (rgb - 0.5) / C0`` with
the degree-0 spherical-harmonic constant ``C0``. Normals and ``f_rest_*`` are zero.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from plyfile import PlyData, PlyElement

from polycc.errors import PolyccError
from polycc.scene.ellipsoids import Ellipsoids
from polycc.scene.readers import (
    SH_C0,  # degree-0 real spherical harmonic, 1 / (2 sqrt(pi)); one source for reader and writer
)

# Number of higher-order SH coefficients in the graphdeco layout (degree 3, 15 x RGB).
N_F_REST = 45
# Opacities are clipped to [OPACITY_EPS, 1 - OPACITY_EPS] before the logit, so that
# fully opaque or transparent splats get a finite stored value.
OPACITY_EPS = 1e-6

GAUSSIAN_PLY_PROPERTIES: tuple[str, ...] = (
    ("x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2")
    + tuple(f"f_rest_{i}" for i in range(N_F_REST))
    + ("opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3")
)


def rotation_to_quaternion(R: np.ndarray) -> np.ndarray:
    """(N, 3, 3) rotation matrices to (N, 4) unit quaternions (w, x, y, z) with w >= 0.

    A matrix with determinant -1 (a reflection) has its third column negated first:
    an ellipsoid is symmetric about each principal axis, so the set is unchanged.
    Uses the largest of |w|, |x|, |y|, |z| as pivot (Shepperd's method), so the result
    is accurate for every rotation, including half turns.
    """
    R = np.array(R, dtype=np.float64, copy=True).reshape(-1, 3, 3)
    flip = np.linalg.det(R) < 0
    R[flip, :, 2] *= -1.0
    m00, m01, m02 = R[:, 0, 0], R[:, 0, 1], R[:, 0, 2]
    m10, m11, m12 = R[:, 1, 0], R[:, 1, 1], R[:, 1, 2]
    m20, m21, m22 = R[:, 2, 0], R[:, 2, 1], R[:, 2, 2]
    # 4 * q_i^2 for each component.
    sq = np.stack(
        [1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22], axis=1
    )
    pivot = np.argmax(sq, axis=1)
    root = np.sqrt(np.maximum(sq[np.arange(len(R)), pivot], 1e-300))  # = 2 |q_pivot|
    q = np.empty((len(R), 4), dtype=np.float64)
    # Each row: (w, x, y, z) * (2 q_pivot), i.e. 4 q_i q_pivot / (2 q_pivot).
    cand = {
        0: (root**2, m21 - m12, m02 - m20, m10 - m01),
        1: (m21 - m12, root**2, m01 + m10, m02 + m20),
        2: (m02 - m20, m01 + m10, root**2, m12 + m21),
        3: (m10 - m01, m02 + m20, m12 + m21, root**2),
    }
    for p, comps in cand.items():
        sel = pivot == p
        if np.any(sel):
            q[sel] = np.stack([c[sel] for c in comps], axis=1) / (2.0 * root[sel, None])
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q[q[:, 0] < 0] *= -1.0
    return q


def gaussian_ply_array(ell: Ellipsoids) -> np.ndarray:
    """The structured float32 array (62 fields, graphdeco order) that encodes ``ell``."""
    n = len(ell)
    out = np.zeros(n, dtype=[(name, "<f4") for name in GAUSSIAN_PLY_PROPERTIES])
    c = np.asarray(ell.centers, dtype=np.float64)
    out["x"], out["y"], out["z"] = c[:, 0], c[:, 1], c[:, 2]
    if ell.colors is not None:
        dc = (np.asarray(ell.colors, dtype=np.float64) / 255.0 - 0.5) / SH_C0
        for i in range(3):
            out[f"f_dc_{i}"] = dc[:, i]
    alpha = np.ones(n) if ell.opacity is None else np.asarray(ell.opacity, dtype=np.float64)
    alpha = np.clip(alpha, OPACITY_EPS, 1.0 - OPACITY_EPS)
    out["opacity"] = np.log(alpha) - np.log1p(-alpha)
    log_sigma = np.log(np.asarray(ell.sigmas, dtype=np.float64))
    for i in range(3):
        out[f"scale_{i}"] = log_sigma[:, i]
    q = rotation_to_quaternion(ell.rotations)
    for i in range(4):
        out[f"rot_{i}"] = q[:, i]
    return out


def _write_ascii(f, arr: np.ndarray) -> None:
    """ASCII body, one line per vertex, float32 values with 9 significant digits (exact).

    plyfile's own ASCII writer formats value by value in Python (about 35 s for 200k
    splats); numpy's row formatter is about ten times faster and gives the same file.
    """
    cols = np.stack([arr[name] for name in arr.dtype.names], axis=1)
    np.savetxt(f, cols, fmt="%.9g", delimiter=" ")


def _write(path: Path, arr: np.ndarray, binary: bool) -> None:
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        if binary:
            PlyData([PlyElement.describe(arr, "vertex")], text=False, byte_order="<").write(str(path))
            return
        header = ["ply", "format ascii 1.0", f"element vertex {len(arr)}"]
        header += [f"property float {name}" for name in arr.dtype.names]
        header.append("end_header")
        with open(path, "w", encoding="ascii", newline="\n") as f:
            f.write("\n".join(header) + "\n")
            _write_ascii(f, arr)
    except OSError as exc:
        raise PolyccError(
            f"{path}: cannot write the PLY file ({exc.strerror or exc}); "
            "choose a writable output path"
        ) from exc


def write_gaussian_ply(path, ell: Ellipsoids, binary: bool = True) -> None:
    """Write ``ell`` to ``path`` as a graphdeco-inria 3DGS ``.ply`` (62 float32 properties).

    ``binary=True`` writes binary little-endian, ``False`` writes ASCII. Centres and
    sigmas are in the ellipsoids' units (metres); ``ell.k`` is not stored (a 3DGS file
    has no such field: the reader's ``--sigma`` sets it). Missing opacities are written
    as fully opaque, missing colours as mid grey.
    """
    if len(ell) == 0:
        raise PolyccError(f"{path}: no ellipsoids to write; pass a non-empty set")
    if np.any(~np.isfinite(ell.sigmas)) or np.any(ell.sigmas <= 0):
        raise PolyccError(f"{path}: sigmas must be finite and > 0 to take their log; fix the input set")
    _write(path, gaussian_ply_array(ell), binary)


def write_point_ply(path, points, radius=None, binary: bool = True) -> None:
    """Write a plain point cloud: a ``vertex`` element with float32 ``x y z`` [``radius``].

    ``points`` is (N, 3) in metres; ``radius`` is None (no property), a scalar, or (N,)
    in metres.
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    if radius is not None:
        fields.append(("radius", "<f4"))
    out = np.zeros(len(pts), dtype=fields)
    out["x"], out["y"], out["z"] = pts[:, 0], pts[:, 1], pts[:, 2]
    if radius is not None:
        out["radius"] = np.broadcast_to(np.asarray(radius, dtype=np.float64), (len(pts),))
    _write(path, out, binary)
