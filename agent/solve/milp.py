"""Integer taps by ``scipy.optimize.milp`` (HiGHS): the exact reference of eq. (9)-(15) and the rounding's fallback.

``solve_milp_reference`` is the exact optimum with hard limits everywhere (tests, benchmarks), in the QP's own
variables (tap steps up and down, each integer); ``milp_tap_changes`` finds integer taps meeting the hard limits of
the nodes that keep them when no rounding within one tap of the relaxation does (``agent.solve.rounding``), in the
*net* form: one integer change per regulator and a continuous ``t >= |change|`` for its cost. Same optimum, half
the integer variables and none of the split form's symmetry (a change of k steps is also k+j up and j down):
on the 24 fallback problems of IEEE 8500's decision bench, HiGHS's median time 0.21 s against 0.49 s, its largest
0.31 s against 1.25 s (docs/agent.md). The fallback calls HiGHS through ``highspy`` with the heuristics and presolve
off: on the 85 fallback problems of a whole IEEE 8500 day, median 0.20 s against 0.89 s with HiGHS's defaults (same
run), the same taps in 77 (an equal-cost alternative in the other 8).
"""

from __future__ import annotations

import highspy
import numpy as np
import scipy.optimize
import scipy.sparse as sp

from agent.cvvc_qp import CvvcInputs, CvvcQp, build_cvvc_qp
from agent.solve.settings import MILP_OPTIONS
from agent.solve.solution import MilpReference

__all__ = ["milp_tap_changes", "solve_milp_reference"]


def _milp(qp: CvvcQp, n_int: int, options: dict[str, float]) -> scipy.optimize.OptimizeResult:
    """``scipy.optimize.milp`` of ``qp``'s linear costs and rows with its first ``n_int`` variables integer."""
    integrality = np.zeros(qp.layout.n)
    integrality[:n_int] = 1
    lo = np.where(np.isfinite(qp.lower), qp.lower, -np.inf)
    hi = np.where(np.isfinite(qp.upper), qp.upper, np.inf)
    return scipy.optimize.milp(
        qp.c,
        integrality=integrality,
        bounds=scipy.optimize.Bounds(-np.inf, np.inf),
        constraints=scipy.optimize.LinearConstraint(sp.csr_matrix(qp.A), lo, hi),
        options=options,
    )


def milp_tap_changes(inputs: CvvcInputs, soft_nodes: np.ndarray, nodes: np.ndarray | None = None,
                     cutoff_cost: float = np.inf) -> np.ndarray | None:
    """(R,) integer tap changes meeting the hard limits of the nodes not in ``soft_nodes``, or None if none exists
    (or none costs less than ``cutoff_cost``).

    Eq. (9)-(15)'s linear costs (no proximal or violation terms: the caller re-solves Q with these taps fixed in
    its own form), violation variables at ``soft_nodes``, rows of ``nodes`` only (default: all). Variables
    ``[d (R, integer), t (R), Q+, Q-, violations]`` with ``t >= d``, ``t >= -d`` and the tap cost on ``t``; the
    voltage rows take ``d`` with a step up's coefficients (``build_cvvc_qp`` gives a step down the negated ones).
    Bounded by a node limit, not a time limit, so that the same inputs give the same taps. HiGHS through ``highspy``
    with its primal heuristics and presolve off (``MILP_OPTIONS``): on this small dense problem they were most of
    its time (its sub-MIPs 0.32 of 0.54 s in one IEEE 8500 problem). ``cutoff_cost`` [cost units, eq. 9] is the
    cost of integer taps the caller already has (HiGHS's objective bound: it prunes every branch that cannot beat it).
    """
    qp = build_cvvc_qp(inputs, soft=soft_nodes, nodes=nodes)
    lay, r, n = qp.layout, inputs.n_reg, qp.nodes.size
    assert lay.tap_up is not None and lay.tap_down is not None  # built with tap variables
    a = qp.A.tocsc()
    rest = slice(lay.tap_down.stop, lay.n)  # Q+, Q- and violation columns
    rest_lo = np.full(lay.n, -np.inf)  # the identity rows after the voltage rows bound taps and Q, not violations
    rest_hi = np.full(lay.n, np.inf)
    n_bounded = lay.q_abs.stop
    rest_lo[:n_bounded], rest_hi[:n_bounded] = qp.lower[n : n + n_bounded], qp.upper[n : n + n_bounded]
    eye = sp.identity(r, format="csc")
    zeros = sp.csc_matrix((r, lay.n - lay.tap_down.stop))
    rows = sp.vstack(
        [
            sp.hstack([a[:n, lay.tap_up], sp.csc_matrix((n, r)), a[:n, rest]]),  # voltage rows
            sp.hstack([-eye, eye, zeros]),  # t - d >= 0
            sp.hstack([eye, eye, zeros]),  # t + d >= 0
        ],
        format="csr",
    )
    cost = np.concatenate([np.zeros(r), qp.c[lay.tap_up], qp.c[rest]])
    integer = np.concatenate([np.ones(r, bool), np.zeros(r + lay.n - lay.tap_down.stop, bool)])
    col_lo = np.concatenate([-rest_hi[lay.tap_down], np.zeros(r), rest_lo[rest]])
    col_hi = np.concatenate([rest_hi[lay.tap_up], np.full(r, np.inf), rest_hi[rest]])
    row_lo = np.concatenate([qp.lower[:n], np.zeros(2 * r)])
    row_hi = np.concatenate([qp.upper[:n], np.full(2 * r, np.inf)])
    x = _highs_milp(cost, integer, col_lo, col_hi, rows.tocsc(), row_lo, row_hi, cutoff_cost / qp.cost_scale)
    return None if x is None else np.round(x[:r])


def _highs_milp(cost: np.ndarray, integer: np.ndarray, col_lo: np.ndarray, col_hi: np.ndarray, a: sp.csc_matrix,
                row_lo: np.ndarray, row_hi: np.ndarray, cutoff: float = np.inf) -> np.ndarray | None:
    """A feasible (at the node limit) or optimal point of the MILP by HiGHS through ``highspy``, or None; ``cutoff``
    (in the units of ``cost``) bounds the objective from above when finite.
    """
    lp = highspy.HighsLp()
    lp.num_col_, lp.num_row_ = cost.size, a.shape[0]
    lp.col_cost_, lp.col_lower_, lp.col_upper_ = cost, col_lo, col_hi
    lp.row_lower_, lp.row_upper_ = row_lo, row_hi
    lp.a_matrix_.format_ = highspy.MatrixFormat.kColwise
    lp.a_matrix_.num_col_, lp.a_matrix_.num_row_ = cost.size, a.shape[0]
    lp.a_matrix_.start_, lp.a_matrix_.index_, lp.a_matrix_.value_ = a.indptr, a.indices, a.data
    lp.integrality_ = [highspy.HighsVarType.kInteger if i else highspy.HighsVarType.kContinuous for i in integer]
    h = highspy.Highs()
    for name, value in MILP_OPTIONS.items():
        h.setOptionValue(name, value)
    if np.isfinite(cutoff):
        h.setOptionValue("objective_bound", float(cutoff))
    h.passModel(lp)
    if h.run() == highspy.HighsStatus.kError:
        # HiGHS's one scheduler per process was started with another thread count (an earlier Highs object of this
        # process): it refuses to run. Restart the scheduler with ours.
        highspy.Highs.resetGlobalScheduler(True)
        h.run()
    if (h.getModelStatus() == highspy.HighsModelStatus.kInfeasible
            or h.getInfo().primal_solution_status != highspy.SolutionStatus.kSolutionStatusFeasible):
        return None
    x = np.asarray(h.getSolution().col_value, float)
    return x if x.shape == cost.shape and np.all(np.isfinite(x)) else None


def solve_milp_reference(inputs: CvvcInputs) -> MilpReference:
    """Exact optimum of eq. (9)-(15) with integer taps and hard limits, for tests and benchmarks.

    Same scaled constraints as the relaxation, no proximal term, ``scipy.optimize.milp`` (HiGHS).
    """
    qp = build_cvvc_qp(inputs, soft=False)
    res = _milp(qp, 2 * inputs.n_reg, {"mip_rel_gap": 1e-9})
    if res.status == 2:
        return MilpReference(
            status="infeasible", taps_new=inputs.taps.copy(), q_new_kvar=inputs.q0_kvar.copy(), cost=float("inf")
        )
    if res.x is None or res.status != 0:
        return MilpReference(
            status="failed", taps_new=inputs.taps.copy(), q_new_kvar=inputs.q0_kvar.copy(), cost=float("inf")
        )
    d = np.round(qp.d_tap(res.x))
    q = qp.q_kvar(res.x)
    return MilpReference(
        status="optimal", taps_new=(inputs.taps + d.astype(int)).astype(int), q_new_kvar=q, cost=inputs.cost(d, q)
    )
