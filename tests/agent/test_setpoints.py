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
