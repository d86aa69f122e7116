"""Online voltage and sensitivity estimation: paper eq. (5)-(7) and the evaluation of eq. (3)-(4) fits.

Pure functions of arrays: no I/O, no state, inputs are never modified. Index conventions are those of
``regression.model`` (``n`` critical node, ``k`` PV plant, ``r`` regulator, ``m`` feature).
All voltages are per unit of each critical node's own base (``_pu``).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from regression.capbanks import bank_voltage_pu, head_q_at_training_banks
from regression.errors import ModelInputError
from regression.model import HEAD_Q_COLUMNS, ModelArrays, SensitivityFit, calendar_features

__all__ = [
    "SensitivityTable",
    "apply_correction",
    "correction_pu",
    "dv_dp_pu_per_kw",
    "dv_dq_pu_per_kvar",
    "estimate_critical_pu",
    "estimate_voltages_pu",
    "extended_features",
    "pv_variability_margins_pu",
]

#: Smallest ``c + q_head_kvar`` [kvar] the power form of eq. (3) is evaluated at (guard against a fit whose
#: ``c`` does not keep the base positive over its clipped range; training is meant to prevent that).
POWER_BASE_FLOOR_KVAR = 1.0

_FORM_CODE = {"constant": 0, "linear": 1, "power": 2}


def estimate_voltages_pu(
    arrays: ModelArrays, features: np.ndarray, taps: np.ndarray, caps: np.ndarray | None = None
) -> np.ndarray:
    """Critical-node voltages from measurements and tap positions, paper eq. (5).

    ``v_hat = alpha[:, :-1] @ M + alpha[:, -1] + dv_dtap_pu @ (T - T0) [+ dv_dcap_pu @ (C - C0)]``.

    The capacitor term is beyond the paper (extended feature set, docs/method.md): a static perturbation per
    closed step, like eq. (4)'s tap term. A paper model ignores ``caps`` here (the agent adds its banks' terms
    with ``regression.capbanks``).

    Parameters
    ----------
    arrays : model arrays (``alpha`` (N, M+1) with trailing intercept, ``dv_dtap_pu`` (N, R), ``tap0`` (R,)).
    features : (..., M) regression features in the model's ``feature_names`` order [kW, kvar; pu for
        calendar and readings of an extended model, see ``extended_features``].
    taps : (..., R) present tap positions [steps].
    caps : (..., C) closed steps of each capacitor bank; None: as in training (no capacitor term).

    Returns
    -------
    (..., N) estimated voltages [pu].
    """
    m = np.asarray(features, float)
    t = np.asarray(taps, float)
    if m.shape[-1] != arrays.alpha.shape[1] - 1:
        raise ModelInputError(
            f"features have {m.shape[-1]} columns but the model expects {arrays.alpha.shape[1] - 1}; "
            "build them with regression.model.features()"
        )
    if t.shape[-1] != arrays.tap0.shape[0]:
        raise ModelInputError(f"taps have {t.shape[-1]} entries but the model has {arrays.tap0.shape[0]} regulators")
    v = m @ arrays.alpha[:, :-1].T + arrays.alpha[:, -1] + (t - arrays.tap0) @ arrays.dv_dtap_pu.T
    if caps is None or not arrays.extended or arrays.cap0.size == 0:
        return v
    c = np.asarray(caps, float)
    if c.shape[-1] != arrays.cap0.shape[0]:
        raise ModelInputError(f"caps have {c.shape[-1]} entries but the model has {arrays.cap0.shape[0]} capacitors")
    return v + (c - arrays.cap0) @ arrays.dv_dcap_pu.T


def extended_features(
    arrays: ModelArrays,
    paper_features: np.ndarray,
    readings_pu: np.ndarray,
    taps: np.ndarray,
    caps: np.ndarray,
    *,
    calendar: np.ndarray | None = None,
    valid: np.ndarray | None = None,
) -> np.ndarray:
    """Features of an extended model: the paper's, the calendar's and the readings, mapped to ``tap0``/``cap0``.

    Beyond the paper (docs/method.md, "extended features"): ``M' = [M, R] - feature_dtap @ (T - T0) -
    feature_dcap @ (C - C0)``: the regression was fitted at the training taps and banks, so a tap or a bank
    step must reach it only through eq. (4)'s static term and the bank term of ``estimate_voltages_pu`` (a
    switched bank's kvar at the head would otherwise read as a load change). A missing reading (``valid``
    False or non-finite) is replaced by its regression on the mapped paper features (``reading_alpha``).

    Parameters
    ----------
    arrays : model arrays of an extended model.
    paper_features : (..., M_paper) ``regression.model.features`` [kW, kvar].
    readings_pu : (..., J) readings in the model's ``readings`` order [pu]: a regulator's raw secondary
        voltage times ``pu_per_v120``, a bank's bus voltage over its ``v_ref_v``.
    taps : (..., R) present taps [steps].
    caps : (..., C) closed steps of each bank.
    calendar : (..., n_calendar) ``regression.model.calendar_features`` of the minute, for a model with them.
    valid : (..., J) bool, optional.

    Returns
    -------
    (..., M_paper + n_calendar + J) features [kW, kvar, 1, pu].
    """
    m = np.asarray(paper_features, float)
    r = np.asarray(readings_pu, float)
    n_paper = arrays.reading_alpha.shape[1] - 1
    if r.shape[-1] != arrays.n_readings or m.shape[-1] != n_paper:
        raise ModelInputError(
            f"{r.shape[-1]} readings and {m.shape[-1]} paper features; the model expects {arrays.n_readings} "
            f"and {n_paper}"
        )
    ok = np.isfinite(r)
    if valid is not None:
        ok &= np.asarray(valid, bool)
    if arrays.n_calendar:
        if calendar is None or np.shape(calendar)[-1] != arrays.n_calendar:
            raise ModelInputError(f"the model needs {arrays.n_calendar} calendar features of the minute")
        cal = np.broadcast_to(np.asarray(calendar, float), (*m.shape[:-1], arrays.n_calendar))
    else:
        cal = np.zeros((*m.shape[:-1], 0))
    raw = np.concatenate([m, cal, np.where(ok, r, 0.0)], axis=-1)
    shift = (np.asarray(taps, float) - arrays.tap0) @ arrays.feature_dtap.T
    if arrays.cap0.size:
        shift = shift + (np.asarray(caps, float) - arrays.cap0) @ arrays.feature_dcap.T
    mapped = raw - shift
    fallback = mapped[..., :n_paper] @ arrays.reading_alpha[:, :-1].T + arrays.reading_alpha[:, -1]
    first = n_paper + arrays.n_calendar
    mapped[..., first:] = np.where(ok, mapped[..., first:], fallback)
    return mapped


def estimate_critical_pu(
    arrays: ModelArrays,
    paper_features: np.ndarray,
    taps: np.ndarray,
    *,
    caps: np.ndarray | None = None,
    reg_v120: np.ndarray | None = None,
    reg_ok: np.ndarray | None = None,
    cap_v_v: np.ndarray | None = None,
    t_ns: np.ndarray | int | None = None,
    eps_filter: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None,
) -> np.ndarray:
    """Critical-node voltages of any model, with its bank terms, corrected by eq. (6)-(7) when ``reg_v120`` is given.

    The one estimate of the project: the online agent calls it for one minute, the training reports (accuracy,
    calibration) for many (leading axes). Per feature set:

    - ``paper``: eq. (5) on the paper's features. Banks switched since training (``caps`` differs from ``cap0``)
      enter as ``regression.capbanks`` says: the head's Q with their kvar added back, then their own ``dv_dcap``
      term (beyond the paper);
    - ``extended`` / ``extended_readings``: the features mapped back to ``tap0``/``cap0`` with the calendar and the
      readings (``extended_features``), then the same ``dv_dcap`` term. The readings are regressors only with the
      correction (``reg_v120`` given): without it every reading takes its fallback regression.

    Parameters
    ----------
    arrays : the model's arrays.
    paper_features : (..., M_paper) ``regression.model.features`` of the measurements [kW, kvar].
    taps : (..., R) present taps [steps].
    caps : (..., C) closed steps of each bank; None: as in training.
    reg_v120 : (..., R) raw regulator secondary voltages [V on the 120 V base]; None: no correction.
    reg_ok : (..., R) bool, regulators whose reading is usable (default: every finite one).
    cap_v_v : (..., C) the banks' bus voltage readings [V] (NaN where missing; models with readings).
    t_ns : (...) UTC epoch nanoseconds of each minute (models with calendar features).
    eps_filter : maps eq. (6)'s corrections ``(R,)`` and their validity ``(R,)`` to the corrections applied
        (the agent's ``agent.state.CorrectionFilter``; one minute only); None: as computed.

    Returns
    -------
    (..., N) estimated voltages [pu of each node's base].
    """
    f = np.asarray(paper_features, float)
    lead = f.shape[:-1]
    n_cap = arrays.cap0.size
    c = None if caps is None or n_cap == 0 else np.broadcast_to(np.asarray(caps, float), (*lead, n_cap))
    ok = None if reg_v120 is None else np.broadcast_to(
        np.ones(arrays.tap0.size, bool) if reg_ok is None else np.asarray(reg_ok, bool), (*lead, arrays.tap0.size))
    if arrays.extended:
        readings = np.full((*lead, arrays.n_readings), np.nan)  # the readings' order: regulators, then banks
        if arrays.n_readings and reg_v120 is not None and ok is not None:
            readings[..., : arrays.tap0.size] = np.where(ok, np.asarray(reg_v120, float) * arrays.reg_pu_per_v120,
                                                          np.nan)
            if cap_v_v is not None:
                readings[..., arrays.tap0.size :] = np.asarray(cap_v_v, float) / arrays.cap_v_ref_v
        calendar = None if t_ns is None else calendar_features(np.asarray(t_ns), arrays.utc_offset_h,
                                                               arrays.calendar_seasonal, arrays.calendar_weekly)
        f = extended_features(arrays, f, readings, taps, arrays.cap0 if c is None else c, calendar=calendar)
    elif c is not None:
        f = f.copy()
        f[..., HEAD_Q_COLUMNS] = head_q_at_training_banks(arrays, f[..., HEAD_Q_COLUMNS], c)
    v = estimate_voltages_pu(arrays, f, taps)
    if c is not None:
        v = v + bank_voltage_pu(arrays, c)
    if reg_v120 is None or ok is None or arrays.tap0.size == 0:
        return v
    measured = np.asarray(reg_v120, float) * arrays.reg_pu_per_v120
    # eq. (6)-(7) index nodes / regulators on axis 0: pass (N, T) and (R, T)
    eps = correction_pu(v.T, arrays.reg_secondary_node, np.broadcast_to(measured, ok.shape).T, valid=ok.T)
    if eps_filter is not None:
        eps = eps_filter(eps, ok)
    return apply_correction(v.T, eps, arrays.upstream_regulator).T


def correction_pu(
    v_hat_pu: np.ndarray,
    reg_secondary_node: np.ndarray,
    measured_secondary_pu: np.ndarray,
    *,
    valid: np.ndarray | None = None,
) -> np.ndarray:
    """Per-regulator correction ``eps_r = V_r - V_hat_r``, paper eq. (6).

    Parameters
    ----------
    v_hat_pu : (N,) uncorrected estimate of eq. (5) [pu].
    reg_secondary_node : (R,) index of each regulator's secondary node into the critical nodes.
    measured_secondary_pu : (R,) measured secondary voltage [pu of the secondary node's base]: the raw
        reading (no line-drop compensation) times ``pu_per_v120``.
    valid : (R,) bool, optional. Regulators without a usable measurement (``False``, or a non-finite
        reading) get ``eps_r = 0``: no correction from them (our rule; the paper assumes every reading).

    Returns
    -------
    (R,) correction [pu], always finite.
    """
    v_hat = np.asarray(v_hat_pu, float)
    measured = np.asarray(measured_secondary_pu, float)
    ok = np.isfinite(measured)
    if valid is not None:
        ok &= np.asarray(valid, bool)
    eps = measured - v_hat[np.asarray(reg_secondary_node, int)]
    return np.where(ok & np.isfinite(eps), eps, 0.0)


def apply_correction(v_hat_pu: np.ndarray, eps_pu: np.ndarray, upstream_regulator: np.ndarray) -> np.ndarray:
    """Corrected estimate ``V_hat_i + eps_{r_i}``, paper eq. (7).

    ``r_i`` is the nearest regulator upstream of node ``i`` on its phase (``upstream_regulator[i]``).
    Nodes with no upstream regulator (``-1``, e.g. the feeder head side of the first regulator) get no
    correction: the paper defines ``eps`` only from regulator secondaries and says nothing about them.

    Parameters
    ----------
    v_hat_pu : (N,) estimate of eq. (5) [pu].
    eps_pu : (R,) corrections of eq. (6) [pu].
    upstream_regulator : (N,) int, index into regulators or -1.

    Returns
    -------
    (N,) corrected estimate [pu] (a new array).
    """
    v_hat = np.asarray(v_hat_pu, float)
    up = np.asarray(upstream_regulator, int)
    eps = np.asarray(eps_pu, float)
    has = up >= 0
    out = v_hat.copy()
    out[has] += eps[up[has]]
    return out


@dataclass(frozen=True)
class SensitivityTable:
    """The (N, K) ``SensitivityFit`` grid of a model as arrays, for vectorised evaluation of eq. (3).

    ``form`` codes: 0 constant, 1 linear, 2 power. Build once per model with ``SensitivityTable.of``.
    """

    form: np.ndarray  # (N, K) int
    a: np.ndarray  # (N, K)
    b: np.ndarray  # (N, K)
    c: np.ndarray  # (N, K) [kvar]
    q_min_kvar: np.ndarray  # (N, K)
    q_max_kvar: np.ndarray  # (N, K)

    @classmethod
    def of(cls, fits: Sequence[Sequence[SensitivityFit]]) -> SensitivityTable:
        """Arrays of a nested ``sens_q[n][k]`` list of fits."""
        n = len(fits)
        k = len(fits[0]) if n else 0
        if any(len(row) != k for row in fits):
            raise ModelInputError("sensitivity fits are not a rectangular (nodes x plants) grid; retrain the model")

        def grid(get):
            return np.array([[get(f) for f in row] for row in fits], float).reshape(n, k)

        return cls(
            form=grid(lambda f: _FORM_CODE[f.form]).astype(int),
            a=grid(lambda f: f.a),
            b=grid(lambda f: f.b),
            c=grid(lambda f: f.c),
            q_min_kvar=grid(lambda f: f.q_min_kvar),
            q_max_kvar=grid(lambda f: f.q_max_kvar),
        )


def dv_dq_pu_per_kvar(fits: SensitivityTable | Sequence[Sequence[SensitivityFit]], q_head_kvar: float) -> np.ndarray:
    """Voltage sensitivity of each critical node to each plant's reactive power, paper eq. (3).

    Each fit is evaluated at the feeder-head reactive power clipped to the fit's training range
    ``[q_min_kvar, q_max_kvar]`` (no extrapolation). Forms: ``power`` ``a / (c + q) ** b`` (eq. 3, with
    ``c + q`` floored at ``POWER_BASE_FLOOR_KVAR`` so the power is always defined), ``linear`` ``a + b q``,
    ``constant`` ``a``.

    Parameters
    ----------
    fits : a ``SensitivityTable`` (fast) or the model's ``sens_q`` grid (N x K ``SensitivityFit``).
    q_head_kvar : total feeder-head reactive power [kvar], into the feeder.

    Returns
    -------
    (N, K) sensitivities [pu/kvar].
    """
    table = fits if isinstance(fits, SensitivityTable) else SensitivityTable.of(fits)
    q_head = float(q_head_kvar)
    if not np.isfinite(q_head):
        raise ModelInputError("feeder-head reactive power is not finite; reject the head frame before estimating")
    q = np.clip(q_head, table.q_min_kvar, table.q_max_kvar)
    out = table.a.copy()
    lin = table.form == 1
    out[lin] += table.b[lin] * q[lin]
    pw = table.form == 2
    base = np.maximum(table.c[pw] + q[pw], POWER_BASE_FLOOR_KVAR)
    out[pw] = table.a[pw] / base ** table.b[pw]
    return out


def dv_dp_pu_per_kw(arrays: ModelArrays, feature_names: Sequence[str], n_pv: int) -> np.ndarray:
    """Voltage change of each critical node per kW more from each plant, read off eq. (5)'s coefficients.

    A plant producing more lowers the feeder-head P by as much (losses aside): the coefficient of the plant's
    P minus the mean of the head's per-phase P coefficients (the plant's kW taken off the three phases
    equally: exact for three-phase plants, an approximation for single-phase ones). Beyond the paper: used
    for the PV variability margin (``pv_variability_margins_pu``).

    Returns
    -------
    (N, K) sensitivities [pu/kW].
    """
    names = list(feature_names)
    try:
        head = [names.index(f"head_p_kw_{ph}") for ph in "abc"]
        plants = [names.index(f"pv{k}_p_kw") for k in range(n_pv)]
    except ValueError as e:
        raise ModelInputError(f"the model's features lack head or plant P: {e}") from e
    alpha = arrays.alpha
    return alpha[:, plants] - alpha[:, head].mean(axis=1, keepdims=True)


def pv_variability_margins_pu(
    dv_dp_pu_per_kw: np.ndarray, pv_p_kw: np.ndarray, recent_pv_p_kw: np.ndarray, cap_pu: float
) -> tuple[np.ndarray, np.ndarray]:
    """How far each critical node's voltage could move if the plants went back to their recent extremes.

    Beyond the paper (docs/method.md, "PV variability margin"): Q set points and taps hold for a whole control
    interval while clouds move the plants' output within it. Each plant may return to the highest or lowest
    output it had in the recent window; the worst rise and fall of each node under those changes, by the
    linear model ``dv_dp_pu_per_kw``, tighten its upper and lower optimization limits.

    Parameters
    ----------
    dv_dp_pu_per_kw : (N, K) from ``dv_dp_pu_per_kw`` [pu/kW].
    pv_p_kw : (K,) output now [kW].
    recent_pv_p_kw : (H, K) outputs at the recent control steps (now included) [kW].
    cap_pu : largest margin on either side [pu].

    Returns
    -------
    ``(rise_pu, fall_pu)``, each (N,) in ``[0, cap_pu]``: subtract ``rise`` from the upper limit, add ``fall``
    to the lower one.
    """
    now = np.asarray(pv_p_kw, float)
    recent = np.asarray(recent_pv_p_kw, float).reshape(-1, now.size)
    up = np.maximum(recent.max(axis=0, initial=-np.inf) - now, 0.0) if recent.size else np.zeros_like(now)
    down = np.maximum(now - recent.min(axis=0, initial=np.inf), 0.0) if recent.size else np.zeros_like(now)
    s = np.asarray(dv_dp_pu_per_kw, float)
    rise = np.maximum(s * up, -s * down).sum(axis=1)
    fall = np.maximum(-s * up, s * down).sum(axis=1)
    return np.clip(rise, 0.0, cap_pu), np.clip(fall, 0.0, cap_pu)
