"""Batch evaluation of a trained model over many minutes, on top of ``regression.estimator``.

The estimation math (paper eq. (5)-(7) and the evaluation of eq. (3)) lives in one place,
``regression/estimator.py``, which the online agent uses. This module only applies it to (T, ...) batches for
training statistics, tests and the accuracy report.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from regression.estimator import (
    SensitivityTable,
    apply_correction,
    correction_pu,
    dv_dq_pu_per_kvar,
    estimate_voltages_pu,
)
from regression.model import ModelArrays, SensitivityFit

__all__ = ["estimate_v_pu", "eval_sensitivities", "sensitivity_arrays"]


def estimate_v_pu(
    arrays: ModelArrays,
    features: np.ndarray,
    taps: np.ndarray,
    reg_v120: np.ndarray | None = None,
) -> np.ndarray:
    """Critical-node voltages, paper eq. (5), corrected by eq. (6)-(7) when ``reg_v120`` is given.

    Parameters
    ----------
    arrays : the model's arrays.
    features : (T, M) feature vectors (``regression.model.features``) [kW, kvar].
    taps : (T, R) present tap positions [steps].
    reg_v120 : (T, R) measured raw regulator secondary voltages [V on the 120 V base], or None.

    Returns
    -------
    (T, N) estimated voltages [pu of each node's base].
    """
    v = estimate_voltages_pu(arrays, np.atleast_2d(features), np.atleast_2d(taps))
    if reg_v120 is None or arrays.tap0.size == 0:
        return v
    measured = np.atleast_2d(np.asarray(reg_v120, float)) * arrays.reg_pu_per_v120
    # the agent's functions index nodes / regulators on axis 0: pass (N, T) and (R, T)
    eps = correction_pu(v.T, arrays.reg_secondary_node, measured.T)
    return apply_correction(v.T, eps, arrays.upstream_regulator).T


def sensitivity_arrays(fits: Sequence[Sequence[SensitivityFit]]) -> SensitivityTable:
    """The (N, K) eq. (3) fits of a model as the agent's ``SensitivityTable``."""
    return SensitivityTable.of(fits)


def eval_sensitivities(table: SensitivityTable, q_head_kvar: np.ndarray) -> np.ndarray:
    """dV_n/dQ_k at each head Q, paper eq. (3) (``regression.estimator.dv_dq_pu_per_kvar``).

    Parameters
    ----------
    table : ``sensitivity_arrays`` of the model.
    q_head_kvar : (T,) feeder-head Q, sum of phases [kvar].

    Returns
    -------
    (T, N, K) [pu/kvar].
    """
    q = np.asarray(q_head_kvar, float).ravel()
    if q.size == 0:
        return np.zeros((0, *table.a.shape))
    return np.stack([dv_dq_pu_per_kvar(table, float(x)) for x in q])
