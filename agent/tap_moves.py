"""Which tap moves a decision takes, over the decisions (beyond the paper): the locks on reversing a recent move, the
tap deadband and rent or buy.

Eq. (9) prices one interval and knows nothing of the decisions before it. Three rules carry what they did:

- **Reversal locks** (``tap_reversal_lockout_s``, every case): the reverse of a regulator's last decided move is not
  offered within the lockout, unless the limits cannot be met without it (the controller solves again unlocked).
- **Tap deadband** (``tap_deadband_pu``, estimated states): a move is not taken for a predicted violation the held
  taps leave within the deadband, and the Q is that of the limits widened by it (docs/method.md "Tap deadband").
- **Rent or buy** (``tap_break_even``, estimated states): Q that stands in for a move is paid until it has cost the
  move's taps, then the move is taken (docs/method.md "Rent or buy").

``TapMoves`` holds their state (each regulator's last move, how long the deadband has held, the Q rent paid) and
makes no solve of its own: ``settle`` is handed the controller's solve.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Literal

import numpy as np

from agent.cvvc_qp import CvvcInputs
from agent.decision import SolveRole
from agent.errors import AgentInputError
from agent.solve import V_TOL_PU, CvvcSolution
from agent.solve.solution import violation_pu
from schemas.settings import AgentOptions

__all__ = ["HELD_BY_DEADBAND", "Settled", "TapMoves", "q_cost"]

Locks = Literal["reversals", "none", "all"]

HELD_BY_DEADBAND = "taps held:"
"""How the reason of a decision whose taps the deadband held starts (``TapMoves.tap_deadband``)."""


def q_cost(inputs: CvvcInputs, solution: CvvcSolution) -> float:
    """Eq. (15)'s part of a solution's cost: its Q set points' [cost units per interval]."""
    return float(inputs.cost_per_kvar @ np.abs(solution.q_new_kvar))


@dataclasses.dataclass(frozen=True)
class Settled:
    """``TapMoves.settle``'s outcome: the decision's solution, the solves made for it (after the caller's), and whether
    it is the deadband's decision on the limits it widened (``Decision.tolerated``).
    """

    solution: CvvcSolution
    solves: tuple[tuple[SolveRole, CvvcSolution], ...]
    tolerated: bool


class TapMoves:
    """The tap rules' state over the decisions, for ``n_reg`` regulators whose tap ranges are ``tap_min``..``tap_max``.

    Raises ``AgentInputError`` on options out of range.
    """

    def __init__(self, options: AgentOptions, tap_min: np.ndarray, tap_max: np.ndarray) -> None:
        o = options
        if not (np.isfinite(o.tap_reversal_lockout_s) and o.tap_reversal_lockout_s >= 0.0):
            raise AgentInputError(f"tap_reversal_lockout_s must be >= 0, not {o.tap_reversal_lockout_s}")
        if not (np.isfinite(o.tap_deadband_pu) and 0.0 <= o.tap_deadband_pu <= 0.02):
            raise AgentInputError(f"tap_deadband_pu must be within 0 to 0.02 pu, not {o.tap_deadband_pu}")
        self._tap_min = np.asarray(tap_min, int)
        self._tap_max = np.asarray(tap_max, int)
        n_reg = self._tap_min.size
        self._lockout_ns = int(o.tap_reversal_lockout_s * 1e9)
        self.deadband_pu = float(o.tap_deadband_pu)
        self._deadband_hold_ns = int(o.tap_deadband_hold_s * 1e9)
        self._deadband_since_ns: int | None = None  # the first of the decisions in a row the deadband held the taps
        self.break_even = bool(o.tap_break_even)
        self._rent = 0.0  # Q paid beyond the offered moves' over the decisions in a row with one [cost units]
        self.bought = 0  # decisions that took the offered move once the Q standing in for it had cost as much
        # each regulator's last decided move: its direction (+1, -1, 0 for none yet) and the step it was decided at
        self._last_move = np.zeros(n_reg, int)
        self._last_move_t_ns = np.zeros(n_reg, np.int64)

    # ------------------------------------------------------------------ reversal locks
    def reversal_locks(self, t_ns: int) -> tuple[np.ndarray, np.ndarray]:
        """``(no_down, no_up)`` (R,) at step ``t_ns``: within ``tap_reversal_lockout_s`` of a regulator's last decided
        move, the reverse move is not offered, unless the limits cannot be met without it (``CvvcController.decide``
        solves again without the locks).
        """
        recent = (self._last_move != 0) & (int(t_ns) - self._last_move_t_ns < self._lockout_ns)
        return recent & (self._last_move > 0), recent & (self._last_move < 0)

    def relocked(self, inputs: CvvcInputs, locks: Locks, t_ns: int) -> CvvcInputs:
        """``inputs`` (a problem of step ``t_ns``) with the regulators' tap ranges that ``locks`` leave: the reverse
        of recent moves not offered (``reversals``), every move offered (``none``) or none (``all``: the taps held);
        the banks' and everything else as they are, so a re-solve builds nothing again.
        """
        n_reg = self._tap_min.size
        taps_now = np.asarray(inputs.taps[:n_reg], int)
        if locks == "reversals":
            no_down, no_up = self.reversal_locks(t_ns)
            if not (no_down.any() or no_up.any()):
                return inputs  # no lock in force: the problem's own tap ranges (no copy to check again)
        else:
            no_down = no_up = np.full(n_reg, locks == "all")
        tap_min, tap_max = np.array(inputs.tap_min), np.array(inputs.tap_max)
        tap_min[:n_reg] = np.where(no_down, np.maximum(self._tap_min, taps_now), self._tap_min)
        tap_max[:n_reg] = np.where(no_up, np.minimum(self._tap_max, taps_now), self._tap_max)
        return inputs.replaced(tap_min=tap_min, tap_max=tap_max)

    def moved(self, moved: np.ndarray, direction: np.ndarray, t_ns: int) -> None:
        """The decision of step ``t_ns`` moved the ``moved`` (R,) regulators, each the way ``direction`` (R,) says."""
        self._last_move = np.where(moved, np.sign(direction), self._last_move)
        self._last_move_t_ns = np.where(moved, int(t_ns), self._last_move_t_ns)

    # ------------------------------------------------------------------ the deadband, rent or buy
    def settle(self, inputs: CvvcInputs, solution: CvvcSolution, taps_now: np.ndarray, n_nodes: int, t_ns: int,
               solve: Callable[[CvvcInputs], CvvcSolution], *, estimated: bool) -> Settled:
        """The solution an estimated state's decision keeps, from ``solution`` (``inputs`` solved, the reversal locks
        settled): the taps held by the deadband, or a move bought once the Q standing in for it has cost as much.

        ``taps_now``: (R,) the regulators' taps; ``n_nodes``: the problem's node rows (a predicted bank's rows come
        after them); ``solve``: the controller's solve (its warm start); ``estimated``: whether the state
        is estimated (case A's voltages are the truth: neither rule, ``solution`` kept).
        """
        n_reg = taps_now.size
        solves: list[tuple[SolveRole, CvvcSolution]] = []
        buy: CvvcSolution | None = None  # a move the Q of ``solution`` stands in for, if any (``rent_or_buy``)
        widened: CvvcSolution | None = None  # the deadband's decision on the limits it widened, if it made one
        held_by_deadband = False
        if estimated and self.deadband_pu > 0 and np.any(solution.taps_new[:n_reg] != taps_now):
            held_problem = self.relocked(inputs, "all", t_ns)
            held = solve(held_problem)
            solves.append(("deadband", held))
            note = self._deadband_in_time(self.tap_deadband(solution, held, held_problem, n_nodes), t_ns)
            held_by_deadband = bool(note)
            if note:  # the taps held: Q only for what the deadband does not tolerate
                tolerated = solve(self.deadband_widened(held_problem, n_nodes))
                solves.append(("tolerated", tolerated))
                if tolerated.status == "optimal":
                    kept = widened = dataclasses.replace(tolerated, status="soft",
                                                         reason=f"{note}; Q for the limits widened by the deadband")
                else:
                    kept = dataclasses.replace(held, reason=f"{note}; {held.reason}" if held.reason else note)
                solution, buy = kept, solution  # held: Q paid every interval; the move: its taps paid once
        elif estimated and self.break_even and solution.status == "optimal" \
                and not np.any(solution.taps_new[:n_reg] != taps_now) and q_cost(inputs, solution) > 0:
            tap_offer = self.tap_offer(inputs, n_reg, solve)
            solves.append(("buy", tap_offer))
            if (tap_offer.status == "optimal" and np.any(tap_offer.taps_new[:n_reg] != taps_now)
                    and q_cost(inputs, tap_offer) < q_cost(inputs, solution) - 1e-9):
                buy = tap_offer
        if not held_by_deadband:
            self._deadband_since_ns = None
        solution = self.rent_or_buy(inputs, solution, buy, n_reg)
        return Settled(solution, tuple(solves), widened is not None and solution is widened)

    def tap_deadband(self, moving: CvvcSolution, held: CvvcSolution, held_problem: CvvcInputs,
                     n_nodes: int) -> str:
        """Why the taps are held instead of ``moving`` (a decision that moves taps), or "" if they are not: ``held``
        (the same problem solved with every tap held, ``held_problem``) predicts no violation of the tightened limits
        beyond ``tap_deadband_pu`` and costs no more.

        Beyond the paper, estimated states only (case A's voltages are the truth): a regulator's own band keeps it
        from moving for a small deviation, and so does this. The limits a decision meets are the optimization limits
        tightened by the estimate's calibrated bounds; whether a node ends a few mV/V inside or outside them moves with
        every estimate, and a tap moved for it is moved back at a later decision (IEEE 8500, first summer day: 150 of
        ~400 moves reversed within 30 minutes, the reversal locks released because the limits could not be met with
        them). The held decision is the soft form's (eq. 17), or the Q of the same problem with the nodes' limits
        widened by the deadband (``deadband_widened``) when those are met (``settle``), and says so. The
        deadband is the nodes' alone: a predicted bank's row (``agent.bank_rows``) may not come closer to its local
        control's setting than with the move (without that rule, the first three October days of IEEE 8500: bank
        switchings 118 -> 240).
        """
        if held.status != "soft" or held.cost > moving.cost:
            return ""
        over, before = violation_pu(held_problem, held.v_pred_pu), violation_pu(held_problem, moving.v_pred_pu)
        worst = float(over[:n_nodes].max(initial=0.0))
        if worst > self.deadband_pu or np.any(over[n_nodes:] > before[n_nodes:] + V_TOL_PU):
            return ""
        return (f"{HELD_BY_DEADBAND} {worst:.4f} pu predicted beyond the tightened limits, within the tap deadband "
                f"{self.deadband_pu:g} pu")

    def _deadband_in_time(self, note: str, t_ns: int) -> str:
        """``note`` (the tap deadband's reason to hold the taps, "" for none), or "" once the deadband has held them
        for ``tap_deadband_hold_s`` in a row: the violation it tolerated has lasted, and the move is taken.

        Beyond the paper: a node the deadband leaves below its limit stays there while the load drifts on (IEEE 123,
        3 January: the same node 0.003 pu below the limit for four decisions in a row, the 1-minute minimum 0.970 pu
        against no control's 0.982), as a regulator's time delay lets a voltage out of band for a while, not for ever.
        """
        if not note:
            return note
        if self._deadband_since_ns is None:
            self._deadband_since_ns = t_ns
        if self._deadband_hold_ns > 0 and t_ns - self._deadband_since_ns >= self._deadband_hold_ns:
            self._deadband_since_ns = None
            return ""
        return note

    def deadband_widened(self, held_problem: CvvcInputs, n_nodes: int) -> CvvcInputs:
        """``held_problem`` (taps held) with its first ``n_nodes`` rows' limits widened by ``tap_deadband_pu``.

        Once the deadband has held the taps, the predicted violation it tolerates is tolerated by the Q too: the soft
        form on the tightened limits bought Q for it, where case A (whose voltages are the truth, no deadband) moves a
        tap at 0.14 (IEEE 123, first 3 days of spring and summer: total cost 1.41x and 1.70x case A's, most of it Q).
        A predicted bank's row keeps its limits.
        """
        rows = np.asarray(held_problem.v0_pu).shape[0]
        lo = np.broadcast_to(np.asarray(held_problem.v_min_pu, float), (rows,)).copy()
        hi = np.broadcast_to(np.asarray(held_problem.v_max_pu, float), (rows,)).copy()
        lo[:n_nodes] -= self.deadband_pu
        hi[:n_nodes] += self.deadband_pu
        return held_problem.replaced(v_min_pu=lo, v_max_pu=hi)

    @staticmethod
    def tap_offer(inputs: CvvcInputs, n_reg: int, solve: Callable[[CvvcInputs], CvvcSolution]) -> CvvcSolution:
        """The same problem with the regulators' taps free of cost, its cost priced back at the taps' (the move
        that would stand in for a decision's Q, when it moves a tap and buys less Q).
        """
        free = np.array(inputs.cost_per_tap, float)
        free[:n_reg] = 0.0
        offer = solve(inputs.replaced(cost_per_tap=free))
        return dataclasses.replace(offer, cost=inputs.cost(offer.taps_new - inputs.taps, offer.q_new_kvar))

    def rent_or_buy(self, inputs: CvvcInputs, solution: CvvcSolution, buy: CvvcSolution | None,
                    n_reg: int) -> CvvcSolution:
        """``solution`` (its Q standing in for a move), or ``buy`` (the move) once the Q it would have saved, summed
        over the decisions in a row that had such a move on offer, reaches the move's taps' price.

        Beyond the paper, estimated states only: eq. (9) prices one interval, where a tap is paid once and the Q
        that stands in for it is paid again every interval (IEEE 123's first summer week before this rule: case D
        1.50x case A's total cost, most of it Q bought where case A had lowered a regulator; docs/results.md).
        Rent or buy: pay the Q while what it has cost beyond the move's Q stays below the move's taps, then move
        (the deterministic break-even rule: at most twice the cost of knowing in advance how long the need lasts).
        The offers are the deadband's moves (``tap_deadband``) and, after an optimal decision that buys Q and moves
        no tap, the same problem with the regulators' taps free (``tap_offer``). Off (``tap_break_even``): the
        decision as eq. (9) prices it.
        """
        if buy is None or not self.break_even:
            self._rent = 0.0
            return solution
        price = float(inputs.cost_per_tap[:n_reg] @ np.abs(buy.taps_new[:n_reg] - inputs.taps[:n_reg]))
        self._rent += max(q_cost(inputs, solution) - q_cost(inputs, buy), 0.0)
        if self._rent < price:
            return solution
        self._rent = 0.0
        self.bought += 1
        return buy
