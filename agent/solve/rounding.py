"""Rounding of the relaxed taps and the Q re-solve with each candidate's taps fixed (a small branch and bound).

Every floor/ceil combination of the (at most ``MAX_ENUMERATED_FRACTIONAL``) most fractional relaxed tap changes
is a candidate, the other taps rounded to nearest; Q is re-solved with each candidate's taps fixed (same form),
best-first by a dual lower bound, by the exact dual active-set method (OSQP if it fails); the cheapest candidate
meeting the hard limits wins. If none does, a MILP looks for integer taps further away that meet them
(``agent.solve.milp``); if there are none, the nearest rounding is re-solved in the soft form.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from typing import Literal

import numpy as np

from agent.cvvc_qp import PROX_WEIGHT, CvvcInputs, CvvcQp, build_cvvc_qp
from agent.solve.milp import milp_tap_changes
from agent.solve.polish import active_set_polish
from agent.solve.relaxation import osqp_run, setup_osqp, solve_qp
from agent.solve.rows import outside_violations, remap, row_ranges, solve_rows
from agent.solve.settings import (
    FRACTIONAL_TOL_STEPS,
    INTEGRAL_TOL_STEPS,
    MAX_ENUMERATED_FRACTIONAL,
    MAX_ITER,
    MAX_ITER_RESOLVE,
    ROUNDING_GAP_REL,
    V_TOL_PU,
)
from agent.solve.solution import Run, violation_pu

__all__ = ["Rounded", "dual_bound", "round_taps", "rounding_candidates"]


@dataclass(frozen=True)
class Rounded:
    """Integer taps and Q of one interval after rounding and re-solve.

    Attributes
    ----------
    status : ``optimal`` (hard limits met) or ``soft`` (eq. 17 form used).
    reason : why ``soft``; the relaxation's reason carried on.
    d_tap : (R,) integer tap changes [steps].
    q_new_kvar : (K,) Q set points before the final rounding to ``Q_DECIMALS`` [kvar].
    iterations : OSQP iterations of the re-solves.
    tried : rounding candidates re-solved.
    """

    status: Literal["optimal", "soft"]
    reason: str
    d_tap: np.ndarray
    q_new_kvar: np.ndarray
    iterations: int
    tried: int


def round_taps(inputs: CvvcInputs, qp: CvvcQp, run: Run, reason: str) -> Rounded:
    """Round the relaxation ``run`` of ``qp`` to integer taps and re-solve Q (``reason``: the relaxation's)."""
    d_rel = qp.d_tap(run.x)
    q_rel = qp.q_kvar(run.x)
    form: Literal["hard", "soft"] = "soft" if qp.soft else "hard"
    iterations = 0

    # Rounding, then Q re-solved with the taps fixed, in the relaxation's form: a small best-first branch
    # and bound over the candidates. Each candidate's score (eq. 9 cost plus the proximal terms, which the
    # relaxation also minimises) has two cheap lower bounds: the relaxed objective (for all of them) and
    # the Lagrangian dual function at the relaxation's multipliers (per candidate). Candidates are tried in
    # order of their bound; the search stops once the best score is within ROUNDING_GAP_REL of the relaxed
    # objective or below the next candidate's bound.
    candidates = rounding_candidates(d_rel)
    bound = qp.objective(run.x)
    hard_nodes = ~qp.soft_nodes
    if np.max(np.abs(candidates[0] - d_rel), initial=0.0) <= INTEGRAL_TOL_STEPS:
        # The relaxed taps are integral (the usual case: no tap move): the relaxation is the answer.
        plan = [(bound, 0, candidates[0], 0.0)]
    else:
        fixed = build_cvvc_qp(inputs, soft=qp.soft_nodes, fixed_d_tap=candidates[0], nodes=qp.nodes)
        x_q0, y_q0 = remap(qp, run.x, run.y, fixed)
        plan = []
        for index, d_int in enumerate(candidates):
            tap_prox = 0.5 * PROX_WEIGHT * fixed.cost_scale * float(d_int @ d_int)
            tap_cost = float(inputs.cost_per_tap @ np.abs(d_int)) + tap_prox
            lo, hi = fixed.bounds_with_d_tap(d_int)
            lower_bound = tap_cost + dual_bound(fixed, lo, hi, y_q0)
            plan.append((lower_bound, index, d_int, tap_cost))
        plan.sort(key=lambda item: (item[0], item[1]))
        ranges = row_ranges(fixed)
    best = None  # (score, d_int, q_new_kvar)
    solver = None
    tried = 0
    for lower_bound, _, d_int, tap_cost in plan:
        if best is not None and (best[0] <= lower_bound or best[0] <= bound + ROUNDING_GAP_REL * abs(bound)):
            break  # no remaining candidate can beat the best by more than the tolerance
        if np.max(np.abs(d_int - d_rel), initial=0.0) <= INTEGRAL_TOL_STEPS:
            q_new = np.clip(q_rel, inputs.q_min_kvar, inputs.q_max_kvar)  # relaxed optimum is integral
            score = qp.objective(run.x)
        else:
            lo, hi = fixed.bounds_with_d_tap(d_int)
            rows = fixed.voltage_rows
            out_of_reach = (ranges[1] < lo[rows] - 1e-9) | (ranges[0] > hi[rows] + 1e-9)
            if np.any(out_of_reach & ~fixed.soft_rows):
                continue  # some hard node cannot meet its limits with these taps, whatever Q does
            res = active_set_polish(fixed, lo, hi, None, None, "active set")  # measured: the box start is better here
            if res is None:
                if solver is None:
                    solver = setup_osqp(fixed)
                    if solver is None:
                        break
                solver.update(l=lo, u=hi)
                res = osqp_run(solver, fixed, lo, hi, x_q0, y_q0, MAX_ITER if best is None else MAX_ITER_RESOLVE)
            iterations += res.iterations
            tried += 1
            if not res.ok:
                continue
            outside = outside_violations(inputs, fixed, d_int, fixed.q_kvar(res.x))
            if outside.size:
                # Nodes without a row are violated: add their rows and re-solve this candidate; the larger
                # problem serves the following candidates too.
                res, bigger = solve_rows(
                    inputs, qp.soft_nodes, d_int, np.union1d(fixed.nodes, outside), (fixed, res.x, res.y)
                )
                iterations += res.iterations
                fixed, solver = bigger, None
                ranges = row_ranges(fixed)
                x_q0, y_q0 = remap(qp, run.x, run.y, fixed)
                if not res.ok:
                    continue
            q_new = np.clip(fixed.q_kvar(res.x), inputs.q_min_kvar, inputs.q_max_kvar)
            score = fixed.objective(res.x) + tap_cost
        v_new = inputs.predict_v_pu(d_int, q_new)
        if np.max(violation_pu(inputs, v_new)[hard_nodes], initial=0.0) > V_TOL_PU:
            continue
        if best is None or score < best[0]:
            best = (score, d_int, q_new)

    status: Literal["optimal", "soft"] = "optimal" if form == "hard" else "soft"
    if best is None and hard_nodes.any():
        # No re-solve succeeded within its budget: take the first candidate that meets the hard limits with
        # the relaxed Q unchanged (feasible, not re-optimised).
        q_keep = np.clip(q_rel, inputs.q_min_kvar, inputs.q_max_kvar)
        for d_int in candidates:
            violation = violation_pu(inputs, inputs.predict_v_pu(d_int, q_keep))
            if np.max(violation[hard_nodes], initial=0.0) <= V_TOL_PU:
                best = (0.0, d_int, q_keep)
                break
    if best is None and hard_nodes.any():
        # No integer point within one tap of the relaxation meets the hard limits; one further away may (the
        # feasible set of a regulated feeder's taps is a thin slab: IEEE 8500 went soft here in 160 of 864
        # winter decisions): integer taps from the MILP, then Q re-solved with them fixed, in the same form.
        best, n = _milp_fallback(inputs, qp, hard_nodes)
        tried += n
    if best is None and hard_nodes.any():
        # No integer taps meet the hard limits: soft Q re-solve at the nearest rounding.
        reason = "no rounding of the relaxed taps meets the hard limits: Q re-solved in soft form (eq. 17)"
        status = "soft"
        soft_fixed = build_cvvc_qp(inputs, soft=True, fixed_d_tap=candidates[0])
        res = active_set_polish(soft_fixed, soft_fixed.lower, soft_fixed.upper, None, None, "active set") or solve_qp(
            soft_fixed, None, None
        )
        iterations += res.iterations
        tried += 1
        if res.ok:
            best = (0.0, candidates[0], np.clip(soft_fixed.q_kvar(res.x), inputs.q_min_kvar, inputs.q_max_kvar))
    if best is None:
        # Every Q re-solve failed within its budget: nearest rounding with the relaxed Q, as the soft form.
        reason = (reason + "; " if reason else "") + "Q re-solve not solved: relaxed Q kept at the nearest taps"
        status = "soft"
        best = (0.0, candidates[0], np.clip(q_rel, inputs.q_min_kvar, inputs.q_max_kvar))
    _, d_int, q_new = best
    return Rounded(status=status, reason=reason, d_tap=d_int, q_new_kvar=q_new, iterations=iterations, tried=tried)


def _milp_fallback(
    inputs: CvvcInputs, qp: CvvcQp, hard_nodes: np.ndarray
) -> tuple[tuple[float, np.ndarray, np.ndarray] | None, int]:
    """``(best, tried)``: the MILP's integer taps with Q re-solved (``best`` None when they fail the hard limits)."""
    d_int = milp_tap_changes(inputs, qp.soft_nodes, qp.nodes)
    if d_int is None:
        return None, 0
    fixed = build_cvvc_qp(inputs, soft=qp.soft_nodes, fixed_d_tap=d_int, nodes=qp.nodes)
    res = active_set_polish(fixed, fixed.lower, fixed.upper, None, None, "active set") or solve_qp(fixed, None, None)
    if not res.ok:
        return None, 1
    q_new = np.clip(fixed.q_kvar(res.x), inputs.q_min_kvar, inputs.q_max_kvar)
    if np.max(violation_pu(inputs, inputs.predict_v_pu(d_int, q_new))[hard_nodes], initial=0.0) > V_TOL_PU:
        return None, 1
    return (0.0, d_int, q_new), 1


def rounding_candidates(d_rel: np.ndarray) -> list[np.ndarray]:
    """Integer tap-change candidates around the relaxed ``d_rel``, nearest rounding first.

    Every floor/ceil combination of the ``MAX_ENUMERATED_FRACTIONAL`` most fractional taps (closest to a
    half step; ties by regulator index); any other fractional tap is rounded to nearest.
    """
    nearest = np.round(d_rel)
    dist = np.abs(d_rel - nearest)
    frac = np.flatnonzero(dist > FRACTIONAL_TOL_STEPS)
    frac = frac[np.argsort(-dist[frac], kind="stable")][:MAX_ENUMERATED_FRACTIONAL]
    out = []
    for bits in itertools.product((0, 1), repeat=frac.size):  # (0, ..., 0) = nearest rounding
        cand = nearest.copy()
        for i, flip in zip(frac, bits, strict=True):
            if flip:
                cand[i] = np.floor(d_rel[i]) if nearest[i] > d_rel[i] else np.ceil(d_rel[i])
        out.append(cand)
    return out


def dual_bound(qp: CvvcQp, lo: np.ndarray, hi: np.ndarray, y: np.ndarray | None) -> float:
    """Lagrangian dual function of ``qp`` (bounds ``lo``, ``hi``) at multipliers ``y`` [cost units].

    ``g(y) = min_x x'Px/2 + c'x + y'Ax - max_{lo<=z<=hi} y'z``, in closed form since ``P`` is a positive
    diagonal. By weak duality it is a lower bound on the optimum for any ``y``; ``-inf`` without ``y``.
    """
    if y is None or y.shape != lo.shape:
        return -np.inf
    grad = qp.c + (qp.a_dense.T @ y if qp.a_dense is not None else qp.A.T @ y)
    support = np.where(y > 0.0, y * hi, 0.0) + np.where(y < 0.0, y * lo, 0.0)
    return float(qp.cost_scale * (-0.5 * np.sum(grad**2 / qp.p_diag) - np.sum(support)))
