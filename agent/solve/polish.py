"""The exact polish: the dual active-set method (DAQP) from a guessed active set, accepted by a KKT check."""

from __future__ import annotations

import numpy as np

from agent.cvvc_qp import CvvcQp
from agent.solve.active_set import solve_dense_qp
from agent.solve.settings import KKT_TOL
from agent.solve.solution import Run

__all__ = ["active_set_polish", "kkt_ok", "warm_polish"]


def active_set_polish(
    qp: CvvcQp, lo: np.ndarray, hi: np.ndarray, x0: np.ndarray | None, y0: np.ndarray | None, status: str
) -> Run | None:
    """The exact optimum by the dual active-set method started at the active set of ``(x0, y0)``, or None.

    The guess is OSQP's polishing rule: a row is lower-active if ``A x - lo < -y``, upper-active if
    ``hi - A x < y`` (equality rows always); without ``(x0, y0)`` the method starts from the unconstrained
    minimum. Accepted only if the KKT conditions hold (a certificate of optimality); ``None`` when the problem
    has no dense copy, the method fails (step or size limit, numerical trouble), or the check fails.
    """
    a_dense = qp.a_dense
    if a_dense is None:
        return None
    guess = None
    if x0 is not None and y0 is not None and x0.shape == (qp.layout.n,) and y0.shape == lo.shape:
        z = a_dense @ x0
        lower = (lo == hi) | (z - lo < -y0)
        upper = ~lower & (hi - z < y0)
        guess = upper.astype(np.int8) - lower.astype(np.int8)
    out = solve_dense_qp(qp.p_diag, qp.c, a_dense, lo, hi, guess=guess)
    if out.status == "infeasible":
        return Run(False, True, "infeasible (active set)", out.x, out.y, 0)
    if out.status != "optimal" or not kkt_ok(a_dense, qp.p_diag, qp.c, lo, hi, out.x, out.y):
        return None
    return Run(True, False, status, out.x, out.y, 0)


def warm_polish(
    qp: CvvcQp, lo: np.ndarray, hi: np.ndarray, x0: np.ndarray | None, y0: np.ndarray | None
) -> Run | None:
    """The optimum from the warm start's active set (no ADMM at all), or None without a usable warm start.

    Between consecutive intervals the binding constraints rarely change: then the active-set method takes
    zero to a few steps. A warm start with no active row (all multipliers zero) is a valid start too: the
    method then begins at the unconstrained minimum.
    """
    if x0 is None or y0 is None or y0.shape != lo.shape:
        return None
    return active_set_polish(qp, lo, hi, x0, y0, "warm active set")


def kkt_ok(
    a: np.ndarray, p_diag: np.ndarray, c: np.ndarray, lo: np.ndarray, hi: np.ndarray, x: np.ndarray, y: np.ndarray
) -> bool:
    """KKT conditions of ``min x'Px/2 + c'x, lo <= Ax <= hi`` hold within ``KKT_TOL`` (so ``x`` is optimal)."""
    ax = a @ x
    if np.max(np.abs(p_diag * x + c + a.T @ y), initial=0.0) > KKT_TOL:
        return False
    if np.any(ax < lo - KKT_TOL) or np.any(ax > hi + KKT_TOL):
        return False
    return not (np.any((y > KKT_TOL) & (ax < hi - KKT_TOL)) or np.any((y < -KKT_TOL) & (ax > lo + KKT_TOL)))
