"""Conformal bounds from correlated calibration windows: node-scaled scores pooled, level set by held-out windows.

The calibration minutes (``training.calibration``) come in a dozen windows of two hours. Minutes of one window are
not exchangeable draws: a customer's load, hence a deep node's regression error, keeps its offset for hours. A
quantile taken node by node over those minutes sees about a dozen independent draws of each node's offset, and the
bounds it gives miss far more often than promised on a window it did not see: held out window by window, 1 % bounds
missed 2.9 % of epri-k1's and 3.3 % of epri-m1's calibration node-minutes, and live, in case D, 3.2-4.1 % and 3.6 %.

So the bounds are built the way they are judged, across windows:

1. **Node-scaled scores, pooled.** Each node's errors are divided by that node's root-mean-square error; the scores
   of every node are pooled, and one quantile of the pool, times each node's scale, is the node's bound (per side).
   The tail of the pool is drawn from windows x nodes, not from windows alone (normalized conformal prediction,
   Lei et al. 2018, with the nodes' scores exchangeable after scaling).
2. **The level set by held-out windows.** The one-sided level starts at ``1 - alpha / 2`` and rises on a fixed grid
   until bounds computed without a window miss at most ``alpha`` of that window's node-minutes, on average over the
   windows (cross-conformal; Vovk 2015). Independent minutes keep the level at ``1 - alpha / 2``; correlated ones
   raise it as far as the held-out windows show they must.

Nothing here is fitted to a feeder: the grid and the rule are fixed, the level is what each feeder's own windows ask.
Pure numpy.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

__all__ = ["LEVEL_GRID_STEPS", "PooledBounds", "conformal_quantile", "held_out_miss_rate", "node_scale",
           "pooled_bounds"]

LEVEL_GRID_STEPS = 50
"""The one-sided levels tried run from ``1 - alpha / 2`` to 1 in this many equal steps."""
_SCALE_FLOOR_PU = 1e-9  # a node the correction pins (a regulator's secondary: errors 0) keeps bounds of about 0


class PooledBounds(NamedTuple):
    """Per-node bounds [pu] (``true - estimate <= upper``, ``estimate - true <= lower``) and the one-sided level
    they were taken at; ``held_out_miss`` the two-sided miss rate of that level on held-out windows (0 with one
    window: nothing to hold out).
    """

    upper: np.ndarray
    lower: np.ndarray
    level: float
    held_out_miss: float


def _rank(n: int, levels: np.ndarray) -> np.ndarray:
    """0-based index, in ``n`` sorted scores, of the split-conformal quantile at each of ``levels``: the
    ceil((n + 1) level)-th smallest, or the largest when there are too few scores for the level (the exact conformal
    bound would be infinite).
    """
    return np.minimum(n, np.ceil((n + 1) * np.asarray(levels, float)).astype(int)) - 1


def conformal_quantile(scores: np.ndarray, level: float) -> np.ndarray:
    """Split-conformal quantile of ``scores`` (T, N) along axis 0, node by node (:func:`_rank`); never below 0."""
    s = np.sort(np.asarray(scores, float), axis=0)
    if s.shape[0] == 0:
        raise ValueError("conformal_quantile: no calibration samples")
    return np.maximum(s[int(_rank(s.shape[0], np.array([level]))[0])], 0.0)


def node_scale(err: np.ndarray) -> np.ndarray:
    """Each node's root-mean-square error over the rows of ``err`` (T, N) [pu], floored just above 0."""
    return np.maximum(np.sqrt(np.mean(np.square(err), axis=0)), _SCALE_FLOOR_PU)


def _levels(alpha: float) -> np.ndarray:
    return np.linspace(1.0 - alpha / 2.0, 1.0, LEVEL_GRID_STEPS + 1)


def _pooled_quantiles(err: np.ndarray, levels: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(scale (N,), upper score quantile (L,), lower score quantile (L,)) of ``err``'s pooled node-scaled scores."""
    scale = node_scale(err)
    s = (err / scale).ravel()
    hi, lo = np.sort(s), np.sort(-s)
    k = _rank(s.size, levels)
    return scale, np.maximum(hi[k], 0.0), np.maximum(lo[k], 0.0)


def held_out_miss_rate(err: np.ndarray, window: np.ndarray, levels: np.ndarray) -> np.ndarray:
    """For each level (L,), the two-sided miss rate of the pooled bounds on each window when computed without it,
    averaged over the windows. ``err`` (T, N), ``window`` (T,) the window of each row. One window: zeros.
    """
    ids = np.unique(window)
    if ids.size < 2:
        return np.zeros(levels.size)
    rates = np.zeros((ids.size, levels.size))
    for i, w in enumerate(ids):
        out = window == w
        scale, q_hi, q_lo = _pooled_quantiles(err[~out], levels)
        s = err[out] / scale  # held-out scores on the training windows' scales
        for j in range(levels.size):
            rates[i, j] = np.mean((s > q_hi[j]) | (-s > q_lo[j]))
    return rates.mean(axis=0)


def pooled_bounds(err: np.ndarray, window: np.ndarray, alpha: float) -> PooledBounds:
    """The bounds of the module docstring for errors ``err`` (T, N) = true - estimate in calibration windows
    ``window`` (T,), promised miscoverage ``alpha`` (two-sided).
    """
    err = np.asarray(err, float)
    window = np.asarray(window)
    if err.ndim != 2 or err.shape[0] == 0:
        raise ValueError("pooled_bounds: no calibration samples")
    if window.shape != (err.shape[0],):
        raise ValueError(f"pooled_bounds: {window.shape[0]} window labels for {err.shape[0]} rows")
    if not 0.0 < alpha < 1.0:
        raise ValueError(f"alpha {alpha} must be in (0, 1)")
    levels = _levels(alpha)
    miss = held_out_miss_rate(err, window, levels)
    ok = np.flatnonzero(miss <= alpha)
    j = int(ok[0]) if ok.size else levels.size - 1  # none holds: the largest score of the pool
    scale, q_hi, q_lo = _pooled_quantiles(err, levels[j:j + 1])
    return PooledBounds(upper=q_hi[0] * scale, lower=q_lo[0] * scale, level=float(levels[j]),
                        held_out_miss=float(miss[j]))
