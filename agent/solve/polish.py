"""The exact polish: the dual active-set method (DAQP) from a guessed active set, accepted by a KKT check."""

from __future__ import annotations

import numpy as np

from agent.cvvc_qp import CvvcQp
from agent.solve.active_set import solve_dense_qp
from agent.solve.settings import FARKAS_MIN_EXCESS, KKT_TOL
from agent.solve.solution import Run

#: Proximal weight on the variables of the least-violation problem (DAQP needs a positive definite Hessian).
_PHASE_ONE_PROX = 1e-6

__all__ = ["active_set_polish", "farkas_excess", "kkt_ok", "least_violation", "least_violation_multipliers",
           "proven_infeasible", "warm_polish"]


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
    out = solve_dense_qp(qp.p_diag, qp.c, a_dense, lo, hi, guess=guess, split=qp.dense_split)
    if out.status == "infeasible":
        return Run(False, True, "infeasible (active set)", out.x, out.y, 0)
    if out.status == "failed" and proven_infeasible(a_dense, lo, hi):
        return Run(False, True, "infeasible (least violation)", np.zeros(qp.layout.n), np.zeros(lo.shape[0]), 0)
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
    ax = a @ x  # (array methods, not np.max / np.any: several calls a decision)
    if np.abs(p_diag * x + c + a.T @ y).max(initial=0.0) > KKT_TOL:
        return False
    if (ax < lo - KKT_TOL).any() or (ax > hi + KKT_TOL).any():
        return False
    return not (((y > KKT_TOL) & (ax < hi - KKT_TOL)).any() or ((y < -KKT_TOL) & (ax > lo + KKT_TOL)).any())


def proven_infeasible(a: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> bool:
    """Whether no ``x`` meets ``lo <= A x <= hi``, proven by a Farkas certificate from the least-violation problem.

    For the problems the dual active-set method gives up on (it cycles on the near-parallel voltage rows of nodes
    behind one regulator), which ADMM then took up to its whole budget to declare infeasible, or never did. Proven
    when ``least_violation_multipliers``' ``y`` have a ``farkas_excess`` above ``FARKAS_MIN_EXCESS`` per unit of
    ``|y|`` on the rows with more than one entry: a least violation that small proves nothing (left to ADMM, as
    before). False when not proven.
    """
    y = least_violation_multipliers(a, lo, hi)
    if y is None:
        return False
    rows = np.count_nonzero(a, axis=1) > 1
    return farkas_excess(a, lo, hi, y) > FARKAS_MIN_EXCESS * float(np.sum(np.abs(y[rows])))


def least_violation_multipliers(a: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray | None:
    """(m,) multipliers of ``lo <= A x <= hi`` from its least-violation problem, or None when its violation is at most
    ``FARKAS_MIN_EXCESS`` (or the method fails).

    The rows with one entry (the variable bounds) stay hard, every other row's bounds widen by one slack ``s >= 0``;
    ``min s^2/2 + 1e-6 |x|^2/2`` (``least_violation``: strictly convex, always feasible). Where the rows conflict, its
    multipliers are a Farkas certificate (``farkas_excess``) up to the small proximal term.
    """
    n = a.shape[1]
    widen = np.count_nonzero(a, axis=1) > 1
    if not widen.any():
        return None
    out = least_violation(a, lo, hi, widen, np.full(n, _PHASE_ONE_PROX), np.zeros(n))
    if out is None or out[1] <= FARKAS_MIN_EXCESS:
        return None
    return out[0]


def least_violation(a: np.ndarray, lo: np.ndarray, hi: np.ndarray, widen: np.ndarray, p_diag: np.ndarray,
                    c: np.ndarray) -> tuple[np.ndarray, float] | None:
    """``(y, s)``: ``min x'diag(p_diag)x/2 + c'x + s^2/2`` with the rows ``widen`` (bool mask) within
    ``[lo - s, hi + s]``, the others within ``[lo, hi]``, ``s >= 0`` (DAQP); ``y`` (m,) the multipliers of the rows
    ``lo <= A x <= hi`` (a widened row's two sides summed), ``s`` the least slack. None when DAQP fails.
    """
    m, n = a.shape
    rows, other = np.flatnonzero(widen), np.flatnonzero(~widen)
    k = rows.size
    one = np.ones((k, 1))
    a1 = np.vstack([
        np.hstack([a[rows], -one]),  # A x - s <= hi
        np.hstack([a[rows], one]),  # A x + s >= lo
        np.hstack([a[other], np.zeros((other.size, 1))]),
        np.hstack([np.zeros((1, n)), np.ones((1, 1))]),  # s >= 0
    ])
    lo1 = np.concatenate([np.full(k, -np.inf), lo[rows], lo[other], [0.0]])
    hi1 = np.concatenate([hi[rows], np.full(k, np.inf), hi[other], [np.inf]])
    out = solve_dense_qp(np.append(p_diag, 1.0), np.append(c, 0.0), a1, lo1, hi1)
    if out.status != "optimal":
        return None
    y = np.zeros(m)
    y[rows] = out.y[:k] + out.y[k : 2 * k]
    y[other] = out.y[2 * k : 2 * k + other.size]
    return y, float(out.x[-1])


def farkas_excess(a: np.ndarray, lo: np.ndarray, hi: np.ndarray, y: np.ndarray) -> float:
    """``min over the box of (A'y)'x - (hi'y+ + lo'y-)``: positive, it proves that no ``x`` meets ``lo <= A x <= hi``.

    The box is the one-entry rows' (the variable bounds); ``-inf`` when ``y`` leans on a missing bound or ``A'y``
    points along a variable without one. Every ``x`` meeting the rows has ``y'Ax <= hi'y+ + lo'y-`` and
    ``y'Ax >= min over the box of (A'y)'x``.
    """
    if np.any((y > 0.0) & ~np.isfinite(hi)) or np.any((y < 0.0) & ~np.isfinite(lo)):
        return -np.inf
    n = a.shape[1]
    box = np.flatnonzero(np.count_nonzero(a, axis=1) == 1)
    upper = float(np.sum(np.where(y > 0.0, y * np.where(y > 0.0, hi, 0.0), 0.0))
                  + np.sum(np.where(y < 0.0, y * np.where(y < 0.0, lo, 0.0), 0.0)))
    col = np.argmax(a[box] != 0.0, axis=1)
    coef = a[box, col]
    x_lo, x_hi = np.full(n, -np.inf), np.full(n, np.inf)
    np.maximum.at(x_lo, col, np.where(coef > 0, lo[box], hi[box]) / coef)
    np.minimum.at(x_hi, col, np.where(coef > 0, hi[box], lo[box]) / coef)
    r = a.T @ y
    with np.errstate(invalid="ignore"):
        least = np.where(r > 0.0, r * x_lo, np.where(r < 0.0, r * x_hi, 0.0))
    if not np.all(np.isfinite(least)):
        return -np.inf
    return float(np.sum(least)) - upper
