"""Streaming evaluation metrics of the paper (IV.F): the same numbers as ``metrics_from_series``, step by step.

``MetricsAccumulator`` keeps a ring buffer of ``window_steps`` x nodes and a few sums, so a month of QSTS never
has to be held; our reading of IV.F is in ``metrics.py``'s docstring and ``docs/profiles-and-metrics.md``.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Unpack

import numpy as np

from simulator_bridge.simulation.metrics import (
    ANSI_RANGE_A_PU,
    TAP_RATE_WINDOW_STEPS,
    VIOLATION_TOLERANCE_PU,
    Metrics,
    MetricsConfig,
    MetricsError,
    MetricsSettings,
    MinuteCounts,
    outside_count,
    over_tap_rate,
    tap_rate_allowance,
    violation_pu,
)

__all__ = ["MetricsAccumulator", "phase_nodes", "zone_phase_nodes"]


def phase_nodes(node_names) -> np.ndarray:
    """(N,) bool: the nodes of phases 1-3 by their OpenDSS names (``bus.1`` .. ``bus.3``; a neutral's ``bus.4`` or a
    bus without a phase is not a voltage a customer sees).
    """
    return np.array([n.rpartition(".")[2] in ("1", "2", "3") for n in node_names], dtype=bool)


def zone_phase_nodes(engine) -> np.ndarray | None:
    """Indices of the nodes a feeder's voltages are judged on: the feeder zone's (downstream of the head meter)
    phase nodes (phases 1-3), of any object with ``node_names`` and ``node_in_feeder`` (a ``FeederEngine``); None
    when it has no zone (every node is judged). The transmission side, other feeders and neutral nodes are not
    this feeder's voltages (``docs/feeders.md``).
    """
    zone = getattr(engine, "node_in_feeder", None)
    if zone is None:
        return None
    return np.flatnonzero(np.asarray(zone, dtype=bool) & phase_nodes(engine.node_names))


class MetricsAccumulator:
    """Streaming IV.F metrics: feed one step at a time with :meth:`update`, read :meth:`result`.

    Memory is bounded: a ring buffer of ``window_steps`` x ``n_nodes`` voltages and a few sums.

    Parameters
    ----------
    n_nodes : int
        Number of nodes in every ``v_pu`` row.
    judged_nodes : sequence of int, optional
        Indices of the nodes judged (the feeder zone's, ``for_feeder``); None: every node. ``v_min_pu``,
        ``v_max_pu``, NVV and MVVM are then of these nodes, and ``mvvm_node`` indexes the whole ``v_pu`` row.
    **settings
        The keywords of ``metrics.MetricsSettings`` (shared with ``metrics_from_series``), as follows.
    regulator_ids, pv_ids : sequence of str
        Names of the regulators (columns of ``tap_changes``) and plants (entries of ``pv_q_kvar``).
    cost_per_tap : float or sequence of float
        Cost of one tap step, per regulator or one for all (the paper's ratio: 0.14).
    cost_per_kvar : float or sequence of float
        Cost of one kvar of set point per control interval, per plant or one for all.
    limits_pu : (float, float)
        Judged limits (v_min, v_max) [pu].
    window_steps : int
        Length of the rolling average [steps] (10 steps of 60 s = 10 minutes).
    step_s : int
        Step length [s].
    control_period_s : int
        Control interval the Q cost is charged per [s].
    capacitor_ids : sequence of str
        Names of the capacitor banks (entries of ``cap_switches``); none by default.
    cost_per_switch : float or sequence of float
        Cost of one switching operation, per bank or one for all.
    tap_delay_s : sequence of float, optional
        Each regulator's RegControl ``tapdelay`` [s]: the steps at which a regulator had moved faster than it
        allows (``metrics.over_tap_rate``) are counted; None: not judged.
    """

    def __init__(self, *, n_nodes: int, judged_nodes: Sequence[int] | np.ndarray | None = None,
                 **settings: Unpack[MetricsSettings]) -> None:
        self._cfg = MetricsConfig.make(n_nodes=n_nodes, **settings)
        cfg = self._cfg
        judged = None if judged_nodes is None else np.asarray(judged_nodes, dtype=np.intp)
        if judged is not None and (judged.ndim != 1 or judged.size == 0 or judged.min() < 0
                                   or judged.max() >= cfg.n_nodes):
            raise MetricsError(f"judged_nodes must be 1..{cfg.n_nodes} node indices below n_nodes = {cfg.n_nodes}")
        self._judged = judged
        n_judged = cfg.n_nodes if judged is None else judged.size
        self._v_judged = np.empty(n_judged)
        self._ring = np.zeros((cfg.window_steps, n_judged))
        self._n_steps = 0
        self._n_judged = 0
        self._mvvm = 0.0
        self._mvvm_node = -1
        self._nvv = 0
        self._steps_in_violation = 0
        self._v_min = np.inf
        self._v_max = -np.inf
        self._avg_min = np.inf
        self._avg_max = -np.inf
        self._taps = np.zeros(cfg.n_regs, dtype=np.int64)
        self._abs_q = np.zeros(cfg.n_pv)
        self._cap_sw = np.zeros(len(cfg.capacitor_ids), dtype=np.int64)
        self._avg = np.empty(n_judged)  # the present rolling average, rewritten in place every step
        self._minutes = [0, 0, 0, 0]  # every step on its own: MinuteCounts' fields
        # the latest steps' tap moves (a ring), against what the RegControls' tapdelays allow
        self._allowance = None if cfg.tap_delay_s is None else tap_rate_allowance(cfg.tap_delay_s, cfg.step_s)
        self._moves = np.zeros((0 if self._allowance is None else TAP_RATE_WINDOW_STEPS, cfg.n_regs), dtype=np.int64)
        self._over_rate = np.zeros(cfg.n_regs, dtype=np.int64)

    @property
    def n_steps(self) -> int:
        """Steps accumulated so far."""
        return self._n_steps

    def update(self, v_pu: np.ndarray, tap_changes: np.ndarray, pv_q_kvar: np.ndarray,
               cap_switches: np.ndarray | None = None) -> None:
        """Add one step.

        Parameters
        ----------
        v_pu : ndarray, shape (n_nodes,)
            Every node's voltage [pu].
        tap_changes : ndarray of int, shape (R,)
            Tap steps each regulator moved during the step (>= 0).
        pv_q_kvar : ndarray, shape (K,)
            Each plant's reactive power during the step [kvar] (either sign).
        cap_switches : ndarray of int, shape (C,), optional
            Switching operations of each capacitor bank during the step (>= 0); None: no bank switched.
        """
        cfg = self._cfg
        v, taps, q, v_lo, v_hi = cfg.check_step(v_pu, tap_changes, pv_q_kvar)
        if cap_switches is not None:
            self._cap_sw += cfg.check_switches(cap_switches)
        if self._judged is not None:  # the feeder zone's nodes only (checked whole above)
            v = np.take(v, self._judged, out=self._v_judged)
            v_lo, v_hi = float(v.min()), float(v.max())
        w = cfg.window_steps
        self._ring[self._n_steps % w] = v
        self._n_steps += 1
        self._count_minute(v, v_lo, v_hi)
        self._v_min = min(self._v_min, v_lo)
        self._v_max = max(self._v_max, v_hi)
        self._taps += taps
        if self._allowance is not None:
            self._moves[:-1] = self._moves[1:]
            self._moves[-1] = taps
            self._over_rate += over_tap_rate(self._moves[-min(self._n_steps, len(self._moves)):], self._allowance)
        self._abs_q += np.abs(q)
        if self._n_steps < w:
            return
        # ``self._ring.mean(axis=0)`` without its temporaries: the same sum (rows added in ring order) and the
        # same division, hence the same numbers.
        avg = np.add.reduce(self._ring, axis=0, out=self._avg)
        np.true_divide(avg, w, out=avg)
        a_lo, a_hi = float(avg.min()), float(avg.max())
        self._n_judged += 1
        self._avg_min = min(self._avg_min, a_lo)
        self._avg_max = max(self._avg_max, a_hi)
        lo, hi = cfg.limits_pu
        # Rounding is monotonic, so the largest ``avg - hi`` is ``max(avg) - hi`` and the largest ``lo - avg`` is
        # ``lo - min(avg)``: when neither exceeds the tolerance no node violates, and violation_pu is not needed.
        if a_hi - hi <= VIOLATION_TOLERANCE_PU and lo - a_lo <= VIOLATION_TOLERANCE_PU:
            return
        viol = violation_pu(avg, cfg.limits_pu)
        n_out = int(np.count_nonzero(viol > 0.0))
        if n_out:
            self._nvv += n_out
            self._steps_in_violation += 1
            worst = int(np.argmax(viol))
            if viol[worst] > self._mvvm:
                self._mvvm = float(viol[worst])
                self._mvvm_node = worst if self._judged is None else int(self._judged[worst])

    def _count_minute(self, v: np.ndarray, v_lo: float, v_hi: float) -> None:
        """Count this step's judged nodes outside the optimization limits and ANSI Range A (nothing to count when
        its extremes are inside both).
        """
        for k, limits in ((0, self._cfg.opt_limits_pu), (2, ANSI_RANGE_A_PU)):
            lo, hi = limits
            if v_hi - hi <= VIOLATION_TOLERANCE_PU and lo - v_lo <= VIOLATION_TOLERANCE_PU:
                continue
            n = int(outside_count(v, limits))
            self._minutes[k] += n
            self._minutes[k + 1] += n > 0

    @classmethod
    def for_feeder(cls, device_map, engine, *, step_s: int | None = None) -> MetricsAccumulator:
        """The accumulator of a feeder: its nodes, devices, costs and judged limits from the device map.

        ``engine`` is any object with ``node_names``, ``regulator_ids`` and ``pv_ids`` (a ``FeederEngine``);
        ``step_s`` defaults to the device map's step; each regulator's ``tapdelay`` is its RegControl's
        (``engine.reg_controls``, when it has them). When it has ``node_in_feeder`` (the feeder zone: downstream
        of the head meter), only the zone's phase nodes (phases 1-3) are judged: the transmission side, other
        feeders and neutral nodes are not this feeder's voltages (``docs/feeders.md``).
        """
        f = device_map.feeder
        judged = zone_phase_nodes(engine)
        controls = getattr(engine, "reg_controls", None)  # the map's regulators first
        n_reg = len(engine.regulator_ids)
        return cls(
            n_nodes=len(engine.node_names), regulator_ids=list(engine.regulator_ids), pv_ids=list(engine.pv_ids),
            cost_per_tap=[r.cost_per_tap for r in device_map.regulator],
            cost_per_kvar=[p.cost_per_kvar for p in device_map.pv],
            limits_pu=tuple(f.judged_limits_pu), step_s=f.step_s if step_s is None else int(step_s),
            control_period_s=f.control_period_s, judged_nodes=judged,
            capacitor_ids=list(getattr(engine, "capacitor_ids", ())),
            cost_per_switch=[c.cost_per_switch for c in device_map.capacitor],
            opt_limits_pu=tuple(f.optimization_limits_pu),
            tap_delay_s=None if controls is None else [c.tap_delay_s for c in controls[:n_reg]],
        )

    def result(self) -> Metrics:
        """The metrics of every step so far (the accumulator can go on afterwards)."""
        return self._cfg.result(
            n_steps=self._n_steps,
            n_steps_judged=self._n_judged,
            mvvm_pu=self._mvvm,
            mvvm_node=self._mvvm_node,
            nvv=self._nvv,
            steps_in_violation=self._steps_in_violation,
            v_min_max=(self._v_min, self._v_max) if self._n_steps else None,
            v_avg_min_max=(self._avg_min, self._avg_max) if self._n_judged else None,
            taps=self._taps,
            abs_q_kvar_steps=self._abs_q,
            cap_switches=self._cap_sw,
            minute_counts=MinuteCounts(opt_nodes=self._minutes[0], opt_steps=self._minutes[1],
                                       ansi_nodes=self._minutes[2], ansi_steps=self._minutes[3]),
            steps_over_tap_rate=None if self._allowance is None else self._over_rate,
        )
