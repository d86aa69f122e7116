"""Conformal bounds from correlated windows (training.conformal), judged on windows they never saw."""

from __future__ import annotations

import numpy as np
import pytest

from training.conformal import LEVEL_GRID_STEPS, conformal_quantile, held_out_miss_rate, pooled_bounds

ALPHA = 0.01


def _windows(rng: np.random.Generator, scale: np.ndarray, n_windows: int, rows: int, offset_share: float):
    """Errors (n_windows * rows, N) whose node offset is drawn once per window (a customer's load keeps its offset
    for hours), ``offset_share`` of each node's spread; the rest independent minute to minute."""
    n = scale.size
    offset = rng.normal(0.0, offset_share * scale, (n_windows, 1, n))
    noise = rng.normal(0.0, np.sqrt(1.0 - offset_share ** 2) * scale, (n_windows, rows, n))
    return (offset + noise).reshape(-1, n), np.repeat(np.arange(n_windows), rows)


def _miss(err: np.ndarray, upper: np.ndarray, lower: np.ndarray) -> float:
    return float(np.mean((err > upper) | (-err > lower)))


@pytest.mark.parametrize("seed", [0, 2, 3])
def test_bounds_from_a_dozen_correlated_windows_hold_on_windows_they_never_saw(seed):
    rng = np.random.default_rng(seed)
    scale = rng.uniform(0.001, 0.01, 40)
    err, window = _windows(rng, scale, 12, 120, offset_share=0.85)
    unseen, _ = _windows(rng, scale, 400, 120, offset_share=0.85)
    # the node-by-node quantile sees a dozen draws of each node's offset: on new windows it misses 3x its promise
    per_node = _miss(unseen, conformal_quantile(err, 1 - ALPHA / 2), conformal_quantile(-err, 1 - ALPHA / 2))
    assert per_node > 2 * ALPHA
    b = pooled_bounds(err, window, ALPHA)
    assert b.held_out_miss <= ALPHA
    assert b.level > 1 - ALPHA / 2  # the held-out windows asked for more than the nominal level
    assert _miss(unseen, b.upper, b.lower) <= 1.5 * ALPHA


def test_independent_minutes_keep_about_the_nominal_level():
    rng = np.random.default_rng(1)
    scale = rng.uniform(0.001, 0.01, 40)
    err, window = _windows(rng, scale, 12, 120, offset_share=0.0)
    b = pooled_bounds(err, window, ALPHA)
    grid_step = (ALPHA / 2) / LEVEL_GRID_STEPS
    assert b.level <= 1 - ALPHA / 2 + 2 * grid_step + 1e-12
    unseen, _ = _windows(rng, scale, 200, 120, offset_share=0.0)
    assert _miss(unseen, b.upper, b.lower) <= 1.5 * ALPHA


def test_each_node_bound_follows_its_own_spread_and_a_pinned_node_stays_at_zero():
    rng = np.random.default_rng(4)
    scale = np.array([0.001, 0.004, 0.008, 0.0])
    err, window = _windows(rng, np.maximum(scale, 1e-12), 12, 120, offset_share=0.5)
    err[:, 3] = 0.0  # a regulator's secondary: its own reading corrects it exactly
    b = pooled_bounds(err, window, ALPHA)
    assert b.upper[0] < b.upper[1] < b.upper[2]
    assert b.lower[0] < b.lower[1] < b.lower[2]
    assert b.upper[3] < 1e-8 and b.lower[3] < 1e-8


def test_the_held_out_miss_rate_falls_with_the_level_and_one_window_holds_nothing_out():
    rng = np.random.default_rng(5)
    err, window = _windows(rng, rng.uniform(0.001, 0.01, 10), 6, 60, offset_share=0.8)
    levels = np.linspace(0.99, 1.0, 11)
    miss = held_out_miss_rate(err, window, levels)
    assert np.all(np.diff(miss) <= 1e-12) and miss[0] > miss[-1]
    assert np.all(held_out_miss_rate(err, np.zeros(len(err), int), levels) == 0.0)


@pytest.mark.parametrize("err, window, alpha, match", [
    (np.zeros((0, 3)), np.zeros(0, int), 0.01, "no calibration samples"),
    (np.zeros((5, 3)), np.zeros(4, int), 0.01, "window labels"),
    (np.zeros((5, 3)), np.zeros(5, int), 1.5, "alpha"),
])
def test_bad_calibration_input_is_refused(err, window, alpha, match):
    with pytest.raises(ValueError, match=match):
        pooled_bounds(err, window, alpha)
