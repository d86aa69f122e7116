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
"""

from __future__ import annotations

import numpy as np

from agent.errors import AgentInputError

__all__ = ["expected_compared_v120", "recentred_setpoint", "setpoint_for_tap_change"]


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
