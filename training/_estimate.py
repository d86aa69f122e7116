"""Private evaluation of a trained model: paper eq. (5)-(7) and eq. (3).

Used by training (fit statistics) and the accuracy report. ``agent/estimator.py`` owns the online
version (``estimate_voltages_pu``); once it exists, the report should call that instead of this module so
there is one estimator in the project.
"""

from __future__ import annotations

import numpy as np

from training.model import ModelArrays, SensitivityFit

__all__ = ["estimate_v_pu", "sensitivity_arrays", "eval_sensitivities"]


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
    features : (T, M) feature vectors (``training.model.features``) [kW, kvar].
    taps : (T, R) present tap positions [steps].
    reg_v120 : (T, R) measured regulator secondary voltages [V on the 120 V base], or None.

    Returns
    -------
    (T, N) estimated voltages [pu of each node's base].
    """
    x = np.atleast_2d(np.asarray(features, float))
    t = np.atleast_2d(np.asarray(taps, float))
    v = x @ arrays.alpha[:, :-1].T + arrays.alpha[:, -1]
    if arrays.tap0.size:
        v = v + (t - arrays.tap0) @ arrays.dv_dtap_pu.T  # eq. (5), second term
    if reg_v120 is None or arrays.tap0.size == 0:
        return v
    measured = np.atleast_2d(np.asarray(reg_v120, float)) * arrays.reg_pu_per_v120
    eps = measured - v[:, arrays.reg_secondary_node]  # eq. (6)
    has = arrays.upstream_regulator >= 0
    v = v.copy()
    v[:, has] += eps[:, arrays.upstream_regulator[has]]  # eq. (7)
    return v


def sensitivity_arrays(fits: list[list[SensitivityFit]]) -> dict[str, np.ndarray]:
    """Collect the (N, K) parameter arrays of the eq. (3) fits.

    Keys: form code (0 constant, 1 linear, 2 power), a, b, c, q_min, q_max.
    """
    code = {"constant": 0, "linear": 1, "power": 2}
    return {
        "form": np.asarray([[code[f.form] for f in row] for row in fits], int),
        "a": np.asarray([[f.a for f in row] for row in fits], float),
        "b": np.asarray([[f.b for f in row] for row in fits], float),
        "c": np.asarray([[f.c for f in row] for row in fits], float),
        "q_min": np.asarray([[f.q_min_kvar for f in row] for row in fits], float),
        "q_max": np.asarray([[f.q_max_kvar for f in row] for row in fits], float),
    }


def eval_sensitivities(params: dict[str, np.ndarray], q_head_kvar: np.ndarray) -> np.ndarray:
    """dV_n/dQ_k at head Q, paper eq. (3) and our linear/constant forms.

    Parameters
    ----------
    params : ``sensitivity_arrays`` output, arrays (N, K).
    q_head_kvar : (T,) feeder-head Q, sum of phases [kvar]; clipped to each fit's training range.

    Returns
    -------
    (T, N, K) [pu/kvar].
    """
    q = np.clip(np.asarray(q_head_kvar, float)[:, None, None], params["q_min"], params["q_max"])
    a, b, c = params["a"], params["b"], params["c"]
    power = a / np.where(params["form"] == 2, c + q, 1.0) ** np.where(params["form"] == 2, b, 0.0)
    linear = a + b * q
    return np.where(params["form"] == 2, power, np.where(params["form"] == 1, linear, a + 0.0 * q))
