"""Solve the CVVC problem: OSQP relaxation, tap rounding, Q re-solve, soft fallback; MILP reference.

The one module that calls a solver (STYLE.md rule 11). ``solve_cvvc`` never raises on numeric trouble and
never returns NaN: a failed relaxation is a ``CvvcSolution`` with ``status="hold"`` (keep taps and Q as they
are) and a reason. Stages, paper section III and DESIGN.md section 4 (details in docs/optimizer.md):

1. presolve: nodes that no action can bring within the limits get violation variables (eq. 16-17), the
   others keep hard limits; if "no action" meets every limit it is the optimum;
2. relaxation (continuous taps) by OSQP; if infeasible or unsolved, the soft form at every node;
3. rounding: every floor/ceil combination of the (at most ``MAX_ENUMERATED_FRACTIONAL``) most fractional
   relaxed tap changes is a candidate, the other taps rounded to nearest;
4. Q re-solved with each candidate's taps fixed (same form), best-first by a dual lower bound, by the exact
   dual active-set method (``agent.active_set``; OSQP if it fails); the cheapest candidate meeting the hard
   limits wins. If none does, the nearest rounding is re-solved in the soft form.

OSQP runs in chunks, each followed by an exact polish: the dual active-set method started from the active
set the iterate suggests, accepted only after a KKT check (``_osqp_run``). A warm start from the previous
interval goes straight to that polish. Determinism: a fresh OSQP object per stage, fixed settings (iteration
limits, no wall-clock limit), warm start only from the ``warm_start`` argument. Same inputs -> bit-identical
solution (timings aside).
"""

from __future__ import annotations

import dataclasses
import itertools
import time
from collections.abc import Mapping
from dataclasses import dataclass
from types import MappingProxyType
from typing import Literal

import numpy as np
import osqp
import scipy.optimize
import scipy.sparse as sp

from agent.active_set import solve_dense_qp
from agent.cvvc_qp import PROX_WEIGHT, CvvcInputs, CvvcQp, build_cvvc_qp

__all__ = [
    "MAX_ENUMERATED_FRACTIONAL",
    "OSQP_SETTINGS",
    "CvvcSolution",
    "MilpReference",
    "StageSeconds",
    "solve_cvvc",
    "solve_milp_reference",
]

#: Fixed OSQP settings (units of the scaled problem: voltages in %, Q in fractions of rating, taps in steps).
#: Rho starts at 1 and adapts on a fixed iteration interval (never the time-based rule): ADMM's path depends
#: only on the data. OSQP's own polishing is replaced by ours after every chunk of ``max_iter`` iterations
#: (see ``_osqp_run``); no wall-clock limit.
#: ``eps_prim_inf`` is loose: proving a rounding candidate infeasible took up to 4000 iterations at 1e-6 and
#: about 10x fewer at 1e-3; a false "infeasible" could only cost optimality (a candidate skipped, or the
#: soft form), and none was seen on the benchmark problems.
OSQP_SETTINGS: Mapping[str, object] = MappingProxyType(
    {
        "verbose": False,
        "eps_abs": 1e-6,
        "eps_rel": 1e-6,
        "eps_prim_inf": 1e-3,
        "eps_dual_inf": 1e-6,
        "rho": 1.0,
        "adaptive_rho": 1,  # rho adapted every 50 iterations (iteration-based, hence deterministic)
        "adaptive_rho_interval": 50,
        "sigma": 1e-6,
        "alpha": 1.6,
        "max_iter": 25,  # first chunk; see FIRST_CHUNK_ITER
        "check_termination": 5,
        "polishing": False,
        "scaling": 10,
        "warm_starting": True,
    }
)
#: Problems too large for the dense active-set polish (soft form over many nodes): OSQP's own polishing,
#: tolerance 1e-4 in scaled units (1e-6 pu of voltage).
LARGE_OSQP_SETTINGS: Mapping[str, object] = MappingProxyType(
    {**OSQP_SETTINGS, "polishing": True, "eps_abs": 1e-4, "eps_rel": 1e-4}
)
#: Iteration budget of a rounding candidate's Q re-solve once a feasible candidate is known (before that,
#: ``MAX_ITER``); a candidate not solved within it is skipped: it could only have improved the cost.
MAX_ITER_RESOLVE = 400
#: ADMM iterations before the first polish attempt; each later chunk is twice as long.
FIRST_CHUNK_ITER = 25
#: Iteration budget of one solve (all chunks) [ADMM iterations].
MAX_ITER = 4000
#: Largest active set the polish solves (its cost grows with the cube); larger ones are left to ADMM.
POLISH_MAX_ACTIVE = 300
#: OSQP tolerance accepted after half the iteration budget (scaled units: 1e-6 pu of voltage).
LOOSE_EPS = 1e-4
#: Tolerance of the KKT optimality check in scaled units (% of voltage, fraction of rating, steps).
KKT_TOL = 1e-6
#: Up to this many fractional taps, every floor/ceil combination is tried (2**3 = 8 Q re-solves).
MAX_ENUMERATED_FRACTIONAL = 3
#: A relaxed tap change this close to an integer counts as integer [steps].
FRACTIONAL_TOL_STEPS = 1e-4
#: A relaxed tap change this close to an integer is taken as integral: its Q needs no re-solve [steps].
INTEGRAL_TOL_STEPS = 1e-6
#: Stop trying rounding candidates once one scores within this fraction of the relaxed objective.
ROUNDING_GAP_REL = 0.01
#: Row generation for large problems (every node of a big feeder): problems up to ROWGEN_MIN_NODES critical
#: nodes get every row at once; larger ones start with the ROWGEN_START nodes closest to a limit and add
#: up to ROWGEN_ADD violated nodes (beyond ROWGEN_TOL_PU) per round.
ROWGEN_MIN_NODES = 100
ROWGEN_START = 50
ROWGEN_ADD = 100
ROWGEN_TOL_PU = 1e-7
#: Q set points are rounded to this many decimals of a kvar.
Q_DECIMALS = 3
#: Voltage-limit tolerance when checking a solution against the linear model [pu].
V_TOL_PU = 1e-5

Status = Literal["optimal", "soft", "hold"]


@dataclass(frozen=True)
class StageSeconds:
    """Wall-clock time of each stage [s]. Diagnostics only: not part of the deterministic result."""

    build_s: float = 0.0
    relaxed_s: float = 0.0
    rounding_s: float = 0.0
    total_s: float = 0.0


@dataclass(frozen=True)
class CvvcSolution:
    """Result of ``solve_cvvc``.

    Attributes
    ----------
    status : ``optimal`` (hard limits met), ``soft`` (eq. 17 form used), ``hold`` (no action; see ``reason``).
    reason : why ``soft`` or ``hold``; empty when optimal.
    taps_new : (R,) int tap positions to apply [steps] (= present taps on hold).
    q_new_kvar : (K,) Q set points to apply [kvar] (= present set points on hold).
    v_pred_pu : (N,) voltages the linear model predicts after the actions [pu].
    cost : eq. (9) value of the actions [cost units].
    max_violation_pu : largest predicted excursion beyond the optimization limits [pu], >= 0.
    iterations : OSQP iterations over all stages.
    relaxed_d_tap : (R,) relaxed (continuous) tap changes [steps].
    relaxed_q_kvar : (K,) relaxed Q set points [kvar].
    relaxed_form : ``hard`` or ``soft``: which relaxation was solved (``none`` on early hold).
    relaxed_x, relaxed_y : primal and dual of the relaxation in scaled units (for warm starts).
    relaxed_problem : the relaxation as finally solved (its rows: see ``CvvcQp.nodes``), None on early hold.
    candidates_tried : rounding candidates re-solved.
    seconds : stage timings (not deterministic).
    """

    status: Status
    reason: str
    taps_new: np.ndarray
    q_new_kvar: np.ndarray
    v_pred_pu: np.ndarray
    cost: float
    max_violation_pu: float
    iterations: int
    relaxed_d_tap: np.ndarray
    relaxed_q_kvar: np.ndarray
    relaxed_form: Literal["hard", "soft", "none"]
    relaxed_x: np.ndarray
    relaxed_y: np.ndarray
    relaxed_problem: CvvcQp | None
    candidates_tried: int
    seconds: StageSeconds


@dataclass(frozen=True)
class MilpReference:
    """Exact optimum of the hard-limit problem with integer taps (``scipy.optimize.milp``, HiGHS)."""

    status: Literal["optimal", "infeasible", "failed"]
    taps_new: np.ndarray
    q_new_kvar: np.ndarray
    cost: float


@dataclass(frozen=True)
class _Run:
    ok: bool
    infeasible: bool
    status: str
    x: np.ndarray
    y: np.ndarray
    iterations: int


def _setup(qp: CvvcQp) -> osqp.OSQP | None:
    """An OSQP solver set up on ``qp`` with the fixed settings, or ``None`` if OSQP refuses the data."""
    solver = osqp.OSQP(algebra="builtin")  # naming it skips a slow probe of optional algebras
    settings = OSQP_SETTINGS if qp.a_dense is not None else LARGE_OSQP_SETTINGS
    try:
        solver.setup(qp.P, qp.c, qp.A, qp.lower, qp.upper, **settings)
    except (ValueError, osqp.OSQPException):
        return None
    return solver


def _osqp(qp: CvvcQp, x0: np.ndarray | None, y0: np.ndarray | None) -> _Run:
    """Solve ``qp``: first the warm start's active set (no ADMM at all), else set up OSQP and iterate."""
    warm = _warm_polish(qp, qp.lower, qp.upper, x0, y0)
    if warm is not None:
        return warm
    solver = _setup(qp)
    if solver is None:
        return _Run(False, False, "OSQP setup refused the problem", np.zeros(qp.layout.n), np.zeros(qp.n_rows), 0)
    return _osqp_run(solver, qp, qp.lower, qp.upper, x0, y0)


def _active_set(
    qp: CvvcQp, lo: np.ndarray, hi: np.ndarray, x0: np.ndarray | None, y0: np.ndarray | None, status: str
) -> _Run | None:
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
    out = solve_dense_qp(qp.p_diag, qp.c, a_dense, lo, hi, guess=guess, max_active=POLISH_MAX_ACTIVE)
    if out.status == "infeasible":
        return _Run(False, True, "infeasible (active set)", out.x, out.y, 0)
    if out.status != "optimal" or not _kkt_ok(a_dense, qp.p_diag, qp.c, lo, hi, out.x, out.y):
        return None
    return _Run(True, False, status, out.x, out.y, 0)


def _warm_polish(
    qp: CvvcQp, lo: np.ndarray, hi: np.ndarray, x0: np.ndarray | None, y0: np.ndarray | None
) -> _Run | None:
    """The optimum from the warm start's active set (no ADMM at all), or None without a usable warm start.

    Between consecutive intervals the binding constraints rarely change: then the active-set method takes
    zero to a few steps. A warm start with no active row (all multipliers zero) is a valid start too: the
    method then begins at the unconstrained minimum.
    """
    if x0 is None or y0 is None or y0.shape != lo.shape:
        return None
    return _active_set(qp, lo, hi, x0, y0, "warm active set")


def _osqp_run(
    solver: osqp.OSQP,
    qp: CvvcQp,
    lo: np.ndarray,
    hi: np.ndarray,
    x0: np.ndarray | None,
    y0: np.ndarray | None,
    max_iter: int = MAX_ITER,
) -> _Run:
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
        return _Run(False, False, f"warm start failed: {e}", np.zeros(n), np.zeros(m), 0)
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
            return _Run(False, False, f"solve failed: {e}", np.zeros(n), np.zeros(m), total)
        total += int(res.info.iter)
        status = osqp.SolverStatus(res.info.status_val)
        status_name = status.name
        if status in (osqp.SolverStatus.OSQP_PRIMAL_INFEASIBLE, osqp.SolverStatus.OSQP_PRIMAL_INFEASIBLE_INACCURATE):
            return _Run(False, True, status_name, np.zeros(n), np.zeros(m), total)
        x = np.asarray(res.x, float)
        y = np.asarray(res.y, float)
        if not (x.shape == (n,) and np.all(np.isfinite(x)) and np.all(np.isfinite(y))):
            return _Run(False, False, f"{status_name} with non-finite iterate", np.zeros(n), np.zeros(m), total)
        if a_dense is not None:
            if _kkt_ok(a_dense, p_diag, qp.c, lo, hi, x, y):
                return _Run(True, False, status_name, x, y, total)
            polished = _active_set(qp, lo, hi, x, y, status_name + "+polish")
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
            return _Run(True, False, status_name, x, y, total)
        chunk *= 2
    return _Run(False, False, f"{status_name} after {total} iterations", np.zeros(n), np.zeros(m), total)


def _kkt_ok(
    a: np.ndarray, p_diag: np.ndarray, c: np.ndarray, lo: np.ndarray, hi: np.ndarray, x: np.ndarray, y: np.ndarray
) -> bool:
    """KKT conditions of ``min x'Px/2 + c'x, lo <= Ax <= hi`` hold within ``KKT_TOL`` (so ``x`` is optimal)."""
    ax = a @ x
    if np.max(np.abs(p_diag * x + c + a.T @ y), initial=0.0) > KKT_TOL:
        return False
    if np.any(ax < lo - KKT_TOL) or np.any(ax > hi + KKT_TOL):
        return False
    return not (np.any((y > KKT_TOL) & (ax < hi - KKT_TOL)) or np.any((y < -KKT_TOL) & (ax > lo + KKT_TOL)))


def _violation_pu(inputs: CvvcInputs, v_pu: np.ndarray) -> np.ndarray:
    """(N,) excursion of each voltage beyond the optimization limits [pu], >= 0."""
    return np.maximum(np.maximum(inputs.v_min_pu - v_pu, v_pu - inputs.v_max_pu), 0.0)


def _candidates(d_rel: np.ndarray) -> list[np.ndarray]:
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


def _hold(inputs: CvvcInputs, reason: str, iterations: int, seconds: StageSeconds) -> CvvcSolution:
    """No action: taps and Q set points as they are, the present voltages as the prediction."""
    v = inputs.v0_pu.copy()
    return CvvcSolution(
        status="hold",
        reason=reason,
        taps_new=inputs.taps.copy(),
        q_new_kvar=inputs.q0_kvar.copy(),
        v_pred_pu=v,
        cost=inputs.cost(np.zeros(inputs.n_reg), inputs.q0_kvar),
        max_violation_pu=float(np.max(_violation_pu(inputs, v), initial=0.0)),
        iterations=iterations,
        relaxed_d_tap=np.zeros(inputs.n_reg),
        relaxed_q_kvar=inputs.q0_kvar.copy(),
        relaxed_form="none",
        relaxed_x=np.zeros(0),
        relaxed_y=np.zeros(0),
        relaxed_problem=None,
        candidates_tried=0,
        seconds=seconds,
    )


def _warm_source(warm: CvvcSolution | None, inputs: CvvcInputs) -> tuple[CvvcQp, np.ndarray, np.ndarray] | None:
    """Warm start from the previous interval's relaxation, on the same feeder (same node count and devices).

    Tap changes are relative to the present taps, so the previous tap *changes* are not a good guess: they
    start at zero; Q (absolute set points), violations and multipliers are reused.
    """
    if warm is None or warm.relaxed_problem is None or warm.relaxed_x.size == 0:
        return None
    prev = warm.relaxed_problem
    if prev.soft_nodes.size != inputs.n_nodes or prev.q_rating_kvar.size != inputs.n_pv:
        return None
    if prev.layout.tap_up is None or prev.layout.tap_up.stop != inputs.n_reg:
        return None
    x = warm.relaxed_x.copy()
    x[prev.layout.tap_up] = 0.0
    x[prev.layout.tap_down] = 0.0
    return prev, x, warm.relaxed_y


def _unreachable_rows(qp: CvvcQp) -> np.ndarray:
    """Voltage rows that no point of the variable box can satisfy: the hard form is infeasible for sure.

    Interval arithmetic over the bound rows (a sufficient test, exact for one node out of resources).
    """
    lo, hi = _row_ranges(qp)
    rows = qp.voltage_rows
    return np.flatnonzero((hi < qp.lower[rows] - 1e-9) | (lo > qp.upper[rows] + 1e-9))


def _zero_is_feasible(qp: CvvcQp) -> bool:
    """No action at all (taps kept, every Q set point 0) meets every constraint: it is then optimal."""
    return bool(np.all(qp.lower <= 0.0) and np.all(qp.upper >= 0.0))


def solve_cvvc(inputs: CvvcInputs, *, warm_start: CvvcSolution | None = None) -> CvvcSolution:
    """Solve one CVVC interval: relaxation, rounding, Q re-solve, soft fallback (paper eq. 9-17).

    Parameters
    ----------
    inputs : the problem (validated on construction: finite, consistent shapes).
    warm_start : the previous interval's solution, or ``None`` (cold start).

    Returns
    -------
    A ``CvvcSolution``; ``status="hold"`` with a reason when the solver fails. Never raises on numeric
    trouble, never contains NaN.
    """
    t_start = time.perf_counter()
    iterations = 0
    hard = build_cvvc_qp(inputs, soft=False)
    t_built = time.perf_counter()

    # Relaxation: hard limits (eq. 9-15); violation variables (eq. 16-17) at the nodes no action can bring
    # within the limits (e.g. a feeder head above 1.04 pu), hard limits at the others; if that is still
    # infeasible or unsolved, the soft form at every node.
    qp, reason = hard, ""
    unreachable = _unreachable_rows(hard)
    soft_mask = np.zeros(inputs.n_nodes, bool)
    soft_mask[unreachable] = True
    start = _start_nodes(inputs, soft_mask, warm_start)
    if unreachable.size:
        names = ", ".join(str(i) for i in unreachable[:5]) + (", ..." if unreachable.size > 5 else "")
        reason = (
            f"{unreachable.size} critical node(s) cannot reach the limits with the actions available (index "
            f"{names}): their violation is minimised (eq. 17), hard limits elsewhere"
        )
        run, qp = _solve_rows(inputs, soft_mask, None, start, _warm_source(warm_start, inputs))
        iterations += run.iterations
        if not run.ok:
            reason += "; the remaining hard limits are infeasible too: soft form at every node"
    elif _zero_is_feasible(hard):
        # Every cost is >= 0 and every variable >= 0, so x = 0 minimises the objective: nothing to solve.
        run = _Run(True, False, "presolve: no action needed", np.zeros(hard.layout.n), np.zeros(hard.n_rows), 0)
    else:
        run, qp = _solve_rows(inputs, soft_mask, None, start, _warm_source(warm_start, inputs), hard)
        iterations += run.iterations
        if not run.ok:
            reason = (
                "hard voltage limits infeasible: soft form (eq. 17) used"
                if run.infeasible
                else f"hard relaxation not solved ({run.status}): soft form (eq. 17) used"
            )
    if not run.ok:
        all_soft = np.ones(inputs.n_nodes, bool)
        run, qp = _solve_rows(inputs, all_soft, None, start, _warm_source(warm_start, inputs))
        iterations += run.iterations
    form: Literal["hard", "soft"] = "soft" if qp.soft else "hard"
    t_relaxed = time.perf_counter()
    if not run.ok:
        return _hold(
            inputs,
            f"soft relaxation not solved ({run.status}); holding taps and Q",
            iterations,
            StageSeconds(t_built - t_start, t_relaxed - t_built, 0.0, t_relaxed - t_start),
        )
    d_rel = qp.d_tap(run.x)
    q_rel = qp.q_kvar(run.x)

    # Rounding, then Q re-solved with the taps fixed, in the relaxation's form: a small best-first branch
    # and bound over the candidates. Each candidate's score (eq. 9 cost plus the proximal terms, which the
    # relaxation also minimises) has two cheap lower bounds: the relaxed objective (for all of them) and
    # the Lagrangian dual function at the relaxation's multipliers (per candidate). Candidates are tried in
    # order of their bound; the search stops once the best score is within ROUNDING_GAP_REL of the relaxed
    # objective or below the next candidate's bound.
    candidates = _candidates(d_rel)
    bound = qp.objective(run.x)
    hard_nodes = ~qp.soft_nodes
    if np.max(np.abs(candidates[0] - d_rel), initial=0.0) <= INTEGRAL_TOL_STEPS:
        # The relaxed taps are integral (the usual case: no tap move): the relaxation is the answer.
        plan = [(bound, 0, candidates[0], 0.0)]
    else:
        fixed = build_cvvc_qp(inputs, soft=qp.soft_nodes, fixed_d_tap=candidates[0], nodes=qp.nodes)
        x_q0, y_q0 = _remap(qp, run.x, run.y, fixed)
        plan = []
        for index, d_int in enumerate(candidates):
            tap_prox = 0.5 * PROX_WEIGHT * fixed.cost_scale * float(d_int @ d_int)
            tap_cost = float(inputs.cost_per_tap @ np.abs(d_int)) + tap_prox
            lo, hi = fixed.bounds_with_d_tap(d_int)
            lower_bound = tap_cost + _dual_bound(fixed, lo, hi, y_q0)
            plan.append((lower_bound, index, d_int, tap_cost))
        plan.sort(key=lambda item: (item[0], item[1]))
        row_ranges = _row_ranges(fixed)
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
            out_of_reach = (row_ranges[1] < lo[rows] - 1e-9) | (row_ranges[0] > hi[rows] + 1e-9)
            if np.any(out_of_reach & ~fixed.soft_rows):
                continue  # some hard node cannot meet its limits with these taps, whatever Q does
            res = _active_set(fixed, lo, hi, None, None, "active set")  # measured: the box start is better here
            if res is None:
                if solver is None:
                    solver = _setup(fixed)
                    if solver is None:
                        break
                solver.update(l=lo, u=hi)
                res = _osqp_run(solver, fixed, lo, hi, x_q0, y_q0, MAX_ITER if best is None else MAX_ITER_RESOLVE)
            iterations += res.iterations
            tried += 1
            if not res.ok:
                continue
            outside = _outside_violations(inputs, fixed, d_int, fixed.q_kvar(res.x))
            if outside.size:
                # Nodes without a row are violated: add their rows and re-solve this candidate; the larger
                # problem serves the following candidates too.
                res, bigger = _solve_rows(
                    inputs, qp.soft_nodes, d_int, np.union1d(fixed.nodes, outside), (fixed, res.x, res.y)
                )
                iterations += res.iterations
                fixed, solver = bigger, None
                row_ranges = _row_ranges(fixed)
                x_q0, y_q0 = _remap(qp, run.x, run.y, fixed)
                if not res.ok:
                    continue
            q_new = np.clip(fixed.q_kvar(res.x), inputs.q_min_kvar, inputs.q_max_kvar)
            score = fixed.objective(res.x) + tap_cost
        v_new = inputs.predict_v_pu(d_int, q_new)
        if np.max(_violation_pu(inputs, v_new)[hard_nodes], initial=0.0) > V_TOL_PU:
            continue
        if best is None or score < best[0]:
            best = (score, d_int, q_new)

    status: Literal["optimal", "soft"] = "optimal" if form == "hard" else "soft"
    if best is None and hard_nodes.any():
        # No re-solve succeeded within its budget: take the first candidate that meets the hard limits with
        # the relaxed Q unchanged (feasible, not re-optimised).
        q_keep = np.clip(q_rel, inputs.q_min_kvar, inputs.q_max_kvar)
        for d_int in candidates:
            violation = _violation_pu(inputs, inputs.predict_v_pu(d_int, q_keep))
            if np.max(violation[hard_nodes], initial=0.0) <= V_TOL_PU:
                best = (0.0, d_int, q_keep)
                break
    if best is None and hard_nodes.any():
        # No integer point within one tap of the relaxation meets the hard limits: soft Q re-solve at the
        # nearest rounding.
        reason = "no rounding of the relaxed taps meets the hard limits: Q re-solved in soft form (eq. 17)"
        status = "soft"
        soft_fixed = build_cvvc_qp(inputs, soft=True, fixed_d_tap=candidates[0])
        res = _active_set(soft_fixed, soft_fixed.lower, soft_fixed.upper, None, None, "active set") or _osqp(
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
    t_rounded = time.perf_counter()
    seconds = StageSeconds(t_built - t_start, t_relaxed - t_built, t_rounded - t_relaxed, t_rounded - t_start)
    _, d_int, q_new = best
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
        max_violation_pu=float(np.max(_violation_pu(inputs, v_pred), initial=0.0)),
        iterations=iterations,
        relaxed_d_tap=d_rel,
        relaxed_q_kvar=q_rel,
        relaxed_form=form,
        relaxed_x=run.x,
        relaxed_y=run.y,
        relaxed_problem=qp,
        candidates_tried=tried,
        seconds=seconds,
    )


def _dual_bound(qp: CvvcQp, lo: np.ndarray, hi: np.ndarray, y: np.ndarray | None) -> float:
    """Lagrangian dual function of ``qp`` (bounds ``lo``, ``hi``) at multipliers ``y`` [cost units].

    ``g(y) = min_x x'Px/2 + c'x + y'Ax - max_{lo<=z<=hi} y'z``, in closed form since ``P`` is a positive
    diagonal. By weak duality it is a lower bound on the optimum for any ``y``; ``-inf`` without ``y``.
    """
    if y is None or y.shape != lo.shape:
        return -np.inf
    grad = qp.c + (qp.a_dense.T @ y if qp.a_dense is not None else qp.A.T @ y)
    support = np.where(y > 0.0, y * hi, 0.0) + np.where(y < 0.0, y * lo, 0.0)
    return float(qp.cost_scale * (-0.5 * np.sum(grad**2 / qp.p_diag) - np.sum(support)))


def _remap(src: CvvcQp, x: np.ndarray, y: np.ndarray, dst: CvvcQp) -> tuple[np.ndarray, np.ndarray | None]:
    """Carry a solution of ``src`` over to ``dst`` as a warm start: same variables and rows by node.

    Taps (when both have them) and Q by position, violation variables and voltage-row multipliers by node,
    zeros for what ``src`` lacks. The multipliers are ``None`` when ``y`` does not fit ``src``.
    """
    s_lay, d_lay = src.layout, dst.layout
    x0 = np.zeros(d_lay.n)
    both_taps = s_lay.tap_up is not None and d_lay.tap_up is not None
    if both_taps:
        x0[d_lay.tap_up] = x[s_lay.tap_up]
        x0[d_lay.tap_down] = x[s_lay.tap_down]
    x0[d_lay.q_inj] = x[s_lay.q_inj]
    x0[d_lay.q_abs] = x[s_lay.q_abs]
    if s_lay.vio is not None and d_lay.vio is not None:
        found, where = _positions(src.nodes[src.soft_rows], dst.nodes[dst.soft_rows])
        x0[d_lay.vio][found] = x[s_lay.vio][where]
    if y.shape != (src.n_rows,):
        return x0, None
    y0 = np.zeros(dst.n_rows)
    n_src, n_dst = src.nodes.size, dst.nodes.size
    found, where = _positions(src.nodes, dst.nodes)
    y0[:n_dst][found] = y[:n_src][where]
    tap_src = 0 if s_lay.tap_up is None else 2 * (s_lay.tap_up.stop - s_lay.tap_up.start)
    tap_dst = 0 if d_lay.tap_up is None else 2 * (d_lay.tap_up.stop - d_lay.tap_up.start)
    if both_taps:
        y0[n_dst : n_dst + tap_dst] = y[n_src : n_src + tap_src]
    y0[n_dst + tap_dst :] = y[n_src + tap_src :]  # the Q bound rows
    return x0, y0


def _positions(src_ids: np.ndarray, dst_ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For sorted ids: which ``dst_ids`` occur in ``src_ids`` (mask) and where (indices of those found)."""
    pos = np.searchsorted(src_ids, dst_ids)
    inside = pos < src_ids.size
    found = np.zeros(dst_ids.size, bool)
    found[inside] = src_ids[pos[inside]] == dst_ids[inside]
    return found, pos[found]


def _outside_violations(inputs: CvvcInputs, qp: CvvcQp, d_tap: np.ndarray, q_kvar: np.ndarray) -> np.ndarray:
    """Nodes without a row in ``qp`` that the actions would take beyond the limits, worst first (capped)."""
    violation = _violation_pu(inputs, inputs.predict_v_pu(d_tap, q_kvar))
    violation[qp.nodes] = 0.0
    worst = np.flatnonzero(violation > ROWGEN_TOL_PU)
    return np.sort(worst[np.argsort(-violation[worst], kind="stable")][:ROWGEN_ADD])


def _solve_rows(
    inputs: CvvcInputs,
    soft: np.ndarray,
    fixed_d_tap: np.ndarray | None,
    nodes: np.ndarray | None,
    source: tuple[CvvcQp, np.ndarray, np.ndarray] | None,
    prebuilt: CvvcQp | None = None,
) -> tuple[_Run, CvvcQp]:
    """Solve with voltage rows for ``nodes`` only (None: all), adding the rows of violated nodes until none.

    A problem with fewer rows is a relaxation, so a solution that violates no other node's limit is optimal
    for the full problem (row generation). Rows only grow, so this ends, at the latest with every node.
    ``source`` is a solved problem to warm-start from.
    """
    iterations = 0
    while True:
        if prebuilt is not None and nodes is None and fixed_d_tap is None and not soft.any():
            qp, prebuilt = prebuilt, None  # the full hard problem the presolve already built
        else:
            qp = build_cvvc_qp(inputs, soft=soft, fixed_d_tap=fixed_d_tap, nodes=nodes)
        x0, y0 = _remap(*source, qp) if source is not None else (None, None)
        run = _osqp(qp, x0, y0)
        iterations += run.iterations
        if not run.ok or qp.nodes.size == inputs.n_nodes:
            break
        outside = _outside_violations(inputs, qp, qp.d_tap(run.x), qp.q_kvar(run.x))
        if outside.size == 0:
            break
        nodes = np.union1d(qp.nodes, outside)
        source = (qp, run.x, run.y)
    return dataclasses.replace(run, iterations=iterations), qp


def _start_nodes(inputs: CvvcInputs, soft: np.ndarray, warm: CvvcSolution | None) -> np.ndarray | None:
    """The first rows of a large problem, or ``None`` (every node) for problems of the paper's size.

    The nodes closest to (or beyond) a limit, the soft ones, and the rows the previous interval ended with.
    """
    if inputs.n_nodes <= ROWGEN_MIN_NODES:
        return None
    margin = np.minimum(inputs.v0_pu - inputs.v_min_pu, inputs.v_max_pu - inputs.v0_pu)
    start = np.argsort(margin, kind="stable")[:ROWGEN_START]
    start = np.union1d(start, np.flatnonzero(soft))
    previous = None if warm is None else warm.relaxed_problem
    if previous is not None and previous.soft_nodes.size == inputs.n_nodes:
        start = np.union1d(start, previous.nodes)
    return start


def _row_ranges(qp: CvvcQp) -> tuple[np.ndarray, np.ndarray]:
    """Lowest and highest value each voltage row can take over the variable box (bound rows)."""
    rows = qp.voltage_rows
    nb = qp.n_rows - rows.stop  # one identity bound row per tap/Q variable, in variable order
    dense = qp.a_dense[rows, :nb] if qp.a_dense is not None else qp.A[: rows.stop, :nb].toarray()
    lb, ub = qp.lower[rows.stop :], qp.upper[rows.stop :]
    return np.minimum(dense * lb, dense * ub).sum(axis=1), np.maximum(dense * lb, dense * ub).sum(axis=1)


def solve_milp_reference(inputs: CvvcInputs) -> MilpReference:
    """Exact optimum of eq. (9)-(15) with integer taps and hard limits, for tests and benchmarks.

    Same scaled constraints as the relaxation, no proximal term, ``scipy.optimize.milp`` (HiGHS).
    """
    qp = build_cvvc_qp(inputs, soft=False)
    lay = qp.layout
    integrality = np.zeros(lay.n)
    integrality[: 2 * inputs.n_reg] = 1
    lo = np.where(np.isfinite(qp.lower), qp.lower, -np.inf)
    hi = np.where(np.isfinite(qp.upper), qp.upper, np.inf)
    res = scipy.optimize.milp(
        qp.c,
        integrality=integrality,
        bounds=scipy.optimize.Bounds(-np.inf, np.inf),
        constraints=scipy.optimize.LinearConstraint(sp.csr_matrix(qp.A), lo, hi),
        options={"mip_rel_gap": 1e-9},
    )
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
