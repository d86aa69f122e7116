"""Solve the CVVC problem: relaxation, tap rounding, Q re-solve, soft fallback (paper eq. 9-17).

The one entry point of the solve package. ``solve_cvvc`` never raises on numeric trouble and never returns
NaN: a failed relaxation is a ``CvvcSolution`` with ``status="hold"`` (keep taps and Q as they are) and a
reason. Stages, paper section III and DESIGN.md section 4 (details in docs/optimizer.md):

1. presolve (``rows``): nodes that no action can bring within the limits get violation variables (eq. 16-17),
   the others keep hard limits; if "no action" meets every limit it is the optimum;
2. relaxation (continuous taps) by OSQP (``relaxation``, polished by ``polish``), rows generated for large
   problems (``rows``); if infeasible or unsolved, the soft form at every node;
3. rounding and Q re-solve (``rounding``).

Same inputs and warm start -> bit-identical solution (timings aside).
"""

from __future__ import annotations

import dataclasses
import time
from typing import Literal

import numpy as np

from agent.cvvc_qp import CvvcInputs, CvvcQp, build_cvvc_qp
from agent.solve.robust import robust_shortfall_pu, robustly_feasible
from agent.solve.rounding import round_taps
from agent.solve.rows import solve_rows, start_nodes, unreachable_rows, zero_is_feasible
from agent.solve.settings import Q_DECIMALS, V_TOL_PU
from agent.solve.solution import (
    CvvcSolution,
    Run,
    StageSeconds,
    WarmStart,
    hold_solution,
    pinned_solution,
    violation_pu,
)

__all__ = ["solve_cvvc"]


def _source(warm: WarmStart | None, inputs: CvvcInputs) -> tuple[CvvcQp, np.ndarray, np.ndarray] | None:
    """The warm start's problem and iterate for ``inputs``, or ``None`` (cold start)."""
    return None if warm is None else warm.source_for(inputs)


def solve_cvvc(inputs: CvvcInputs, *, warm_start: WarmStart | CvvcSolution | None = None) -> CvvcSolution:
    """Solve one CVVC interval: relaxation, rounding, Q re-solve, soft fallback (paper eq. 9-17).

    Parameters
    ----------
    inputs : the problem (validated on construction: finite, consistent shapes).
    warm_start : where to start: the previous interval's ``WarmStart`` (or its solution), or ``None`` (cold).

    Returns
    -------
    A ``CvvcSolution``; ``status="hold"`` with a reason when the solver fails. Never raises on numeric
    trouble, never contains NaN.
    """
    t_start = time.perf_counter()
    if np.all(inputs.q_min_kvar == inputs.q_max_kvar) and np.all(inputs.max_taps_per_interval == 0):
        t = time.perf_counter() - t_start
        return pinned_solution(inputs, StageSeconds(t, 0.0, 0.0, t))
    warm = warm_start.warm_start if isinstance(warm_start, CvvcSolution) else warm_start
    iterations = 0
    hard = build_cvvc_qp(inputs, soft=False)
    t_built = time.perf_counter()

    # Relaxation: hard limits (eq. 9-15); violation variables (eq. 16-17) at the nodes no action can bring
    # within the limits (e.g. a feeder head above 1.04 pu), hard limits at the others; if that is still
    # infeasible or unsolved, the soft form at every node.
    qp, reason = hard, ""
    unreachable = unreachable_rows(hard)
    soft_mask = np.zeros(inputs.n_nodes, bool)
    soft_mask[unreachable] = True
    start = start_nodes(inputs, soft_mask, warm)
    if unreachable.size:
        names = ", ".join(str(i) for i in unreachable[:5]) + (", ..." if unreachable.size > 5 else "")
        reason = (
            f"{unreachable.size} critical node(s) cannot reach the limits with the actions available (index "
            f"{names}): their violation is minimised (eq. 17), hard limits elsewhere"
        )
        run, qp = solve_rows(inputs, soft_mask, None, start, _source(warm, inputs))
        iterations += run.iterations
        if not run.ok:
            reason += "; the remaining hard limits are infeasible too: soft form at every node"
    elif zero_is_feasible(hard):
        # Every cost is >= 0 and every variable >= 0, so x = 0 minimises the objective: nothing to solve.
        run = Run(True, False, "presolve: no action needed", np.zeros(hard.layout.n), np.zeros(hard.n_rows), 0)
    else:
        run, qp = solve_rows(inputs, soft_mask, None, start, _source(warm, inputs), hard)
        iterations += run.iterations
        if not run.ok:
            reason = (
                "hard voltage limits infeasible: soft form (eq. 17) used"
                if run.infeasible
                else f"hard relaxation not solved ({run.status}): soft form (eq. 17) used"
            )
    if run.ok and inputs.dv_dq_rel_error > 0.0 and not np.all(qp.soft_nodes):
        hard_nodes = ~qp.soft_nodes
        if (robust_shortfall_pu(inputs, qp.d_tap(run.x), qp.q_kvar(run.x), hard_nodes) > V_TOL_PU
                and not robustly_feasible(inputs, hard_nodes)):
            run = dataclasses.replace(run, ok=False)
            reason = (reason + "; " if reason else "") + (
                "hard voltage limits met only on the Q sensitivities' exact values (not within "
                f"{inputs.dv_dq_rel_error:.0%} of them): soft form (eq. 17) used")
    if not run.ok:
        all_soft = np.ones(inputs.n_nodes, bool)
        run, qp = solve_rows(inputs, all_soft, None, start, _source(warm, inputs))
        iterations += run.iterations
    form: Literal["hard", "soft"] = "soft" if qp.soft else "hard"
    t_relaxed = time.perf_counter()
    if not run.ok:
        return hold_solution(
            inputs,
            f"soft relaxation not solved ({run.status}); holding taps and Q",
            iterations,
            StageSeconds(t_built - t_start, t_relaxed - t_built, 0.0, t_relaxed - t_start),
        )
    d_rel = qp.d_tap(run.x)
    q_rel = qp.q_kvar(run.x)
    rounded = round_taps(inputs, qp, run, reason)
    iterations += rounded.iterations
    status, reason, d_int, q_new, tried = (
        rounded.status, rounded.reason, rounded.d_tap, rounded.q_new_kvar, rounded.tried
    )
    t_rounded = time.perf_counter()
    seconds = StageSeconds(t_built - t_start, t_relaxed - t_built, t_rounded - t_relaxed, t_rounded - t_start,
                           rounded.milp_s)
    # Commands to 1 var resolution (ADMM leaves 1e-7 kvar dust); moves voltages by < 1e-7 pu.
    q_new = np.clip(np.round(q_new, Q_DECIMALS), inputs.q_min_kvar, inputs.q_max_kvar) + 0.0
    v_pred = inputs.predict_v_pu(d_int, q_new)
    return CvvcSolution(
        status=status,
        reason=reason,
        taps_new=(inputs.taps + d_int.astype(int)).astype(int),
        q_new_kvar=q_new,
        v_pred_pu=v_pred,
        cost=inputs.cost(d_int, q_new),
        max_violation_pu=float(np.max(violation_pu(inputs, v_pred), initial=0.0)),
        iterations=iterations,
        relaxed_d_tap=d_rel,
        relaxed_q_kvar=q_rel,
        relaxed_form=form,
        relaxed_x=run.x,
        relaxed_y=run.y,
        relaxed_problem=qp,
        candidates_tried=tried,
        seconds=seconds,
        lattice_tried=rounded.lattice_tried,
        milp_solves=rounded.milp_solves,
    )
