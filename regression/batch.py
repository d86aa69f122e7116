"""Batch evaluation of a trained model over many minutes, on top of ``regression.estimator``.

The estimation math (paper eq. (5)-(7) and the evaluation of eq. (3)) lives in one place,
``regression/estimator.py``, which the online agent uses. This module only applies it to (T, ...) batches for
training statistics, tests and the accuracy report.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from regression.estimator import SensitivityTable, dv_dq_pu_per_kvar, estimate_critical_pu
from regression.model import ModelArrays, SensitivityFit

__all__ = ["estimate_v_pu", "eval_sensitivities", "sensitivity_arrays"]


def estimate_v_pu(
    arrays: ModelArrays,
    features: np.ndarray,
    taps: np.ndarray,
    reg_v120: np.ndarray | None = None,
    *,
    caps: np.ndarray | None = None,
    cap_v_v: np.ndarray | None = None,
    t_ns: np.ndarray | None = None,
) -> np.ndarray:
    """Critical-node voltages of (T,) minutes: ``regression.estimator.estimate_critical_pu`` (the agent's estimate).

    Eq. (5) with the model's bank terms (a paper model's as the agent applies them: head-Q add-back and
    ``dv_dcap``), corrected by eq. (6)-(7) when ``reg_v120`` is given; an extended model then also takes the
    readings as regressors.

    Parameters
    ----------
    arrays : the model's arrays.
    features : (T, M_paper) feature vectors (``regression.model.features``) [kW, kvar].
    taps : (T, R) present tap positions [steps].
    reg_v120 : (T, R) measured raw regulator secondary voltages [V on the 120 V base], or None.
    caps : (T, C) closed steps of each capacitor bank (None: as in training).
    cap_v_v : (T, C) the banks' bus voltage readings [V] (extended models with readings).
    t_ns : (T,) UTC epoch nanoseconds of each minute (models with calendar features).

    Returns
    -------
    (T, N) estimated voltages [pu of each node's base].
    """
    f = np.atleast_2d(np.asarray(features, float))
    return estimate_critical_pu(arrays, f, np.atleast_2d(np.asarray(taps, float)), caps=caps, reg_v120=reg_v120,
                                cap_v_v=cap_v_v, t_ns=t_ns)


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
