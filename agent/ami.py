"""AMI meter readings at critical nodes: an explicit option beyond the paper (``[[meter]]`` in the device map).

A few critical nodes deep in customer secondaries follow their own customers' load, which no feeder-level
measurement sees (epri-ckt24: three 240 V secondaries hold 97 % of the estimation error). An AMI meter there reads
the node's voltage every ``interval_s`` (``schemas.messages.MeterFrame``). The agent keeps its own estimate of every
critical node at each decision; at a later decision ``t`` a metered node's estimate becomes

    v(t) = reading(t_r) + (est(t) - est(t_r))

(the reading's offset to the estimate at the reading's step ``t_r``, carried forward: ``training.ami`` measures the
same rule offline), while the reading is at most ``max_age_s`` old. Its bounds are then the model's AMI bounds
(``EstimateBounds.ami_upper_pu``/``ami_lower_pu``, calibrated on the training year's held-out minutes with a reading
every ``ami_interval_s``), when the model has them and the meter reads at least that often; otherwise the node keeps
its ordinary bounds. Readings of nodes that are not critical, from the future or older than the newest are counted
and ignored.
"""

from __future__ import annotations

import dataclasses
from collections import Counter, OrderedDict

import numpy as np

from agent.state import GridState
from regression.model import CvvcModel
from schemas import messages as m

__all__ = ["AmiReadings"]

#: Decisions whose estimates are kept to pair with readings (a day of 5-minute control periods).
HISTORY_STEPS = 288
#: Future time a reading may carry (clock skew between meter and agent) [ns].
FUTURE_TOLERANCE_NS = 60 * 1_000_000_000


class AmiReadings:
    """The latest meter reading of each metered critical node and the estimates it is compared with.

    Parameters
    ----------
    model : the model (critical-node names and, optionally, AMI bounds).
    max_age_multiple : a reading serves until it is this many meter intervals old.
    """

    def __init__(self, model: CvvcModel, max_age_multiple: float = 2.0) -> None:
        self._index = {c.name.lower(): i for i, c in enumerate(model.critical_nodes)}
        n = len(model.critical_nodes)
        b = model.bounds
        self.interval_s = 0 if b is None else int(b.ami_interval_s)
        self._lo = None if b is None or not b.ami_lower_pu else np.asarray(b.ami_lower_pu, float)
        self._hi = None if b is None or not b.ami_upper_pu else np.asarray(b.ami_upper_pu, float)
        self._max_age_multiple = float(max_age_multiple)
        self._period_ns = int(model.control_period_s) * 1_000_000_000  # a reading pairs with a decision this close
        self.latest: dict[int, tuple[int, float, int]] = {}  # node -> (t_ns, v_pu, interval_s)
        self._history: OrderedDict[int, np.ndarray] = OrderedDict()  # decision t_ns -> estimate (before AMI)
        self.fresh = np.zeros(n, bool)  # nodes whose estimate a reading corrected at the last decision
        self.tight = np.zeros(n, bool)  # ... and whose AMI bounds apply
        self.counts: Counter[str] = Counter()

    def add(self, frame: m.MeterFrame, now_t_ns: int | None = None) -> str | None:
        """Keep a reading; why it is ignored (counted), or None."""
        i = self._index.get(frame.node.lower())
        if i is None:
            self.counts["ami_not_critical"] += 1
            return f"meter {frame.meter_id}: node {frame.node} is not a critical node of the model"
        if not 0.5 <= frame.v_pu <= 1.5:
            self.counts["ami_out_of_range"] += 1
            return f"meter {frame.meter_id}: reading {frame.v_pu} pu outside 0.5..1.5"
        if now_t_ns is not None and frame.t_ns > now_t_ns + FUTURE_TOLERANCE_NS:
            self.counts["ami_future"] += 1
            return f"meter {frame.meter_id}: reading from the future (t_ns {frame.t_ns})"
        last = self.latest.get(i)
        if last is not None and frame.t_ns <= last[0]:
            self.counts["ami_not_newer"] += 1
            return f"meter {frame.meter_id}: reading not newer than the one kept"
        self.latest[i] = (int(frame.t_ns), float(frame.v_pu), int(frame.interval_s))
        self.counts["ami_readings"] += 1
        return None

    def correct(self, t_ns: int, state: GridState) -> GridState:
        """``state`` with each metered node's estimate moved by its latest usable reading (see the module)."""
        self._history[t_ns] = state.v0_pu.copy()
        while len(self._history) > HISTORY_STEPS:
            self._history.popitem(last=False)
        self.fresh[:] = False
        self.tight[:] = False
        if not self.latest:
            return state
        v = state.v0_pu.copy()
        for i, (t_r, v_r, interval_s) in self.latest.items():
            age = t_ns - t_r
            if age < 0 or age > self._max_age_multiple * interval_s * 1_000_000_000:
                continue
            est_r = self._estimate_at(t_r)
            if est_r is None:
                continue  # no decision at or shortly before the reading: nothing to compare it with
            v[i] = v_r + (state.v0_pu[i] - est_r[i])
            self.fresh[i] = True
            self.tight[i] = self._lo is not None and 0 < interval_s <= self.interval_s
        self.counts["ami_used"] += int(self.fresh.sum())
        return dataclasses.replace(state, v0_pu=v)

    def bounds(self, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(lo, hi)`` with the AMI bounds of the nodes a reading corrected at the last decision (never wider)."""
        if self._lo is None or self._hi is None or not self.tight.any():
            return lo, hi
        return (np.where(self.tight, np.minimum(lo, self._lo), lo), np.where(self.tight, np.minimum(hi, self._hi), hi))

    def _estimate_at(self, t_r: int) -> np.ndarray | None:
        """The estimate of the latest decision at or before ``t_r``, if within one control period of it."""
        for t, v in reversed(self._history.items()):
            if t <= t_r:
                return v if t_r - t <= self._period_ns else None
        return None
