"""Conservative rounding of half-planes to the stored number format (always outward).

For a polytope P = conv(V) with half-planes n . p <= d, the stored half-plane is
``n_q . p <= d_q`` where ``n_q`` is ``n`` rounded to the storage format with
``|n_q| <= 1`` (so a value n_q . p - d_q >= r still puts p at distance >= r from the
plane), and ``d_q >= max_v n_q . v`` rounded up, so the stored half-space still contains
every vertex of P, hence P itself (and every occupied voxel P contains).
"""

from __future__ import annotations

import numpy as np

_EPS64 = np.finfo(np.float64).eps


def f32_up(x: np.ndarray) -> np.ndarray:
    """Smallest float32 >= x, elementwise."""
    x = np.asarray(x, np.float64)
    f = x.astype(np.float32)
    low = f.astype(np.float64) < x
    f[low] = np.nextafter(f[low], np.float32(np.inf))
    return f


def f32_unit_normals(n: np.ndarray) -> np.ndarray:
    """Round unit normals (H, 3) to float32 with |n_q| <= 1 exactly (float64 check)."""
    n = np.asarray(n, np.float64)
    n = n / np.linalg.norm(n, axis=1, keepdims=True)
    q = n.astype(np.float32)
    for _ in range(8):
        too_long = np.einsum("ij,ij->i", q.astype(np.float64), q.astype(np.float64)) > 1.0
        if not too_long.any():
            return q
        rows = np.flatnonzero(too_long)
        col = np.argmax(np.abs(q[rows]), axis=1)
        q[rows, col] = np.nextafter(q[rows, col], np.float32(0))
    raise AssertionError("could not shorten float32 normals below unit length")


def outward_offsets(normals_q: np.ndarray, vertices: np.ndarray) -> np.ndarray:
    """d_q >= max_v n_q . v for each stored normal (float64 dot, error bound added, rounded up to float32)."""
    nq = np.asarray(normals_q, np.float64)
    v = np.asarray(vertices, np.float64)
    dots = v @ nq.T  # (V, H)
    bound = 8 * _EPS64 * (np.abs(v) @ np.abs(nq).T)  # float64 rounding of each dot
    return f32_up((dots + bound).max(axis=0))


def quantize_float32(halfplanes: np.ndarray, vertices: np.ndarray) -> np.ndarray:
    """(H, 4) float32 [nx, ny, nz, d] that contain conv(vertices) and have |n| <= 1."""
    nq = f32_unit_normals(np.asarray(halfplanes)[:, :3])
    d = outward_offsets(nq, vertices)
    return np.c_[nq, d].astype(np.float32)
