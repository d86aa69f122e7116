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
    extended_features,
)
from regression.model import ModelArrays, SensitivityFit, calendar_features

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
    """Critical-node voltages, paper eq. (5), corrected by eq. (6)-(7) when ``reg_v120`` is given.

    An extended model (``arrays.n_readings > 0``) also takes the readings as regressors when ``reg_v120`` is
    given (its "with correction"); without them every reading is replaced by its regression on the paper
    features (``regression.estimator.extended_features``).

    Parameters
    ----------
    arrays : the model's arrays.
    features : (T, M_paper) feature vectors (``regression.model.features``) [kW, kvar].
    taps : (T, R) present tap positions [steps].
    reg_v120 : (T, R) measured raw regulator secondary voltages [V on the 120 V base], or None.
    caps : (T, C) closed steps of each capacitor bank (extended models; None: as in training).
    cap_v_v : (T, C) the banks' bus voltage readings [V] (extended models with readings).
    t_ns : (T,) UTC epoch nanoseconds of each minute (models with calendar features).

    Returns
    -------
    (T, N) estimated voltages [pu of each node's base].
    """
    f = np.atleast_2d(np.asarray(features, float))
    t = np.atleast_2d(np.asarray(taps, float))
    if arrays.extended:
        c = np.tile(arrays.cap0, (f.shape[0], 1)) if caps is None else np.atleast_2d(np.asarray(caps, float))
        if reg_v120 is None or arrays.n_readings == 0:
            readings = np.full((f.shape[0], arrays.n_readings), np.nan)
        else:
            reg = np.atleast_2d(np.asarray(reg_v120, float)) * arrays.reg_pu_per_v120
            n_cap = arrays.cap0.size
            cap = np.full((f.shape[0], n_cap), np.nan) if cap_v_v is None \
                else np.atleast_2d(np.asarray(cap_v_v, float)) / arrays.cap_v_ref_v  # NaN: not given, fallback
            readings = np.concatenate([reg, cap], axis=1)
        cal = None if t_ns is None else calendar_features(np.asarray(t_ns), arrays.utc_offset_h)
        f = extended_features(arrays, f, readings, t, c, calendar=cal)
        v = estimate_voltages_pu(arrays, f, t, c)
    else:
        v = estimate_voltages_pu(arrays, f, t)
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
