"""Case A of the paper (Table I): the same CVVC problem with full visibility.

The bridge's oracle gives the true voltage of every node and perturbation sensitivities of every node to
each plant's Q and each regulator's tap, at the present state; the problem then constrains every node, not
only the critical ones, and taps are commanded directly. The agent's PV variability margin (beyond the paper,
docs/method.md) applies here too, from the oracle's dV/dP of every node, so that case A and case D plan
against the same cloud movements within an interval. Device order is the device map's, which is also
the model's (training builds the model from the same map).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from agent.controller import CvvcController, Decision, MeasurementSnapshot
from agent.cvvc_qp import CvvcInputs
from agent.errors import AgentInputError
from agent.solve import solve_cvvc
from schemas import messages as m

__all__ = ["decide_full_visibility", "full_visibility_inputs"]


def full_visibility_inputs(controller: CvvcController, snap: MeasurementSnapshot, reply: m.OracleReply) -> CvvcInputs:
    """CVVC inputs from an oracle reply: all nodes, true voltages, perturbation sensitivities."""
    model = controller.model
    n_pv, n_reg = len(model.pv), len(model.regulators)
    v0 = np.asarray(reply.v_pu, float)
    dv_dq = np.asarray(reply.dv_dq_pu_per_kvar, float).reshape(v0.size, -1)
    dv_dtap = np.asarray(reply.dv_dtap_pu, float).reshape(v0.size, -1)
    if dv_dq.shape[1] != n_pv or dv_dtap.shape[1] != n_reg:
        raise AgentInputError(f"oracle reply has {dv_dq.shape[1]} plants and {dv_dtap.shape[1]} regulators; "
                              f"the model has {n_pv} and {n_reg}")
    # Nodes that are not energised (0 pu) cannot be constrained.
    live = v0 > 0.5
    regs = model.regulators
    p = np.asarray(snap.pv_p_kw, float)
    headroom = np.sqrt(np.maximum(np.asarray(snap.pv_kva_available, float) ** 2 - p**2, 0.0))
    pv_ok = np.asarray(snap.pv_valid, bool)
    q0 = np.asarray(snap.pv_q_kvar, float)
    taps = np.asarray(reply.taps, int) if len(reply.taps) == n_reg else np.asarray(snap.reg_tap, int)
    lo, hi = model.optimization_limits_pu
    # an oracle without dV/dP (an older bridge): no margin
    dv_dp = np.asarray(reply.dv_dp_pu_per_kw or np.zeros((v0.size, n_pv)), float).reshape(v0.size, -1)
    if dv_dp.shape[1] != n_pv:
        raise AgentInputError(f"oracle reply has dV/dP for {dv_dp.shape[1]} plants; the model has {n_pv}")
    rise, fall = controller.pv_margins_pu(dv_dp[live], p)
    return CvvcInputs(
        v0_pu=v0[live], dv_dq_pu_per_kvar=dv_dq[live], dv_dtap_pu=dv_dtap[live], q0_kvar=q0,
        q_min_kvar=np.where(pv_ok, -headroom, q0), q_max_kvar=np.where(pv_ok, headroom, q0),
        q_rating_kvar=np.maximum([pv.kva for pv in model.pv], 1.0), taps=taps,
        tap_min=np.array([r.tap_min for r in regs]), tap_max=np.array([r.tap_max for r in regs]),
        max_taps_per_interval=np.where(np.asarray(snap.reg_valid, bool), [r.max_taps_per_interval for r in regs], 0),
        cost_per_tap=np.array([r.cost_per_tap for r in regs], float),
        cost_per_kvar=np.array([pv.cost_per_kvar for pv in model.pv], float), v_min_pu=lo + fall,
        v_max_pu=hi - rise)


def decide_full_visibility(controller: CvvcController, snap: MeasurementSnapshot, estimated: Decision,
                           reply: m.OracleReply | None) -> Decision:
    """Replace the estimator-based decision by the full-visibility one (taps commanded directly).

    Without an oracle reply, or when the estimator-based decision already holds (no head frame), it holds.
    """
    if estimated.status == "hold":
        return estimated
    if reply is None:
        return dataclasses.replace(estimated, status="hold", reason="case A: no oracle reply from the bridge",
                                   pv_q_kvar=None, reg_tap=None, pv_command=np.zeros_like(estimated.pv_command),
                                   reg_command=np.zeros_like(estimated.reg_command), v_pred_pu=None)
    try:
        inputs = full_visibility_inputs(controller, snap, reply)
    except AgentInputError as e:
        return dataclasses.replace(estimated, status="hold", reason=f"case A: {e}", pv_q_kvar=None, reg_tap=None,
                                   pv_command=np.zeros_like(estimated.pv_command),
                                   reg_command=np.zeros_like(estimated.reg_command), v_pred_pu=None)
    sol = solve_cvvc(inputs)
    if sol.status == "hold":
        return dataclasses.replace(estimated, status="hold", reason=f"case A: {sol.reason}", pv_q_kvar=None,
                                   reg_tap=None, pv_command=np.zeros_like(estimated.pv_command),
                                   reg_command=np.zeros_like(estimated.reg_command), v_pred_pu=None)
    return dataclasses.replace(
        estimated, status=sol.status, reason=sol.reason, pv_q_kvar=sol.q_new_kvar.copy(), reg_tap=sol.taps_new.copy(),
        reg_setpoint_v120=None, reg_band_v120=None, v_pu=None, v_pred_pu=None, dv_dq_pu_per_kvar=None,
        iterations=sol.iterations, objective=sol.cost, solver_status=sol.status)
