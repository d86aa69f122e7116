"""Live accuracy: the agent's estimates and calibrated bounds judged against the truth of the same step.

Every ``Decision`` lists, per critical node, the estimate ``v`` it acted on and the bounds it promised: the true
voltage is expected in ``[v - bound_low, v + bound_high]`` [pu]. The bridge (the only process with the truth) and
``cvvc report run`` (from a recording's truth frames) feed each decision's estimates and the truth of its step to a
:class:`LiveAccuracyAccumulator`; :class:`LiveAccuracy` is what a run reports:

- the error ``estimate - truth`` at the critical nodes over every (decision, node): mean, RMSE, largest, and the
  share within ``WITHIN_PU`` (the offline accuracy report's figures, ``training.accuracy``, live);
- the bounds' realised miss rate: the share of (decision, node) with bounds whose true voltage is outside them,
  split into below (``true < v - bound_low``) and above (``true > v + bound_high``);
- the extremes' capture: the share of decisions whose true highest and lowest zone nodes are both estimated;
- per node, the same counts, so the worst node can be named and plotted.

Pure numpy; nothing here knows Zenoh or files.
"""

from __future__ import annotations

from collections.abc import Sequence

import msgspec
import numpy as np

__all__ = ["HOLD_FACTOR", "MISS_TOLERANCE_PU", "WITHIN_PU", "LiveAccuracy", "LiveAccuracyAccumulator", "NodeAccuracy"]

HOLD_FACTOR = 2.0
"""The bounds hold when their realised miss rate is at most this many times the rate they promise."""

WITHIN_PU = 0.01
"""The accuracy band of the offline report (``training.accuracy.WITHIN_PU``) [pu]."""

MISS_TOLERANCE_PU = 1e-6
"""A true voltage this close outside the bounds is inside [pu]: a ``Decision`` carries its estimates and bounds
rounded to 6 decimals and a ``TruthPack`` its voltages as float32 (6e-8 pu), so a node whose bounds are 0 (a
regulator's secondary, corrected by its own reading) would otherwise miss by rounding alone."""


class NodeAccuracy(msgspec.Struct, frozen=True, kw_only=True):
    """One critical node's live figures: samples, RMSE [pu] and bound misses (below, above)."""

    node: str
    samples: int
    rmse_pu: float
    misses_below: int
    misses_above: int


class LiveAccuracy(msgspec.Struct, frozen=True, kw_only=True):
    """The agent's estimates against the truth over a run (see the module docstring).

    ``decisions``: decisions with estimates judged; ``samples``: (decision, node) pairs. Errors are
    ``estimate - truth`` [pu]. ``bound_samples``: the pairs with bounds (a model without calibrated bounds sends
    none); ``bound_misses = misses_below + misses_above``; ``bound_miss_rate`` their share (0 without bounds).
    ``extremes_captured``: share of decisions whose true zone maximum and minimum nodes are both estimated.
    ``worst``: the node with the most bound misses (else the largest RMSE). ``promised_miss_rate``: the bounds'
    calibrated miscoverage, when the caller knows it (the model's ``bounds.alpha``), else None.
    """

    decisions: int = 0
    samples: int = 0
    bias_pu: float = 0.0
    rmse_pu: float = 0.0
    max_abs_pu: float = 0.0
    within_001: float = 0.0
    bound_samples: int = 0
    bound_misses: int = 0
    misses_below: int = 0
    misses_above: int = 0
    bound_miss_rate: float = 0.0
    extremes_captured: float = 0.0
    worst: NodeAccuracy | None = None
    promised_miss_rate: float | None = None

    def bounds_hold(self, factor: float = HOLD_FACTOR) -> bool | None:
        """Whether the realised miss rate is at most ``factor`` x the promised one (None: nothing to judge)."""
        if self.promised_miss_rate is None or self.bound_samples == 0:
            return None
        return self.bound_miss_rate <= factor * self.promised_miss_rate


class LiveAccuracyAccumulator:
    """Adds decisions one at a time; :meth:`result` gives the :class:`LiveAccuracy` so far.

    Parameters
    ----------
    node_names : every node's name, in the order of the truth's ``v_pu``.
    zone_nodes : indices of the nodes judged for the extremes (the feeder zone's phase nodes); None: every node.
    """

    def __init__(self, node_names: Sequence[str], zone_nodes: Sequence[int] | np.ndarray | None = None) -> None:
        self._index = {n: i for i, n in enumerate(node_names)}
        self._zone = None if zone_nodes is None else np.asarray(zone_nodes, dtype=np.intp)
        self._decisions = self._samples = self._within = 0
        self._sum = self._sum2 = self._max_abs = 0.0
        self._bound_samples = self._below = self._above = self._captured = 0
        self._per_node: dict[str, list[float]] = {}  # name -> [samples, sum of squared errors, below, above]
        self.unknown_nodes = 0  # estimates of a node the truth does not have (not judged)

    def add(self, nodes: Sequence[str], v_pu: np.ndarray, bound_low_pu: np.ndarray, bound_high_pu: np.ndarray,
            v_true_pu: np.ndarray) -> None:
        """Judge one decision.

        Parameters
        ----------
        nodes : the estimated nodes' names.
        v_pu, bound_low_pu, bound_high_pu : (len(nodes),) the estimates and their bounds as applied [pu] (all 0: the
            model has no bounds).
        v_true_pu : every node's true voltage at the decision's step [pu], in ``node_names`` order.
        """
        idx = [self._index.get(n, -1) for n in nodes]
        keep = np.array([i >= 0 for i in idx], dtype=bool)
        self.unknown_nodes += int((~keep).sum())
        if not keep.any():
            return
        cols = np.array([i for i in idx if i >= 0], dtype=np.intp)
        v = np.asarray(v_pu, dtype=float)[keep]
        lo, hi = np.asarray(bound_low_pu, dtype=float)[keep], np.asarray(bound_high_pu, dtype=float)[keep]
        truth = np.asarray(v_true_pu, dtype=float)
        err = v - truth[cols]
        # a model without calibrated bounds sends zeros for every node; one with them may have 0 at a node (a
        # regulator's secondary, corrected by its own reading)
        has_bounds = np.full(v.size, bool(np.any(lo > 0.0) or np.any(hi > 0.0)))
        below = has_bounds & (truth[cols] < v - lo - MISS_TOLERANCE_PU)
        above = has_bounds & (truth[cols] > v + hi + MISS_TOLERANCE_PU)
        self._decisions += 1
        self._samples += err.size
        self._sum += float(err.sum())
        self._sum2 += float((err ** 2).sum())
        self._max_abs = max(self._max_abs, float(np.abs(err).max()))
        self._within += int((np.abs(err) <= WITHIN_PU).sum())
        self._bound_samples += int(has_bounds.sum())
        self._below += int(below.sum())
        self._above += int(above.sum())
        zone = truth if self._zone is None else truth[self._zone]
        zone_idx = np.arange(truth.size) if self._zone is None else self._zone
        estimated = set(cols.tolist())
        if int(zone_idx[np.argmax(zone)]) in estimated and int(zone_idx[np.argmin(zone)]) in estimated:
            self._captured += 1
        kept_names = [n for n, k in zip(nodes, keep, strict=True) if k]
        for j, name in enumerate(kept_names):
            acc = self._per_node.setdefault(name, [0.0, 0.0, 0.0, 0.0])
            acc[0] += 1
            acc[1] += float(err[j] ** 2)
            acc[2] += float(below[j])
            acc[3] += float(above[j])

    def result(self, promised_miss_rate: float | None = None) -> LiveAccuracy:
        """The figures so far; ``promised_miss_rate`` the bounds' calibrated miscoverage, if known."""
        if not self._samples:
            return LiveAccuracy(promised_miss_rate=promised_miss_rate)
        n = self._samples
        misses = self._below + self._above
        return LiveAccuracy(
            decisions=self._decisions, samples=n, bias_pu=self._sum / n, rmse_pu=float(np.sqrt(self._sum2 / n)),
            max_abs_pu=self._max_abs, within_001=self._within / n, bound_samples=self._bound_samples,
            bound_misses=misses, misses_below=self._below, misses_above=self._above,
            bound_miss_rate=misses / self._bound_samples if self._bound_samples else 0.0,
            extremes_captured=self._captured / self._decisions, worst=self.worst(),
            promised_miss_rate=promised_miss_rate)

    def worst(self) -> NodeAccuracy | None:
        """The node with the most bound misses (ties, and runs without misses: the largest RMSE)."""
        if not self._per_node:
            return None
        name, acc = max(self._per_node.items(), key=lambda kv: (kv[1][2] + kv[1][3], kv[1][1] / kv[1][0]))
        return NodeAccuracy(node=name, samples=int(acc[0]), rmse_pu=float(np.sqrt(acc[1] / acc[0])),
                            misses_below=int(acc[2]), misses_above=int(acc[3]))
