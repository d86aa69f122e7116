"""The agent's estimates and bounds judged against the truth of their step
(``simulator_bridge.simulation.live_accuracy``)."""

import numpy as np
import pytest

from simulator_bridge.simulation.live_accuracy import MISS_TOLERANCE_PU, LiveAccuracyAccumulator

NAMES = ["a.1", "b.1", "c.1", "d.1", "e.1"]


def test_misses_are_counted_below_and_above_with_their_node():
    acc = LiveAccuracyAccumulator(NAMES)
    truth = np.array([1.00, 1.02, 0.98, 1.01, 1.03])
    # estimates of a, b, c: a inside, b's truth above v + high, c's truth below v - low
    acc.add(["a.1", "b.1", "c.1"], np.array([1.001, 1.012, 0.988]), np.full(3, 0.005), np.full(3, 0.005), truth)
    acc.add(["a.1", "b.1", "c.1"], np.array([1.000, 1.019, 0.981]), np.full(3, 0.005), np.full(3, 0.005), truth)
    r = acc.result(promised_miss_rate=0.01)
    assert (r.decisions, r.samples, r.bound_samples) == (2, 6, 6)
    assert (r.misses_below, r.misses_above, r.bound_misses) == (1, 1, 2)
    assert r.bound_miss_rate == pytest.approx(2 / 6)
    err = np.array([0.001, -0.008, 0.008, 0.0, -0.001, 0.001])
    assert r.rmse_pu == pytest.approx(np.sqrt(np.mean(err ** 2)))
    assert r.bias_pu == pytest.approx(err.mean())
    assert r.within_001 == pytest.approx(1.0)
    assert r.bounds_hold() is False and r.bounds_hold(factor=40.0) is True
    assert r.worst is not None and r.worst.node in ("b.1", "c.1") and r.worst.misses_below + r.worst.misses_above == 1


def test_rounding_is_no_miss_and_a_model_without_bounds_has_none_to_judge():
    acc = LiveAccuracyAccumulator(NAMES)
    truth = np.array([1.0, 1.0, 1.0, 1.0, 1.0])
    # a regulator's secondary: bounds 0, the estimate its own reading up to the message's 6 decimals
    acc.add(["a.1", "b.1"], np.array([1.0 - 0.4 * MISS_TOLERANCE_PU, 0.999]), np.array([0.0, 0.002]),
            np.array([0.0, 0.002]), truth)
    assert acc.result().bound_misses == 0
    acc.add(["a.1", "b.1"], np.array([1.0 - 3 * MISS_TOLERANCE_PU, 0.999]), np.array([0.0, 0.002]),
            np.array([0.0, 0.002]), truth)
    assert acc.result().misses_above == 1
    none = LiveAccuracyAccumulator(NAMES)
    none.add(["a.1", "b.1"], np.array([0.99, 1.01]), np.zeros(2), np.zeros(2), truth)
    r = none.result(promised_miss_rate=0.01)
    assert (r.bound_samples, r.bound_misses, r.bound_miss_rate) == (0, 0, 0.0) and r.bounds_hold() is None
    assert r.rmse_pu == pytest.approx(0.01)


def test_extremes_are_captured_only_when_both_are_estimated_within_the_zone():
    zone = [0, 1, 2, 3]  # e.1 (index 4) is another feeder's node: its voltage is not this feeder's extreme
    acc = LiveAccuracyAccumulator(NAMES, zone)
    truth = np.array([1.00, 1.04, 0.97, 1.01, 1.09])
    acc.add(["b.1", "c.1"], np.array([1.04, 0.97]), np.full(2, 0.01), np.full(2, 0.01), truth)  # both
    acc.add(["b.1", "d.1"], np.array([1.04, 1.01]), np.full(2, 0.01), np.full(2, 0.01), truth)  # min missed
    acc.add(["x.1"], np.array([1.0]), np.full(1, 0.01), np.full(1, 0.01), truth)  # unknown node: not judged
    r = acc.result()
    assert r.decisions == 2 and r.extremes_captured == pytest.approx(0.5)
    assert acc.unknown_nodes == 1
    assert LiveAccuracyAccumulator(NAMES).result().samples == 0  # nothing judged yet
