"""The drift margin: room in the limits for the load's drift until the next decision (beyond the paper, an option).

The optimization holds the limits at the decision's instant, and the load moves on until the next decision. A
decision that puts a node on its limit during a morning ramp leaves it past the limit for most of the interval (IEEE
13, first 3 winter days: the 1-minute minimum 0.967 pu against the optimization limit 0.975 and no control's 0.972).

A node's drift over an interval is how far its estimate at a decision lies from what the decision one control period
before predicted for it once its actions were applied. Where the last two intervals drifted the same way (a ramp),
the smaller of the two drifts is the margin on that side, capped like the PV variability margin. One interval's drift
alone moved taps for ramps that had ended (epri-k1, first 3 days of fall: 5 -> 10 tap changes; with two in a row, 6).
Measured on the shared feeders in docs/method.md ("Drift margin and the deadband's hold"): not on by default.
"""

from __future__ import annotations

import numpy as np

__all__ = ["DriftMargin"]


class DriftMargin:
    """The critical nodes' drift margins, from each decision's prediction and the next decision's estimate.

    ``predicted`` takes a decision's prediction (``forget`` a decision that predicted nothing: a hold);
    ``margins`` the next decision's estimate, and gives ``(fall, rise)`` [pu].
    """

    def __init__(self, period_ns: int, cap_pu: float) -> None:
        self._period_ns = int(period_ns)
        self._cap_pu = float(cap_pu)
        self._last: tuple[int, np.ndarray] | None = None  # (t_ns, prediction) of the last decision
        self._drift: np.ndarray | None = None  # the drift over the interval before the latest one

    def predicted(self, t_ns: int, v_pred_pu: np.ndarray) -> None:
        """The critical nodes' voltages the decision of step ``t_ns`` predicts once its actions are applied [pu]."""
        self._last = (int(t_ns), np.array(v_pred_pu, float))

    def forget(self) -> None:
        """The last decision predicted nothing (a hold, case A): the next interval's drift is not measured."""
        self._last = None

    def margins(self, t_ns: int, v0_pu: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        """``(fall, rise)`` margins of the critical nodes whose estimate at step ``t_ns`` is ``v0_pu`` [pu], each
        in ``[0, cap]``; None until two intervals in a row were measured (after a hold or a gap).
        """
        last, before = self._last, self._drift
        self._drift = None
        if last is None:
            return None
        t_last, v_pred = last
        v0 = np.asarray(v0_pu, float)
        if t_ns - t_last != self._period_ns or v_pred.shape != v0.shape:
            return None
        d = self._drift = v0 - v_pred
        if before is None or before.shape != d.shape:
            return None
        return (np.clip(np.minimum(-d, -before), 0.0, self._cap_pu),
                np.clip(np.minimum(d, before), 0.0, self._cap_pu))
