"""A regulator's reading fitted on the feeder head's readings: noise filtering without lag (beyond the paper, opt-in).

SCADA-class noise of 1 % is 1.2 V on a 120 V-base regulator reading. The mean of the readings of
one control period (``AgentSettings.reading_window_s``, five 1-minute frames) leaves 0.54 V, more than half a tap
step (0.375 V), the margin eq. (8) leaves between the band edge and the desired tap; a longer mean lags the load
(a 10-minute mean let the noiseless rural winter week violate). The head meter's P, Q and voltage (PMU class)
carry the load's and the source's variation without that noise, so the readings of a longer window
(``AgentSettings.reading_fit_s``), each moved to the present tap by its tap difference times the tap step, are
regressed on them,

    v_k = a + b P_k + c Q_k + d V_head,k + e_k,

and evaluated at the present head: with ``n`` readings the fitted value's noise is about ``sqrt(4 / n)`` of one
reading's (0.31 V for an hour), and a load change moves it at once. A column that does not vary (a flat night) is
left out; the present reading is one of the fitted points, so the fit is never extrapolated. Upstream regulators'
tap changes are not modelled (the fit absorbs them over the window).

Measured (docs/results.md, "Robust by default"): rural winter week, 1 % SCADA noise, NVV 10 -> 0 and tap changes
207 -> 86 (noiseless: 24 -> 29); but the summer week with noise went from NVV 0 to 15, so it stays off by default.
"""

from __future__ import annotations

import numpy as np

__all__ = ["fitted_reading_v120"]


def fitted_reading_v120(v_v120: np.ndarray, x: np.ndarray, x_now: np.ndarray, *,
                        min_points: int = 8) -> float | None:
    """A regulator reading regressed on the head's readings, evaluated at the present head (module docstring).

    Parameters
    ----------
    v_v120 : (n,) readings at the present tap [V on the 120 V base].
    x : (n, k) the head's readings at the same instants (P [kW], Q [kvar], the phase's voltage [V], ...).
    x_now : (k,) the head's readings now, same units.
    min_points : fewer readings than this give None (the caller keeps its plain mean).

    Returns
    -------
    The fitted reading now [V on the 120 V base], or None (too few readings, or not finite).
    """
    v = np.asarray(v_v120, float)
    xs = np.asarray(x, float).reshape(v.size, -1) if v.size else np.zeros((0, 0))
    n = v.size
    if n < min_points:
        return None
    columns, now = [np.ones(n)], [1.0]
    for col, col_now in zip(xs.T, np.asarray(x_now, float), strict=True):
        spread = float(col.std())
        if spread > 1e-6 * max(1.0, float(np.abs(col).max())):  # a column that does not vary is left out
            columns.append((col - col.mean()) / spread)
            now.append((col_now - float(col.mean())) / spread)
    coef, *_ = np.linalg.lstsq(np.column_stack(columns), v, rcond=None)
    value = float(np.asarray(now) @ coef)
    return value if np.isfinite(value) else None
