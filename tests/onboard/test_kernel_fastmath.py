"""polycc_exp / polycc_log: documented error bounds, the sign facts the certificate uses,
and bit parity between the C (host) and polycc/fastmath.py."""

from __future__ import annotations

import numpy as np
import pytest

from polycc.onboard.fastmath import exp32, log32

kffi = pytest.importorskip("polycc.sim.kernel_ffi")

EXP_REL_MAX = 3.0e-7  # documented in polycc_kernel.h
LOG_ABS_MAX = 6.0e-7  # on [1, 65536]
LOG_REL_MAX = 3.0e-7


def test_exp_error_bound_dense_grid():
    x = np.linspace(-87.0, 88.0, 4_000_001).astype(np.float32)
    y = exp32(x)
    assert np.array_equal(y.view(np.uint32), kffi.exp_batch(x).view(np.uint32))
    t = np.exp(x.astype(np.float64))
    rel = np.abs(y - t) / t
    assert rel.max() <= EXP_REL_MAX, rel.max()


def test_exp_special_values():
    x = np.array([0.0, -0.0, -87.0, -87.00001, -1e30, -np.inf, np.nan, 88.0, 1e30, np.inf], np.float32)
    y = kffi.exp_batch(x)
    assert np.array_equal(y.view(np.uint32), exp32(x).view(np.uint32))
    assert y[0] == 1.0 and y[1] == 1.0, "exp(0) == 1 exactly (the certificate needs S >= 1)"
    assert y[2] > 0 and np.all(y[3:7] == 0)
    assert np.all(np.isfinite(y)) and y[7] == y[8] == y[9]


def test_log_error_bound():
    x = np.exp(np.linspace(0.0, np.log(65536.0), 2_000_001)).astype(np.float32)
    y = log32(x)
    assert np.array_equal(y.view(np.uint32), kffi.log_batch(x).view(np.uint32))
    t = np.log(x.astype(np.float64))
    err = np.abs(y - t)
    assert err.max() <= LOG_ABS_MAX
    big = x > 1.001
    assert (err[big] / t[big]).max() <= LOG_REL_MAX


def _floats_between(lo: float, hi: float) -> np.ndarray:
    a, b = np.float32(lo).view(np.uint32), np.float32(hi).view(np.uint32)
    return np.arange(a, b + 1, dtype=np.uint32).view(np.float32)


def test_log_nonnegative_exhaustive_first_octaves():
    """Every float32 in [1, 4]: log >= 0 (the soft-min needs log(S) >= 0 for S >= 1)."""
    x = _floats_between(1.0, 4.0)
    assert log32(x[:1])[0] == 0.0
    for chunk in np.array_split(x, 8):
        assert np.all(log32(chunk) >= 0)


@pytest.mark.slow
def test_log_nonnegative_exhaustive_to_65536():
    x = _floats_between(4.0, 65536.0)
    for chunk in np.array_split(x, 64):
        assert np.all(log32(chunk) >= 0)


@pytest.mark.slow
def test_exp_exhaustive_nonpositive_bitexact_and_bounded():
    """Every float32 in [-87, -1/64] (the soft-max/soft-min range that matters):
    C == Python bit for bit, 0 < exp <= 1, within the bound."""
    x = _floats_between(1.0 / 64.0, 87.0)
    for chunk in np.array_split(-x, 32):
        y = exp32(chunk)
        assert np.array_equal(y.view(np.uint32), kffi.exp_batch(chunk).view(np.uint32))
        assert np.all((y > 0) & (y <= 1))
        t = np.exp(chunk.astype(np.float64))
        assert (np.abs(y - t) / t).max() <= EXP_REL_MAX
