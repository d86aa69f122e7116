"""Paper eq. (8): tap change to regulator set point, hand-computed and against a local controller."""

import numpy as np
import pytest

from agent.errors import AgentInputError
from agent.setpoints import expected_compared_v120, recentred_setpoint, setpoint_for_tap_change


@pytest.mark.parametrize(
    ("d_tap", "expected"),
    [
        (0, 121.0),  # no change: V_s^1
        (2, 121.0 + (4.0 - 0.75) / 2),  # raise: 122.625
        (-1, 121.0 - (4.0 - 0.75) / 2),  # lower: 119.375
    ],
)
def test_eq8_by_hand(d_tap, expected):
    assert setpoint_for_tap_change(121.0, d_tap, 4.0, 0.75) == pytest.approx(expected, abs=1e-12)


def _local_control(tap: int, v_at_tap0: float, step: float, setpoint: float, band: float) -> int:
    """A conventional regulator controller: one step at a time until the compared voltage is in band."""
    for _ in range(64):
        v = v_at_tap0 + tap * step
        if v < setpoint - band / 2:
            tap += 1
        elif v > setpoint + band / 2:
            tap -= 1
        else:
            return tap
    raise AssertionError("controller hunts")


@pytest.mark.parametrize("d_tap", [-3, -2, -1, 0, 1, 2, 3])
@pytest.mark.parametrize("band", [2.0, 4.0])
def test_eq8_set_point_makes_local_control_land_on_the_desired_tap(d_tap, band):
    step, tap0, v_now = 0.75, 3, 122.3
    v_at_tap0 = v_now - tap0 * step
    v_s1 = v_now + d_tap * step  # compared voltage once the desired tap is reached
    setpoint = setpoint_for_tap_change(v_s1, d_tap, band, step)
    assert _local_control(tap0, v_at_tap0, step, setpoint, band) == tap0 + d_tap


def test_eq8_rejects_band_not_wider_than_a_step_and_nan():
    with pytest.raises(AgentInputError, match="bandwidth"):
        setpoint_for_tap_change(120.0, 1, 0.75, 0.75)
    with pytest.raises(AgentInputError):
        setpoint_for_tap_change(float("nan"), 1, 4.0, 0.75)


def test_expected_compared_voltage_adds_the_predicted_change():
    v = expected_compared_v120(np.array([121.0, 119.0]), np.array([0.00625, -0.0125]), np.array([1 / 120, 1 / 120]))
    np.testing.assert_allclose(v, [121.75, 117.5], atol=1e-12)


@pytest.mark.parametrize(
    ("before", "target", "now", "expected"),
    [
        (3, 5, 4, 122.9),  # stepped one of two so far: centred on the reading (the rest is the regulator's)
        (3, 5, 5, 122.9),
        (3, 5, 6, 122.9),  # one past the target: held there
        (3, 5, 3, 124.6),  # not stepped yet: eq. (8) again
        (3, 1, 2, 122.9),
        (3, 1, 4, 124.6),  # stepped the other way: not what eq. (8) asked, eq. (8) again
    ],
)
def test_the_band_is_recentred_once_the_regulator_stepped_the_way_eq8_asked(before, target, now, expected):
    assert recentred_setpoint(before, target, now, 122.9, 124.6) == expected


def test_recentred_band_holds_the_landed_tap_against_the_drift_that_moved_it_again():
    """Landed by eq. (8) half a step inside its band edge, the regulator steps again for a drift of half a step;
    re-centred on its reading, it holds through that drift."""
    step, band, tap0, v_now = 0.75, 4.0, 0, 121.0
    v_s1 = v_now + step
    eq8 = setpoint_for_tap_change(v_s1, 1, band, step)
    landed = _local_control(tap0, v_now, step, eq8, band)
    assert landed == 1
    drift = -0.5  # the voltage falls by two thirds of a step before the next decision
    assert _local_control(landed, v_now + drift, step, eq8, band) == 2
    centred = recentred_setpoint(tap0, 1, landed, v_now + landed * step, eq8)
    assert _local_control(landed, v_now + drift, step, centred, band) == 1


def test_a_step_landed_on_the_measured_step_holds_against_a_drift_that_the_models_step_does_not():
    """A regulator whose compared reading moves 0.5 V per 0.75 V tap step (line-drop compensation): eq. (8) on the
    model's step lands it 0.125 V from its band edge, and a 0.2 V sag after the raise makes it step twice; landed on
    its measured step it steps once, and without a drift it steps once either way."""
    band, model_step, measured, tap0, v_now = 4.0, 0.75, 0.5, 3, 121.0

    def taps_after(step_assumed: float, drift: float) -> int:
        setpoint = setpoint_for_tap_change(v_now + step_assumed, 1, band, step_assumed)
        return _local_control(tap0, v_now - tap0 * measured + drift, measured, setpoint, band) - tap0

    assert taps_after(model_step, -0.2) == 2
    assert taps_after(measured, -0.2) == 1
    assert taps_after(measured, 0.0) == taps_after(model_step, 0.0) == 1


def test_measured_steps_are_the_median_of_the_latest_moves_once_enough_are_seen():
    from agent.setpoints import STEP_PLAUSIBLE, STEPS_KEPT, STEPS_LEAST, MeasuredSteps

    steps = MeasuredSteps(np.array([0.75, 0.75]))
    usable = np.array([True, True])
    steps.observe((((1, 0.50), (2, 0.60)), ()), usable)
    assert np.isnan(steps.step_v120()).all()  # fewer than STEPS_LEAST moves: the model's step
    steps.observe((((2, 0.60), (3, 0.55)), ((1, 0.7),)), usable)  # the move at 2 again: counted once
    np.testing.assert_allclose(steps.step_v120(), [0.55, np.nan])
    assert STEPS_LEAST == 3
    steps.observe(((), ((2, 0.7), (3, 0.7))), np.array([True, False]))  # the second regulator's readings noisy
    assert np.isnan(steps.step_v120()[1])
    steps.observe((tuple((10 + i, 0.65) for i in range(STEPS_KEPT)), ()), usable)  # only the latest are kept
    assert steps.step_v120()[0] == pytest.approx(0.65)
    lo, _ = STEP_PLAUSIBLE
    odd = MeasuredSteps(np.array([0.75]))
    odd.observe((((1, 0.1), (2, 0.1), (3, 0.1)),), np.array([True]))
    assert 0.1 < lo * 0.75 and np.isnan(odd.step_v120()[0])  # implausible: not believed


def test_a_regulators_step_is_seen_at_its_own_single_step_moves_only():
    """Frames a minute apart: vr3 raised one step alone (seen), lowered while vr0, whose step moves vr3's secondary,
    moved too (not seen), raised two steps at once (not seen); vr0's two moves (seen: no other regulator's step moves
    its secondary); a move older than two control periods (not seen: the controller has it already)."""
    import msgspec

    from agent.aligner import AlignedFrames
    from agent.snapshot import steps_seen_v120
    from benchmarks.synthetic import synthetic_model
    from schemas import messages as m
    from schemas.examples import examples

    model = synthetic_model(0)
    base = examples()[m.RegFrame]
    minute, t_end = 60_000_000_000, 1_672_549_200_000_000_000 + 12 * 300_000_000_000
    # per minute (oldest first): (vr0 tap, vr0 compared, vr3 tap, vr3 compared)
    rows = [(0, 120.0, 0, 120.0), (0, 120.0, 1, 120.6),  # an old move of vr3 (more than two periods ago)
            *[(0, 120.0, 1, 120.6)] * 8,
            (0, 120.0, 2, 121.1),  # vr3 up one alone: +0.5 V
            (1, 120.7, 1, 120.9),  # vr3 down with vr0 up: blurred
            (1, 120.7, 3, 122.1),  # vr3 up two at once
            (0, 120.1, 3, 122.0)]  # vr0 down one alone: -0.6 V
    times = [t_end - (len(rows) - 1 - i) * minute for i in range(len(rows))]

    def frame(reg: str, t: int, tap: int, v: float) -> m.RegFrame:
        return msgspec.structs.replace(base, regulator_id=reg, t_ns=t, tap=tap, v_compared_120=v)

    recent = {"vr0": tuple(frame("vr0", t, a, va) for t, (a, va, _, _) in zip(times, rows, strict=True)),
              "vr3": tuple(frame("vr3", t, b, vb) for t, (_, _, b, vb) in zip(times, rows, strict=True))}
    aligned = AlignedFrames(t_ns=t_end, head=None, pv={}, vr={}, missing=(), vr_recent=recent)
    seen = steps_seen_v120(aligned, model)
    assert seen[3] == ((times[10], pytest.approx(0.5)),)
    assert seen[0] == ((times[11], pytest.approx(0.7)), (times[13], pytest.approx(0.6)))
    assert all(not s for r, s in enumerate(seen) if r not in (0, 3))


def test_only_a_one_step_move_lands_on_the_measured_step():
    from agent.setpoints import with_measured_steps

    d_tap = np.array([1, -1, 2, 0, 1])
    measured = np.array([0.5, 0.5, 0.5, 0.5, np.nan])
    v_s1, step = with_measured_steps(np.full(5, 121.0), d_tap, np.full(5, 0.75), np.full(5, 0.8), measured)
    np.testing.assert_allclose(v_s1, [121.0 - 0.3, 121.0 + 0.3, 121.0, 121.0, 121.0])
    np.testing.assert_allclose(step, [0.5, 0.5, 0.75, 0.75, 0.75])


def test_a_held_band_is_narrowed_to_where_a_node_would_leave_its_limits_never_widened():
    from agent.setpoints import safety_band

    # 4 V band on 122 V; the first node below would reach its lower limit 1.0 V down, its upper limit 3 V up
    sp, band = safety_band(122.0, 4.0, 122.0, 1.0, 3.0, 0.6)
    assert (sp - band / 2, sp + band / 2) == pytest.approx((121.0, 124.0))  # lower edge at 1 V, upper kept
    sp, band = safety_band(122.0, 4.0, 122.0, -0.5, 0.2, 0.6)  # already outside: one tap step each side, no closer
    assert (sp - band / 2, sp + band / 2) == pytest.approx((121.4, 122.6))
    assert safety_band(122.0, 4.0, 122.0, 5.0, 5.0, 0.6) == (122.0, 4.0)  # margins wider than the band: unchanged
    # a held set point the reading has drifted from: the band is narrowed where it has room, and never below two
    # steps wide
    sp, band = safety_band(122.0, 4.0, 123.0, 0.5, 0.1, 0.6)
    assert (sp - band / 2, sp + band / 2) == pytest.approx((122.4, 123.6))
    assert safety_band(122.0, 4.0, 123.5, 0.5, 0.1, 0.6) == (122.0, 4.0)  # 1.1 V wide would be left: unchanged
    assert safety_band(122.0, 4.0, 122.0, float("nan"), 1.0, 0.6) == (122.0, 4.0)
