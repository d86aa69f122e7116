"""Which tap moves the controller takes over its decisions (agent.tap_moves): reversal locks, the tap deadband, rent
or buy."""

import dataclasses

import msgspec
import numpy as np
import pytest

from agent.controller import Decision
from agent.errors import AgentInputError
from tests.controller_cases import HIGH, MODEL, K, R, paper_controller, snapshot


def test_a_tap_move_is_not_reversed_soon_after_unless_the_limits_need_it():
    """Under-voltage raises taps; five minutes later an over-voltage the plants' Q can absorb: with the lockout the
    raised regulators are not lowered (Q does it), without it they are; with no Q headroom left they are lowered all
    the same (the limits need it), and once the lockout is over the reverse move is offered again."""
    low, high = -3.0 * HIGH, HIGH  # readings 3 % below the estimate: under-voltage; 1 % above: over-voltage
    dear_q = msgspec.structs.replace(MODEL, pv=[msgspec.structs.replace(p, cost_per_kvar=0.05) for p in MODEL.pv])

    def pair(lockout_s: float, kva: float = 1200.0, second_t_s: int = 300) -> tuple[Decision, Decision]:
        c = paper_controller(dear_q,
                           tap_reversal_lockout_s=lockout_s)
        d1 = c.decide(snapshot(0, reading_error_pu=low))
        s2 = snapshot(second_t_s * 10**9, reading_error_pu=high, taps=d1.reg_tap)
        return d1, c.decide(dataclasses.replace(s2, pv_kva_available=np.full(K, kva)))

    d1, free = pair(0.0)  # Q at 0.05 per kvar: lowering taps is the cheaper way down
    raised = d1.reg_tap > 0
    assert d1.status == "optimal" and raised.any()
    assert free.status == "optimal" and np.any(free.reg_tap[raised] < d1.reg_tap[raised])
    _, locked = pair(900.0)
    assert locked.status == "optimal", locked.reason
    assert np.all(locked.reg_tap[raised] >= d1.reg_tap[raised])  # not reversed: Q absorbs instead
    assert locked.pv_q_kvar.sum() < free.pv_q_kvar.sum() - 1.0
    _, needed = pair(900.0, kva=900.0)  # no Q headroom (P = 900 kW): only the taps can bring the voltages down
    assert needed.status == "optimal" and np.any(needed.reg_tap[raised] < d1.reg_tap[raised])
    _, later = pair(900.0, second_t_s=1200)
    np.testing.assert_array_equal(later.reg_tap, free.reg_tap)
    with pytest.raises(AgentInputError, match="tap_reversal_lockout_s"):
        paper_controller(tap_reversal_lockout_s=-1.0)


def test_no_tap_moves_for_a_predicted_violation_within_the_deadband():
    """No Q headroom and readings 3 % below the estimate: one tap up meets the limits; the taps held leave 0.003 pu
    below them. Within a 0.004 pu deadband the taps stay (a soft decision that says why); 3.2 % below (0.005 pu) or
    without the deadband, the tap moves."""

    def decide(error_pu: float, deadband_pu: float) -> Decision:
        snap = snapshot(0, reading_error_pu=np.full(R, error_pu))
        return paper_controller(tap_deadband_pu=deadband_pu).decide(
            dataclasses.replace(snap, pv_kva_available=np.full(K, 900.0)))

    moved = decide(-0.03, 0.0)
    assert moved.status == "optimal" and moved.reg_tap.sum() == 1
    held = decide(-0.03, 0.004)
    assert held.status == "soft" and not held.reg_tap.any() and "tap deadband" in held.reason
    lo, _ = MODEL.optimization_limits_pu
    assert 0.001 < lo - held.v_pred_pu.min() <= 0.004 + 1e-9
    assert decide(-0.032, 0.004).reg_tap.sum() >= 1
    assert held.tolerated and not moved.tolerated
    beyond = decide(-0.2, 0.004)  # no taps and Q can meet the limits: the soft form (eq. 17), not the deadband's
    assert beyond.status == "soft" and not beyond.tolerated and "tap deadband" not in beyond.reason
    with pytest.raises(AgentInputError, match="tap_deadband_pu"):
        paper_controller(tap_deadband_pu=-0.001)
    # each decision lists its solves by role (what the stage benchmark reads): the held one is the deadband's, the
    # decision the one with the limits widened by the deadband
    assert [role for role, _ in moved.solves] == ["main"]
    assert [role for role, _ in held.solves] == ["main", "deadband", "tolerated"]
    assert held.solves[2][1].cost == held.objective and held.solves[0][1].taps_new[:R].sum() == 1


def test_the_deadband_holds_the_taps_for_a_lasting_violation_only_so_long():
    """The same violation within the deadband at every decision: with ``tap_deadband_hold_s`` of one control period
    the taps are held at the first decision and move at the second; a decision in between that the deadband did not
    hold starts the count again; 0 holds them as long as the violation lasts."""
    period = int(MODEL.control_period_s) * 1_000_000_000

    def taps(hold_s: float, errors: list[float]) -> list[int]:
        c = paper_controller(tap_deadband_pu=0.004, tap_deadband_hold_s=hold_s)
        out = []
        for i, e in enumerate(errors):
            snap = snapshot(i * period, reading_error_pu=np.full(R, e))
            d = c.decide(dataclasses.replace(snap, pv_kva_available=np.full(K, 900.0)))
            out.append(int(d.reg_tap.sum()))
        return out

    assert taps(0.0, [-0.03] * 3) == [0, 0, 0]
    assert taps(float(MODEL.control_period_s), [-0.03] * 2) == [0, 1]
    assert taps(float(MODEL.control_period_s), [-0.03, 0.0, -0.03]) == [0, 0, 0]  # not in a row: held again


def test_taps_held_by_the_deadband_buy_no_q_for_what_it_tolerates():
    """Some Q headroom and dear taps: the held decision's soft form buys Q for the 0.003 pu the deadband tolerates;
    the decision takes the Q of the limits widened by the deadband instead (none here), not below them."""
    dear = msgspec.structs.replace(MODEL, regulators=[msgspec.structs.replace(r, cost_per_tap=0.5)
                                                      for r in MODEL.regulators])
    snap = dataclasses.replace(snapshot(0, reading_error_pu=np.full(R, -0.03)), pv_kva_available=np.full(K, 902.0))
    d = paper_controller(dear, tap_deadband_pu=0.004).decide(snap)
    roles = dict(d.solves)
    assert [role for role, _ in d.solves] == ["main", "deadband", "tolerated"] and not d.reg_tap.any()
    assert np.abs(roles["deadband"].q_new_kvar).sum() > 100.0  # the soft form's Q for 0.003 pu
    assert np.abs(d.pv_q_kvar).sum() < 1.0 and d.status == "soft" and "widened by the deadband" in d.reason
    assert d.tolerated  # the deadband's soft decision, not the soft form (eq. 17)
    lo, _ = MODEL.optimization_limits_pu
    assert 0.001 < lo - d.v_pred_pu.min() <= 0.004 + 1e-9
    no_tolerance = paper_controller(dear, tap_deadband_pu=0.0).decide(snap)
    assert no_tolerance.reg_tap.sum() == 1  # without the deadband the tap moves


def test_taps_held_by_the_deadband_rent_q_only_until_it_has_cost_the_move():
    """Readings 3.15 % below the estimate and some Q headroom: the deadband holds the tap and buys 51 kvar (0.051 an
    interval) where one tap (0.14) meets the limits. Held decision after held decision, the Q paid adds up; once it
    would pass the tap's price the tap moves (rent or buy), and the count starts again. Without the rule the taps
    stay held, paying every interval."""

    def run(break_even: bool) -> list[Decision]:
        c = paper_controller(tap_deadband_pu=0.004, tap_break_even=break_even, sensitivity_error=0.3)
        snap = dataclasses.replace(snapshot(0, reading_error_pu=np.full(R, -0.0315)),
                                   pv_kva_available=np.full(K, 930.0))
        return [c.decide(dataclasses.replace(snap, t_ns=i * 300 * 10**9)) for i in range(6)]

    renting = run(False)
    assert all(d.status == "soft" and not d.reg_tap.any() and "tap deadband" in d.reason for d in renting)
    assert all(d.tolerated for d in renting)
    rent = renting[0].objective
    assert 0.14 / 3 < rent < 0.14 / 2  # two held decisions cost less than the tap, three more
    assert np.abs(renting[0].pv_q_kvar).sum() > 10.0
    buying = run(True)
    assert [int(d.reg_tap.sum()) for d in buying] == [0, 0, 1, 0, 0, 1]
    for d in (buying[2], buying[5]):
        assert d.status == "optimal" and d.objective == pytest.approx(0.14) and "tap deadband" not in d.reason
        assert not d.tolerated  # the move bought, not the deadband's decision
    assert all(d.objective == pytest.approx(rent) for i, d in enumerate(buying) if i not in (2, 5))


def test_q_standing_in_for_a_tap_is_paid_until_it_has_cost_the_tap():
    """Dear taps (0.5 a step) and Q headroom: eq. (9) buys 338 kvar (0.338 an interval) where one tap meets the limits
    without Q. The second such decision in a row has paid more than the tap's price: the tap moves, and the count
    starts again. Without the rule every decision buys the Q."""
    dear = msgspec.structs.replace(MODEL, regulators=[msgspec.structs.replace(r, cost_per_tap=0.5)
                                                      for r in MODEL.regulators])
    buying_controller = None

    def run(break_even: bool) -> list[Decision]:
        nonlocal buying_controller
        c = buying_controller = paper_controller(dear, tap_break_even=break_even)
        snap = dataclasses.replace(snapshot(0, reading_error_pu=np.full(R, -0.03)),
                                   pv_kva_available=np.full(K, 1000.0))
        return [c.decide(dataclasses.replace(snap, t_ns=i * 300 * 10**9)) for i in range(4)]

    renting = run(False)
    assert all(d.status == "optimal" and not d.reg_tap.any() for d in renting)
    assert 0.25 < renting[0].objective < 0.5 and [r for r, _ in renting[0].solves] == ["main"]
    buying = run(True)
    assert [int(d.reg_tap.sum()) for d in buying] == [0, 1, 0, 1]
    assert buying_controller.tap_moves.bought == 2
    assert [r for r, _ in buying[0].solves] == ["main", "buy"]
    for d in buying[1::2]:
        assert d.status == "optimal" and d.objective == pytest.approx(0.5) and np.abs(d.pv_q_kvar).sum() < 1.0
        lo, hi = MODEL.optimization_limits_pu
        assert lo - 1e-5 <= d.v_pred_pu.min() and d.v_pred_pu.max() <= hi + 1e-5
