"""Whether the hard limits hold within the Q sensitivities' error (beyond the paper; ``dv_dq_rel_error``).

Estimated Q sensitivities of nearby nodes differ by less than their error (epri-ckt24: a high node at 3.1, 3.9,
4.3 and a low one at 3.1, 3.7, 3.7 uV/V per kvar of the three plants, each known to about 30 %). When the band
between a high and a low node is too narrow, the hard form (eq. 9-15) closes it by pulling the plants against each
other on those differences: +110 / -3,150 kvar for 0.0015 pu, a decision no real feeder would reward. So a hard
relaxation that uses Q is kept only if some action meets the hard limits for every sensitivity within the error
(the robust counterpart of eq. 13 under box uncertainty: ``v0 + S dq + s_t dT +- err |S| |dq|`` within the limits);
otherwise the soft form with the error term decides.

The error acts on the change ``dq = q - q0``: the estimate ``v0`` is at the plants' present set points, and eq. (13)
predicts from there. Taken on the set point's magnitude ``|q|`` instead (as the soft form's error term is, which
keeps the plants from drifting apart decision by decision), a plant holding a large Q failed the check at every
decision that kept it: IEEE 8500's first 3 fall days went to the soft form in 42 decisions, epri-ckt5's summer in 52
(case D at ``69b537c``; docs/method.md, "The soft form with estimated sensitivities").

The check is one feasibility problem, run only when the relaxation's own action fails it: the least-norm point of
the robust rows by the dense dual active-set method (DAQP, ``agent.solve.active_set``), which proves infeasibility
exactly as an LP would, in tens of microseconds instead of the milliseconds of an LP set-up.
"""

from __future__ import annotations

import numpy as np

from agent.cvvc_qp import CvvcInputs, build_cvvc_qp
from agent.solve.active_set import solve_dense_qp

__all__ = ["robust_shortfall_pu", "robustly_feasible"]


def robust_shortfall_pu(inputs: CvvcInputs, d_tap: np.ndarray, q_kvar: np.ndarray, hard: np.ndarray) -> float:
    """Largest overshoot [pu] of the ``hard`` nodes' limits by this action when each Q sensitivity is off by its
    relative error in the worst direction over the change from the present set points (0 when the action holds them
    robustly).
    """
    if not hard.any():
        return 0.0
    v = inputs.predict_v_pu(d_tap, q_kvar)[hard]
    spread = inputs.dv_dq_rel_error * np.abs(inputs.dv_dq_pu_per_kvar[hard]) @ np.abs(q_kvar - inputs.q0_kvar)
    v_min = np.broadcast_to(inputs.v_min_pu, (inputs.n_nodes,))[hard]
    v_max = np.broadcast_to(inputs.v_max_pu, (inputs.n_nodes,))[hard]
    return float(max(np.max(v + spread - v_max, initial=0.0), np.max(v_min - (v - spread), initial=0.0)))


def robustly_feasible(inputs: CvvcInputs, hard: np.ndarray) -> bool:
    """Whether some action (taps continuous, as in the relaxation) keeps every ``hard`` node within its limits
    for every Q sensitivity within ``inputs.dv_dq_rel_error`` of its estimate. True when the solver cannot tell.

    The hard QP's own scaled rows and variable box (``build_cvvc_qp`` over the ``hard`` nodes, whose Q variables are
    the new set point's parts ``Q+ - Q-``), with one more variable per plant, ``t >= |Q+ - Q- - Q0|``, the change's
    size; each row split in two: its upper limit with ``+ err |S| t``, its lower limit with ``- err |S| t``.
    """
    idx = np.flatnonzero(hard)
    if idx.size == 0:
        return True
    key = ("robustly feasible", idx.tobytes())  # a problem priced anew (the tap offer) asks again: one answer
    memo = inputs.feasible_set_memo
    if key not in memo:
        memo[key] = _robust_action_exists(inputs, idx)
    verdict: bool = memo[key]
    return verdict


def _robust_action_exists(inputs: CvvcInputs, idx: np.ndarray) -> bool:
    """``robustly_feasible`` over the nodes ``idx``, solved."""
    qp = build_cvvc_qp(inputs, soft=False, nodes=idx)
    n, k, lay = idx.size, inputs.n_pv, qp.layout
    rows = qp.a_dense[:n] if qp.a_dense is not None else qp.A.toarray()[:n]  # voltage rows [%]: taps up/down, Q+, Q-
    spread = inputs.dv_dq_rel_error * np.abs(rows[:, lay.q_inj])  # (n, K) err |S| [% per rating]
    # variables: the hard QP's, then t (K,) [rating]; rows: the voltage rows' upper limits with + err |S| t, their
    # lower limits with - err |S| t, the hard QP's variable box, t - (Q+ - Q-) >= -Q0 and t + (Q+ - Q-) >= Q0
    # (t >= |Q+ - Q- - Q0|)
    a = np.zeros((2 * n + lay.n + 2 * k, lay.n + k))
    a[:n, : lay.n] = rows
    a[:n, lay.n :] = spread
    a[n : 2 * n, : lay.n] = rows
    a[n : 2 * n, lay.n :] = -spread
    a[2 * n + np.arange(lay.n), np.arange(lay.n)] = 1.0
    t_rows = 2 * n + lay.n + np.arange(2 * k)
    a[t_rows, lay.n + np.tile(np.arange(k), 2)] = 1.0
    plant = np.arange(k)
    a[t_rows[:k], lay.q_inj.start + plant] = -1.0
    a[t_rows[:k], lay.q_abs.start + plant] = 1.0
    a[t_rows[k:], lay.q_inj.start + plant] = 1.0
    a[t_rows[k:], lay.q_abs.start + plant] = -1.0
    q0 = inputs.q0_kvar / inputs.q_rating_kvar
    lo = np.concatenate([np.full(n, -np.inf), qp.lower[:n], qp.lower[n:], -q0, q0])
    hi = np.concatenate([qp.upper[:n], np.full(n, np.inf), qp.upper[n:], np.full(2 * k, np.inf)])
    out = solve_dense_qp(np.ones(lay.n + k), np.zeros(lay.n + k), a, lo, hi)  # the least-norm robust action, if any
    return out.status != "infeasible"  # failed (limits hit) gives the hard form its chance
