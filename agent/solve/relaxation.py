"""The OSQP side of the solve: set-up with the fixed settings, ADMM in chunks each followed by the polish.

Determinism: a fresh OSQP object per stage, fixed settings (iteration limits, no wall-clock limit), warm start
only from the caller's iterate. Same inputs -> bit-identical iterates.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping

import numpy as np
import osqp

from agent.cvvc_qp import CvvcQp
from agent.solve.polish import active_set_polish, kkt_ok, warm_polish
from agent.solve.settings import FIRST_CHUNK_ITER, LARGE_OSQP_SETTINGS, LOOSE_EPS, MAX_ITER, OSQP_SETTINGS
from agent.solve.solution import Run

__all__ = ["osqp_run", "osqp_settings", "setup_osqp", "solve_qp"]


def osqp_settings(qp: CvvcQp) -> Mapping[str, object]:
    """OSQP's fixed settings for ``qp``: the dense-size ones, or the large feeders' when ``qp`` is sparse."""
    return OSQP_SETTINGS if qp.a_dense is not None else LARGE_OSQP_SETTINGS


def setup_osqp(qp: CvvcQp) -> osqp.OSQP | None:
    """An OSQP solver set up on ``qp`` with the fixed settings, or ``None`` if OSQP refuses the data."""
    solver = osqp.OSQP(algebra="builtin")  # naming it skips a slow probe of optional algebras
    settings = osqp_settings(qp)
    try:
        solver.setup(qp.P, qp.c, qp.A, qp.lower, qp.upper, **settings)
    except (ValueError, osqp.OSQPException):
        return None
    return solver


def solve_qp(qp: CvvcQp, x0: np.ndarray | None, y0: np.ndarray | None) -> Run:
    """Solve ``qp``: first the warm start's active set (no ADMM at all), else set up OSQP and iterate."""
    warm = warm_polish(qp, qp.lower, qp.upper, x0, y0)
    if warm is not None:
        return warm
    solver = setup_osqp(qp)
    if solver is None:
        return Run(False, False, "OSQP setup refused the problem", np.zeros(qp.layout.n), np.zeros(qp.n_rows), 0)
    return osqp_run(solver, qp, qp.lower, qp.upper, x0, y0)


def osqp_run(
    solver: osqp.OSQP,
    qp: CvvcQp,
    lo: np.ndarray,
    hi: np.ndarray,
    x0: np.ndarray | None,
    y0: np.ndarray | None,
    max_iter: int = MAX_ITER,
) -> Run:
    """ADMM in chunks (25, 50, 100, ... iterations), each followed by an active-set polish checked by KKT.

    OSQP polishes only once its tolerances are met, which on this nearly linear problem can take thousands
    of iterations although the active set is right after a few dozen. After every chunk we guess the
    active set from the iterate, solve the equality-constrained QP on it, and accept the result when it
    satisfies the KKT conditions (a certificate of optimality, not a heuristic). The next chunk continues
    the ADMM iterates where the last one stopped. Deterministic: no clock, fixed chunk and iteration limits.
    """
    n, m = qp.layout.n, qp.n_rows
    a_dense, p_diag = qp.a_dense, qp.p_diag
    try:
        solver.warm_start(
            x=np.zeros(n) if x0 is None or x0.shape != (n,) else x0,
            y=np.zeros(m) if y0 is None or y0.shape != (m,) else y0,
        )
    except (ValueError, osqp.OSQPException) as e:
        return Run(False, False, f"warm start failed: {e}", np.zeros(n), np.zeros(m), 0)
    total = 0
    loosened = False
    chunk = FIRST_CHUNK_ITER
    status_name = "OSQP_UNSOLVED"
    while total < max_iter:
        try:
            if total >= max_iter // 2 and not loosened:
                # Half the budget spent without a certified answer (degenerate or badly conditioned, e.g.
                # a soft form over many nodes): accept OSQP's own convergence at a looser tolerance.
                solver.update_settings(eps_abs=LOOSE_EPS, eps_rel=LOOSE_EPS)
                loosened = True
            solver.update_settings(max_iter=min(chunk, max_iter - total))
            res = solver.solve(raise_error=False)
        except (ValueError, osqp.OSQPException) as e:
            return Run(False, False, f"solve failed: {e}", np.zeros(n), np.zeros(m), total)
        total += int(res.info.iter)
        status = osqp.SolverStatus(res.info.status_val)
        status_name = status.name
        if status in (osqp.SolverStatus.OSQP_PRIMAL_INFEASIBLE, osqp.SolverStatus.OSQP_PRIMAL_INFEASIBLE_INACCURATE):
            return Run(False, True, status_name, np.zeros(n), np.zeros(m), total)
        x = np.asarray(res.x, float)
        y = np.asarray(res.y, float)
        if not (x.shape == (n,) and np.all(np.isfinite(x)) and np.all(np.isfinite(y))):
            return Run(False, False, f"{status_name} with non-finite iterate", np.zeros(n), np.zeros(m), total)
        if a_dense is not None:
            if kkt_ok(a_dense, p_diag, qp.c, lo, hi, x, y):
                return Run(True, False, status_name, x, y, total)
            polished = active_set_polish(qp, lo, hi, x, y, status_name + "+polish")
            if polished is not None:
                return dataclasses.replace(polished, iterations=total)
        if status not in (
            osqp.SolverStatus.OSQP_MAX_ITER_REACHED,
            osqp.SolverStatus.OSQP_SOLVED,
            osqp.SolverStatus.OSQP_SOLVED_INACCURATE,
        ):
            break
        if status == osqp.SolverStatus.OSQP_SOLVED:
            # Converged to the tight tolerance: accept the iterate (within eps of the optimum).
            return Run(True, False, status_name, x, y, total)
        chunk *= 2
    return Run(False, False, f"{status_name} after {total} iterations", np.zeros(n), np.zeros(m), total)
