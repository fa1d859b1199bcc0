"""Outward inflation of splats whose file stores them quantized (file frame, file units).

A quantized format (.splat, SuperSplat .compressed.ply, Niantic .spz) stores a code, and every
encoder input that produces that code is a possible true splat. The readers return the decoded
values plus per-splat bounds (:class:`QuantBounds`):

* centre:   |c - c_hat|_i <= pos_err_i per axis;
* sigmas:   s_i <= sigma_hi_i (inf: the code saturated, the size is not bounded);
* rotation: the true unit quaternion q satisfies |q - q_hat|_2 <= quat_err (sign chosen to match).

:func:`inflated_sigmas` turns them into sigmas S' with E_true ⊆ {c_hat + R_hat S' u : |u| <= k}
for EVERY such splat. Proof (details in docs/formats.md): with R = R_hat D, ||D - I||_2 <= eta =
2 quat_err (the angle phi between q and the line through q_hat has sin phi <= |q - q_hat| since
q_hat lies on it, theta = 2 phi, ||D - I|| = 2 sin(theta/2)), every p in E_true is

    p - c_hat = (c - c_hat) + R_hat S u + R_hat (D - I) S u  in  R_hat (S_hi B_k) (+) B(r),
    r = |pos_err|_2 + eta k max_i sigma_hi_i,

and an axis-aligned ellipsoid with semi-axes a_i, Minkowski-summed with a ball of radius r, lies in
the ellipsoid with semi-axes A_i = sqrt((1 + t) a_i^2 + (1 + 1/t) r^2) for ANY t > 0 (support
functions: (1+t) h_a^2 + (1+1/t) r^2 >= (h_a + r)^2 since 2 h_a r <= t h_a^2 + r^2 / t). t is
chosen per splat from a grid to make the volume small; any t is valid, so the grid only affects size.
Rigid motions and uniform scales preserve containment, so the inflation is done in the file frame,
before the scene transform.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

# t candidates for the ball term (any t > 0 is valid; the grid only decides how tight).
_T_GRID = np.logspace(-6, 3, 37)
_BLOCK = 16_384


@dataclass
class QuantBounds:
    """Per-splat outward bounds of a quantized file (file frame, file units).

    pos_err:    (N, 3) per-axis bound on |c_true - c_decoded|.
    sigma_hi:   (N, 3) upper bound on each true standard deviation (inf: saturated code).
    quat_err:   (N,) bound on |q_true - q_decoded|_2 (both as (w, x, y, z), sign matched).
    opacity_hi: (N,) upper bound on the true activated opacity (the opacity filter keeps a splat
                unless even this bound is below ``--min-opacity``).
    what:       one line naming the format's quantization (for summaries).
    """

    pos_err: np.ndarray
    sigma_hi: np.ndarray
    quat_err: np.ndarray
    opacity_hi: np.ndarray
    what: str = ""

    def subset(self, idx) -> "QuantBounds":
        return QuantBounds(self.pos_err[idx], self.sigma_hi[idx], self.quat_err[idx], self.opacity_hi[idx], self.what)

    def saturated(self) -> np.ndarray:
        """(N,) bool: a size code saturated at the format's top value, so the true size is unbounded."""
        return ~np.isfinite(self.sigma_hi).all(axis=1)


def rotation_eta(quat_err: np.ndarray) -> np.ndarray:
    """(N,) bound on ||R_hat^T R_true - I||_2 from the quaternion error bound."""
    return np.minimum(2.0 * np.asarray(quat_err, np.float64), 2.0)


def rotation_angle_deg(quat_err: np.ndarray) -> np.ndarray:
    """(N,) bound on the rotation angle between decoded and true rotation, degrees."""
    return np.degrees(2.0 * np.arcsin(np.minimum(np.asarray(quat_err, np.float64), 1.0)))


def inflated_sigmas(bounds: QuantBounds, k: float) -> np.ndarray:
    """(N, 3) sigmas S' such that {c_hat + R_hat S' u : |u| <= k} holds every true k-sigma ellipsoid.

    Rows whose ``sigma_hi`` is infinite come back infinite (refused by the loader)."""
    a = k * np.asarray(bounds.sigma_hi, np.float64)
    ec = np.linalg.norm(bounds.pos_err, axis=1)
    with np.errstate(invalid="ignore"):
        r = ec + rotation_eta(bounds.quat_err) * a.max(axis=1)
    out = a.copy()
    rows_all = np.flatnonzero((r > 0) & np.isfinite(r))
    t = _T_GRID[None, :, None]
    for lo in range(0, rows_all.size, _BLOCK):
        rows = rows_all[lo: lo + _BLOCK]
        a2 = (a[rows] ** 2)[:, None, :]
        r2 = (r[rows] ** 2)[:, None, None]
        A2 = (1.0 + t) * a2 + (1.0 + 1.0 / t) * r2
        best = np.argmin(np.log(A2).sum(axis=2), axis=1)
        # one ulp-scale widening per axis so the float64 sqrt cannot round the bound inward
        out[rows] = np.sqrt(A2[np.arange(rows.size), best]) * (1.0 + 4e-16)
    out[~np.isfinite(r)] = np.inf
    return out / k


def quat_err_from_components(delta: np.ndarray) -> np.ndarray:
    """|q - q_hat|_2 bound when every stored component is known within ``delta`` (N, 4)."""
    return np.sqrt(np.sum(np.asarray(delta, np.float64) ** 2, axis=1))


def quat_err_smallest(small: np.ndarray, delta: float, cap: float) -> np.ndarray:
    """|q - q_hat| bound for 'smallest-m' codes: ``small`` (N, m) decoded components, each within
    ``delta`` of the true one, the remaining component reconstructed as sqrt(1 - |small|^2); the
    true small part has norm <= ``cap`` (sqrt(3)/2 when the largest component is left out, 1 for
    spz v2's x, y, z with w >= 0)."""
    m = small.shape[1]
    rho = math.sqrt(m) * delta
    n = np.linalg.norm(small, axis=1)
    lo = np.clip(n - rho, 0.0, cap)
    hi = np.clip(n + rho, 0.0, cap)
    big_hat = np.sqrt(np.maximum(0.0, 1.0 - n * n))
    big_lo = np.sqrt(np.maximum(0.0, 1.0 - hi * hi))
    big_hi = np.sqrt(np.maximum(0.0, 1.0 - lo * lo))
    dbig = np.maximum(np.abs(big_hat - big_lo), np.abs(big_hat - big_hi))
    return np.sqrt(rho * rho + dbig * dbig)


# --------------------------------------------------------------------------- .splat quaternion

# Writers of antimatter15 .splat files disagree on how a unit quaternion component q in [-1, 1]
# becomes the byte u: antimatter15's convert.py and SuperSplat truncate q*128 + 128, others
# round it, and splat-transform decodes u as (u - 127.5)/127.5 (so it writes round(q*127.5 + 127.5)).
# The true component lies in the union of the three buckets:
#   truncate, 128:   [(u - 128)/128,   (u - 127)/128]
#   round, 128:      [(u - 128.5)/128, (u - 127.5)/128]
#   round, 127.5:    [(u - 128)/127.5, (u - 127)/127.5]
SPLAT_QUAT_SLACK = 2e-6  # float32 normalisation in the writer


def splat_quat_interval(u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(lo, hi) bounds of the true unit-quaternion component behind each .splat byte ``u``."""
    u = np.asarray(u, np.float64)
    lo = np.minimum.reduce([(u - 128.0) / 128.0, (u - 128.5) / 128.0, (u - 128.0) / 127.5])
    hi = np.maximum.reduce([(u - 127.0) / 128.0, (u - 127.5) / 128.0, (u - 127.0) / 127.5])
    return np.clip(lo - SPLAT_QUAT_SLACK, -1.0, 1.0), np.clip(hi + SPLAT_QUAT_SLACK, -1.0, 1.0)


def decode_splat_quaternion(rot: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """.splat quaternion bytes (N, 4) (w, x, y, z) -> (q_hat (N, 4), quat_err (N,)).

    q_hat is the centre of each component's bucket (not normalised; the loader normalises, which
    keeps the direction and so the rotation), and quat_err bounds |q_true - q_hat|_2 for every unit
    q_true whose bytes are ``rot`` under any of the writers above."""
    lo, hi = splat_quat_interval(rot)
    q_hat = 0.5 * (lo + hi)
    return q_hat, quat_err_from_components(0.5 * (hi - lo))


def splat_opacity_hi(a: np.ndarray) -> np.ndarray:
    """Upper bound of the true opacity behind a .splat alpha byte (floor or round of 255 alpha)."""
    return np.minimum((np.asarray(a, np.float64) + 1.0) / 255.0, 1.0)
