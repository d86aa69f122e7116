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

Identity from the device map, never from the payload: a reading counts only from a meter the map declares
(``[[meter]]``, ``AgentSettings.meters``), for that meter's node, and it serves for the *map's* interval of that
meter (a reading's own ``interval_s`` is ignored: a forged 86,400 s would let one reading serve two days). A map
without meters takes no reading at all. A reading stamped more than ``FUTURE_TOLERANCE_NS`` (5 s) ahead of the newest
frame is refused ``future``.
"""

from __future__ import annotations

import dataclasses
from collections import Counter, OrderedDict
from collections.abc import Iterable

import numpy as np

from agent.state import GridState
from regression.model import CvvcModel
from schemas import messages as m
from schemas.devicemap import MeterSpec

__all__ = ["AmiReadings", "REFUSED_KINDS"]

#: Decisions whose estimates are kept to pair with readings (a day of 5-minute control periods).
HISTORY_STEPS = 288
#: How far ahead of the newest frame a reading may be stamped [ns]: 5 s, as the agent's default clock tolerance
#: (``AgentSettings.clock_tolerance_s``). A step's readings follow its head frame, so a meter of the feeder's clock is
#: never ahead; a reading whose step's head frame was lost is refused ``future`` (the next one serves). Up to a whole
#: 1-minute step (the former tolerance), a forged reading stamped 59 s ahead stood as the meter's newest.
FUTURE_TOLERANCE_NS = 5 * 1_000_000_000
#: Why a reading is refused (counted with the agent's rejected inputs), by the kind ``add`` returns; the other
#: kinds (a declared meter at a node that is not critical) are only counted in ``counts``.
REFUSED_KINDS = {"ami_unknown_meter": "unknown_device", "ami_wrong_node": "unknown_device",
                 "ami_out_of_range": "implausible", "ami_future": "future", "ami_not_newer": "out_of_order"}


class AmiReadings:
    """The latest meter reading of each metered critical node and the estimates it is compared with.

    Parameters
    ----------
    model : the model (critical-node names and, optionally, AMI bounds).
    meters : the device map's meters (``[[meter]]``); readings of any other meter are refused.
    max_age_multiple : a reading serves until it is this many of its meter's (map) intervals old.
    future_tolerance_ns : how far ahead of the newest frame a reading may be stamped [ns].
    """

    def __init__(self, model: CvvcModel, meters: Iterable[MeterSpec] = (), max_age_multiple: float = 2.0,
                 future_tolerance_ns: int = FUTURE_TOLERANCE_NS) -> None:
        self._meters = {x.id: x for x in meters}
        self._future_ns = int(future_tolerance_ns)
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

    def add(self, frame: m.MeterFrame, now_t_ns: int | None = None) -> tuple[str, str] | None:
        """Keep a reading; or ``(kind, why)`` it is ignored (counted in ``counts`` under ``kind``; the kinds of
        ``REFUSED_KINDS`` are refusals). ``now_t_ns``: the newest frame's time [ns], None before the first.
        """
        meter = self._meters.get(frame.meter_id)
        if meter is None:
            return self._ignore("ami_unknown_meter", f"meter {frame.meter_id[:64]!r} is not in the device map")
        if frame.node.lower() != meter.node.lower():
            return self._ignore("ami_wrong_node", f"meter {meter.id}: node {frame.node[:64]!r}, the map says "
                                f"{meter.node!r}")
        i = self._index.get(frame.node.lower())
        if i is None:
            return self._ignore("ami_not_critical", f"meter {meter.id}: node {frame.node} is not a critical node "
                                "of the model")
        if not 0.5 <= frame.v_pu <= 1.5:
            return self._ignore("ami_out_of_range", f"meter {meter.id}: reading {frame.v_pu} pu outside 0.5..1.5")
        if now_t_ns is not None and frame.t_ns > now_t_ns + self._future_ns:
            return self._ignore("ami_future", f"meter {meter.id}: reading from the future (t_ns {frame.t_ns}, "
                                f"newest frame {now_t_ns})")
        last = self.latest.get(i)
        # a kept reading from the future (taken before the first frame dated it) never locks the meter out
        if last is not None and frame.t_ns <= last[0] and (now_t_ns is None or last[0] <= now_t_ns + self._future_ns):
            return self._ignore("ami_not_newer", f"meter {meter.id}: reading not newer than the one kept")
        self.latest[i] = (int(frame.t_ns), float(frame.v_pu), int(meter.interval_s))  # the map's interval
        self.counts["ami_readings"] += 1
        return None

    def _ignore(self, kind: str, why: str) -> tuple[str, str]:
        self.counts[kind] += 1
        return kind, why

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
