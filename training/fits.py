"""Regressions of the estimator (paper II.D): eq. (5) voltage model, eq. (3) Q sensitivities, eq. (4) taps.

Pure functions of arrays. Deviations from the paper, each written down where it happens:

- Eq. (5) is fitted on standardised features with a truncated-SVD least squares (``rcond``), then mapped
  back to raw coefficients and an intercept; constant features get a zero coefficient. The paper uses plain
  least squares, which on nearly collinear inputs fits huge opposite coefficients to noise (reference
  experiment, trap 1). The condition number of the standardised design is reported.
- Eq. (3) ``a / (c + Q_s)^b`` is one of three candidate forms per (node, plant) pair, with ``linear``
  (``a + b Q_s``) and ``constant`` (``a``); the one with the lowest error on held-out scenarios is kept, a
  simpler form winning ties within ``tie_rel``. ``c`` is chosen per feeder (``choose_c_kvar``), not the
  paper's 3000 kvar, and the exponent is bounded; the fitted exponent may be negative (sensitivity rising
  with head Q), which the paper's "inverse shape" did not anticipate (trap 2).
- Eq. (4) is the plain difference of two power flows, as in the paper.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np
from scipy.optimize import OptimizeWarning, curve_fit

from regression.model import SensitivityFit
from training.errors import TrainingError

__all__ = [
    "SensitivitySamples",
    "VoltageFit",
    "choose_c_kvar",
    "fit_sensitivity",
    "fit_voltage_regression",
    "fit_voltages_with_holdout",
    "sensitivity_rel_err",
    "sensitivity_samples",
    "tap_sensitivities",
]

_B_BOUND = 8.0  # |b| of eq. (3): beyond this the power form is a numerical accident, not a trend
_A_MAX = 1e11  # |a| that still fits the model file's finite range with margin


@dataclass(frozen=True)
class VoltageFit:
    """Result of the eq. (5) regression for all nodes.

    ``alpha[n]`` holds the raw-feature coefficients then the intercept [pu per feature unit, pu].
    """

    alpha: np.ndarray  # (N, M+1)
    rmse_pu: np.ndarray  # (N,) training residual RMSE
    max_abs_pu: float  # largest training residual
    condition_number: float  # of the standardised design matrix (kept columns)
    rank: int  # effective rank used by the truncated SVD
    dropped_features: tuple[int, ...]  # constant features (coefficient 0)


def fit_voltage_regression(
    x: np.ndarray, v_pu: np.ndarray, *, rcond: float = 1e-6, weights: np.ndarray | None = None
) -> VoltageFit:
    """Least squares of node voltages on features, paper eq. (5) (first term).

    Parameters
    ----------
    x : (F, M) features of F power flows (``regression.model.features``) [kW, kvar].
    v_pu : (F, N) node voltages [pu of each node's base].
    rcond : singular values of the standardised design below ``rcond * s_max`` are dropped.
    weights : (F,) positive weight of each flow in the least squares (None: all 1). The statistics
        (``rmse_pu``, ``max_abs_pu``) stay unweighted.

    Raises
    ------
    TrainingError
        On non-finite inputs, or fewer power flows than non-constant features + 1.
    """
    x = np.asarray(x, float)
    v_pu = np.asarray(v_pu, float)
    if x.ndim != 2 or v_pu.ndim != 2 or x.shape[0] != v_pu.shape[0]:
        raise TrainingError(f"feature/voltage shapes disagree: {x.shape} vs {v_pu.shape}")
    if not (np.all(np.isfinite(x)) and np.all(np.isfinite(v_pu))):
        raise TrainingError("non-finite feature or voltage in the training power flows; check the feeder")
    n_flows, n_feat = x.shape
    w = np.ones(n_flows) if weights is None else np.asarray(weights, float)
    if w.shape != (n_flows,) or not np.all(np.isfinite(w)) or np.any(w <= 0):
        raise TrainingError(f"regression weights must be ({n_flows},) positive finite numbers, one per flow")
    w = w / w.mean()
    mu = w @ x / n_flows
    sd = np.sqrt(w @ (x - mu) ** 2 / n_flows)
    keep = sd > 1e-9 * np.maximum(1.0, np.abs(mu))
    if n_flows < int(keep.sum()) + 2:
        raise TrainingError(
            f"singular regression: {n_flows} power flows for {int(keep.sum())} varying features; "
            "use more blocks or more scenarios (e.g. --blocks 5 5)"
        )
    sw = np.sqrt(w)[:, None]
    z = (x[:, keep] - mu[keep]) / sd[keep]
    v_mean = w @ v_pu / n_flows
    beta, _, rank, s = np.linalg.lstsq(z * sw, (v_pu - v_mean) * sw, rcond=rcond)
    coef = np.zeros((n_feat, v_pu.shape[1]))
    coef[keep] = beta / sd[keep, None]
    intercept = v_mean - mu @ coef
    alpha = np.concatenate([coef.T, intercept[:, None]], axis=1)
    resid = x @ coef + intercept - v_pu
    cond = float(s[0] / s[-1]) if s.size and s[-1] > 0 else float("inf")
    return VoltageFit(
        alpha=alpha,
        rmse_pu=np.sqrt(np.mean(resid**2, axis=0)),
        max_abs_pu=float(np.max(np.abs(resid))) if resid.size else 0.0,
        condition_number=cond,
        rank=int(rank),
        dropped_features=tuple(int(i) for i in np.flatnonzero(~keep)),
    )


def fit_voltages_with_holdout(scenario: np.ndarray, x: np.ndarray, v_pu: np.ndarray, *, rcond: float,
                              weights: np.ndarray, every: int) -> tuple[VoltageFit, float, float]:
    """Eq. (5) fit on every flow, plus its RMSE and max error [pu] on held-out scenarios (fitted on the others).

    Parameters
    ----------
    scenario : (F,) scenario of each flow; every ``every``-th scenario (``scenario % every == every - 1``) is held out.
    x, v_pu, rcond, weights : as ``fit_voltage_regression``.
    every : the holdout period.

    Returns
    -------
    The fit on every flow, the held-out RMSE and max |error| (NaN when there is too little to hold out).
    """
    holdout = (np.asarray(scenario) % every) == every - 1
    val_rmse, val_max = float("nan"), float("nan")
    if holdout.any() and (~holdout).sum() > x.shape[1] + 1:
        part = fit_voltage_regression(x[~holdout], v_pu[~holdout], rcond=rcond, weights=weights[~holdout])
        err = x[holdout] @ part.alpha[:, :-1].T + part.alpha[:, -1] - v_pu[holdout]
        val_rmse, val_max = float(np.sqrt(np.mean(err**2))), float(np.max(np.abs(err)))
    return fit_voltage_regression(x, v_pu, rcond=rcond, weights=weights), val_rmse, val_max


def tap_sensitivities(v0_pu: np.ndarray, v_tap_pu: np.ndarray) -> np.ndarray:
    """Paper eq. (4): ``delta^VR_{i,r} = V_i^r - V_i^0`` [pu/step].

    Parameters
    ----------
    v0_pu : (N,) voltages before the tap change [pu].
    v_tap_pu : (R, N) voltages after raising regulator r by one step [pu].

    Returns
    -------
    (N, R) voltage change per tap step [pu/step].
    """
    return (np.asarray(v_tap_pu, float) - np.asarray(v0_pu, float)[None, :]).T


@dataclass(frozen=True)
class SensitivitySamples:
    """Finite-difference dV/dQ samples from consecutive Q steps of one plant (paper II.D)."""

    plant: np.ndarray  # (S,) int, the plant whose Q changed
    scenario: np.ndarray  # (S,) int
    q_head_kvar: np.ndarray  # (S,) feeder-head Q (sum of phases) at the midpoint of the two flows [kvar]
    dv_dq_pu_per_kvar: np.ndarray  # (S, N) [pu/kvar]


def sensitivity_samples(
    scenario: np.ndarray,
    plant: np.ndarray,
    pv_q_kvar: np.ndarray,
    q_head_kvar: np.ndarray,
    v_pu: np.ndarray,
    *,
    min_dq_kvar: float = 1.0,
) -> SensitivitySamples:
    """Differences of consecutive power flows of one plant's Q sweep, divided by the Q change.

    The sweep of plant k in a scenario is its own flows (``plant == k``) plus the scenario's base flow
    (``plant == -1``, every plant at Q = 0), ordered by plant k's applied Q. Flows of combined
    perturbations (``plant == -2``) are not used.

    Parameters
    ----------
    scenario, plant : (F,) int labels of each power flow.
    pv_q_kvar : (F, K) applied plant Q [kvar], generator convention.
    q_head_kvar : (F,) feeder-head Q, sum of phases [kvar].
    v_pu : (F, N) node voltages [pu].
    min_dq_kvar : pairs closer than this in Q are skipped (would divide noise by a tiny step).
    """
    scenario = np.asarray(scenario)
    plant = np.asarray(plant)
    out_k, out_s, out_q, out_dv = [], [], [], []
    for s in np.unique(scenario):
        in_s = scenario == s
        for k in range(pv_q_kvar.shape[1]):
            idx = np.flatnonzero(in_s & ((plant == k) | (plant == -1)))
            if idx.size < 2:
                continue
            idx = idx[np.argsort(pv_q_kvar[idx, k], kind="stable")]
            dq = np.diff(pv_q_kvar[idx, k])
            ok = dq >= min_dq_kvar
            if not ok.any():
                continue
            dv = np.diff(v_pu[idx], axis=0)[ok] / dq[ok, None]
            qm = 0.5 * (q_head_kvar[idx[:-1]] + q_head_kvar[idx[1:]])[ok]
            out_k.append(np.full(qm.size, k))
            out_s.append(np.full(qm.size, s))
            out_q.append(qm)
            out_dv.append(dv)
    if not out_q:
        raise TrainingError(
            "no PV reactive-power sweep gave a usable sensitivity sample; check that the PV plants "
            "have reactive headroom (kva > pmpp_kw) in the device map"
        )
    return SensitivitySamples(
        plant=np.concatenate(out_k),
        scenario=np.concatenate(out_s),
        q_head_kvar=np.concatenate(out_q),
        dv_dq_pu_per_kvar=np.concatenate(out_dv),
    )


def choose_c_kvar(q_min_kvar: float, q_max_kvar: float) -> float:
    """Choose the ``c`` of eq. (3) for one feeder [kvar].

    The paper's ``c = 3000`` kvar belongs to its feeder. We choose ``c`` so that ``c + Q_s`` runs from the
    training span to twice the span over the training range ``[q_min, q_max]``: positive everywhere (the
    evaluation clips ``Q_s`` to that range), with the same end-to-end ratio (about 2) as ``3000 + Q_s`` on a
    feeder whose head Q spans 0..3000 kvar.
    """
    span = max(q_max_kvar - q_min_kvar, 1.0)
    return float(span - q_min_kvar)


def _eval_form(form: str, a: float, b: float, c: float, q: np.ndarray) -> np.ndarray:
    if form == "power":
        return a / (c + q) ** b
    if form == "linear":
        return a + b * q
    return np.full(q.shape, a)


def _fit_form(form: str, q: np.ndarray, y: np.ndarray, c: float) -> tuple[float, float] | None:
    """Fit (a, b) of one form by least squares; None when the form does not apply."""
    if form == "constant":
        return float(y.mean()), 0.0
    if form == "linear":
        if np.ptp(q) <= 0:
            return None
        b, a = np.polyfit(q, y, 1)
        return float(a), float(b)
    # power: needs one sign and c + q > 0
    sign = np.sign(y.mean())
    if sign == 0 or np.any(np.sign(y) != sign) or np.any(c + q <= 0) or np.ptp(q) <= 0:
        return None
    lc = np.log(c + q)
    slope, inter = np.polyfit(lc, np.log(np.abs(y)), 1)  # log|y| = log|a| - b log(c+q)
    p0 = (float(inter), float(np.clip(-slope, -_B_BOUND, _B_BOUND)))
    scale = float(np.mean(np.abs(y)))

    def model(qq, la, bb):
        return sign * np.exp(la - bb * np.log(c + qq)) / scale

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", OptimizeWarning)
            warnings.simplefilter("ignore", RuntimeWarning)
            lo = (p0[0] - 50.0, -_B_BOUND)
            hi = (p0[0] + 50.0, _B_BOUND)
            (la, bb), _ = curve_fit(model, q, y / scale, p0=p0, bounds=(lo, hi), maxfev=2000)
    except (RuntimeError, ValueError):
        la, bb = p0
    a = float(sign * np.exp(la))
    if not (np.isfinite(a) and np.isfinite(bb) and abs(a) <= _A_MAX):
        return None
    return a, float(bb)


def fit_sensitivity(
    q_head_kvar: np.ndarray,
    dv_dq: np.ndarray,
    *,
    c_kvar: float,
    q_range_kvar: tuple[float, float],
    holdout: np.ndarray | None = None,
    tie_rel: float = 0.01,
) -> tuple[SensitivityFit, dict[str, float]]:
    """Fit dV/dQ of one (node, plant) pair against head Q, paper eq. (3), choosing the form.

    Parameters
    ----------
    q_head_kvar : (S,) feeder-head Q of each sample [kvar].
    dv_dq : (S,) sensitivity samples [pu/kvar].
    c_kvar : ``c`` of eq. (3) (``choose_c_kvar``).
    q_range_kvar : the training range that evaluation clips head Q to.
    holdout : (S,) bool, samples used only for choosing the form; None or all-False: training error.
    tie_rel : a simpler form wins when within this relative validation error of a complex one.

    Returns
    -------
    The chosen fit (refitted on all samples) and the validation RMSE of each candidate form [pu/kvar].
    """
    q = np.asarray(q_head_kvar, float)
    y = np.asarray(dv_dq, float)
    if holdout is None or not holdout.any() or holdout.all():
        train, val = np.ones(q.size, bool), np.ones(q.size, bool)
    else:
        train, val = ~holdout, holdout
    scores: dict[str, float] = {}
    for form in ("constant", "linear", "power"):
        ab = _fit_form(form, q[train], y[train], c_kvar)
        if ab is None:
            continue
        pred = _eval_form(form, ab[0], ab[1], c_kvar, np.clip(q[val], *q_range_kvar))
        scores[form] = float(np.sqrt(np.mean((pred - y[val]) ** 2)))
    best = "constant"
    for form in ("linear", "power"):  # simpler first; a complex form must beat it clearly
        if form in scores and scores[form] < scores[best] * (1.0 - tie_rel):
            best = form
    ab = _fit_form(best, q, y, c_kvar)
    if ab is None:  # the refit on all samples failed: fall back to the constant
        best, ab = "constant", (float(y.mean()), 0.0)
    a, b = ab
    fit = SensitivityFit(
        form=best,  # type: ignore[arg-type]
        a=a,
        b=b,
        c=c_kvar if best == "power" else 0.0,
        q_min_kvar=float(q_range_kvar[0]),
        q_max_kvar=float(q_range_kvar[1]),
    )
    return fit, scores


def sensitivity_rel_err(sens: list[list[SensitivityFit]], samples: SensitivitySamples) -> float:
    """Median relative error of the eq. (3) fits on their samples, over significant pairs.

    A (node, plant) pair is significant when its median |dV/dQ| is at least 10 % of the node's largest.
    """
    from regression.batch import eval_sensitivities, sensitivity_arrays

    n_pv = len(sens[0]) if sens else 0
    pred = eval_sensitivities(sensitivity_arrays(sens), samples.q_head_kvar)
    pred = pred[np.arange(samples.plant.size), :, samples.plant]  # (S, N): each sample's own plant
    truth = samples.dv_dq_pu_per_kvar
    med = np.stack([np.median(np.abs(truth[samples.plant == k]), axis=0) for k in range(n_pv)])  # (K, N)
    rel = []
    for k in range(n_pv):
        sig = med[k] >= 0.1 * med.max(axis=0)
        m = samples.plant == k
        t, p = truth[m][:, sig], pred[m][:, sig]
        ok = np.abs(t) > 0
        rel.append(np.abs(p[ok] - t[ok]) / np.abs(t[ok]))
    rel_all = np.concatenate(rel) if rel else np.zeros(0)
    return float(np.median(rel_all)) if rel_all.size else float("nan")
