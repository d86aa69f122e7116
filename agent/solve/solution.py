"""The results of the CVVC solve (qpsolvers' ``Solution`` boundary): typed, frozen, never NaN.

``CvvcSolution`` is what ``solve_cvvc`` returns, ``WarmStart`` the part of it the next interval starts from,
``MilpReference`` the exact optimum for tests and benchmarks; ``Run`` is one QP solve inside the package.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from agent.cvvc_qp import CvvcInputs, CvvcQp
from agent.solve.settings import V_TOL_PU

__all__ = ["CvvcSolution", "MilpReference", "Run", "StageSeconds", "Status", "WarmStart", "hold_solution",
           "violation_pu"]

Status = Literal["optimal", "soft", "hold"]


@dataclass(frozen=True)
class StageSeconds:
    """Wall-clock time of each stage [s]. Diagnostics only: not part of the deterministic result."""

    build_s: float = 0.0
    relaxed_s: float = 0.0
    rounding_s: float = 0.0
    total_s: float = 0.0
    milp_s: float = 0.0  # the part of rounding_s spent in the MILP fallback


@dataclass(frozen=True)
class WarmStart:
    """Where the next interval's solve starts: the previous relaxation as finally solved, and its iterate.

    Attributes
    ----------
    problem : the relaxation (its rows: see ``CvvcQp.nodes``).
    x, y : its primal and dual in scaled units.
    """

    problem: CvvcQp
    x: np.ndarray
    y: np.ndarray

    def source_for(self, inputs: CvvcInputs) -> tuple[CvvcQp, np.ndarray, np.ndarray] | None:
        """The warm start for ``inputs`` on the same feeder (same node count and devices), else ``None``.

        Tap changes are relative to the present taps, so the previous tap *changes* are not a good guess: they
        start at zero; Q (absolute set points), violations and multipliers are reused.
        """
        prev = self.problem
        if prev.soft_nodes.size != inputs.n_nodes or prev.q_rating_kvar.size != inputs.n_pv:
            return None
        if prev.layout.tap_up is None or prev.layout.tap_up.stop != inputs.n_reg:
            return None
        x = self.x.copy()
        x[prev.layout.tap_up] = 0.0
        x[prev.layout.tap_down] = 0.0
        return prev, x, self.y


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
    lattice_tried : integer taps near no move re-solved when no rounding met the hard limits.
    milp_solves : MILP solves of the rounding's last fallback (0 or 1).
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
    lattice_tried: int = 0
    milp_solves: int = 0

    @property
    def warm_start(self) -> WarmStart | None:
        """What the next interval starts from; ``None`` after an early hold (no relaxation solved)."""
        if self.relaxed_problem is None or self.relaxed_x.size == 0:
            return None
        return WarmStart(problem=self.relaxed_problem, x=self.relaxed_x, y=self.relaxed_y)


@dataclass(frozen=True)
class MilpReference:
    """Exact optimum of the hard-limit problem with integer taps (``scipy.optimize.milp``, HiGHS)."""

    status: Literal["optimal", "infeasible", "failed"]
    taps_new: np.ndarray
    q_new_kvar: np.ndarray
    cost: float


@dataclass(frozen=True)
class Run:
    """One QP solve: converged (``ok``), proven infeasible, or neither; iterate in scaled units."""

    ok: bool
    infeasible: bool
    status: str
    x: np.ndarray
    y: np.ndarray
    iterations: int


def violation_pu(inputs: CvvcInputs, v_pu: np.ndarray) -> np.ndarray:
    """(N,) excursion of each voltage beyond the optimization limits [pu], >= 0."""
    return np.maximum(np.maximum(inputs.v_min_pu - v_pu, v_pu - inputs.v_max_pu), 0.0)


def hold_solution(inputs: CvvcInputs, reason: str, iterations: int, seconds: StageSeconds) -> CvvcSolution:
    """No action: taps and Q set points as they are, the present voltages as the prediction."""
    return _unmoved(inputs, "hold", reason, inputs.q0_kvar.copy(), iterations, seconds)


def pinned_solution(inputs: CvvcInputs, seconds: StageSeconds) -> CvvcSolution:
    """Nothing can move (every plant's Q and every tap or bank fixed): the one possible point, without a solve.

    OSQP declared such problems' soft form infeasible ("primal infeasible inaccurate": every variable pinned at a
    bound, e.g. PV at night with no Q headroom and the banks frozen; epri-ckt5 case A held 135 of 864 decisions of
    a summer run), although a violation is then simply what remains. ``soft`` when a limit stays violated.
    """
    q = inputs.q_min_kvar + 0.0  # a fresh array, without -0.0
    worst = float(np.max(violation_pu(inputs, inputs.predict_v_pu(np.zeros(inputs.n_reg), q)), initial=0.0))
    if worst <= V_TOL_PU:
        return _unmoved(inputs, "optimal", "", q, 0, seconds)
    return _unmoved(inputs, "soft", f"no action available (every plant's Q and every tap fixed): {worst:.4f} pu "
                    "beyond the limits stays", q, 0, seconds)


def _unmoved(inputs: CvvcInputs, status: Status, reason: str, q_kvar: np.ndarray, iterations: int,
             seconds: StageSeconds) -> CvvcSolution:
    """Taps as they are and Q set points ``q_kvar``, without a relaxation (no warm start for the next one)."""
    v = inputs.predict_v_pu(np.zeros(inputs.n_reg), q_kvar)
    return CvvcSolution(
        status=status,
        reason=reason,
        taps_new=inputs.taps.copy(),
        q_new_kvar=q_kvar,
        v_pred_pu=v,
        cost=inputs.cost(np.zeros(inputs.n_reg), q_kvar),
        max_violation_pu=float(np.max(violation_pu(inputs, v), initial=0.0)),
        iterations=iterations,
        relaxed_d_tap=np.zeros(inputs.n_reg),
        relaxed_q_kvar=q_kvar.copy(),
        relaxed_form="none",
        relaxed_x=np.zeros(0),
        relaxed_y=np.zeros(0),
        relaxed_problem=None,
        candidates_tried=0,
        seconds=seconds,
    )
