"""Exact dense QP solver for small strictly convex problems with a diagonal Hessian: DAQP's dual active-set method.

Solves ``min x'Px/2 + c'x  s.t.  lo <= A x <= hi`` with ``P = diag(p)``, ``p > 0``, by DAQP (Arnström, Bemporad
and Axehill 2022, "A dual active-set solver for embedded quadratic programming using recursive LDL' updates",
IEEE TAC 67(8)), a dual active-set method in C: from the unconstrained minimum (or a guessed active set), add
the most violated constraint and drop constraints whose multiplier would turn negative until none is violated.
Every iterate stays dual feasible and the objective rises strictly: the method ends at the exact optimum or
proves the problem infeasible. No time limit: the same data give the same iterates (deterministic).

Rows with a single non-zero entry are handed to DAQP as variable bounds (its cheap "simple bounds"), the others
as general rows. ``agent.solve`` uses it as the polish of OSQP and for the Q re-solves of the rounding; its
answers are accepted only after a KKT check, and a failure (iteration limit, numerical trouble) returns a
``failed`` result and the caller goes on with ADMM. Multipliers are returned in OSQP's sign convention:
``y > 0`` on rows at their upper bound, ``y < 0`` at their lower bound.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import daqp
import numpy as np

from agent.dense_split import DenseSplit, dense_split

__all__ = ["ActiveSetResult", "solve_dense_qp"]

#: DAQP's constraint kinds (its ``sense`` flags): a row guessed active (a warm start), an equality.
_ACTIVE = 1
_EQUALITY = 5
#: DAQP's exit flags: optimal, and a proven infeasible problem.
_OPTIMAL = 1
_INFEASIBLE = -1
_ITERATION_LIMIT = -4


@dataclass(frozen=True)
class ActiveSetResult:
    """Outcome of ``solve_dense_qp``.

    ``status``: ``optimal`` (``x``, ``y`` hold the solution), ``infeasible`` (the constraints have no common
    point), ``failed`` (inconsistent data, the step limit, or numerical trouble; ``x``, ``y`` are zeros).
    ``steps`` counts the method's iterations (constraints added or dropped).
    """

    status: Literal["optimal", "infeasible", "failed"]
    x: np.ndarray
    y: np.ndarray
    steps: int
    reason: str = ""


def solve_dense_qp(
    p_diag: np.ndarray,
    c: np.ndarray,
    a: np.ndarray,
    lo: np.ndarray,
    hi: np.ndarray,
    *,
    guess: np.ndarray | None = None,
    max_steps: int | None = None,
    split: DenseSplit | None = None,
) -> ActiveSetResult:
    """Solve the QP exactly; ``y`` has OSQP's multiplier signs.

    Parameters
    ----------
    p_diag : (n,) positive diagonal of ``P``.
    c : (n,) linear cost.
    a : (m, n) dense constraint matrix.
    lo, hi : (m,) bounds, ``lo <= hi`` (infinite for a missing side); ``lo == hi`` is an equality.
    guess : (m,) optional start: non-zero marks a row guessed active (DAQP's warm start); the method drops
        the rows of a wrong guess, so only the number of steps depends on it.
    max_steps : limit on the method's iterations (default ``2 (m + n) + 100``).
    split : ``dense_split(a)``, for a caller that solves with one matrix many times (made here when None).

    Returns
    -------
    An ``ActiveSetResult``; never raises on numeric trouble.
    """
    n, m = p_diag.shape[0], a.shape[0]
    # (array methods, not np.any / np.unique: several calls a decision, each a few microseconds of wrappers)
    if (p_diag <= 0.0).any() or (lo > hi).any() or a.shape != (m, n) or c.shape != (n,):
        return _failed(n, m, 0, "inconsistent data (P not positive, lo > hi or shapes)")
    if split is None:
        split = dense_split(a)
    bound_rows, general, column, coef = split.bound_rows, split.general, split.column, split.coef
    b_lo = np.full(n, -np.inf)
    b_hi = np.full(n, np.inf)
    b_lo[column] = np.where(coef > 0, lo[bound_rows], hi[bound_rows]) / coef
    b_hi[column] = np.where(coef > 0, hi[bound_rows], lo[bound_rows]) / coef
    upper = np.concatenate([b_hi, hi[general]])
    lower = np.concatenate([b_lo, lo[general]])
    sense = np.zeros(n + general.size, np.intc)
    sense[lower == upper] = _EQUALITY
    limit = 2 * (m + n) + 100 if max_steps is None else max_steps
    h, f, a_rows = np.diag(p_diag), np.array(c, float), split.a_rows
    flag, steps = 0, 0
    if guess is not None and np.asarray(guess).any():
        # Warm: the guessed rows start active. A guess DAQP cannot start from (dependent rows) is dropped.
        warm = sense.copy()
        guessed = np.zeros(sense.size, bool)
        guessed[split.rows_of[np.asarray(guess)[split.order] != 0]] = True
        warm[guessed & (warm == 0)] = _ACTIVE
        x, _, flag, info = daqp.solve(h, f, a_rows, upper, lower, warm, iter_limit=limit)
        steps = int(info["iterations"])
        if flag == _OPTIMAL and not np.isfinite(info["lam"]).all():
            flag = 0
    if flag != _OPTIMAL:
        x, _, flag, info = daqp.solve(h, f, a_rows, upper, lower, sense, iter_limit=limit)
        steps += int(info["iterations"])
    if flag == _INFEASIBLE:
        return ActiveSetResult("infeasible", np.zeros(n), np.zeros(m), steps, "no point meets every constraint")
    if flag != _OPTIMAL:
        why = f"step limit ({limit})" if flag == _ITERATION_LIMIT else f"DAQP exit flag {flag}"
        return _failed(n, m, steps, why)
    lam = np.asarray(info["lam"], float)
    y = np.zeros(m)
    y[bound_rows] = lam[column] / coef
    y[general] = lam[n:]
    x = np.asarray(x, float)
    if not (np.isfinite(x).all() and np.isfinite(y).all()):
        return _failed(n, m, steps, "non-finite solution")
    return ActiveSetResult("optimal", x, y, steps)


def _failed(n: int, m: int, steps: int, why: str) -> ActiveSetResult:
    """A ``failed`` result (zeros for ``x`` and ``y``) saying ``why``."""
    return ActiveSetResult("failed", np.zeros(n), np.zeros(m), steps, why)
