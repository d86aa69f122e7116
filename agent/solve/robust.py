"""Whether the hard limits hold within the Q sensitivities' error (beyond the paper; ``dv_dq_rel_error``).

Estimated Q sensitivities of nearby nodes differ by less than their error (epri-ckt24: a high node at 3.1, 3.9,
4.3 and a low one at 3.1, 3.7, 3.7 uV/V per kvar of the three plants, each known to about 30 %). When the band
between a high and a low node is too narrow, the hard form (eq. 9-15) closes it by pulling the plants against each
other on those differences: +110 / -3,150 kvar for 0.0015 pu, a decision no real feeder would reward. So a hard
relaxation that uses Q is kept only if some action meets the hard limits for every sensitivity within the error
(the robust counterpart of eq. 13 under box uncertainty: ``v0 + S dq + s_t dT +- err |S| |q|`` within the limits,
``|q|`` the new set point's magnitude as in the soft form's error term); otherwise the soft form with the error
term decides. The check is one feasibility LP (HiGHS), run only when the relaxation's own action fails it.
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import linprog

from agent.cvvc_qp import CvvcInputs

__all__ = ["robust_shortfall_pu", "robustly_feasible"]

_PCT_PER_PU = 100.0


def robust_shortfall_pu(inputs: CvvcInputs, d_tap: np.ndarray, q_kvar: np.ndarray, hard: np.ndarray) -> float:
    """Largest overshoot [pu] of the ``hard`` nodes' limits by this action when each Q sensitivity is off by its
    relative error in the worst direction (0 when the action holds them robustly).
    """
    if not hard.any():
        return 0.0
    v = inputs.predict_v_pu(d_tap, q_kvar)[hard]
    spread = inputs.dv_dq_rel_error * np.abs(inputs.dv_dq_pu_per_kvar[hard]) @ np.abs(q_kvar)
    v_min = np.broadcast_to(inputs.v_min_pu, (inputs.n_nodes,))[hard]
    v_max = np.broadcast_to(inputs.v_max_pu, (inputs.n_nodes,))[hard]
    return float(max(np.max(v + spread - v_max, initial=0.0), np.max(v_min - (v - spread), initial=0.0)))


def robustly_feasible(inputs: CvvcInputs, hard: np.ndarray) -> bool:
    """Whether some action (taps continuous, as in the relaxation) keeps every ``hard`` node within its limits
    for every Q sensitivity within ``inputs.dv_dq_rel_error`` of its estimate. True when HiGHS cannot tell.
    """
    idx = np.flatnonzero(hard)
    if idx.size == 0:
        return True
    k, r = inputs.n_pv, inputs.n_reg
    rating = inputs.q_rating_kvar
    s = _PCT_PER_PU * inputs.dv_dq_pu_per_kvar[idx] * rating  # (n, K) % per rating
    e = inputs.dv_dq_rel_error * np.abs(s)
    s_t = _PCT_PER_PU * inputs.dv_dtap_pu[idx]
    v_base = _PCT_PER_PU * inputs.v0_pu[idx] - s @ (inputs.q0_kvar / rating)
    v_lo = _PCT_PER_PU * np.broadcast_to(inputs.v_min_pu, (inputs.n_nodes,))[idx] - v_base
    v_hi = _PCT_PER_PU * np.broadcast_to(inputs.v_max_pu, (inputs.n_nodes,))[idx] - v_base
    # x = [dT+ (R), dT- (R), Q+ (K), Q- (K)] >= 0, Q in units of each plant's rating.
    upper_rows = np.hstack([s_t, -s_t, s + e, -s + e])  # v + err |S||q| <= v_max
    lower_rows = np.hstack([-s_t, s_t, -(s - e), s + e])  # -(v - err |S||q|) <= -v_min
    max_t = inputs.max_taps_per_interval.astype(float)
    room_up = np.maximum(inputs.tap_max - inputs.taps, 0).astype(float)
    room_down = np.maximum(inputs.taps - inputs.tap_min, 0).astype(float)
    q_min, q_max = inputs.q_min_kvar / rating, inputs.q_max_kvar / rating
    q_lo = np.concatenate([np.maximum(q_min, 0.0), np.maximum(-q_max, 0.0)])  # as the QP's variable bounds
    q_hi = np.concatenate([np.maximum(q_max, 0.0), np.maximum(-q_min, 0.0)])
    tap_hi = np.concatenate([np.minimum(max_t, room_up), np.minimum(max_t, room_down)])
    bounds = [(0.0, u) for u in tap_hi] + list(zip(q_lo, q_hi, strict=True))
    lp = linprog(np.zeros(2 * r + 2 * k), A_ub=np.vstack([upper_rows, lower_rows]),
                 b_ub=np.concatenate([v_hi, -v_lo]), bounds=bounds, method="highs")
    return bool(lp.status != 2)  # 2: infeasible; anything else (solved, limits hit) gives the hard form its chance
