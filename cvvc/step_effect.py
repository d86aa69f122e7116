"""Each regulator's tap step against the model: what one step did to the true voltages of the critical nodes it moves,
as a share of what the model's dV/dtap (eq. 4, the decisions' ``dv_dtap_pu``) says it does.

The agent predicts every decision's voltages with the model's tap sensitivities; a model that over- or under-states a
step's effect mis-predicts every move by that share. A recording holds the truth of every minute, so each *single*
step (one regulator, one step, between two consecutive minutes; no other tap, no bank and no plant's Q changed then or
in the minute before) is a measurement: at the critical nodes the step moves at least ``REACHED_SHARE`` as much as its
most moved one, the true change minus the change of the minute before (the load's trend, which the steps follow: a
regulator raises while the voltage falls) against the model's. The share is the least-squares slope over every such
step of the run (1: the model is right; 0.8: a step does 80 % of what the model says).

Pure numpy; ``cvvc report run`` feeds it a recording's truth frames (``cvvc.report.read_trace``).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Sequence
from typing import NamedTuple

import msgspec
import numpy as np

__all__ = ["PV_Q_STILL_KVAR", "REACHED_SHARE", "TapStepAccumulator", "TapStepEffect", "tap_steps_text"]

REACHED_SHARE = 0.5
"""A critical node is reached by a step when the model moves it at least this share of the step's most moved node (the
share ``training.critical.upstream_regulators`` calls a node downstream of a regulator)."""

PV_Q_STILL_KVAR = 1.0
"""A plant's Q changed by less than this between two minutes counts as unchanged [kvar] (set points are rounded to
0.001 kvar; a plant's Q follows its set point within the inverter's own noise)."""

_MINUTE_NS = 61_000_000_000  # consecutive truth frames: at most a minute (and a second of clock) apart


class TapStepEffect(msgspec.Struct, frozen=True, kw_only=True):
    """One regulator's single steps in a run: how many, and the true change at the critical nodes they reach as a
    share of the model's (least squares over every reached node of every step).
    """

    regulator: str
    steps: int
    share_of_model: float


class TapStepAccumulator:
    """Adds a run's truth frames in time order; :meth:`result` gives each regulator's :class:`TapStepEffect`.

    Parameters
    ----------
    node_names : every node's name, in the order of the truth's ``v_pu``.
    critical_nodes : the decisions' estimated nodes, in the order of the rows of ``dv_dtap_pu``.
    dv_dtap_pu : (len(critical_nodes), R) the model's voltage change per tap step up of each regulator [pu/step].
    regulator_ids : (R,) the regulators, in the order of the truth's ``taps``.
    """

    def __init__(self, node_names: Sequence[str], critical_nodes: Sequence[str], dv_dtap_pu: np.ndarray,
                 regulator_ids: Sequence[str]) -> None:
        index = {n: i for i, n in enumerate(node_names)}
        known = [j for j, n in enumerate(critical_nodes) if n in index]
        self._cols = np.array([index[critical_nodes[j]] for j in known], dtype=np.intp)
        model = np.asarray(dv_dtap_pu, float).reshape(len(critical_nodes), -1)
        self._model = model[known]
        self._ids = tuple(regulator_ids)
        n_reg = len(self._ids)
        self._num, self._den, self._steps = np.zeros(n_reg), np.zeros(n_reg), np.zeros(n_reg, dtype=np.int64)
        self._recent: deque[_Frame] = deque(maxlen=3)  # this frame and the two before

    def add(self, t_ns: int, v_pu: np.ndarray, taps: np.ndarray, pv_q_kvar: np.ndarray,
            cap_states: np.ndarray) -> None:
        """Add the next truth frame (every node's voltage [pu], the regulators' taps, the plants' Q [kvar], the banks'
        closed steps); a single step between the frame before and this one is measured.
        """
        self._recent.append(_Frame(int(t_ns), np.asarray(v_pu, float)[self._cols], np.asarray(taps, np.int64),
                                   np.asarray(pv_q_kvar, float), np.asarray(cap_states, np.int64)))
        if len(self._recent) == 3 and self._model.shape[1] == len(self._ids) == self._recent[-1].taps.size:
            self._measure(*self._recent)

    def _measure(self, z: _Frame, a: _Frame, b: _Frame) -> None:
        """One regulator's single step between ``a`` and ``b``, after a still minute ``z`` to ``a``."""
        if not (0 < a.t_ns - z.t_ns <= _MINUTE_NS and 0 < b.t_ns - a.t_ns <= _MINUTE_NS):
            return
        if not (_still(z, a) and np.array_equal(a.caps, b.caps) and _q_still(a, b)):
            return
        moved = b.taps - a.taps
        if np.count_nonzero(moved) != 1 or np.abs(moved).sum() != 1:
            return
        r = int(np.flatnonzero(moved)[0])
        model = self._model[:, r] * moved[r]
        if not np.any(model):
            return
        reached = np.abs(model) >= REACHED_SHARE * np.abs(model).max()
        true = (b.v - a.v) - (a.v - z.v)  # the step's change, the minute's trend taken out
        self._num[r] += float(true[reached] @ model[reached])
        self._den[r] += float(model[reached] @ model[reached])
        self._steps[r] += 1

    def result(self) -> tuple[TapStepEffect, ...]:
        """Each regulator with at least one single step, in the truth's order."""
        return tuple(TapStepEffect(regulator=rid, steps=int(self._steps[r]),
                                   share_of_model=float(self._num[r] / self._den[r]))
                     for r, rid in enumerate(self._ids) if self._steps[r])


class _Frame(NamedTuple):
    t_ns: int
    v: np.ndarray  # at the critical nodes [pu]
    taps: np.ndarray
    q_kvar: np.ndarray
    caps: np.ndarray


def _still(z: _Frame, a: _Frame) -> bool:
    """No tap, no bank and no plant's Q changed between two frames."""
    return np.array_equal(z.taps, a.taps) and np.array_equal(z.caps, a.caps) and _q_still(z, a)


def _q_still(a: _Frame, b: _Frame) -> bool:
    return a.q_kvar.shape == b.q_kvar.shape and bool(np.all(np.abs(b.q_kvar - a.q_kvar) <= PV_Q_STILL_KVAR))


def tap_steps_text(effects: Sequence[TapStepEffect], n: int = 8) -> str:
    """One line: each regulator's single steps as a share of the model's (the ``n`` with the most steps)."""
    top = sorted(effects, key=lambda e: -e.steps)[:n]
    text = ", ".join(f"{e.regulator} {e.share_of_model:.2f} ({e.steps} step{'s' if e.steps != 1 else ''})" for e in top)
    more = f" and {len(effects) - n} more" if len(effects) > n else ""
    return (f"tap steps against the model (single steps, the minute's trend taken out; the true change at the critical "
            f"nodes each reaches as a share of the model's dV/dtap): {text}{more}")
