"""Tap change to regulator voltage set point, paper eq. (8) as read in DESIGN.md section 4.

A conventional regulator controller keeps its *compared* voltage (the secondary reading with line-drop
compensation applied; equal to the raw reading when R = X = 0) inside ``set point +/- B/2``. To make it land on a
desired tap without being told taps, eq. (8) moves the band:

- no change: ``V_T = V_s^1`` (the regulator sits at the centre of its band);
- raise:     ``V_T = V_s^1 + (B - T)/2``;
- lower:     ``V_T = V_s^1 - (B - T)/2``;

where ``V_s^1`` is the compared voltage expected once *all* actions of the interval are applied (present
compared reading plus the change the linear model predicts at the secondary, including the regulator's own
tap change), ``B`` the bandwidth and ``T`` the voltage of one tap step, all in volts on the 120 V base
(0.75 V for a +/-10 %, 32-step regulator). With the desired tap applied the compared voltage is ``V_s^1``,
which is then half a step inside the new band edge: the desired tap is the first tap inside the band.

Beyond the paper, the band re-centred once the regulator has stepped (``recentred_setpoint``): landed half a step
inside its band edge, a regulator under its own control steps again for any drift of half a step the same way
before the next decision re-centres it (IEEE 8500, first summer week, case D: 14-35 % of each downstream
regulator's tap changes came between decisions, 70-94 % of those after a move of the agent in that control period,
the same way). The agent sends the band again, centred on the regulator's reading, at the next step after a move.

Beyond the paper, ``T`` and the regulator's own share of ``V_s^1`` measured (``MeasuredSteps``): eq. (8) takes a tap
step to move the compared voltage by the model's step at the secondary, but it moves less: line-drop compensation
(IEEE 123's substation regulator: the raw reading 0.75 V a step, the compared one 0.57-0.60 V) and, where there is
none, a raw change below the training's static step (epri-ckt24's LTC: compared 0.58 V, raw 0.63 V, the model's
0.87 V; IEEE 8500's most-moved regulators 0.67-0.81 against 0.83-0.87 V). Landed on the model's step, the regulator sits
closer to its band edge than half a step, and a small drift the same way steps it again: on IEEE 123's first spring
week, case D, 7 of 15 single-step raises and 7 of 15 lowerings of the substation regulator moved two steps. The
agent measures each regulator's step on its compared reading from its own single-step moves
(``agent.snapshot.steps_seen_v120``) and, once it has ``STEPS_LEAST`` of them, lands eq. (8) with that step.
"""

from __future__ import annotations

import numpy as np

from agent.errors import AgentInputError
from schemas.settings import ANSI_RANGE_A_PU

__all__ = ["STEPS_KEPT", "STEPS_LEAST", "MeasuredSteps", "expected_compared_v120", "narrow_held_bands",
           "recentred_setpoint", "safety_band", "setpoint_for_tap_change", "with_measured_steps"]

STEPS_KEPT = 24  # the latest single-step moves each regulator's measured step is the median of
STEPS_LEAST = 3  # fewer moves seen: eq. (8) with the model's step
#: a measured step outside this share of the model's is not believed (a reading error, not the regulator's step)
STEP_PLAUSIBLE = (0.5, 1.5)


def setpoint_for_tap_change(v_s1_v120: float, d_tap: int, band_v120: float, step_v120: float) -> float:
    """Regulator voltage set point for a desired tap change, paper eq. (8).

    Parameters
    ----------
    v_s1_v120 : expected compared voltage after all actions, ``V_s^1`` [V on 120 V base].
    d_tap : desired tap change (only its sign matters) [steps].
    band_v120 : bandwidth ``B`` of the regulator controller (full width) [V on 120 V base].
    step_v120 : voltage of one tap step ``T`` [V on 120 V base].

    Returns
    -------
    Set point ``V_T`` [V on 120 V base].
    """
    if not (np.isfinite(v_s1_v120) and np.isfinite(band_v120) and np.isfinite(step_v120)):
        raise AgentInputError("eq. (8) inputs must be finite; reject the regulator frame instead")
    if band_v120 <= step_v120:
        raise AgentInputError(
            f"bandwidth {band_v120} V must exceed one tap step {step_v120} V, or the regulator hunts; "
            "use a wider band (the paper's case C uses 4 V)"
        )
    half = 0.5 * (band_v120 - step_v120)
    if d_tap > 0:
        return float(v_s1_v120 + half)
    if d_tap < 0:
        return float(v_s1_v120 - half)
    return float(v_s1_v120)


def expected_compared_v120(
    compared_v120: np.ndarray, dv_secondary_pu: np.ndarray, pu_per_v120: np.ndarray
) -> np.ndarray:
    """``V_s^1`` of eq. (8): present compared reading plus the predicted change at each secondary.

    The predicted change is taken from the linear model (eq. 13's terms evaluated at the chosen actions) in
    per unit of the secondary node's base and converted to the 120 V base. Line-drop compensation is assumed
    to shift the compared voltage by a constant over the interval (load current does not change with the
    actions to first order).

    Parameters
    ----------
    compared_v120 : (R,) compared voltage now [V on 120 V base].
    dv_secondary_pu : (R,) predicted voltage change at each regulator's secondary node [pu].
    pu_per_v120 : (R,) per unit of the secondary node per volt on the 120 V base.

    Returns
    -------
    (R,) expected compared voltage after the actions [V on 120 V base].
    """
    return np.asarray(compared_v120, float) + np.asarray(dv_secondary_pu, float) / np.asarray(pu_per_v120, float)


def recentred_setpoint(tap_before: int, tap_target: int, tap_now: int, compared_now_v120: float,
                       setpoint_v120: float) -> float:
    """The set point to send a step after an eq. (8) move from ``tap_before`` towards ``tap_target``.

    Once the regulator has stepped that way (``tap_now`` past ``tap_before`` towards the target, or beyond it), its
    band is centred on its present compared reading ``compared_now_v120`` (eq. 8's no-change rule, a step later),
    so it holds there under its own control unless the voltage drifts half a band; before it has stepped, eq.
    (8)'s ``setpoint_v120`` is sent again unchanged (the regulator is on its way).
    """
    if not (np.isfinite(compared_now_v120) and np.isfinite(setpoint_v120)):
        raise AgentInputError("the follow-up set point needs finite readings; reject the regulator frame instead")
    direction = int(np.sign(tap_target - tap_before))
    stepped = direction != 0 and (tap_now - tap_before) * direction > 0
    return float(compared_now_v120) if stepped else float(setpoint_v120)


class MeasuredSteps:
    """Each regulator's compared-reading change per tap step, measured from its own single-step moves.

    ``observe`` takes a snapshot's ``reg_steps_seen`` (``agent.snapshot.steps_seen_v120``: each move once per
    frame time, however many snapshots carry it); ``step_v120`` is the median of each regulator's latest
    ``STEPS_KEPT`` moves, NaN with fewer than ``STEPS_LEAST`` or when the median lies outside ``STEP_PLAUSIBLE`` of
    ``model_step_v120`` (eq. 8 then takes the model's step).
    """

    def __init__(self, model_step_v120: np.ndarray) -> None:
        self._model_step = np.asarray(model_step_v120, float)
        self._seen: list[dict[int, float]] = [{} for _ in range(self._model_step.size)]
        self._step = np.full(self._model_step.size, np.nan)  # the medians, updated when a regulator's moves change

    def observe(self, seen: tuple[tuple[tuple[int, float], ...], ...], usable: np.ndarray) -> None:
        """Keep the moves of the regulators whose readings are ``usable`` (valid and not noisy)."""
        lo, hi = STEP_PLAUSIBLE
        for r, moves in enumerate(seen[: len(self._seen)]):
            if not usable[r] or not moves:
                continue
            kept = self._seen[r]
            kept.update((int(t), float(v)) for t, v in moves if np.isfinite(v))
            for t in sorted(kept)[: max(0, len(kept) - STEPS_KEPT)]:
                del kept[t]
            step = float(np.median(list(kept.values()))) if len(kept) >= STEPS_LEAST else np.nan
            plausible = lo * self._model_step[r] <= step <= hi * self._model_step[r]
            self._step[r] = step if plausible else np.nan

    def step_v120(self) -> np.ndarray:
        """(R,) each regulator's measured step [V on 120 V base], NaN where not (yet) measured."""
        return self._step.copy()


def with_measured_steps(v_s1_v120: np.ndarray, d_tap: np.ndarray, model_step_v120: np.ndarray,
                        own_step_v120: np.ndarray, measured_v120: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(V_s^1, T)`` of eq. (8) per regulator, a one-step move's taken with the regulator's measured step.

    ``v_s1_v120`` is ``expected_compared_v120``'s, whose own-tap share is ``d_tap * own_step_v120`` (the model's
    dV/dtap at the secondary); where ``|d_tap| == 1`` and ``measured_v120`` is known (``MeasuredSteps.step_v120``),
    that share becomes ``d_tap * measured`` and ``T`` the measured step. A longer move keeps the model's: single
    steps are what was measured (IEEE 8500's line regulators, first three winter days: a four-step move of vreg3_b
    moved its compared reading 0.80 V a step where its 14 clean single steps of those days had moved it 0.72 V (their
    median), and landed one step further with the measured step).
    """
    use = (np.abs(np.asarray(d_tap)) == 1) & np.isfinite(measured_v120)
    v_s1 = np.where(use, v_s1_v120 + d_tap * (measured_v120 - own_step_v120), v_s1_v120)
    return v_s1, np.where(use, measured_v120, model_step_v120)


def safety_band(setpoint_v120: float, band_v120: float, compared_v120: float, lo_margin_v120: float,
                hi_margin_v120: float, step_v120: float) -> tuple[float, float]:
    """A held regulator's ``(set point, band)`` narrowed so that its own control steps before a node it moves
    leaves its limits between two decisions, never widened.

    Beyond the paper: the band eq. (8) holds a regulator in (``B`` wide) lets its compared reading drift ``B/2``
    before its own control acts, where with no control its native band would have stepped it earlier (epri-ckt24's
    LTC, winter nights: its native band 3 V; held by a 4 V band it rose 5-10 minutes later than with no control, a
    deep secondary below 0.95 pu meanwhile). ``lo_margin_v120`` / ``hi_margin_v120``: how far the compared reading
    (expected at ``compared_v120``) may fall / rise before the first node this regulator moves reaches its limit [V on
    120 V base]. Each band edge comes to that distance from the expected reading, but no closer than one tap step
    (so a step lands inside the band: no hunting) and no farther than the band's own edge. Unchanged when less than
    two steps would be left between the edges, or any input is not finite.
    """
    if not np.all(np.isfinite([setpoint_v120, band_v120, compared_v120, lo_margin_v120, hi_margin_v120, step_v120])):
        return setpoint_v120, band_v120
    lo_edge = max(setpoint_v120 - band_v120 / 2, compared_v120 - max(lo_margin_v120, step_v120))
    hi_edge = min(setpoint_v120 + band_v120 / 2, compared_v120 + max(hi_margin_v120, step_v120))
    if hi_edge - lo_edge < 2 * step_v120 - 1e-9:
        return setpoint_v120, band_v120
    return 0.5 * (lo_edge + hi_edge), hi_edge - lo_edge


def narrow_held_bands(setpoints: np.ndarray, bands: np.ndarray, held: np.ndarray, v_s1: np.ndarray, step: np.ndarray,
                      v_pred_pu: np.ndarray, dv_dtap: np.ndarray, secondary_node: np.ndarray,
                      pu_per_v120: np.ndarray) -> None:
    """Narrow the bands of the ``held`` regulators in place (``safety_band``): each edge where the compared reading,
    moving from ``v_s1``, would bring the predicted voltage of the first critical node the regulator moves (at least
    half as much as its secondary) to ANSI Range A.

    The estimates, not their bounds: with the bounds (and the judged limits, 0.965-1.05 pu) the bands stepped
    IEEE 8500's regulators far more often (first 3 summer days: NTC 1,231 -> 1,786, case A 948); with the
    estimates and ANSI Range A, 1,204 (docs/method.md "A held regulator's band"). ``dv_dtap``: (N, R) the
    critical nodes' tap sensitivities [pu/step]; ``secondary_node``: (R,) each regulator's secondary among them;
    ``pu_per_v120``: (R,) pu of its secondary per volt on the 120 V base.
    """
    v = np.asarray(v_pred_pu, float)[:dv_dtap.shape[0], None]
    lo_pu, hi_pu = ANSI_RANGE_A_PU
    n_reg = dv_dtap.shape[1]
    own = dv_dtap[secondary_node, np.arange(n_reg)]
    held = np.asarray(held, bool) & (own > 0)
    if not held.any():
        return
    share = dv_dtap / np.where(own > 0, own, 1.0)  # (N, R): each node's move per step of its secondary's
    moved = share >= 0.5  # the secondary's own row is 1: every held regulator moves at least one node
    per_v = np.asarray(pu_per_v120, float)
    lo_margin = np.min(np.where(moved, (v - lo_pu) / np.where(moved, share, 1.0), np.inf), axis=0) / per_v
    hi_margin = np.min(np.where(moved, (hi_pu - v) / np.where(moved, share, 1.0), np.inf), axis=0) / per_v
    for r in np.flatnonzero(held):
        setpoints[r], bands[r] = safety_band(float(setpoints[r]), float(bands[r]), float(v_s1[r]),
                                             float(lo_margin[r]), float(hi_margin[r]), float(step[r]))
