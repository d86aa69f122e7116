"""Where the controller's picture of the grid comes from: the estimator (cases B-D) or the bridge's oracle (A).

Both sources give a ``GridState``: voltages of the nodes to constrain, their sensitivities to each plant's Q and
P and to each regulator's tap, and the present taps. The controller builds one CVVC problem from it, whichever
the source (paper Table I: case A is the same problem with full visibility).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from agent.errors import AgentInputError
from regression.capbanks import head_q_at_training_banks
from regression.estimator import SensitivityTable, dv_dq_pu_per_kvar, estimate_critical_pu
from regression.model import CvvcModel, ModelArrays, features
from schemas import messages as m

__all__ = ["CorrectionFilter", "CorrectionNoise", "GridState", "OracleSource", "estimated_state",
           "filter_gap_bounds_pu", "noise_bounds_pu", "oracle_state"]

#: Case A's source: the bridge's oracle reply for a step time [ns], or None when it did not answer.
OracleSource = Callable[[int], "m.OracleReply | None"]


@dataclass(frozen=True)
class GridState:
    """The grid at one control step, as the CVVC problem needs it.

    Attributes
    ----------
    v0_pu : (N,) present voltages of the nodes to constrain [pu of each node's base].
    dv_dq_pu_per_kvar : (N, K) sensitivity to each plant's Q [pu/kvar].
    dv_dtap_pu : (N, R) sensitivity to each regulator's tap [pu/step].
    dv_dp_pu_per_kw : (N, K) sensitivity to each plant's P [pu/kW] (the PV variability margin).
    taps : (R,) present taps [steps].
    corrected : eq. (6)-(7) correction applied (estimator only).
    critical : the nodes are the model's critical nodes (the decision reports their estimates); False for the
        oracle's every live node.
    """

    v0_pu: np.ndarray
    dv_dq_pu_per_kvar: np.ndarray
    dv_dtap_pu: np.ndarray
    dv_dp_pu_per_kw: np.ndarray
    taps: np.ndarray
    corrected: bool
    critical: bool


class CorrectionFilter:
    """Eq. (6)'s corrections averaged over decisions: an exponential mean with weight ``weight`` per decision.

    Beyond the paper. The correction ``eps_r`` is the regulator's reading minus its estimate; with SCADA-class noise
    on the readings (1 %: 1.2 V; about 0.5 V, 1.2 V / sqrt(5), after the 5-minute mean) each decision's ``eps``
    jumps by the noise and the QP moves taps after it (rural winter week: NTC 24 without noise, 196 with it, NVV 10).
    What ``eps`` should carry, the model's error at the regulator, changes slowly; its exponential mean over the
    last hour or so (``weight`` 0.1 per 5-minute decision) keeps it and sheds most of the noise (docs/results.md). A
    regulator without a usable reading keeps its last mean; the first reading is taken as it is. A reading that is
    usable but not this step's own (a last-good frame standing in for a lost one) is applied through the mean
    without entering it: a stale reading against the present load is not the model's error, and the mean would
    carry it for an hour.

    Until a regulator has had ``1 / weight`` readings in its mean, the mean is their plain average (the weight of
    its ``n``-th reading is ``max(weight, 1 / n)``): an exponential mean started from the first reading alone would
    keep 0.9^(n-1) of that one reading's noise (IEEE 8500, winter, 1 % SCADA noise: 729 node-minutes under 0.965 pu
    in the run's first hour, NVV 803 in three days against 15 without noise).

    When the estimate's own inputs are not this step's (``inputs_fresh`` False: the head's or a plant's frame lost
    and a last-good one standing in), a fresh reading's ``eps`` is applied as it is (eq. 6 as in the paper) and does
    not enter the mean: the estimate then misses the change since the stale frame (at sunset on 17 July of the rural
    summer week the plants' Q went from 370 kvar to 0 during a head outage), the mean knows nothing of it, and the
    fresh reading measures it. The mean alone let the 10-minute average fall to 0.962 pu there.
    """

    def __init__(self, n_regulators: int, weight: float) -> None:
        if not 0.0 < weight <= 1.0:
            raise AgentInputError(f"correction filter weight must be in (0, 1], not {weight}")
        self.weight = float(weight)
        self._eps = np.zeros(n_regulators)  # the mean so far (0 until a regulator's first usable reading)
        self._count = np.zeros(n_regulators)  # readings that entered each mean (0: never seen fresh)

    def __call__(self, eps: np.ndarray, ok: np.ndarray, fresh: np.ndarray | None = None, *,
                 inputs_fresh: bool = True) -> np.ndarray:
        """The corrections to apply [pu] for this decision's ``eps`` (R,) [pu] and their validity ``ok`` (R,).

        ``fresh`` (R,) bool marks the readings that are this step's own (default: every usable one);
        ``inputs_fresh``: the estimate's head and plant frames are this step's own (class docstring).
        """
        eps = np.asarray(eps, float)
        ok = np.asarray(ok, bool) & np.isfinite(eps)
        own = ok if fresh is None else ok & np.asarray(fresh, bool)
        update = own & bool(inputs_fresh)
        # a plain average until 1 / weight readings (the first one, weight 1, is taken as it is)
        weight = np.maximum(self.weight, 1.0 / (self._count + 1.0))
        self._eps = np.where(update, weight * eps + (1.0 - weight) * self._eps, self._eps)
        self._count = self._count + update
        # a fresh reading against stale inputs, or a stale reading of a regulator never seen fresh: taken as it is,
        # without entering the mean
        raw = (own & ~update) | (ok & (self._count == 0))
        return np.where(raw, eps, self._eps)


def filter_gap_bounds_pu(lo_pu: np.ndarray, hi_pu: np.ndarray, gap_pu: np.ndarray,
                         upstream_regulator: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Estimate bounds that hold for the filtered correction too: ``(lo, hi)`` (N,) [pu], new arrays.

    The calibrated bounds (``training.calibration``) are of the estimate corrected by eq. (6) as computed at the
    minute: the truth is expected in ``[v_inst - lo, v_inst + hi]``. The agent applies the filtered correction
    (``CorrectionFilter``), so its estimate is ``v = v_inst - gap`` at every node below regulator ``r``, with
    ``gap_r`` = eq. (6)'s correction as computed minus as applied (0 where the reading was not this step's own).
    Measured on epri-m1 (case D, 1 July): 37 % of node-decisions outside the calibrated bounds around ``v``, 3 %
    around ``v_inst``: the filter's lag, not the regression, was what the bounds missed. The bounds around ``v``
    that contain both intervals: ``lo + max(-gap, 0)`` below and ``hi + max(gap, 0)`` above (never narrower).

    Parameters
    ----------
    lo_pu, hi_pu : (N,) the bounds as they would be applied [pu]. gap_pu : (R,) per regulator [pu].
    upstream_regulator : (N,) each node's nearest upstream regulator (eq. 7's ``r_i``), -1 for none.
    """
    gap = _below_regulators(gap_pu, upstream_regulator)
    return (np.asarray(lo_pu, float) + np.maximum(-gap, 0.0), np.asarray(hi_pu, float) + np.maximum(gap, 0.0))


def _below_regulators(per_regulator: np.ndarray, upstream_regulator: np.ndarray) -> np.ndarray:
    """(N,) each node's value of its nearest upstream regulator (eq. 7's ``r_i``), 0 for a node with none (-1)."""
    up = np.asarray(upstream_regulator, int)
    values = np.asarray(per_regulator, float)
    return np.where(up >= 0, values[np.maximum(up, 0)] if values.size else 0.0, 0.0)


class CorrectionNoise:
    """The noise the filtered correction (``CorrectionFilter`` of weight ``weight``) keeps of noisy readings, per
    regulator, learnt from the gap between the correction as computed and as applied.

    With readings of noise ``s`` (the window's mean) the exponential mean of weight ``w`` keeps a noise ``s_f``,
    ``s_f^2 = s^2 w / (2 - w)``, and the gap ``(1 - w)(eps - mean before)`` has the mean square
    ``(1 - w)^2 (s^2 + s_f^2)``, so ``s_f^2 = gap^2 w / (2 (1 - w)^2)``. The calibrated bounds are of the correction
    from a clean reading: they missed 21.5 % of IEEE 123's node-decisions with 1 % SCADA noise (``noise_bounds_pu``).
    """

    def __init__(self, n_regulators: int, weight: float) -> None:
        self._w = float(weight)
        self._gap_sq = np.full(n_regulators, np.nan)  # NaN until a noisy reading entered [pu^2]
        self._noisy = np.zeros(n_regulators, bool)  # each regulator's readings as last told

    def observe(self, gap_pu: np.ndarray, own: np.ndarray, loud: np.ndarray, told: np.ndarray) -> np.ndarray:
        """(R,) the filtered correction's noise [pu], 0 for regulators whose readings are quiet.

        ``gap_pu``: this decision's correction as computed minus as applied; ``own``: the regulators whose reading is
        this step's own; ``loud``: whose readings were told noisy at this step; ``told``: whose noise could be told at
        all (not just after a move: those are taken as last told).
        """
        told = np.asarray(told, bool)
        loud = told & np.asarray(loud, bool)
        self._noisy = np.where(told, loud, self._noisy)
        w, sq = self._w, self._gap_sq
        gap = np.asarray(gap_pu, float)
        seen = np.asarray(own, bool) & loud & np.isfinite(gap)
        self._gap_sq = np.where(seen, np.where(np.isfinite(sq), (1.0 - w) * sq + w * gap**2, gap**2), sq)
        if w >= 1.0:
            return np.zeros_like(sq)
        return np.where(self._noisy, np.sqrt(np.nan_to_num(self._gap_sq) * w / (2.0 * (1.0 - w) ** 2)), 0.0)


def noise_bounds_pu(lo_pu: np.ndarray, hi_pu: np.ndarray, margin_pu: np.ndarray,
                    upstream_regulator: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Estimate bounds widened on both sides by ``margin_pu`` (R,) of each node's nearest upstream regulator (eq. 7's
    ``r_i``; none for -1): the noise of a noisy reading's filtered correction, which the calibrated bounds (of a clean
    reading's) do not hold. New arrays [pu].
    """
    m = _below_regulators(margin_pu, upstream_regulator)
    return np.asarray(lo_pu, float) + m, np.asarray(hi_pu, float) + m


def estimated_state(
    arrays: ModelArrays,
    sens: SensitivityTable,
    dv_dp_pu_per_kw: np.ndarray,
    *,
    t_ns: int,
    head_p_kw: np.ndarray,
    head_q_kvar: np.ndarray,
    pv_p_kw: np.ndarray,
    pv_q_kvar: np.ndarray,
    taps: np.ndarray,
    caps: np.ndarray,
    reg_v120: np.ndarray | None,
    reg_ok: np.ndarray,
    cap_v_v: np.ndarray,
    eps_filter: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None,
) -> GridState:
    """The critical nodes by the estimator (``regression.estimator.estimate_critical_pu``) and eq. (3).

    Eq. (5) of the model's feature set with its bank terms, corrected by eq. (6)-(7) when ``reg_v120`` is given;
    eq. (3)'s sensitivities at the head's Q as training knew it (the kvar of banks switched since added back).

    Parameters
    ----------
    arrays, sens, dv_dp_pu_per_kw : the model's arrays, eq. (3) fits and (N, K) dV/dP [pu/kW].
    t_ns : the minute [ns since epoch] (calendar features).
    head_p_kw, head_q_kvar : (3,) feeder-head P [kW] and Q [kvar] per phase, as measured.
    pv_p_kw, pv_q_kvar : (K,) plant output (last known where missing) [kW], [kvar].
    taps : (R,) taps (last known where missing) [steps].
    caps : (C,) closed steps of each bank (last known where missing).
    reg_v120 : (R,) raw regulator secondary voltages [V on the 120 V base], or None (no correction).
    reg_ok : (R,) bool, regulators whose reading is usable.
    cap_v_v : (C,) the banks' bus voltage readings [V], NaN where missing (models with readings).
    eps_filter : maps eq. (6)'s corrections and their validity to those applied (the controller's
        ``CorrectionFilter`` for this step), None: eq. (6) as computed.
    """
    paper = features(head_p_kw, head_q_kvar, pv_p_kw, pv_q_kvar)
    v_hat = estimate_critical_pu(arrays, paper, taps, caps=caps, reg_v120=reg_v120, reg_ok=reg_ok, cap_v_v=cap_v_v,
                                 t_ns=t_ns, eps_filter=eps_filter)
    corrected = reg_v120 is not None and bool(np.any(reg_ok))
    head_q = head_q_at_training_banks(arrays, head_q_kvar, caps) if arrays.cap0.size else head_q_kvar
    dv_dq = dv_dq_pu_per_kvar(sens, float(np.sum(head_q)))
    return GridState(v0_pu=v_hat, dv_dq_pu_per_kvar=dv_dq, dv_dtap_pu=arrays.dv_dtap_pu,
                     dv_dp_pu_per_kw=dv_dp_pu_per_kw, taps=taps, corrected=corrected, critical=True)


def oracle_state(model: CvvcModel, reply: m.OracleReply, taps: np.ndarray) -> GridState:
    """Every energised node from the bridge's oracle: true voltages and perturbation sensitivities (case A).

    Device order is the device map's, which is also the model's (training builds the model from the same map).
    ``taps`` (R,) [steps] stand in when the reply carries none. Raises ``AgentInputError`` when the reply's
    device counts are not the model's.
    """
    n_pv, n_reg = len(model.pv), len(model.regulators)
    v0 = np.asarray(reply.v_pu, float)
    dv_dq = np.asarray(reply.dv_dq_pu_per_kvar, float).reshape(v0.size, -1)
    dv_dtap = np.asarray(reply.dv_dtap_pu, float).reshape(v0.size, -1)
    if dv_dq.shape[1] != n_pv or dv_dtap.shape[1] != n_reg:
        raise AgentInputError(f"oracle reply has {dv_dq.shape[1]} plants and {dv_dtap.shape[1]} regulators; "
                              f"the model has {n_pv} and {n_reg}")
    # an oracle without dV/dP (an older bridge): no margin
    dv_dp = np.asarray(reply.dv_dp_pu_per_kw or np.zeros((v0.size, n_pv)), float).reshape(v0.size, -1)
    if dv_dp.shape[1] != n_pv:
        raise AgentInputError(f"oracle reply has dV/dP for {dv_dp.shape[1]} plants; the model has {n_pv}")
    live = v0 > 0.5  # nodes that are not energised (0 pu) cannot be constrained
    present = np.asarray(reply.taps, int) if len(reply.taps) == n_reg else np.asarray(taps, int)
    return GridState(v0_pu=v0[live], dv_dq_pu_per_kvar=dv_dq[live], dv_dtap_pu=dv_dtap[live],
                     dv_dp_pu_per_kw=dv_dp[live], taps=present, corrected=False, critical=False)
