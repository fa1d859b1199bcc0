"""Frame transforms from the trainer's frame to the world frame in metres.

A transform is a 4x4 affine matrix ``T`` (p_world = A p + t). JSON files may hold

* ``{"matrix": [[...4 rows...]]}`` or a bare 4x4 list (a 3x4 matrix gets the row 0 0 0 1), or
* a similarity ``{"scale": s, "rotation": R, "translation": [tx, ty, tz]}`` where
  ``rotation`` is a 3x3 matrix or a quaternion ``[w, x, y, z]`` (each key optional), or
* nerfstudio's ``dataparser_transforms.json`` (``{"transform": 3x4, "scale": s}``, the map from the
  capture's frame to nerfstudio's normalised one, p_ns = s (T p)): polycc applies its INVERSE, so
  splats exported by ``ns-export gaussian-splat`` (nerfstudio's frame) go back to the capture's frame
  (metres when the poses were, e.g. ARKit/Polycam/Record3D captures).

An affine image of an ellipsoid is an ellipsoid: L' = A L, re-factored as R' S' by SVD.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from polycc.errors import PolyccError
from polycc.scene.ellipsoids import Ellipsoids, quaternion_to_rotation

_FORMATS = (
    '{"matrix": [[a,b,c,tx],[d,e,f,ty],[g,h,i,tz],[0,0,0,1]]} (4x4 or 3x4), '
    '{"scale": s, "rotation": [w,x,y,z] or 3x3, "translation": [tx,ty,tz]} or nerfstudio\'s '
    'dataparser_transforms.json'
)


def _affine(m, what: str) -> np.ndarray:
    T = np.asarray(m, dtype=np.float64)
    if T.shape == (3, 4):
        T = np.vstack([T, [0.0, 0.0, 0.0, 1.0]])
    if T.shape != (4, 4):
        raise ValueError(f"{what} has shape {T.shape}, expected 4x4 or 3x4")
    if not np.allclose(T[3], [0, 0, 0, 1]):
        raise ValueError("the last row must be 0 0 0 1 (no projective transforms)")
    return T


def load_transform(path: str | Path) -> np.ndarray:
    """Read a transform JSON file into a 4x4 float64 matrix."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        raise PolyccError(f"{path}: transform file not found; give a JSON file like {_FORMATS}") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise PolyccError(f"{path}: not valid JSON ({exc}); write it like {_FORMATS}") from None
    try:
        if isinstance(data, list):
            data = {"matrix": data}
        if not isinstance(data, dict):
            raise ValueError("expected an object or a 4x4 list")
        if "matrix" in data:
            T = _affine(data["matrix"], "matrix")
        elif "transform" in data:  # nerfstudio dataparser_transforms.json: p_ns = scale * (T p); invert it
            fwd = _affine(data["transform"], "transform")
            s = float(data.get("scale", 1.0))
            if not s > 0:
                raise ValueError("scale must be positive")
            fwd[:3, :] *= s
            if abs(np.linalg.det(fwd[:3, :3])) < 1e-12:
                raise ValueError("the transform's 3x3 part is singular")
            T = np.linalg.inv(fwd)
            T[3] = [0.0, 0.0, 0.0, 1.0]
        else:
            unknown = set(data) - {"scale", "rotation", "translation"}
            if unknown:
                raise ValueError(f"unknown keys {sorted(unknown)}")
            s = float(data.get("scale", 1.0))
            rot = np.asarray(data.get("rotation", np.eye(3)), dtype=np.float64)
            if rot.shape == (4,):
                if np.linalg.norm(rot) < 1e-12:
                    raise ValueError("rotation quaternion has zero length")
                rot = quaternion_to_rotation((rot / np.linalg.norm(rot))[None])[0]
            elif rot.shape != (3, 3):
                raise ValueError(f"rotation has shape {rot.shape}, expected [w,x,y,z] or 3x3")
            elif not np.allclose(rot @ rot.T, np.eye(3), atol=1e-6):
                raise ValueError("rotation matrix is not orthonormal")
            t = np.asarray(data.get("translation", [0, 0, 0]), dtype=np.float64)
            if t.shape != (3,):
                raise ValueError("translation must have 3 numbers")
            if not s > 0:
                raise ValueError("scale must be positive")
            T = np.eye(4)
            T[:3, :3] = s * rot
            T[:3, 3] = t
    except (ValueError, TypeError) as exc:
        raise PolyccError(f"{path}: bad transform ({exc}); write it like {_FORMATS}") from None
    check_transform(T, str(path))
    return T


def check_transform(T: np.ndarray, where: str) -> None:
    if not np.all(np.isfinite(T)):
        raise PolyccError(f"{where}: the transform has NaN or Inf entries; fix the numbers")
    if abs(np.linalg.det(T[:3, :3])) < 1e-12:
        raise PolyccError(f"{where}: the transform's 3x3 part is singular; it must be invertible (non-zero scale)")


def scale_matrix(s: float) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] *= s
    return T


def apply_transform(ell: Ellipsoids, T: np.ndarray) -> Ellipsoids:
    """The image of every ellipsoid under p -> A p + t (k unchanged)."""
    A, t = T[:3, :3], T[:3, 3]
    centers = ell.centers @ A.T + t
    # Similarity fast path: A = s Q with Q orthonormal keeps sigma ratios and axes.
    s = np.cbrt(abs(np.linalg.det(A)))
    Q = A / s
    if np.allclose(Q @ Q.T, np.eye(3), atol=1e-12):
        R = _proper(np.einsum("ij,njk->nik", Q, ell.rotations))
        return Ellipsoids(centers, R, ell.sigmas * s, ell.k, ell.opacity, ell.colors)
    L = np.einsum("ij,njk->nik", A, ell.rotations * ell.sigmas[:, None, :])
    U, S, _ = np.linalg.svd(L)
    return Ellipsoids(centers, _proper(U), S, ell.k, ell.opacity, ell.colors)


def _proper(R: np.ndarray) -> np.ndarray:
    """Flip the third axis where det(R) = -1 (an ellipsoid is symmetric), so every R is a rotation."""
    neg = np.linalg.det(R) < 0
    if neg.any():
        R = R.copy()
        R[neg, :, 2] *= -1.0
    return R
