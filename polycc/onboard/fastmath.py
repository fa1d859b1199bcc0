"""float32 mirrors of ``polycc_exp`` / ``polycc_log`` (firmware_app/src/polycc_kernel.c).

Same constants (parsed from the same decimal strings), same operations, same order, so the
results are bit-identical to the C compiled with ``-ffp-contract=off``.
"""

from __future__ import annotations

import numpy as np

F = np.float32

_LOG2E = F("1.44269502")
_MAGIC = F("12582912.0")  # 1.5 * 2^23: round to nearest integer
LN2_HI = F("0.693145751953125")
LN2_LO = F("1.42860677e-06")
_EXP_C = [F(s) for s in ("1.0", "0.5", "0.166666672", "0.0416666679", "0.00833333377", "0.00138888892")]
_LOG_C = [F(s) for s in ("2.0", "0.666666687", "0.400000006", "0.285714298", "0.222222224")]
ONE = F(1.0)


def exp32(x) -> np.ndarray:
    """Mirror of ``polycc_exp`` (elementwise on a float32 array)."""
    x = np.asarray(x, dtype=F)
    out = np.zeros(x.shape, F)
    ok = x >= F(-87.0)  # false for NaN, as in C
    xc = np.minimum(x[ok], F(88.0))
    t = xc * _LOG2E
    kf = (t + _MAGIC) - _MAGIC
    r = (xc - kf * LN2_HI) - kf * LN2_LO
    c1, c2, c3, c4, c5, c6 = _EXP_C
    p = ONE + r * (c1 + r * (c2 + r * (c3 + r * (c4 + r * (c5 + r * c6)))))
    scale = ((kf.astype(np.int32) + 127).astype(np.uint32) << np.uint32(23)).view(F)
    out[ok] = p * scale
    return out


def log32(x) -> np.ndarray:
    """Mirror of ``polycc_log`` (normal finite x > 0)."""
    x = np.asarray(x, dtype=F)
    b = x.view(np.uint32)
    e = ((b >> np.uint32(23)) & np.uint32(0xFF)).astype(np.int32) - 127
    mb = (b & np.uint32(0x007FFFFF)) | np.uint32(0x3F800000)
    big = mb > np.uint32(0x3FB504F3)
    mb = np.where(big, mb - np.uint32(0x00800000), mb).astype(np.uint32)
    e = e + big.astype(np.int32)
    f = mb.view(F)
    s = (f - ONE) / (f + ONE)
    z = s * s
    c0, c1, c2, c3, c4 = _LOG_C
    w = s * (c0 + z * (c1 + z * (c2 + z * (c3 + z * c4))))
    ef = e.astype(F)
    return ef * LN2_HI + (w + ef * LN2_LO)
