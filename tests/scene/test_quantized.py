"""Quantized formats: every true splat behind the stored bits is inside the loaded (inflated) ellipsoid.

Regression (safety): polycc's .splat reader decoded the 8-bit quaternion as (u - 128)/128 and
treated it as exact; writers truncate or round (with 128 or 127.5), so the true rotation is only
known within a bucket of ~1-2 degrees and a thin, wide splat could stick out of its ellipsoid.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from polycc.scene.ellipsoids import quaternion_to_rotation
from polycc.scene.load import SceneOptions, load_scene
from polycc.scene.quantized import QuantBounds, inflated_sigmas

BUCKETS = {  # [lo, hi) of the unit-quaternion component each writer stores as byte u
    "truncate128": lambda u: ((u - 128) / 128, (u - 127) / 128),
    "round128": lambda u: ((u - 128.5) / 128, (u - 127.5) / 128),
    "round127.5": lambda u: ((u - 128) / 127.5, (u - 127) / 127.5),
}
WRITERS = {
    "truncate128": lambda q: np.clip(q * 128 + 128, 0, 255).astype(np.uint8),          # antimatter15, SuperSplat
    "round128": lambda q: np.clip(np.floor(q * 128 + 128.5), 0, 255).astype(np.uint8),
    "round127.5": lambda q: np.clip(np.floor(q * 127.5 + 128.0), 0, 255).astype(np.uint8),  # splat-transform
}


def _write_splat(path, pos, scale, q_bytes, alpha=255):
    rec = np.zeros(len(pos), dtype=[("pos", "<f4", 3), ("scale", "<f4", 3), ("rgba", "u1", 4), ("rot", "u1", 4)])
    rec["pos"], rec["scale"], rec["rot"] = pos, scale, q_bytes
    rec["rgba"] = [200, 100, 50, alpha]
    rec.tofile(path)
    return path


def _surface_points(c, R, s, k, m=400, seed=0):
    """Points on the true k-sigma ellipsoid surface: 6 axis ends + m random."""
    rng = np.random.default_rng(seed)
    u = np.concatenate([np.eye(3), -np.eye(3), rng.normal(size=(m, 3))])
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    return c + (k * u * s) @ R.T


def _inside(ell, i, p):
    M = ell.whitening()[i]
    w = (p - ell.centers[i]) @ M.T
    return np.einsum("ij,ij->i", w, w) <= 1.0


def _random_unit_q(rng, n):
    q = rng.normal(size=(n, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)


@pytest.mark.parametrize("writer", sorted(WRITERS))
def test_splat_true_rotation_anywhere_in_bucket_is_covered(tmp_path, writer):
    """For each stored code, true quaternions all over its bucket (same bytes) stay inside the loaded splat."""
    rng = np.random.default_rng(1)
    enc = WRITERS[writer]
    n_codes, per_code = 40, 25
    base = _random_unit_q(rng, n_codes)
    codes = enc(base)
    scale = np.tile([0.30, 0.12, 0.0005], (n_codes, 1)).astype(np.float32)  # a wide, thin disc (worst case)
    pos = rng.uniform(-1, 1, (n_codes, 3)).astype(np.float32)
    p = _write_splat(tmp_path / "s.splat", pos, scale, codes)
    for k in (1.0, 3.0):
        ell = load_scene(p, SceneOptions(sigma=k)).ellipsoids
        covered = 0
        for i in range(n_codes):
            # true unit quaternions with the same bytes: rejection-sample around the bucket
            # three components uniform over their whole buckets, the largest one from |q| = 1
            lo, hi = BUCKETS[writer](codes[i].astype(np.float64))
            j = int(np.argmax(np.abs(base[i])))
            cand = rng.uniform(lo, hi, (20000, 4))
            rest = np.delete(np.arange(4), j)
            cand[:, j] = np.sign(base[i, j]) * np.sqrt(np.maximum(0, 1 - (cand[:, rest] ** 2).sum(1)))
            same = cand[np.all(enc(cand) == codes[i], axis=1)][:per_code]
            assert len(same) >= 5, "the rejection sampler found too few quaternions in the bucket"
            for q in same:
                R = quaternion_to_rotation(q[None])[0]
                pts = _surface_points(pos[i].astype(np.float64), R, scale[i].astype(np.float64), k)
                assert _inside(ell, i, pts).all(), f"{writer}: true splat {i} outside its loaded ellipsoid"
                covered += 1
        assert covered >= 5 * n_codes


def test_bare_splat_decode_would_miss(tmp_path):
    """The old reading ((u - 128)/128, no inflation) leaves true rotations outside: the test can fail."""
    rng = np.random.default_rng(2)
    q = _random_unit_q(rng, 200)
    codes = WRITERS["truncate128"](q)
    scale = np.array([0.30, 0.12, 0.0005])
    old = (codes.astype(np.float64) - 128) / 128
    old /= np.linalg.norm(old, axis=1, keepdims=True)
    misses = 0
    for i in range(len(q)):
        pts = _surface_points(np.zeros(3), quaternion_to_rotation(q[i:i + 1])[0], scale, 1.0)
        w = pts @ quaternion_to_rotation(old[i:i + 1])[0] / scale
        misses += bool((np.einsum("ij,ij->i", w, w) > 1.0).any())
    assert misses > 150


@given(st.floats(1e-4, 1.0), st.floats(1e-4, 1.0), st.floats(1e-4, 1.0), st.floats(0.0, 0.05),
       st.floats(0.0, 0.01), st.floats(0.5, 3.0), st.integers(0, 2**31 - 1))
def test_inflation_contains_every_perturbed_ellipsoid(s0, s1, s2, e_pos, e_q, k, seed):
    """inflated_sigmas: any centre/rotation/scale within the bounds stays inside the inflated ellipsoid."""
    rng = np.random.default_rng(seed)
    s = np.array([s0, s1, s2])
    q_hat = _random_unit_q(rng, 1)
    b = QuantBounds(pos_err=np.full((1, 3), e_pos), sigma_hi=s[None], quat_err=np.array([e_q]),
                    opacity_hi=np.ones(1))
    S = inflated_sigmas(b, k)[0]
    R_hat = quaternion_to_rotation(q_hat)[0]
    for _ in range(10):
        dq = rng.normal(size=4)
        dq *= rng.uniform(0, e_q) / np.linalg.norm(dq)
        q = q_hat[0] + dq
        q /= np.linalg.norm(q)  # |q - q_hat| <= e_q before normalising; normalising moves it along the ray
        R = quaternion_to_rotation(q[None])[0]
        c = rng.uniform(-e_pos, e_pos, 3)
        st_true = s * rng.uniform(0.5, 1.0, 3)
        pts = _surface_points(c, R, st_true, k, m=60, seed=int(rng.integers(1 << 30)))
        w = (pts @ R_hat) / (k * S)
        assert np.all(np.einsum("ij,ij->i", w, w) <= 1.0 + 1e-9)


def test_splat_opacity_filter_is_outward(tmp_path):
    """--min-opacity keeps a .splat splat unless even the top of its alpha bucket is below it."""
    p = _write_splat(tmp_path / "a.splat", np.zeros((1, 3), np.float32), np.full((1, 3), 0.01, np.float32),
                     np.array([[255, 128, 128, 128]], np.uint8), alpha=127)  # 127/255 = 0.498
    assert load_scene(p, SceneOptions(min_opacity=0.5)).stats.kept == 1  # (127 + 1)/255 = 0.502 >= 0.5
