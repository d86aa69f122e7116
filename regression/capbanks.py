"""Switched capacitor banks in the estimate (beyond the paper; docs/method.md "Capacitor decisions").

Eq. (5) was fitted on power flows with every bank at the training state ``closed0``. A bank switched since
changes two things the regression sees differently from the truth:

- its kvar shows in the feeder-head reactive power (a closed step lowers the head's Q by about its kvar),
  which eq. (5) would read as less reactive load: ``head_q_at_training_banks`` adds that kvar back, so the
  regression sees the head as it would be with the banks at ``closed0``;
- the bank moves the voltages by its own sensitivity: ``bank_voltage_pu`` adds ``dv_dcap @ (C - C0)``.

Pure functions of arrays; no I/O.
"""

from __future__ import annotations

import numpy as np

from regression.errors import ModelInputError
from regression.model import ModelArrays

__all__ = ["bank_voltage_pu", "head_q_at_training_banks"]


def _delta_steps(arrays: ModelArrays, cap_steps: np.ndarray) -> np.ndarray:
    c = np.asarray(cap_steps, float)
    if c.shape[-1:] != arrays.cap0.shape:
        raise ModelInputError(f"bank states have shape {c.shape} but the model has {arrays.cap0.size} bank(s)")
    return c - arrays.cap0


def head_q_at_training_banks(arrays: ModelArrays, head_q_kvar: np.ndarray, cap_steps: np.ndarray) -> np.ndarray:
    """(..., 3) feeder-head Q per phase as it would be with every bank at its training state [kvar].

    Each step closed since training supplies ``kvar_rated / steps`` spread evenly over the bank's phases
    (``ModelArrays.cap_head_q_kvar``; the voltage's square scaling of that kvar is neglected: below 1 % within the
    limits). ``head_q_kvar`` (..., 3) and ``cap_steps`` (..., C) may carry leading (minute) axes.
    """
    return np.asarray(head_q_kvar, float) + _delta_steps(arrays, cap_steps) @ arrays.cap_head_q_kvar


def bank_voltage_pu(arrays: ModelArrays, cap_steps: np.ndarray) -> np.ndarray:
    """(..., N) voltage change of the critical nodes from the banks' states against training ``dv_dcap @ (C - C0)``."""
    return _delta_steps(arrays, cap_steps) @ arrays.dv_dcap_pu.T
