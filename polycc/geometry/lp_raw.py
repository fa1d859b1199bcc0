"""scipy's HiGHS linear programs, called without ``linprog``'s Python bookkeeping.

``scipy.optimize.linprog(method="highs")`` spends about 1.5 ms per call on a 4-variable LP (the Chebyshev
centre of a polytope, ~6 000 per 6M-splat build) in its own Python: input cleaning, one option check per
option, the result object; HiGHS itself takes about 0.2 ms. :func:`linprog_highs` builds the same HiGHS
model with the same options through the class ``linprog`` ends in (``scipy.optimize._highspy._core``) and
runs the same result check, so its solution is ``linprog``'s, bit for bit (tested against it). If those
private names ever change, it calls ``linprog`` itself.
"""

from __future__ import annotations

import numpy as np

try:
    import scipy.optimize._highspy._core as _h
    from scipy.optimize._linprog_util import _check_result
except ImportError:  # pragma: no cover - private API drift
    _h = None


def _options():
    """The options ``_linprog_highs`` passes for ``method="highs"`` with no user options, as
    ``_highs_wrapper`` sets them (the ``None`` ones are left at HiGHS's defaults)."""
    from scipy.optimize._highspy import _highs_options  # noqa: F401  (the wrapper's own import)
    from scipy.optimize._linprog_highs import HighsDebugLevel, s_c

    o = _h.HighsOptions()
    o.presolve = "on"
    o.highs_debug_level = HighsDebugLevel.kHighsDebugLevelNone
    o.log_to_console = False
    o.output_flag = False
    o.simplex_strategy = s_c.SimplexStrategy.kSimplexStrategyDual
    return o


_OPTIONS = None


def linprog_highs(c: np.ndarray, A_ub: np.ndarray, b_ub: np.ndarray, lb: np.ndarray, ub: np.ndarray
                  ) -> tuple[int, np.ndarray | None, np.ndarray | None]:
    """(scipy status, x, the inequalities' marginals) of ``res = linprog(c, A_ub, b_ub, bounds=zip(lb, ub),
    method="highs")`` for a dense ``A_ub`` (float64): ``res.status`` (0 = optimal and checked), ``res.x``,
    ``res.ineqlin.marginals``."""
    global _OPTIONS
    c = np.asarray(c, np.float64)
    A = np.asarray(A_ub, np.float64)
    b = np.asarray(b_ub, np.float64)
    lb = np.asarray(lb, np.float64)
    ub = np.asarray(ub, np.float64)
    if _h is not None:
        try:
            if _OPTIONS is None:
                _OPTIONS = _options()
            return _run(c, A, b, lb, ub)
        except (AttributeError, TypeError, ImportError):  # pragma: no cover - private API drift
            _OPTIONS = None
    from scipy.optimize import linprog

    res = linprog(c=c, A_ub=A, b_ub=b, bounds=list(zip(lb, ub)), method="highs")
    return int(res.status), res.x, res.ineqlin.marginals


def _run(c, A, b, lb, ub):
    m, n = A.shape
    nz = A.T != 0  # column-major nonzeros, rows ascending: the csc_array of the dense matrix
    lp = _h.HighsLp()
    lp.num_col_ = n
    lp.num_row_ = m
    lp.a_matrix_.num_col_ = n
    lp.a_matrix_.num_row_ = m
    lp.a_matrix_.format_ = _h.MatrixFormat.kColwise
    lp.col_cost_ = c
    lp.col_lower_ = lb.copy()
    lp.col_upper_ = ub.copy()
    lp.row_lower_ = np.full(m, -np.inf)
    lp.row_upper_ = b
    lp.a_matrix_.start_ = np.concatenate([[0], np.cumsum(nz.sum(axis=1))]).astype(np.int32)
    lp.a_matrix_.index_ = np.nonzero(nz)[1].astype(np.int32)
    lp.a_matrix_.value_ = A.T[nz]
    highs = _h._Highs()
    if highs.passOptions(_OPTIONS) == _h.HighsStatus.kError or highs.passModel(lp) == _h.HighsStatus.kError:
        return 4, None, None
    if highs.run() == _h.HighsStatus.kError or highs.getModelStatus() != _h.HighsModelStatus.kOptimal:
        return 2, None, None  # any failure: the callers only test status != 0
    info = highs.getInfo()
    sol = highs.getSolution()
    x = np.array(sol.col_value)
    slack = b - np.asarray(sol.row_value)[:m]
    status, _ = _check_result(x, info.objective_function_value, 0, slack, np.empty(0), np.c_[lb, ub], 1e-9, "",
                              None)
    return int(status), x, np.array(sol.row_dual)[:m]
