"""Rounding of the relaxed taps and the Q re-solve with each candidate's taps fixed (a small branch and bound).

Every floor/ceil combination of the (at most ``MAX_ENUMERATED_FRACTIONAL``) most fractional relaxed tap changes
is a candidate, the other taps rounded to nearest; Q is re-solved with each candidate's taps fixed (same form),
best-first by a dual lower bound that each re-solve's multipliers tighten for the others, by the exact dual
active-set method (OSQP if it fails); the cheapest candidate meeting the hard limits wins. If none does, integer
taps further away: first those near "no move", with Lagrangian cuts and a proof of optimality
(``agent.solve.lattice``), then, without that proof, a MILP cut off at the best of them (``agent.solve.milp``); if
there are none, the nearest rounding is re-solved in the soft form.
"""

from __future__ import annotations

import itertools
import time
from dataclasses import dataclass
from typing import Literal

import numpy as np

from agent.cvvc_qp import PROX_WEIGHT, CvvcInputs, CvvcQp, build_cvvc_qp
from agent.solve.lattice import (
    LagrangianCut,
    cut_at,
    feasibility_cut,
    phase_one_multipliers,
    region_bound,
    tap_bounds,
    tap_lattice,
)
from agent.solve.milp import milp_tap_changes
from agent.solve.polish import active_set_polish
from agent.solve.relaxation import osqp_run, setup_osqp, solve_qp
from agent.solve.rows import outside_violations, remap, row_ranges, solve_rows
from agent.solve.settings import (
    FRACTIONAL_TOL_STEPS,
    INTEGRAL_TOL_STEPS,
    LATTICE_MAX_POINTS,
    LATTICE_MAX_SOLVES,
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
    lattice_tried : integer points near no move re-solved when no rounding met the hard limits
        (``agent.solve.lattice``).
    milp_solves : MILP solves (0 or 1): only when the lattice search cannot prove its best optimal.
    milp_s : wall time of the MILP and its Q re-solve [s] (diagnostics, not deterministic).
    """

    status: Literal["optimal", "soft"]
    reason: str
    d_tap: np.ndarray
    q_new_kvar: np.ndarray
    iterations: int
    tried: int
    lattice_tried: int = 0
    milp_solves: int = 0
    milp_s: float = 0.0


def round_taps(inputs: CvvcInputs, qp: CvvcQp, run: Run, reason: str) -> Rounded:
    """Round the relaxation ``run`` of ``qp`` to integer taps and re-solve Q (``reason``: the relaxation's)."""
    d_rel = qp.d_tap(run.x)
    q_rel = qp.q_kvar(run.x)
    form: Literal["hard", "soft"] = "soft" if qp.soft else "hard"

    # Rounding, then Q re-solved with the taps fixed, in the relaxation's form: a small best-first branch
    # and bound over the candidates. Each candidate's score (eq. 9 cost plus the proximal terms, which the
    # relaxation also minimises) has two cheap lower bounds: the relaxed objective (for all of them) and
    # the Lagrangian dual function at the relaxation's multipliers (per candidate). Candidates are tried in
    # order of their bound; the search stops once the best score is within ROUNDING_GAP_REL of the relaxed
    # objective or below the next candidate's bound.
    candidates = rounding_candidates(d_rel)
    bound = qp.objective(run.x)
    hard_nodes = ~qp.soft_nodes
    resolver = _Resolver(inputs, qp, run)
    if np.max(np.abs(candidates[0] - d_rel), initial=0.0) <= INTEGRAL_TOL_STEPS:
        # The relaxed taps are integral (the usual case: no tap move): the relaxation is the answer.
        q_new = np.clip(q_rel, inputs.q_min_kvar, inputs.q_max_kvar)
        v_new = inputs.predict_v_pu(candidates[0], q_new)
        if np.max(violation_pu(inputs, v_new)[hard_nodes], initial=0.0) <= V_TOL_PU:
            resolver.best = (bound, candidates[0], q_new)
    else:
        resolver.search(candidates, stop_at=bound + ROUNDING_GAP_REL * abs(bound))
    best = resolver.best

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
    milp_solves, milp_s = 0, 0.0
    if best is None and hard_nodes.any():
        # No integer point within one tap of the relaxation meets the hard limits; one further away may (the
        # feasible set of a regulated feeder's taps is a thin slab: IEEE 8500 went soft here in 160 of 864
        # winter decisions). First the integer points nearest "no move", cheapest first, with a proof of
        # optimality from their tap cost alone; only without that proof the MILP, and the better of the two.
        best, certified = resolver.lattice_search()
        if not certified:
            t_milp = time.perf_counter()
            found, n = _milp_fallback(inputs, qp, hard_nodes, np.inf if best is None else best[0])
            milp_s = time.perf_counter() - t_milp
            resolver.tried += n
            milp_solves = 1
            if found is not None and (best is None or found[0] < best[0]):
                best = found
    iterations, tried = resolver.iterations, resolver.tried
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
    return Rounded(status=status, reason=reason, d_tap=d_int, q_new_kvar=q_new, iterations=iterations, tried=tried,
                   lattice_tried=resolver.lattice_tried, milp_solves=milp_solves, milp_s=milp_s)


class _Resolver:
    """The Q re-solve of integer tap candidates with the taps fixed, in the relaxation's form, and the best so far.

    Holds one tap-fixed problem (its rows grow when a candidate violates a node without a row), the OSQP solver
    set up on it if the active-set method ever fails, and the warm start remapped from the relaxation.
    ``best`` is ``(score, d_int, q_new_kvar)``: the score is eq. (9)'s cost plus the proximal terms [cost units].
    """

    def __init__(self, inputs: CvvcInputs, qp: CvvcQp, run: Run) -> None:
        self.inputs, self.qp, self.run = inputs, qp, run
        self.hard_nodes = ~qp.soft_nodes
        self.fixed: CvvcQp | None = None
        self.solver = None
        self.best: tuple[float, np.ndarray, np.ndarray] | None = None
        self.iterations = self.tried = self.lattice_tried = self.failed = 0
        self.seen: set[bytes] = set()  # candidates already re-solved (float64 bytes)

    def _fixed(self, d_first: np.ndarray | None = None) -> CvvcQp:
        """The tap-fixed problem, built at ``d_first`` (default no move) on first use; any taps re-fix its bounds."""
        if self.fixed is None:
            d = np.zeros(self.inputs.n_reg) if d_first is None else d_first
            self.fixed = build_cvvc_qp(self.inputs, soft=self.qp.soft_nodes, fixed_d_tap=d, nodes=self.qp.nodes)
            self.ranges = row_ranges(self.fixed)
            self.x_q0, self.y_q0 = remap(self.qp, self.run.x, self.run.y, self.fixed)
        return self.fixed

    def tap_cost(self, d_int: np.ndarray) -> float:
        """Eq. (14)'s cost of ``d_int`` plus its proximal term [cost units]: the part of the score Q leaves alone."""
        tap_prox = 0.5 * PROX_WEIGHT * self._fixed().cost_scale * float(d_int @ d_int)
        return float(self.inputs.cost_per_tap @ np.abs(d_int)) + tap_prox

    def search(self, candidates: list[np.ndarray], stop_at: float = -np.inf) -> None:
        """Re-solve ``candidates`` best-first by their dual lower bound, keeping the best that meets the hard limits.

        Every candidate's score has a lower bound: its tap cost plus the dual function of its Q re-solve at the
        relaxation's multipliers, then also at each feasible re-solve's own (the dual function is affine in the
        taps: ``agent.solve.lattice.cut_at``). A candidate whose bound is not below the best score is skipped;
        the search stops once none is left or the best score is at most ``stop_at``.
        """
        if not candidates:
            return
        fixed = self._fixed(candidates[0])
        points = np.array(candidates, float)
        taps = np.array([self.tap_cost(d_int) for d_int in candidates])
        bounds = taps + _q_bounds(fixed, self.y_q0, points)
        order = np.argsort(bounds, kind="stable")  # ties by candidate order
        points, taps, bounds = points[order], taps[order], bounds[order]
        for i in range(points.shape[0]):
            if self.best is not None and (self.best[0] <= bounds[i:].min() or self.best[0] <= stop_at):
                break  # no remaining candidate can beat the best by more than the tolerance
            if self.best is not None and self.best[0] <= bounds[i]:
                continue  # a later re-solve's bound: this one cannot beat the best
            outcome, problem, y = self.evaluate(points[i], float(taps[i]))
            if outcome == "no solver":
                break
            if outcome == "feasible" and y is not None and problem is not None:
                np.maximum(bounds[i + 1 :], taps[i + 1 :] + _q_bounds(problem, y, points[i + 1 :]),
                           out=bounds[i + 1 :])

    def evaluate(self, d_int: np.ndarray, tap_cost: float) -> tuple[str, CvvcQp | None, np.ndarray | None]:
        """``(outcome, problem, y)``: re-solve one candidate, keep it if it is the best feasible one.

        ``outcome``: ``feasible`` (``y`` the multipliers of ``problem``, the tap-fixed problem it was solved on;
        ``None`` for the relaxation's own taps), ``infeasible`` (no Q meets the hard limits with these taps),
        ``seen`` (re-solved before), ``failed`` (not solved within the budget) or ``no solver``.
        """
        inputs = self.inputs
        key = np.asarray(d_int, float).tobytes()
        if key in self.seen:
            return "seen", None, None
        self.seen.add(key)
        d_rel = self.qp.d_tap(self.run.x)
        fixed: CvvcQp | None = None
        y = None
        if np.max(np.abs(d_int - d_rel), initial=0.0) <= INTEGRAL_TOL_STEPS:
            q_new = np.clip(self.qp.q_kvar(self.run.x), inputs.q_min_kvar, inputs.q_max_kvar)
            score = self.qp.objective(self.run.x)  # relaxed optimum is integral
        else:
            fixed = self._fixed()
            lo, hi = fixed.bounds_with_d_tap(d_int)
            rows = fixed.voltage_rows
            out_of_reach = (self.ranges[1] < lo[rows] - 1e-9) | (self.ranges[0] > hi[rows] + 1e-9)
            if np.any(out_of_reach & ~fixed.soft_rows):
                return "infeasible", fixed, None  # some hard node cannot meet its limits, whatever Q does
            res = active_set_polish(fixed, lo, hi, None, None, "active set")  # measured: the box start is better here
            if res is None:
                if self.solver is None:
                    self.solver = setup_osqp(fixed)
                    if self.solver is None:
                        self.failed += 1
                        return "no solver", None, None
                self.solver.update(l=lo, u=hi)
                res = osqp_run(self.solver, fixed, lo, hi, self.x_q0, self.y_q0,
                               MAX_ITER if self.best is None else MAX_ITER_RESOLVE)
            self.iterations += res.iterations
            self.tried += 1
            if not res.ok:
                self.failed += not res.infeasible
                return ("infeasible" if res.infeasible else "failed"), fixed, None
            outside = outside_violations(inputs, fixed, d_int, fixed.q_kvar(res.x))
            if outside.size:
                # Nodes without a row are violated: add their rows and re-solve this candidate; the larger
                # problem serves the following candidates too.
                res, bigger = solve_rows(
                    inputs, self.qp.soft_nodes, d_int, np.union1d(fixed.nodes, outside), (fixed, res.x, res.y)
                )
                self.iterations += res.iterations
                self.fixed, self.solver = bigger, None
                self.ranges = row_ranges(bigger)
                self.x_q0, self.y_q0 = remap(self.qp, self.run.x, self.run.y, bigger)
                fixed = bigger
                if not res.ok:
                    self.failed += not res.infeasible
                    return ("infeasible" if res.infeasible else "failed"), fixed, None
            q_new = np.clip(fixed.q_kvar(res.x), inputs.q_min_kvar, inputs.q_max_kvar)
            score = fixed.objective(res.x) + tap_cost
            y = res.y
        v_new = inputs.predict_v_pu(d_int, q_new)
        if np.max(violation_pu(inputs, v_new)[self.hard_nodes], initial=0.0) > V_TOL_PU:
            return "infeasible", fixed, None
        if self.best is None or score < self.best[0]:
            self.best = (score, d_int, q_new)
        return "feasible", fixed, y

    def lattice_search(self) -> tuple[tuple[float, np.ndarray, np.ndarray] | None, bool]:
        """``(best, certified)``: the best integer taps within ``k`` steps in all of no move, and whether no
        integer taps at all can score lower (``agent.solve.lattice``).

        The points (``tap_lattice``, ``k`` as large as ``LATTICE_MAX_POINTS`` allows) are re-solved cheapest
        bound first (at most ``LATTICE_MAX_SOLVES``, else uncertified), each bound the tap cost plus the best
        Lagrangian cut so far (and at least 0 for Q); every re-solve adds a cut, and an infeasible one's Farkas
        certificate drops every point it covers (``feasibility_cut``). Certified when the best is at most
        every remaining point's bound and the bound of every point further away (``region_bound``), or when the
        points are all the integer taps there are.
        """
        inputs = self.inputs
        fixed = self._fixed()
        if fixed.a_dense is None:
            return self.best, False
        lo_steps, hi_steps = tap_bounds(inputs)
        points, k, complete = tap_lattice(lo_steps, hi_steps, LATTICE_MAX_POINTS)
        prox = 0.5 * PROX_WEIGHT * fixed.cost_scale
        tap = np.abs(points) @ inputs.cost_per_tap + prox * np.sum(points * points, axis=1)
        q_part = np.zeros(points.shape[0])  # best lower bound on the Q part of each point's score so far
        unsolved = np.ones(points.shape[0], bool)
        floor = region_bound(None, inputs.cost_per_tap, lo_steps, hi_steps, k + 1)

        def add(cut: LagrangianCut | None) -> None:
            nonlocal floor
            if cut is not None:
                np.maximum(q_part, cut.const + points @ cut.slope, out=q_part)
                floor = max(floor, region_bound(cut, inputs.cost_per_tap, lo_steps, hi_steps, k + 1))

        if self.y_q0 is not None:
            add(cut_at(fixed, self.y_q0, np.zeros(inputs.n_reg) if fixed.fixed_d_tap is None else fixed.fixed_d_tap,
                       scale_to_best=False))
        while unsolved.any():
            if self.lattice_tried >= LATTICE_MAX_SOLVES:
                return self.best, False  # left to the MILP
            bound = np.where(unsolved, tap + q_part, np.inf)
            i = int(np.argmin(bound))
            if self.best is not None and self.best[0] <= bound[i]:
                break
            unsolved[i] = False
            d_int = points[i]
            outcome, problem, y = self.evaluate(d_int, float(tap[i]))
            self.lattice_tried += outcome != "seen"
            if outcome in ("failed", "no solver"):
                return self.best, False  # a point may have been missed
            if problem is None:
                continue
            if outcome == "feasible" and y is not None:
                add(cut_at(problem, y, d_int, scale_to_best=False))
            elif outcome == "infeasible":
                y1 = phase_one_multipliers(problem, d_int)
                if y1 is not None:
                    add(cut_at(problem, y1, d_int, scale_to_best=True))
                infeasible = feasibility_cut(problem, d_int)
                if infeasible is not None:
                    # every point the certificate covers is infeasible too: never re-solved
                    unsolved &= infeasible.const + points @ infeasible.slope <= 0.0
        return self.best, complete or (self.best is not None and self.best[0] <= floor)


def _milp_fallback(
    inputs: CvvcInputs, qp: CvvcQp, hard_nodes: np.ndarray, cutoff_cost: float
) -> tuple[tuple[float, np.ndarray, np.ndarray] | None, int]:
    """``(best, tried)``: the MILP's integer taps with Q re-solved (``best`` None when they fail the hard limits or
    no integer taps cost less than ``cutoff_cost`` [cost units]: the score of taps the caller has, an upper bound on
    their eq. (9) cost).
    """
    d_int = milp_tap_changes(inputs, qp.soft_nodes, qp.nodes, cutoff_cost * (1.0 + 1e-9))
    if d_int is None:
        return None, 0
    fixed = build_cvvc_qp(inputs, soft=qp.soft_nodes, fixed_d_tap=d_int, nodes=qp.nodes)
    res = active_set_polish(fixed, fixed.lower, fixed.upper, None, None, "active set") or solve_qp(fixed, None, None)
    if not res.ok:
        return None, 1
    q_new = np.clip(fixed.q_kvar(res.x), inputs.q_min_kvar, inputs.q_max_kvar)
    if np.max(violation_pu(inputs, inputs.predict_v_pu(d_int, q_new))[hard_nodes], initial=0.0) > V_TOL_PU:
        return None, 1
    tap_prox = 0.5 * PROX_WEIGHT * fixed.cost_scale * float(d_int @ d_int)
    return (fixed.objective(res.x) + float(inputs.cost_per_tap @ np.abs(d_int)) + tap_prox, d_int, q_new), 1


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


def _q_bounds(qp: CvvcQp, y: np.ndarray | None, points: np.ndarray) -> np.ndarray:
    """(M,) lower bounds on the Q part of the score of the tap changes ``points`` (M, R) re-solved on the tap-fixed
    ``qp``: its dual function at ``y`` (``-inf`` without ``y``) [cost units].
    """
    if y is None or y.shape != qp.lower.shape or points.shape[0] == 0:
        return np.full(points.shape[0], -np.inf)
    if qp.a_dense is not None:
        cut = cut_at(qp, y, points[0], scale_to_best=False)
        return np.full(points.shape[0], -np.inf) if cut is None else cut.const + points @ cut.slope
    return np.array([dual_bound(qp, *qp.bounds_with_d_tap(d), y) for d in points])


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
