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

from collections.abc import Sequence

import numpy as np

from regression.errors import ModelInputError
from regression.model import CapacitorInfo, ModelArrays

__all__ = ["bank_voltage_pu", "head_q_at_training_banks"]


def _delta_steps(arrays: ModelArrays, cap_steps: np.ndarray) -> np.ndarray:
    cap0 = np.zeros(0) if arrays.cap0 is None else arrays.cap0
    c = np.asarray(cap_steps, float)
    if c.shape != cap0.shape:
        raise ModelInputError(f"bank states have shape {c.shape} but the model has {cap0.size} bank(s)")
    return c - cap0


def head_q_at_training_banks(
    arrays: ModelArrays, banks: Sequence[CapacitorInfo], head_q_kvar: np.ndarray, cap_steps: np.ndarray
) -> np.ndarray:
    """(3,) feeder-head Q per phase as it would be with every bank at its training state [kvar].

    Each step closed since training supplies ``kvar_rated / steps`` spread evenly over the bank's phases
    (the voltage's square scaling of that kvar is neglected: below 1 % within the limits).
    """
    delta = _delta_steps(arrays, cap_steps)
    q = np.array(head_q_kvar, float)
    for c, bank in enumerate(banks):
        per_phase = delta[c] * bank.kvar_rated / bank.steps / len(bank.phases)
        for ph in bank.phases:
            q[ph - 1] += per_phase
    return q


def bank_voltage_pu(arrays: ModelArrays, cap_steps: np.ndarray) -> np.ndarray:
    """(N,) voltage change of the critical nodes from the banks' states against training ``dv_dcap @ (C - C0)``."""
    delta = _delta_steps(arrays, cap_steps)
    if arrays.dv_dcap_pu is None or delta.size == 0:
        return np.zeros(arrays.alpha.shape[0])
    return arrays.dv_dcap_pu @ delta
