"""A regulator's reading fitted on the feeder head's load: noise filtering without lag (beyond the paper).

Issue 17, item 7: SCADA-class noise of 1 % is 1.2 V on a 120 V-base regulator reading. The mean of the readings of
one control period (``AgentSettings.reading_window_s``, five 1-minute frames) leaves 0.54 V, more than half a tap
step (0.375 V), the margin eq. (8) leaves between the band edge and the desired tap; a longer mean lags the load
(a 10-minute mean let the noiseless rural winter week violate). The head meter's P and Q (PMU class) carry the
load's variation without that noise, so the reading over a longer window at unchanged taps is regressed on them,

    v_k = a + b P_k + c Q_k + e_k,

and evaluated at the present head: with ``n`` readings the fitted value's noise is about ``sqrt(3 / n)`` of one
reading's (0.27 V for an hour), and a load change moves it at once. A column that does not vary (a flat night) is
left out; the present reading is one of the fitted points, so the fit is never extrapolated.
"""

from __future__ import annotations

import numpy as np

__all__ = ["fitted_reading_v120"]


def fitted_reading_v120(v_v120: np.ndarray, p_kw: np.ndarray, q_kvar: np.ndarray, p_now_kw: float,
                        q_now_kvar: float, *, min_points: int = 8) -> float | None:
    """A regulator reading regressed on the head's P and Q, evaluated at the present head (module docstring).

    Parameters
    ----------
    v_v120 : (n,) readings at unchanged taps [V on the 120 V base].
    p_kw, q_kvar : (n,) the head's total P [kW] and Q [kvar] at the same instants.
    p_now_kw, q_now_kvar : the head's P [kW] and Q [kvar] now.
    min_points : fewer readings than this give None (the caller keeps its plain mean).

    Returns
    -------
    The fitted reading now [V on the 120 V base], or None (too few readings, or not finite).
    """
    v = np.asarray(v_v120, float)
    n = v.size
    if n < min_points or n != np.size(p_kw) or n != np.size(q_kvar):
        return None
    columns, now = [np.ones(n)], [1.0]
    for x, x_now in ((np.asarray(p_kw, float), p_now_kw), (np.asarray(q_kvar, float), q_now_kvar)):
        spread = float(x.std())
        if spread > 1e-6 * max(1.0, float(np.abs(x).max())):
            columns.append((x - x.mean()) / spread)
            now.append((x_now - float(x.mean())) / spread)
    coef, *_ = np.linalg.lstsq(np.column_stack(columns), v, rcond=None)
    value = float(np.asarray(now) @ coef)
    return value if np.isfinite(value) else None
