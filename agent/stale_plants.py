"""A PV plant behind a stale frame: its present output and Q as the controller takes them (beyond the paper).

When a plant's frames are lost the runtime lets its last good frame stand in (``AgentSettings.
last_good_s``). That frame's P is from before the loss, its Q from before the commands sent since. In the rural
winter week with 5 % of the frames lost in 10-minute outages the
11:55 decision of 19 January stood on pv3's frame of 11:49: its P from before a midday rise (the estimate of
b0138.1 0.027 pu low) and its Q of -373 kvar where the 11:50 command had taken it to -895 kvar. The QP then moved
pv3 to -39 kvar, a 856 kvar rise it counted as 334, and b0138.1 reached 1.07 pu.

What this module does for a plant whose frame is not its own (``MeasurementSnapshot.pv_fresh`` False):

- **P projected from the fresh plants** (``project_stale_p_kw``): nearby plants share the sky, so the stale plant's
  P is its P at its last fresh step times the ratio of the fresh plants' P now to theirs at that step.
- **Q from our last command** while that command is in force: the plant follows it; the stale frame's Q is
  the one it had before.
- **Not moved towards a higher voltage**: its Q may go down (absorb more) but not up from that Q; with the
  estimate's inputs unsure, the decision must not lean on the plant to raise the voltage.
- **Its P's uncertainty in the upper limits** (``stale_rise_pu``): the PV variability margin (``regression.
  estimator.pv_variability_margins_pu``, at most ``pv_margin_cap_pu``) gets, on top, the rise the stale plants
  would make by going back to their highest P of the margin window, up to 1.5 times that cap. The projection alone
  missed a cloud over one plant: in the same week pv3 stood at 440 kW in its last frame, was projected at 373 kW
  from the two others and was at 1,161 kW when its frames came back; the 16:55 estimate of b0138.1 was 0.03 pu low
  and its 10-minute mean reached 1.0500 pu (NVV 1 with the three points above, 0 with this one).
"""

from __future__ import annotations

import numpy as np

from regression.estimator import pv_variability_margins_pu

__all__ = ["StalePlants", "project_stale_p_kw", "stale_rise_pu"]

#: A group of fresh plants producing less than this share of its rating is dark: the ratio is not used [-].
_DARK_SHARE = 0.02
#: The margin with the stale plants' rise reaches at most this many times the PV variability margin's cap [-]
#: (2 took the rural 20 % outage weeks from 98 and 100 tap changes to 138 and 137; 1.5: winter 70, NVV 0).
STALE_RISE_CAP_FACTOR = 1.5


def project_stale_p_kw(p_then_kw: float, others_then_kw: np.ndarray, others_now_kw: np.ndarray,
                       others_kva: np.ndarray, kva: float) -> float | None:
    """A stale plant's present P [kW] from the fresh plants' P now and at its last fresh step.

    Parameters
    ----------
    p_then_kw : the stale plant's P at its last fresh step [kW].
    others_then_kw, others_now_kw : (J,) the other plants' P then and now (plants fresh at both steps) [kW].
    others_kva : (J,) their ratings [kVA].
    kva : the stale plant's rating [kVA].

    Returns
    -------
    ``p_then_kw`` times the group's ratio now/then, or, when the group was dark then (under 2 % of its rating),
    its share of rating now times ``kva``; clipped to ``[0, kva]``. None without another plant.
    """
    then = np.asarray(others_then_kw, float)
    now = np.asarray(others_now_kw, float)
    rated = float(np.sum(others_kva))
    if then.size == 0 or rated <= 0.0:
        return None
    then_sum, now_sum = float(then.sum()), float(now.sum())
    if then_sum > _DARK_SHARE * rated:
        p = p_then_kw * now_sum / then_sum
    else:
        p = now_sum / rated * kva
    return float(np.clip(p, 0.0, kva))


def stale_rise_pu(rise_pu: np.ndarray, dv_dp_pu_per_kw: np.ndarray, pv_p_kw: np.ndarray, recent_pv_p_kw: np.ndarray,
                  stale: np.ndarray, cap_pu: float) -> np.ndarray:
    """The PV variability margin's rise [pu] with the stale plants' own added on top, up to 1.5 ``cap_pu``.

    Parameters
    ----------
    rise_pu : (N,) the margin's rise as computed for every plant (at most ``cap_pu``) [pu].
    dv_dp_pu_per_kw : (N, K) [pu/kW].
    pv_p_kw : (K,) the plants' P as the decision takes it (stale ones projected) [kW].
    recent_pv_p_kw : (H, K) their P at the steps of the margin window [kW].
    stale : (K,) bool, the plants behind a stale frame.
    cap_pu : the margin's cap [pu].

    Returns
    -------
    (N,) new array: ``rise_pu`` where no plant is stale, else ``max(rise_pu, min(rise_pu + stale rise, 1.5 cap_pu))``,
    the stale rise being ``pv_variability_margins_pu`` over the stale plants' columns alone.
    """
    rise = np.asarray(rise_pu, float)
    sel = np.asarray(stale, bool)
    if not np.any(sel):
        return rise.copy()
    s = np.asarray(dv_dp_pu_per_kw, float) * sel.astype(float)
    top = STALE_RISE_CAP_FACTOR * cap_pu
    extra, _ = pv_variability_margins_pu(s, pv_p_kw, recent_pv_p_kw, top)
    return np.maximum(rise, np.minimum(rise + extra, top))


class StalePlants:
    """What the controller remembers to treat a stale plant: each plant's last fresh step and our last command.

    Parameters
    ----------
    kva : (K,) the plants' ratings [kVA].
    command_valid_ns : how long a Q command stays in force after its step [ns].
    """

    def __init__(self, kva: np.ndarray, command_valid_ns: int) -> None:
        self.kva = np.asarray(kva, float)
        n = self.kva.size
        self._ref_p = np.full((n, n), np.nan)  # row k: every plant's P at plant k's last fresh step [kW]
        self._ref_ok = np.zeros((n, n), bool)  # row k: which of them were fresh then
        self._cmd_q = np.full(n, np.nan)  # our last Q command [kvar]
        self._cmd_t = np.full(n, -1, np.int64)  # its step [ns]
        self._valid_ns = int(command_valid_ns)

    def observe(self, p_kw: np.ndarray, fresh_ok: np.ndarray) -> None:
        """Take in a step's plant outputs ``p_kw`` (K,) [kW]; ``fresh_ok`` (K,) the plants usable and fresh."""
        ok = np.asarray(fresh_ok, bool)
        for k in np.flatnonzero(ok):
            self._ref_p[k] = np.asarray(p_kw, float)
            self._ref_ok[k] = ok

    def commanded(self, t_ns: int, q_kvar: np.ndarray, sent: np.ndarray) -> None:
        """Remember the Q commands ``q_kvar`` (K,) [kvar] sent at step ``t_ns`` to the plants ``sent`` (K,)."""
        for k in np.flatnonzero(np.asarray(sent, bool)):
            self._cmd_q[k] = float(q_kvar[k])
            self._cmd_t[k] = int(t_ns)

    def projected_p_kw(self, p_kw: np.ndarray, fresh_ok: np.ndarray, stale: np.ndarray) -> np.ndarray:
        """(K,) P [kW]: ``p_kw`` with each ``stale`` plant's projected from the fresh ones (module docstring)."""
        out = np.asarray(p_kw, float).copy()
        fresh = np.asarray(fresh_ok, bool)
        for k in np.flatnonzero(np.asarray(stale, bool)):
            others = fresh & self._ref_ok[k]
            others[k] = False
            if not self._ref_ok[k, k]:
                continue
            p = project_stale_p_kw(float(self._ref_p[k, k]), self._ref_p[k, others], out[others],
                                   self.kva[others], float(self.kva[k]))
            if p is not None:
                out[k] = p
        return out

    def commanded_q_kvar(self, t_ns: int) -> np.ndarray:
        """(K,) our Q command in force at ``t_ns`` [kvar], NaN where none is."""
        live = (self._cmd_t >= 0) & (int(t_ns) - self._cmd_t <= self._valid_ns) & (self._cmd_t < int(t_ns))
        return np.where(live, self._cmd_q, np.nan)
