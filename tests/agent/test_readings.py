"""A regulator reading fitted on the head's load (agent/readings.py): noise filtering without lag."""

from __future__ import annotations

import numpy as np
import pytest

from agent.readings import fitted_reading_v120


def test_a_noiseless_linear_reading_is_recovered_exactly():
    p = np.linspace(800.0, 3000.0, 30)
    q = 0.25 * p + np.sin(p)  # not collinear with P
    vh = 7200.0 + 30.0 * np.cos(p / 300.0)  # the source's voltage moves too
    v = 123.0 - 0.0012 * p + 0.004 * q + 0.016 * (vh - 7200.0)
    x = np.column_stack([p, q, vh])
    assert fitted_reading_v120(v, x, x[-1]) == pytest.approx(v[-1], abs=1e-9)


def test_noise_is_reduced_below_the_five_reading_mean_without_its_lag():
    """1 % SCADA noise (1.2 V) on a reading that falls 3.6 V over the hour as the load rises."""
    rng = np.random.default_rng(1)
    p = np.linspace(1000.0, 4000.0, 60)
    q = 0.3 * p + rng.normal(0.0, 5.0, 60)
    true = 122.0 - 0.0012 * p
    fit, mean5 = [], []
    for _ in range(400):
        v = true + rng.normal(0.0, 1.2, 60)
        fit.append(fitted_reading_v120(v, np.column_stack([p, q]), [p[-1], q[-1]]) - true[-1])
        mean5.append(v[-5:].mean() - true[-1])
    assert abs(np.mean(fit)) < 0.05 and np.std(fit) < 0.75 * np.std(mean5)  # no lag, less noise
    assert np.mean(mean5) > 0.09  # the mean of the last five lags the falling reading by two minutes (0.12 V)


def test_a_flat_load_gives_the_plain_mean():
    v = np.array([120.0, 121.0, 119.5, 120.5, 120.2, 119.8, 120.4, 120.6])
    flat = np.full(v.size, 1500.0)
    assert fitted_reading_v120(v, np.column_stack([flat, flat * 0.3]), [1500.0, 450.0]) == pytest.approx(v.mean())


@pytest.mark.parametrize("n", [0, 1, 7])  # fewer than min_points: the caller keeps its mean
def test_too_few_readings_give_none(n):
    x = np.arange(n, dtype=float)
    assert fitted_reading_v120(120.0 + x, np.column_stack([1000.0 + x, 300.0 + x]), [1000.0, 300.0]) is None


def test_inputs_are_not_mutated():
    v, now = np.full(10, 120.0), np.array([2.0, 1.0])
    x = np.column_stack([np.linspace(1, 2, 10), np.linspace(3, 1, 10)])
    before = (v.copy(), x.copy(), now.copy())
    fitted_reading_v120(v, x, now)
    assert all(np.array_equal(a, b) for a, b in zip(before, (v, x, now), strict=True))
